"""Every flag of a sample or an estimate, in one place (a leaf: the standard library only).

Two vocabularies, both fixed by what is already on the wire and in files:

* ``Flag``: the bits of the compensator's flag word, the same bit for bit in the ``flags`` of a
  compensated sample, of every estimate, of the UDP datagram (a u16) and, by name, of the NDJSON ANGLE
  object and of the compensated-rows files::

      bit 0 gap                frames were missing (or the estimate is settling after a gap)
      bit 1 thermometer_fault  a thermometer read NaN or implausibly, or its fault bit was set
      bit 2 input_stale        a thermometer's value is frozen (no valid reading, no healthy partner)
      bit 3 uncompensated      no drift estimate applied (start-up, or inputs never valid)
      bit 4 adapting           the weights are adapting online, or adapted weights give the estimate
      bit 5 guard              a runaway or non-finite estimate, or a disagreeing reference, was rejected
      bit 6 extrapolating      inputs outside the model's fit box, or its estimate clipped
      bit 7 substituted        a faulted thermometer replaced by a healthy one plus their offset
      bit 8 recovering         the model settling after a faulted thermometer came back
      bit 9 scale_factor       the scale factor learned from table angles corrects the angle
      bits 10..15              reserved, zero

  ``FLAG_NAMES`` maps each bit to its name (``Flag.GAP`` -> ``"gap"``), in bit order;
  ``flag_names(bits)`` and ``flags_from_names(names)`` go between the two forms.  The ``FLAG_*``
  constants are the same bits as plain ``int`` (for numpy arrays and for arithmetic whose result must
  stay an ``int``).

* The flags a format decoder puts on a sample it decodes (``ImuSample.flags``, a set of names: the
  device's own status, before the sample stream maps them to protocol v1's status bits):
  ``SAMPLE_SENSOR_INVALID``, ``SAMPLE_STARTUP``, ``SAMPLE_TEMPERATURE_INVALID``, ``SAMPLE_OVER_RANGE``.
"""

from __future__ import annotations

import enum
import functools
from collections.abc import Iterable
from typing import Final


class Flag(enum.IntFlag):
    """The compensator's flag word (module docstring: the meaning of each bit)."""

    GAP = 1 << 0
    THERMOMETER_FAULT = 1 << 1
    INPUT_STALE = 1 << 2
    UNCOMPENSATED = 1 << 3
    ADAPTING = 1 << 4
    GUARD = 1 << 5
    EXTRAPOLATING = 1 << 6
    SUBSTITUTED = 1 << 7
    RECOVERING = 1 << 8
    SCALE_FACTOR = 1 << 9


#: The same bits as plain ints.
FLAG_GAP: Final = int(Flag.GAP)
FLAG_THERMOMETER_FAULT: Final = int(Flag.THERMOMETER_FAULT)
FLAG_INPUT_STALE: Final = int(Flag.INPUT_STALE)
FLAG_UNCOMPENSATED: Final = int(Flag.UNCOMPENSATED)
FLAG_ADAPTING: Final = int(Flag.ADAPTING)
FLAG_GUARD: Final = int(Flag.GUARD)
FLAG_EXTRAPOLATING: Final = int(Flag.EXTRAPOLATING)
FLAG_SUBSTITUTED: Final = int(Flag.SUBSTITUTED)
FLAG_RECOVERING: Final = int(Flag.RECOVERING)
FLAG_SCALE_FACTOR: Final = int(Flag.SCALE_FACTOR)

#: bit -> name, in bit order: ``{1: "gap", 2: "thermometer_fault", ..., 256: "recovering"}``.
FLAG_NAMES: Final[dict[int, str]] = {int(bit): str(bit.name).lower() for bit in Flag}
#: name -> bit, the inverse of ``FLAG_NAMES``.
FLAG_BITS: Final[dict[str, int]] = {name: bit for bit, name in FLAG_NAMES.items()}


def flag_names(bits: int) -> list[str]:
    """The names of the bits set in ``bits``, in bit order (a new list each call); reserved bits have none."""
    return list(_flag_names(int(bits)))


@functools.lru_cache(maxsize=1024)
def _flag_names(bits: int) -> tuple[str, ...]:
    return tuple(name for bit, name in FLAG_NAMES.items() if bits & bit)


def flags_from_names(names: Iterable[str]) -> Flag:
    """The flag word of ``names``: the OR of their bits.  A name not in ``FLAG_NAMES`` (a newer daemon's) is
    ignored, as a reserved bit would be."""
    bits = 0
    for name in set(names):
        bits |= FLAG_BITS.get(name, 0)
    return Flag(bits)


# --- a format decoder's flags on a decoded sample, by name (``ImuSample.flags``) ------------------------

SAMPLE_SENSOR_INVALID: Final = "sensor_invalid"  #: a gyro axis reported invalid by the device
SAMPLE_STARTUP: Final = "startup"  #: the device says its output is not yet valid (warm-up, just configured)
SAMPLE_TEMPERATURE_INVALID: Final = "temperature_invalid"  #: a temperature channel reported invalid
SAMPLE_OVER_RANGE: Final = "over_range"  #: a gyro axis beyond its range
#: Every flag a format decoder may set, in this order.
SAMPLE_FLAGS: Final = (SAMPLE_SENSOR_INVALID, SAMPLE_STARTUP, SAMPLE_TEMPERATURE_INVALID, SAMPLE_OVER_RANGE)

__all__ = [
    "FLAG_ADAPTING",
    "FLAG_BITS",
    "FLAG_EXTRAPOLATING",
    "FLAG_GAP",
    "FLAG_GUARD",
    "FLAG_INPUT_STALE",
    "FLAG_NAMES",
    "FLAG_RECOVERING",
    "FLAG_SCALE_FACTOR",
    "FLAG_SUBSTITUTED",
    "FLAG_THERMOMETER_FAULT",
    "FLAG_UNCOMPENSATED",
    "SAMPLE_FLAGS",
    "SAMPLE_OVER_RANGE",
    "SAMPLE_SENSOR_INVALID",
    "SAMPLE_STARTUP",
    "SAMPLE_TEMPERATURE_INVALID",
    "Flag",
    "flag_names",
    "flags_from_names",
]
