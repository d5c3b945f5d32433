"""Adapting from the turntable's angles: the readout learns from dwell-to-dwell intervals.

A station that knows its table's angle at every dwell (an encoder, or a polygon and an autocollimator)
gives the law a learning signal that a creeping table cannot fool: the table's own angle changes with
the creep, so the gyro's angle change minus the table's is what the compensation left, whatever the
table did.  (The rate path of ``adapt.OnlineReadout`` learns the rate against a declared rate: a slow
creep there cannot be told from drift.)

The observation.  Dwells a and b (``dwell.Dwell``), and between them the blocks j of the model (length
``block_s``), with the frozen drift D_hat_j, shape regressors g_j (below), measured rates m_j (deg/h =
arcsec/s) and ring temperature T_j (the mean of the top and bottom thermometers; the only one when a format
has one).  The gyro's angle
measured at a dwell is the mean, over the whole blocks inside its trimmed window (``dwell``), of the
cumulative angle at each block's middle; the same mean is taken of every cumulative regressor.  Their
difference between b and a is an integral under a kernel K(t) that rises linearly over a's window,
is 1 between the windows and falls over b's::

    theta = sum_j K_j m_j dur_j        x = sum_j K_j g_j B        T_eff = sum_j K_j B
    T_int = sum_j K_j T_j B / T_eff    F = sum_j K_j D_hat_j B    (B = block_s, dur_j the frames' time)

With A the table's angles at the windows' mean times (``dwell.angle_at_deg``, arcsec: for a dwell whose angle
changed, its mean over the window's block middles), dA = A_b - A_a (a whole-turn
ambiguity resolved against the gyro, below)::

    r = theta - dA - F - bias T_eff
      = x . dw + T_eff db + 1e-6 dA s0 + 1e-6 dA (T_int - SF_REF_C) s1 + e

the drift the frozen model missed, as weights dw on the shape regressors and a level db, and the scale
factor error ``s(T) = s0 + s1 (T - 25 degC)`` ppm times the move (a 36-degree move at 25 ppm is 3.2
arcsec, as large as the drift integral: the two are estimated jointly, told apart by moves of both signs
and several sizes).  ``bias`` is everything constant (the Earth rate, the turn-on bias), captured first:
the T_eff-weighted mean of ``r / T_eff`` over the first intervals spanning ``bias_capture_s``.  The level db is
the bias's too, and like it is not published: the drift in use is ``D_hat + g . dw``.  It absorbs the capture's
error (a few minutes of intervals) and the frozen drift's mean error, which a station's ``?BIAS`` or zero window
removes with the bias; published, it would move the drift with the intervals' noise (``benchmarks/bench_table.py``;
docs/decisions/2026-12-07-table-law-level.md).

The shape regressors (``SHAPES``).  With a model file that has candidate structures (the coils that explain the
fit data within the noise of the chosen one, which ``uncertainty`` runs beside the model), g_j are their drifts'
departures from the frozen one, ``g_cj = D_c,j - D_hat_j``: the adapted drift ``D_hat + sum_c dw_c (D_c -
D_hat)`` is a blend of the structures the fit could not tell apart, a handful of coefficients.  Against the
simulator's truth they span most of the frozen model's error on a run outside the fit
(``benchmarks/bench_candidate_span.py``); the model's own regressors (tens of them) let the intervals' noise in
where the model was already good (``benchmarks/bench_table.py``; docs/decisions/2026-12-07-table-law-shapes.md).
Without candidates (a polynomial, an older model
file) g_j are the model's own regressors f_j (``D_hat = f . w0 + b0``).

The noise of r: the gyro's white noise under the kernel, ``N^2 int K^2 = N^2 (L_a / 3 + G + L_b / 3)``
(L the windows' lengths, G the time between them; N^2 from the block rates at the dwells: half the
mean squared difference of successive block rates, times B), and the frozen model's own uncertainty over
the interval, ``(MODEL_NOISE_SHARE sigma_D T_eff)^2`` (sigma_D the compensator's ``drift_sigma_dph``):
``R``.

The law.  The paper's sums (``readout``: ``dH/dt = -l H + X X^T``, ``dI/dt = -l I + X D``) with the
intervals as impulses weighted by their inverse noise, ``H = k k^T o H + phi phi^T / R``, ``I = k o I + phi
r / R`` (phi the row above; k = sqrt(beta) on the drift's rows, ``beta = exp(-dt / TABLE_MEMORY_S)``, and 1 on the
scale factor's: the drift forgets, the scale factor, a constant of the coil, does not), and the law's fixed point with a
leakage towards the frozen weights, ``(H + L0) delta = I``: each interval is taken to the point the law
``dW/dt = -K (H W - I + L0 (W - W0))`` converges to, and ``P = (H + L0)^-1`` is the estimate's
covariance.  The leakage L0 is a prior: on the correction's variation, ``F C / s_D^2`` with C the covariance of the
regressors over the blocks (so the adapted drift's shape departs from the frozen one's by about s_D where the
data say nothing); on its mean level ``m . dw + db`` (m the regressors' mean), the runaway bound (the table's
angles see the level, which the rate path cannot); on the scale factor, ``SF_PRIOR_PPM`` and
``SF_SLOPE_PRIOR_PPM_PER_C``.

The prior's scale s_D is weighed, not set.  The law solves for each of ``PRIOR_SCALES`` (runaway bounds) over
the same H and I; the scale 0 keeps the frozen shape (``dw = 0``: the level and the scale factor alone).
Before an interval is learned, each scale k predicts it, ``N(phi . delta_k, c (R + phi P_k phi^T))``, and its
log predictive density adds to the scale's evidence ``E_k = beta E_k + log p_k(r)`` (forgetting as H does).
The estimate in use is the mixture's mean, ``delta = sum_k w_k delta_k`` with ``w_k ~ exp(E_k)`` and prior
odds ``exp(FROZEN_LOG_ODDS)`` for the frozen shape (Bayesian model averaging: the weights move smoothly, so
the drift has no steps), and P the mixture's covariance ``sum_k w_k (P_k + (delta_k - delta)(delta_k -
delta)^T)``.  A model that is right keeps its shape: a wider prior predicts the intervals no better and pays
for its spread.

Safe by construction.  A dwell is refused (out of time order, a window without a whole block, a window
reaching back past a break) or rejected and flagged ``guard`` (the gyro saw motion during the dwell: a
block rate farther than ``static_threshold_dph`` from a steady drift, a robust straight line through the
dwell's blocks, ``MOTION_MARGIN_S`` at each end excepted; its rate changed within the dwell, a quarter of its
block rates off their least-squares line by more than ``STEADY_SIGMAS`` standard errors (``_unsteady_sigmas``: a
table that began to creep or slipped within the dwell, whose mean angle the log's start and end angles do not
give); the creep it declares (``angle_end_deg``) is farther than ``CREEP_SIGMAS`` sigmas from what the gyro saw
within it (``_creep_disagreement``: the same creep declared at every dwell moves their mean angles alike, which
the intervals do not see, but the gyro's rate within them does); the interval disagrees with
the gyro by more than ``TABLE_SIGMAS`` sigmas of its innovation, ``sqrt(c (R + phi P phi^T))``, c the
running mean of the squared normalized innovations, capped, over ``CALIBRATION_INTERVALS``; a move more
than ``AMBIGUOUS_DEG`` from every whole turn of the gyro's); nothing is learned from it.  After a rejected
interval the next one starts from the last dwell accepted, so a single wrong angle costs no interval;
after two rejections in a row the chain starts again from the latest dwell.  A dwell is also judged by its
neighbours: a wrong angle shows in both intervals around its dwell, and the first can pass the gate when that
interval's own error points the other way.  The gate then rejects the next one, which cannot say which of its
two dwells was wrong; the dwell after it decides, by which single wrong dwell explains the three intervals best.
When it is the dwell learned last, its interval is undone and the one around it learned in its place, if the
gate lets it through (``_judge_by_neighbours``).  An interval is not learned
across a break: a link gap, a non-finite input (the chain starts again), or blocks with degraded inputs
(thermometer fault, stale, settling: the interval is skipped, its end is the next start), or the warm-up's
(the first ``warmup_s`` of device time: skipped too, its reason says "the warm-up" and when it ends).

The comparison guard and the runaway bound stay (``adapt``): each accepted interval compares, out of
sample, the frozen and the adapted drift's errors over it (``r - scale factor part`` against ``r - phi .
delta``, in deg/h over T_eff, about their running levels).  The weighing has already asked whether the adapted
drift is better; the guard asks the other way round: the frozen drift is published again when the adapted
one's mean gain falls below minus ``TABLE_COMPARE_SIGMAS`` standard errors after ``compare_min_windows``
intervals.  The adapted drift published is never farther than the runaway bound from the frozen one: beyond it,
it is held at the bound and flagged ``guard`` (``clamped_blocks``), and the law keeps what it learned.  (The rate
path resets its law there, against a reference it cannot check; the table law's intervals are each checked
against the gyro, and a reset would throw away what a model far off for the run needs most:
docs/decisions/2026-12-07-table-law-guard.md.)  A non-finite number resets the law.

The scale factor.  Once the bias is captured and s0 is known to ``SF_APPLY_SIGMA_PPM`` (its posterior
sigma), the angle is corrected by it: ``dtheta_comp = dtheta - D_hat dt - 1e-6 s(T) dtheta``, flagged
``scale_factor``.
"""

