"""The NDJSON codec of the daemon's client protocol, sans-IO and standard library only: a leaf that the daemon and
the client library both import.  The protocol itself (its lines, classes and commands) is written in
``docs/reference/ndjson.md``; this module is the part of it both sides read and write the same way.

``LineBuffer`` splits a byte stream into lines, with one policy for a line that is too long: a line of more
than ``max_line_bytes`` bytes before its newline is reported once (``OVERLONG``, as soon as it is known: at its
newline, or as soon as the bytes buffered for it exceed the limit) and its bytes are dropped up to its newline;
the next line is read as usual.  Each side chooses its limit (the hub's ``limits.DEFAULT_MAX_LINE_BYTES``, the
client's ``wire.MAX_LINE_BYTES``).  A buffer may also bound the bytes without any newline
(``max_unterminated_bytes``: ``UNTERMINATED``, after which the hub closes).

``encode`` writes one protocol line (compact JSON, absent values omitted, ``\\n``); ``parse_command`` reads one
command line (``?NAME;`` or ``?NAME={json object};``) the way the hub does.
"""

from __future__ import annotations

import enum
import json
import math
import re
from collections.abc import Iterator
from typing import Any, NamedTuple

__all__ = [
    "OVERLONG",
    "UNTERMINATED",
    "Command",
    "CommandError",
    "LineBuffer",
    "LineEvent",
    "clean",
    "encode",
    "parse_command",
]


class LineEvent(enum.Enum):
    """What ``LineBuffer.feed`` yields besides lines."""

    #: A line longer than ``max_line_bytes``: dropped up to its newline.
    OVERLONG = "overlong"
    #: More than ``max_unterminated_bytes`` without a newline (the over-long line's dropped bytes included).
    UNTERMINATED = "unterminated"


OVERLONG = LineEvent.OVERLONG
UNTERMINATED = LineEvent.UNTERMINATED


class LineBuffer:
    """Splits a byte stream, fed in chunks split anywhere, into lines (without their ``\\n``).

    The rule: a line is the bytes between two newlines.  One of at most ``max_line_bytes`` bytes is yielded as
    ``bytes`` (a ``\\r`` before the newline is kept: it counts against the limit).  A longer one yields one
    ``OVERLONG`` when it is known to be too long (at its newline, or when the bytes buffered for it exceed
    ``max_line_bytes``) and is dropped up to its newline.  With ``max_unterminated_bytes``, more than that many
    bytes since the last newline yield ``UNTERMINATED`` (once per feed; the caller is expected to stop).

    ``feed`` is a generator: it does its work as it is consumed, so a consumer may act on each line (and stop)
    before the next one is read.  Memory is bounded by ``max_line_bytes`` plus one chunk.
    """

    __slots__ = ("_buf", "_discarding", "_unterminated", "max_line_bytes", "max_unterminated_bytes")

    def __init__(self, max_line_bytes: int, max_unterminated_bytes: int | None = None) -> None:
        if max_line_bytes < 1:
            raise ValueError("max_line_bytes must be at least 1")
        self.max_line_bytes = max_line_bytes
        self.max_unterminated_bytes = max_unterminated_bytes
        self._buf = bytearray()  # the start of the current line (never more than max_line_bytes)
        self._discarding = False  # inside an over-long line: its bytes are dropped up to its newline
        self._unterminated = 0  # bytes since the last newline, dropped ones included

    @property
    def buffered_bytes(self) -> int:
        """Bytes held for the line being read (at most ``max_line_bytes``: an over-long line's are dropped)."""
        return len(self._buf)

    @property
    def unterminated_bytes(self) -> int:
        """Bytes received since the last newline (an over-long line's dropped bytes included)."""
        return self._unterminated

    def feed(self, data: bytes) -> Iterator[bytes | LineEvent]:
        """The lines (and ``OVERLONG`` / ``UNTERMINATED`` events) that ``data`` completes, in order."""
        limit = self.max_line_bytes
        *pieces, rest = bytes(data).split(b"\n")
        for piece in pieces:  # each ends a line
            self._unterminated = 0
            if self._discarding:
                self._discarding = False
                continue
            if self._buf:
                self._buf += piece
                line = bytes(self._buf)
                self._buf.clear()
            else:
                line = piece
            yield OVERLONG if len(line) > limit else line
        self._unterminated += len(rest)
        if self.max_unterminated_bytes is not None and self._unterminated > self.max_unterminated_bytes:
            yield UNTERMINATED
            return
        if not self._discarding:
            self._buf += rest
            if len(self._buf) > limit:
                self._buf.clear()
                self._discarding = True
                yield OVERLONG


