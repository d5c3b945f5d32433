"""The screen of a dwell: what is refused, and what is rejected and flagged ``guard``, before any interval.

Refused (bad input, nothing changed): a trimmed window without a whole block (``dwell.trimmed_window``), no
block since the last break, a window reaching back past a break, a dwell ending after the last block closed.
(A dwell out of time order is refused by the law before the screen: ``dwell.out_of_order``.)  A dwell longer
than the ring is taken over its last ``window.MAX_WINDOW_S``.

Rejected (the gyro saw motion the log does not declare), on the block rates of the untrimmed dwell less
``MOTION_MARGIN_S`` at each end:

- motion: a block rate farther than ``static_threshold_dph`` from a steady drift (``motion_dph``: a robust
  straight line through the medians of the two halves);
- an unsteady rate: a segment of ``STEADY_SEGMENTS`` off the rates' least-squares line by more than
  ``STEADY_SIGMAS`` standard errors (``unsteady_sigmas``: a table that began to creep or slipped within the
  dwell, whose mean angle the log's start and end angles do not give);
- a declared creep (``angle_end_deg``) farther than ``CREEP_SIGMAS`` sigmas from what the gyro saw within the
  dwell (``creep_disagreement``: the same creep declared at every dwell moves their mean angles alike, which the
  intervals do not see, but the gyro's rate within them does).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from ...dwells import Dwell
from .. import numerics
from ..dwell import angle_at_deg, blocks_within, trimmed_window
from .estimate import ARCSEC_PER_DEG, MODEL_NOISE_SHARE, SF_PRIOR_PPM, TABLE_SIGMAS, MixtureLaw
from .window import BlockWindow

__all__ = ["CREEP_SIGMAS", "Refused", "Rejected", "Screened", "creep_disagreement", "screen"]

#: The motion check looks at the whole blocks inside the dwell less this at each end: a station's clock and
#: the frames' time stamps may be a few tenths of a second off the table's; a message 1 s late or more is
#: still seen moving.
MOTION_MARGIN_S = 0.5
#: The steadiness test of a dwell: its block rates in this many equal segments; rejected when a segment's mean
#: strays from the rates' straight line by more than ``STEADY_SIGMAS`` standard errors (motion the log does not
#: declare: a table that began to creep, or slipped, within the dwell).
STEADY_SEGMENTS = 4
STEADY_SIGMAS = 6.0
#: A dwell whose declared creep (``angle_end_deg``) is farther than this, in sigmas, from what the gyro saw
#: within it is rejected (``creep_disagreement``).
CREEP_SIGMAS = TABLE_SIGMAS


def motion_dph(rates: np.ndarray) -> float:
    """How far the block rates stray from a steady drift: the largest deviation from their straight line
    (fitted robustly: through the medians of the two halves), deg/h."""
    n = len(rates)
    if n < 4:
        return float(np.max(np.abs(rates - np.median(rates)))) if n else 0.0
    half = n // 2
    k = np.arange(n, dtype=np.float64)
    first, second = float(np.median(rates[:half])), float(np.median(rates[n - half :]))
    slope = (second - first) / (n - half)
    line = first + slope * (k - (half - 1) / 2.0)
    return float(np.max(np.abs(rates - line)))


def unsteady_sigmas(rates: np.ndarray, v: float) -> float:
    """How far a dwell's rate departs from a steady one, in standard errors.  Steady: a straight line in time
    (the drift, plus the constant rate of a move the log declares with ``angle_end_deg``).  The rates' least-squares
    line ``a + b k``; the mean residual of each of ``STEADY_SEGMENTS`` equal segments over its standard error
    ``sqrt(v / n_seg)``, v the white noise variance of a block rate (``white_var_dph2``); the
    largest.  0 below two blocks a segment.  ``STEADY_SIGMAS`` lies between what a steady dwell and a creeping
    one give (docs/decisions/2026-12-07-steady-dwell-threshold.md)."""
    n = len(rates)
    if n < 2 * STEADY_SEGMENTS:
        return 0.0
    k = np.arange(n, dtype=np.float64)
    k_mean, r_mean = numerics.total(k) / n, numerics.total(rates) / n
    dk = k - k_mean
    slope = numerics.total(dk * (rates - r_mean)) / numerics.total(dk * dk)
    resid = rates - (r_mean + slope * dk)
    if not v > 0.0:
        return 0.0
    return max(
        abs(numerics.total(seg)) / len(seg) / math.sqrt(v / len(seg)) for seg in np.array_split(resid, STEADY_SEGMENTS)
    )


def white_var_dph2(rates: np.ndarray) -> float:
    """The white noise variance of a block rate, from successive differences: half their mean square."""
    return 0.5 * float(np.mean(np.diff(rates) ** 2))


class Screened(NamedTuple):
    """A dwell through the screen: its window's whole blocks (``first`` to ``end``), the block rates of the
    untrimmed dwell and their white noise variance (NaN below three blocks)."""

    first: int
    end: int
    rates: np.ndarray
    white_var_dph2: float


class Refused(NamedTuple):
    reason: str


class Rejected(NamedTuple):
    reason: str


def screen(dwell: Dwell, window: BlockWindow, static_threshold_dph: float) -> Screened | Refused | Rejected:
    """``dwell`` (in time order) against the blocks on ``window`` (module docstring), but for its declared creep
    (``creep_disagreement``, which needs the law's estimate)."""
    try:
        t0, t1 = trimmed_window(dwell.t_start_s, dwell.t_end_s)
    except ValueError as exc:
        return Refused(str(exc))
    b = window.block_s
    first, end = blocks_within(t0, t1, b)
    last = window.last_block
    if window.first is None or last is None:
        return Refused("no block since the last break (a gap, a restart, a zero)")
    if first < window.first:
        if not window.dropped_old:
            return Refused("the dwell reaches back past a break (a gap, a restart, a zero)")
        first = window.first  # a dwell longer than the ring: its last MAX_WINDOW_S
    if end > last + 1:
        return Refused("the dwell ends after the last block closed")
    if end <= first:
        return Refused("no whole block inside the dwell's trimmed window")
    # motion: every block of the untrimmed dwell still on the ring within the threshold of their median
    lo, hi = blocks_within(dwell.t_start_s + MOTION_MARGIN_S, dwell.t_end_s - MOTION_MARGIN_S, b)
    lo, hi = max(lo, window.first), min(hi, last + 1)
    rates = window.rates(lo, hi)
    spread = motion_dph(rates)
    if spread > static_threshold_dph:
        return Rejected(f"the gyro shows motion during the dwell ({spread:.0f} deg/h off a steady drift)")
    v = white_var_dph2(rates) if len(rates) >= 3 else math.nan
    unsteady = unsteady_sigmas(rates, v)
    if unsteady > STEADY_SIGMAS:
        return Rejected(f"the gyro's rate changed during the dwell ({unsteady:.0f} standard errors off a steady one)")
    return Screened(first, end, rates, v)


def creep_disagreement(
    dwell: Dwell,
    window: BlockWindow,
    screened: Screened,
    mixture: MixtureLaw,
    bias: tuple[float, float] | None,
    prior_dph: float,
) -> tuple[float, float, float] | None:
    """A dwell that declares a creep (``angle_end_deg``) against the gyro within its window, from the middle of
    its first whole block to the middle of its last (span S): the declared creep c over S (the table's
    angle at the two, ``angle_at_deg``), the gyro's angle change less the frozen drift, the bias and the
    adapted drift over S, and their difference ``e = theta - F - bias S - phi . delta - c`` (phi: the
    shape regressors' and the level's sums over S, and the scale factor's ``1e-6 c``); its variance the
    gyro's white noise over S, the frozen model's share (as an interval's), the estimate's ``phi P phi``,
    the bias's spread (``prior_dph``, and the capture's between-interval variance while it runs) and the
    scale factor's prior times c::

        var = N^2 B S + (MODEL_NOISE_SHARE sigma_D S)^2 + phi P phi^T + (1e-6 SF_PRIOR_PPM c)^2
              + (prior_dph^2 + bias_var) S^2

    ``bias``: (bias, its between-interval variance), None before the run's first interval.  Returns ``(e,
    sigma, c)`` in arcsec; None when it cannot be judged: no bias yet or a window of one block."""
    first, end = screened.first, screened.end
    if end - first < 2 or bias is None:
        return None
    bias_dph, bias_var = bias
    b = window.block_s
    rows = window.middles(first, end)
    d = window.columns.between(rows[0], rows[-1])  # from the first block's middle to the last's
    span = d.time_s
    t0, t1 = (first + 0.5) * b, (end - 0.5) * b
    at = [angle_at_deg(dwell.angle_deg, dwell.angle_end_deg, dwell.t_start_s, dwell.t_end_s, t) for t in (t0, t1)]
    declared = (at[1] - at[0]) * ARCSEC_PER_DEG
    t_int = d.temperature_c_s / span
    phi = mixture.layout.row(d.shape, span, declared, t_int)
    e = d.angle_arcsec - d.frozen_arcsec - bias_dph * span - float(np.dot(phi, mixture.delta)) - declared
    v = screened.white_var_dph2
    white = mixture.noise_var_dph2 if math.isfinite(mixture.noise_var_dph2) else v if math.isfinite(v) else 0.0
    model = MODEL_NOISE_SHARE * mixture.model_sigma_dph * span
    sf = 1e-6 * SF_PRIOR_PPM * declared
    var = white * b * span + model * model + float(phi @ mixture.cov @ phi) + sf * sf
    var += (prior_dph**2 + bias_var) * span * span
    return e, math.sqrt(max(var, 1e-30)), declared
