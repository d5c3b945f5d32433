"""The Weiss / Voetsch (weiss technik) SIMSERV protocol over TCP (the SIMSERV interface description of Weiss
Umwelttechnik / Voetsch: the frame of fields separated by byte 0xB6, the command numbers and the answer codes).

A request is ``COMMAND 0xB6 CHAMBER [0xB6 CHANNEL [0xB6 VALUE]]`` ending CR; CHAMBER is the chamber's index
(1 for the first), CHANNEL the loop (1 the temperature).  An answer is ``STATUS [0xB6 VALUE ...]`` ending CR
(a LF after it is dropped): STATUS ``1`` is OK, anything else an error code.

- ``11001 CHB CH VALUE``: set the set point (one decimal: resolution 0.1), answers ``1``;
- ``11002 CHB CH``: the set point; ``11004 CHB CH``: the actual value (the air);
- ``11007 CHB CH`` / ``11009 CHB CH``: the set point's lower and upper limit (the range; the numbers are the
  driver's defaults and may be overridden per controller);
- ``14001 CHB 1`` starts manual mode, ``14001 CHB 0`` stops it (the safe stop).

The protocol has no state read the driver relies on (state ``unknown``) and works in degC.
"""

from __future__ import annotations

from ..base import ControllerProtocolError
from .lines import one_decimal, parse_number, shown, split_line

SEPARATOR = b"\xb6"
TERMINATOR = b"\r"
WHO = "simserv"
OK = "1"

SET_SETPOINT = 11001
GET_SETPOINT = 11002
GET_ACTUAL = 11004
GET_LOWER_LIMIT = 11007
GET_UPPER_LIMIT = 11009
MANUAL_MODE = 14001


def request(*fields: int | str) -> bytes:
    """The fields joined by 0xB6, ending CR (``request(11004, 1, 1)`` -> ``b"11004\\xb61\\xb61\\r"``)."""
    parts = [str(field) for field in fields]
    for part in parts:
        if not part or not part.isascii() or not part.isprintable():
            raise ValueError(f"not a SIMSERV field: {part!r}")
    return SEPARATOR.join(part.encode("ascii") for part in parts) + TERMINATOR


def encode_read(command: int, chamber: int, channel: int) -> bytes:
    """A read of one value (11002 the set point, 11004 the actual value, the limits) of ``channel``."""
    return request(command, chamber, channel)


def encode_write_setpoint(chamber: int, channel: int, setpoint: float) -> bytes:
    """``11001 CHB CH VALUE``: one decimal, rounded half away from zero."""
    return request(SET_SETPOINT, chamber, channel, one_decimal(setpoint))


def encode_manual_mode(chamber: int, *, start: bool) -> bytes:
    """``14001 CHB 1`` (start manual mode) or ``14001 CHB 0`` (stop it)."""
    return request(MANUAL_MODE, chamber, 1 if start else 0)


def decode_fields(reply: bytes) -> list[str]:
    """The answer's fields after its status ``1``; another status is a ``ControllerProtocolError`` naming it."""
    fields = split_line(reply, TERMINATOR, SEPARATOR, who=WHO)
    if fields[0] != OK:
        raise ControllerProtocolError(f"{WHO}: the controller answered error {shown(fields[0])}")
    return fields[1:]


def decode_ack(reply: bytes) -> None:
    """A setting's answer: status ``1`` (any field after it is ignored)."""
    decode_fields(reply)


def decode_value(reply: bytes, *, what: str) -> float:
    """A read's answer ``1 0xB6 VALUE``."""
    fields = decode_fields(reply)
    if not fields:
        raise ControllerProtocolError(f"{WHO}: {what}: an OK answer without a value: {shown(reply)}")
    return parse_number(fields[0], who=WHO, what=what)
