"""Tests of fog_driver.tools.watch: the `fog-driver watch` client of the daemon's NDJSON protocol.

The daemon is a tiny fake server in a thread: a listening socket that is bound and listening
before ``run_watch`` connects (the kernel's accept backlog is the readiness; nothing sleeps),
which sends a scripted conversation and closes.  The non-terminal view is what the tests read.
"""

from __future__ import annotations

import io
import itertools
import json
import math
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time

import pytest

from fog_driver.cli import main
from fog_driver.client import CommandRefused
from fog_driver.errors import DeviceError, TemporaryFailure, UsageError
from fog_driver.tools.watch import (
    DEFAULT_IDLE_S,
    MAX_LINE_BYTES,
    LineReader,
    compact_line,
    format_address,
    format_arcsec,
    format_dms,
    idle_limit_s,
    parse_address,
    parse_line,
    render,
    run_watch,
)

GUARD_S = 30.0  # a hang guard only, never a synchronisation

VERSION = {
    "class": "VERSION",
    "release": "0.1.0",
    "proto_major": 1,
    "proto_minor": 0,
    "instrument": {"serial": "FOG-SYN-0001", "firmware": "1.2", "rate_hz": 100},
}
DEVICE = {
    "class": "DEVICE",
    "path": "/tmp/fog-driver-sim.tty",
    "state": "activated",
    "serial": "FOG-SYN-0001",
    "rate_hz": 100,
}
STATUS = {
    "class": "STATUS",
    "frames": 4242,
    "crc_errors": 3,
    "missing_frames": 7,
    "clients": 1,
    "cpu_percent": 2.5,
    "port_state": "open",
    "some_future_key": "x",
}


def angle(seq: int, **extra) -> dict:
    obj = {
        "class": "ANGLE",
        "seq": seq,
        "t_s": 12.34 + 0.1 * (seq - 1),
        "angle_arcsec": 3723.5 + seq,
        "angle_raw_arcsec": -59.995 - seq,
        "rate_dph": 15.041,
        "drift_dph": 0.1234,
        "temps_c": {"top": 20.25, "bottom": 19.88, "housing": 19.6},
        "flags": ["gap"] if seq == 2 else [],
    }
    obj.update(extra)
    return obj


def ndjson(*objs) -> bytes:
    return b"".join(o if isinstance(o, bytes) else json.dumps(o).encode() + b"\n" for o in objs)


class FakeDaemon:
    """One connection: greet, read the WATCH request, send ``chunks``, then ``then`` ('close' or 'wait')."""

    def __init__(self, chunks: list[bytes], *, then: str = "close") -> None:
        self.listener = socket.create_server(("127.0.0.1", 0))  # listening before the client runs
        self.port = self.listener.getsockname()[1]
        self.chunks, self.then = chunks, then
        self.request = b""
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        try:
            self.listener.settimeout(GUARD_S)
            conn, _ = self.listener.accept()
            with conn:
                conn.settimeout(GUARD_S)
                conn.sendall(ndjson(VERSION, DEVICE))
                while not self.request.endswith(b"\n"):  # the whole request, so close() sends FIN, not RST
                    data = conn.recv(4096)
                    if not data:
                        return
                    self.request += data
                conn.sendall(
                    ndjson({"class": "WATCH", "enable": True, "rate_hz": json.loads(self.request[7:-2])["rate_hz"]})
                )
                for chunk in self.chunks:
                    conn.sendall(chunk)
                if self.then == "wait":  # until the client hangs up
                    try:
                        while conn.recv(4096):
                            pass
                    except ConnectionResetError:
                        # A client that closes with our later lines still unread in its buffer
                        # resets the connection (RST, not FIN): that is hanging up too.
                        pass
        except BaseException as exc:  # noqa: BLE001 - reported by join()
            self.error = exc
        finally:
            self.listener.close()

    def join(self) -> None:
        self.thread.join(GUARD_S)
        assert not self.thread.is_alive()
        if self.error is not None:
            raise self.error


def watch(daemon: FakeDaemon, **kwargs) -> tuple[int, str]:
    out = io.StringIO()
    status = run_watch("127.0.0.1", daemon.port, out=out, **kwargs)
    daemon.join()
    return status, out.getvalue()


CONVERSATION = [
    ndjson(angle(1), STATUS),
    b"this is not json\n",
    ndjson({"class": "SKY", "satellites": 12}, ["not", "an", "object"], {"no": "class"}),
    ndjson(angle(2))[:20],  # a line split across two sends
    ndjson(angle(2))[20:],
    ndjson(angle(3, unknown_key={"x": 1})),
    ndjson(angle(4)),
]


def test_conversation_fixture_is_well_formed():
    data = b"".join(CONVERSATION)
    lines = [parse_line(line) for line in data.split(b"\n") if line]
    assert [o["seq"] for o in lines if o and o["class"] == "ANGLE"] == [1, 2, 3, 4]
    assert sum(o is None for o in lines) == 3  # not json, a list, no class


# --------------------------------------------------------------------------- run_watch


def test_count_reached_exits_0_with_the_latest_values():
    daemon = FakeDaemon(CONVERSATION, then="wait")
    status, text = watch(daemon, count=3, rate_hz=10)
    assert status == 0
    assert daemon.request == b'?WATCH={"enable":true,"rate_hz":10};\n'
    lines = text.splitlines()
    assert lines[0] == (
        "connected to 127.0.0.1:2948: server 0.1.0, protocol 1.0; instrument serial FOG-SYN-0001, firmware 1.2, 100 Hz"
    ).replace("2948", str(daemon.port))
    assert lines[1] == "device /tmp/fog-driver-sim.tty, activated, serial FOG-SYN-0001, 100 Hz"
    last = lines[-1]  # the final compact line: the third ANGLE (count=3), not the fourth
    assert "seq 3 |" in last and "t 12.540 s" in last
    assert 'angle 3726.50" (1°02\'06.50")' in last
    assert 'raw -63.00" (-0°01\'03.00")' in last  # -59.995 - 3 = -62.995..., rounded away from zero
    # the mean rate since the gap (seq 2, after seq 1 unflagged: frames lost between them): seq 2 to 3 are adjacent
    # frames, so the mean over them is frame 3's own rate
    assert "rate 15.04 deg/h (mean over 0.1 s)" in last and "drift 0.1234 deg/h" in last
    assert "temps top 20.25 bottom 19.88 housing 19.60 degC" in last
    assert "flags none" in last
    assert "3 ANGLE" in last and "3 malformed" in last and "1 unknown class" in last  # WATCH is known
    assert "(WATCH 10 Hz)" in last
    assert (
        "status clients=1 cpu_percent=2.5 crc_errors=3 frames=4242 missing_frames=7 port_state=open some_future_key=x"
    ) in last
    assert "None" not in text and "null" not in text


