"""Tests of fog_driver.sim.serve: the real-time loop, the pty server, devices and the CLI.

Every byte goes through a real pty and ``PortReader`` (pyserial), as a driver would read it.
Nothing here sleeps to synchronise: the tests wait on events, queues and lines, with
generous timeouts only as guards against a hang.  Timing is checked only from below (the
pacing must pace); upper bounds on time would measure the machine, not the code.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import structlog.testing
from readerthread import Reader
from sim_serving import GUARD_S, REPO, SHORT_TEST, _next_line, _start_cli

from fog_driver.errors import DeviceError, OutputFileError
from fog_driver.lab.profiles import load_profile
from fog_driver.protocol import MAX_FRAME_LEN, SEQ_MODULUS, decode_bytes
from fog_driver.sim.capture import simulate_to_file
from fog_driver.sim.faults import parse_fault_spec
from fog_driver.sim.instrument import Simulator
from fog_driver.sim.serve import PtyServer, serve, serve_device, serve_pty
from fog_driver.transport import PtyPair

SERIAL = "FOG-SIM-0001"  # the default instrument's serial


def make_sim(rate_hz: int = 1000, seed: int = 5, faults: str = "none") -> Simulator:
    return Simulator(load_profile(str(SHORT_TEST)), rate_hz=rate_hz, seed=seed, faults=parse_fault_spec(faults))


def capture_bytes(tmp_path: Path, duration_s: float, **sim_args) -> bytes:
    """The capture file of the same simulator settings, as ``fog-driver simulate --out`` writes it."""
    out = tmp_path / f"reference-{len(list(tmp_path.glob('reference-*.bin')))}.bin"
    simulate_to_file(make_sim(**sim_args), out, duration_s=duration_s)
    return out.read_bytes()


def frame_index(seq: np.ndarray, sim: Simulator) -> np.ndarray:
    """Frame numbers k of received SAMPLE frames (seq counts up from the run's random seq0)."""
    return (seq.astype(np.int64) - sim.seq0) % SEQ_MODULUS


# ---------------------------------------------------------------------------------------------
# serve(): the real-time loop, through a real pty


@pytest.mark.parametrize("speed", [1.0, 6.0])
def test_live_stream_through_a_pty_equals_the_capture_file(tmp_path: Path, speed: float) -> None:
    duration_s = 3.0
    sim = make_sim()
    with PtyPair() as pair:
        reader = Reader(pair.slave_path, reconnect=False)
        try:
            assert reader.opened.wait(GUARD_S), "reader never opened the pty"
            due_ok = []
            t_before = time.monotonic()

            def write(data: bytes) -> None:
                # The chunk's last frame is sim.next_frame - 1; it may not go out before it is due.
                due_ok.append(time.monotonic() >= t_before + (sim.next_frame - 1) * sim.period_true_s / speed)
                pair.write(data)

            stats = serve(sim, write, duration_s=duration_s, speed=speed)
            wall_s = time.monotonic() - t_before
            expected = capture_bytes(tmp_path, duration_s)
            received = reader.receive(len(expected))
        finally:
            reader.finish()
    assert received == expected
    assert stats.frames == 3000 and stats.bytes == len(expected) and not stats.stopped
    # Pacing paces: never ahead of the schedule (a lower bound, not a timing measurement).
    assert all(due_ok)
    assert wall_s >= (stats.frames - 1) * sim.period_true_s / speed - 1e-3
    assert stats.wall_s >= (stats.frames - 1) * sim.period_true_s / speed - 1e-3
    assert stats.cpu_s > 0


@pytest.mark.parametrize("warn_behind", [True, False])
def test_a_stalled_writer_catches_up_and_still_delivers_the_same_bytes(tmp_path: Path, warn_behind: bool) -> None:
    """``warn_behind=False`` (the daemon's demonstration) logs the stall at info: no warning about itself."""
    sim = make_sim(rate_hz=500)
    out: list[bytes] = []
    stall = threading.Event()  # never set: waiting on it is the simulated stall of the machine

    def write(data: bytes) -> None:
        if len(out) == 5:
            stall.wait(0.3)  # 0.3 s wall = 1.5 s of device time at speed 5: far behind the schedule
        out.append(data)

    with structlog.testing.capture_logs() as logs:
        stats = serve(sim, write, duration_s=2.0, speed=5.0, warn_behind=warn_behind)
    assert b"".join(out) == capture_bytes(tmp_path, 2.0, rate_hz=500)
    assert stats.stalls >= 1 and stats.late_writes > stats.stalls  # the stall made several writes late...
    behind = [e for e in logs if e["event"] == "serve_behind"]
    assert len(behind) == stats.stalls  # ...and was logged once
    assert {e["log_level"] for e in behind} == {"warning" if warn_behind else "info"}


def test_stop_ends_the_loop_at_once_mid_stream() -> None:
    sim = make_sim(rate_hz=100)
    stop = threading.Event()
    writes = []

    def write(data: bytes) -> None:
        writes.append(data)
        if len(writes) == 3:
            stop.set()

    stats = serve(sim, write, stop=stop)  # the whole 20-minute profile unless stop works
    assert stats.stopped
    assert len(writes) == 3 and stats.frames < 20


def test_disconnect_windows_call_back_at_their_edges_and_bytes_still_match(tmp_path: Path) -> None:
    faults = "disconnect=0.5:0.2+0.7:0.001+1.3:0.05"
    sim = make_sim(faults=faults)
    out: list[bytes] = []
    events: list[tuple[str, int]] = []
    stats = serve(
        sim,
        out.append,
        duration_s=1.5,
        speed=8.0,
        on_cut=lambda: events.append(("cut", sim.next_frame)),
        on_reconnect=lambda: events.append(("reconnect", sim.next_frame)),
    )
    # on_cut once the window's first frame is out (next_frame = a + 1), on_reconnect at its end (b).
    assert events == [
        ("cut", 501),
        ("reconnect", 700),
        ("cut", 701),
        ("reconnect", 701),
        ("cut", 1301),
        ("reconnect", 1350),
    ]
    assert stats.cuts == 3
    assert b"".join(out) == capture_bytes(tmp_path, 1.5, faults=faults)


def test_bad_arguments_are_value_errors() -> None:
    sim = make_sim()
    for kwargs in ({"speed": 0}, {"speed": float("nan")}, {"chunk_s": 0}, {"duration_s": -1}):
        with pytest.raises(ValueError):
            serve(sim, lambda data: None, **kwargs)


# ---------------------------------------------------------------------------------------------
# serve_pty(): a pty behind a stable symlink, unplugged and replugged at disconnects


def test_disconnect_unplugs_the_pty_and_a_reader_reconnects_through_the_link(tmp_path: Path) -> None:
    faults = "disconnect=1:0.5"
    link = tmp_path / "ttyFOG0"
    sim = make_sim(faults=faults)
    readers: list[Reader] = []
    slaves: list[str] = []

    def on_ready(server: PtyServer) -> None:
        slaves.append(server.slave_path)
        readers.append(Reader(str(link), reconnect=True, backoff_initial_s=0.02, backoff_max_s=0.1))
        assert readers[0].opened.wait(GUARD_S), "reader never opened the link"

    items: list[tuple[str, object]] = []
    try:
        stats = serve_pty(sim, link=link, duration_s=2.5, speed=2.0, on_ready=on_ready)
        assert not link.exists() and not link.is_symlink()  # removed at the end
        # Take everything until the reader has seen the final unplug and waits to retry a link now gone.
        while True:
            kind, item = readers[0].items.get(timeout=GUARD_S)
            items.append((kind, item))
            losses = sum(k == "state" and i.state == "lost" for k, i in items)
            if kind == "state" and item.state == "retry_wait" and losses == 2:
                break
    finally:
        if readers:
            items += readers[0].finish()
    assert stats.cuts == 1 and stats.frames == 2500

    states = [item.state for kind, item in items if kind == "state"]
    lost = [i for i, (kind, item) in enumerate(items) if kind == "state" and item.state == "lost"]
    reopened = next(
        i for i, (kind, item) in enumerate(items) if i > lost[0] and kind == "state" and item.state == "open"
    )
    assert states[:2] == ["opening", "open"] and states.count("open") == 2
    before = b"".join(item for kind, item in items[: lost[0]] if kind == "data")
    after = b"".join(item for kind, item in items[reopened : lost[1]] if kind == "data")
    reference = capture_bytes(tmp_path, 2.5, faults=faults)

    # Before the cut: a prefix of the capture (the last bytes on the wire may die with the pty).
    assert before and reference.startswith(before)
    k_before = frame_index(decode_bytes(before).samples.seq, sim)
    assert k_before[-1] <= 999 and np.all(np.diff(k_before) == 1)
    # After reconnecting: frames again, their seq continuing past the gap, up to the end (drained).
    decoded = decode_bytes(after)
    assert decoded.counters.crc_errors <= 1
    k_after = frame_index(decoded.samples.seq, sim)
    assert len(k_after) > 0 and k_after[0] >= 1500 and k_after[-1] == 2499
    assert np.all(np.diff(k_after) == 1)
    first = int(decoded.samples.offset[0])
    assert reference.endswith(after[first:])
    assert len(slaves) == 1


def test_link_refuses_to_replace_a_regular_file(tmp_path: Path) -> None:
    path = tmp_path / "not-a-link"
    path.write_text("precious")
    with pytest.raises(OutputFileError, match="the path is a regular file, not a link of ours"):
        PtyServer(path)
    assert path.read_text() == "precious"


def test_link_replaces_a_stale_symlink_and_is_removed_on_close(tmp_path: Path) -> None:
    """A symlink whose target is gone (the pty of a run that ended without removing its link) is replaced."""
    link = tmp_path / "ttyFOG0"
    link.symlink_to(tmp_path / "pts-of-a-run-that-ended")
    with PtyServer(link) as server:
        assert os.readlink(link) == server.slave_path
        server.cut()
        assert not link.is_symlink() and server.slave_path is None
        server.reconnect()
        assert os.readlink(link) == server.slave_path
    assert not link.is_symlink()
    assert not list(tmp_path.glob(".*tmp"))  # no temporary link left behind


def test_pty_writes_without_a_reader_are_dropped_not_blocking(tmp_path: Path) -> None:
    with PtyServer(tmp_path / "ttyFOG0", write_timeout_s=0.0) as server:
        chunk = b"\xaa" * 4096
        for _ in range(20):  # 80 kB: more than a pty holds with nobody reading
            server.write(chunk)
        assert server.dropped_writes > 0
        assert server.dropped_bytes == server.dropped_writes * len(chunk)


# ---------------------------------------------------------------------------------------------
# serve_device(): a serial device (here the slave side of a pty, read on the master side)


def test_serve_device_writes_the_stream_to_a_tty(tmp_path: Path) -> None:
    sim = make_sim(rate_hz=200)
    expected = capture_bytes(tmp_path, 1.0, rate_hz=200)
    got = bytearray()
    with PtyPair() as pair:
        done = threading.Event()

        def drain_master() -> None:
            # until every byte has come through, or GUARD_S after the writer finished: a pty under load hands
            # the last bytes over after the writer has returned, so an empty read is no end of stream
            deadline = math.inf
            while len(got) < len(expected) and time.monotonic() < deadline:
                got.extend(pair.read_available(0.02))
                if done.is_set() and deadline == math.inf:
                    deadline = time.monotonic() + GUARD_S

        thread = threading.Thread(target=drain_master, daemon=True)
        thread.start()
        try:
            stats = serve_device(sim, pair.slave_path, baudrate=921600, duration_s=1.0, speed=10.0)
        finally:
            done.set()
            thread.join(GUARD_S)
    assert bytes(got) == expected
    assert stats.bytes == len(expected) and stats.dropped_bytes == 0


def test_serve_to_a_nonexistent_device_is_a_one_line_device_error(tmp_path: Path) -> None:
    missing = str(tmp_path / "ttyUSB99")
    with pytest.raises(DeviceError) as info:
        serve_device(make_sim(), missing, duration_s=1.0)
    message = str(info.value)
    assert missing in message and "\n" not in message


def test_cli_serve_to_a_nonexistent_device_exits_69_with_one_line(tmp_path: Path) -> None:
    missing = str(tmp_path / "ttyUSB99")
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "fog_driver",
            "simulate",
            "--serve",
            missing,
            "--profile",
            str(SHORT_TEST),
            "--duration",
            "1",
        ],
        check=False,
        capture_output=True,
        text=True,
        cwd=REPO,
        timeout=GUARD_S,
        stdin=subprocess.DEVNULL,
    )
    err = proc.stderr.strip().splitlines()
    assert proc.returncode == 69, proc.stderr
    assert len(err) == 1 and err[0].startswith("fog-driver: error: cannot open") and missing in err[0]
    assert proc.stdout == ""  # no readiness line for a device that never opened


