"""Serve a simulated instrument live: its byte stream in real time on a pty or a serial device.

``serve(sim, write)`` is the real-time loop.  It asks the simulator for chunks
of about ``chunk_s`` device seconds and hands each chunk's bytes to ``write``
when the chunk's last frame is due: frame k (counted from where the simulator
stood at the start) is due at ``start + k * sim.period_true_s / speed`` on the
monotonic clock.  The schedule is fixed at the start, so the stream never
drifts however long it runs; a writer that fell behind (a stalled machine)
writes at once until it has caught up, and the stall is logged once.  The bytes
are exactly ``sim.stream``'s, so a live stream equals the capture file of the
same seed (``simulate_to_file``), faults included.

Disconnect windows of the fault spec (device time) are the link's, not the
instrument's: the instrument keeps running (the frames are generated, their
bytes are already missing from ``sim.stream``), ``on_cut()`` is called once the
window's first frame is due (after the half frame that was on the wire when the
cable came out) and ``on_reconnect()`` when the first frame after the window is due.

``serve_pty`` serves on a fresh raw pty, behind a stable symlink only when given one (``link``, like a udev
rule's ``/dev/ttyFOG0``; ``fog-driver simulate --serve pty`` gives ``DEFAULT_LINK`` or ``--link``): a
disconnect window unplugs the pty (readers get EIO, exactly as from a pulled USB adapter) and removes the
symlink; after the window a new pty is made and the symlink points at it, so a reader that reconnects
through the symlink gets the stream again.  Without a link (``link=None``, the default: the daemon's own
demonstration, which reads the pty it made) no symlink is made, re-pointed or removed.  A link path may only
be missing or a stale symlink (its target gone: a run that ended without removing it); a regular file, a
directory or a symlink to something that exists (another simulator's pty, a device) is in the way: a one-line
``OutputFileError`` (exit 73), nothing replaced.  ``serve_device`` writes to a serial device or pyserial URL.
``serve_cli`` is ``fog-driver simulate --serve``.
"""

from __future__ import annotations

import fcntl
import math
import os
import stat
import struct
import termios
import threading
import time
from collections.abc import Callable
from contextlib import nullcontext, suppress
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Self

import serial
import structlog

from ..client.display import Progress
from ..errors import DeviceError, OutputFileError, UsageError
from ..protocol import IDENTITY_FRAME_LEN
from ..signals import stop_on_signals
from ..transport import DEFAULT_BAUDRATE, PtyPair, open_port
from .instrument import Simulator

__all__ = [
    "DEFAULT_LINK",
    "PtyServer",
    "ServeStats",
    "check_link_path",
    "serve",
    "serve_cli",
    "serve_device",
    "serve_pty",
]

log = structlog.get_logger("fog_driver.sim")

#: The stable name of ``--serve pty`` unless ``--link`` says otherwise.
DEFAULT_LINK = "/tmp/fog-driver-sim.tty"
#: How long the end of a stream may wait for the reader to take the last bytes out of the pty.
DRAIN_TIMEOUT_S = 1.0
#: The speeds a stream may run at, times real time: slower waits too long for any clock (a speed of 1e-300 puts
#: the next frame past the platform's time_t), faster is only late writes.
MIN_SPEED = 1e-3
MAX_SPEED = 1e6
#: Bits per byte on a serial line at 8N1 (start + 8 data + stop).
_BITS_PER_BYTE = 10


@dataclass
class ServeStats:
    """What a serving run did.  ``cpu_s`` is the serving thread's CPU time (``time.thread_time``)."""

    frames: int = 0  #: frames generated (device time covered, disconnect windows included)
    bytes: int = 0  #: bytes handed to the writer
    wall_s: float = 0.0  #: monotonic seconds from start to end of the loop
    cpu_s: float = 0.0  #: CPU seconds of the serving thread during the loop
    process_cpu_s: float = 0.0  #: CPU seconds of the whole process during the loop (all threads)
    late_writes: int = 0  #: writes made more than one chunk's wall time after they were due
    stalls: int = 0  #: episodes of falling behind (each logged once)
    cuts: int = 0  #: disconnect windows entered
    dropped_bytes: int = 0  #: bytes the link did not accept in time (set by serve_pty / serve_device)
    dropped_writes: int = 0  #: writes not accepted in full (each counts whole in ``dropped_bytes``)
    stopped: bool = False  #: ended by the stop event, not by the duration or the profile end

    @property
    def cpu_percent(self) -> float:
        """CPU of the serving thread as % of one core over the wall time."""
        return 100.0 * self.cpu_s / self.wall_s if self.wall_s > 0 else 0.0


