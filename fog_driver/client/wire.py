"""The client library's lowest layer: the daemon's NDJSON lines, its address and its token.

One place for what every client of ``fog-driver run`` needs (``Client``, ``AsyncClient``, ``fog-driver ctl``): the
address (``parse_address``, ``format_address``, the default ``127.0.0.1:2948``), the token (``FOG_DRIVER_TOKEN`` or a
token file, never a command-line argument: every user's ``ps`` shows those), the connection with its greeting
(``Connection.open``: a daemon that cannot be reached, or a peer that closes or says nothing before
the ``VERSION`` line, is one ``DeviceError`` line, exit 69, at once), the command lines
(``command_line``), and the defensive line reading (``LineReader``, ``parse_line``: a line is at most
64 KiB, anything that is not a JSON object with a string ``"class"`` is skipped and counted).
"""

from __future__ import annotations

import contextlib
import json
import os
import select
import socket
import time
from collections import deque
from pathlib import Path
from typing import Any

from ..errors import DeviceError, InputFileError, UsageError
from .address import DEFAULT_HOST, DEFAULT_PORT, format_address, parse_host_port
from .ndjson import LineBuffer

__all__ = [
    "DEFAULT_HOST",
    "DEFAULT_PORT",
    "MAX_LINE_BYTES",
    "MAX_TOKEN_BYTES",
    "TOKEN_ENV",
    "Connection",
    "LineReader",
    "command_line",
    "format_address",
    "parse_address",
    "parse_line",
    "read_token",
]

MAX_LINE_BYTES = 64 * 1024  # a protocol line longer than this (without its newline) is skipped
#: The environment variable clients read a daemon's token from (never a command-line argument: those
#: show in every user's process list).
TOKEN_ENV = "FOG_DRIVER_TOKEN"
#: A token file larger than this is refused (a token is a line of text, not a document).
MAX_TOKEN_BYTES = 4096
#: How long ``Connection.open`` waits for the daemon's VERSION greeting by default.
GREETING_TIMEOUT_S = 5.0
_RECV_BYTES = 65536


def parse_line(line: bytes) -> dict[str, Any] | None:
    """One protocol line -> its JSON object, or ``None`` when it is not a usable protocol object.

    Surrounding whitespace (the newline, a ``\\r``) is ignored.  ``None`` for: an empty line,
    a line over ``MAX_LINE_BYTES``, bytes that are not UTF-8, text that is not JSON, JSON that
    is not an object, and an object without a string ``"class"``.
    """
    if len(line) > MAX_LINE_BYTES + 2:  # room for "\r\n"
        return None
    line = line.strip()
    if not line or len(line) > MAX_LINE_BYTES:
        return None
    try:
        obj = json.loads(line.decode("utf-8"))
    except (UnicodeDecodeError, ValueError, RecursionError):
        return None
    if not isinstance(obj, dict) or not isinstance(obj.get("class"), str):
        return None
    return obj


class LineReader:
    """Splits a byte stream into lines of at most ``max_line`` bytes (plus a ``\\r``); longer ones are dropped and
    counted (``oversized``): ``ndjson.LineBuffer``'s policy, with the client's limit."""

    def __init__(self, max_line: int = MAX_LINE_BYTES) -> None:
        self.max_line = max_line
        self.oversized = 0
        self._buffer = LineBuffer(max_line + 1)  # room for a "\r" before the newline

    def feed(self, data: bytes) -> list[bytes]:
        lines: list[bytes] = []
        for item in self._buffer.feed(data):
            if isinstance(item, bytes):
                lines.append(item)
            else:  # OVERLONG
                self.oversized += 1
        return lines


def parse_address(
    text: str | None, *, default_host: str = DEFAULT_HOST, default_port: int = DEFAULT_PORT
) -> tuple[str, int]:
    """``HOST:PORT``, ``HOST``, ``:PORT``, ``PORT`` or ``[IPV6]:PORT`` -> ``(host, port)``; ``UsageError`` if bad."""
    try:
        return parse_host_port(text, default_host=default_host, default_port=default_port, allow_zero=False)
    except ValueError as exc:
        raise UsageError(str(exc)) from None


def read_token(token_file: str | None = None) -> str | None:
    """The daemon's client token: the first line of ``token_file`` when given, else ``$FOG_DRIVER_TOKEN``
    (None when neither is set).  A token file that is missing, unreadable, larger than ``MAX_TOKEN_BYTES``,
    not UTF-8 or empty is an ``InputFileError`` (exit 65)."""
    if token_file is None:
        return os.environ.get(TOKEN_ENV) or None
    path = Path(token_file)
    try:
        with path.open("rb") as f:
            data = f.read(MAX_TOKEN_BYTES + 1)
    except OSError as exc:
        raise InputFileError(f"{path}: cannot read the token file: {exc.strerror or exc}") from None
    if len(data) > MAX_TOKEN_BYTES:
        raise InputFileError(f"{path}: not a token file (over {MAX_TOKEN_BYTES} bytes)")
    try:
        lines = data.decode("utf-8").splitlines()
    except UnicodeDecodeError:
        raise InputFileError(f"{path}: not a token file (not UTF-8 text)") from None
    token = lines[0].strip() if lines else ""
    if not token:
        raise InputFileError(f"{path}: the token file is empty")
    return token


