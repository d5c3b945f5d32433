"""The daemon's client multiplexer (NDJSON over TCP) and UDP datagrams, on real loopback sockets.

No sleeps synchronise anything here: tests wait for lines to arrive (socket
timeouts are only failure guards) or on threading Events.
"""

from __future__ import annotations

import contextlib
import json
import math
import socket
import struct
import threading
import time

import numpy as np
import pytest
import structlog
from hub_fixtures import TIMEOUT_S, VERSION, Conn, angle
from hypothesis import given, settings
from hypothesis import strategies as st

from fog_driver.daemon.hub import Hub, clean, encode, is_loopback_host
from fog_driver.daemon.limits import MAX_UNTERMINATED_BYTES
from fog_driver.daemon.udp import DATAGRAM_SIZE, UdpPublisher, decode_datagram, encode_datagram
from fog_driver.flags import FLAG_BITS, FLAG_GAP, FLAG_NAMES, FLAG_THERMOMETER_FAULT, FLAG_UNCOMPENSATED

# --------------------------------------------------------------------------- greeting, clean


def test_version_then_device_on_connect(make_hub):
    hub, address, _ = make_hub()
    c = Conn(address)
    version = c.expect("VERSION")
    assert version == {"class": "VERSION", **VERSION}
    device = c.expect("DEVICE")
    assert device == {"class": "DEVICE", "path": "/dev/ttyFOG0", "serial": "FOG-TEST-0001", "rate_hz": 100}
    c.send("?VERSION;\n")
    assert c.expect("VERSION") == version
    assert hub.clients == 1 and hub.watchers == 0


def test_no_device_line_when_no_device(make_hub):
    _, address, _ = make_hub(device=lambda: None)
    c = Conn(address)
    c.expect("VERSION")
    c.send("?VERSION\n")  # the trailing ; is optional
    c.expect("VERSION")  # and no DEVICE came in between


def test_clean_drops_none_and_non_finite_recursively():
    obj = {
        "a": None,
        "b": math.nan,
        "c": math.inf,
        "d": -math.inf,
        "e": 1.5,
        "f": 0,
        "g": False,
        "h": {"x": None, "y": [1.0, math.nan, None, 2]},
        "i": np.float64("nan"),
        "j": np.float32(2.5),
        "k": np.int64(7),
        "l": np.array([1.0, np.nan]),
        "m": "text",
        "n": (None, 3),
    }
    assert clean(obj) == {
        "e": 1.5,
        "f": 0,
        "g": False,
        "h": {"y": [1.0, 2]},
        "j": 2.5,
        "k": 7,
        "l": [1.0],
        "m": "text",
        "n": [3],
    }
    assert json.dumps(clean(obj), allow_nan=False)


_LEAVES = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(2**70), 2**70),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=12),
    st.sampled_from(["null", "a null here", "nullable"]),
    st.floats(allow_nan=True, allow_infinity=True).map(np.float64),
    st.integers(-1000, 1000).map(np.int64),
    st.booleans().map(np.bool_),
)
_OBJECTS = st.dictionaries(
    st.text(max_size=8),
    st.recursive(
        _LEAVES,
        lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner, max_size=4),
        max_leaves=12,
    ),
    max_size=8,
)


@settings(max_examples=200, deadline=None)
@given(_OBJECTS)
def test_encode_gives_the_line_of_the_cleaned_object_whatever_it_holds(obj):
    """``encode`` skips ``clean`` for objects that are clean already: the line must be the same as encoding the
    cleaned object, for Nones, non-finite floats, numpy scalars and the text "null" anywhere."""
    reference = (json.dumps(clean(obj), separators=(",", ":"), allow_nan=False) + "\n").encode()
    assert encode(obj) == reference


def test_absent_values_are_omitted_in_output(make_hub):
    hub, address, _ = make_hub()
    c = Conn(address)
    c.greeting()
    c.send('?WATCH={"enable":true}\n')
    c.expect("WATCH")
    hub.publish_angles(
        [
            angle(
                1,
                1.0,
                t_top_c=math.nan,
                t_bottom_c=None,
                t_housing_c=20.25,
                drift_dph=math.inf,
                extra={"q": None, "r": [math.nan, 1]},
            )
        ]
    )
    hub.publish({"class": "STATUS", "state": "running", "fault": None, "rate": math.nan})
    raw = c.raw_line()
    assert json.loads(raw) == {
        "class": "ANGLE",
        "seq": 1,
        "t_s": 1.0,
        "angle_arcsec": 0.5,
        "t_housing_c": 20.25,
        "extra": {"r": [1]},
    }
    assert b"null" not in raw and b"NaN" not in raw and b"Infinity" not in raw
    assert c.line() == {"class": "STATUS", "state": "running"}


