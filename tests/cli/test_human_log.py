"""The log a person reads (``--log-format human``): a warning repeated again and again is shown once a minute with
the count of those held back, a recovery has its own line; the JSON log for machines keeps every event."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
import structlog

from fog_driver.console import RepeatLimiter, configure_logging, render_human
from fog_driver.protocol import FrameDecoder, SampleFrame
from fog_driver.transport import PtyPair

DATA = Path(__file__).resolve().parents[1] / "data"
SHORT = (DATA / "sim-short.bin").read_bytes()


class Clock:
    def __init__(self) -> None:
        self.now_s = 0.0

    def __call__(self) -> float:
        return self.now_s


def _log(limiter: RepeatLimiter, clock: Clock, level: str, event: str, **fields) -> list[str]:
    """The lines one event gives (none when held back), at ``clock``'s time, its timestamp HH:MM:SS from it."""
    stamp = f"00:{int(clock.now_s) // 60:02d}:{int(clock.now_s) % 60:02d}"
    try:
        entry = limiter(None, "", {"event": event, "level": level, "timestamp": stamp, **fields})
    except structlog.DropEvent:
        return []
    return render_human(None, "", entry).split("\n")


def test_a_pulled_port_for_145_s_is_five_lines_not_145():
    """The review's finding 9: a pulled port gave a warning a second, 145 of them, and nothing when it came
    back.  Now the first, one a minute with the count held back, the count of the last ones, the recovery."""
    clock = Clock()
    limiter = RepeatLimiter(clock=clock)
    lines = []
    for attempt in range(145):  # a retry warning each second, its attempt number and delay changing
        clock.now_s = float(attempt)
        lines += _log(
            limiter,
            clock,
            "warning",
            "port_state",
            state="retry_wait",
            url="/dev/ttyUSB0",
            detail="cannot open /dev/ttyUSB0: no such device",
            attempt=attempt + 1,
            retry_in_s=1.0,
        )
    clock.now_s = 145.0
    lines += _log(limiter, clock, "warning", "port_recovered", url="/dev/ttyUSB0", down_s=145.0, frames_missing=1112)
    retry = "port_state  state=retry_wait url=/dev/ttyUSB0 detail='cannot open /dev/ttyUSB0: no such device'"
    assert lines == [
        f"00:00:00 warning {retry} attempt=1 retry_in_s=1.0",
        f"00:01:00 warning {retry} attempt=61 retry_in_s=1.0  (59 more like it since 00:00:00 not shown)",
        f"00:02:00 warning {retry} attempt=121 retry_in_s=1.0  (59 more like it since 00:01:00 not shown)",
        "00:02:25 warning port_state  24 more like it since 00:02:00 not shown",
        "00:02:25 warning port open again after 145 s, 1,112 frames missing  url=/dev/ttyUSB0",
    ]
    assert 3 + 59 + 59 + 24 == 145  # every warning shown or counted


def test_other_warnings_and_info_lines_are_not_held_back():
    clock = Clock()
    limiter = RepeatLimiter(clock=clock)
    assert len(_log(limiter, clock, "warning", "model_warning", message="a weak fit")) == 1
    assert len(_log(limiter, clock, "warning", "model_warning", message="no stored range")) == 1  # other text
    for _ in range(3):
        assert len(_log(limiter, clock, "info", "status", frames=100)) == 1  # -v's status lines, every one


def test_the_json_log_keeps_every_event(capsys):
    """For machines (journald, Loki, a script): every event, each attempt's detail with it; they count."""
    configure_logging(0, "json")
    log = structlog.get_logger("test")
    for attempt in range(5):
        log.warning("port_state", state="retry_wait", url="/dev/ttyUSB0", attempt=attempt + 1)
    entries = [json.loads(line) for line in capsys.readouterr().err.splitlines()]
    assert [entry["attempt"] for entry in entries] == [1, 2, 3, 4, 5]


def test_at_a_terminal_the_log_is_limited_too(capsys):
    configure_logging(0, "human")
    log = structlog.get_logger("test")
    for attempt in range(5):
        log.warning("port_state", state="retry_wait", url="/dev/ttyUSB0", attempt=attempt + 1)
    assert len(capsys.readouterr().err.splitlines()) == 1  # within a minute: the first only


@pytest.mark.serial
def test_the_daemon_says_when_its_port_is_open_again_and_how_many_frames_the_outage_cost(tmp_path):
    """A pty unplugged, then a new one on the same link, the stream going on some frames later: the daemon's
    human log has "port open again after N s, K frames missing" with K the frames the stream skipped."""
    from daemon_hil import Client, Daemon

    frames = [f for f in FrameDecoder().feed(SHORT) if isinstance(f, SampleFrame)]
    before, after = frames[100], frames[140]  # the last frame sent before the unplug, the first after it
    ends = {f.offset: g.offset for f, g in zip(frames, frames[1:], strict=False)}
    missing = after.seq - before.seq - 1
    link = tmp_path / "ttyFOG0"
    pty = PtyPair()
    pty.symlink(link)
    daemon = Daemon(tmp_path, str(link), "--log-format", "human")
    try:
        client = Client(daemon.address)
        client.send('?WATCH={"enable":true};')
        client.wait_device("activated")
        pty.write(SHORT[: ends[before.offset]])
        while client.next("ANGLE")["seq"] != before.seq:
            pass
        pty.unplug()
        client.wait_device("deactivated")
        pty.close()
        pty = PtyPair()
        pty.symlink(link)
        client.wait_device("activated")
        pty.write(SHORT[after.offset :])
        first = client.next("ANGLE")
        assert first["seq"] == after.seq and "gap" in first["flags"]
        assert daemon.terminate() == 0
    finally:
        pty.close()
        daemon.kill()
    log = daemon.log_path.read_text()
    recovered = [line for line in log.splitlines() if "port open again" in line]
    assert len(recovered) == 1, log
    when = r"\d\d:\d\d:\d\d"
    pattern = rf"{when} warning port open again after [\d,]+ s, {missing:,} frames missing  url={re.escape(str(link))}"
    assert re.fullmatch(pattern, recovered[0]), recovered


def test_a_flood_of_distinct_warnings_keeps_the_limiter_bounded():
    from fog_driver.console import MAX_KINDS

    clock = Clock()
    limiter = RepeatLimiter(clock=clock)
    for n in range(3 * MAX_KINDS):
        clock.now_s = n * 0.001
        assert len(_log(limiter, clock, "warning", "client_failed", peer=f"10.0.{n // 256}.{n % 256}")) == 1
    assert len(limiter._kinds) <= MAX_KINDS