def command_line(name: str, args: dict[str, Any] | None = None) -> bytes:
    """One command line: ``?NAME;`` or ``?NAME={compact json};`` with its newline (``name``: upper-case letters)."""
    if not (name.isascii() and name.isalpha() and name.isupper()):
        raise ValueError(f"not a command name: {name!r}")
    if args is None:
        return f"?{name};\n".encode("ascii")
    return f"?{name}=".encode("ascii") + json.dumps(args, separators=(",", ":")).encode("utf-8") + b";\n"


def _reason(exc: OSError) -> str:
    if isinstance(exc, TimeoutError):  # socket.timeout is TimeoutError
        return "timed out"
    return exc.strerror or str(exc) or type(exc).__name__


class Connection:
    """A connection to a daemon: the socket, its line reader, and the protocol objects read but not yet taken.

    ``open`` connects and waits for the VERSION greeting; ``read(timeout_s)`` returns the next protocol
    line as ``(raw_bytes, object)`` (``None`` when nothing came within ``timeout_s``; ``ConnectionClosed``
    on EOF or a lost connection).  Malformed lines are skipped and counted in ``malformed``.
    """

    def __init__(self, sock: socket.socket, address: str) -> None:
        self.sock = sock
        self.address = address
        self.reader = LineReader()
        self.malformed = 0
        self.version: dict[str, Any] | None = None
        self._pending: deque[tuple[bytes, dict[str, Any]]] = deque()

    @classmethod
    def open(cls, host: str, port: int, *, timeout_s: float = GREETING_TIMEOUT_S) -> Connection:
        """Connect and read up to the daemon's VERSION line (kept, with anything before it, for ``read``).

        ``DeviceError`` (one line, exit 69) when the connection fails, or when the peer closes it or sends
        no VERSION within ``timeout_s``: ``could not connect to HOST:PORT: <reason> (is `fog-driver run`
        running?)``."""
        address = format_address(host, port)
        hint = "(is `fog-driver run` running?)"
        try:
            sock = socket.create_connection((host, port), timeout=timeout_s)
        except OSError as exc:
            raise DeviceError(f"could not connect to {address}: {_reason(exc)} {hint}") from None
        conn = cls(sock, address)
        deadline = time.monotonic() + timeout_s
        greeting: list[tuple[bytes, dict[str, Any]]] = []
        try:
            while conn.version is None:
                item = conn.read(max(0.0, deadline - time.monotonic()))
                if item is None:
                    raise DeviceError(
                        f"could not connect to {address}: no VERSION greeting within {timeout_s:g} s "
                        f"(not a fog-driver daemon?)"
                    )
                greeting.append(item)
                if item[1]["class"] == "VERSION":
                    conn.version = item[1]
                elif item[1]["class"] == "ERROR":  # refused at once: too many clients
                    raise DeviceError(
                        f"could not connect to {address}: the daemon refused the connection: "
                        f"{_text(item[1].get('message'))}"
                    )
        except ConnectionClosed as exc:
            conn.close()
            raise DeviceError(
                f"could not connect to {address}: {exc.reason} before the VERSION greeting {hint}"
            ) from None
        except BaseException:
            conn.close()
            raise
        conn._pending.extendleft(reversed(greeting))  # ahead of what was read with it, in order
        return conn

    def send(self, data: bytes) -> None:
        """Send command lines; ``ConnectionClosed`` when the daemon has gone."""
        try:
            self.sock.settimeout(GREETING_TIMEOUT_S)
            self.sock.sendall(data)
        except OSError as exc:
            raise ConnectionClosed(_reason(exc)) from None

    def fileno(self) -> int:
        return self.sock.fileno()

    def has_pending(self) -> bool:
        """Objects already read from the socket and not taken yet (``read(0)`` returns one without waiting)."""
        return bool(self._pending)

    def read(self, timeout_s: float | None) -> tuple[bytes, dict[str, Any]] | None:
        """The next protocol line and its object, waiting at most ``timeout_s`` (None: without limit)."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while not self._pending:
            wait = None if deadline is None else max(0.0, deadline - time.monotonic())
            if not select.select([self.sock], [], [], wait)[0]:
                return None
            self.receive()
        return self._pending.popleft()

    def receive(self) -> None:
        """Read what the socket holds now (call when it is readable) into the pending objects."""
        try:
            self.sock.setblocking(False)
            data = self.sock.recv(_RECV_BYTES)
        except BlockingIOError:
            return
        except OSError as exc:
            raise ConnectionClosed(f"lost the connection: {_reason(exc)}") from None
        if not data:
            raise ConnectionClosed("the daemon closed the connection")
        for line in self.reader.feed(data):
            if not line.strip():
                continue  # an empty line (a keep-alive) is not an error
            obj = parse_line(line)
            if obj is None:
                self.malformed += 1
            else:
                self._pending.append((line.rstrip(b"\r"), obj))

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.sock.close()


class ConnectionClosed(Exception):
    """The daemon closed or lost the connection; ``reason`` says which, in words."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


def _text(value: Any) -> str:
    """A server's message as one printable line (at most 200 characters)."""
    text = value if isinstance(value, str) else json.dumps(value, default=str)
    text = "".join(ch if ch.isprintable() else "?" for ch in text)
    return text if len(text) <= 200 else text[:197] + "..."
