"""The hub against hostile or broken clients, and slow or late answers from the service.

Real loopback sockets and the Hub alone, with fake callbacks (as in test_daemon_hub.py,
whose client and fixtures these tests reuse).  Nothing is synchronised by sleeping: the
tests wait for a line, a closed socket, a log event or a threading.Event, each wait
bounded by a timeout so that a regression fails instead of hanging.  Timing bounds are
generous on purpose (a shared 2-core machine): they tell "delivered meanwhile" from
"delivered after the slow thing ended", nothing finer.
"""

from __future__ import annotations

import concurrent.futures
import threading
import time

import pytest
import structlog

from fog_driver.daemon.hub import Deferred
from test_daemon_hub import TIMEOUT_S, Conn, Control, angle, make_hub  # noqa: F401 - make_hub is a fixture


class Service(Control):
    """Control plus the slow and late answers of a real service.

    DEFER answers with ``Deferred(future, timeout_s)`` (``timeout_s`` from the args, 30 s by
    default), LATE with a bare Future, BLOCK blocks its worker thread for up to 2 s (until
    ``release`` is set), SVCERR answers like the service does for a name it does not know.
    """

    def __init__(self) -> None:
        super().__init__()
        self.futures: list[concurrent.futures.Future] = []
        self.answered_later = threading.Event()
        self.blocking = threading.Event()
        self.release = threading.Event()
        self.block_ended = threading.Event()

    def __call__(self, name: str, args: dict, client_id: int):
        if name in ("DEFER", "LATE"):
            self.calls.append((name, args, client_id))
            future: concurrent.futures.Future = concurrent.futures.Future()
            self.futures.append(future)
            self.answered_later.set()
            return Deferred(future, args.get("timeout_s", 30.0)) if name == "DEFER" else future
        if name == "BLOCK":
            self.calls.append((name, args, client_id))
            self.blocking.set()
            self.release.wait(2.0)
            self.block_ended.set()
            return {"class": "BLOCK"}
        if name == "SVCERR":
            return {"class": "ERROR", "message": "unknown command ?SVCERR"}
        return super().__call__(name, args, client_id)


class LogEvents:
    """A structlog processor that keeps every event (and prints none); tests wait on it."""

    def __init__(self) -> None:
        self.entries: list[dict] = []
        self.changed = threading.Condition()

    def __call__(self, logger, method_name: str, event_dict: dict) -> dict:
        with self.changed:
            self.entries.append(dict(event_dict))
            self.changed.notify_all()
        raise structlog.DropEvent

    def named(self, event: str) -> list[dict]:
        with self.changed:
            return [e for e in self.entries if e["event"] == event]

    def wait_for(self, event: str, count: int = 1, timeout_s: float = TIMEOUT_S) -> bool:
        with self.changed:
            return self.changed.wait_for(lambda: len([e for e in self.entries if e["event"] == event]) >= count,
                                         timeout_s)


@pytest.fixture
def log_events():
    events = LogEvents()
    structlog.configure(processors=[events])
    return events  # conftest resets structlog after the test


def hang_up_hard(conn: Conn) -> None:
    """Close without reading what the server sent: the kernel answers with a RST."""
    conn.sock.close()


def wait_until_gone(hub, log_events: LogEvents, disconnects: int) -> None:
    """Publish STATUS until the hub has noticed ``disconnects`` hang-ups (it notices on its next write)."""
    deadline = time.monotonic() + TIMEOUT_S
    while not log_events.wait_for("client_disconnected", disconnects, timeout_s=0.05):
        assert time.monotonic() < deadline, "the hub never noticed the hang-up"
        hub.publish({"class": "STATUS"})


# --------------------------------------------------------------------------- C1: the service's Future is never cancelled


@pytest.mark.parametrize("command", ["DEFER", "LATE"])
def test_a_hang_up_never_cancels_the_services_future(make_hub, log_events, command):
    # before: the client's reader task was cancelled and asyncio.wrap_future cancelled the service's
    # Future with it; the acquisition thread's set_result then raised InvalidStateError (the daemon died)
    hub, address, service = make_hub(control=Service())
    c = Conn(address)
    c.send(f"?{command};\n")
    assert service.answered_later.wait(TIMEOUT_S)
    hang_up_hard(c)
    wait_until_gone(hub, log_events, 1)
    future = service.futures[0]
    assert not future.cancelled()
    future.set_result({"class": "BIAS", "bias_dph": 0.01})  # the acquisition thread's call: must not raise
    assert future.result() == {"class": "BIAS", "bias_dph": 0.01}
    other = Conn(address)  # and the hub serves on
    other.greeting()
    other.send("?ECHO;\n")
    other.expect("ECHO")


def test_a_timed_out_command_leaves_its_future_to_its_owner(make_hub):
    _, address, service = make_hub(control=Service(), control_timeout_s=0.2)
    c = Conn(address)
    c.greeting()
    c.send("?LATE;\n")
    assert c.line() == {"class": "ERROR", "message": "no answer within 0.2 s", "command": "LATE"}
    future = service.futures[0]
    assert not future.cancelled()
    future.set_result({"class": "LATE"})  # must not raise
    c.send("?ECHO;\n")  # the connection is fine, and the late answer was not sent
    c.expect("ECHO")


def test_a_deferred_is_waited_for_its_own_timeout_not_the_default(make_hub):
    _, address, service = make_hub(control=Service(), control_timeout_s=0.2)
    a, b = Conn(address), Conn(address)
    a.greeting()
    b.greeting()
    a.send('?DEFER={"timeout_s":60};\n')
    assert service.answered_later.wait(TIMEOUT_S)
    b.send("?LATE;\n")  # a bare Future, begun after a's: its 0.2 s pass first
    assert b.expect("ERROR")["message"] == "no answer within 0.2 s"
    service.futures[0].set_result({"bias_dph": 0.25})
    assert a.line() == {"class": "DEFER", "bias_dph": 0.25}  # not the default timeout's ERROR


