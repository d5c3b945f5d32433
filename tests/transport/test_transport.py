"""Tests of fog_driver.transport: the replay:// handler, PortReader and PtyPair.

No test sleeps to synchronise: threads hand results over through
``queue.Queue``/``threading.Event``, and every timeout below is only a guard
that turns a hang into a failure.
"""

from __future__ import annotations

import errno
import importlib
import math
import os
import queue
import select
import termios
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import serial
from readerthread import Reader

import fog_driver.transport
from fog_driver.protocol import SAMPLE_FRAME_LEN, encode_identity, encode_sample
from fog_driver.transport import (
    PortError,
    PortEvent,
    PortReader,
    PtyPair,
    open_port,
    parse_replay_url,
    replay_schedule,
)
from fog_driver.transport.protocol_replay import UNPLUGGED_MESSAGE

GUARD_S = 10.0  #: failure guard for waits on other threads; never reached when things work

# ---------------------------------------------------------------------------------------------
# captures


def build_capture(n_samples: int, *, identity_every: int = 25) -> tuple[bytes, list[int]]:
    """A capture with garbage, IDENTITY frames and a tail, plus its expected release schedule.

    The schedule is computed here from the construction, independently of the
    decoder: entry k is the byte count up to the end of SAMPLE k, the last
    entry is the whole capture (the tail goes out with the last sample).
    """
    out = bytearray(b"\x00\xff\xaa")  # leading garbage, including a lone sync byte
    ends: list[int] = []
    for k in range(n_samples):
        if k % identity_every == 0:
            out += encode_identity("FOG-0042", 0x0103, 1000, 0.0123)
        if k % 7 == 3:
            out += b"\xaa\x55\x01\x12junk\r\n"  # a false sync with a SAMPLE header: CRC fails
        out += encode_sample(k, 1000 * k, k - 50, 25 * 256, 24 * 256, 30 * 256, status=k & 0x1F)
        ends.append(len(out))
    out += b"\xaa\x55\x01"  # a truncated frame at the end
    ends[-1] = len(out)
    return bytes(out), ends


@pytest.fixture
def capture(tmp_path: Path) -> tuple[Path, bytes, list[int]]:
    data, ends = build_capture(120)
    path = tmp_path / "capture.bin"
    path.write_bytes(data)
    return path, data, ends


# ---------------------------------------------------------------------------------------------
# helpers for PortReader in a thread


class ReaderThread(Reader):
    """``readerthread.Reader`` with chunks and state events in two queues (``chunks``, ``events``)."""

    def __init__(self, url: str, **kwargs: object) -> None:
        self.events: queue.Queue[PortEvent] = queue.Queue()
        self.chunks: queue.Queue[bytes] = queue.Queue()
        self.seen: list[PortEvent] = []
        kwargs.setdefault("read_timeout_s", 0.05)
        super().__init__(url, **kwargs)

    def _on_state(self, event: PortEvent) -> None:
        self.events.put(event)
        if event.state == "open":
            self.opened.set()

    def _on_chunk(self, chunk: bytes) -> None:
        self.chunks.put(chunk)

    def receive(self, n_bytes: int) -> bytes:
        """Collect exactly ``n_bytes`` (fails on a guard timeout or on extra bytes)."""
        got = bytearray()
        while len(got) < n_bytes:
            got += self.chunks.get(timeout=GUARD_S)
        assert len(got) == n_bytes
        return bytes(got)

    def next_event(self) -> PortEvent:
        """The next state event (kept in ``seen`` too)."""
        event = self.events.get(timeout=GUARD_S)
        self.seen.append(event)
        return event

    def wait_state(self, state: str) -> PortEvent:
        """Next event with ``state``; the events passed on the way are kept in ``seen``."""
        while True:
            event = self.next_event()
            if event.state == state:
                return event

    def finish(self) -> list[PortEvent]:  # type: ignore[override]
        """Stop, join, re-raise a reader error, and return every event reported."""
        self.join()
        while not self.events.empty():
            self.seen.append(self.events.get_nowait())
        return self.seen


