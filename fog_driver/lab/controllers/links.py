"""The controllers' links: a TCP socket or a serial line, as a byte stream with timeouts.

``StreamLink`` sends bytes and reads exact counts or up to a terminator, every read bounded in bytes and time.
Any failure of the link (refused, reset, a timeout, the peer closing, a serial port gone) is a one-line
``ControllerUnreachable``; what the bytes mean is the codecs' business (``codecs``).
"""

from __future__ import annotations

import socket
import time

import serial

from .base import ControllerUnreachable

#: The most a single reply may hold (the longest a codec expects is a Modbus frame, 256 bytes).
MAX_REPLY_BYTES = 4096


class StreamLink:
    """A byte stream to ``host:port`` (TCP) or to the serial ``device`` at ``baud``; ``where`` names it in
    messages.  Not connected until ``connect()``; ``close()`` is idempotent."""

    def __init__(
        self,
        *,
        where: str,
        host: str | None = None,
        port: int | None = None,
        device: str | None = None,
        baud: int = 9600,
        timeout_s: float = 2.0,
    ) -> None:
        if (host is None) == (device is None):
            raise ValueError("a link is to a host or to a serial device")
        self.where = where
        self.host, self.port, self.device, self.baud = host, port, device, baud
        self.timeout_s = timeout_s
        self._sock: socket.socket | None = None
        self._serial: serial.Serial | None = None
        self._buffer = bytearray()

    @property
    def connected(self) -> bool:
        return self._sock is not None or self._serial is not None

    def connect(self) -> None:
        self.close()
        try:
            if self.host is not None:
                self._sock = socket.create_connection((self.host, self.port or 0), timeout=self.timeout_s)
                self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            else:
                self._serial = serial.Serial(self.device, self.baud, timeout=self.timeout_s, exclusive=True)
        except (OSError, serial.SerialException, ValueError) as exc:
            self.close()
            raise ControllerUnreachable(f"{self.where}: cannot connect: {_reason(exc)}") from None

    def close(self) -> None:
        sock, ser = self._sock, self._serial
        self._sock = self._serial = None
        self._buffer.clear()
        try:
            if sock is not None:
                sock.close()
            if ser is not None:
                ser.close()
        except (OSError, serial.SerialException):
            pass

    def discard_input(self) -> None:
        """Drop whatever arrived unasked (a late reply to a request that timed out)."""
        self._buffer.clear()
        try:
            if self._sock is not None:
                self._sock.setblocking(False)
                try:
                    while self._sock.recv(MAX_REPLY_BYTES):
                        pass
                except (BlockingIOError, InterruptedError):
                    pass
                finally:
                    self._sock.settimeout(self.timeout_s)
            elif self._serial is not None:
                self._serial.reset_input_buffer()
        except (OSError, serial.SerialException) as exc:
            self._lost(exc)

    def send(self, data: bytes) -> None:
        try:
            if self._sock is not None:
                self._sock.sendall(data)
            elif self._serial is not None:
                self._serial.write(data)
                self._serial.flush()
            else:
                raise ControllerUnreachable(f"{self.where}: not connected")
        except (OSError, serial.SerialException) as exc:
            self._lost(exc)

    def _fill(self, deadline: float) -> None:
        """Read what is there (at least one byte) into the buffer before ``deadline``; else the link is lost."""
        left = deadline - time.monotonic()
        if left <= 0:
            self._lost(TimeoutError("no reply"))
        try:
            if self._sock is not None:
                self._sock.settimeout(left)
                chunk = self._sock.recv(MAX_REPLY_BYTES)
                if not chunk:
                    self._lost(ConnectionResetError("the controller closed the connection"))
            elif self._serial is not None:
                self._serial.timeout = left
                chunk = self._serial.read(max(1, self._serial.in_waiting))
                if not chunk:
                    self._lost(TimeoutError("no reply"))
            else:
                raise ControllerUnreachable(f"{self.where}: not connected")
        except (OSError, serial.SerialException) as exc:  # socket.timeout is an OSError
            self._lost(exc)
        self._buffer += chunk

    def read_exact(self, n: int) -> bytes:
        """Exactly ``n`` bytes (``n`` <= ``MAX_REPLY_BYTES``), within the link's timeout."""
        deadline = time.monotonic() + self.timeout_s
        while len(self._buffer) < n:
            self._fill(deadline)
        out = bytes(self._buffer[:n])
        del self._buffer[:n]
        return out

    def read_until(self, terminator: bytes, max_bytes: int = MAX_REPLY_BYTES) -> bytes:
        """The bytes up to and including ``terminator``, within the link's timeout; a reply longer than
        ``max_bytes`` without one is garbage (``ControllerUnreachable``, the link is reset)."""
        deadline = time.monotonic() + self.timeout_s
        while True:
            at = self._buffer.find(terminator)
            if at >= 0:
                end = at + len(terminator)
                out = bytes(self._buffer[:end])
                del self._buffer[:end]
                return out
            if len(self._buffer) > max_bytes:
                self._lost(ValueError(f"a reply of more than {max_bytes} bytes without its end"))
            self._fill(deadline)

    def _lost(self, exc: BaseException) -> None:
        self.close()
        raise ControllerUnreachable(f"{self.where}: link lost: {_reason(exc)}") from None


def _reason(exc: BaseException) -> str:
    if isinstance(exc, OSError) and exc.strerror:
        return exc.strerror.lower() if not isinstance(exc, TimeoutError) else "no reply (timed out)"
    if isinstance(exc, TimeoutError):
        return "no reply (timed out)"
    return " ".join(str(exc).split()) or type(exc).__name__
