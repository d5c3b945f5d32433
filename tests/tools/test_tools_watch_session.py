"""``fog-driver watch`` talking to a daemon (``run_watch``): a fake daemon in a thread that sends a scripted
conversation (a socket bound and listening before ``run_watch`` connects: the kernel's accept backlog is the
readiness, nothing sleeps), a hub in this process, or a real daemon: how a watch ends, what it sends, the
daemon's refusals and its token, and ``--json`` through a pipe."""

from __future__ import annotations

import io
import json
import re
import signal
import socket
import subprocess
import sys
import threading
import time

import pytest
from watch_fakes import DEVICE, GUARD_S, STATUS, FakeDaemon, FakeTty, angle, ndjson, watch

from fog_driver.cli import main
from fog_driver.client import CommandRefused
from fog_driver.errors import DeviceError, TemporaryFailure, UsageError
from fog_driver.tools.watch import (
    MAX_LINE_BYTES,
    parse_line,
    run_watch,
)

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


def test_log_view_prints_a_line_each_second():
    daemon = FakeDaemon([ndjson(angle(1), STATUS)], then="wait")
    status, text = watch(daemon, duration_s=1.5)
    assert status == 0
    compact = [line for line in text.splitlines() if line.startswith("[")]
    assert len(compact) == 1  # at 1 s; nothing new arrived after it, so no final line
    assert re.match(r"\[ +1\.\d s\] seq 1 \|", compact[0])
    assert "0.0 ANGLE/s" not in compact[0]  # the one ANGLE is still inside the 2-s rate window


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


def test_watch_json_passes_the_daemons_lines_through_a_pipe_unchanged(tmp_path):
    """``watch --json`` is ``gpspipe -w``: the daemon's bytes, one line each, flushed per line; a reader that
    goes away (``| head``) ends it with exit 0 and nothing on stderr."""

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
