"""The client library (``fog_driver.client``): the protocol without I/O byte by byte, the typed objects, the
blocking and asyncio clients against a hub in this process (reconnects, gaps, refusals) and against a real
daemon (control commands, the samples equal to the daemon's own lines), and the example station script.

No sleeps to synchronize: readiness is the daemon's "listening on" line, the hub's bound port, the client's
own answers; a publisher thread paces samples (a pace, not a synchronization)."""

from __future__ import annotations

import asyncio
import csv
import json
import math
import os
import subprocess
import sys
import threading
from pathlib import Path

import pytest
from daemon_hil import Client as RawClient
from daemon_hil import Daemon

from fog_driver.client import (
    Angle,
    AsyncClient,
    Bias,
    Client,
    CommandRefused,
    ConnectError,
    ConnectionLost,
    Device,
    ErrorReply,
    Other,
    Reply,
    Session,
    Status,
    Unauthorized,
    UnknownCommand,
    Version,
    since_bias_sigma_dph,
)
from fog_driver.daemon.hub import Hub

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT / "tests" / "data"
GUARD_S = 30.0


# --------------------------------------------------------------------------- the session, without I/O

SCRIPT = [
    b'{"class":"VERSION","release":"0.1.0","proto_major":1,"proto_minor":0,"model":"wesn"}',
    b'{"class":"DEVICE","path":"/dev/ttyFOG","state":"activated","format":"fog-v1","serial":"FOG-1","rate_hz":1000}',
    b'{"class":"WATCH","enable":true}',
    b'{"class":"ANGLE","seq":7,"t_s":0.007,"angle_arcsec":1.5,"angle_raw_arcsec":2.5,"rate_dph":0.1,'
    b'"rate_raw_dph":0.2,"drift_dph":0.05,"temps_c":{"top":25.5,"bottom":24.0,"housing":23.0},"flags":["gap"],'
    b'"utc":"2026-12-02T14:56:26.123Z"}',
    b"not json at all",
    b'{"class":"ANGLE","t_s":1.0}',  # no seq: not a usable sample
    b'{"class":"FUTURE","x":1}',
    b'{"class":"ZERO","zeroed":true}',
    b'{"class":"BIAS","state":"done","capture_id":3,"bias_dph":0.25,"seconds":60.0}',
    b'{"class":"ERROR","message":"unknown command ?FOO","command":"FOO"}',
    b'{"class":"STATUS","uptime_s":1.5,"port_state":"open","frames":10,"crc_errors":0,"adapting":false,"new_key":3}',
    b"",
    b'{"class":"ANGLE","seq":8,"t_s":0.008,"angle_arcsec":1.6,"temps_c":{"top":"hot"},"flags":"gap","rate_dph":'
    + b"9" * 400
    + b"}",  # an integer beyond float's range: absent, not an OverflowError
]
STREAM = b"".join(line + b"\r\n" if i == 3 else line + b"\n" for i, line in enumerate(SCRIPT))


def _run_session(chunks: list[bytes]) -> tuple[Session, list, list]:
    session = Session()
    session.connection_made()
    zero, _ = session.request("ZERO")
    foo, _ = session.request("FOO")
    status, _ = session.request("STATUS")
    out = []
    for chunk in chunks:
        out += session.receive(chunk)
    return session, out, [zero, foo, status]


def test_the_session_types_every_object_and_pairs_answers_with_requests():
    session, out, (zero, foo, status) = _run_session([STREAM])
    kinds = [type(m).__name__ for m in out]
    assert kinds == ["Version", "Device", "Reply", "Angle", "Other", "Reply", "Bias", "ErrorReply", "Status", "Angle"]
    version, device, watch, angle, other, zeroed, bias, error, stat, second = out
    assert version == Version(release="0.1.0", proto_major=1, proto_minor=0, model="wesn")  # a daemon before 1.1
    assert device.activated and device.format == "fog-v1" and device.rate_hz == 1000.0 and device.firmware is None
    assert watch.kind == "WATCH" and watch.get("enable") is True
    assert angle == Angle(
        seq=7,
        t_s=0.007,
        angle_arcsec=1.5,
        angle_raw_arcsec=2.5,
        rate_dph=0.1,
        rate_raw_dph=0.2,
        drift_dph=0.05,
        temps_c={"top": 25.5, "bottom": 24.0, "housing": 23.0},
        flags=("gap",),
        utc="2026-12-02T14:56:26.123Z",
    )
    assert angle.drift_sigma_dph is None and bias.bias_sigma_dph is None and stat.bias_sigma_dph is None
    assert angle.line == SCRIPT[3] and json.loads(angle.line) == dict(angle.raw)  # the \r is not part of it
    assert isinstance(other, Other) and other.kind == "FUTURE" and other.raw["x"] == 1
    assert (zero.reply, foo.reply, status.reply) == (zeroed, error, stat)  # in order, events in between skipped
    assert bias.state == "done" and bias.bias_dph == 0.25 and bias.capture_id == 3
    assert isinstance(error, ErrorReply) and error.command == "FOO"
    assert stat.frames == 10 and stat.adapting is False and stat.raw["new_key"] == 3 and stat.bias_dph is None
    assert second.temps_c == {} and second.flags == () and second.drift_dph is None  # wrong types: absent
    assert second.rate_dph is None and second.angle_arcsec == 1.6
    assert session.malformed == 2 and session.unknown == 1
    assert (session.version, session.device, session.status) == (version, device, stat)
    with pytest.raises(TypeError):
        angle.temps_c["top"] = 0.0  # read-only


