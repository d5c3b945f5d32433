"""The Watlow F4T's Modbus register map (sans-IO): where a loop's values are, how a float sits in two registers,
what the enumerated values mean.

Sources (addresses are the manual's "relative" ones, the protocol's 0-based addresses):

- Watlow, *F4T Controller Setup and Operations User's Guide*, document 0600-0093-0000 Rev. F (April 2016),
  Chapter 6 Appendix, the Modbus register table.  Control loop N's set point 2782, process value 2820, range
  low 2774 and high 2776, each ``+ 160 (N - 1)``, each an IEEE 754 float in two registers of which the table
  lists the first; by default the first register holds the float's low 16 bits (word order Low High, which the
  controller's Modbus settings can turn to High Low).  Display Units at 1328: F = 30, C = 15.  Profile
  control: 16558 (start profile), 16562 (profile action request, 1782 = start).
- Espec North America's ChamberConnectLibrary (``chamberconnectlibrary/watlowf4t.py``, MIT), which drives the
  F4T in Espec's chambers: the loop's control mode at 2730 + 160 (N - 1) (Off = 62, Auto = 10, Manual = 54),
  the profile state at 16568 (Running = 149, Pause = 146) and the pause/terminate request at 16566
  (Terminate = 148).  These are not in the pages of the manual we could read: they are defaults a user can
  override (``*_register`` options), and the state they feed is ``unknown`` when the controller refuses them.
  That library reads the unit at 6730 (TCP) or 14080 (RTU) rather than 1328: a controller whose Modbus unit
  differs from its display's is set with ``units_register=6730``.

Every register is overridable (``F4TMap``'s fields), so a controller set up differently is fixed without code.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Sequence
from dataclasses import dataclass

from ..base import CHAMBER_STATES, ControllerProtocolError

LOOP_STRIDE = 160
LOOPS = 4  # the F4T has up to four control loops
WORD_ORDERS = ("low", "high")

SETPOINT_1 = 2782
PROCESS_VALUE_1 = 2820
RANGE_LOW_1 = 2774
RANGE_HIGH_1 = 2776
CONTROL_MODE_1 = 2730
DISPLAY_UNITS = 1328
PROFILE_STATE = 16568
PROFILE_ACTION = 16566

#: Display Units' values (manual): the temperature unit the controller's values are in.
UNITS = {30: "F", 15: "C"}
#: A loop's control mode (Espec's library): Off = 62 (standby), Auto = 10 (to its set point), Manual = 54.
CONTROL_MODE_OFF = 62
CONTROL_MODES = {CONTROL_MODE_OFF: "standby", 10: "constant", 54: "local"}
#: The profile state values meaning the controller runs (or holds, paused) a profile of its own.
PROFILE_RUNNING = 149
PROFILE_PAUSED = 146
PROFILE_TERMINATE = 148


@dataclass(frozen=True)
class F4TMap:
    """The registers of one loop.  ``units``/``control_mode``/``profile_state``/``profile_action`` ``None``: not
    read (the unit is then assumed degC; the state is ``unknown``; the safe stop has nothing to write)."""

    setpoint: int
    process_value: int
    range_low: int
    range_high: int
    units: int | None = DISPLAY_UNITS
    control_mode: int | None = None
    profile_state: int | None = PROFILE_STATE
    profile_action: int | None = PROFILE_ACTION
    word_order: str = "low"

    def __post_init__(self) -> None:
        if self.word_order not in WORD_ORDERS:
            raise ValueError(f"word order {self.word_order!r} is not low or high")
        for name in ("setpoint", "process_value", "range_low", "range_high"):
            if not 0 <= getattr(self, name) <= 0xFFFE:
                raise ValueError(f"{name} register {getattr(self, name)} is not 0..65534")


def loop_map(loop: int, *, word_order: str = "low") -> F4TMap:
    """The manual's registers of control loop ``loop`` (1..4)."""
    if not 1 <= loop <= LOOPS:
        raise ValueError(f"loop {loop} is not 1..{LOOPS}")
    offset = LOOP_STRIDE * (loop - 1)
    return F4TMap(
        setpoint=SETPOINT_1 + offset,
        process_value=PROCESS_VALUE_1 + offset,
        range_low=RANGE_LOW_1 + offset,
        range_high=RANGE_HIGH_1 + offset,
        control_mode=CONTROL_MODE_1 + offset,
        word_order=word_order,
    )


def encode_float(value: float, word_order: str) -> tuple[int, int]:
    """A 32-bit IEEE float as two registers in the controller's word order (``low``: the low word first)."""
    if not math.isfinite(value):
        raise ValueError(f"{value} is not a finite number")
    high, low = struct.unpack(">HH", struct.pack(">f", value))
    return (low, high) if word_order == "low" else (high, low)


def decode_float(registers: Sequence[int], word_order: str) -> float:
    """Two registers (in the controller's word order) as a float; a NaN or infinity is garbage."""
    if len(registers) != 2:
        raise ControllerProtocolError(f"a float is two registers, not {len(registers)}")
    first, second = registers
    high, low = (second, first) if word_order == "low" else (first, second)
    (value,) = struct.unpack(">f", struct.pack(">HH", high, low))
    if not math.isfinite(value):
        raise ControllerProtocolError(
            f"registers {first:#06x} {second:#06x} are not a finite float (word order {word_order})"
        )
    return float(value)


def decode_units(value: int) -> str:
    """``C`` or ``F`` from the Display Units register."""
    if value not in UNITS:
        raise ControllerProtocolError(f"the unit register holds {value}, neither F (30) nor C (15)")
    return UNITS[value]


def chamber_state(profile_state: int | None, control_mode: int | None) -> str | None:
    """The chamber's state (one of ``CHAMBER_STATES``) from what could be read; ``None`` when a value read
    means nothing known (the caller says so and reports ``unknown``)."""
    if profile_state in (PROFILE_RUNNING, PROFILE_PAUSED):
        return "program"
    if control_mode is None:
        return "unknown"
    state = CONTROL_MODES.get(control_mode)
    assert state is None or state in CHAMBER_STATES
    return state
