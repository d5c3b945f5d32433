"""``FakeKvhDevice``: a KVH DSP-1750 stand-in answering configuration-mode commands on a pty.

It sits on the master side of a ``fog_driver.transport.PtyPair`` (the driver opens the slave as its
port) and behaves as the KVH 1775 IMU technical manual describes the command interface (section 7,
https://www.easymanua.ls/kvh-industries/1775-imu/manual?p=57; see ``fog_driver.transport.setup``):

* a command ends at CR or LF (CR LF counts once); input is case-insensitive; nothing is echoed;
* normal mode streams Format A frames (every ``1 / rate_hz`` s when ``rate_hz`` > 0) and ignores every
  command but ``=CONFIG,1`` (answered ``CONFIG,1`` after the ``frames_before_config`` frames still on
  their way) and ``?BIT`` (a BIT frame);
* configuration mode stops the frames and answers everything: ``=KEY,VALUE`` for a known setting and an
  accepted value -> ``KEY,VALUE`` (upper case), ``?KEY`` -> ``KEY,VALUE``, anything else ->
  ``INVALID,<the text received>``; ``=CONFIG,0`` -> ``CONFIG,0``, then ``frames_after_config`` frames at
  once and the stream resumes.

Settings tracked: ``TEMPUNITS`` (C, F, C_100, F_100: the temperature word's unit, which the frames it
sends follow), ``ROTFMT`` (DELTA, RATE), ``ROTUNITS`` (DEG, RAD), ``DR`` (1..5000 Hz).  The defaults are
assumptions (the manual's default table was not read).  With ``silent=True`` it records what it receives
and never answers: a device that is off, or at another baud rate.

Everything received is kept in ``received`` (bytes, terminators included); each command handled is put
on ``commands`` (a queue, so a test waits for one without sleeping); everything sent is kept in ``sent``.
"""

from __future__ import annotations

import contextlib
import os
import queue
import select
import threading
import time
from types import TracebackType

from ..formats.kvh import encode_kvh_bit_frame, encode_kvh_frame
from ..transport.pty import PtyPair

__all__ = ["FakeKvhDevice"]

_CHOICES = {
    "TEMPUNITS": ("C", "F", "C_100", "F_100"),
    "ROTFMT": ("DELTA", "RATE"),
    "ROTUNITS": ("DEG", "RAD"),
}
_DEFAULTS = {"TEMPUNITS": "C", "ROTFMT": "DELTA", "ROTUNITS": "RAD", "DR": "1000"}
#: the raw temperature word per degree C, by TEMPUNITS (Fahrenheit words are converted from 25 degC)
_TEMP_WORD_25C = {"C": 25, "C_100": 2500, "F": 77, "F_100": 7700}