def test_protocol_1_1_sigma_keys_are_typed_and_combine_in_the_since_bias_form():
    lines = [
        b'{"class":"ANGLE","seq":1,"t_s":0.1,"drift_dph":0.05,"drift_sigma_dph":0.03,"flags":[]}',
        b'{"class":"ANGLE","seq":2,"t_s":0.2,"drift_dph":0.0,"flags":["uncompensated"]}',  # no estimate: omitted
        b'{"class":"ANGLE","seq":3,"t_s":0.3,"drift_sigma_dph":"small"}',  # the wrong type: absent
        b'{"class":"BIAS","state":"done","capture_id":1,"bias_dph":9.5,"seconds":60.0,"bias_sigma_dph":0.04}',
        b'{"class":"STATUS","bias_captured":true,"bias_dph":9.5,"bias_sigma_dph":0.04}',
    ]
    session = Session()
    session.connection_made()
    first, second, third, bias, status = session.receive(b"\n".join(lines) + b"\n")
    assert (first.drift_sigma_dph, second.drift_sigma_dph, third.drift_sigma_dph) == (0.03, None, None)
    assert bias.bias_sigma_dph == 0.04 and status.bias_sigma_dph == 0.04 and status.bias_captured is True
    # sqrt(sigma(t)^2 + sigma(t_b)^2): 0.03 and 0.04 make 0.05; anything absent makes it absent
    assert since_bias_sigma_dph(first.drift_sigma_dph, status.bias_sigma_dph) == pytest.approx(0.05, rel=1e-15)
    assert since_bias_sigma_dph(5.0, 12.0) == 13.0
    for a, b in ((second.drift_sigma_dph, 0.04), (0.03, None), (math.nan, 0.04), (0.03, True), (None, None)):
        assert since_bias_sigma_dph(a, b) is None


def test_the_session_gives_the_same_messages_byte_by_byte_and_at_every_split():
    _, whole, _ = _run_session([STREAM])
    _, bytewise, _ = _run_session([STREAM[i : i + 1] for i in range(len(STREAM))])
    assert bytewise == whole and [m.line for m in bytewise] == [m.line for m in whole]
    for cut in range(1, len(STREAM)):
        _, split, requests = _run_session([STREAM[:cut], STREAM[cut:]])
        assert split == whole, cut
        assert all(r.reply is not None for r in requests)


def _angle_line(seq: int) -> bytes:
    return json.dumps({"class": "ANGLE", "seq": seq, "t_s": seq / 100, "angle_arcsec": 0.0}).encode() + b"\n"


def test_the_first_sample_after_a_reconnect_carries_the_gap():
    clock = iter([100.0, 102.5, 200.0, 201.0]).__next__
    session = Session(clock=clock)
    session.connection_made()
    first = session.receive(_angle_line(10) + _angle_line(11))
    assert [a.gap_before for a in first] == [None, None]
    session.connection_lost()  # at t=100
    session.connection_made()
    after = session.receive(_angle_line(15) + _angle_line(16))
    gap = after[0].gap_before  # seen at t=102.5
    assert (gap.last_seq, gap.seq, gap.missed, gap.down_s) == (11, 15, 3, 2.5) and after[1].gap_before is None
    session.connection_lost()  # t=200: the daemon restarts, its sequence starts again
    session.connection_made()
    (restarted,) = session.receive(_angle_line(2))
    assert restarted.gap_before.missed is None and "restarted" in restarted.gap_before.reason
    assert restarted.gap_before.down_s == 1.0