def test_server_closing_early_exits_1_with_a_note():
    daemon = FakeDaemon(CONVERSATION, then="close")
    status, text = watch(daemon, count=100)
    assert status == 1
    lines = text.splitlines()
    assert lines[-1] == f"fog-driver watch: 127.0.0.1:{daemon.port} closed the connection (4 ANGLE received)"
    assert "seq 4 |" in lines[-2] and "4 ANGLE" in lines[-2]


def test_server_closing_before_any_angle():
    daemon = FakeDaemon([], then="close")
    status, text = watch(daemon)
    assert status == 1
    assert text.splitlines()[-1].endswith("closed the connection (0 ANGLE received)")


def test_error_and_device_changes_are_printed_as_they_come():
    deactivated = dict(DEVICE, state="deactivated")
    del deactivated["serial"]
    daemon = FakeDaemon([ndjson({"class": "ERROR", "message": "port lost"}, deactivated, angle(1))], then="wait")
    status, text = watch(daemon, count=1)
    assert status == 0
    assert "server error: port lost\n" in text
    assert "device /tmp/fog-driver-sim.tty, deactivated, 100 Hz  *** LINK DOWN ***\n" in text


def test_oversized_and_binary_lines_are_skipped_and_counted():
    huge = b'{"class":"ANGLE","seq":99,"pad":"' + b"x" * (MAX_LINE_BYTES + 10) + b'"}\n'
    daemon = FakeDaemon([huge[:70000], huge[70000:], b"\xff\xfe\x00garbage\n", b"\n", ndjson(angle(1))], then="wait")
    status, text = watch(daemon, count=1)
    assert status == 0
    last = text.splitlines()[-1]
    assert "seq 1 |" in last and "1 ANGLE" in last
    assert "1 oversized" in last and "1 malformed" in last  # the empty line is not an error


def test_duration_ends_the_watch_with_0():
    daemon = FakeDaemon([ndjson(angle(1))], then="wait")
    started = time.monotonic()
    status, text = watch(daemon, duration_s=0.3)
    assert status == 0
    assert time.monotonic() - started >= 0.3
    assert "seq 1 |" in text.splitlines()[-1]


class CtrlCOnError(io.StringIO):
    """Sends the process a real SIGINT (Ctrl-C) when the view prints the server's ERROR line."""

    def write(self, text: str) -> int:
        n = super().write(text)
        if text.startswith("server error: stop"):
            signal.raise_signal(signal.SIGINT)
        return n


def test_ctrl_c_is_a_clean_exit_0():
    # Python's Ctrl-C handler, as at a terminal: a run started in the background (CI's, say) inherits SIGINT
    # ignored, and then Python installs none, so the SIGINT below would do nothing.
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        _ctrl_c_is_a_clean_exit_0()
    finally:
        signal.signal(signal.SIGINT, previous)


def _ctrl_c_is_a_clean_exit_0():
    daemon = FakeDaemon([ndjson(angle(1), STATUS, {"class": "ERROR", "message": "stop"})], then="wait")
    out = CtrlCOnError()
    status = run_watch("127.0.0.1", daemon.port, out=out)  # no count, no duration: only Ctrl-C or the server ends it
    daemon.join()  # the server waits for the client to hang up
    assert status == 0
    lines = out.getvalue().splitlines()
    assert lines[-2] == "server error: stop"
    assert "seq 1 |" in lines[-1]  # the last state is still shown


def test_rate_hz_is_sent_as_given():
    daemon = FakeDaemon([ndjson(angle(1))], then="wait")
    status, text = watch(daemon, count=1, rate_hz=2.5)
    assert status == 0
    assert daemon.request == b'?WATCH={"enable":true,"rate_hz":2.5};\n'
    assert "(WATCH 2.5 Hz)" in text


class FakeTty(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_terminal_view_redraws_a_block_in_place():
    daemon = FakeDaemon([ndjson(angle(1), STATUS, angle(2), angle(3))], then="wait")
    out = FakeTty()
    started = time.monotonic()
    status = run_watch("127.0.0.1", daemon.port, out=out, count=3)
    elapsed = time.monotonic() - started
    daemon.join()
    assert status == 0
    text = out.getvalue()
    frames = text.split("\x1b[H")[1:]
    assert frames, text
    assert len(frames) <= 2 + 10 * elapsed  # at most 10 redraws a second (+ the first and the last)
    last = frames[-1]
    assert "\x1b[K\n" in last and "\x1b[J" in last
    assert 'angle       3726.50" (1°02\'06.50")' in last
    assert "temps       top 20.25  bottom 19.88  housing 19.60 degC" in last
    assert "device      /tmp/fog-driver-sim.tty, activated" in last
    assert text.endswith("\x1b[?25h")  # the cursor is shown again


def test_connection_refused_is_a_one_line_device_error():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))  # bound, never listening: the port is ours and refuses connections
        port = s.getsockname()[1]
        with pytest.raises(DeviceError) as info:
            run_watch("127.0.0.1", port, out=io.StringIO(), timeout_s=GUARD_S)
    message = str(info.value)
    assert message == f"could not connect to 127.0.0.1:{port}: Connection refused (is `fog-driver run` running?)"
    assert "\n" not in message
    assert info.value.exit_status == 69


@pytest.mark.parametrize("kwargs", [{"count": 0}, {"count": 1.5}, {"duration_s": 0}, {"rate_hz": -1}])
def test_bad_arguments_are_usage_errors(kwargs):
    with pytest.raises(UsageError):
        run_watch("127.0.0.1", 1, out=io.StringIO(), **kwargs)


@pytest.mark.parametrize("json_lines", [False, True], ids=["view", "json"])
def test_watch_at_a_rate_the_daemon_refuses_ends_with_its_error_line(make_hub, json_lines):
    """Finding 15: ``watch --rate-hz 20000`` (through the library: the command line bounds it now) waited for
    ever on ``waiting for ANGLE`` while the daemon had answered ``rate_hz must be ... <= 10000``; it ends at
    once with that line (exit 65, a command the daemon refused), the view (or the ERROR line) shown first."""
    hub, (host, port), _ = make_hub()
    out = io.StringIO()
    with pytest.raises(CommandRefused) as info:  # idle_s a hang guard only (before: TemporaryFailure after it)
        run_watch(host, port, rate_hz=20000, out=out, json_lines=json_lines, timeout_s=GUARD_S, idle_s=GUARD_S)
    daemon_said = "rate_hz must be a number > 0 and <= 10000"
    assert str(info.value) == f"the daemon at {host}:{port} refused ?WATCH: {daemon_said}"
    assert info.value.exit_status == 65 and info.value.message == daemon_said
    if json_lines:
        assert json.loads(out.getvalue().splitlines()[-1]) == {
            "class": "ERROR",
            "message": daemon_said,
            "command": "WATCH",
        }
    else:
        assert f"?WATCH refused: {daemon_said}" in out.getvalue()
    assert hub.watchers == 0