def _first_frame_at_or_after(t_s: float, rate_hz: int) -> int:
    """The smallest k >= 0 with ``k / rate_hz >= t_s``, with the simulator's own float arithmetic."""
    k = max(0, math.ceil(t_s * rate_hz))
    while k > 0 and (k - 1) / rate_hz >= t_s:
        k -= 1
    while k / rate_hz < t_s:
        k += 1
    return k


def cut_windows(sim: Simulator, first: int, end: int) -> list[tuple[int, int]]:
    """Disconnect windows as frame ranges ``[a, b)`` that overlap ``[first, end)``, in order.

    Frame k is inside a window ``(start, duration)`` when ``start <= k / rate < start + duration``
    (``Simulator.emit``'s rule).  ``a`` is raised to ``first`` (a window already under way);
    ``b`` is kept even past ``end``; windows with no frame in ``[first, end)`` are left out.
    """
    windows = []
    for start, duration in sim.faults.disconnects:
        a = _first_frame_at_or_after(start, sim.rate_hz)
        b = _first_frame_at_or_after(start + duration, sim.rate_hz)
        a, b_clipped = max(a, first), min(b, end)
        if a < b_clipped:
            windows.append((a, b))
    return windows


def _check_pace(speed: float, chunk_s: float, duration_s: float | None) -> None:
    """``serve``'s numbers: each finite and > 0, ``speed`` from ``MIN_SPEED`` to ``MAX_SPEED`` (``duration_s``
    None: to the profile's end)."""
    if not MIN_SPEED <= speed <= MAX_SPEED:
        raise ValueError(f"speed must be {MIN_SPEED:g} to {MAX_SPEED:g}, got {speed!r}")
    if not (math.isfinite(chunk_s) and chunk_s > 0):
        raise ValueError(f"chunk_s must be a finite number > 0, got {chunk_s!r}")
    if duration_s is not None and not (math.isfinite(duration_s) and duration_s > 0):
        raise ValueError(f"duration_s must be a finite number > 0, got {duration_s!r}")


class _Pacer:
    """Real-time pacing for ``serve``: frame k is due ``(k - k0) * frame_wall_s`` after the first chunk is ready;
    a write more than ``late_after_s`` after it is late, and a run of late writes is one stall."""

    def __init__(
        self,
        stats: ServeStats,
        stop: threading.Event,
        k0: int,
        frame_wall_s: float,
        late_after_s: float,
        warn_behind: bool = True,
    ) -> None:
        self.stats, self.stop, self.k0 = stats, stop, k0
        self.log_behind = log.warning if warn_behind else log.info
        self.frame_wall_s, self.late_after_s = frame_wall_s, late_after_s
        self.t0: float | None = None  # when frame k0 is due: set once the first chunk is ready (its set-up is slow)
        self.behind = False
        self.t_start = time.monotonic()
        self.cpu0, self.pcpu0 = time.thread_time(), time.process_time()

    def finish(self, frames: int) -> None:
        """The run's accounting: ``frames`` generated, its wall time, the thread's and the process's CPU."""
        self.stats.frames = frames
        self.stats.wall_s = time.monotonic() - self.t_start
        self.stats.cpu_s = time.thread_time() - self.cpu0
        self.stats.process_cpu_s = time.process_time() - self.pcpu0

    def wait_due(self, k: int) -> bool:
        """Wait until frame ``k`` is due; False if stopped.  Tracks late writes and stalls."""
        stats = self.stats
        if self.t0 is None:
            self.t0 = time.monotonic()
        due = self.t0 + (k - self.k0) * self.frame_wall_s
        delay = due - time.monotonic()
        if delay > 0:
            if self.behind:
                self.behind = False
                log.info("serve_caught_up", frame=k)
            if self.stop.wait(delay):
                stats.stopped = True
                return False
            return True
        if -delay > self.late_after_s:
            stats.late_writes += 1
            if not self.behind:
                self.behind = True
                stats.stalls += 1
                self.log_behind(
                    "serve_behind", frame=k, behind_s=round(-delay, 3), detail="writing at once to catch up"
                )
        if self.stop.is_set():
            stats.stopped = True
            return False
        return True