@pytest.fixture
def guard_stop() -> Iterator[threading.Event]:
    """A stop event that a timer sets after GUARD_S, so a broken reader fails instead of hanging."""
    stop = threading.Event()
    timer = threading.Timer(GUARD_S, stop.set)
    timer.start()
    yield stop
    timer.cancel()


# ---------------------------------------------------------------------------------------------
# registration and URL parsing


def test_handler_registration_is_idempotent() -> None:
    importlib.reload(fog_driver.transport)
    importlib.reload(fog_driver.transport)
    assert serial.protocol_handler_packages.count("fog_driver.transport") == 1


def test_replay_url_paths_absolute_relative_and_escaped(
    capture: tuple[Path, bytes, list[int]], monkeypatch: pytest.MonkeyPatch
) -> None:
    path, data, _ = capture
    sub = path.parent / "sub dir"
    sub.mkdir()
    (sub / "c.bin").write_bytes(data[:100])
    monkeypatch.chdir(path.parent)
    assert parse_replay_url(f"replay://{path}?rate=500&unplug=1").path == path
    assert parse_replay_url("replay://capture.bin").path == Path("capture.bin")
    options = parse_replay_url("replay://sub%20dir/c.bin?unplug=0")
    assert (options.path, options.rate_hz, options.unplug) == (Path("sub dir/c.bin"), None, False)
    for url, expected in [
        (f"replay://{path}", data),
        ("replay://capture.bin", data),
        ("replay://sub%20dir/c.bin", data[:100]),
    ]:
        port = open_port(url, timeout_s=0)
        try:
            assert port.read(len(data) + 10) == expected
        finally:
            port.close()


@pytest.mark.parametrize(
    ("query", "message"),
    [
        ("?rate=abc", "bad rate 'abc'"),
        ("?rate=0", "bad rate '0'"),
        ("?rate=-5", "bad rate '-5'"),
        ("?rate=inf", "bad rate 'inf'"),
        ("?rate=nan", "bad rate 'nan'"),
        ("?rate=", "bad rate ''"),
        ("?unplug=2", "bad unplug '2'"),
        ("?unplug=yes", "bad unplug 'yes'"),
        ("?speed=10", "unknown parameter 'speed'"),
        ("?rate=10&rate=20", "parameter 'rate' given 2 times"),
        ("?rate", "malformed query"),
    ],
)
def test_replay_bad_query_raises_clear_serial_exception(
    capture: tuple[Path, bytes, list[int]], query: str, message: str
) -> None:
    path, _, _ = capture
    with pytest.raises(serial.SerialException, match=message.replace("?", r"\?")) as info:
        open_port(f"replay://{path}{query}")
    assert str(path) in str(info.value)


def test_replay_missing_file_or_no_path_raises_clear_serial_exception(tmp_path: Path) -> None:
    missing = tmp_path / "nope.bin"
    with pytest.raises(serial.SerialException, match="replay capture not found") as info:
        open_port(f"replay://{missing}?rate=100")
    assert str(missing) in str(info.value)
    with pytest.raises(serial.SerialException, match="no capture file"):
        open_port("replay://")


# ---------------------------------------------------------------------------------------------
# replay without rate


@pytest.mark.parametrize("read_size", [1, 7, 26, 1000, 1 << 16])
def test_replay_serves_exact_bytes_then_idles(capture: tuple[Path, bytes, list[int]], read_size: int) -> None:
    path, data, _ = capture
    port = open_port(f"replay://{path}", timeout_s=0.01)
    try:
        got = bytearray()
        while len(got) < len(data):
            assert port.in_waiting == len(data) - len(got)
            chunk = port.read(read_size)
            assert len(chunk) == min(read_size, len(data) - len(got))
            got += chunk
        assert bytes(got) == data
        assert port.in_waiting == 0
        assert port.read(read_size) == b""  # idle: after the timeout, not an error
        assert port.read(1) == b""
        assert port.in_waiting == 0
    finally:
        port.close()