def test_watch_without_the_token_a_daemon_needs_still_waits_saying_why(make_hub):
    """An ``unauthorized`` ?WATCH is not such a refusal: the watch waits on (the documented form), here bounded
    by --idle-s, and says why no sample came."""
    _, (host, port), _ = make_hub(token="a-token-of-sixteen-chars")
    with pytest.raises(TemporaryFailure) as info:
        run_watch(host, port, out=io.StringIO(), idle_s=0.5, timeout_s=GUARD_S)
    assert str(info.value) == f"no samples for 0.5 s from {host}:{port}: ?WATCH refused, unauthorized"


@pytest.mark.parametrize("rate", ["20000", "10000.5", "1e308", "inf", "nan", "0", "-1"])
def test_watch_with_a_rate_no_daemon_takes_is_refused_before_connecting(capsys, rate):
    """``--rate-hz`` is bounded as the protocol documents ``?WATCH``'s ``rate_hz``: 0 < R <= 10000 (argparse,
    exit 2; the address is a closed port, never tried)."""
    with pytest.raises(SystemExit) as exc:
        main(["watch", "127.0.0.1:1", f"--rate-hz={rate}", "--count", "1"])
    out, err = capsys.readouterr()
    assert (
        exc.value.code == 2
        and out == ""
        and err.splitlines()[-1].startswith("fog-driver watch: error: argument --rate-hz: ")
    )


# --------------------------------------------------------------------------- pure functions


@pytest.mark.parametrize(
    ("arcsec", "text"),
    [
        (3723.5, "1°02'03.50\""),
        (-62.995000000000005, "-0°01'03.00\""),
        (-3723.5, "-1°02'03.50\""),
        (0.0, "0°00'00.00\""),
        (0, "0°00'00.00\""),
        (59.994, "0°00'59.99\""),
        (59.995, "0°01'00.00\""),  # rounding carries into the minutes
        (-59.995, "-0°01'00.00\""),
        (3599.995, "1°00'00.00\""),  # ... and into the degrees
        (-0.004, "0°00'00.00\""),  # no "-0"
        (-0.005, "-0°00'00.01\""),
        (0.125, "0°00'00.13\""),
        (1296000.0, "360°00'00.00\""),  # an integrated angle is not wrapped
        (float("nan"), "nan"),
        (float("-inf"), "-inf"),
    ],
)
def test_format_dms(arcsec, text):
    assert format_dms(arcsec) == text


def test_format_dms_ascii_degree():
    assert format_dms(3723.5, degree="d") == "1d02'03.50\""


@pytest.mark.parametrize(
    ("arcsec", "text"),
    [
        (1e30, "1e+30"),
        (-1e26, "-1e+26"),
        (1e15, "1000000000000000.0"),
        (10**400, "1.000000e+400"),
        (-(10**400), "-1.000000e+400"),
        (float("inf"), "inf"),
    ],
    ids=["1e30", "-1e26", "1e15", "10**400", "-10**400", "inf"],
)
def test_absurd_angles_are_shown_plainly(arcsec, text):
    # before: decimal.InvalidOperation from 1e26" on, OverflowError for an integer beyond float's range
    assert format_dms(arcsec) == text
    assert format_arcsec(arcsec) == text


def test_the_views_survive_absurd_values():
    absurd = angle(
        2,
        angle_arcsec=1e30,
        angle_raw_arcsec=-(10**400),
        rate_dph=10**400,
        t_s=1e300,
        temps_c={"top": 10**400, "housing": 20.0},
    )
    lines = render({**FULL_STATE, "angle": absurd}, width=200)
    assert 'angle       1e+30" (1e+30)    raw -1.000000e+400" (-1.000000e+400)' in lines
    assert "rate        1.000000e+400 deg/h (one sample)" in lines and "drift       0.1234 deg/h" in lines
    assert "temps       top 1.000000e+400  bottom -  housing 20.00 degC" in lines
    assert "1e+30" in compact_line({**FULL_STATE, "angle": absurd})
    daemon = FakeDaemon([ndjson(absurd)], then="wait")
    status, text = watch(daemon, count=1)
    assert status == 0 and "1e+30" in text


@pytest.mark.parametrize(
    ("line", "expected"),
    [
        (b'{"class":"ANGLE","seq":1}\n', {"class": "ANGLE", "seq": 1}),
        (b'{"class":"X"}\r\n', {"class": "X"}),
        (b"", None),
        (b"\n", None),
        (b"not json\n", None),
        (b"[1,2]\n", None),
        (b'"ANGLE"\n', None),
        (b'{"seq":1}\n', None),
        (b'{"class":5}\n', None),
        (b"\xff\xfe{}\n", None),
        (b'{"class":"ANGLE",', None),
        (b'{"class":"A","p":"' + b"x" * MAX_LINE_BYTES + b'"}', None),
        (b"[" * 100_000 + b"]" * 100_000, None),  # deeply nested: no RecursionError
    ],
)
def test_parse_line(line, expected):
    assert parse_line(line) == expected


def test_line_reader_limits_line_length_across_chunks():
    reader = LineReader(max_line=10)
    assert reader.feed(b"abc\nde") == [b"abc"]
    assert reader.feed(b"f\n" + b"x" * 8) == [b"def"]
    assert reader.feed(b"y" * 8) == []  # now over the limit: dropped up to its newline
    assert reader.feed(b"zzz\nok\n") == [b"ok"]
    assert reader.oversized == 1
    assert reader.feed(b"0123456789012\nfine\n") == [b"fine"]
    assert reader.oversized == 2


FULL_STATE = {
    "address": "127.0.0.1:2948",
    "elapsed_s": 3.25,
    "version": VERSION,
    "device": DEVICE,
    "angle": angle(2),
    "status": STATUS,
    "angles": 30,
    "angle_rate_hz": 10.0,
    "angle_age_s": 0.04,
    "malformed": 2,
    "unknown": 1,
    "error": "port lost",
}


def test_render_full_state():
    lines = render(FULL_STATE, width=200)
    assert lines[0] == "fog-driver watch 127.0.0.1:2948  |  server 0.1.0, protocol 1.0  |  3.2 s"
    assert lines[1:] == [
        "instrument  serial FOG-SYN-0001, firmware 1.2, 100 Hz",
        "model       -",  # a daemon before protocol 1.2 does not say
        "device      /tmp/fog-driver-sim.tty, activated, serial FOG-SYN-0001, 100 Hz",
        'angle       3725.50" (1°02\'05.50")    raw -62.00" (-0°01\'02.00")',  # the two forms agree
        "rate        15.0 deg/h (one sample)",
        "drift       0.1234 deg/h",
        "temps       top 20.25  bottom 19.88  housing 19.60 degC",
        "flags       gap",
        "sample      seq 2  t 12.440 s  (received 0.0 s ago)",
        "received    10.0 ANGLE/s  30 ANGLE  2 malformed  1 unknown class",
        "status      clients=1  cpu_percent=2.5  crc_errors=3  frames=4242  missing_frames=7  port_state=open  "
        "some_future_key=x",
        "error       port lost",
    ]