def serve(
    sim: Simulator,
    write: Callable[[bytes], Any],
    *,
    duration_s: float | None = None,
    stop: threading.Event | None = None,
    speed: float = 1.0,
    chunk_s: float = 0.02,
    on_cut: Callable[[], Any] | None = None,
    on_reconnect: Callable[[], Any] | None = None,
    warn_behind: bool = True,
) -> ServeStats:
    """Stream ``sim`` through ``write(data)`` in real time (``speed`` times faster); see the module docstring.

    Stops after ``duration_s`` device seconds from where the simulator stands, at the profile's
    end, or as soon as ``stop`` is set (the wait between chunks is ``stop.wait``).  Exceptions from
    ``write`` and the callbacks propagate.  ``warn_behind``: a stall (``serve_behind``) is logged as a
    warning; False logs it at info (the daemon's demonstration: its own simulator, sharing its process, is
    no news to the person running it; the daemon reports what a stall does to the stream).
    """
    _check_pace(speed, chunk_s, duration_s)
    stop = stop if stop is not None else threading.Event()
    rate = sim.rate_hz
    k0 = sim.next_frame
    end = sim.total_frames()
    if duration_s is not None:
        end = min(end, k0 + round(duration_s * rate))
    per_chunk = max(1, round(chunk_s * rate))
    frame_wall_s = sim.period_true_s / speed
    late_after_s = per_chunk * frame_wall_s  # a reader sees at least a double chunk
    windows = cut_windows(sim, k0, end)
    stats = ServeStats()

    _log_start(sim, k0, end, speed, per_chunk, len(windows))
    pacer = _Pacer(stats, stop, k0, frame_wall_s, late_after_s, warn_behind)
    wait_due = pacer.wait_due

    def send(data: bytes) -> None:
        if data:
            write(data)
            stats.bytes += len(data)

    k = k0
    w = 0  # index of the next (or current) window in ``windows``
    try:
        while k < end and not stop.is_set():
            a, b = windows[w] if w < len(windows) else (end, end)
            if k == a:
                # The window's first frame: the half frame on the wire as the cable came out, then the cut.
                _, data = sim.stream(1)
                k += 1
                if not wait_due(a):
                    break
                send(data)
                stats.cuts += 1
                log.info("link_cut", frame=a, device_s=a / rate, frames_lost=min(b, end) - a)
                if on_cut is not None:
                    on_cut()
            else:
                # Before the next window (a >= k), or inside one (a < k < b: no bytes, but paced all the same).
                n = min(per_chunk, (a if a > k else min(b, end)) - k)
                _, data = sim.stream(n)
                k += n
                if not wait_due(k - 1):
                    break
                send(data)
            if a < k == b < end:
                w += 1
                if not wait_due(b):
                    break
                log.info("link_restored", frame=b, device_s=b / rate)
                if on_reconnect is not None:
                    on_reconnect()
        if k < end and stop.is_set():
            stats.stopped = True
    finally:
        pacer.finish(k - k0)
    _log_end(stats)
    return stats


def _log_start(sim: Simulator, k0: int, end: int, speed: float, per_chunk: int, disconnects: int) -> None:
    log.info(
        "serve_start",
        profile=sim.profile.name,
        rate_hz=sim.rate_hz,
        first_frame=k0,
        frames=max(0, end - k0),
        speed=speed,
        frames_per_chunk=per_chunk,
        disconnects=disconnects,
    )


def _log_end(stats: ServeStats) -> None:
    log.info(
        "serve_end",
        frames=stats.frames,
        bytes=stats.bytes,
        wall_s=round(stats.wall_s, 3),
        cpu_percent=round(stats.cpu_percent, 2),
        late_writes=stats.late_writes,
        stopped=stats.stopped,
    )


