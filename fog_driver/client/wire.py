"""The client library's lowest layer: the daemon's NDJSON lines, its address and its token.

One place for what every client of ``fog-driver run`` needs (``Client``, ``AsyncClient``, ``fog-driver ctl``): the
address (``parse_address``, ``format_address``, the default ``127.0.0.1:2948``), the token (``FOG_DRIVER_TOKEN`` or a
token file, never a command-line argument: every user's ``ps`` shows those), the command lines
(``command_line``), and the defensive line reading (``LineReader``, ``parse_line``: a line is at most
64 KiB, anything that is not a JSON object with a string ``"class"`` is skipped and counted).
"""

from __future__ import annotations

import json
import os
import stat
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from ..errors import InputFileError, UsageError
from ..ndjson import OVERLONG, LineBuffer, LineEvent
from .address import DEFAULT_HOST, DEFAULT_PORT, format_address, parse_host_port

__all__ = [
    "DEFAULT_HOST",
    "DEFAULT_PORT",
    "MAX_LINE_BYTES",
    "MAX_TOKEN_BYTES",
    "TOKEN_ENV",
    "LineReader",
    "command_line",
    "format_address",
    "parse_address",
    "parse_line",
    "read_token",
]

#: A protocol line longer than this (without its newline) is no protocol line: the clients raise
#: ``ProtocolError`` for it (``fog-driver watch`` skips and counts it).
MAX_LINE_BYTES = 64 * 1024
#: The environment variable clients read a daemon's token from (never a command-line argument: those
#: show in every user's process list).
TOKEN_ENV = "FOG_DRIVER_TOKEN"
#: A token file larger than this is refused (a token is a line of text, not a document).
MAX_TOKEN_BYTES = 4096
#: How long the clients wait to connect and for the daemon's VERSION greeting by default.
GREETING_TIMEOUT_S = 5.0


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

    @property
    def buffered_bytes(self) -> int:
        """Bytes held for the line being read: at most ``max_line + 1``."""
        return self._buffer.buffered_bytes

    def feed(self, data: bytes) -> list[bytes]:
        """The lines ``data`` completes, in order; over-long ones are left out (and counted)."""
        return [item for item in self.events(data) if isinstance(item, bytes)]

    def events(self, data: bytes) -> Iterator[bytes | LineEvent]:
        """The lines ``data`` completes and, in their place, ``OVERLONG`` for each over-long one (counted): as
        soon as it is known, at its newline or once the bytes buffered for it pass ``max_line + 1``."""
        for item in self._buffer.feed(data):
            if item is OVERLONG:
                self.oversized += 1
            yield item


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
    (None when neither is set).  A token file that is missing, unreadable, not a regular file (a FIFO, a
    directory: never waited on), larger than ``MAX_TOKEN_BYTES``, not UTF-8 or empty is an ``InputFileError``
    (exit 65)."""
    if token_file is None:
        return os.environ.get(TOKEN_ENV) or None
    path = Path(token_file)
    try:  # (the rule of ``files.bounded``, which this stdlib-only package cannot import: no FIFO holds the open)
        with os.fdopen(os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC), "rb") as f:
            if not stat.S_ISREG(os.fstat(f.fileno()).st_mode):
                raise InputFileError(f"{path}: not a regular file: a token file must be one")
            os.set_blocking(f.fileno(), True)
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