# -- lines out ------------------------------------------------------------------------------------------------


class _Absent:
    __slots__ = ()


_ABSENT: Any = _Absent()


def clean(obj: Any) -> Any:
    """``obj`` without None values and non-finite floats, recursively (dict values, list items).

    Absent values are omitted from the protocol, never sent as ``null``; numpy
    scalars become Python numbers and numpy arrays lists.  Dict keys are kept as given.
    """
    if isinstance(obj, dict):
        out = {}
        for key, value in obj.items():
            value = clean(value)
            if value is not _ABSENT:
                out[key] = value
        return out
    return _clean_value(obj)


def _clean_value(value: Any) -> Any:
    if value is None:
        return _ABSENT
    if isinstance(value, bool):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else _ABSENT
    if isinstance(value, (int, str)):
        return value
    if isinstance(value, dict):
        return clean(value)
    if isinstance(value, (list, tuple)):
        items = (_clean_value(v) for v in value)
        return [v for v in items if v is not _ABSENT]
    # numpy scalars and arrays, without importing numpy here
    tolist = getattr(value, "tolist", None)
    if tolist is not None and hasattr(value, "dtype"):
        return _clean_value(tolist())
    return value


_ENCODER = json.JSONEncoder(separators=(",", ":"), allow_nan=False)


def encode(obj: dict[str, Any]) -> bytes:
    """One protocol line: ``clean(obj)`` as compact JSON plus ``\\n`` (raises on unserializable values).

    Most objects are clean already (every ANGLE the daemon makes): they are encoded as they are, and
    ``clean`` runs only when that fails or might differ, i.e. when the object holds a non-finite float
    (ValueError), a numpy integer or array (TypeError) or a ``null`` (None; the text ``null`` inside a
    string also takes the slow path, which gives the same line)."""
    try:
        text = _ENCODER.encode(obj)
    except (ValueError, TypeError):
        text = None
    if text is None or "null" in text:
        text = _ENCODER.encode(clean(obj))
    return text.encode() + b"\n"


# -- command lines in -----------------------------------------------------------------------------------------

_COMMAND_RE = re.compile(r"\?([A-Z]+)(?:=(.*))?\Z", re.DOTALL)


class Command(NamedTuple):
    """A command line read: its NAME, its argument object (``{}`` when none) and whether ``=...`` was given."""

    name: str
    args: dict[str, Any]
    has_args: bool


class CommandError(NamedTuple):
    """A line that is no usable command: the ERROR ``message``, and the ``command`` name when it could be read."""

    message: str
    command: str | None = None


def parse_command(raw: bytes) -> Command | CommandError | None:
    """One command line (without its newline) -> ``Command``, ``CommandError``, or None for a blank line.

    The grammar: ``?NAME;`` or ``?NAME={json object};``, NAME upper-case ASCII letters, the trailing ``;``
    optional, surrounding whitespace (a ``\\r``) ignored; bytes that are not UTF-8 are replaced (U+FFFD).
    An empty argument (``?NAME=;``) is no argument object (``{}``) but still ``has_args``.
    """
    text = raw.decode("utf-8", errors="replace").strip()
    if not text:
        return None
    if text.endswith(";"):
        text = text[:-1].rstrip()
    m = _COMMAND_RE.match(text)
    if m is None:
        return CommandError("not a command: expected ?NAME; or ?NAME={json object};")
    name, payload = m.group(1), m.group(2)
    args: Any = {}
    if payload is not None and payload.strip():
        try:
            args = json.loads(payload)
        except (ValueError, RecursionError) as exc:  # 4 KiB of "[" nests deeper than Python recurses
            return CommandError(f"invalid JSON: {str(exc) or type(exc).__name__}", name)
        if not isinstance(args, dict):
            return CommandError("the argument must be a JSON object", name)
    return Command(name, args, payload is not None)