class FakeKvhDevice:
    """Answers KVH configuration commands on ``pair``'s master side from a thread (see the module docstring)."""

    def __init__(
        self,
        pair: PtyPair,
        *,
        rate_hz: float = 0.0,
        frames_before_config: int = 2,
        frames_after_config: int = 2,
        silent: bool = False,
    ) -> None:
        self.pair = pair
        self.rate_hz = rate_hz
        self.frames_before_config = frames_before_config
        self.frames_after_config = frames_after_config
        self.silent = silent
        self.settings: dict[str, str] = dict(_DEFAULTS)
        self.config_mode = False
        self.config_entries = 0  #: how many times configuration mode was entered
        self.received = bytearray()
        self.sent = bytearray()
        self.commands: queue.Queue[str] = queue.Queue()
        self._line = bytearray()
        self._seq = 0
        self._stop = threading.Event()
        self._wake_r, self._wake_w = os.pipe()
        self._thread = threading.Thread(target=self._run, name="fake-kvh", daemon=True)
        self._thread.start()

    def __enter__(self) -> FakeKvhDevice:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def close(self) -> None:
        """Stop the thread (within one select) and release the wake-up pipe; safe to call twice."""
        if not self._stop.is_set():
            self._stop.set()
            os.write(self._wake_w, b"x")
            self._thread.join(5.0)
            os.close(self._wake_r)
            os.close(self._wake_w)

    def unplug(self) -> None:
        """Stop answering and unplug the pty: the driver's reads fail as with a pulled USB adapter.

        The thread is stopped first: a pty master closed while another thread still waits on it in
        select() stays alive until that wait ends, so the slave would not see the hang-up.
        """
        self.close()
        self.pair.unplug()

    def frame(self) -> bytes:
        """The next Format A frame (at rest, 1 g on z), its temperature word in the current TEMPUNITS."""
        temp = _TEMP_WORD_25C[self.settings["TEMPUNITS"]]
        out = encode_kvh_frame("a", (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), seq=self._seq % 128, temp=temp)
        self._seq += 1
        return out

    # -- the device's thread -------------------------------------------------------------------------------

    def _send(self, data: bytes) -> None:
        self.sent += data
        self.pair.write(data)

    def _run(self) -> None:
        period_s = 1.0 / self.rate_hz if self.rate_hz > 0 else None
        next_frame = time.monotonic()
        while not self._stop.is_set():
            streaming = period_s is not None and not self.config_mode and not self.silent
            timeout = max(0.0, next_frame - time.monotonic()) if streaming else None
            try:
                readable, _, _ = select.select([self.pair.master_fd, self._wake_r], [], [], timeout)
            except (OSError, ValueError):  # the pty was unplugged under us
                return
            if self.pair.master_fd in readable:
                try:
                    data = os.read(self.pair.master_fd, 4096)
                except OSError:  # EIO while no slave is open: nothing to read
                    data = b""
                self._receive(data)
            if streaming and not self.config_mode and period_s is not None and time.monotonic() >= next_frame:
                self._write_quietly(self.frame())
                next_frame += period_s

    def _write_quietly(self, data: bytes) -> None:
        # unplugged or nobody reading: a real device would not notice either
        with contextlib.suppress(OSError, TimeoutError):
            self._send(data)

    def _receive(self, data: bytes) -> None:
        self.received += data
        for byte in data:
            if byte in (0x0D, 0x0A):
                if self._line:
                    self._handle(self._line.decode("ascii", "replace"))
                    self._line.clear()
            else:
                self._line.append(byte)

    def _handle(self, text: str) -> None:
        command = text.upper()
        if not self.silent:
            self._write_quietly(self._answer(text, command))
        self.commands.put(text)

    def _answer(self, text: str, command: str) -> bytes:
        """The bytes the device sends for one command line (empty: ignored)."""
        if not self.config_mode:
            if command == "=CONFIG,1":
                frames = b"".join(self.frame() for _ in range(self.frames_before_config))
                self.config_mode = True
                self.config_entries += 1
                return frames + b"CONFIG,1\r\n"
            if command in ("?BIT", "=BIT"):
                return encode_kvh_bit_frame(0xAA, bytes([0x7F] * 6))
            return b""  # normal mode ignores everything else
        if command in ("=CONFIG,0", "=CONFIG,1"):
            reply = command[1:].encode("ascii") + b"\r\n"
            if command == "=CONFIG,0":
                self.config_mode = False
                reply += b"".join(self.frame() for _ in range(self.frames_after_config))
            return reply
        key, _, value = command[1:].partition(",")
        if command.startswith("?") and key in self.settings and not value:
            return f"{key},{self.settings[key]}\r\n".encode("ascii")
        if command.startswith("=") and key in self.settings and self._accepts(key, value):
            self.settings[key] = value
            return f"{key},{value}\r\n".encode("ascii")
        return f"INVALID,{text}\r\n".encode("ascii", "replace")

    @staticmethod
    def _accepts(key: str, value: str) -> bool:
        if key == "DR":
            return value.isdigit() and 1 <= int(value) <= 5000
        return value in _CHOICES.get(key, ())
