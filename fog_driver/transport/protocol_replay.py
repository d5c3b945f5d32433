"""pyserial URL handler ``replay://PATH?rate=HZ&unplug=1``: a capture file served as a read-only port.

A capture is the raw byte stream exactly as read from a port (PROTOCOL.md,
"Captures"), so replaying it through an object that behaves like a serial port
lets the whole driver run on recorded data with no special case: the driver
opens ``replay://capture.bin`` where it would open ``/dev/ttyUSB0``.

pyserial finds this module because ``fog_driver.transport`` (the package
``__init__``) appends itself to ``serial.protocol_handler_packages``; the module
name ``protocol_replay`` is what ``serial.serial_for_url`` looks for when the
scheme is ``replay``.  Modelled on pyserial's ``serial/urlhandler/protocol_loop.py``.

URL
    ``replay:///abs/path/x.bin`` (absolute) or ``replay://x.bin`` /
    ``replay://dir/x.bin`` (relative to the current directory); percent-escapes
    in the path are decoded.

``rate=HZ`` (optional, > 0, finite)
    Pace the replay per SAMPLE frame: the bytes up to and including the end of
    the k-th SAMPLE frame (k = 0, 1, ...) become readable at ``k / HZ`` seconds
    after ``open()`` on the monotonic clock.  Whatever lies between two SAMPLE
    frames (IDENTITY frames, unknown frames, garbage) travels with the next
    SAMPLE; bytes after the last SAMPLE frame travel with the last one; a
    capture with no SAMPLE frame at all is readable at once.  Without ``rate``
    the whole file is readable at once.

``unplug=1`` (optional, ``0``/``1``)
    Once every byte has been read, behave like an unplugged USB adapter:
    ``read`` raises ``SerialException("device reports readiness to read but
    returned no data ...")`` (pyserial's own message for that case) and
    ``in_waiting`` raises ``OSError(EIO)``.  Without it the port goes idle at the
    end: ``read`` returns ``b''`` after its timeout, forever.

Port behaviour
    * ``read(size)`` returns up to ``size`` readable bytes as soon as at least
      one is readable, waiting up to ``timeout`` for the first one
      (``timeout=None`` blocks, ``timeout=0`` never waits).  Note that a real
      POSIX port keeps collecting until ``size`` bytes or the timeout; with the
      driver's ``read(in_waiting or 1)`` idiom both give the same chunks.
    * ``write`` raises ``SerialException``: a replay is read-only, and a driver
      that writes to it has a bug worth hearing about.
    * ``reset_input_buffer`` is a no-op: pyserial calls it when a real port
      opens, and a replay must not drop the start of its capture.
    * The serial settings (baud rate, parity, ...) are accepted and ignored,
      apart from a sanity check of the baud rate like ``loop://``.
"""

from __future__ import annotations

import errno
import math
import mmap
import numbers
import os
import stat
import threading
import time
import urllib.parse
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from serial.serialutil import PortNotOpenError, SerialBase, SerialException

from fog_driver.protocol import SAMPLE_FRAME_LEN, decode_bytes, iter_decode_file

SCHEME = "replay"
URL_FORM = "replay://PATH[?rate=HZ][&unplug=0|1]"

#: pyserial's message when a disconnected device is readable but yields nothing.
UNPLUGGED_MESSAGE = (
    "device reports readiness to read but returned no data (device disconnected or multiple access on port?)"
)


@dataclass(frozen=True, slots=True)
class ReplayOptions:
    """What a ``replay://`` URL asks for."""

    path: Path  #: the capture file, as given (relative paths resolve against the cwd)
    rate_hz: float | None  #: SAMPLE frames per second, or None for "all at once"
    unplug: bool  #: raise like an unplugged adapter at the end instead of idling