def test_an_oversized_line_is_a_protocol_error_in_its_place_and_the_next_one_read():
    session = Session()
    session.connection_made()
    out = session.receive(_angle_line(0) + b'{"class":"ANGLE","x":"' + b"y" * 70_000 + b'"}\n' + _angle_line(1))
    assert [type(m).__name__ for m in out] == ["Angle", "ProtocolError", "Angle"]
    assert [out[0].seq, out[2].seq] == [0, 1] and session.reader.oversized == 1
    assert "line over 65536 bytes" in str(out[1]) and out[1].exit_status == 76


def test_watch_arguments_are_checked_before_anything_is_sent():
    assert Session.watch_args(None) == {"enable": True}
    assert Session.watch_args(10) == {"enable": True, "rate_hz": 10}
    for bad in (0, -1, math.inf, math.nan, 10_001, True, "10"):
        with pytest.raises(ValueError):
            Session.watch_args(bad)


# --------------------------------------------------------------------------- against a hub in this process


class Instrument:
    """A hub fed by a thread publishing samples at 100 Hz from ``first_seq`` (a pace, not a synchronization).

    ``proto_minor`` 1: its samples carry ``drift_sigma_dph`` = ``sigma_of(seq)``, omitted on every third
    (no estimate); 0: a daemon from before that key."""

    def __init__(
        self, port: int = 0, first_seq: int = 1, token: str | None = None, control=None, proto_minor: int = 0
    ) -> None:
        self.proto_minor = proto_minor
        self.hub = Hub(
            "127.0.0.1",
            port,
            version=lambda: {"release": "test", "proto_major": 1, "proto_minor": proto_minor},
            device=lambda: {"path": "/dev/test", "state": "activated"},
            control=control or (lambda name, args, cid: {"class": name}),
            token=token,
        )
        self.address = self.hub.start()
        self.seq = first_seq
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._publish, daemon=True)
        self.thread.start()

    @staticmethod
    def sigma_of(seq: int) -> float | None:
        return None if seq % 3 == 0 else 0.01 + seq * 1e-6

    def _publish(self) -> None:
        while not self.stop.is_set():
            obj = {"seq": self.seq, "t_s": self.seq / 100, "angle_arcsec": self.seq * 0.5, "drift_dph": 0.25}
            if self.proto_minor >= 1 and self.sigma_of(self.seq) is not None:
                obj["drift_sigma_dph"] = self.sigma_of(self.seq)
            self.hub.publish_angles([{**obj, "temps_c": {"top": 25.0}, "flags": []}])
            self.seq += 1
            self.stop.wait(0.01)

    def close(self) -> None:
        self.stop.set()
        self.thread.join(GUARD_S)
        self.hub.stop()


@pytest.fixture
def instrument():
    made = []

    def make(**kwargs) -> Instrument:
        made.append(Instrument(**kwargs))
        return made[-1]

    yield make
    for inst in made:
        inst.close()


def test_a_lost_connection_is_made_again_and_the_gap_reported(instrument):
    first = instrument()
    host, port = first.address
    with Client(first.address, backoff_initial_s=0.01, backoff_max_s=0.05) as c:
        assert c.version.release == "test" and c.device.activated
        seen = []
        for a in c.angles():
            seen.append(a)
            if len(seen) == 5:
                last = a.seq
                first.close()  # the daemon goes; another comes on the same port, 1000 samples later
                instrument(port=port, first_seq=last + 1001)
            if a.gap_before is not None:
                break
        assert [a.seq for a in seen[1:5]] == [seen[0].seq + k for k in range(1, 5)]  # every sample, in order
        gap = seen[-1].gap_before
        assert gap.last_seq == last and gap.missed == seen[-1].seq - last - 1 >= 1000
        assert c.reconnects == 1


@pytest.mark.parametrize("proto_minor", [0, 1])
def test_both_clients_read_the_drift_sigma_and_a_daemon_before_1_1_gives_none(instrument, proto_minor):
    inst = instrument(proto_minor=proto_minor)

    def expected(a):
        return Instrument.sigma_of(a.seq) if proto_minor >= 1 else None

    with Client(inst.address) as c:
        assert c.version.proto_minor == proto_minor
        got = [a for a, _ in zip(c.angles(), range(6))]
    assert [a.drift_sigma_dph for a in got] == [expected(a) for a in got] and [a.drift_dph for a in got] == [0.25] * 6

    async def main():
        got = []
        async with AsyncClient(inst.address) as c:
            async for a in c.angles():
                got.append(a)
                if len(got) == 6:
                    break
        return got

    got = asyncio.run(asyncio.wait_for(main(), GUARD_S))
    assert [a.drift_sigma_dph for a in got] == [expected(a) for a in got]
    assert any(v is None for v in map(expected, got)) and (proto_minor == 0 or any(map(expected, got)))