def test_render_wraps_the_status_counters():
    lines = render(FULL_STATE, width=60)
    first = next(i for i, line in enumerate(lines) if line.startswith("status"))
    status = [lines[first]] + list(itertools.takewhile(lambda line: line.startswith(" " * 12), lines[first + 1 :]))
    assert len(status) >= 2 and all(len(line) <= 60 for line in lines)
    assert " ".join(" ".join(status).split()) == (
        "status clients=1 cpu_percent=2.5 crc_errors=3 frames=4242 missing_frames=7 port_state=open some_future_key=x"
    )


def test_the_terminal_view_fits_80_columns_and_loses_nothing():
    """Before: at 80 columns the rate line lost its drift and sigma, the bias banner its command, the sample line
    its time of day: lines were cut at the terminal's edge.  Now they fold, under the label."""
    state = {
        **FULL_STATE,
        "address": "gyro-pc.lab.example.org:2948",
        "keys": True,
        "angle": angle(
            2,
            angle_arcsec=-1234567.891,
            angle_raw_arcsec=-1234560.5,
            drift_sigma_dph=0.0237,
            utc="2026-12-04T11:05:07.123456Z",
            temps_c={"housing": 19.6, "bottom": 19.88, "top": 20.25},  # sent in another order
        ),
        "angle_age_s": 0.1,
        "rate_mean_dph": -10.6123,
        "rate_span_s": 1.0,
        "status": {**FULL_STATE["status"], "bias_captured": False, "bias_sigma_dph": 0.0051},
    }
    for width in (80, 79):  # the view draws at the terminal's width less one
        lines = render(state, width=width)
        assert all(len(line) <= width for line in lines), [line for line in lines if len(line) > width]
        text = " ".join(" ".join(lines).split())
        for shown in (
            "press b (or `fog-driver ctl gyro-pc.lab.example.org:2948 bias 60`)",
            "rate -10.61 deg/h (mean over 1.0 s)",
            "drift 0.1234 deg/h +- 0.0237 (1-sigma)",
            "utc 2026-12-04T11:05:07.123456Z (received 0.1 s ago)",
            "q quit z zero the angle b capture the bias (60 s, table still)",
            "some_future_key=x",
        ):
            assert shown in text, shown
        assert "temps       top 20.25  bottom 19.88  housing 19.60 degC" in lines  # top, bottom, housing


@pytest.mark.parametrize(
    "state",
    [
        {},
        {"angle": {"class": "ANGLE"}},
        {"angle": {"class": "ANGLE", "seq": 1, "temps_c": {"top": 20.0}}},  # two thermometers absent
        {"angle": {"class": "ANGLE", "angle_arcsec": None, "temps_c": None, "flags": None}},
        {"angle": {"class": "ANGLE", "angle_arcsec": "bad", "rate_dph": [1], "temps_c": "hot", "flags": "gap"}},
        {"version": {"class": "VERSION"}, "device": {"class": "DEVICE"}, "status": {"class": "STATUS"}},
        {"version": {"class": "VERSION", "instrument": None}, "device": {"class": "DEVICE", "state": "deactivated"}},
        {"version": "nonsense", "device": 5, "angle": [], "status": {"nested": {"a": None}, "list": [None]}},
        {"version": {"class": "VERSION", "proto_major": 2}},
    ],
)
def test_render_with_missing_fields_never_crashes_or_shows_none(state):
    for lines in (render(state), [compact_line(state)]):
        assert lines and all(isinstance(line, str) for line in lines)
        text = "\n".join(lines)
        assert "None" not in text and "null" not in text


def test_render_missing_fields_show_a_dash():
    lines = render({"angle": {"class": "ANGLE", "seq": 7, "temps_c": {"top": 20.0}}})
    assert "instrument  -" in lines
    assert "device      -" in lines
    assert "angle       -    raw -" in lines
    assert "temps       top 20.00  bottom -  housing - degC" in lines
    assert "flags       -" in lines
    assert "status      -" in lines
    assert not any(line.startswith("error") for line in lines)
    assert "waiting for ANGLE" in "\n".join(render({}))


@pytest.mark.parametrize(
    "angle_sigma, status, shown",
    [
        (0.03, {"bias_captured": False}, "drift 0.1234 deg/h +- 0.0300 (1-sigma)"),  # before a bias: sigma(t)
        (0.03, {}, "drift 0.1234 deg/h +- 0.0300 (1-sigma)"),  # no STATUS yet
        # sqrt(0.03^2 + 0.04^2) = 0.05 once a bias was captured with sigma(t_b) = 0.04
        (
            0.03,
            {"bias_captured": True, "bias_sigma_dph": 0.04},
            "drift 0.1234 deg/h +- 0.0500 (1-sigma since the bias)",
        ),
        (
            0.012,
            {"bias_captured": True, "bias_sigma_dph": 0.005},
            "drift 0.1234 deg/h +- 0.0130 (1-sigma since the bias)",
        ),
        (
            0.03,
            {"bias_captured": True},
            "drift 0.1234 deg/h +- - (1-sigma since the bias: unknown, the bias was captured without one)",
        ),
        (None, {"bias_captured": True, "bias_sigma_dph": 0.04}, "drift 0.1234 deg/h"),  # no estimate, or 1.0
    ],
)
def test_the_drift_sigma_is_shown_plain_before_a_bias_and_in_the_since_bias_form_after(angle_sigma, status, shown):
    sample = angle(1) if angle_sigma is None else angle(1, drift_sigma_dph=angle_sigma)
    state = {"angle": sample, "status": {"class": "STATUS", **status}}
    drift_line = next(line for line in render(state, width=200) if line.startswith("drift "))
    assert drift_line == f"drift       {shown.removeprefix('drift ')}"
    assert f"| {shown} |" in compact_line(state)
    if angle_sigma is None:
        assert "+-" not in compact_line(state) and "sigma" not in drift_line


def test_watch_shows_the_since_bias_form_once_the_daemon_says_a_bias_was_captured():
    before = {**STATUS, "bias_captured": False}
    after = {**STATUS, "bias_captured": True, "bias_dph": 9.9, "bias_sigma_dph": 0.04}
    chunks = [
        ndjson(before, angle(1, drift_sigma_dph=0.03), angle(2, drift_sigma_dph=0.03)),
        ndjson(after, angle(3, drift_sigma_dph=0.03)),
    ]
    daemon = FakeDaemon(chunks, then="wait")
    status, text = watch(daemon, count=3, rate_hz=10)
    assert status == 0
    assert "drift 0.1234 deg/h +- 0.0500 (1-sigma since the bias)" in text.splitlines()[-1].split(" | ")


