"""The Thermotron 8800 / 8200 programmers' ASCII interface (Thermotron's "8800 Programmer/Controller Interface
Communications" manual: the query and command mnemonics ``PVARn?``, ``SETPn``, ``MRMPn``, ``RUNM``, ``HOLD``,
``STOP`` and ``SCOD?``).

A request is one line ending CR; an answer is one line ending CR (a LF after it is dropped, whichever of CR
or CR LF the interface is set to send).  A setting with data answers its value (the 8200 manual's example:
``SETP1,22.000`` -> ``22.000``, bytes ``53 45 54 50 31 2C 32 32 2E 30 30 30 0D`` -> ``32 32 2E 30 30 30
0D``); ``RUNM`` ("places a stopped 8200 in run manual mode"), ``HOLD`` and ``STOP`` answer nothing.

- ``PVAR1?`` -> the loop's process variable (the air);
- ``SETP1?`` -> its set point; ``SETP1,20.0`` sets it (one decimal: resolution 0.1);
- ``MRMP1,2.0`` sets the manual ramp rate (degrees per minute);
- ``SCOD?`` -> the status code, read as ``STATUS_CODES`` says.

The interface has no read of the set point's range nor of the unit: the driver takes both from its URL or
config (``range=LOW:HIGH``, ``unit=C|F``) and refuses to open without a range.  A query answered with a
text that is not a number is a ``ControllerProtocolError`` naming the answer.
"""

from __future__ import annotations

from .lines import decode_line, one_decimal, parse_number

TERMINATOR = b"\r"
WHO = "thermotron"

#: SCOD? status code -> the interface's state (any other code: ``unknown``).  0 stop, 1 run manual,
#: 2 run program, 3 hold program, 4 suspend program: the driver's reading, not checked against a manual's
#: table yet (a code it does not know is ``unknown``, never a guess).
STATUS_CODES = {0: "standby", 1: "constant", 2: "program", 3: "program", 4: "program"}


def request(command: str) -> bytes:
    """One command line as bytes (``PVAR1?`` -> ``b"PVAR1?\\r"``)."""
    if "\r" in command or "\n" in command or not command.isascii():
        raise ValueError(f"not one ASCII command line: {command!r}")
    return command.encode("ascii") + TERMINATOR


def _check_loop(loop: int) -> int:
    if not 1 <= loop <= 8:
        raise ValueError(f"a Thermotron loop is 1..8, not {loop}")
    return loop


def encode_read_air(loop: int) -> bytes:
    return request(f"PVAR{_check_loop(loop)}?")


def encode_read_setpoint(loop: int) -> bytes:
    return request(f"SETP{_check_loop(loop)}?")


def encode_write_setpoint(loop: int, setpoint: float) -> bytes:
    """``SETPn,20.0``: one decimal, rounded half away from zero."""
    return request(f"SETP{_check_loop(loop)},{one_decimal(setpoint)}")


def encode_ramp_rate(loop: int, rate_per_min: float) -> bytes:
    """``MRMPn,rate``: the manual ramp rate, one decimal."""
    return request(f"MRMP{_check_loop(loop)},{one_decimal(rate_per_min)}")


def encode_run_manual() -> bytes:
    return request("RUNM")


def encode_hold() -> bytes:
    return request("HOLD")


def encode_stop() -> bytes:
    return request("STOP")


def encode_read_status() -> bytes:
    return request("SCOD?")


def decode_number(reply: bytes, *, what: str) -> float:
    """A query's numeric answer (``PVAR1?``, ``SETP1?``)."""
    return parse_number(decode_line(reply, TERMINATOR, who=WHO), who=WHO, what=what)


def decode_status(reply: bytes) -> str:
    """``SCOD?``'s answer -> a state (``ControllerProtocolError`` if it is not a whole number)."""
    code = decode_number(reply, what="the status code")
    if code != int(code):
        return "unknown"
    return STATUS_CODES.get(int(code), "unknown")
