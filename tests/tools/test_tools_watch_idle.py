"""``fog-driver watch`` when no samples come: a bounded watch ends after ``idle_s`` (exit 75) saying why, an
unbounded one waits on saying so, and the idle limit's rule and option."""

from __future__ import annotations

import io
import json
import math
import re
import signal
import subprocess
import sys

import pytest
from watch_fakes import DEVICE, GUARD_S, STATUS, FakeDaemon, FakeTty, angle, ndjson

from fog_driver.errors import TemporaryFailure, UsageError
from fog_driver.tools.watch import (
    DEFAULT_IDLE_S,
    idle_limit_s,
    run_watch,
)


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