def test_replay_unplug_raises_only_after_every_byte(capture: tuple[Path, bytes, list[int]]) -> None:
    path, data, _ = capture
    port = open_port(f"replay://{path}?unplug=1", timeout_s=0.01)
    try:
        assert port.read(len(data) - 1) == data[:-1]
        assert port.in_waiting == 1
        assert port.read(10) == data[-1:]
        with pytest.raises(OSError) as info:
            port.in_waiting  # noqa: B018 - the property is the call under test
        assert info.value.errno == errno.EIO
        for _ in range(2):
            with pytest.raises(serial.SerialException) as read_info:
                port.read(1)
            assert str(read_info.value) == UNPLUGGED_MESSAGE
    finally:
        port.close()


def test_replay_is_read_only_and_reopens_from_the_start(capture: tuple[Path, bytes, list[int]]) -> None:
    path, data, _ = capture
    port = open_port(f"replay://{path}", timeout_s=0)
    try:
        with pytest.raises(serial.SerialException, match="read-only"):
            port.write(b"\x01")
        assert port.read(10) == data[:10]
        port.close()
        with pytest.raises(serial.PortNotOpenError):
            port.read(1)
        port.open()
        assert port.read(len(data)) == data
    finally:
        port.close()


def test_replay_cancel_read_and_close_wake_a_blocked_read(capture: tuple[Path, bytes, list[int]]) -> None:
    path, data, _ = capture
    port = open_port(f"replay://{path}", timeout_s=None)  # idle at the end: read would block forever
    assert port.read(len(data)) == data
    results: queue.Queue[bytes | BaseException] = queue.Queue()

    def blocked_read() -> None:
        try:
            results.put(port.read(1))
        except BaseException as exc:
            results.put(exc)

    threading.Thread(target=blocked_read, daemon=True).start()
    port.cancel_read()
    assert results.get(timeout=GUARD_S) == b""
    threading.Thread(target=blocked_read, daemon=True).start()
    port.close()
    # b'' if the read was already waiting, PortNotOpenError if close came first; never a hang.
    result = results.get(timeout=GUARD_S)
    assert result == b"" or isinstance(result, serial.PortNotOpenError)


# ---------------------------------------------------------------------------------------------
# replay with rate


def test_replay_schedule_matches_capture_construction() -> None:
    data, ends = build_capture(60)
    assert replay_schedule(data).tolist() == ends
    garbage_only = b"\x00\xaa\x55junk"
    assert replay_schedule(garbage_only).tolist() == [len(garbage_only)]
    one = encode_sample(0, 0, 0, 0, 0, 0)
    assert replay_schedule(one).tolist() == [SAMPLE_FRAME_LEN]


def test_replay_schedule_of_a_file_equals_that_of_its_bytes(tmp_path: Path) -> None:
    data, ends = build_capture(60)
    for name, content in (("c.bin", data), ("g.bin", b"\x00\xaa\x55junk"), ("e.bin", b"")):
        path = tmp_path / name
        path.write_bytes(content)
        assert replay_schedule(path).tolist() == replay_schedule(content).tolist()


def test_replay_slow_rate_releases_exactly_the_first_frame(capture: tuple[Path, bytes, list[int]]) -> None:
    """At 0.01 Hz frame 1 is 100 s away: only the bytes up to the end of frame 0 are readable."""
    path, data, ends = capture
    port = open_port(f"replay://{path}?rate=0.01", timeout_s=0.02)
    try:
        assert port.in_waiting == ends[0]
        assert port.read(10_000) == data[: ends[0]]
        assert port.in_waiting == 0
        assert port.read(10_000) == b""  # waited for the timeout, nothing released
    finally:
        port.close()