def test_angle_objects_need_t_s(make_hub):
    hub, address, _ = make_hub()
    c = Conn(address)
    c.greeting()
    c.send("?WATCH={}\n")
    c.expect("WATCH")
    with pytest.raises(ValueError, match="t_s"):
        hub.publish_angles([{"seq": 1}])
    with pytest.raises(ValueError, match="t_s"):
        hub.publish_angles([{"seq": 1, "t_s": math.nan}])
    hub.publish_angles([{"seq": 2, "t_s": 0.0}])  # class defaults to ANGLE
    assert c.line() == {"class": "ANGLE", "seq": 2, "t_s": 0.0}


# --------------------------------------------------------------------------- WATCH


def test_watch_enables_decimates_and_disables(make_hub):
    hub, address, _ = make_hub()
    every, decimated, idle = Conn(address), Conn(address), Conn(address)
    for c in (every, decimated, idle):
        c.greeting()
    every.send('?WATCH={"enable":true};\n')
    assert every.line() == {"class": "WATCH", "enable": True}
    decimated.send('?WATCH={"enable":true,"rate_hz":3};\n')
    assert decimated.line() == {"class": "WATCH", "enable": True, "rate_hz": 3}
    idle.send("?WATCH;\n")  # no object: report the policy, change nothing
    assert idle.line() == {"class": "WATCH", "enable": False}
    assert hub.watchers == 2 and hub.clients == 3

    # device time in ms: 5003 + 10 k (100 Hz, clear of the period boundaries), in two batches
    n = 250
    t_ms = [5003 + 10 * k for k in range(n)]
    objs = [angle(k, t_ms[k] / 1000) for k in range(n)]
    hub.publish_angles(objs[:117])
    hub.publish_angles(objs[117:])
    hub.publish({"class": "STATUS", "n": 1})

    assert [every.expect("ANGLE")["seq"] for _ in range(n)] == list(range(n))
    assert every.expect("STATUS") == {"class": "STATUS", "n": 1}

    # independently: the first sample of each 1/3 s period, in exact integer arithmetic
    expected, last = [], None
    for k, ms in enumerate(t_ms):
        period = ms * 3 // 1000
        if period != last:
            expected.append(k)
            last = period
    got = []
    while True:
        obj = decimated.line()
        if obj["class"] == "STATUS":
            break
        got.append(obj["seq"])
    assert got == expected
    assert len(expected) == math.floor(7.493 * 3) - math.floor(5.003 * 3) + 1

    # a non-watcher gets STATUS, never ANGLE
    assert idle.line() == {"class": "STATUS", "n": 1}

    every.send('?WATCH={"enable":false}\n')
    assert every.line() == {"class": "WATCH", "enable": False}
    assert hub.watchers == 1
    hub.publish_angles([angle(1000, 100.0)])
    every.sync()  # the next line after the disable is the answer: no ANGLE came
    assert decimated.expect("ANGLE")["seq"] == 1000


def test_watch_rejects_bad_policy(make_hub):
    hub, address, _ = make_hub()
    c = Conn(address)
    c.greeting()
    for bad in ('{"enable":"yes"}', '{"rate_hz":0}', '{"rate_hz":-1}', '{"rate_hz":"fast"}', '{"rate_hz":true}'):
        c.send(f"?WATCH={bad};\n")
        err = c.expect("ERROR")
        assert err["command"] == "WATCH"
    assert hub.watchers == 0


# --------------------------------------------------------------------------- input limits and errors


