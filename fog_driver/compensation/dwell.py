"""The one definition of what the gyro measured over a dwell of the turntable (a leaf of compensation).

A dwell (``fog_driver.dwells.Dwell``): the table stood from ``t_start_s`` to ``t_end_s`` (device time, seconds
from the capture's first sample) at ``angle_deg``, cumulative (360 is not 0); with ``angle_end_deg`` it moved
within the dwell (a creep), linearly to that angle.  A station's table log holds one per row
(``fog_driver.dwells.read_table_log``); the daemon's ``?TABLE`` gives one live.

The measurement, shared by ``evaluate``'s positioning table and the table-angle law
(``compensation.table``): the mean of the gyro's angle over the dwell's trimmed window, ``DWELL_TRIM_S``
cut from both ends so that the table's settling and a late message are excluded
(``trimmed_window``), held against the table's mean angle over that window (``reference_deg``: the
window being symmetric, the mean of the start and end angles).  ``evaluate`` takes the frames inside
the window; the law, which lives at the model's block rate, the whole model blocks inside it
(``blocks_within``): the same window, on the block grid.
"""

from __future__ import annotations

import math

__all__ = [
    "DWELL_TRIM_S",
    "MIN_LIVE_DWELL_S",
    "blocks_within",
    "out_of_order",
    "angle_at_deg",
    "reference_deg",
    "trimmed_window",
]

#: Cut from both ends of a dwell before its mean is taken (the table settling, a message a little late).
DWELL_TRIM_S = 5.0
#: The shortest dwell a live ``?TABLE`` may claim: two trims and two whole 1-s blocks.
MIN_LIVE_DWELL_S = 12.0


def out_of_order(t_start_s: float, previous_end_s: float | None) -> str | None:
    """Why a dwell starting at ``t_start_s`` cannot follow one that ended at ``previous_end_s`` (None: it can;
    dwells are one stream in time order, whoever sends them)."""
    if previous_end_s is not None and t_start_s < previous_end_s - 1e-9:
        return (
            f"out of time order: the dwell starts at {t_start_s:.3f} s, {previous_end_s - t_start_s:.1f} s before "
            f"the previous one ended ({previous_end_s:.3f} s)"
        )
    return None


def reference_deg(angle_deg: float, angle_end_deg: float | None) -> float:
    """The table's mean angle over the dwell's trimmed window: ``angle_deg``, or with ``angle_end_deg`` the mean
    of the two (a linear move within the dwell, over a window symmetric in it)."""
    return angle_deg if angle_end_deg is None else 0.5 * (angle_deg + angle_end_deg)


def angle_at_deg(angle_deg: float, angle_end_deg: float | None, t_start_s: float, t_end_s: float, t_s: float) -> float:
    """The table's angle at ``t_s`` within the dwell: ``angle_deg``, or with ``angle_end_deg`` the straight line
    from one to the other over ``t_start_s..t_end_s`` (a creep).  The mean over instants whose mean time is
    ``t_s``: the table law's window is whole blocks, not symmetric in the dwell, and at 20 deg/h half a second
    off its middle is 10 arcsec."""
    if angle_end_deg is None:
        return angle_deg
    span = t_end_s - t_start_s
    return angle_deg + (angle_end_deg - angle_deg) * ((t_s - t_start_s) / span if span > 0 else 0.5)


def trimmed_window(t_start_s: float, t_end_s: float, trim_s: float = DWELL_TRIM_S) -> tuple[float, float]:
    """``(t_start_s + trim_s, t_end_s - trim_s)``; a dwell not longer than two trims is a ``ValueError``."""
    t0, t1 = t_start_s + trim_s, t_end_s - trim_s
    if not t1 > t0:
        raise ValueError(f"the dwell {t_start_s:g}..{t_end_s:g} s is not longer than twice dwell_trim_s ({trim_s:g} s)")
    return t0, t1


def blocks_within(t0_s: float, t1_s: float, block_s: float) -> tuple[int, int]:
    """The model blocks lying wholly inside ``[t0_s, t1_s]``: block j spans ``[j block_s, (j + 1) block_s)`` from
    the first sample; returns ``(first, last + 1)`` (empty when ``first >= last + 1``)."""
    first = math.ceil(t0_s / block_s - 1e-9)
    end = math.floor(t1_s / block_s + 1e-9)
    return first, end
