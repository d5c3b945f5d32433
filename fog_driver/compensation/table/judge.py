"""The judge of a dwell by its neighbours: which of two dwells was wrong, when the gate cannot tell.

A wrong angle L at dwell k shows in the two intervals around it, as innovations ``+L`` and ``-L``; the first can
pass the gate when the interval's own error points the other way.  The gate then rejects the next one, which
cannot say which of its two dwells was wrong (on it alone, e_A and e_B cancelling, the honest dwell before a
lie is blamed as often as a lie is caught); the dwell after it decides.  With the innovations e and sigmas s of
A = (k-1, k) (learned, ``Learned``), B = (k, k+1) (rejected, ``Doubted``) and C = (k+1, k+2) (predicted now,
nothing learned), each hypothesis with its L at its best::

    k wrong:    chi2_k  = (e_A + e_B)^2 / (s_A^2 + s_B^2) + (e_C / s_C)^2
    k+1 wrong:  chi2_k1 = (e_A / s_A)^2 + (e_B + e_C)^2 / (s_B^2 + s_C^2)
    neither:    chi2_0  = (e_A / s_A)^2 + (e_B / s_B)^2 + (e_C / s_C)^2

Dwell k is blamed when ``chi2_k < chi2_k1`` and ``chi2_k + TABLE_SIGMAS^2 < chi2_0`` (a wrong dwell costs what
the gate charges one).  The law then undoes A and judges (k-1, k+1) in its place (``law.TableLaw``); when it is
learned, the verdict (``outcomes.Revision``) makes dwell k rejected and gives dwell k+1 that interval's outcome,
in a new log of outcomes.
"""

from __future__ import annotations

from typing import Any, NamedTuple

from ...dwells import Dwell
from .estimate import TABLE_SIGMAS
from .outcomes import Revision, TableOutcome
from .window import Anchor

__all__ = ["BLAMED_REASON", "Doubted", "Learned", "blames_the_learned", "revision"]

#: The reason a dwell learned and blamed afterwards is rejected for.
BLAMED_REASON = "disagrees with both neighbours: the intervals around it agree"


class Learned(NamedTuple):
    """The interval learned last, while it may still be undone: interval A."""

    before: dict[str, Any]  # the law before the interval was learned (``law.TableLaw._snapshot``)
    t_end_s: float  # the dwell it ended at
    anchor: Anchor  # that dwell's anchor
    innovation_arcsec: float
    sigma_arcsec: float


class Doubted(NamedTuple):
    """The interval the gate rejected last: interval B."""

    start: Anchor
    end: Anchor
    dwell: Dwell
    innovation_arcsec: float
    sigma_arcsec: float


def blames_the_learned(learned: Learned, doubted: Doubted, e_c: float, s_c: float) -> bool:
    """Dwell k (the end of ``learned``, the start of ``doubted``) explains the three intervals best, given C's
    innovation ``e_c`` and sigma ``s_c`` (module docstring)."""
    e_a, s_a = learned.innovation_arcsec, learned.sigma_arcsec
    e_b, s_b = doubted.innovation_arcsec, doubted.sigma_arcsec
    chi2_k = (e_a + e_b) ** 2 / (s_a * s_a + s_b * s_b) + (e_c / s_c) ** 2
    chi2_k1 = (e_a / s_a) ** 2 + (e_b + e_c) ** 2 / (s_b * s_b + s_c * s_c)
    chi2_none = (e_a / s_a) ** 2 + (e_b / s_b) ** 2 + (e_c / s_c) ** 2
    return not (chi2_k >= chi2_k1 or chi2_k + TABLE_SIGMAS**2 >= chi2_none)


def revision(learned: Learned, merged: TableOutcome) -> Revision:
    """The verdict once (k-1, k+1) is learned as ``merged``: dwell k (``learned``'s end) rejected, dwell k+1's
    outcome ``merged``."""
    return Revision(learned.t_end_s, merged, BLAMED_REASON)