def test_oversized_line_gives_error_and_connection_survives(make_hub):
    _, address, _ = make_hub(max_line_bytes=4096)
    c = Conn(address)
    c.greeting()
    c.send("?ECHO=" + json.dumps({"pad": "x" * 5000}) + ";\n")
    assert "longer than 4096" in c.expect("ERROR")["message"]
    # an oversized line arriving in pieces gives one ERROR; its tail is discarded, not parsed
    c.send(b"?ECHO=" + b"y" * 3000)
    c.send(b"y" * 3000)
    c.send(b"y" * 3000 + b'}\n?ECHO={"ok":1};\n')
    assert "longer than" in c.expect("ERROR")["message"]
    assert c.expect("ECHO")["args"] == {"ok": 1}
    c.send("?ECHO=" + json.dumps({"pad": "z" * 4000}) + "\n")  # under the limit: fine
    assert len(c.expect("ECHO")["args"]["pad"]) == 4000


def test_64k_without_newline_disconnects(make_hub):
    _, address, _ = make_hub()
    c = Conn(address)
    c.greeting()
    with contextlib.suppress(BrokenPipeError, ConnectionResetError):
        c.send(b"?" + b"A" * (MAX_UNTERMINATED_BYTES + 10))
    lines = []
    try:
        while True:
            lines.append(c.line())
    except (EOFError, ConnectionResetError):
        pass
    assert lines and lines[-1]["class"] == "ERROR" and "without a newline" in lines[-1]["message"]
    assert all(obj["class"] == "ERROR" for obj in lines)
    c2 = Conn(address)  # the hub itself is fine
    c2.greeting()


def test_bad_json_non_object_malformed_and_unknown_commands(make_hub):
    _, address, control = make_hub()
    c = Conn(address)
    c.greeting()
    c.send('?ECHO={"a":;\n?ECHO=[1,2];\n?ECHO=3\nhello\n?lower;\n?NOSUCH;\n?NOSUCH={"x":1}\n\n\r\n?ECHO={"a":1}\r\n')
    err = c.expect("ERROR")
    assert err["command"] == "ECHO" and "invalid JSON" in err["message"]
    err = c.expect("ERROR")
    assert err["command"] == "ECHO" and "object" in err["message"]
    assert c.expect("ERROR")["command"] == "ECHO"
    assert "command" not in c.expect("ERROR")
    assert "command" not in c.expect("ERROR")
    assert c.expect("ERROR") == {"class": "ERROR", "message": "unknown command ?NOSUCH", "command": "NOSUCH"}
    assert c.expect("ERROR")["command"] == "NOSUCH"
    assert c.expect("ECHO")["args"] == {"a": 1}  # empty lines ignored, \r tolerated
    c.send("?ECHO=" + "[" * 4000 + "\n")  # deeper than Python's recursion limit
    assert "invalid JSON" in c.expect("ERROR")["message"]
    c.sync()
    assert [name for name, _, _ in control.calls] == ["NOSUCH", "NOSUCH", "ECHO"]


def test_rate_limit_refuses_excess_then_disconnects(make_hub):
    _, address, _ = make_hub()
    c = Conn(address)
    c.greeting()
    c.send("?VERSION;\n" * 150)
    kinds = [c.line()["class"] for _ in range(101)]
    # a stalled machine may roll the 1 s window: then more VERSION lines, and the refusal later
    assert kinds[:100] == ["VERSION"] * 100 and kinds[100] in ("ERROR", "VERSION")
    c.send("?VERSION;\n" * 1500)
    lines = 0
    try:
        while True:
            c.line()
            lines += 1
    except (EOFError, ConnectionResetError):
        pass
    assert lines < 1500  # closed after 1000 refused commands


def test_client_half_close_still_gets_replies(make_hub):
    _, address, _ = make_hub()
    c = Conn(address)
    c.greeting()
    c.send('?ECHO={"n":1};\n')
    c.sock.shutdown(socket.SHUT_WR)
    assert c.expect("ECHO")["args"] == {"n": 1}
    with pytest.raises(EOFError):
        c.line()


# --------------------------------------------------------------------------- control callback