def test_replay_fast_rate_never_runs_ahead_of_schedule(tmp_path: Path) -> None:
    """2000 Hz, 100 frames: every read ends on a release boundary no later than the schedule allows."""
    data, ends = build_capture(100)
    path = tmp_path / "fast.bin"
    path.write_bytes(data)
    rate_hz = 2000.0
    boundaries = set(ends)
    t0_s = time.monotonic()  # before open, so the handler's clock can only lag behind this one
    port = open_port(f"replay://{path}?rate={rate_hz:g}", timeout_s=0.5)
    try:
        got = bytearray()
        reads = 0
        while len(got) < len(data) and reads < 10_000:
            chunk = port.read(1 << 16)
            elapsed_s = time.monotonic() - t0_s
            reads += 1
            got += chunk
            allowed = ends[min(math.floor(elapsed_s * rate_hz), len(ends) - 1)]
            assert len(got) <= allowed, f"{len(got)} bytes read at {elapsed_s:.4f} s, schedule allows {allowed}"
            assert len(got) in boundaries, f"read ended at {len(got)}, not on a frame release boundary"
        assert bytes(got) == data
        port.timeout = 0.01
        assert port.read(1) == b""
    finally:
        port.close()


# ---------------------------------------------------------------------------------------------
# PortReader on replays


def test_reader_reconnects_and_serves_the_file_again(
    capture: tuple[Path, bytes, list[int]], guard_stop: threading.Event
) -> None:
    path, data, _ = capture
    events: list[PortEvent] = []
    url = f"replay://{path}?unplug=1"
    reader = PortReader(url, backoff_initial_s=0.001, backoff_max_s=0.001, on_state=events.append)
    got = bytearray()
    for chunk in reader.chunks(guard_stop):
        assert chunk
        got += chunk
        if len(got) >= 2 * len(data):
            guard_stop.set()
    assert bytes(got) == data + data
    assert [e.state for e in events] == ["opening", "open", "lost", "retry_wait", "opening", "open", "closed"]
    assert all(e.url == url for e in events)
    lost, retry = events[2], events[3]
    assert "Input/output error" in lost.detail
    assert retry.retry_in_s == pytest.approx(0.001)
    assert [e.attempt for e in events[:6]] == [1, 1, 1, 1, 1, 1]
    assert (reader.opens, reader.losses, reader.bytes_read) == (2, 1, 2 * len(data))


def test_reader_without_reconnect_returns_at_the_end_of_an_unplugging_replay(
    capture: tuple[Path, bytes, list[int]], guard_stop: threading.Event
) -> None:
    path, data, _ = capture
    events: list[PortEvent] = []
    reader = PortReader(f"replay://{path}?unplug=1", reconnect=False, on_state=events.append)
    assert b"".join(reader.chunks(guard_stop)) == data
    assert not guard_stop.is_set()
    assert [e.state for e in events] == ["opening", "open", "lost", "closed"]


def test_first_open_failure_without_reconnect_raises_port_error(tmp_path: Path) -> None:
    missing = str(tmp_path / "no-such-tty")
    events: list[PortEvent] = []
    reader = PortReader(missing, reconnect=False, on_state=events.append)
    with pytest.raises(PortError) as info:
        next(reader.chunks(threading.Event()))
    assert missing in str(info.value)
    assert [e.state for e in events] == ["opening", "closed"]
    assert missing in events[-1].detail
    assert (reader.opens, reader.open_failures) == (0, 1)


def test_first_open_failure_with_reconnect_backs_off_until_stop(tmp_path: Path, guard_stop: threading.Event) -> None:
    missing = str(tmp_path / "no-such-tty")
    retries: list[PortEvent] = []
    events: list[PortEvent] = []

    def on_state(event: PortEvent) -> None:
        events.append(event)
        if event.state == "retry_wait":
            retries.append(event)
            if len(retries) == 6:
                guard_stop.set()

    reader = PortReader(missing, backoff_initial_s=0.001, backoff_max_s=0.004, on_state=on_state)
    assert list(reader.chunks(guard_stop)) == []
    assert len(retries) == 6, "stopped by the guard timer, not by the test"
    assert [e.retry_in_s for e in retries] == pytest.approx([0.001, 0.002, 0.004, 0.004, 0.004, 0.004])
    assert [e.attempt for e in retries] == [1, 2, 3, 4, 5, 6]
    assert all(missing in e.detail for e in retries)
    assert [e.state for e in events] == ["opening", "retry_wait"] * 6 + ["closed"]
    assert (reader.opens, reader.open_failures) == (0, 6)