def parse_replay_url(url: str) -> ReplayOptions:
    """Parse a ``replay://`` URL; raise ``SerialException`` naming the problem when it is malformed.

    The file itself is not checked here (see ``Serial.from_url``), so parsing
    stays a pure function.
    """
    parts = urllib.parse.urlsplit(url)
    if parts.scheme.lower() != SCHEME:
        raise SerialException(f"expected a URL of the form {URL_FORM}, got scheme {parts.scheme!r} in {url!r}")
    path_text = urllib.parse.unquote(parts.netloc + parts.path)
    if not path_text:
        raise SerialException(f"no capture file in {url!r}; expected {URL_FORM}")
    rate_hz: float | None = None
    unplug = False
    try:
        query = urllib.parse.parse_qs(parts.query, keep_blank_values=True, strict_parsing=bool(parts.query))
    except ValueError as exc:
        raise SerialException(f"malformed query in {url!r}: {exc}; expected {URL_FORM}") from None
    for name, values in query.items():
        if len(values) != 1:
            raise SerialException(f"parameter {name!r} given {len(values)} times in {url!r}")
        value = values[0]
        if name == "rate":
            try:
                rate_hz = float(value)
            except ValueError:
                rate_hz = math.nan
            if not (math.isfinite(rate_hz) and rate_hz > 0):
                raise SerialException(f"bad rate {value!r} in {url!r}: expected a finite number of Hz > 0")
        elif name == "unplug":
            if value not in ("0", "1"):
                raise SerialException(f"bad unplug {value!r} in {url!r}: expected 0 or 1")
            unplug = value == "1"
        else:
            raise SerialException(f"unknown parameter {name!r} in {url!r}; expected {URL_FORM}")
    return ReplayOptions(path=Path(path_text), rate_hz=rate_hz, unplug=unplug)


def replay_schedule(capture: bytes | str | Path) -> np.ndarray:
    """Byte count readable once SAMPLE frame k is released, for k = 0 .. n-1 (int64, non-decreasing).

    Entry k is the end of the k-th SAMPLE frame, except the last entry, which is
    the capture's length so the tail after the last SAMPLE goes out with it.  A
    capture without SAMPLE frames gives ``[length]``: everything at once.
    ``capture`` is the bytes or a file path; a file is decoded block by block, so
    memory stays bounded by the schedule itself (8 bytes per frame).
    """
    if isinstance(capture, (bytes, bytearray, memoryview)):
        parts = [decode_bytes(capture, final=True)]
    else:
        parts = list(iter_decode_file(capture))
    ends = np.concatenate([p.samples.offset for p in parts]) + SAMPLE_FRAME_LEN
    length = parts[-1].counters.bytes_in
    if ends.size == 0:
        return np.array([length], dtype=np.int64)
    ends[-1] = length
    return ends


def _map_file(path: Path) -> bytes | mmap.mmap:
    """The file's bytes, memory-mapped read-only (the OS pages a long capture in as it is read).  A path that is not a
    regular file (a FIFO, a device, a directory) is an ``OSError``: opened without blocking, never waited on (the
    rule of ``files.bounded``, a layer this one cannot import)."""
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        os.close(fd)
        raise OSError(errno.EINVAL, "not a regular file")
    with os.fdopen(fd, "rb") as f:
        if os.fstat(f.fileno()).st_size == 0:
            return b""
        return mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)