from __future__ import annotations

import math
import re
from collections import Counter, deque
from typing import Any, NamedTuple

import numpy as np

from ...flags import FLAG_ADAPTING, FLAG_GUARD
from .. import numerics
from ..adapt import RUNAWAY_FIT_RESIDUALS, ComparisonGuard
from ..adapt_config import AdaptConfig, blocks_in
from ..dwell import Dwell, angle_at_deg, blocks_within, out_of_order, trimmed_window

__all__ = ["SF_REF_C", "TABLE_SIGMAS", "OutcomeTally", "TableLaw", "TableOutcome", "reason_kind"]

ARCSEC_PER_DEG = 3600.0
TURN_ARCSEC = 360.0 * ARCSEC_PER_DEG
#: The comparison guard's significance for the table law, in standard errors of the mean gain: the frozen drift
#: is published again when the adapted one is worse by more than this (``TableLaw.adapted_in_use``), a backstop
#: behind the weighing (a switch puts steps in the drift).  ``benchmarks/bench_table.py`` measures it;
#: docs/decisions/2026-12-07-table-law-guard.md.
TABLE_COMPARE_SIGMAS = 3.0
#: The comparison guard's memory for the table law, in intervals (about 4 h of 5-min intervals): over the
#: rate path's 12 a gain of squared errors cannot reach 3 standard errors, however much worse the adapted drift.
TABLE_COMPARE_MEMORY_INTERVALS = 48.0
#: The rejection threshold, in sigmas of the interval's innovation.
TABLE_SIGMAS = 3.0
#: A move farther than this from every whole turn of the gyro's own is ambiguous: refused.
AMBIGUOUS_DEG = 90.0
#: The scale factor's reference temperature: s(T) = s0 + s1 (T - SF_REF_C).
SF_REF_C = 25.0
SF_PRIOR_PPM = 100.0
SF_SLOPE_PRIOR_PPM_PER_C = 2.0
#: The learned scale factor is applied once its offset is known to this (posterior sigma, ppm).
SF_APPLY_SIGMA_PPM = 5.0
#: The memory of the law's sums and of the evidence (the exponential forgetting of old intervals), 24 h
#: (``benchmarks/bench_table.py``; docs/decisions/2026-12-07-table-law-prior.md).
TABLE_MEMORY_S = 24 * 3600.0
#: The drift prior's scales the law weighs (s_D, in runaway bounds); 0 is the frozen shape (the level and the
#: scale factor learned), weighed by their evidence rather than one scale for all (``benchmarks/bench_table.py``;
#: docs/decisions/2026-12-07-table-law-prior.md).
PRIOR_SCALES = (0.0, 0.025, 0.05, 0.1, 0.2)
#: The frozen shape's prior log odds against each of the others (e^3: a prior weight of 0.83 among five):
#: the evidence must earn a departure (``benchmarks/bench_table.py``; docs/decisions/2026-12-07-table-law-prior.md).
FROZEN_LOG_ODDS = 3.0
#: The drift's spread the bias capture allows for, in runaway bounds.
CAPTURE_PRIOR_RUNAWAYS = 0.1
#: The share of the frozen model's drift sigma counted as the interval's noise.
MODEL_NOISE_SHARE = 0.5
#: The innovation calibration's memory (intervals), its prior weight (intervals at 1), and the cap on
#: one interval's squared normalized innovation (a liar must not widen the threshold much).
CALIBRATION_INTERVALS = 20.0
CALIBRATION_PRIOR = 4.0
CALIBRATION_CAP = 16.0
#: The most of a dwell's window the law looks back over (the ring of blocks it keeps).
MAX_WINDOW_S = 3600.0
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
#: within it is rejected (``TableLaw._creep_disagreement``).
CREEP_SIGMAS = TABLE_SIGMAS
#: The outcomes kept (a daemon runs for months; the counters count every dwell).
MAX_OUTCOMES = 10_000
#: The gram of the regressors: its memory.
GRAM_MEMORY_S = TABLE_MEMORY_S
#: The law's shape regressors (module docstring): the candidate structures' departures from the frozen drift
#: (a model file with candidates), or the model's own regressors (without).
SHAPE_CANDIDATES = "candidates"
SHAPE_REGRESSORS = "regressors"
SHAPES = (SHAPE_CANDIDATES, SHAPE_REGRESSORS)


def _motion_dph(rates: np.ndarray) -> float:
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