def test_control_dict_future_and_exceptions(make_hub):
    hub, address, control = make_hub()
    a, b = Conn(address), Conn(address)
    a.greeting()
    b.greeting()
    a.send('?ECHO={"x":[1,2]};\n')
    echo = a.expect("ECHO")
    assert echo["args"] == {"x": [1, 2]} and "nothing" not in echo
    client_a = echo["client"]
    a.send("?BARE;\n")
    assert a.line() == {"class": "BARE", "ok": True}  # a reply without class takes the command's name
    a.send("?FAIL;\n")
    assert a.line() == {"class": "ERROR", "message": "the instrument is on fire", "command": "FAIL"}
    a.send("?FUTFAIL;\n")
    assert a.line() == {"class": "ERROR", "message": "future failed", "command": "FUTFAIL"}

    # a pending Future blocks neither the loop nor other clients
    a.send('?SLOW={"n":5};\n')
    assert control.slow_called.wait(TIMEOUT_S)
    b.send("?ECHO;\n")
    assert b.expect("ECHO")["client"] != client_a
    hub.publish({"class": "STATUS", "n": 2})
    assert b.expect("STATUS")["n"] == 2
    assert a.expect("STATUS")["n"] == 2  # a's published lines still flow
    threading.Thread(target=control.pending.set_result, args=({"class": "SLOW", "done": True, "x": None},)).start()
    assert a.line() == {"class": "SLOW", "done": True}
    assert ("SLOW", {"n": 5}, client_a) in control.calls


def test_control_future_timeout(make_hub):
    _, address, _ = make_hub(control_timeout_s=0.2)
    c = Conn(address)
    c.greeting()
    c.send("?SLOW;\n")
    err = c.expect("ERROR")
    assert err["command"] == "SLOW" and "no answer" in err["message"]
    c.sync()


def test_token_required_for_control_commands(make_hub):
    _, address, control = make_hub(token="s3cret")
    c = Conn(address)
    c.expect("VERSION")  # no DEVICE before AUTH
    c.send("?ECHO;\n")
    assert c.line() == {"class": "ERROR", "message": "unauthorized", "command": "ECHO"}
    c.send("?NOSUCH;\n")
    assert c.expect("ERROR")["message"] == "unauthorized"
    c.send('?WATCH={"enable":true};\n')  # reading needs the token too (asking for the policy and VERSION do not)
    assert c.line() == {"class": "ERROR", "message": "unauthorized", "command": "WATCH"}
    c.send("?WATCH;\n")
    assert c.expect("WATCH")["enable"] is False
    c.sync()
    c.send('?AUTH={"token":"wrong"};\n?AUTH;\n')
    assert c.expect("ERROR")["command"] == "AUTH"
    assert c.expect("ERROR")["command"] == "AUTH"
    assert control.calls == []
    c.send('?AUTH={"token":"s3cret"};\n')
    assert c.line() == {"class": "AUTH", "authorized": True}
    c.expect("DEVICE")  # now that it may know
    c.send("?ECHO;\n")
    c.expect("ECHO")
    other = Conn(address)  # authorization is per connection
    other.expect("VERSION")
    other.send("?ECHO;\n")
    assert other.expect("ERROR")["message"] == "unauthorized"


def test_repeated_bad_tokens_disconnect(make_hub):
    _, address, _ = make_hub(token="s3cret")
    c = Conn(address)
    c.expect("VERSION")
    c.send('?AUTH={"token":"guess"};\n' * 10)
    errors = 0
    with pytest.raises((EOFError, ConnectionResetError)):
        while True:
            c.expect("ERROR")
            errors += 1
    assert errors == 5


def test_non_loopback_bind_needs_a_token():
    kwargs = {"version": lambda: VERSION, "device": lambda: None, "control": lambda *a: None}
    for host in ("0.0.0.0", "", "::", "192.0.2.7"):
        with pytest.raises(ValueError, match="token"):
            Hub(host, 0, **kwargs)
    with pytest.raises(ValueError):
        Hub("127.0.0.1", 0, token="", **kwargs)
    Hub("0.0.0.0", 0, token="s3cret", **kwargs)  # constructed, not started
    for host in ("127.0.0.1", "127.0.0.2", "::1", "localhost"):
        Hub(host, 0, **kwargs)
        assert is_loopback_host(host)


# --------------------------------------------------------------------------- slow clients, threads


