"""Wrong table logs for tests and benchmarks: the station's mistakes, made on purpose.

A table log is a list of dwells (``fog_driver.dwells.Dwell``, as ``fog_driver.dwells.read_table_log`` reads them).
``lie`` puts one dwell's angle off by a set amount: the truth plus ``off_deg``, at its start and its end alike;
to put it off by N sigmas of its interval's innovation, take ``off_deg = N sigma_arcsec / 3600`` from the sigma
an honest run's law reported for it (``TableOutcome.sigma_arcsec``).  ``late`` ends one dwell later than the
table did: the angle sent after the table began to move.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

from ..dwells import Dwell

__all__ = ["late", "lie"]


def _check(dwells: Sequence[Dwell], index: int, amount: float, name: str) -> None:
    if not 0 <= index < len(dwells):
        raise ValueError(f"dwell {index} of a log of {len(dwells)}")
    if not math.isfinite(amount):
        raise ValueError(f"{name} must be finite, got {amount!r}")


def lie(dwells: Sequence[Dwell], index: int, off_deg: float) -> list[Dwell]:
    """The log with dwell ``index``'s angle ``off_deg`` off (its end angle too, when it has one)."""
    _check(dwells, index, off_deg, "off_deg")
    out = list(dwells)
    d = out[index]
    end = None if d.angle_end_deg is None else d.angle_end_deg + off_deg
    out[index] = dataclasses.replace(d, angle_deg=d.angle_deg + off_deg, angle_end_deg=end)
    return out


def late(dwells: Sequence[Dwell], index: int, late_s: float) -> list[Dwell]:
    """The log with dwell ``index`` ending ``late_s`` seconds after the table's true end."""
    _check(dwells, index, late_s, "late_s")
    out = list(dwells)
    d = out[index]
    out[index] = dataclasses.replace(d, t_end_s=d.t_end_s + late_s)
    return out
