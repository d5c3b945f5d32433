"""The controllers' one small interface: what the lab's runner asks of a thermal chamber (and, beside it, of a
turntable), whatever its protocol.

A ``Controller`` connects, closes and has a safe stop; a ``ChamberController`` adds the air temperature, the set
point (read and write), the range and, where the controller has them, its state and alarms.  Every temperature
crossing this interface is in degC: a driver whose controller is set to degF converts at its edge
(``f_to_c``/``c_to_f``), and one whose unit cannot be read assumes degC and says so once (``on_notice``).

Errors (all one line, ``FogDriverError``):

- ``ControllerUnreachable`` (exit 69): no connection, or the link was lost (a timeout, a connection reset, a
  reply cut off).  The runner takes it as a lost link: the controller holds its last set point, and the runner
  reconnects with backoff;
- ``ControllerProtocolError`` (exit 69): the controller answered, but garbage or an exception to a required read
  or write; nothing more is written;
- ``ControllerRefused`` (exit 69): the controller refuses remote writes (local or manual mode).

A turntable's controller (to come) is a ``Controller`` with angles instead of temperatures; its stop angles feed
the table law as ``?TABLE`` does.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

from ...errors import DeviceError, InputFileError

#: The documented states of a chamber controller (``ChamberStatus.state``).
CHAMBER_STATES = (
    "constant",  # controlling to its set point (remote writes accepted)
    "program",  # running a program of its own
    "standby",  # not controlling (off, stopped, standby)
    "local",  # in local or manual mode: remote writes refused
    "alarm",  # an alarm stops or limits it
    "unknown",  # the controller does not say (no such read, or it answered an exception)
)


class ControllerError(DeviceError):
    """A controller could not be driven (exit 69)."""


class ControllerUnreachable(ControllerError):
    """No connection to the controller, or the link was lost (timeout, reset, a reply cut off)."""


class ControllerProtocolError(ControllerError):
    """The controller answered garbage, or an exception to a required read or write."""


class ControllerRefused(ControllerError):
    """The controller refuses remote writes (local or manual mode)."""


class ProgramOutOfRange(InputFileError):
    """A program asks for a temperature outside the controller's range (exit 65; nothing written)."""


def f_to_c(value_f: float) -> float:
    """degF -> degC: (F - 32) * 5 / 9."""
    return (value_f - 32.0) * 5.0 / 9.0


def c_to_f(value_c: float) -> float:
    """degC -> degF: C * 9 / 5 + 32."""
    return value_c * 9.0 / 5.0 + 32.0


@dataclass(frozen=True)
class ChamberRange:
    """The temperatures the controller accepts as a set point, degC, ``low_c < high_c``."""

    low_c: float
    high_c: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.low_c) and math.isfinite(self.high_c) and self.low_c < self.high_c):
            raise ControllerProtocolError(f"the controller's range is not a range: {self.low_c:g} .. {self.high_c:g}")

    def contains(self, value_c: float) -> bool:
        return self.low_c <= value_c <= self.high_c


@dataclass(frozen=True)
class ChamberStatus:
    """The controller's state (one of ``CHAMBER_STATES``) and its active alarms, as the controller words them."""

    state: str = "unknown"
    alarms: tuple[str, ...] = field(default_factory=tuple)

    def __post_init__(self) -> None:
        if self.state not in CHAMBER_STATES:
            raise ValueError(f"chamber state {self.state!r} is not one of {', '.join(CHAMBER_STATES)}")


#: Where a driver says a thing once (the unit assumed, a state it cannot read): a line for the user.
Notice = Callable[[str], None]


@runtime_checkable
class Controller(Protocol):
    """What every lab controller has: a URL (as the user gave it), an address (the lock's key: one runner per
    address), a connection and a safe stop."""

    url: str
    address: str

    def connect(self) -> None:
        """Open the link (``ControllerUnreachable`` if it cannot); again after a lost link."""

    def close(self) -> None:
        """Close the link; the controller keeps doing what it was last told.  Idempotent."""

    def safe_stop(self) -> None:
        """The controller's own safe state (a chamber: standby; a table: stop)."""


@runtime_checkable
class ChamberController(Controller, Protocol):
    """A thermal chamber's controller, in degC.  ``resolution_c``: the smallest step of the set point it takes
    (0.1 for the ASCII protocols, which take one decimal)."""

    resolution_c: float

    def read_air_c(self) -> float:
        """The air temperature (the loop's process value)."""

    def read_setpoint_c(self) -> float:
        """The set point the controller holds now."""

    def write_setpoint_c(self, setpoint_c: float) -> None:
        """Set the set point (the controller rounds it to ``resolution_c``)."""

    def read_range_c(self) -> ChamberRange:
        """The set point's range."""

    def read_status(self) -> ChamberStatus:
        """The state and alarms; state ``unknown`` where the controller does not say (said once)."""