# -- a pty behind a stable symlink --------------------------------------------------------------


def check_link_path(link: str | os.PathLike[str]) -> None:
    """Refuse a link path that is in the way (``OutputFileError``, exit 73, one line): the path may be missing
    or a stale symlink, whose target is gone (a run that ended without removing its link: replaced).  A regular
    file, a directory or anything else, and a symlink to something that exists (another simulator's pty, a
    device, a file) are not ours to replace."""
    in_the_way = None
    try:
        st = os.lstat(link)
    except FileNotFoundError:
        return
    except OSError as exc:
        raise OutputFileError(f"--link {link}: {exc.strerror or exc}") from None
    if stat.S_ISLNK(st.st_mode):
        target = os.readlink(link)
        if os.path.exists(link):
            in_the_way = f"a symlink to {target}, which exists (another simulator's pty?)"
    elif stat.S_ISDIR(st.st_mode):
        in_the_way = "a directory"
    elif stat.S_ISREG(st.st_mode):
        in_the_way = "a regular file"
    else:
        in_the_way = "not a symlink"
    if in_the_way is not None:
        raise OutputFileError(
            f"--link {link}: the path is {in_the_way}, not a link of ours; "
            "remove it or give another --link PATH (nothing was replaced)"
        )


def _unread_bytes(fd: int) -> int:
    """Bytes waiting in a tty's input queue (``FIONREAD``)."""
    return struct.unpack("i", fcntl.ioctl(fd, termios.FIONREAD, b"\0\0\0\0"))[0]


class PtyServer:
    """A raw pty for the simulated instrument, reachable through the stable symlink ``link`` (None, the default:
    no symlink, the pty's own path only).  A path in the link's way (anything but nothing or a stale symlink,
    ``check_link_path``) is a one-line ``OutputFileError``.

    ``write`` never waits longer than ``write_timeout_s``: bytes the pty does not accept in time
    (nobody reading, or a reader far behind) are lost, as on a real UART, and counted.
    ``cut()`` unplugs the pty and removes the symlink; ``reconnect()`` makes a new pty and points
    the symlink at it.  ``close()`` unplugs and removes the symlink (if it is still ours).
    """

    def __init__(self, link: str | os.PathLike[str] | None = None, *, write_timeout_s: float = 0.01) -> None:
        self.link = Path(link) if link is not None else None
        self.write_timeout_s = write_timeout_s
        self.dropped_bytes = 0
        self.dropped_writes = 0
        self.ptys_made = 0
        self._dropping = False
        self._check_link()
        self.pty: PtyPair | None = None
        self._new_pty()

    # -- the symlink ------------------------------------------------------------------------

    def _check_link(self) -> None:
        if self.link is not None:
            check_link_path(self.link)

    def _point_link(self, target: str) -> None:
        """Make ``link`` point at ``target`` atomically (readers never see it half made); no link: nothing."""
        if self.link is None:
            return
        self._check_link()
        tmp = self.link.with_name(f".{self.link.name}.{os.getpid()}.tmp")
        try:
            tmp.unlink(missing_ok=True)
            os.symlink(target, tmp)
            os.replace(tmp, self.link)
        except OSError as exc:
            tmp.unlink(missing_ok=True)
            raise OutputFileError(f"--link {self.link}: cannot make the symlink: {exc.strerror or exc}") from None

    def _remove_link(self) -> None:
        """Remove the symlink if it still points at our pty (another server may have taken the name)."""
        if self.pty is None or self.link is None:
            return
        try:
            if os.readlink(self.link) == self.pty.slave_path:
                self.link.unlink()
        except OSError:
            pass

    # -- the pty ----------------------------------------------------------------------------

    def _new_pty(self) -> None:
        try:
            self.pty = PtyPair()
        except OSError as exc:
            raise DeviceError(f"cannot make a pty: {exc.strerror or exc}") from None
        self.ptys_made += 1
        try:
            self._point_link(self.pty.slave_path)
        except BaseException:
            self.pty.close()
            self.pty = None
            raise
        log.info("pty_ready", slave=self.pty.slave_path, **({"link": str(self.link)} if self.link is not None else {}))

    @property
    def slave_path(self) -> str | None:
        """The current pty's slave path (None inside a disconnect window)."""
        return self.pty.slave_path if self.pty is not None else None

    def write(self, data: bytes) -> None:
        if self.pty is None:  # inside a disconnect window: the bytes go nowhere
            self.dropped_bytes += len(data)
            self.dropped_writes += 1
            return
        try:
            self.pty.write(data, timeout_s=self.write_timeout_s)
        except TimeoutError:
            # A real UART does not wait for its receiver.  PtyPair.write does not say how much of the
            # chunk went in before the timeout, so the whole chunk counts as dropped.
            self.dropped_bytes += len(data)
            self.dropped_writes += 1
            if not self._dropping:  # info: a server waiting for its reader is normal; the summary counts drops
                log.info("pty_full", slave=self.pty.slave_path, detail="no reader, or a reader far behind: dropping")
            self._dropping = True
        else:
            self._dropping = False

    def cut(self) -> None:
        """Pull the cable: the symlink disappears (as udev's would) and readers get EIO."""
        if self.pty is None:
            return
        self._remove_link()
        self.pty.close()
        log.info("pty_unplugged", slave=self.pty.slave_path)
        self.pty = None

    def reconnect(self) -> None:
        """Plug a new cable: a new pty, the symlink pointing at it."""
        if self.pty is None:
            self._new_pty()

    def drain(self, timeout_s: float = DRAIN_TIMEOUT_S, stop: threading.Event | None = None) -> bool:
        """Wait (up to ``timeout_s``, or until ``stop``) until a reader has taken every byte; True if it has."""
        if self.pty is None:
            return True
        stop = stop if stop is not None else threading.Event()
        deadline = time.monotonic() + timeout_s
        empty_in_a_row = 0
        while True:
            try:
                empty_in_a_row = empty_in_a_row + 1 if _unread_bytes(self.pty.slave_fd) == 0 else 0
            except OSError:
                return False
            if empty_in_a_row >= 2:  # twice, so bytes still on their way into the queue are seen
                return True
            left = deadline - time.monotonic()
            if left <= 0 or stop.wait(min(0.01, left)):
                return False

    def close(self) -> None:
        """Unplug and remove the symlink (if it still points at our pty); safe to call twice."""
        if self.pty is not None:
            self._remove_link()
            self.pty.close()
            self.pty = None

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