def _unsteady_sigmas(rates: np.ndarray, v: float) -> float:
    """How far a dwell's rate departs from a steady one, in standard errors.  Steady: a straight line in time
    (the drift, plus the constant rate of a move the log declares with ``angle_end_deg``).  The rates' least-squares
    line ``a + b k``; the mean residual of each of ``STEADY_SEGMENTS`` equal segments over its standard error
    ``sqrt(v / n_seg)``, v the white noise variance of a block rate (``_white_var_dph2``); the
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


def _white_var_dph2(rates: np.ndarray) -> float:
    """The white noise variance of a block rate, from successive differences: half their mean square."""
    return 0.5 * float(np.mean(np.diff(rates) ** 2))


class TableOutcome(NamedTuple):
    """What became of one dwell.  ``status``: ``anchor`` (the start of a chain), ``bias`` (an interval of the
    bias capture), ``learned``, ``skipped`` (degraded inputs in the interval, or the warm-up's blocks,
    ``AdaptConfig.warmup_s``: not learned, not a fault),
    ``rejected`` (flagged ``guard``) or ``refused`` (bad input: nothing changed)."""

    t_end_s: float
    status: str
    reason: str = ""
    innovation_arcsec: float = math.nan
    sigma_arcsec: float = math.nan
    move_deg: float = math.nan
    interval_s: float = math.nan


#: A number in a reason (``reason_kind`` leaves them out).
_NUMBER = re.compile(r"[-+]?\d[\d,]*(?:\.\d+)?(?:e[-+]?\d+)?|\bnan\b|\binf\b")


def reason_kind(reason: str) -> str:
    """What a reason says, its numbers left out (``#``): the outcomes of one kind, whatever their figures."""
    return _NUMBER.sub("#", reason)


class OutcomeTally:
    """Every outcome counted, by status and by status and reason kind (``reason_kind``), with the first
    ``EXAMPLES`` outcomes of each kind."""

    EXAMPLES = 3

    def __init__(self) -> None:
        self.by_status: Counter[str] = Counter()
        #: (status, reason kind) -> [count, the first outcomes], in the order the kinds first came
        self.by_reason: dict[tuple[str, str], tuple[list[int], list[TableOutcome]]] = {}

    def add(self, outcome: TableOutcome) -> None:
        self.by_status[outcome.status] += 1
        count, examples = self.by_reason.setdefault((outcome.status, reason_kind(outcome.reason)), ([0], []))
        count[0] += 1
        if len(examples) < self.EXAMPLES:
            examples.append(outcome)

    @property
    def total(self) -> int:
        return sum(self.by_status.values())

    def copy(self) -> OutcomeTally:
        out = OutcomeTally()
        out.by_status = Counter(self.by_status)
        out.by_reason = {k: ([n[0]], list(e)) for k, (n, e) in self.by_reason.items()}
        return out


def _outcome(dwell: Dwell, status: str, reason: str, values: dict[str, float] | None) -> TableOutcome:
    v = values or {}
    return TableOutcome(
        dwell.t_end_s,
        status,
        reason,
        v.get("innovation_arcsec", math.nan),
        v.get("sigma_arcsec", math.nan),
        v.get("move_deg", math.nan),
        v.get("interval_s", math.nan),
    )


class _Anchor(NamedTuple):
    summary: np.ndarray  # the window means of the cumulative columns
    angle_arcsec: float
    window_blocks: int
    first_block: int
    end_block: int
    epoch: int


def _copied(value: Any) -> Any:
    """An array copied (the law updates its arrays in place), anything else as it is."""
    return np.copy(value) if isinstance(value, np.ndarray) else value


class _Prediction(NamedTuple):
    """One interval as an observation of the law (``TableLaw._predict``)."""

    phi: np.ndarray
    r_arcsec: float
    r_var: float
    move_deg: float
    off_deg: float
    degraded: bool
    warming_up: bool  # degraded by the warm-up alone (``AdaptConfig.warmup_s``)

    @property
    def t_eff_s(self) -> float:
        return float(self.phi[-3])


class _Undo(NamedTuple):
    """The interval learned last, while it may still be undone (``TableLaw._judge_by_neighbours``)."""

    before: dict[str, Any]  # the law before the interval was learned (``TableLaw._snapshot``)
    t_end_s: float  # the dwell it ended at
    anchor: _Anchor  # that dwell's anchor
    innovation_arcsec: float
    sigma_arcsec: float


class _Doubt(NamedTuple):
    """The interval the gate rejected last (``TableLaw._judge_by_neighbours``)."""

    start: _Anchor
    end: _Anchor
    dwell: Dwell
    innovation_arcsec: float
    sigma_arcsec: float


class TableLaw(ComparisonGuard):
    """The readout's law from table angles (module docstring): ``estimate(f)`` per block (a priori),
    ``block(...)`` to record it, ``observe(dwell)`` when a dwell's blocks have closed."""

    compare_sigmas = TABLE_COMPARE_SIGMAS

    def _compare_memory(self) -> float:
        """``TABLE_COMPARE_MEMORY_INTERVALS``, not the rate path's windows."""
        return TABLE_COMPARE_MEMORY_INTERVALS

    def __init__(
        self,
        frozen_weights: np.ndarray,
        frozen_intercept: float,
        block_s: float,
        config: AdaptConfig | None = None,
        fit_residual_dph: float | None = None,
        coil: tuple[float, int] | None = None,
        shape: str = SHAPE_REGRESSORS,
        n_shape: int | None = None,
    ) -> None:
        if shape not in SHAPES:
            raise ValueError(f"the table law's shape regressors are one of {', '.join(SHAPES)}, got {shape!r}")
        #: what the law's shape regressors g are (module docstring): the candidate structures' departures from
        #: the frozen drift, or the model's own regressors
        self.shape = shape
        self.config = config if config is not None else AdaptConfig()
        #: the coil's lag as the model found it (stage time, stages): the scale factor's temperature lags the
        #: ring's by it; None: the ring's own temperature
        self.coil = coil
        self._coil_a = 0.0 if coil is None else 1.0 - math.exp(-float(block_s) / coil[0])
        self.coil_c: list[float] = []
        self.w0 = np.array(frozen_weights, dtype=np.float64)
        self.b0 = float(frozen_intercept)
        #: the shape regressors' count (the frozen weights' when they are the model's own)
        self.n_features = f = len(self.w0) if n_shape is None else int(n_shape)
        self.block_s = float(block_s)
        self._set_bounds(fit_residual_dph)
        #: the drift's spread the bias capture allows for (the middle of the prior scales)
        self.prior_dph = CAPTURE_PRIOR_RUNAWAYS * self.runaway_dph
        #: the frozen model's error scale over an interval: its fit residual (1-min RMS), as the runaway bound has it
        self.model_sigma_dph = self.runaway_dph / RUNAWAY_FIT_RESIDUALS
        self._cap = max(2, int(math.ceil(MAX_WINDOW_S / self.block_s)) + 2)
        self._width = f + 6  # cumulative: g (f), 1, T, theta, degraded blocks, the frozen drift, warm-up blocks
        self._ring_mid = np.zeros((self._cap, self._width))
        self._ring_rate = np.zeros(self._cap)
        self._gram_a = 1.0 - math.exp(-self.block_s / GRAM_MEMORY_S)
        self.bias_capture_s = blocks_in(self.config.bias_capture_s, self.block_s) * self.block_s
        #: the dwells' outcomes, in order, the last ``MAX_OUTCOMES`` (``tally`` counts them all)
        self.outcomes: deque[TableOutcome] = deque(maxlen=MAX_OUTCOMES)
        #: the outcomes that fell off ``outcomes``' old end, counted (none is changed once that far back)
        self._dropped = OutcomeTally()
        self._noted = 0  # outcomes ever noted
        self._last_ring_c = math.nan
        self._start()

    def _start(self) -> None:
        self.reset_to_frozen()  # H, I, the weights' change and its covariance P (from the first update on)
        self.gram = np.zeros((self.n_features + 1, self.n_features + 1))
        self.gram_weight = 0.0
        self.noise_var_dph2 = math.nan  # the block rates' white noise variance (deg/h)^2
        self.noise_dwells = 0
        self.calibration_sum = 0.0
        self.calibration_n = 0.0
        self.last_update_s: float | None = None
        self.accepted = self.rejected = self.refused = self.skipped = 0
        self.guards = 0
        self.clamped_blocks = 0
        self.rejections_in_row = 0
        self._flag_pending = 0
        self.begin_run()

    def begin_run(self) -> None:
        """A new switch-on: the bias is captured again, the chain of dwells starts afresh, and the level, the
        bias's, is a new one too (``_new_level``); the law's sums on the shape and the scale factor are kept."""
        self._new_level()
        self.bias_dph: float | None = None if self.bias_capture_s > 0 else 0.0
        self.bias_sum_arcsec = 0.0
        self.bias_time_s = 0.0
        self.bias_rates: list[tuple[float, float]] = []
        self._epoch = 0
        self._break()
        self.last_dwell_end_s: float | None = None

    def _new_level(self) -> None:
        """The level db out of the sums, marginalized: with l its index, ``H <- H - H[:, l] H[l, :] / H[l, l]``,
        ``I <- I - H[:, l] I[l] / H[l, l]`` (row and column l then 0), so what the intervals said of the shape
        and the scale factor, whatever the level was, stays, and the level is learned afresh.  Each switch-on has
        its own turn-on bias, and a level carried from the run before is wrong for the next; held in the sums, it
        would bend the shape's weights (docs/decisions/2026-12-07-table-law-level.md)."""
        lvl = self.n_features
        h_ll = float(self.h[lvl, lvl])
        if not h_ll > 0:
            return
        col = self.h[:, lvl].copy()
        self.i -= col * (self.i[lvl] / h_ll)
        self.h -= np.outer(col, col) / h_ll
        self.h[lvl, :] = 0.0
        self.h[:, lvl] = 0.0
        self.i[lvl] = 0.0
        try:
            self._blend(self._candidates())
        except np.linalg.LinAlgError:
            self.reset_to_frozen()
            self.guards += 1

    def _break(self) -> None:
        """The chain is broken (a gap, a restart, ``?ZERO``): no interval is learned across it."""
        self._epoch += 1
        self._cum = np.zeros(self._width)
        self._ring_first: int | None = None  # the block index at ring position _ring_pos0
        self._ring_len = 0
        self._ring_pos0 = 0
        self._ring_full_since = False  # blocks were dropped off the ring's old end (not a break)
        #: device time the chain of blocks began at (its first block's start), None before a block
        self.chain_start_s: float | None = None
        self.anchor: _Anchor | None = None
        #: the last interval learned, while it may still be undone (``_judge_by_neighbours``)
        self._undo: _Undo | None = None
        #: the interval the gate rejected last (``_judge_by_neighbours``)
        self._doubted: _Doubt | None = None

    def _reset_comparison(self) -> None:
        self.compare_windows = 0
        self.compare_gain = 0.0
        self.compare_gain_sq = 0.0
        self.compare_level_frozen_dph = 0.0
        self.compare_level_adapted_dph = 0.0
        self.compare_dev_sq_adapted_dph2 = 0.0

    def reset_to_frozen(self) -> None:
        """The adapted weights back to the frozen ones, the law's information cleared (non-finite numbers)."""
        n = self.n_features + 3
        self.h = np.zeros((n, n))
        self.i = np.zeros(n)
        self.delta = np.zeros(n)
        self.cov = np.zeros((n, n))
        #: each prior scale's cumulative log predictive likelihood of the intervals (forgetting as H does)
        self.evidence = np.zeros(len(PRIOR_SCALES))
        self._reset_comparison()

    # -- per block -------------------------------------------------------------------------------

    @property
    def adapted_in_use(self) -> bool:
        """Once the bias is captured, unless the comparison guard finds the adapted drift worse than the frozen
        one (``adapt.ComparisonGuard._comparison_fails``): the weighing of the prior scales has already chosen
        between the frozen drift and the adapted ones, on the same out-of-sample errors."""
        return self.bias_dph is not None and not self._comparison_fails()

    @property
    def frozen_weight(self) -> float:
        """The frozen drift's weight among the prior scales (1 before any interval is learned)."""
        if not self.h.any():
            return 1.0
        return float(sum(w for w, scale in zip(self._weights(), PRIOR_SCALES) if scale == 0))

    @property
    def scale_factor_applied(self) -> bool:
        return bool(
            self.bias_dph is not None
            and self.accepted > 0
            and 0.0 < self.cov[self.n_features + 1, self.n_features + 1] <= SF_APPLY_SIGMA_PPM**2
        )

    @property
    def scale_factor_ppm(self) -> tuple[float, float]:
        """The learned (s0 ppm, s1 ppm/degC)."""
        return float(self.delta[self.n_features + 1]), float(self.delta[self.n_features + 2])

    def scale_ppm_at(self, t_ring_c: float) -> float:
        """``s(T)`` in ppm when applied, else 0."""
        if not self.scale_factor_applied or not math.isfinite(t_ring_c):
            return 0.0
        s0, s1 = self.scale_factor_ppm
        return s0 + s1 * (t_ring_c - SF_REF_C)

    def estimate(self, y_frozen: float, g: np.ndarray) -> tuple[float, float, int]:
        """``(frozen estimate, estimate in use, flags)`` from this block's frozen drift and shape regressors ``g``
        (the weights before any dwell this block delivers): ``y_frozen + g . dw``, without the level ``db``, which
        is the bias's (module docstring).  A change beyond the runaway bound is held at it (``guard``); a
        non-finite one resets the law."""
        flags, self._flag_pending = self._flag_pending, 0
        if not math.isfinite(y_frozen):
            return y_frozen, y_frozen, FLAG_GUARD
        f_n = self.n_features
        change = float(np.dot(g, self.delta[:f_n]))
        if not math.isfinite(change) or not math.isfinite(self.delta[f_n]):
            self.reset_to_frozen()
            self.guards += 1
            return y_frozen, y_frozen, flags | FLAG_GUARD
        if abs(change) > self.runaway_dph:  # held at the bound, flagged; what the law learned is kept
            if self.adapted_in_use:
                self.clamped_blocks += 1
                return y_frozen, y_frozen + math.copysign(self.runaway_dph, change), flags | FLAG_GUARD | FLAG_ADAPTING
            return y_frozen, y_frozen, flags | FLAG_GUARD
        if self.adapted_in_use and change != 0.0:
            return y_frozen, y_frozen + change, flags | FLAG_ADAPTING
        return y_frozen, y_frozen, flags

    def block(
        self,
        index: int,
        y_frozen: float,
        g: np.ndarray | None,
        rate_dph: float,
        frames_s: float,
        t_ring_c: float,
        clean: bool,
        warming_up: bool = False,
    ) -> None:
        """Record a closed block: its frozen drift and shape regressors ``g`` (None: no estimate), mean rate,
        the time its frames span, the ring temperature, and whether its inputs are clean (``warming_up``: not
        clean for the warm-up alone, ``config.warmup_s``).  A block that cannot be integrated (a gap's block,
        non-finite values) breaks the chain."""
        b = self.block_s
        t_ring_c = self._coil_temperature(t_ring_c)
        self._last_ring_c = t_ring_c
        finite = math.isfinite(rate_dph) and math.isfinite(t_ring_c) and math.isfinite(frames_s)
        if g is None or not finite or not math.isfinite(y_frozen) or not np.isfinite(g).all():
            self._break()
            return
        if self._ring_first is not None and index != self._ring_first + self._ring_len:
            self._break()  # blocks missing in between
        f_n = self.n_features
        inc = np.empty(self._width)
        inc[:f_n] = g
        inc[:f_n] *= b
        inc[f_n] = b
        inc[f_n + 1] = t_ring_c * b
        inc[f_n + 2] = rate_dph * frames_s
        inc[f_n + 3] = 0.0 if clean else 1.0
        inc[f_n + 4] = y_frozen * b
        inc[f_n + 5] = 1.0 if warming_up and not clean else 0.0
        mid = self._cum + 0.5 * inc
        self._cum += inc
        if self._ring_first is None:
            self._ring_first, self._ring_pos0, self._ring_len = index, 0, 0
            self.chain_start_s = index * b
        if self._ring_len == self._cap:  # the oldest block drops off
            self._ring_pos0 = (self._ring_pos0 + 1) % self._cap
            self._ring_first += 1
            self._ring_len -= 1
            self._ring_full_since = True
        pos = (self._ring_pos0 + self._ring_len) % self._cap
        self._ring_mid[pos] = mid
        self._ring_rate[pos] = rate_dph
        self._ring_len += 1
        if clean:  # the regressors' gram, for the prior
            row = np.append(g, 1.0)
            self.gram_weight += self._gram_a * (1.0 - self.gram_weight)
            self.gram += self._gram_a * (np.outer(row, row) - self.gram)

    def _coil_temperature(self, t_ring_c: float) -> float:
        """The coil's temperature: the ring's through the model's coil stages (each
        ``s_k += a (s_(k-1) - s_k)``, ``a = 1 - exp(-B / stage)``, s_0 the ring), started at the first finite
        ring temperature, held while it is not finite."""
        if self.coil is None:
            return t_ring_c
        if not math.isfinite(t_ring_c):
            return self.coil_c[-1] if self.coil_c else t_ring_c
        if not self.coil_c:
            self.coil_c = [t_ring_c] * self.coil[1]
            return t_ring_c
        upstream = t_ring_c
        for k in range(len(self.coil_c)):
            self.coil_c[k] += self._coil_a * (upstream - self.coil_c[k])
            upstream = self.coil_c[k]
        return upstream

    @property
    def coil_temperature_c(self) -> float:
        """The temperature the scale factor is taken at now (the coil's, else the last ring reading)."""
        return self.coil_c[-1] if self.coil_c else self._last_ring_c

    @property
    def last_block(self) -> int | None:
        """The index of the newest block recorded since the last break (None: none)."""
        return None if self._ring_first is None else self._ring_first + self._ring_len - 1

    def _rows(self, first: int, end: int) -> np.ndarray:
        assert self._ring_first is not None
        pos = (self._ring_pos0 + np.arange(first - self._ring_first, end - self._ring_first)) % self._cap
        return pos

    # -- per dwell -------------------------------------------------------------------------------

    def _refuse(self, dwell: Dwell, reason: str) -> TableOutcome:
        self.refused += 1
        return self._note(TableOutcome(dwell.t_end_s, "refused", reason))

    def _note(self, outcome: TableOutcome) -> TableOutcome:
        if len(self.outcomes) == self.outcomes.maxlen:
            self._dropped.add(self.outcomes[0])
        self.outcomes.append(outcome)
        self._noted += 1
        return outcome

    def tally(self) -> OutcomeTally:
        """Every dwell's outcome since the law was made, counted (``outcomes`` keeps the last ``MAX_OUTCOMES``)."""
        out = self._dropped.copy()
        for outcome in self.outcomes:
            out.add(outcome)
        return out

    def observe(self, dwell: Dwell) -> TableOutcome:
        """One dwell, once the blocks up to its end have closed.  Returns (and records in ``outcomes``) what
        became of it."""
        order = out_of_order(dwell.t_start_s, self.last_dwell_end_s)
        if order is not None:
            return self._refuse(dwell, order)
        self.last_dwell_end_s = dwell.t_end_s
        try:
            t0, t1 = trimmed_window(dwell.t_start_s, dwell.t_end_s)
        except ValueError as exc:
            return self._refuse(dwell, str(exc))
        b = self.block_s
        first, end = blocks_within(t0, t1, b)
        if self._ring_first is None or self.last_block is None:
            return self._refuse(dwell, "no block since the last break (a gap, a restart, a zero)")
        if first < self._ring_first:
            if not self._ring_full_since:
                return self._refuse(dwell, "the dwell reaches back past a break (a gap, a restart, a zero)")
            first = self._ring_first  # a dwell longer than the ring: its last MAX_WINDOW_S
        if end > self.last_block + 1:
            return self._refuse(dwell, "the dwell ends after the last block closed")
        if end <= first:
            return self._refuse(dwell, "no whole block inside the dwell's trimmed window")
        # motion: every block of the untrimmed dwell still on the ring within the threshold of their median
        lo, hi = blocks_within(dwell.t_start_s + MOTION_MARGIN_S, dwell.t_end_s - MOTION_MARGIN_S, b)
        lo, hi = max(lo, self._ring_first), min(hi, self.last_block + 1)
        rates = self._ring_rate[self._rows(lo, hi)]
        spread = _motion_dph(rates)
        if spread > self.config.static_threshold_dph:
            return self._reject(
                dwell, f"the gyro shows motion during the dwell ({spread:.0f} deg/h off a steady drift)"
            )
        v = _white_var_dph2(rates) if len(rates) >= 3 else math.nan
        unsteady = _unsteady_sigmas(rates, v)
        if unsteady > STEADY_SIGMAS:
            return self._reject(
                dwell, f"the gyro's rate changed during the dwell ({unsteady:.0f} standard errors off a steady one)"
            )
        if dwell.angle_end_deg is not None:  # the creep it declares, against the gyro's rate within it
            creep = self._creep_disagreement(dwell, first, end, v)
            if creep is not None and abs(creep[0]) > CREEP_SIGMAS * creep[1]:
                e, sigma, declared = creep
                return self._reject(
                    dwell,
                    f"the creep it declares ({declared:+.1f} arcsec over the window) disagrees with the gyro's rate "
                    f"within the dwell by {abs(e) / sigma:.1f} sigma",
                    {"innovation_arcsec": e, "sigma_arcsec": sigma},
                )
        if len(rates) >= 3:  # the white noise of a block rate
            self.noise_dwells += 1
            old = 0.0 if math.isnan(self.noise_var_dph2) else self.noise_var_dph2
            self.noise_var_dph2 = old + (v - old) / min(self.noise_dwells, CALIBRATION_INTERVALS)
        summary = self._ring_mid[self._rows(first, end)].mean(axis=0)
        t_mid_s = 0.5 * (first + end) * b  # the mean time of the window's block middles
        angle = angle_at_deg(dwell.angle_deg, dwell.angle_end_deg, dwell.t_start_s, dwell.t_end_s, t_mid_s)
        angle *= ARCSEC_PER_DEG
        here = _Anchor(summary, angle, end - first, first, end, self._epoch)
        anchor = self.anchor
        if anchor is None or anchor.epoch != self._epoch:
            self.anchor = here
            return self._note(TableOutcome(dwell.t_end_s, "anchor"))
        return self._interval(dwell, anchor, here)

    def _creep_disagreement(self, dwell: Dwell, first: int, end: int, v: float) -> tuple[float, float, float] | None:
        """A dwell that declares a creep (``angle_end_deg``) against the gyro within its window, from the middle of
        its first whole block to the middle of its last (span S): the declared creep c over S (the table's
        angle at the two, ``angle_at_deg``), the gyro's angle change less the frozen drift, the bias and the
        adapted drift over S, and their difference ``e = theta - F - bias S - phi . delta - c`` (phi: the
        shape regressors' and the level's sums over S, and the scale factor's ``1e-6 c``); its variance the
        gyro's white noise over S, the frozen model's share (as an interval's), the estimate's ``phi P phi``,
        the bias's spread (``prior_dph``, and the capture's between-interval variance while it runs) and the
        scale factor's prior times c.  Returns ``(e, sigma, c)`` in arcsec; None when it cannot be judged: no
        bias yet (the run's first interval not taken) or a window of one block."""
        if end - first < 2:
            return None
        if self.bias_dph is not None:
            bias, bias_var = self.bias_dph, 0.0
        elif self.bias_time_s > 0:  # the capture so far
            bias = self.bias_sum_arcsec / self.bias_time_s
            spread = [q for q, _ in self.bias_rates]
            bias_var = float(np.var(spread)) if len(spread) >= 2 else 0.0
        else:
            return None
        f_n = self.n_features
        b = self.block_s
        rows = self._ring_mid[self._rows(first, end)]
        d = rows[-1] - rows[0]  # from the first block's middle to the last's
        span = float(d[f_n])
        t0, t1 = (first + 0.5) * b, (end - 0.5) * b
        at = [angle_at_deg(dwell.angle_deg, dwell.angle_end_deg, dwell.t_start_s, dwell.t_end_s, t) for t in (t0, t1)]
        declared = (at[1] - at[0]) * ARCSEC_PER_DEG
        t_int = float(d[f_n + 1]) / span
        phi = np.empty(f_n + 3)
        phi[:f_n] = d[:f_n]
        phi[f_n] = span
        phi[f_n + 1] = 1e-6 * declared
        phi[f_n + 2] = 1e-6 * declared * (t_int - SF_REF_C)
        e = float(d[f_n + 2]) - float(d[f_n + 4]) - bias * span - float(np.dot(phi, self.delta)) - declared
        white = self.noise_var_dph2 if math.isfinite(self.noise_var_dph2) else v if math.isfinite(v) else 0.0
        model = MODEL_NOISE_SHARE * self.model_sigma_dph * span
        sf = 1e-6 * SF_PRIOR_PPM * declared
        var = white * b * span + model * model + float(phi @ self.cov @ phi) + sf * sf
        var += (self.prior_dph**2 + bias_var) * span * span
        return e, math.sqrt(max(var, 1e-30)), declared

    def _reject(self, dwell: Dwell, reason: str, values: dict[str, float] | None = None) -> TableOutcome:
        self.rejected += 1
        self._flag_pending |= FLAG_GUARD
        self.rejections_in_row += 1
        return self._note(_outcome(dwell, "rejected", reason, values))

    def _predict(self, a: _Anchor, bb: _Anchor) -> _Prediction:
        """The interval from anchor ``a`` to ``bb`` as an observation (module docstring): its regressors ``phi``
        (the shape regressors' sums, ``T_eff``, and the scale factor's ``1e-6 m`` and ``1e-6 m (T_int - T_ref)``),
        the angle error left after the frozen drift and the bias (once captured), ``r = theta - m - sum_j K_j
        D_hat_j B - bias T_eff``, in arcsec, and its variance ``R`` from the gyro's white noise and the model's
        share; no state changes."""
        f_n = self.n_features
        b = self.block_s
        d = bb.summary - a.summary
        t_eff = float(d[f_n])
        x = d[:f_n]
        t_int = float(d[f_n + 1]) / t_eff
        theta = float(d[f_n + 2])
        move = bb.angle_arcsec - a.angle_arcsec
        predicted = float(d[f_n + 4])
        bias = 0.0 if self.bias_dph is None else self.bias_dph
        adapted = float(np.dot(x, self.delta[:f_n]) + t_eff * self.delta[f_n])
        gyro_move = theta - bias * t_eff - predicted - adapted
        turns = round((gyro_move - move) / TURN_ARCSEC)
        move += turns * TURN_ARCSEC
        la, lb = a.window_blocks * b, bb.window_blocks * b
        gap = (bb.first_block - a.end_block) * b
        k2 = la / 3.0 + gap + lb / 3.0
        noise = self.noise_var_dph2 * b if math.isfinite(self.noise_var_dph2) else 0.0
        model = MODEL_NOISE_SHARE * self.model_sigma_dph * t_eff
        phi = np.empty(f_n + 3)
        phi[:f_n] = x
        phi[f_n] = t_eff
        phi[f_n + 1] = 1e-6 * move
        phi[f_n + 2] = 1e-6 * move * (t_int - SF_REF_C)
        return _Prediction(
            phi=phi,
            r_arcsec=theta - move - predicted - bias * t_eff,
            r_var=noise * k2 + model * model,
            move_deg=move / ARCSEC_PER_DEG,
            off_deg=(gyro_move - move) / ARCSEC_PER_DEG,
            degraded=bool(d[f_n + 3] > 0.5),
            warming_up=bool(d[f_n + 3] - d[f_n + 5] < 0.5),
        )

    def _innovation(self, p: _Prediction) -> tuple[float, float]:
        """The interval's innovation against the estimate in use, ``e = r - phi . delta``, and its variance before
        the calibration, ``R + phi P phi^T``."""
        return p.r_arcsec - float(np.dot(p.phi, self.delta)), p.r_var + float(p.phi @ self.cov @ p.phi)

    def _calibration(self) -> float:
        """``c``, the running mean of the squared normalized innovations (module docstring)."""
        return (CALIBRATION_PRIOR + self.calibration_sum) / (CALIBRATION_PRIOR + self.calibration_n)

    def _interval(self, dwell: Dwell, a: _Anchor, bb: _Anchor) -> TableOutcome:
        f_n = self.n_features
        b = self.block_s
        p = self._predict(a, bb)
        if p.degraded:  # blocks with degraded inputs in it: not learned; the chain goes on from here
            self.anchor = bb
            self.skipped += 1
            if p.warming_up:
                w = self.config.warmup_s
                why = f"the warm-up: nothing is learned from the first {w:g} s of device time (warmup_s), until {w:g} s"
            else:
                why = "degraded inputs in the interval"
            return self._note(TableOutcome(dwell.t_end_s, "skipped", why))
        if abs(p.off_deg) > AMBIGUOUS_DEG:
            return self._reject(
                dwell, f"the move is {p.off_deg:+.1f} deg from every whole turn of the gyro's: ambiguous"
            )
        phi, r, r_var, t_eff = p.phi, p.r_arcsec, p.r_var, p.t_eff_s
        values = {"move_deg": p.move_deg, "interval_s": t_eff}
        if self.bias_dph is None:  # the bias capture: the T_eff-weighted mean rate left
            return self._capture(dwell, bb, r, t_eff, r_var, values)
        judged = self._judge_by_neighbours(dwell, a, bb)
        if judged is not None:
            return judged
        before = self._snapshot(a)
        calibration = self._calibration()
        try:
            candidates = self._candidates()
        except np.linalg.LinAlgError:
            return self._singular(dwell, bb)
        if not self.h.any():  # nothing learned yet (or since a reset): the priors' spread
            self._blend(candidates)
        e, s_raw = self._innovation(p)
        sigma = math.sqrt(max(s_raw, 1e-30) * calibration)
        z2 = e * e / max(s_raw, 1e-30)
        keep = 1.0 - 1.0 / CALIBRATION_INTERVALS
        self.calibration_sum = keep * self.calibration_sum + min(z2, CALIBRATION_CAP)
        self.calibration_n = keep * self.calibration_n + 1.0
        values.update(innovation_arcsec=e, sigma_arcsec=sigma)
        if abs(e) > TABLE_SIGMAS * sigma:
            outcome = self._reject(dwell, f"disagrees with the gyro by {abs(e) / sigma:.1f} sigma", values)
            self._doubted = _Doubt(a, bb, dwell, e, sigma)
            if self.rejections_in_row >= 2:  # the anchor itself may be the wrong one: start again here
                self.anchor = bb
                self.rejections_in_row = 0
                self._undo = None
            return outcome
        self.rejections_in_row = 0
        sf = phi[f_n + 1] * self.delta[f_n + 1] + phi[f_n + 2] * self.delta[f_n + 2]
        self._add_window((r - sf) / t_eff, e / t_eff)
        t_now = bb.end_block * b
        beta = 1.0 if self.last_update_s is None else math.exp(-max(t_now - self.last_update_s, 0.0) / TABLE_MEMORY_S)
        self.last_update_s = t_now
        weight = 1.0 / max(r_var, 1e-30)
        forget = np.ones(f_n + 3)  # the drift forgets, the scale factor (a constant of the coil) does not
        forget[: f_n + 1] = math.sqrt(beta)
        for k, (delta_k, cov_k) in enumerate(candidates):  # each scale's prediction of r, before learning it
            e_k = r - float(np.dot(phi, delta_k))
            v = (r_var + float(phi @ cov_k @ phi)) * calibration
            self.evidence[k] = beta * self.evidence[k] - 0.5 * (math.log(max(v, 1e-30)) + e_k * e_k / max(v, 1e-30))
        self.h *= np.outer(forget, forget)
        self.h += weight * np.outer(phi, phi)
        self.i *= forget
        self.i += (weight * r) * phi
        try:
            self._blend(self._candidates())
        except np.linalg.LinAlgError:
            return self._singular(dwell, bb)
        self.accepted += 1
        self.anchor = bb
        self._undo = _Undo(before, dwell.t_end_s, bb, e, sigma)
        return self._note(_outcome(dwell, "learned", "", values))

    def _singular(self, dwell: Dwell, bb: _Anchor) -> TableOutcome:
        """The law's equations became singular (not seen in practice): back to the frozen weights, flagged."""
        self.reset_to_frozen()
        self.guards += 1
        self._flag_pending |= FLAG_GUARD
        self.anchor = bb
        return self._note(
            _outcome(dwell, "skipped", "the law's equations are singular: reset to the frozen weights", None)
        )

    #: what learning an interval changes (``_snapshot``): the sums, the estimate, the evidence, the calibration and
    #: the comparison; then the counters (``_COUNTERS``) and the chain's anchor
    _LEARNED = (
        "h",
        "i",
        "delta",
        "cov",
        "evidence",
        "calibration_sum",
        "calibration_n",
        "compare_windows",
        "compare_gain",
        "compare_gain_sq",
        "compare_level_frozen_dph",
        "compare_level_adapted_dph",
        "compare_dev_sq_adapted_dph2",
        "last_update_s",
    )
    _COUNTERS = ("accepted", "rejected", "skipped", "guards", "rejections_in_row", "_flag_pending")

    def _snapshot(self, anchor: _Anchor) -> dict[str, Any]:
        """The law's state before an interval from ``anchor``, to return to (``_restore``)."""
        out: dict[str, Any] = {k: _copied(getattr(self, k)) for k in (*self._LEARNED, *self._COUNTERS)}
        out["anchor"] = anchor
        return out

    def _restore(self, snapshot: dict[str, Any], counters: bool) -> None:
        """Back to ``snapshot``'s learning state and anchor, and its counters when ``counters`` (else they stay:
        what happened since, a dwell rejected for motion say, still happened)."""
        for k in (*self._LEARNED, *self._COUNTERS) if counters else self._LEARNED:
            setattr(self, k, _copied(snapshot[k]))  # a copy: a snapshot kept for a later undo stays as it was
        self.anchor = snapshot["anchor"]

    def _judge_by_neighbours(self, dwell: Dwell, a: _Anchor, bb: _Anchor) -> TableOutcome | None:
        """Dwell k+2 (``bb``) has come after the gate rejected (k, k+1), k the dwell learned last (``a``): which
        of dwells k and k+1 was wrong?  A wrong angle L at a dwell shows in the two intervals around it, as
        innovations ``+L`` and ``-L``; the first can pass the gate when the interval's own error points the other
        way (a 5-sigma lie, about 2 % of the time).  With the innovations e and sigmas s of A = (k-1, k) (learned),
        B = (k, k+1) (rejected) and C = (k+1, k+2) (predicted now, nothing learned), each hypothesis with its L at
        its best:

            k wrong:    chi2_k  = (e_A + e_B)^2 / (s_A^2 + s_B^2) + (e_C / s_C)^2
            k+1 wrong:  chi2_k1 = (e_A / s_A)^2 + (e_B + e_C)^2 / (s_B^2 + s_C^2)
            neither:    chi2_0  = (e_A / s_A)^2 + (e_B / s_B)^2 + (e_C / s_C)^2

        When ``chi2_k < chi2_k1`` and ``chi2_k + TABLE_SIGMAS^2 < chi2_0`` (a wrong dwell costs what the gate
        charges one; without it, an honest run's hard stretch had its dwells blamed), A is undone and (k-1, k+1)
        judged in its place: if it is learned, dwell k is rejected (flagged ``guard`` now: what was published in
        between used it), dwell k+1's outcome is that interval's, and C is judged as usual; its outcome is
        returned.  Otherwise (or when A and B are not the last learned and rejected from ``a``, or C has degraded
        inputs or an ambiguous move) the law is as it was and None is returned: the interval (k, k+2) is judged
        as usual.  (Judged on B alone, with e_A and e_B cancelling, the honest dwell before a lie was blamed as
        often as a lie was caught: on B alone the two cannot be told apart.)"""
        undo, doubt = self._undo, self._doubted
        if undo is None or doubt is None or undo.anchor is not a or doubt.start is not a:
            return None
        c = self._predict(doubt.end, bb)
        if c.degraded or abs(c.off_deg) > AMBIGUOUS_DEG:
            return None
        e_c, s_c_raw = self._innovation(c)
        s_c = math.sqrt(max(s_c_raw, 1e-30) * self._calibration())
        e_a, s_a, e_b, s_b = undo.innovation_arcsec, undo.sigma_arcsec, doubt.innovation_arcsec, doubt.sigma_arcsec
        chi2_k = (e_a + e_b) ** 2 / (s_a * s_a + s_b * s_b) + (e_c / s_c) ** 2
        chi2_k1 = (e_a / s_a) ** 2 + (e_b + e_c) ** 2 / (s_b * s_b + s_c * s_c)
        chi2_none = (e_a / s_a) ** 2 + (e_b / s_b) ** 2 + (e_c / s_c) ** 2
        if chi2_k >= chi2_k1 or chi2_k + TABLE_SIGMAS**2 >= chi2_none:
            return None
        after = self._snapshot(a)
        noted = self._noted
        self._undo = self._doubted = None
        self._restore(undo.before, counters=False)
        merged = self._interval(doubt.dwell, undo.before["anchor"], doubt.end)
        if merged.status != "learned":  # (k-1, k+1) does not agree either: the law as it was
            for _ in range(self._noted - noted):  # the trial's outcome
                self.outcomes.pop()
            self._noted = noted
            self._restore(after, counters=True)
            self._undo, self._doubted = undo, doubt
            return None
        self.outcomes.pop()  # (k-1, k+1)'s outcome goes to dwell k+1, dwell k's becomes rejected
        self._noted -= 1
        for n in range(len(self.outcomes) - 1, -1, -1):
            o = self.outcomes[n]
            if o.t_end_s == doubt.dwell.t_end_s and o.status == "rejected":
                self.outcomes[n] = merged
            elif o.t_end_s == undo.t_end_s and o.status == "learned":
                self.outcomes[n] = o._replace(
                    status="rejected", reason="disagrees with both neighbours: the intervals around it agree"
                )
                break
        self.accepted -= 1  # dwell k's interval, undone (dwell k+1's rejection becomes dwell k's)
        self._flag_pending |= FLAG_GUARD
        return self._interval(dwell, doubt.end, bb)

    def _capture(
        self, dwell: Dwell, bb: _Anchor, r: float, t_eff: float, r_var: float, values: dict[str, float]
    ) -> TableOutcome:
        rate = r / t_eff
        if self.bias_time_s > 0:  # consistent with the capture so far?
            mean = self.bias_sum_arcsec / self.bias_time_s
            spread = [q for q, _ in self.bias_rates]
            between = float(np.var(spread)) if len(spread) >= 2 else 0.0
            sf = 1e-6 * SF_PRIOR_PPM * values["move_deg"] * ARCSEC_PER_DEG / t_eff  # the scale factor, not yet known
            sigma = math.sqrt(r_var / t_eff**2 + between + self.prior_dph**2 + sf * sf)
            if abs(rate - mean) > TABLE_SIGMAS * sigma:
                values.update(innovation_arcsec=(rate - mean) * t_eff, sigma_arcsec=sigma * t_eff)
                return self._reject(
                    dwell, f"disagrees with the bias captured so far by {abs(rate - mean) / sigma:.1f} sigma", values
                )
        self.rejections_in_row = 0
        self.bias_rates.append((rate, t_eff))
        self.bias_sum_arcsec += r
        self.bias_time_s += t_eff
        if self.bias_time_s >= self.bias_capture_s:
            self.bias_dph = self.bias_sum_arcsec / self.bias_time_s
        self.anchor = bb
        return self._note(_outcome(dwell, "bias", "", values))

    def _candidates(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """Each prior scale's estimate and covariance, ``(H + L0(s_D)) delta = I``; the scale 0 learns the level
        and the scale factor alone (the drift's shape stays the frozen one's: ``dw = 0``)."""
        f_n = self.n_features
        out = []
        for scale in PRIOR_SCALES:
            delta = np.zeros(f_n + 3)
            cov = np.zeros((f_n + 3, f_n + 3))
            if scale > 0:
                cov[:] = np.linalg.inv(self.h + self._prior(scale * self.runaway_dph))
                delta[:] = cov @ self.i
            else:
                own = slice(f_n, f_n + 3)  # the level and the scale factor: L0's block of them (dw = 0)
                cov[own, own] = np.linalg.inv(self.h[own, own] + self._prior(self.runaway_dph)[own, own])
                delta[own] = cov[own, own] @ self.i[own]
            out.append((delta, cov))
        return out

    def _weights(self) -> np.ndarray:
        """The prior scales' posterior weights: their evidence, with the frozen drift's prior odds."""
        log_w = self.evidence.copy()
        log_w[[k for k, scale in enumerate(PRIOR_SCALES) if scale == 0]] += FROZEN_LOG_ODDS
        w = np.exp(log_w - log_w.max())
        return np.asarray(w / w.sum())

    def _blend(self, candidates: list[tuple[np.ndarray, np.ndarray]]) -> None:
        """The estimate in use: the candidates' mean under their weights, and its covariance (the mixture's)."""
        w = self._weights()
        self.delta = sum(wk * d for wk, (d, _) in zip(w, candidates))
        self.cov = sum(wk * (c + np.outer(d - self.delta, d - self.delta)) for wk, (d, c) in zip(w, candidates))

    def _prior(self, prior_dph: float) -> np.ndarray:
        """L0: the correction's variation over the blocks seen (``dw`` through the regressors' covariance C)
        within ``s_D``, its mean level (``m . dw + db``, m the regressors' mean) within the runaway bound (the
        table's angles see the level: only the runaway bound limits it), the scale factor within its priors."""
        f_n = self.n_features
        n = f_n + 3
        out = np.zeros((n, n))
        if self.gram_weight > 0:
            g = self.gram / self.gram_weight
            mean = g[f_n, :f_n]
            cov = g[:f_n, :f_n] - np.outer(mean, mean)
        else:
            mean, cov = np.zeros(f_n), np.eye(f_n)
        ridge = 1e-6 * float(np.trace(cov)) / max(f_n, 1) + 1e-12
        level = 1.0 / self.runaway_dph**2
        out[:f_n, :f_n] = f_n * (cov + ridge * np.eye(f_n)) / prior_dph**2 + level * np.outer(mean, mean)
        out[:f_n, f_n] = out[f_n, :f_n] = level * mean
        out[f_n, f_n] = level
        out[f_n + 1, f_n + 1] = 1.0 / SF_PRIOR_PPM**2
        out[f_n + 2, f_n + 2] = 1.0 / SF_SLOPE_PRIOR_PPM_PER_C**2
        return out

    # -- state ---------------------------------------------------------------------------------------

    _ARRAYS = ("h", "i", "delta", "cov", "gram", "evidence")
    _FLOATS = (
        "gram_weight",
        "noise_var_dph2",
        "calibration_sum",
        "calibration_n",
        "compare_gain",
        "compare_gain_sq",
        "compare_level_frozen_dph",
        "compare_level_adapted_dph",
        "compare_dev_sq_adapted_dph2",
    )
    _COUNTS = (
        "noise_dwells",
        "accepted",
        "rejected",
        "refused",
        "skipped",
        "guards",
        "clamped_blocks",
        "compare_windows",
    )
    #: keys a state saved by an earlier version lacks, and what they start from
    _ADDED = {
        "evidence": lambda: [0.0] * len(PRIOR_SCALES),
        "clamped_blocks": lambda: 0,
        "shape": lambda: SHAPE_REGRESSORS,
    }

    def state_dict(self) -> dict[str, Any]:
        """What the law learned, as plain YAML-safe values (exact): its sums, weights, covariance and the
        regressors' gram, the noise and innovation calibration, the comparison, the counters, and the frozen
        weights it was learned against.  Not the run's own chain (the ring of blocks, the bias, the anchor):
        a restored law starts a new run (``begin_run``)."""
        d: dict[str, Any] = {
            "frozen_weights": [float(v) for v in self.w0],
            "frozen_intercept": self.b0,
            "shape": self.shape,
        }
        d.update({k: np.asarray(getattr(self, k)).tolist() for k in self._ARRAYS})
        d.update({k: float(getattr(self, k)) for k in self._FLOATS})
        d.update({k: int(getattr(self, k)) for k in self._COUNTS})
        return d

    def load_state(self, d: dict[str, Any]) -> None:
        """Inverse of ``state_dict``, as a new run; ``ValueError`` (nothing changed) for missing or unknown keys,
        bad values, or a state learned against other frozen weights (another model)."""
        keys = {"frozen_weights", "frozen_intercept", "shape", *self._ARRAYS, *self._FLOATS, *self._COUNTS}
        if isinstance(d, dict) and keys - set(d) <= set(self._ADDED) and set(d) <= keys:
            d = {**{k: make() for k, make in self._ADDED.items() if k not in d}, **d}  # saved by an earlier version
        if not isinstance(d, dict) or set(d) != keys:
            got = sorted(d) if isinstance(d, dict) else type(d).__name__
            raise ValueError(f"table law state needs exactly the keys {sorted(keys)}, got {got}")
        try:
            w0 = np.array(d["frozen_weights"], dtype=np.float64)
            arrays = {k: np.array(d[k], dtype=np.float64) for k in self._ARRAYS}
            floats = {k: float(d[k]) for k in self._FLOATS}
            b0 = float(d["frozen_intercept"])
        except (TypeError, ValueError) as exc:
            raise ValueError(f"table law state: not numbers: {exc}") from None
        if w0.shape != self.w0.shape or not np.array_equal(w0, self.w0) or b0 != self.b0:
            raise ValueError("table law state was learned against another model (its frozen weights differ)")
        if d["shape"] != self.shape:
            raise ValueError(
                f"table law state was learned on the {d['shape']!r} shape regressors, this law's are {self.shape!r}"
                " (saved by an earlier version, or with the model file's candidates removed or added)"
            )
        n = self.n_features
        shapes = {
            "h": (n + 3, n + 3),
            "i": (n + 3,),
            "delta": (n + 3,),
            "cov": (n + 3, n + 3),
            "gram": (n + 1, n + 1),
            "evidence": (len(PRIOR_SCALES),),
        }
        for k, shape in shapes.items():
            if arrays[k].shape != shape or not np.isfinite(arrays[k]).all():
                raise ValueError(f"table law state: {k} must be {shape} finite numbers")
        if not all(math.isfinite(v) or (k == "noise_var_dph2" and math.isnan(v)) for k, v in floats.items()):
            raise ValueError("table law state: values must be finite")
        counts = {k: d[k] for k in self._COUNTS}
        if any(isinstance(v, bool) or not isinstance(v, int) or v < 0 for v in counts.values()):
            raise ValueError("table law state: counts must be integers >= 0")
        for k, v in {**arrays, **floats, **counts}.items():
            setattr(self, k, v)
        self.last_update_s = None
        self.begin_run()

    def summary(self) -> dict[str, Any]:
        """Counts and the scale factor, for STATUS and reports."""
        s0, s1 = self.scale_factor_ppm
        p = self.n_features + 1
        return {
            "accepted": self.accepted,
            "rejected": self.rejected,
            "refused": self.refused,
            "skipped": self.skipped,
            "guards": self.guards,
            "clamped_blocks": self.clamped_blocks,
            "bias_dph": self.bias_dph,
            "adapted_in_use": self.adapted_in_use,
            "frozen_weight": self.frozen_weight,
            "shape": self.shape,
            "shape_regressors": self.n_features,
            "scale_factor_ppm": s0,
            "scale_factor_ppm_per_c": s1,
            "scale_factor_sigma_ppm": math.sqrt(self.cov[p, p]) if self.accepted else SF_PRIOR_PPM,
            "scale_factor_applied": self.scale_factor_applied,
        }