def test_unknown_scheme_is_a_port_error_even_with_reconnect() -> None:
    reader = PortReader("nosuchscheme://x", reconnect=True)
    with pytest.raises(PortError, match="nosuchscheme"):
        next(reader.chunks(threading.Event()))


# ---------------------------------------------------------------------------------------------
# PtyPair and PortReader on a real tty


def test_pty_passes_every_byte_value_through_port_reader() -> None:
    payload = bytes(range(256)) * 8 + bytes(reversed(range(256))) * 8 + b"\r\n\n\r\x03\x04\x11\x13\x1a\x7f\xff"
    with PtyPair() as pair:
        reader = ReaderThread(pair.slave_path, read_timeout_s=0.02)
        try:
            assert reader.opened.wait(GUARD_S), "reader never opened the pty"
            pair.write(payload)
            assert reader.receive(len(payload)) == payload
            assert pair.read_available(0.0) == b""  # raw mode: nothing echoed back to the master
        finally:
            events = reader.finish()
    assert [e.state for e in events] == ["opening", "open", "closed"]
    assert reader.reader.bytes_read == len(payload)


def test_pty_symlink_is_a_stable_name_removed_on_close(tmp_path: Path) -> None:
    link = tmp_path / "ttyFOG0"
    frame = encode_sample(1, 2, 3, 4, 5, 6)
    with PtyPair() as pair:
        assert pair.symlink(link) == link
        assert link.resolve() == Path(pair.slave_path).resolve()
        reader = ReaderThread(str(link))
        try:
            assert reader.opened.wait(GUARD_S)
            pair.write(frame)
            assert reader.receive(len(frame)) == frame
        finally:
            reader.finish()
    assert not link.exists() and not link.is_symlink()


def test_pty_unplug_reports_lost_then_retry_wait() -> None:
    with PtyPair() as pair:
        reader = ReaderThread(pair.slave_path, backoff_initial_s=0.01, backoff_max_s=0.05)
        try:
            assert reader.opened.wait(GUARD_S)
            pair.write(b"\xaa\x55before")
            assert reader.receive(8) == b"\xaa\x55before"
            pair.unplug()
            lost = reader.wait_state("lost")
            assert lost.detail
            retry = reader.next_event()
            assert retry.state == "retry_wait"
            assert retry.retry_in_s == pytest.approx(0.01)
            assert retry.detail == lost.detail
        finally:
            events = reader.finish()
    assert [e.state for e in events[:4]] == ["opening", "open", "lost", "retry_wait"]
    assert events[-1] == PortEvent("closed", pair.slave_path)  # stopped: no error detail
    assert reader.reader.losses == 1


def test_pty_unplug_without_reconnect_returns_cleanly() -> None:
    with PtyPair() as pair:
        reader = ReaderThread(pair.slave_path, reconnect=False)
        assert reader.opened.wait(GUARD_S)
        pair.write(b"last words")
        assert reader.receive(10) == b"last words"
        pair.unplug()
        assert reader.done.wait(GUARD_S), "chunks did not return after the unplug"
        assert not reader.stop.is_set()
        events = reader.finish()
    assert [e.state for e in events] == ["opening", "open", "lost", "closed"]