def serve_pty(
    sim: Simulator,
    *,
    link: str | os.PathLike[str] | None = None,
    duration_s: float | None = None,
    stop: threading.Event | None = None,
    speed: float = 1.0,
    chunk_s: float = 0.02,
    write_timeout_s: float | None = None,
    drain_timeout_s: float = DRAIN_TIMEOUT_S,
    on_ready: Callable[[PtyServer], Any] | None = None,
    warn_behind: bool = True,
) -> ServeStats:
    """Serve ``sim`` on a new raw pty, behind the symlink ``link`` if given (None, the default: no symlink).

    ``on_ready(server)`` is called once the pty and the symlink exist, before the first byte
    (``server.slave_path``, ``server.link``).  Disconnect windows unplug the pty and bring up a new
    one after the window.  At the end the reader gets up to ``drain_timeout_s`` to take the last
    bytes, then the pty is unplugged and the symlink removed (also on an exception or a stop).
    ``write_timeout_s`` defaults to half a chunk's wall time.  ``warn_behind``: ``serve``'s.
    """
    if not (math.isfinite(speed) and speed > 0):
        raise ValueError(f"speed must be a finite number > 0, got {speed!r}")
    if write_timeout_s is None:
        write_timeout_s = 0.5 * chunk_s / speed
    stop = stop if stop is not None else threading.Event()
    with PtyServer(link, write_timeout_s=write_timeout_s) as server:
        if on_ready is not None:
            on_ready(server)
        stats = serve(
            sim,
            server.write,
            duration_s=duration_s,
            stop=stop,
            speed=speed,
            chunk_s=chunk_s,
            on_cut=server.cut,
            on_reconnect=server.reconnect,
            warn_behind=warn_behind,
        )
        if not stop.is_set():
            server.drain(drain_timeout_s, stop)
    stats.dropped_bytes += server.dropped_bytes
    stats.dropped_writes += server.dropped_writes
    return stats