def test_serve_device_refuses_a_baud_rate_too_slow_for_the_stream() -> None:
    with pytest.raises(Exception, match="too slow"):
        serve_device(make_sim(rate_hz=1000), "/dev/null", baudrate=9600, duration_s=1.0)


# ---------------------------------------------------------------------------------------------
# fog-driver simulate --serve pty, as a separate process


def test_cli_serves_a_pty_that_a_reader_opens_through_the_link(tmp_path: Path) -> None:
    link = tmp_path / "ttyFOG0"
    proc, lines = _start_cli("--rate-hz", "200", "--duration", "3", link=link)
    try:
        ready = _next_line(proc, lines)
        assert ready.startswith("serving short-test at 200 Hz on /dev/") and ready.endswith(f"(link {link})\n")
        slave = ready.split(" on ", 1)[1].split(" (link ", 1)[0]
        assert os.readlink(link) == slave
        reader = Reader(str(link), reconnect=False)
        assert reader.done.wait(GUARD_S), "reader did not see the end of the stream"
        items = reader.finish()
        assert proc.wait(GUARD_S) == 0, proc.stderr.read()
        summary = _next_line(proc, lines)
    finally:
        if proc.poll() is None:
            proc.kill()
    received = b"".join(item for kind, item in items if kind == "data")
    assert [item.state for kind, item in items if kind == "state"] == ["opening", "open", "lost", "closed"]

    decoded = decode_bytes(received)
    first = int(decoded.samples.offset[0])
    assert first < MAX_FRAME_LEN  # at most one partial frame before the first whole one
    clean = decode_bytes(received[first:])
    c = clean.counters
    assert c.crc_errors == 0 and c.length_errors == 0 and c.bytes_discarded == 0 and c.truncated_frames == 0
    assert c.seq_gaps == 0 and c.missing_frames == 0 and len(clean.samples) >= 100
    assert {identity.serial for identity in clean.identities} == {SERIAL}
    reference = capture_bytes(tmp_path, 3.0, rate_hz=200, seed=0)
    assert reference.endswith(received[first:])  # the same bytes as the capture, up to the very end
    assert summary.startswith("served 600 frames (3.0 s of device time)")
    assert not link.exists() and not link.is_symlink()