def test_stalled_client_is_dropped_while_another_receives_everything(make_hub):
    hub, address, control = make_hub(max_backlog_s=0.3)
    stalled = Conn(address, rcvbuf=4096)
    stalled.send('?WATCH={"enable":true};\n?SYNC;\n')  # and never reads again
    assert control.sync.wait(TIMEOUT_S)
    good = Conn(address)
    good.greeting()
    good.send('?WATCH={"enable":true};\n')
    good.expect("WATCH")
    assert hub.watchers == 2

    pad = "p" * 400
    batch, seq, published = 100, 0, 0
    slowest_publish_s = 0.0
    deadline = time.monotonic() + 10.0
    while hub.dropped_clients == 0:  # lockstep: publish a batch, the good client reads all of it
        assert time.monotonic() < deadline, "the stalled client was never dropped"
        objs = [angle(seq + i, (seq + i) / 1000, pad=pad) for i in range(batch)]
        t0 = time.monotonic()
        hub.publish_angles(objs)
        slowest_publish_s = max(slowest_publish_s, time.monotonic() - t0)
        seq += batch
        published += batch
        for i in range(batch):
            assert good.line()["seq"] == seq - batch + i
    for _ in range(3):  # after the drop, publishing goes on
        hub.publish_angles([angle(seq + i, (seq + i) / 1000) for i in range(batch)])
        seq += batch
    hub.publish({"class": "STATUS", "end": True})
    tail = []
    while (obj := good.line())["class"] == "ANGLE":
        tail.append(obj["seq"])
    assert obj == {"class": "STATUS", "end": True}
    assert tail == list(range(published, seq))  # every published line, in order, exactly once
    assert hub.dropped_clients == 1 and hub.clients == 1 and hub.watchers == 1
    assert slowest_publish_s < 1.0  # publishing never waited for the stalled client
    stalled.wait_closed()


def test_publish_from_another_thread_preserves_order(make_hub):
    hub, address, _ = make_hub(max_backlog_s=30.0)
    conns = [Conn(address) for _ in range(2)]
    for c in conns:
        c.greeting()
        c.send('?WATCH={"enable":true};\n')
        c.expect("WATCH")
    batches, per_batch = 400, 25
    results: dict[int, list] = {}

    def read_all(i: int, c: Conn) -> None:
        got = []
        while True:
            obj = c.line()
            if obj["class"] == "STATUS" and obj.get("last"):
                break
            got.append(obj["seq"] if obj["class"] == "ANGLE" else ("S", obj["n"]))
        results[i] = got

    readers = [threading.Thread(target=read_all, args=(i, c)) for i, c in enumerate(conns)]
    for r in readers:
        r.start()

    def produce() -> None:
        for b in range(batches):
            hub.publish_angles([angle(b * per_batch + i, (b * per_batch + i) / 100) for i in range(per_batch)])
            if b % 50 == 49:
                hub.publish({"class": "STATUS", "n": b})
        hub.publish({"class": "STATUS", "last": True})

    producer = threading.Thread(target=produce)
    producer.start()
    producer.join(TIMEOUT_S * 2)
    for r in readers:
        r.join(TIMEOUT_S * 2)
    expected = []
    for b in range(batches):
        expected.extend(range(b * per_batch, (b + 1) * per_batch))
        if b % 50 == 49:
            expected.append(("S", b))
    assert results[0] == expected
    assert results[1] == expected
    assert hub.dropped_clients == 0
    assert hub.bytes_sent > 0


def test_lifecycle(make_hub):
    hub, address, _ = make_hub()
    assert address[0] == "127.0.0.1" and address[1] > 0
    c = Conn(address)
    c.greeting()
    hub.stop()
    with pytest.raises((EOFError, ConnectionResetError)):
        c.line()
    hub.stop()  # idempotent
    hub.publish({"class": "STATUS"})  # after stop: a no-op, never an error
    hub.publish_angles([angle(1, 1.0)])
    with pytest.raises(ConnectionRefusedError):
        socket.create_connection(address, timeout=TIMEOUT_S)


def test_start_reports_bind_failure(make_hub):
    _, address, _ = make_hub()
    hub = Hub(*address, version=lambda: VERSION, device=lambda: None, control=lambda *a: None)
    with pytest.raises(OSError):
        hub.start()


# --------------------------------------------------------------------------- UDP