# -- a serial device --------------------------------------------------------------------------


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


def required_baud(sim: Simulator, speed: float = 1.0) -> int:
    """Line speed (8N1) the stream needs: the frames of its wire format (plus, protocol v1, one IDENTITY per
    device second)."""
    identity = IDENTITY_FRAME_LEN if sim.wire_format == "fog-v1" else 0
    bytes_per_s = (sim.rate_hz * sim.frame_len_bytes + identity) * speed
    return math.ceil(bytes_per_s * _BITS_PER_BYTE)


def serve_device(
    sim: Simulator,
    device: str,
    *,
    baudrate: int = DEFAULT_BAUDRATE,
    duration_s: float | None = None,
    stop: threading.Event | None = None,
    speed: float = 1.0,
    chunk_s: float = 0.02,
    write_timeout_s: float = 1.0,
    on_ready: Callable[[str], Any] | None = None,
) -> ServeStats:
    """Serve ``sim`` to a serial device path or pyserial URL at ``baudrate``.

    A port that cannot be opened or fails while writing is a one-line ``DeviceError``; a baud rate
    too slow for the stream is a ``UsageError``.  Disconnect windows send nothing (a device cannot
    be unplugged from here).  Bytes the port does not take within ``write_timeout_s`` are dropped
    and counted.
    """
    need = required_baud(sim, speed)
    if need > baudrate:
        raise UsageError(
            f"--baud {baudrate} is too slow for {sim.rate_hz} Hz"
            + (f" at speed {speed:g}" if speed != 1 else "")
            + f": the stream needs at least {need} baud (8N1)"
        )
    try:
        port = open_port(device, baudrate=baudrate, timeout_s=0)
    except (serial.SerialException, OSError, ValueError) as exc:
        raise DeviceError(f"cannot open {device}: {_one_line(exc)}") from None
    stats = ServeStats()
    try:
        port.write_timeout = write_timeout_s

        def write(data: bytes) -> None:
            try:
                port.write(data)
            except serial.SerialTimeoutException:
                stats.dropped_bytes += len(data)
                stats.dropped_writes += 1
            except (serial.SerialException, OSError) as exc:
                raise DeviceError(f"{device}: write failed: {_one_line(exc)}") from None

        if on_ready is not None:
            on_ready(device)
        result = serve(sim, write, duration_s=duration_s, stop=stop, speed=speed, chunk_s=chunk_s)
        if not result.stopped:
            try:
                port.flush()
            except (serial.SerialException, OSError, termios.error) as exc:
                raise DeviceError(f"{device}: flush failed: {_one_line(exc)}") from None
    finally:
        with suppress(serial.SerialException, OSError, termios.error):
            port.close()
    result.dropped_bytes += stats.dropped_bytes
    result.dropped_writes += stats.dropped_writes
    return result


# -- the command line ---------------------------------------------------------------------------


class ServeProgress:
    """A progress line while serving, on a terminal only: device time served of the total, and the bytes a
    pty dropped because nobody read them (a reader that never came, or one far behind)."""

    def __init__(
        self, sim: Simulator, speed: float, duration_s: float | None, every_s: float = 0.5, stream: Any = None
    ) -> None:
        self.display = Progress(stream)
        self.total_s = (sim.total_frames() - sim.next_frame) / sim.rate_hz
        if duration_s is not None:
            self.total_s = min(self.total_s, duration_s)
        self.speed = speed
        self.every_s = every_s
        self._done = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self, server: PtyServer | None) -> None:
        if not self.display.enabled:
            return
        started = time.monotonic()

        def show() -> None:
            while not self._done.wait(self.every_s):
                served_s = min(self.total_s, (time.monotonic() - started) * self.speed)
                dropped = server.dropped_bytes if server is not None else 0
                self.display.show(
                    f"served {served_s:,.0f} / {self.total_s:,.0f} s of device time"
                    + (f"; {dropped:,} bytes dropped (is anything reading?)" if dropped else ""),
                    force=True,
                )

        self._thread = threading.Thread(target=show, name="serve-progress", daemon=True)
        self._thread.start()

    def __enter__(self) -> ServeProgress:
        return self

    def __exit__(self, *exc: object) -> None:
        self._done.set()
        if self._thread is not None:
            self._thread.join()
        self.display.clear()