def test_cli_sigterm_stops_cleanly_and_removes_the_link(tmp_path: Path) -> None:
    link = tmp_path / "ttyFOG0"
    proc, lines = _start_cli(link=link)  # the whole 20-minute profile unless stopped
    try:
        assert _next_line(proc, lines).startswith("serving short-test")
        assert link.is_symlink()
        proc.terminate()
        assert proc.wait(GUARD_S) == 0, proc.stderr.read()
        assert _next_line(proc, lines).startswith("stopped after ")
    finally:
        if proc.poll() is None:
            proc.kill()
    assert not link.exists() and not link.is_symlink()


def test_serving_shows_progress_and_dropped_bytes_on_a_terminal():
    """``simulate --serve`` was silent until stopped: bytes dropped for want of a reader showed only at
    the end.  On a terminal a line now says how far it is and what was dropped."""
    import io
    import threading

    from fog_driver.sim.serve import ServeProgress

    class Terminal(io.StringIO):
        def __init__(self) -> None:
            super().__init__()
            self.dropped_shown = threading.Event()

        def isatty(self) -> bool:
            return True

        def write(self, text: str) -> int:
            if "bytes dropped" in text:
                self.dropped_shown.set()
            return super().write(text)

    class Server:
        dropped_bytes = 1234

    sim = Simulator(load_profile("paper"), rate_hz=10, seed=0)
    terminal = Terminal()
    with ServeProgress(sim, speed=1.0, duration_s=60.0, every_s=0.01, stream=terminal) as progress:
        progress.start(Server())
        assert terminal.dropped_shown.wait(10)
    shown = terminal.getvalue()
    assert "/ 60 s of device time; 1,234 bytes dropped (is anything reading?)" in shown
    assert shown.endswith("\r")  # cleared at the end: the summary line starts on a clean line