def test_udp_datagram_exact_bytes_and_round_trip():
    data = encode_datagram(
        seq=123456789012,
        t_s=1234.5625,
        angle_arcsec=-3.25,
        angle_raw_arcsec=-3.5,
        rate_dph=15.041,
        drift_dph=0.0125,
        t_top_c=20.1,
        t_bottom_c=None,
        t_housing_c=19.875,
        flags=FLAG_GAP | FLAG_THERMOMETER_FAULT,
    )
    # independently: the documented layout, field by field
    expected = (
        b"FOGA"
        + struct.pack(">H", 1)
        + struct.pack(">H", 3)
        + struct.pack(">Q", 123456789012)
        + struct.pack(">d", 1234.5625)
        + struct.pack(">d", -3.25)
        + struct.pack(">d", -3.5)
        + struct.pack(">d", 15.041)
        + struct.pack(">d", 0.0125)
        + struct.pack(">f", 20.1)
        + bytes.fromhex("7fc00000")
        + struct.pack(">f", 19.875)
    )
    assert data == expected
    assert len(data) == DATAGRAM_SIZE == 68
    decoded = decode_datagram(data)
    assert decoded["version"] == 1 and decoded["flags"] == 3 and decoded["seq"] == 123456789012
    assert decoded["t_s"] == 1234.5625 and decoded["rate_dph"] == 15.041
    assert decoded["t_top_c"] == float(np.float32(20.1))
    assert math.isnan(decoded["t_bottom_c"]) and decoded["t_housing_c"] == 19.875
    assert decode_datagram(data + b"future fields")["seq"] == 123456789012
    for bad in (data[:67], b"FOGB" + data[4:], data[:4] + b"\x00\x02" + data[6:]):
        with pytest.raises(ValueError):
            decode_datagram(bad)


def test_udp_publisher_sends_one_datagram_per_sample_and_never_raises():
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.settimeout(TIMEOUT_S)
    try:
        pub = UdpPublisher(*rx.getsockname())
        assert pub.send(seq=1, t_s=0.01, angle_arcsec=1.0, t_top_c=20.0)
        assert (
            pub.send_many(
                [
                    {
                        "class": "ANGLE",
                        "seq": 2,
                        "t_s": 0.02,
                        "angle_arcsec": 2.0,
                        "flags": 1,
                        "t_housing_c": None,
                        "unknown": "ignored",
                    }
                ]
            )
            == 1
        )
        # the service's ANGLE object: thermometers in temps_c, flags as names
        assert pub.send(
            {
                "class": "ANGLE",
                "seq": 3,
                "t_s": 0.03,
                "rate_dph": 1.5,
                "temps_c": {"top": 20.5, "housing": 19.5},
                "flags": ["gap", "uncompensated", "new"],
            }
        )
        first = decode_datagram(rx.recv(2048))
        second_raw = rx.recv(2048)
        assert len(second_raw) == 68
        second = decode_datagram(second_raw)
        assert (first["seq"], first["angle_arcsec"], first["t_top_c"]) == (1, 1.0, 20.0)
        assert math.isnan(first["rate_dph"])
        assert (second["seq"], second["flags"], second["t_s"]) == (2, 1, 0.02)
        assert math.isnan(second["t_housing_c"])
        third = decode_datagram(rx.recv(2048))
        assert (third["seq"], third["rate_dph"], third["t_top_c"], third["t_housing_c"]) == (3, 1.5, 20.5, 19.5)
        assert math.isnan(third["t_bottom_c"])
        assert third["flags"] == FLAG_GAP | FLAG_UNCOMPENSATED
        assert pub.sent == 3 and pub.send_errors == 0
        pub.close()
        assert pub.send(seq=4) is False  # a dead socket is counted, never raised
        assert pub.send_errors == 1 and pub.last_error
    finally:
        rx.close()


def test_udp_flag_bits_are_the_compensators():
    assert {name: bit for bit, name in FLAG_NAMES.items()} == FLAG_BITS


def test_a_client_hanging_up_is_logged_at_info_not_as_a_failure(make_hub):
    """A client that resets its connection (a script exiting with lines unread) was logged at level
    ``error`` as ``client_failed``; a hang-up is no bug: ``client_hung_up`` at info."""
    seen: list[dict] = []
    gone = threading.Event()

    def keep(_logger, method, event):
        seen.append({**event, "level": method})
        if event.get("event") in ("client_hung_up", "client_failed", "client_closed"):
            gone.set()
        raise structlog.DropEvent

    structlog.configure(processors=[keep], wrapper_class=structlog.make_filtering_bound_logger(0))
    _, address, _ = make_hub()
    c = Conn(address)
    c.greeting()
    c.sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))  # close sends RST
    c.sock.close()
    assert gone.wait(10)
    events = [(e["event"], e["level"]) for e in seen if e["event"].startswith("client_")]
    assert ("client_hung_up", "info") in events
    assert not [e for e in seen if e["level"] in ("error", "warning")]