def serve_cli(sim: Simulator, args: Any) -> int:
    """``fog-driver simulate --serve pty|DEVICE``: a readiness line, the stream, a summary line.

    The readiness line (stdout, flushed) is ``serving <profile> at <rate> Hz on <path> (link <link>)``
    for a pty and ``serving <profile> at <rate> Hz on <device> at <baud> baud`` for a device.  The pty's link is
    ``--link PATH`` (default ``DEFAULT_LINK``); a path in its way (``check_link_path``) is one line, exit 73, before
    any pty is made.  SIGINT and SIGTERM end the stream cleanly (a second one interrupts at once) and remove the
    link if it still points at the pty.

    ``--chamber-serve URL`` (``args.chamber_serve``): a simulated chamber served on the URL's protocol in the
    same process (``chamber_serve.serve_chamber``; the line ``serving the chamber on URL`` with the bound port
    comes first), whose air the instrument's temperatures follow (``chamber_serve.coupled_chamber``); the
    chamber's clock starts with the stream, at the same ``--speed``.
    """
    speed = getattr(args, "speed", None)
    speed = 1.0 if speed is None else float(speed)
    if not MIN_SPEED <= speed <= MAX_SPEED:
        raise UsageError(f"--speed {speed:g}: a stream runs {MIN_SPEED:g} to {MAX_SPEED:g} times as fast as real time")
    link = getattr(args, "link", None)
    if args.serve != "pty" and link is not None:
        raise UsageError("--link applies to --serve pty only")
    chamber_url = getattr(args, "chamber_serve", None)
    chamber_server = None
    start_chamber: Callable[[], None] = lambda: None  # noqa: E731
    if chamber_url is not None:
        from .chamber_serve import coupled_chamber, serve_chamber  # start-up time: only with --chamber-serve

        sim, chamber, clock, url = coupled_chamber(chamber_url, sim, speed)
        chamber_server = serve_chamber(url, chamber)
        start_chamber = clock.start
    try:
        return _serve_cli(sim, args, speed, link, chamber_server, start_chamber)
    finally:
        if chamber_server is not None:
            chamber_server.stop()


def _serve_cli(
    sim: Simulator,
    args: Any,
    speed: float,
    link: str | None,
    chamber_server: Any,
    start_chamber: Callable[[], None],
) -> int:
    stop = threading.Event()
    signals = stop_on_signals(stop) if threading.current_thread() is threading.main_thread() else nullcontext()
    where = f"{sim.profile.name} at {sim.rate_hz} Hz"
    progress = ServeProgress(sim, speed, args.duration)
    with signals, progress:
        if chamber_server is not None:
            print(f"serving the chamber on {chamber_server.url}", flush=True)
        if args.serve == "pty":

            def pty_ready(server: PtyServer) -> None:
                print(f"serving {where} on {server.slave_path} (link {server.link})", flush=True)
                start_chamber()
                progress.start(server)

            link = link if link is not None else DEFAULT_LINK
            stats = serve_pty(sim, link=link, duration_s=args.duration, stop=stop, speed=speed, on_ready=pty_ready)
        else:

            def device_ready(device: str) -> None:
                print(f"serving {where} on {device} at {args.baud} baud", flush=True)
                start_chamber()
                progress.start(None)

            stats = serve_device(
                sim,
                args.serve,
                baudrate=args.baud,
                duration_s=args.duration,
                stop=stop,
                speed=speed,
                on_ready=device_ready,
            )
    cpu_pct = 100.0 * stats.process_cpu_s / stats.wall_s if stats.wall_s > 0 else 0.0
    print(
        f"{'stopped after' if stats.stopped else 'served'} {stats.frames:,} frames "
        f"({stats.frames / sim.rate_hz:.1f} s of device time), {stats.bytes:,} bytes in {stats.wall_s:.1f} s; "
        f"CPU {cpu_pct:.1f} % of one core; {stats.late_writes} late writes, {stats.dropped_bytes:,} bytes dropped, "
        f"{stats.cuts} disconnects",
        flush=True,
    )
    return 0