def test_without_reconnect_a_lost_connection_ends_the_iteration(instrument):
    inst = instrument()
    with Client(inst.address, reconnect=False) as c, pytest.raises(ConnectionLost, match="closed the connection"):
        for n, _ in enumerate(c.angles(), 1):
            if n == 3:
                inst.close()


def test_a_daemon_that_is_not_there_is_a_connect_error_at_once():
    with socket_port() as port:
        pass  # bound, then closed: nothing listens there now
    with pytest.raises(ConnectError, match=f"could not connect to 127.0.0.1:{port}"):
        Client(("127.0.0.1", port)).connect()


class socket_port:
    def __enter__(self) -> int:
        import socket

        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        return self.sock.getsockname()[1]

    def __exit__(self, *exc) -> None:
        self.sock.close()


def test_a_token_daemon_refuses_a_wrong_token_and_serves_the_right_one(instrument):
    inst = instrument(token="a-long-token")
    with pytest.raises(Unauthorized):
        Client(inst.address, token="wrong-token").connect()
    with Client(inst.address, reconnect=False) as c, pytest.raises(Unauthorized):  # no token: control is refused, typed
        c.zero()
    with Client(inst.address, token="a-long-token") as c:
        assert isinstance(c.zero(), Reply)
        assert next(iter(c.angles())).seq > 0


def test_a_command_answered_with_an_error_raises_it_typed(instrument):
    def control(name, args, cid):
        if name == "ZERO":
            return {"class": "ERROR", "message": "no samples yet: nothing to zero"}
        return {"class": "ERROR", "message": f"unknown command ?{name}", "command": name}

    inst = instrument(control=control)
    with Client(inst.address) as c:
        with pytest.raises(CommandRefused, match="nothing to zero") as refused:
            c.zero()
        assert refused.value.command == "ZERO" and refused.value.exit_status == 65
        with pytest.raises(UnknownCommand):
            c.reload()


def test_the_asyncio_client_reads_samples_while_another_task_sends_commands(instrument):
    inst = instrument()
    host, port = inst.address

    async def main():
        async with AsyncClient(inst.address, backoff_initial_s=0.01, backoff_max_s=0.05) as c:
            assert c.version.release == "test"
            seen = []
            zero = asyncio.create_task(c.zero())
            async for a in c.angles(rate_hz=1000):
                seen.append(a)
                if len(seen) == 5:
                    assert isinstance(await zero, Reply) and zero.result().kind == "ZERO"
                    last = a.seq
                    inst.close()
                    instrument(port=port, first_seq=last + 501)
                if a.gap_before is not None:
                    break
            return seen, last, c.reconnects

    seen, last, reconnects = asyncio.run(asyncio.wait_for(main(), GUARD_S))
    assert [a.seq for a in seen[:5]] == list(range(seen[0].seq, seen[0].seq + 5))
    assert seen[-1].gap_before.missed == seen[-1].seq - last - 1 >= 500 and reconnects == 1


def test_the_asyncio_client_without_reconnect_raises_connection_lost(instrument):
    inst = instrument()

    async def main():
        async with AsyncClient(inst.address, reconnect=False) as c:
            async for n, _ in _enumerate(c.angles()):
                if n == 3:
                    inst.close()

    with pytest.raises(ConnectionLost):
        asyncio.run(asyncio.wait_for(main(), GUARD_S))


async def _enumerate(iterator):
    n = 0
    async for item in iterator:
        n += 1
        yield n, item


# --------------------------------------------------------------------------- against a real daemon


@pytest.fixture
def daemon(tmp_path):
    d = Daemon(tmp_path, f"replay://{DATA / 'sim-short.bin'}?rate=300")
    yield d
    d.kill()