def test_render_flags_a_newer_protocol():
    assert (
        "protocol 2.0 (this client speaks 1.x)"
        in render({"version": {"class": "VERSION", "release": "9", "proto_major": 2}})[0]
    )


def test_compact_line_is_one_line():
    line = compact_line(FULL_STATE)
    assert "\n" not in line
    assert re.match(r"\[ +3\.2 s\] seq 2 \| t 12\.440 s \| angle 3725\.50\" \(1°02'05\.50\"\)", line)


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        (None, ("127.0.0.1", 2948)),
        ("", ("127.0.0.1", 2948)),
        ("gyro-pc", ("gyro-pc", 2948)),
        ("gyro-pc:3000", ("gyro-pc", 3000)),
        (":3000", ("127.0.0.1", 3000)),
        ("3000", ("127.0.0.1", 3000)),
        ("[::1]:3000", ("::1", 3000)),
        ("[::1]", ("::1", 2948)),
        ("::1", ("::1", 2948)),
    ],
)
def test_parse_address(text, expected):
    assert parse_address(text) == expected


@pytest.mark.parametrize(
    ("host", "text"),
    [
        ("127.0.0.1", "127.0.0.1:2948"),
        ("gyro-pc", "gyro-pc:2948"),
        ("::1", "[::1]:2948"),
        ("fe80::1%eth0", "[fe80::1%eth0]:2948"),
    ],
)
def test_format_address_is_read_back_by_parse_address(host, text):
    assert format_address(host, 2948) == text
    assert parse_address(text) == (host, 2948)


@pytest.mark.parametrize("text", ["host:port", "host:0", "host:70000", "[::1", "[::1]x"])
def test_parse_address_rejects(text):
    with pytest.raises(UsageError):
        parse_address(text)


@pytest.mark.parametrize(
    ("arcsec", "text"), [(3723.5, "3723.50"), (-59.995, "-60.00"), (-0.004, "0.00"), (2.675, "2.68")]
)
def test_format_arcsec_agrees_with_format_dms(arcsec, text):
    assert format_arcsec(arcsec) == text


def test_log_view_prints_a_line_each_second():
    daemon = FakeDaemon([ndjson(angle(1), STATUS)], then="wait")
    status, text = watch(daemon, duration_s=1.5)
    assert status == 0
    compact = [line for line in text.splitlines() if line.startswith("[")]
    assert len(compact) == 1  # at 1 s; nothing new arrived after it, so no final line
    assert re.match(r"\[ +1\.\d s\] seq 1 \|", compact[0])
    assert "0.0 ANGLE/s" not in compact[0]  # the one ANGLE is still inside the 2-s rate window


def test_server_text_cannot_inject_control_characters():
    state = {
        "error": "bad\nline\x1b[2J",
        "status": {"class": "STATUS", "k\x1b[H": "v\r"},
        "device": {"class": "DEVICE", "path": "/dev/tty\x07", "state": "activated"},
    }
    for text in ("\n".join(render(state)), compact_line(state)):
        assert "\x1b" not in text and "\r" not in text and "\x07" not in text
    assert "error       bad?line?[2J" in render(state)


@pytest.mark.parametrize(
    ("policy", "shown"),
    [
        ({"enable": True, "rate_hz": 10}, "(WATCH 10 Hz)"),
        ({"enable": True, "rate_hz": None}, "(WATCH every sample)"),
        ({"enable": True}, "(WATCH every sample)"),
        ({"enable": False}, "(WATCH disabled)"),
    ],
)
def test_render_shows_the_watch_policy_in_force(policy, shown):
    received = [line for line in render({"watch": {"class": "WATCH", **policy}}) if line.startswith("received")]
    assert received[0].endswith(shown)


# --------------------------------------------------------------------------- a daemon with a token


def test_the_token_is_sent_first_so_a_token_daemon_keeps_the_watch():
    """A token-protected daemon closes a client that has not authorized within its auth deadline: the watch
    sends ?AUTH before ?WATCH (the token from FOG_DRIVER_TOKEN), and without it is closed."""
    from fog_driver.daemon.hub import Hub

    hub = Hub(
        "127.0.0.1",
        0,
        version=lambda: {"release": "0.1.0", "proto_major": 1, "proto_minor": 0},
        device=lambda: None,
        control=lambda name, args, cid: {"class": name},
        token="a-long-token",
        auth_deadline_s=0.3,
    )
    host, port = hub.start()
    stop = threading.Event()

    def publish() -> None:  # the instrument: 100 samples a second (a pace, not a synchronisation)
        seq = 0
        while not stop.is_set():
            seq += 1
            hub.publish_angles([angle(seq, t_s=0.01 * seq)])
            stop.wait(0.01)

    publisher = threading.Thread(target=publish, daemon=True)
    publisher.start()
    try:
        out = io.StringIO()
        assert run_watch(host, port, rate_hz=None, count=100, out=out, token="a-long-token") == 0
        out = io.StringIO()
        assert run_watch(host, port, rate_hz=None, count=100_000, out=out) == 1  # closed at the deadline
        assert "closed the connection" in out.getvalue()
    finally:
        stop.set()
        publisher.join(GUARD_S)
        hub.stop()


def test_watch_command_takes_the_token_from_the_environment(monkeypatch):
    from fog_driver.tools import watch as watch_module

    seen = {}
    monkeypatch.setattr(watch_module, "run_watch", lambda host, port, **kwargs: seen.update(kwargs) or 0)
    monkeypatch.setenv("FOG_DRIVER_TOKEN", "from-the-env")
    assert watch_module.watch_command("127.0.0.1:1") == 0 and seen["token"] == "from-the-env"
    monkeypatch.delenv("FOG_DRIVER_TOKEN")
    watch_module.watch_command("127.0.0.1:1")
    assert seen["token"] is None


# --------------------------------------------------------------------------- operator tools (issue 13, item 5)


def test_a_peer_that_closes_before_the_greeting_is_could_not_connect_at_once():
    """The review's finding 19: an unreachable host was "closed the connection (0 ANGLE received)", exit 1,
    after --duration."""
    listener = socket.create_server(("127.0.0.1", 0))
    port = listener.getsockname()[1]

    def accept_and_close() -> None:
        listener.settimeout(GUARD_S)
        conn, _ = listener.accept()
        conn.close()

    server = threading.Thread(target=accept_and_close, daemon=True)
    server.start()
    started = time.monotonic()
    try:
        with pytest.raises(DeviceError) as info:
            run_watch("127.0.0.1", port, out=io.StringIO(), duration_s=60)
    finally:
        server.join(GUARD_S)
        listener.close()
    assert time.monotonic() - started < 30  # not after --duration
    assert str(info.value) == (
        f"could not connect to 127.0.0.1:{port}: the daemon closed the connection before the "
        "VERSION greeting (is `fog-driver run` running?)"
    )
    assert info.value.exit_status == 69