def test_pty_is_raw_before_any_reader_opens_it() -> None:
    """Without a reader's own termios setup, the helper's raw mode alone passes every byte unchanged."""
    payload = bytes(range(256)) + b"\r\n\x03\x04\x11\x13\x7f"
    with PtyPair() as pair:
        iflag, oflag, _, lflag = termios.tcgetattr(pair.slave_fd)[:4]
        assert lflag & (termios.ICANON | termios.ECHO | termios.ISIG | termios.IEXTEN) == 0
        assert iflag & (termios.ICRNL | termios.IXON | termios.ISTRIP) == 0
        assert oflag & termios.OPOST == 0
        pair.write(payload)
        got = bytearray()
        while len(got) < len(payload):
            readable, _, _ = select.select([pair.slave_fd], [], [], GUARD_S)
            assert readable, f"only {len(got)} of {len(payload)} bytes arrived"
            got += os.read(pair.slave_fd, 4096)
        assert bytes(got) == payload
        assert pair.read_available(0.0) == b""  # no echo


def test_reader_chunks_are_bounded_even_when_megabytes_wait(tmp_path: Path) -> None:
    from fog_driver.transport.port import MAX_READ_BYTES

    path = tmp_path / "big.bin"
    data = bytes(range(256)) * (4 * MAX_READ_BYTES // 256 + 3)
    path.write_bytes(data)
    chunks = list(PortReader(f"replay://{path}?unplug=1", reconnect=False).chunks(threading.Event()))
    assert b"".join(chunks) == data
    assert max(len(c) for c in chunks) == MAX_READ_BYTES and len(chunks) >= 5


# ---------------------------------------------------------------------------------------------
# read_available: what one read of the acquisition takes


class LumpPort:
    """A stand-in for a non-POSIX port (pyserial's ``read``/``in_waiting`` only): nothing waiting when the read
    starts, then a lump whose first byte wakes the read."""

    def __init__(self, lump: bytes, fail_after_first: bool = False) -> None:
        self.lump = lump
        self.fail_after_first = fail_after_first
        self.calls: list[tuple[str, int]] = []
        self.first = True

    @property
    def in_waiting(self) -> int:
        if self.first:
            return 0
        if self.fail_after_first:
            raise serial.SerialException("gone")
        return len(self.lump)

    def read(self, size: int) -> bytes:
        self.calls.append(("read", size))
        if self.first:
            self.first = False
            out, self.lump = self.lump[:1], self.lump[1:]
            return out
        out, self.lump = self.lump[:size], self.lump[size:]
        return out


def test_read_available_takes_the_rest_of_a_lump_with_the_byte_that_woke_it() -> None:
    """A read woken by a lump's first byte returns the whole lump as one chunk (pyserial's ``read(1)`` alone
    gave a chunk of one byte, and the pipeline ran twice per lump)."""
    from fog_driver.transport.port import read_available

    port = LumpPort(b"abcdefghij")
    assert read_available(port) == b"abcdefghij"
    assert port.calls == [("read", 1), ("read", 9)]


def test_read_available_keeps_the_first_byte_when_the_port_fails_after_it() -> None:
    from fog_driver.transport.port import read_available

    port = LumpPort(b"abc", fail_after_first=True)
    assert read_available(port) == b"a"  # the byte read is data; the next read meets the error


def test_read_available_on_a_pty_reads_the_descriptor_directly() -> None:
    """A POSIX port is read with select and one read(2), not through pyserial's byte-at-a-time ``read``: the
    lump comes whole and in order, a port with nothing gives b"" at its timeout, ``cancel_read`` wakes it, and a
    vanished far end (readable, no bytes) is pyserial's own error for an unplugged adapter."""
    from fog_driver.transport.port import read_available

    lump = bytes(range(256)) * 8
    with PtyPair() as pair:
        port = open_port(pair.slave_path, timeout_s=GUARD_S)
        try:
            port.read = None  # pyserial's read must not be used (calling it would raise TypeError)
            pair.write(lump)
            got = b""
            while len(got) < len(lump):
                got += read_available(port)
            assert got == lump
            port.timeout = 0.01
            assert read_available(port) == b""
            port.timeout = GUARD_S
            port.cancel_read()
            assert read_available(port) == b""  # woken by the cancel, not the guard timeout
            pair.unplug()
            with pytest.raises(serial.SerialException, match="readiness to read but returned no data"):
                read_available(port)
        finally:
            del port.read
            port.close()