def test_the_samples_are_the_daemons_own_lines_typed(daemon):
    raw = RawClient(daemon.address)
    raw.send('?WATCH={"enable":true};')
    with Client(daemon.address) as c:
        got = {}
        for a in c.angles():
            got[a.seq] = a
            if len(got) == 200:
                break
    lines = {}
    while not set(got) <= set(lines):
        obj = raw.next("ANGLE")
        lines[obj["seq"]] = obj
    raw.close()
    seqs = sorted(got)
    assert seqs == list(range(seqs[0], seqs[0] + 200))  # every sample, none twice
    for seq, a in got.items():
        obj = lines[seq]
        assert (a.t_s, a.angle_arcsec, a.angle_raw_arcsec, a.rate_dph, a.drift_dph) == (
            obj["t_s"],
            obj["angle_arcsec"],
            obj["angle_raw_arcsec"],
            obj["rate_dph"],
            obj.get("drift_dph"),
        )
        assert dict(a.temps_c) == obj["temps_c"] and list(a.flags) == obj["flags"]
    assert daemon.terminate() == 0


def test_control_commands_against_the_daemon(daemon):
    with Client(daemon.address) as c:
        stream = c.angles(rate_hz=10)
        before = next(stream)
        assert isinstance(c.status(), Status) and c.status().frames > 0
        assert c.zero().kind == "ZERO"
        after = next(a for a in stream if a.seq > before.seq + 5)
        assert abs(after.angle_arcsec) < abs(before.angle_arcsec) + 50  # zeroed here: starts again near 0
        result = c.bias(seconds=2)
        assert isinstance(result, Bias) and result.state == "done" and math.isfinite(result.bias_dph)
        assert c.adapt(True, 0.0).get("enable") is True and c.adapt(False).get("enable") is False
        assert c.reload().kind == "RELOAD"
        with pytest.raises(CommandRefused, match="adapt_state"):
            c.save()  # this daemon has no adapt_state file
        assert isinstance(c.device, Device) and c.device.serial == "FOG-SIM-0001"
    assert daemon.terminate() == 0


def test_the_example_station_script_logs_the_angles_the_daemon_publishes(daemon, tmp_path):
    out = tmp_path / "angles.csv"
    raw = RawClient(daemon.address)
    raw.send('?WATCH={"enable":true};')
    host, port = daemon.address
    proc = subprocess.run(
        [
            sys.executable,
            str(ROOT / "examples" / "station_csv.py"),
            f"{host}:{port}",
            "--out",
            str(out),
            "--count",
            "50",
            "--rate-hz",
            "0",
        ],
        capture_output=True,
        text=True,
        timeout=GUARD_S,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    assert proc.returncode == 0, proc.stderr
    with out.open(newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 50
    published = {}
    while int(rows[-1]["seq"]) not in published:
        obj = raw.next("ANGLE")
        published[obj["seq"]] = obj
    raw.close()
    for row in rows:
        obj = published[int(row["seq"])]
        assert float(row["angle_arcsec"]) == obj["angle_arcsec"] and float(row["t_s"]) == obj["t_s"]
        assert row["utc"] == obj["utc"] and row["flags"] == " ".join(obj["flags"])
        assert row["drift_sigma_dph"] == (repr(obj["drift_sigma_dph"]) if "drift_sigma_dph" in obj else "")
    assert daemon.terminate() == 0


def test_asyncio_control_commands_against_the_daemon(daemon):
    async def main():
        async with AsyncClient(daemon.address) as c:
            stream = c.angles(rate_hz=10)
            first = await anext(stream)
            status, zeroed = await asyncio.gather(c.status(), c.zero())  # two commands in flight, answered in order
            bias = await c.bias(seconds=2)
            later = await anext(stream)
            await stream.aclose()
            return first, status, zeroed, bias, later, c.device

    first, status, zeroed, bias, later, device = asyncio.run(asyncio.wait_for(main(), GUARD_S))
    assert isinstance(status, Status) and status.frames > 0 and zeroed.kind == "ZERO"
    assert bias.state == "done" and math.isfinite(bias.bias_dph) and later.seq > first.seq
    assert device.serial == "FOG-SIM-0001" and device.activated
    assert daemon.terminate() == 0


def test_messages_and_poll_give_everything_in_order(instrument):
    inst = instrument()
    with Client(inst.address) as c:
        first = c.poll(GUARD_S)
        assert isinstance(first, Version)  # the greeting, then the DEVICE, then what the watch brings
        c.watch()
        kinds = []
        for message in c.messages():
            kinds.append(type(message).__name__)
            if kinds.count("Angle") == 3:
                break
        assert kinds[0] == "Device" and kinds.count("Angle") == 3
        request = c.send("ZERO")  # without waiting: the answer comes in the stream
        reply = next(m for m in c.messages() if isinstance(m, Reply))
        assert reply is request.reply and reply.kind == "ZERO"