def test_the_rate_shown_is_the_mean_over_the_last_second_not_one_sample():
    """The review's finding 6: one decimated sample's rate, quantized, with 4 decimals."""
    rates = [9.0, 12.0, 14.0, 9.0, 11.0, 10.0, 8.0, 13.0, 10.0, 9.0, 12.0, 11.0, 10.0]  # one count steps
    angles, arcsec = [], 100.0
    for k, rate in enumerate(rates):
        arcsec += rate * 0.1  # deg/h = arcsec/s: each sample's increment over its 0.1 s
        angles.append(angle(k + 1, t_s=20.0 + 0.1 * k, angle_arcsec=arcsec, rate_dph=rate, flags=[]))
    daemon = FakeDaemon([ndjson(*angles)], then="wait")
    status, text = watch(daemon, count=len(rates))
    assert status == 0
    mean = sum(rates[-10:]) / 10  # the last 1.0 s of device time: the samples after the window's first point
    assert f"rate {mean:.2f} deg/h (mean over 1.0 s)" in text.splitlines()[-1]


def test_the_daemons_rates_average_to_the_angle_difference(tmp_path):
    """What the averaged rate rests on: over every published sample, the mean of ``rate_dph`` is the angle's
    difference over the device time (1 arcsec/s = 1 deg/h)."""
    from daemon_hil import SHORT, watch_all, watched_daemon

    from fog_driver.protocol import decode_bytes

    with watched_daemon(tmp_path) as (pty, daemon, client):
        pty.write(SHORT[:20000])
        angles = watch_all(client, decode_bytes(SHORT[:20000], final=False).counters.sample_frames)
        assert daemon.terminate() == 0
    window = [a for a in angles if "gap" not in a["flags"]][-11:]
    mean = sum(a["rate_dph"] for a in window[1:]) / 10
    assert mean == pytest.approx(
        (window[-1]["angle_arcsec"] - window[0]["angle_arcsec"]) / (window[-1]["t_s"] - window[0]["t_s"]), abs=1e-9
    )


@pytest.mark.parametrize(
    ("state", "banner"),
    [
        ({"device": {"state": "deactivated"}}, "*** LINK DOWN: the daemon's instrument port is closed"),
        ({"status": {"port_state": "lost"}}, "*** LINK DOWN"),
        ({"elapsed_s": 7.2}, "*** NO DATA for 7 s ***"),
        ({"angle": angle(1), "angle_age_s": 4.0}, "*** NO DATA for 4 s ***"),
        (
            {"status": {"bias_captured": False}, "keys": True},
            "bias not removed: at rest the angle climbs with Earth rate + bias; press b (or `fog-driver ctl bias 60`)",
        ),
        (
            {"status": {"bias_captured": False}, "address": "gyro-pc:2948"},
            "bias not removed: at rest the angle climbs with Earth rate + bias; "
            "run `fog-driver ctl gyro-pc:2948 bias 60`",
        ),
        (
            {"status": {"bias_captured": False, "bias_capture_s": 12.0, "bias_capture_target_s": 60.0}},
            "capturing the bias: 12.0 / 60 s of data; keep the table still",
        ),
    ],
)
def test_banners(state, banner):
    lines = render(state)
    shown = " ".join(" ".join(lines[1:4]).split())  # a long banner folds at 80 columns
    assert shown.startswith(banner), lines  # right under the head line
    assert compact_line(state).split(" | ")[0].split("] ")[1] in banner  # and first in the log line


@pytest.mark.parametrize(
    "state",
    [
        {"status": {"bias_captured": True}, "elapsed_s": 1.0},
        {"angle": angle(1), "angle_age_s": 0.5, "device": {"state": "activated"}},
        {"status": {"bias_dph": 0.0}},
    ],
)
def test_no_banner_when_all_is_well(state):
    assert not any(line.startswith(("***", "bias", "capturing")) for line in render(state))


def test_watch_json_passes_the_daemons_lines_through_a_pipe_unchanged(tmp_path):
    """``watch --json`` is ``gpspipe -w``: the daemon's bytes, one line each, flushed per line; a reader that
    goes away (``| head``) ends it with exit 0 and nothing on stderr."""
    import subprocess
    import sys

    from daemon_hil import SHORT, watched_daemon

    with watched_daemon(tmp_path) as (pty, daemon, _):
        host, port = daemon.address
        proc = subprocess.Popen(
            [sys.executable, "-m", "fog_driver", "watch", f"{host}:{port}", "--json", "--rate-hz", "10"],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            stdin=subprocess.DEVNULL,
        )
        try:
            lines = [proc.stdout.readline()]
            assert json.loads(lines[0])["class"] == "VERSION"
            while json.loads(lines[-1])["class"] != "WATCH":  # its WATCH is in force: the same decimation as ours
                lines.append(proc.stdout.readline())
            reference = socket.create_connection(daemon.address, timeout=GUARD_S)
            ref_file = reference.makefile("rb")
            reference.sendall(b'?WATCH={"enable":true,"rate_hz":10};\n')
            while not ref_file.readline().startswith(b'{"class":"WATCH"'):
                pass
            pty.write(SHORT[:20000])
            theirs: dict[int, bytes] = {}
            ours: dict[int, bytes] = {}
            while len(theirs) < 5:
                line = proc.stdout.readline()
                assert line.endswith(b"\n") and json.loads(line)["class"]
                if line.startswith(b'{"class":"ANGLE"'):
                    theirs[json.loads(line)["seq"]] = line
            while not set(theirs) <= set(ours):
                line = ref_file.readline()
                if line.startswith(b'{"class":"ANGLE"'):
                    ours[json.loads(line)["seq"]] = line
            assert all(theirs[seq] == ours[seq] for seq in theirs)  # byte for byte, utc included
            proc.stdout.close()  # the reader goes away: the next line (a STATUS within 1 s) meets EPIPE
            assert proc.wait(GUARD_S) == 0
            assert proc.stderr.read() == b""
        finally:
            proc.kill()
            proc.wait(GUARD_S)
        reference.close()
        assert daemon.terminate() == 0


