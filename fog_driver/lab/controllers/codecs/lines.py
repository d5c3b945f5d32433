"""What the ASCII chamber protocols (Espec, Thermotron, SIMSERV) share as text: a reply line to a ``str``, a
number in a reply, a set point written with one decimal.

Sans-IO: bytes in, values out; every failure is a one-line ``ControllerProtocolError`` naming the reply.
"""

from __future__ import annotations

import math
from decimal import ROUND_HALF_UP, Decimal, InvalidOperation

from ..base import ControllerProtocolError

#: The longest reply line the ASCII drivers read (the longest a manual shows is well under 100 bytes).
MAX_LINE_BYTES = 256


def shown(reply: bytes | str, limit: int = 60) -> str:
    """A reply as a message shows it: ``repr``, cut at ``limit`` characters."""
    text = repr(reply)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def decode_line(reply: bytes, terminator: bytes, *, who: str) -> str:
    """The text of one reply line: ``terminator`` (and any CR/LF around it) stripped, printable ASCII only."""
    return split_line(reply, terminator, b"", who=who)[0]


def split_line(reply: bytes, terminator: bytes, separator: bytes, *, who: str) -> list[str]:
    """The fields of one reply line split at ``separator`` (b"": one field), each printable ASCII, stripped;
    the ``terminator`` and any CR/LF around the line are dropped."""
    if not reply.endswith(terminator):
        raise ControllerProtocolError(f"{who}: a reply without its line end: {shown(reply)}")
    body = reply[: -len(terminator)].strip(b"\r\n")
    fields = body.split(separator) if separator else [body]
    try:
        texts = [field.decode("ascii") for field in fields]
    except UnicodeDecodeError:
        raise ControllerProtocolError(f"{who}: a reply that is not ASCII text: {shown(reply)}") from None
    if not all(text.isprintable() for text in texts):
        raise ControllerProtocolError(f"{who}: a reply with control characters: {shown(reply)}")
    return [text.strip() for text in texts]


def parse_number(field: str, *, who: str, what: str) -> float:
    """A decimal number in a reply (``ControllerProtocolError`` naming ``what`` if it is not a finite one)."""
    try:
        value = float(field)
    except ValueError:
        raise ControllerProtocolError(f"{who}: {what} is not a number: {shown(field)}") from None
    if not math.isfinite(value):
        raise ControllerProtocolError(f"{who}: {what} is not a finite number: {shown(field)}")
    return value


def one_decimal(value: float) -> str:
    """``value`` with one decimal, rounded half away from zero (20.05 -> "20.1", -20.05 -> "-20.1", the
    decimal text of the float decides: 0.15 -> "0.2"); -0.0 and anything rounding to zero -> "0.0"."""
    if not math.isfinite(value):
        raise ValueError(f"a set point must be a finite number, not {value!r}")
    try:
        rounded = Decimal(repr(value)).quantize(Decimal("0.1"), rounding=ROUND_HALF_UP)
    except InvalidOperation:
        raise ValueError(f"a set point too large to write: {value!r}") from None
    if rounded == 0:
        return "0.0"
    return f"{rounded:.1f}"
