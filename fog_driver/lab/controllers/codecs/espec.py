"""The Espec P-300 / SCP-220 controllers' ASCII protocol (Espec's "Communication manual" for the P-300 and
SCP-220 controllers: the command frames, the ``TEMP?``/``MODE?``/``ALARM?`` monitor commands, the ``TEMP, S``
and ``MODE,`` setting commands and the ``OK:``/``NA:`` answers).

Each request is one line ending CR LF; each answer is one line ending CR LF:

- ``TEMP?`` -> ``PV,SP,UPPER,LOWER``: the air, the set point, and the upper and lower limits (the range);
- ``TEMP, S20.0`` -> ``OK:TEMP, S20.0`` (one decimal: the set point's resolution is 0.1);
- ``MODE?`` -> ``CONSTANT`` | ``RUN`` | ``STANDBY`` | ``OFF``; ``MODE, CONSTANT`` and ``MODE, STANDBY`` ->
  ``OK:MODE, ...``;
- ``ALARM?`` -> ``0`` (no alarm) or ``N,CODE1,...,CODEN`` (the number of alarms, then their codes);
- an error: ``NA:MESSAGE`` (``NA:COMMAND ERR``, ``NA:PARAMETER ERR``, ``NA:DATA NOT READY``, ...).

The protocol has no unit read: the driver takes the unit from its URL.  An ``NA:`` whose message says the
controller is in local mode or not ready for remote settings (``LOCAL``, ``CONTROLLER NOT READY``) is a
``ControllerRefused``; any other ``NA:`` a ``ControllerProtocolError`` naming the message.
"""

from __future__ import annotations

from dataclasses import dataclass

from ..base import ControllerProtocolError, ControllerRefused
from .lines import decode_line, one_decimal, parse_number, shown

TERMINATOR = b"\r\n"
WHO = "espec"

#: MODE? answers -> the interface's states
MODE_STATES = {"CONSTANT": "constant", "RUN": "program", "STANDBY": "standby", "OFF": "standby"}

#: Words in an NA: message that mean the controller takes no remote settings now (local mode)
REFUSAL_WORDS = ("LOCAL", "CONTROLLER NOT READY")


@dataclass(frozen=True)
class TempReply:
    """``TEMP?``'s answer, in the controller's unit."""

    air: float
    setpoint: float
    upper: float
    lower: float


def request(command: str) -> bytes:
    """One command line as bytes (``TEMP?`` -> ``b"TEMP?\\r\\n"``)."""
    if "\r" in command or "\n" in command or not command.isascii():
        raise ValueError(f"not one ASCII command line: {command!r}")
    return command.encode("ascii") + TERMINATOR


def encode_read_temp() -> bytes:
    return request("TEMP?")


def encode_write_setpoint(setpoint: float) -> bytes:
    """``TEMP, S20.0``: the set point with one decimal, rounded half away from zero."""
    return request(f"TEMP, S{one_decimal(setpoint)}")


def encode_read_mode() -> bytes:
    return request("MODE?")


def encode_mode(mode: str) -> bytes:
    """``MODE, CONSTANT`` or ``MODE, STANDBY`` (the modes the driver sets)."""
    if mode not in ("CONSTANT", "STANDBY"):
        raise ValueError(f"the driver sets MODE CONSTANT or STANDBY, not {mode!r}")
    return request(f"MODE, {mode}")


def encode_read_alarm() -> bytes:
    return request("ALARM?")


def answer_text(reply: bytes) -> str:
    """The text of an answer; an ``NA:`` answer raises (``ControllerRefused`` for local mode)."""
    text = decode_line(reply, TERMINATOR, who=WHO)
    if text.upper().startswith("NA:"):
        message = text[3:].strip() or "(no message)"
        if any(word in message.upper() for word in REFUSAL_WORDS):
            raise ControllerRefused(f"{WHO}: the controller refuses remote settings: NA:{message}")
        raise ControllerProtocolError(f"{WHO}: the controller answered an error: NA:{message}")
    return text


def decode_ok(reply: bytes) -> str:
    """A setting command's acknowledgement ``OK:...``; returns what follows ``OK:``."""
    text = answer_text(reply)
    if not text.upper().startswith("OK:"):
        raise ControllerProtocolError(f"{WHO}: a setting answered neither OK: nor NA:: {shown(text)}")
    return text[3:].strip()


def decode_temp(reply: bytes) -> TempReply:
    """``PV,SP,UPPER,LOWER`` -> ``TempReply``."""
    text = answer_text(reply)
    fields = [field.strip() for field in text.split(",")]
    if len(fields) != 4:
        raise ControllerProtocolError(f"{WHO}: TEMP? answered {len(fields)} fields, not 4: {shown(text)}")
    names = ("the air", "the set point", "the upper limit", "the lower limit")
    air, setpoint, upper, lower = (parse_number(f, who=WHO, what=n) for f, n in zip(fields, names, strict=True))
    return TempReply(air=air, setpoint=setpoint, upper=upper, lower=lower)


def decode_mode(reply: bytes) -> str:
    """``MODE?``'s answer -> one of the interface's states (``unknown`` for a mode the table does not know)."""
    return MODE_STATES.get(answer_text(reply).upper(), "unknown")


def decode_alarm(reply: bytes) -> tuple[str, ...]:
    """``0`` -> no alarm; ``N,C1,...,CN`` -> the codes as ``"alarm C1"``, ..."""
    text = answer_text(reply)
    fields = [field.strip() for field in text.split(",")]
    if not fields[0].isdigit():
        raise ControllerProtocolError(f"{WHO}: ALARM? answered no alarm count: {shown(text)}")
    count = int(fields[0])
    codes = fields[1:]
    if count != len(codes):
        raise ControllerProtocolError(f"{WHO}: ALARM? counts {count} alarms but lists {len(codes)}: {shown(text)}")
    return tuple(f"alarm {code}" for code in codes)