class Terminal:
    """A pty for ``fog-driver watch`` to run in: what it drew (escape sequences removed), keys to type."""

    def __init__(self) -> None:
        import os
        import pty
        import termios

        self.master, self.slave = pty.openpty()
        termios.tcsetattr(self.slave, termios.TCSANOW, termios.tcgetattr(self.slave))
        self.screen = ""
        self._os = os

    def wait_for(self, text: str) -> None:
        """Read the output until ``text`` appears in it (GUARD_S at most)."""
        import select

        deadline = time.monotonic() + GUARD_S
        while text not in self.screen:
            assert time.monotonic() < deadline, f"{text!r} never shown; the last screen: {self.screen[-3000:]}"
            if select.select([self.master], [], [], 0.5)[0]:
                data = self._os.read(self.master, 65536).decode("utf-8", "replace")
                self.screen += re.sub(r"\x1b\[[0-9;?]*[A-Za-z]", "", data)

    def type(self, keys: bytes) -> None:
        self._os.write(self.master, keys)

    def close(self) -> None:
        self._os.close(self.master)
        self._os.close(self.slave)


def popen_watch_in(term: Terminal, address: tuple[str, int], **popen) -> subprocess.Popen:
    """``fog-driver watch HOST:PORT`` started in ``term`` (its stdin and stdout), stderr piped."""
    host, port = address
    return subprocess.Popen(
        [sys.executable, "-m", "fog_driver", "watch", f"{host}:{port}"],
        stdin=term.slave,
        stdout=term.slave,
        stderr=subprocess.PIPE,
        **popen,
    )


def press_q(term: Terminal, proc: subprocess.Popen) -> None:
    """q: the watch ends, exit 0, nothing on stderr."""
    term.type(b"q")
    assert proc.wait(GUARD_S) == 0
    assert proc.stderr.read() == b""


def test_keys_z_b_q_on_a_terminal_and_the_terminal_restored(tmp_path):
    """z sends ?ZERO, b ?BIAS (60 s) with its result in the banner, q quits with exit 0; stdin was in cbreak
    mode meanwhile and has its settings back afterwards."""
    import termios

    from daemon_hil import N_SHORT, SHORT, watch_all, watched_daemon

    from fog_driver.protocol import decode_bytes

    head = 20000
    term = Terminal()
    before = termios.tcgetattr(term.slave)
    with watched_daemon(tmp_path) as (pty, daemon, client):
        pty.write(SHORT[:head])
        n_head = decode_bytes(SHORT[:head], final=False).counters.sample_frames
        watch_all(client, n_head)
        proc = popen_watch_in(term, daemon.address)
        try:
            term.wait_for("keys        q quit")
            term.wait_for("bias not removed: at rest the angle climbs with Earth rate + bias; press b")
            assert not termios.tcgetattr(term.slave)[3] & termios.ICANON  # cbreak: one key at a time
            term.type(b"z")
            term.wait_for("zeroed: the angle starts again from 0 here")
            term.type(b"b")
            term.wait_for("bias capture started: 60 s of data; keep the table still")
            pty.write(SHORT[head:])  # 270 s of device data: the capture completes
            term.wait_for("bias captured: ")
            press_q(term, proc)
        finally:
            proc.kill()
            proc.wait(GUARD_S)
        angles = watch_all(client, N_SHORT - n_head)
        assert abs(angles[0]["angle_arcsec"]) < 5.0  # the z reached the daemon
        assert daemon.terminate() == 0
    assert termios.tcgetattr(term.slave) == before  # the terminal's settings are back
    term.close()


def _default_ctrl_c() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


#: How a shell starts a command in the foreground: Ctrl-C at its default (this test run may have inherited it
#: ignored, as a background job does, and Python then installs no KeyboardInterrupt handler), and a process
#: group of its own whose parent is in the same session, so Ctrl-Z stops it (the kernel discards SIGTSTP sent
#: to an orphaned process group, such as a detached CI run's).
AS_A_SHELLS_FOREGROUND_JOB = {"preexec_fn": _default_ctrl_c, "process_group": 0}


@pytest.mark.parametrize("how", ["SIGTERM", "SIGINT", "SIGTSTP"])
def test_the_terminal_is_restored_when_a_signal_ends_or_suspends_the_watch(tmp_path, how):
    import termios

    from daemon_hil import watched_daemon

    term = Terminal()
    before = termios.tcgetattr(term.slave)
    with watched_daemon(tmp_path) as (_, daemon, _client):
        proc = popen_watch_in(term, daemon.address, **AS_A_SHELLS_FOREGROUND_JOB)
        try:
            term.wait_for("keys        q quit")
            assert termios.tcgetattr(term.slave) != before
            proc.send_signal(getattr(signal, how))
            if how == "SIGTSTP":  # Ctrl-Z: the shell gets its terminal back while the watch is stopped
                deadline = time.monotonic() + GUARD_S
                while True:  # until the watch has stopped itself (a SIGCONT before that would be lost)
                    pid, status = os.waitpid(proc.pid, os.WUNTRACED | os.WNOHANG)
                    if pid and os.WIFSTOPPED(status):
                        break
                    assert time.monotonic() < deadline, "never stopped on Ctrl-Z"
                    term.wait_for("")  # (drains the output; returns at once)
                assert termios.tcgetattr(term.slave) == before, "not restored on Ctrl-Z"
                proc.send_signal(signal.SIGCONT)
                term.screen = ""
                term.wait_for("keys        q quit")  # redrawn after fg
                term.type(b"q")
            assert proc.wait(GUARD_S) == 0
        finally:
            proc.kill()
            proc.wait(GUARD_S)
        assert daemon.terminate() == 0
    assert termios.tcgetattr(term.slave) == before
    term.close()


def frames_after_a_replug(rng_seed: int = 13) -> tuple[list[dict], list[int], list[float]]:
    """A 100 Hz instrument's frames as the daemon publishes them around a replug: 3 s, then 145 s of frames that
    never arrived (the angle holds, device time runs on), then 5 s all flagged ``gap`` while the estimate
    settles.  Each frame's rate is a whole number of deg/h (one count per frame), its angle the running sum of
    rate x 0.01 s.  Returns the frames and each one's seq and rate (the reference)."""
    import numpy as np

    rng = np.random.default_rng(rng_seed)
    seqs = [*range(0, 300), *range(14800, 15300)]
    frames, rates, arcsec = [], [], 1000.0
    for seq in seqs:
        rate = float(rng.integers(6, 15))
        arcsec += rate * 0.01  # deg/h = arcsec/s
        flags = ["gap"] if seq >= 14800 else []
        frames.append(angle(seq, t_s=50.0 + seq / 100, angle_arcsec=arcsec, rate_dph=rate, flags=flags))
        rates.append(rate)
    return frames, seqs, rates


def decimated(frames: list[dict], rate_hz: float) -> list[dict]:
    """The daemon's decimation (``Connection.keep_angles``): the first frame of each 1/rate_hz of device time."""
    kept, last = [], None
    for frame in frames:
        bucket = math.floor(frame["t_s"] * rate_hz)
        if bucket != last:
            kept.append(frame)
            last = bucket
    return kept