class Serial(SerialBase):
    """A capture file served as a read-only serial port (see the module docstring for the URL)."""

    def __init__(self, *args: object, **kwargs: object) -> None:
        self._cond = threading.Condition()
        self._data: bytes | mmap.mmap = b""
        self._schedule = np.array([0], dtype=np.int64)
        self._rate_hz: float | None = None
        self._unplug = False
        self._read_pos = 0
        self._t0_s = 0.0
        self._cancel_read = False
        self.options: ReplayOptions | None = None
        super().__init__(*args, **kwargs)

    # -- life cycle -------------------------------------------------------------------------

    def open(self) -> None:
        """Load the capture named by the URL and start its clock; ``SerialException`` if it cannot."""
        if self.is_open:
            raise SerialException("Port is already open.")
        if self._port is None:
            raise SerialException("Port must be configured before it can be used.")
        self.from_url(self._port)
        self._reconfigure_port()
        with self._cond:
            self._read_pos = 0
            self._cancel_read = False
            self._t0_s = time.monotonic()
            self.is_open = True
        self.reset_input_buffer()
        self.reset_output_buffer()

    def close(self) -> None:
        """Close the port; a ``read`` blocked in another thread returns ``b''``."""
        with self._cond:
            self.is_open = False
            if isinstance(self._data, mmap.mmap):
                self._data.close()
            self._data = b""
            self._cond.notify_all()
        # Like pyserial's POSIX ``Serial.close``, io.RawIOBase.close is not called, so the
        # object can be opened again.

    def from_url(self, url: str) -> None:
        """Apply the URL's options and load the capture (raises ``SerialException`` when unusable)."""
        options = parse_replay_url(url)
        try:
            data = _map_file(options.path)
            schedule = (
                replay_schedule(options.path) if options.rate_hz is not None else np.array([len(data)], dtype=np.int64)
            )
        except FileNotFoundError:
            raise SerialException(f"replay capture not found: {str(options.path)!r} (from {url!r})") from None
        except OSError as exc:
            raise SerialException(f"cannot read replay capture {str(options.path)!r} (from {url!r}): {exc}") from None
        with self._cond:
            self.options = options
            self._data = data
            self._schedule = schedule
            self._rate_hz = options.rate_hz
            self._unplug = options.unplug

    def _reconfigure_port(self) -> None:
        """Settings mean nothing to a replay; only reject a nonsensical baud rate like ``loop://`` does."""
        if not isinstance(self._baudrate, numbers.Integral) or not 0 < self._baudrate < 2**32:
            raise ValueError(f"invalid baudrate: {self._baudrate!r}")

    # -- pacing -----------------------------------------------------------------------------

    def _released_end(self, now_s: float) -> tuple[int, float | None]:
        """(bytes readable at ``now_s``, monotonic time of the next release or None if all released)."""
        schedule = self._schedule
        last = len(schedule) - 1
        if self._rate_hz is None:
            return int(schedule[last]), None
        k = int((now_s - self._t0_s) * self._rate_hz)
        if k >= last:
            return int(schedule[last]), None
        k = max(k, 0)
        return int(schedule[k]), self._t0_s + (k + 1) / self._rate_hz

    def _exhausted(self) -> bool:
        return self._read_pos >= len(self._data) and (
            self._rate_hz is None or self._released_end(time.monotonic())[1] is None
        )

    # -- reading ----------------------------------------------------------------------------

    @property
    def in_waiting(self) -> int:
        """Bytes readable now; ``OSError(EIO)`` once an ``unplug=1`` replay has been read to the end."""
        with self._cond:
            if not self.is_open:
                raise PortNotOpenError()
            if self._unplug and self._exhausted():
                raise OSError(errno.EIO, "Input/output error (replay unplugged)")
            return self._released_end(time.monotonic())[0] - self._read_pos

    def read(self, size: int = 1) -> bytes:
        """Up to ``size`` readable bytes, waiting up to ``timeout`` for the first one (see module doc)."""
        if size <= 0:
            if not self.is_open:
                raise PortNotOpenError()
            return b""
        timeout_s = self._timeout
        deadline_s = None if timeout_s is None else time.monotonic() + timeout_s
        with self._cond:
            if not self.is_open:
                raise PortNotOpenError()
            while True:
                if not self.is_open:
                    return b""
                if self._cancel_read:
                    self._cancel_read = False
                    return b""
                now_s = time.monotonic()
                end, next_release_s = self._released_end(now_s)
                if end > self._read_pos:
                    start = self._read_pos
                    self._read_pos = min(end, start + size)
                    return self._data[start : self._read_pos]
                if next_release_s is None and self._read_pos >= len(self._data) and self._unplug:
                    raise SerialException(UNPLUGGED_MESSAGE)
                if deadline_s is not None and now_s >= deadline_s:
                    return b""
                wake_s = deadline_s
                if next_release_s is not None and (wake_s is None or next_release_s < wake_s):
                    wake_s = next_release_s
                # The port's own timed wait (or a wait for close/cancel_read when there is no limit).
                self._cond.wait(None if wake_s is None else max(wake_s - now_s, 0.0))

    def cancel_read(self) -> None:
        """Make a pending (or the next) ``read`` return ``b''`` at once, like pyserial's POSIX ports."""
        with self._cond:
            self._cancel_read = True
            self._cond.notify_all()

    def reset_input_buffer(self) -> None:
        """No-op on purpose: pyserial calls it on open, and a replay must keep its first bytes."""
        if not self.is_open:
            raise PortNotOpenError()

    # -- writing and modem lines: a replay has none -----------------------------------------

    def write(self, data: bytes) -> int:
        """Always raises ``SerialException``: a replay is read-only."""
        if not self.is_open:
            raise PortNotOpenError()
        raise SerialException(f"{self._port!r} is a read-only replay; cannot write {len(data)} bytes")

    def reset_output_buffer(self) -> None:
        """Nothing is ever buffered for output."""
        if not self.is_open:
            raise PortNotOpenError()

    @property
    def out_waiting(self) -> int:
        return 0

    def _update_break_state(self) -> None:
        pass

    def _update_rts_state(self) -> None:
        pass

    def _update_dtr_state(self) -> None:
        pass

    @property
    def cts(self) -> bool:
        return True

    @property
    def dsr(self) -> bool:
        return True

    @property
    def ri(self) -> bool:
        return False

    @property
    def cd(self) -> bool:
        return True