def test_a_deferred_times_out_at_its_own_deadline(make_hub):
    _, address, service = make_hub(control=Service())  # the default: 30 s
    c = Conn(address)
    c.greeting()
    t0 = time.monotonic()
    c.send('?DEFER={"timeout_s":0.3};\n')
    assert c.line() == {"class": "ERROR", "message": "no answer within 0.3 s", "command": "DEFER"}
    assert time.monotonic() - t0 < TIMEOUT_S  # (Conn's timeout would have failed first anyway)
    assert not service.futures[0].cancelled()
    service.futures[0].set_exception(RuntimeError("too late"))  # must not raise either


def test_deferred_validates_its_fields():
    future: concurrent.futures.Future = concurrent.futures.Future()
    assert Deferred(future, 5).timeout_s == 5
    for bad in (0, -1, float("inf"), float("nan"), True, "5"):
        with pytest.raises(ValueError):
            Deferred(future, bad)
    with pytest.raises(TypeError):
        Deferred("not a future", 5.0)


def test_service_errors_carry_the_command(make_hub):
    _, address, _ = make_hub(control=Service())
    c = Conn(address)
    c.greeting()
    c.send("?SVCERR;\n")
    assert c.line() == {"class": "ERROR", "message": "unknown command ?SVCERR", "command": "SVCERR"}


# --------------------------------------------------------------------------- H5: control runs off the loop


def test_a_blocking_control_callback_delays_nobody_elses_angles(make_hub):
    hub, address, service = make_hub(control=Service())
    watcher, operator, other = Conn(address), Conn(address), Conn(address)
    for c in (watcher, operator, other):
        c.greeting()
    watcher.send('?WATCH={"enable":true};\n')
    watcher.expect("WATCH")
    operator.send("?BLOCK;\n?ECHO;\n")
    assert service.blocking.wait(TIMEOUT_S)
    t0 = time.monotonic()
    hub.publish_angles([angle(1, 1.0)])
    assert watcher.expect("ANGLE")["seq"] == 1
    delivered_s = time.monotonic() - t0  # measured: about 1 ms; before the change, 2 s (after the block)
    other.send("?ECHO;\n")  # a second worker answers another client meanwhile
    other.expect("ECHO")
    assert not service.block_ended.is_set(), "the ANGLE line waited for the blocked control callback"
    assert delivered_s < 1.5
    service.release.set()
    assert operator.expect("BLOCK") == {"class": "BLOCK"}  # one client's commands: answered in order
    assert operator.expect("ECHO")["args"] == {}


# --------------------------------------------------------------------------- H1: one client cannot stop delivery to others


def watch(conn: Conn, policy: str = '{"enable":true}') -> None:
    conn.send(f"?WATCH={policy};\n")
    conn.expect("WATCH")


@pytest.mark.parametrize("rate", ["1e308", "1" + "0" * 3999, "1e999", "NaN", "10000.5", "-0.0", "1e-400"])
def test_watch_refuses_absurd_rates(make_hub, rate):
    # before: 1e308 and a 4000-digit integer were accepted, and every batch then raised OverflowError
    hub, address, _ = make_hub()
    attacker = Conn(address)
    attacker.greeting()
    attacker.send(f'?WATCH={{"enable":true,"rate_hz":{rate}}};\n')
    assert attacker.line() == {"class": "ERROR", "message": "rate_hz must be a number > 0 and <= 10000",
                               "command": "WATCH"}
    victim = Conn(address)
    victim.greeting()
    watch(victim)
    assert hub.watchers == 1
    hub.publish_angles([angle(1, 1e6)])  # device time far from 0: t_s * rate would overflow
    assert victim.expect("ANGLE")["seq"] == 1


def test_watch_accepts_the_fastest_rate(make_hub):
    hub, address, _ = make_hub()
    c = Conn(address)
    c.greeting()
    c.send('?WATCH={"enable":true,"rate_hz":10000};\n')
    assert c.line() == {"class": "WATCH", "enable": True, "rate_hz": 10000}
    hub.publish_angles([angle(1, 1e6), angle(2, 1e6 + 1e-5), angle(3, 1e6 + 1e-3)])
    assert [c.expect("ANGLE")["seq"] for _ in range(2)] == [1, 3]


def test_a_delivery_failure_costs_only_that_client(make_hub, log_events):
    hub, address, _ = make_hub()
    before, broken, after = Conn(address), Conn(address), Conn(address)
    for c in (before, broken, after):
        c.greeting()
        watch(c, '{"enable":true,"rate_hz":5}')
    broken.send("?ECHO;\n")
    broken_id = broken.expect("ECHO")["client"]
    # a bug for one client: its decimation now raises (float('inf') * t_s cannot be floored)
    hub._loop.call_soon_threadsafe(setattr, hub._clients[broken_id], "rate_hz", float("inf"))
    broken.sync()  # the change is in place
    for seq in range(3):  # before: every batch stopped at the broken client, "after" got nothing
        hub.publish_angles([angle(seq, 10.0 + seq)])
    assert [before.expect("ANGLE")["seq"] for _ in range(3)] == [0, 1, 2]
    assert [after.expect("ANGLE")["seq"] for _ in range(3)] == [0, 1, 2]
    broken.wait_closed()
    failures = log_events.named("client_failed")
    assert len(failures) == 1 and failures[0]["client"] == broken_id and "OverflowError" in failures[0]["error"]
    assert hub.watchers == 2