def test_watch_after_a_replug_shows_the_one_second_mean_while_the_samples_are_flagged_gap():
    """The review's finding 13: for the minutes after a replug every sample is flagged ``gap`` (the estimate
    settling), and watch showed one sample's rate (``8.0 deg/h (one sample)``, 1 deg/h steps) where the web view
    kept the 1-s mean.  The mean over the last second of device time is every frame's rate in it, the frames
    the decimation dropped included."""
    frames, seqs, rates = frames_after_a_replug()
    kept = decimated(frames, 10.0)
    daemon = FakeDaemon([ndjson(*kept)], then="wait")
    status, text = watch(daemon, count=len(kept), rate_hz=10)
    assert status == 0
    last = kept[-1]
    first = max((k for k in kept if k["t_s"] <= last["t_s"] - 1.0), key=lambda k: k["t_s"])  # the window's start
    window = [r for s, r in zip(seqs, rates) if first["seq"] < s <= last["seq"]]
    assert len(window) == 100
    mean = sum(window) / len(window)
    assert f"rate {mean:.2f} deg/h (mean over {last['t_s'] - first['t_s']:.1f} s)" in text.splitlines()[-1]


# --------------------------------------------------------------------------- no samples


@pytest.mark.parametrize("out", [io.StringIO, FakeTty], ids=["not at a terminal", "at a terminal"])
@pytest.mark.parametrize("bound", [{"count": 10}, {"duration_s": 600.0}], ids=["count", "duration"])
def test_watch_count_while_the_daemons_link_is_down_ends_with_75_after_idle_s(out, bound):
    """The review's finding 2: ``watch --count 10`` hung for 10 minutes while the daemon's link was down.  A
    bounded watch ends after ``idle_s`` without a sample, saying so and why, at a terminal or not."""
    lost = dict(DEVICE, state="deactivated")
    daemon = FakeDaemon([ndjson(angle(1), lost, dict(STATUS, port_state="lost"))], then="wait")
    stream = out()
    with pytest.raises(TemporaryFailure) as info:
        run_watch("127.0.0.1", daemon.port, out=stream, idle_s=0.5, **bound)
    daemon.join()
    assert info.value.exit_status == 75
    assert re.fullmatch(rf"no samples for 0\.5 s from 127\.0\.0\.1:{daemon.port}: link down", str(info.value))
    assert "seq 1" in stream.getvalue()  # the last view was shown first
    if out is FakeTty:
        assert stream.getvalue().endswith("\x1b[?25h")  # the cursor is back


def test_a_watch_without_count_or_duration_waits_on_and_says_why_no_samples_come():
    """Not bounded, not at a terminal (a log): one line a second says no data came and why, and the watch goes on
    (only Ctrl-C, the server or an explicit ``idle_s`` end it)."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:

        class CtrlCOnNoData(io.StringIO):
            def write(self, text: str) -> int:
                n = super().write(text)
                if "NO DATA for" in text:
                    signal.raise_signal(signal.SIGINT)
                return n

        lost = dict(DEVICE, state="deactivated")
        daemon = FakeDaemon([ndjson(lost, dict(STATUS, port_state="lost"))], then="wait")
        out = CtrlCOnNoData()
        assert run_watch("127.0.0.1", daemon.port, out=out) == 0
        daemon.join()
    finally:
        signal.signal(signal.SIGINT, previous)
    line = next(line for line in out.getvalue().splitlines() if "NO DATA" in line)
    assert re.search(r"\| NO DATA for \d s \(link down\) \|", line), line


@pytest.mark.parametrize(
    ("count", "duration_s", "idle_s", "limit"),
    [(10, None, None, DEFAULT_IDLE_S), (None, 5.0, None, DEFAULT_IDLE_S), (None, None, None, None), (None, None, 3, 3)],
)
def test_the_idle_limit_is_10_s_for_a_bounded_watch_and_none_otherwise_unless_given(count, duration_s, idle_s, limit):
    assert DEFAULT_IDLE_S == 10.0
    assert idle_limit_s(count, duration_s, idle_s) == limit


def test_watch_idle_s_is_parsed_and_refused_when_not_positive():
    from fog_driver.cli.parser import build_parser

    parser = build_parser(["watch"])
    assert parser.parse_args(["watch", "--count", "10"]).idle_s is None  # idle_limit_s makes it 10
    assert parser.parse_args(["watch", "--idle-s", "2.5"]).idle_s == 2.5
    with pytest.raises(UsageError, match="--idle-s"):
        run_watch("127.0.0.1", 1, out=io.StringIO(), idle_s=math.inf)


def run_fog_driver_watch(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "fog_driver", "watch", *args],
        stdin=subprocess.DEVNULL,
        capture_output=True,
        text=True,
        timeout=GUARD_S,
    )


@pytest.mark.parametrize("json_lines", [False, True], ids=["view", "json"])
def test_fog_driver_watch_count_from_a_daemon_whose_instrument_sends_nothing_exits_75(tmp_path, json_lines):
    """A real daemon on a pty that sends no frame: the port is open, no sample comes; ``watch --count 10`` ends
    with one line and exit 75, its view (or the daemon's lines, with ``--json``) printed first."""
    from daemon_hil import watched_daemon

    with watched_daemon(tmp_path) as (_, daemon, _client):
        host, port = daemon.address
        done = run_fog_driver_watch(
            f"{host}:{port}", "--count", "10", "--idle-s", "1", *(["--json"] if json_lines else [])
        )
        assert daemon.terminate() == 0
    assert done.returncode == 75, done.stderr
    assert done.stderr.splitlines() == [
        f"fog-driver: error: no samples for 1.0 s from {host}:{port}: port open, no samples from the instrument"
    ]
    if json_lines:
        assert [json.loads(line)["class"] for line in done.stdout.splitlines()][:2] == ["VERSION", "DEVICE"]
    else:
        assert "device " in done.stdout and "waiting for ANGLE" in done.stdout


def test_fog_driver_watch_at_a_terminal_without_count_waits_and_says_why_on_its_status_line(tmp_path):
    """At a terminal without --count or --duration it keeps waiting, the reason on the banner line; q ends it."""
    from daemon_hil import watched_daemon

    term = Terminal()
    with watched_daemon(tmp_path) as (_, daemon, _client):
        proc = popen_watch_in(term, daemon.address)
        try:
            term.wait_for("(port open, no samples from the instrument) ***")
            press_q(term, proc)
        finally:
            proc.kill()
            proc.wait(GUARD_S)
        assert daemon.terminate() == 0
    assert re.search(r"\*\*\* NO DATA for \d+ s \(port open, no samples from the instrument\) \*\*\*", term.screen)
    term.close()
