"""Adapting from the turntable's angles: the readout learns from dwell-to-dwell intervals (``TableLaw``).

A station that knows its table's angle at every dwell (an encoder, or a polygon and an autocollimator)
gives the law a learning signal that a creeping table cannot fool: the table's own angle changes with
the creep, so the gyro's angle change minus the table's is what the compensation left, whatever the
table did.  (The rate path of ``adapt.OnlineReadout`` learns the rate against a declared rate: a slow
creep there cannot be told from drift.)

The rooms, in the order a dwell goes through them:

- ``window``: the chain's blocks on a ring, their cumulative sums by named column; a dwell's summary, and the
  sums under the kernel between two dwells (x, T_eff, T_int, theta, F).
- ``screen``: what is refused (bad input) and what is rejected for motion, an unsteady rate or a declared
  creep the gyro did not see.
- ``estimate``: the interval as an observation ``r = x . dw + T_eff db + 1e-6 dA s(T_int) + e``, the sums
  H and I, the prior scales' mixture and the estimate in use, ``D_hat + g . dw``.
- ``bias``: the run's bias, captured from its first intervals.
- ``judge``: which of two dwells was wrong, by the intervals around them.
- ``outcomes``: what became of each dwell (``OutcomeStatus``), the log and its tally.
- ``state``: what the law learned and the run's own chain, saved and restored.

The shape regressors g (``SHAPES``).  With a model file that has candidate structures (the coils that explain
the fit data within the noise of the chosen one), g_j are their drifts' departures from the frozen one,
``g_cj = D_c,j - D_hat_j``: the adapted drift ``D_hat + sum_c dw_c (D_c - D_hat)`` is a blend of the structures
the fit could not tell apart (``benchmarks/bench_candidate_span.py``; docs/decisions/2026-12-07-table-law-shapes.md).
Without candidates (a polynomial, an older model file) g_j are the model's own regressors f_j (``D_hat = f . w0 +
b0``).

The bias and the level.  The bias (everything constant) is captured first (``bias``, over ``bias_capture_s``).
The level db is the bias's too, and like it is not published: the drift in use is ``D_hat + g . dw``.  It absorbs
the capture's error and the frozen drift's mean error, which a station's ``?BIAS`` or zero window removes with the
bias (``benchmarks/bench_table.py``; docs/decisions/2026-12-07-table-law-level.md).  Each switch-on
(``begin_run``) captures the bias again and marginalizes the level out of the sums.

The chain.  An interval is rejected and flagged ``guard`` when its innovation is farther than ``TABLE_SIGMAS``
sigmas, ``sqrt(c (R + phi P phi^T))``, or its move more than ``AMBIGUOUS_DEG`` from every whole turn of the
gyro's; nothing is learned from it.  After a rejected interval the next one starts from the last dwell accepted,
so a single wrong angle costs no interval; after two rejections in a row the chain starts again from the latest
dwell.  No interval is learned across a break (``break_chain``: a link gap, a non-finite input) or from blocks
with degraded inputs (thermometer fault, stale, settling) or the warm-up's (the first ``warmup_s`` of device
time): such an interval is skipped, its end the next start.

The guards (``adapt``).  Each interval learned compares, out of sample, the frozen and the adapted drift's errors
over it (``r - scale factor part`` against ``r - phi . delta``, in deg/h over T_eff): the frozen drift is published
again when the adapted one's mean gain falls below minus ``TABLE_COMPARE_SIGMAS`` standard errors after
``compare_min_windows`` intervals.  The adapted drift published is never farther than the runaway bound from the
frozen one: beyond it, it is held at the bound and flagged ``guard`` (``clamped_blocks``), and the law keeps what
it learned (docs/decisions/2026-12-07-table-law-guard.md).  A non-finite number resets the law.

The scale factor.  Once the bias is captured and s0 is known to ``SF_APPLY_SIGMA_PPM`` (its posterior
sigma), the angle is corrected by it: ``dtheta_comp = dtheta - D_hat dt - 1e-6 s(T) dtheta``, flagged
``scale_factor``; T the coil's temperature (the ring's through the model's coil stages, when it has them).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from typing import Any

import numpy as np

from ...dwells import Dwell
from ...flags import FLAG_ADAPTING, FLAG_GUARD
from ..adapt import ComparisonGuard
from ..adapt_config import AdaptConfig, blocks_in
from ..dwell import angle_at_deg, out_of_order
from . import judge
from .bias import BiasCapture
from .estimate import (
    AMBIGUOUS_DEG,
    ARCSEC_PER_DEG,
    SF_PRIOR_PPM,
    SF_REF_C,
    SHAPE_REGRESSORS,
    SHAPES,
    TABLE_SIGMAS,
    MixtureLaw,
)
from .outcomes import OutcomeLog, OutcomeStatus, OutcomeTally, TableOutcome, outcome
from .screen import CREEP_SIGMAS, Refused, Rejected, creep_disagreement, screen
from .state import (
    CHAIN_KEY,
    MIXTURE_KEYS,
    anchor_from,
    anchor_state,
    checked_state,
    dwell_from,
    dwell_state,
    learned_part,
    state_of,
)
from .window import Anchor, BlockWindow

__all__ = ["TableLaw"]

#: The comparison guard's significance for the table law, in standard errors of the mean gain: the frozen drift
#: is published again when the adapted one is worse by more than this (``TableLaw.adapted_in_use``), a backstop
#: behind the weighing (a switch puts steps in the drift).  ``benchmarks/bench_table.py`` measures it;
#: docs/decisions/2026-12-07-table-law-guard.md.
TABLE_COMPARE_SIGMAS = 3.0
#: The comparison guard's memory for the table law, in intervals (about 4 h of 5-min intervals): over the
#: rate path's 12 a gain of squared errors cannot reach 3 standard errors, however much worse the adapted drift.
TABLE_COMPARE_MEMORY_INTERVALS = 48.0
#: The learned scale factor is applied once its offset is known to this (posterior sigma, ppm).
SF_APPLY_SIGMA_PPM = 5.0
#: The drift's spread the bias capture allows for, in runaway bounds.
CAPTURE_PRIOR_RUNAWAYS = 0.1


class TableLaw(ComparisonGuard):
    """The readout's law from table angles (module docstring): ``estimate(y_frozen, g)`` per block (a priori),
    ``block(...)`` to record it, ``observe(dwell)`` when a dwell's blocks have closed; ``break_chain`` at a
    break; ``get_state``/``set_state`` for what it learned and its chain."""

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
        #: what the law's shape regressors g are (module docstring)
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
        self.n_features = len(self.w0) if n_shape is None else int(n_shape)
        self.block_s = float(block_s)
        self._set_bounds(fit_residual_dph)
        #: the drift's spread the bias capture allows for
        self.prior_dph = CAPTURE_PRIOR_RUNAWAYS * self.runaway_dph
        self.bias_capture_s = blocks_in(self.config.bias_capture_s, self.block_s) * self.block_s
        #: the estimate: the sums, the prior scales' mixture, the noise and the calibration
        self.mixture = MixtureLaw(self.n_features, self.block_s, self.runaway_dph)
        self.window = BlockWindow(self.n_features, self.block_s)
        self._log = OutcomeLog()
        self._last_ring_c = math.nan
        self._reset_comparison()
        self.accepted = self.rejected = self.refused = self.skipped = 0
        self.guards = 0
        self.clamped_blocks = 0
        self.rejections_in_row = 0
        self._flag_pending = 0
        self.begin_run()

    def begin_run(self) -> None:
        """A new switch-on: the bias is captured again, the chain of dwells starts afresh, and the level, the
        bias's, is a new one too (``MixtureLaw.new_level``); the law's sums on the shape and the scale factor are
        kept."""
        try:
            self.mixture.new_level()
        except np.linalg.LinAlgError:
            self.reset_to_frozen()
            self.guards += 1
        self.bias = BiasCapture(self.bias_capture_s)
        self.break_chain()
        self.last_dwell_end_s: float | None = None

    def break_chain(self) -> None:
        """The chain is broken (a gap, a restart, ``?ZERO``): no interval is learned across it."""
        self.window.break_chain()
        self.anchor: Anchor | None = None
        #: the last interval learned, while it may still be undone (``judge``)
        self._learned: judge.Learned | None = None
        #: the interval the gate rejected last (``judge``)
        self._doubted: judge.Doubted | None = None

    def _reset_comparison(self) -> None:
        self.compare_windows = 0
        self.compare_gain = 0.0
        self.compare_gain_sq = 0.0
        self.compare_level_frozen_dph = 0.0
        self.compare_level_adapted_dph = 0.0
        self.compare_dev_sq_adapted_dph2 = 0.0

    def reset_to_frozen(self) -> None:
        """The adapted weights back to the frozen ones, the law's information cleared (non-finite numbers)."""
        self.mixture.reset()
        self._reset_comparison()

    # -- what the law holds ----------------------------------------------------------------------

    @property
    def bias_dph(self) -> float | None:
        """The run's bias (``bias``), None while it is captured."""
        return self.bias.bias_dph

    @bias_dph.setter
    def bias_dph(self, value: float | None) -> None:
        self.bias.bias_dph = value

    @property
    def h(self) -> np.ndarray:
        return self.mixture.h

    @property
    def i(self) -> np.ndarray:
        return self.mixture.i

    @property
    def delta(self) -> np.ndarray:
        """The estimate in use (``estimate.Layout``: dw, db, s0, s1)."""
        return self.mixture.delta

    @delta.setter
    def delta(self, value: np.ndarray) -> None:
        self.mixture.delta = value

    @property
    def cov(self) -> np.ndarray:
        return self.mixture.cov

    @property
    def evidence(self) -> np.ndarray:
        return self.mixture.evidence

    @property
    def outcomes(self) -> deque[TableOutcome]:
        """The dwells' outcomes, in order, the last ``outcomes.MAX_OUTCOMES`` (``tally`` counts them all)."""
        return self._log.recent

    def tally(self) -> OutcomeTally:
        """Every dwell's outcome since the law was made, counted."""
        return self._log.tally()

    @property
    def chain_start_s(self) -> float | None:
        """Device time the chain of blocks began at (its first block's start), None before a block."""
        return self.window.chain_start_s

    @property
    def last_block(self) -> int | None:
        """The index of the newest block recorded since the last break (None: none)."""
        return self.window.last_block

    @property
    def adapted_in_use(self) -> bool:
        """Once the bias is captured, unless the comparison guard finds the adapted drift worse than the frozen
        one (``adapt.ComparisonGuard._comparison_fails``): the weighing of the prior scales has already chosen
        between the frozen drift and the adapted ones, on the same out-of-sample errors."""
        return self.bias_dph is not None and not self._comparison_fails()

    @property
    def frozen_weight(self) -> float:
        """The frozen drift's weight among the prior scales (1 before any interval is learned)."""
        return self.mixture.frozen_weight

    @property
    def scale_factor_applied(self) -> bool:
        """Once the bias is captured and an interval learned, s0's posterior variance at most
        ``SF_APPLY_SIGMA_PPM^2``."""
        sf0 = self.mixture.layout.sf0
        return bool(
            self.bias_dph is not None
            and self.accepted > 0
            and 0.0 < self.mixture.cov[sf0, sf0] <= SF_APPLY_SIGMA_PPM**2
        )

    @property
    def scale_factor_ppm(self) -> tuple[float, float]:
        """The learned (s0 ppm, s1 ppm/degC)."""
        return self.mixture.scale_factor_ppm

    def scale_ppm_at(self, t_ring_c: float) -> float:
        """``s(T) = s0 + s1 (T - SF_REF_C)`` in ppm when applied, else 0."""
        if not self.scale_factor_applied or not math.isfinite(t_ring_c):
            return 0.0
        s0, s1 = self.scale_factor_ppm
        return s0 + s1 * (t_ring_c - SF_REF_C)

    # -- per block -------------------------------------------------------------------------------

    def estimate(self, y_frozen: float, g: np.ndarray) -> tuple[float, float, int]:
        """``(frozen estimate, estimate in use, flags)`` from this block's frozen drift and shape regressors ``g``
        (the weights before any dwell this block delivers): ``y_frozen + g . dw``, without the level ``db``, which
        is the bias's (module docstring).  A change beyond the runaway bound is held at it (``guard``); a
        non-finite one resets the law."""
        flags, self._flag_pending = self._flag_pending, 0
        if not math.isfinite(y_frozen):
            return y_frozen, y_frozen, FLAG_GUARD
        lay = self.mixture.layout
        change = float(np.dot(g, self.mixture.delta[lay.shape]))
        if not math.isfinite(change) or not math.isfinite(self.mixture.delta[lay.level]):
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
        t_ring_c = self._coil_temperature(t_ring_c)
        self._last_ring_c = t_ring_c
        finite = math.isfinite(rate_dph) and math.isfinite(t_ring_c) and math.isfinite(frames_s)
        if g is None or not finite or not math.isfinite(y_frozen) or not np.isfinite(g).all():
            self.break_chain()
            return
        if not self.window.follows(index):
            self.break_chain()  # blocks missing in between
        inc = self.window.columns.increment(g, y_frozen, self.block_s, t_ring_c, rate_dph, frames_s, clean, warming_up)
        self.window.add(index, inc, rate_dph)
        if clean:  # the regressors' gram, for the prior
            self.mixture.add_to_gram(g)

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

    # -- per dwell -------------------------------------------------------------------------------

    def observe(self, dwell: Dwell) -> TableOutcome:
        """One dwell, once the blocks up to its end have closed.  Returns (and records in ``outcomes``) what
        became of it."""
        judged = self._judged(dwell)  # first: judging may revise the log (``_judge_by_neighbours``)
        return self._log.note(judged)

    def _judged(self, dwell: Dwell) -> TableOutcome:
        order = out_of_order(dwell.t_start_s, self.last_dwell_end_s)
        if order is not None:
            return self._refuse(dwell, order)
        self.last_dwell_end_s = dwell.t_end_s
        screened = screen(dwell, self.window, self.config.static_threshold_dph)
        if isinstance(screened, Refused):
            return self._refuse(dwell, screened.reason)
        if isinstance(screened, Rejected):
            return self._reject(dwell, screened.reason)
        if dwell.angle_end_deg is not None:  # the creep it declares, against the gyro's rate within it
            creep = creep_disagreement(dwell, self.window, screened, self.mixture, self.bias.so_far(), self.prior_dph)
            if creep is not None and abs(creep[0]) > CREEP_SIGMAS * creep[1]:
                e, sigma, declared = creep
                return self._reject(
                    dwell,
                    f"the creep it declares ({declared:+.1f} arcsec over the window) disagrees with the gyro's rate "
                    f"within the dwell by {abs(e) / sigma:.1f} sigma",
                    {"innovation_arcsec": e, "sigma_arcsec": sigma},
                )
        first, end = screened.first, screened.end
        if len(screened.rates) >= 3:  # the white noise of a block rate
            self.mixture.add_noise(screened.white_var_dph2)
        summary = self.window.means(first, end)
        t_mid_s = 0.5 * (first + end) * self.block_s  # the mean time of the window's block middles
        angle = angle_at_deg(dwell.angle_deg, dwell.angle_end_deg, dwell.t_start_s, dwell.t_end_s, t_mid_s)
        angle *= ARCSEC_PER_DEG
        here = Anchor(summary, angle, end - first, first, end, self.window.epoch)
        anchor = self.anchor
        if anchor is None or anchor.epoch != self.window.epoch:
            self.anchor = here
            return TableOutcome(dwell.t_end_s, OutcomeStatus.ANCHOR)
        return self._interval(dwell, anchor, here)

    def _refuse(self, dwell: Dwell, reason: str) -> TableOutcome:
        self.refused += 1
        return TableOutcome(dwell.t_end_s, OutcomeStatus.REFUSED, reason)

    def _reject(self, dwell: Dwell, reason: str, values: dict[str, float] | None = None) -> TableOutcome:
        self.rejected += 1
        self._flag_pending |= FLAG_GUARD
        self.rejections_in_row += 1
        return outcome(dwell, OutcomeStatus.REJECTED, reason, values)

    def _interval(self, dwell: Dwell, a: Anchor, bb: Anchor) -> TableOutcome:
        """The interval from ``a`` to ``bb``, ending at ``dwell``: skipped, rejected, an interval of the bias
        capture, or judged by the neighbours (``_judge_by_neighbours``), gated and learned."""
        p = self.mixture.predict(a, bb, self.window.columns, self.bias_dph)
        if p.degraded:  # blocks with degraded inputs in it: not learned; the chain goes on from here
            self.anchor = bb
            self.skipped += 1
            if p.warming_up:
                w = self.config.warmup_s
                why = f"the warm-up: nothing is learned from the first {w:g} s of device time (warmup_s), until {w:g} s"
            else:
                why = "degraded inputs in the interval"
            return TableOutcome(dwell.t_end_s, OutcomeStatus.SKIPPED, why)
        if abs(p.off_deg) > AMBIGUOUS_DEG:
            return self._reject(
                dwell, f"the move is {p.off_deg:+.1f} deg from every whole turn of the gyro's: ambiguous"
            )
        r, r_var, t_eff = p.r_arcsec, p.r_var, p.t_eff_s
        values = {"move_deg": p.move_deg, "interval_s": t_eff}
        if self.bias_dph is None:  # the bias capture: the T_eff-weighted mean rate left
            return self._capture(dwell, bb, r, t_eff, r_var, values)
        judged = self._judge_by_neighbours(dwell, a, bb)
        if judged is not None:
            return judged
        before = self._snapshot(a)
        calibration = self.mixture.calibration()
        try:
            candidates = self.mixture.candidates()
        except np.linalg.LinAlgError:
            return self._singular(dwell, bb)
        if not self.mixture.h.any():  # nothing learned yet (or since a reset): the priors' spread
            self.mixture.blend(candidates)
        e, s_raw = self.mixture.innovation(p)
        sigma = math.sqrt(max(s_raw, 1e-30) * calibration)
        self.mixture.calibrate(e * e / max(s_raw, 1e-30))
        values.update(innovation_arcsec=e, sigma_arcsec=sigma)
        if abs(e) > TABLE_SIGMAS * sigma:
            rejected = self._reject(dwell, f"disagrees with the gyro by {abs(e) / sigma:.1f} sigma", values)
            self._doubted = judge.Doubted(a, bb, dwell, e, sigma)
            if self.rejections_in_row >= 2:  # the anchor itself may be the wrong one: start again here
                self.anchor = bb
                self.rejections_in_row = 0
                self._learned = None
            return rejected
        self.rejections_in_row = 0
        sf = self.mixture.scale_factor_part(p.phi)
        self._add_window((r - sf) / t_eff, e / t_eff)
        try:
            self.mixture.learn(p, candidates, calibration, bb.end_block * self.block_s)
        except np.linalg.LinAlgError:
            return self._singular(dwell, bb)
        self.accepted += 1
        self.anchor = bb
        self._learned = judge.Learned(before, dwell.t_end_s, bb, e, sigma)
        return outcome(dwell, OutcomeStatus.LEARNED, "", values)

    def _capture(
        self, dwell: Dwell, bb: Anchor, r: float, t_eff: float, r_var: float, values: dict[str, float]
    ) -> TableOutcome:
        """An interval of the bias capture (``bias``): rejected when it disagrees with the capture so far, else
        taken."""
        off = self.bias.disagreement(r, t_eff, r_var, values["move_deg"], self.prior_dph)
        if off is not None:
            rate_off, sigma = off
            values.update(innovation_arcsec=rate_off * t_eff, sigma_arcsec=sigma * t_eff)
            return self._reject(
                dwell, f"disagrees with the bias captured so far by {abs(rate_off) / sigma:.1f} sigma", values
            )
        self.rejections_in_row = 0
        self.bias.add(r, t_eff)
        self.anchor = bb
        return outcome(dwell, OutcomeStatus.BIAS, "", values)

    def _singular(self, dwell: Dwell, bb: Anchor) -> TableOutcome:
        """The law's equations became singular (not seen in practice): back to the frozen weights, flagged."""
        self.reset_to_frozen()
        self.guards += 1
        self._flag_pending |= FLAG_GUARD
        self.anchor = bb
        return TableOutcome(
            dwell.t_end_s, OutcomeStatus.SKIPPED, "the law's equations are singular: reset to the frozen weights"
        )

    # -- the judge by the neighbours -------------------------------------------------------------

    #: the comparison's figures, which learning an interval changes beside the law's (``_snapshot``)
    _COMPARISON = (
        "compare_windows",
        "compare_gain",
        "compare_gain_sq",
        "compare_level_frozen_dph",
        "compare_level_adapted_dph",
        "compare_dev_sq_adapted_dph2",
    )
    #: the counters an undone trial puts back (``_restore``)
    _COUNTERS = ("accepted", "rejected", "skipped", "guards", "rejections_in_row", "_flag_pending")

    def _snapshot(self, anchor: Anchor) -> dict[str, Any]:
        """The law's state before an interval from ``anchor``, to return to (``_restore``)."""
        return {
            "law": self.mixture.snapshot(),
            **{k: getattr(self, k) for k in (*self._COMPARISON, *self._COUNTERS)},
            "anchor": anchor,
        }

    def _restore(self, snapshot: dict[str, Any], counters: bool) -> None:
        """Back to ``snapshot``'s learning state and anchor, and its counters when ``counters`` (else they stay:
        what happened since, a dwell rejected for motion say, still happened)."""
        self.mixture.restore(snapshot["law"])
        for k in (*self._COMPARISON, *self._COUNTERS) if counters else self._COMPARISON:
            setattr(self, k, snapshot[k])
        self.anchor = snapshot["anchor"]

    def _judge_by_neighbours(self, dwell: Dwell, a: Anchor, bb: Anchor) -> TableOutcome | None:
        """Dwell k+2 (``bb``) has come after the gate rejected (k, k+1), k the dwell learned last (``a``): when
        the judge blames dwell k (``judge.blames_the_learned``), (k-1, k) is undone and (k-1, k+1) judged in
        its place: if it is learned, the outcomes are revised (``judge.revision``: dwell k rejected, flagged
        ``guard`` now, since what was published in between used it; dwell k+1's outcome that interval's) and
        (k+1, k+2) is judged as usual, its outcome returned.  Otherwise (or when (k-1, k) and (k, k+1) are not
        the last learned and rejected from ``a``, or (k+1, k+2) has degraded inputs or an ambiguous move) the
        law is as it was and None is returned: the interval (k, k+2) is judged as usual."""
        learned, doubted = self._learned, self._doubted
        if learned is None or doubted is None or learned.anchor is not a or doubted.start is not a:
            return None
        c = self.mixture.predict(doubted.end, bb, self.window.columns, self.bias_dph)
        if c.degraded or abs(c.off_deg) > AMBIGUOUS_DEG:
            return None
        e_c, s_c_raw = self.mixture.innovation(c)
        s_c = math.sqrt(max(s_c_raw, 1e-30) * self.mixture.calibration())
        if not judge.blames_the_learned(learned, doubted, e_c, s_c):
            return None
        after = self._snapshot(a)
        self._learned = self._doubted = None
        self._restore(learned.before, counters=False)
        merged = self._interval(doubted.dwell, learned.before["anchor"], doubted.end)
        if merged.status != OutcomeStatus.LEARNED:  # (k-1, k+1) does not agree either: the law as it was
            self._restore(after, counters=True)
            self._learned, self._doubted = learned, doubted
            return None
        self._log = self._log.revised(judge.revision(learned, merged))
        self.accepted -= 1  # dwell k's interval, undone (dwell k+1's rejection becomes dwell k's)
        self._flag_pending |= FLAG_GUARD
        return self._interval(dwell, doubted.end, bb)

    # -- state -----------------------------------------------------------------------------------

    def get_state(self) -> dict[str, Any]:
        """Everything the law continues from, as plain YAML-safe values (exact; ``state``): what it learned (its
        sums, weights, covariance and the regressors' gram, the noise and innovation calibration, the comparison,
        the counters, and the frozen weights it was learned against: ``state.learned_part``) and, under
        ``state.CHAIN_KEY``, the run's own chain (``_chain_state``)."""
        state = self.learned_state()
        state[CHAIN_KEY] = self._chain_state()
        return state

    def learned_state(self) -> dict[str, Any]:
        """What the law learned: ``get_state`` without its chain (``state.learned_part`` of it), built without the
        chain; what the adaptation document keeps."""
        return state_of(self.w0, self.b0, self.shape, lambda k: getattr(self.mixture if k in MIXTURE_KEYS else self, k))

    def set_state(self, state: dict[str, Any]) -> None:
        """Inverse of ``get_state``: the law continues exactly; a state without the chain (what the law learned
        alone, ``state.learned_part``) as a new run (``begin_run``).  ``ValueError`` (nothing changed) for missing or
        unknown keys, bad values, or a state learned against other frozen weights (another model)."""
        chain = state.get(CHAIN_KEY) if isinstance(state, dict) else None
        values = checked_state(
            learned_part(state) if isinstance(state, dict) else state, self.w0, self.b0, self.shape, self.n_features
        )
        restore_chain = None if chain is None else self._chain_from(chain)
        for k, v in values.items():
            setattr(self.mixture if k in MIXTURE_KEYS else self, k, v)
        if restore_chain is None:
            self.mixture.last_update_s = None
            self.begin_run()
        else:
            restore_chain()

    def _chain_state(self) -> dict[str, Any]:
        """The run's own chain as plain values: the ring, the bias capture, the outcome log, the anchors (each
        once: the law tells them apart by identity) and which is the current one, the interval learned last
        (with the law before it) and the one rejected last, the coil's temperatures, the last ring temperature,
        the rejections in a row, the flags pending, the last dwell's end and the last interval's time."""
        anchors: list[Anchor] = []

        def ref(a: Anchor | None) -> int | None:
            if a is None:
                return None
            for k, seen in enumerate(anchors):
                if seen is a:
                    return k
            anchors.append(a)
            return len(anchors) - 1

        learned_last, doubted = self._learned, self._doubted
        chain: dict[str, Any] = {
            "window": self.window.get_state(),
            "bias": self.bias.get_state(),
            "outcomes": self._log.get_state(),
            "anchor": ref(self.anchor),
            "learned": None,
            "doubted": None,
            "coil_c": [float(v) for v in self.coil_c],
            "last_ring_c": float(self._last_ring_c),
            "rejections_in_row": int(self.rejections_in_row),
            "flag_pending": int(self._flag_pending),
            "last_dwell_end_s": _optional(self.last_dwell_end_s),
            "last_update_s": _optional(self.mixture.last_update_s),
        }
        if learned_last is not None:
            before = learned_last.before
            chain["learned"] = {
                "before": {
                    "law": {k: _plain(v) for k, v in before["law"].items()},
                    **{k: _plain(before[k]) for k in (*self._COMPARISON, *self._COUNTERS)},
                    "anchor": ref(before["anchor"]),
                },
                "t_end_s": float(learned_last.t_end_s),
                "anchor": ref(learned_last.anchor),
                "innovation_arcsec": float(learned_last.innovation_arcsec),
                "sigma_arcsec": float(learned_last.sigma_arcsec),
            }
        if doubted is not None:
            chain["doubted"] = {
                "start": ref(doubted.start),
                "end": ref(doubted.end),
                "dwell": dwell_state(doubted.dwell),
                "innovation_arcsec": float(doubted.innovation_arcsec),
                "sigma_arcsec": float(doubted.sigma_arcsec),
            }
        chain["anchors"] = [anchor_state(a) for a in anchors]
        return chain

    def _chain_from(self, chain: dict[str, Any]) -> Callable[[], None]:
        """``_chain_state``'s values checked and made: a function that puts them in place (nothing changed until
        it is called); ``ValueError`` for values that are not a chain of this law."""
        try:
            window = BlockWindow(self.n_features, self.block_s)
            window.set_state(chain["window"])
            bias = BiasCapture(self.bias_capture_s)
            bias.set_state(chain["bias"])
            log = OutcomeLog()
            log.set_state(chain["outcomes"])
            anchors = [anchor_from(a, window.columns.width) for a in chain["anchors"]]

            def at(k: Any) -> Anchor | None:
                if k is not None and not 0 <= int(k) < len(anchors):
                    raise ValueError(f"no anchor {k!r} of {len(anchors)}")
                return None if k is None else anchors[int(k)]

            def held(k: Any) -> Anchor:
                a = at(k)
                if a is None:
                    raise ValueError("an interval's anchor is missing")
                return a

            learned_last = doubted = None
            if chain["learned"] is not None:
                c = chain["learned"]
                b = c["before"]
                law = {k: _array_or(b["law"][k]) for k in self.mixture.LEARNED}
                snapshot = {
                    "law": law,
                    **{k: _number_like(getattr(self, k), b[k]) for k in (*self._COMPARISON, *self._COUNTERS)},
                    "anchor": at(b["anchor"]),
                }
                learned_last = judge.Learned(
                    snapshot,
                    float(c["t_end_s"]),
                    held(c["anchor"]),
                    float(c["innovation_arcsec"]),
                    float(c["sigma_arcsec"]),
                )
            if chain["doubted"] is not None:
                c = chain["doubted"]
                doubted = judge.Doubted(
                    held(c["start"]),
                    held(c["end"]),
                    dwell_from(c["dwell"]),
                    float(c["innovation_arcsec"]),
                    float(c["sigma_arcsec"]),
                )
            coil_c = [float(v) for v in chain["coil_c"]]
            scalars = (
                at(chain["anchor"]),
                float(chain["last_ring_c"]),
                int(chain["rejections_in_row"]),
                int(chain["flag_pending"]),
                _optional(chain["last_dwell_end_s"]),
                _optional(chain["last_update_s"]),
            )
            if len(chain) != len(CHAIN_FIELDS) or set(chain) != CHAIN_FIELDS:
                raise ValueError(f"needs exactly the keys {sorted(CHAIN_FIELDS)}, got {sorted(chain)}")
            if len(coil_c) != (0 if self.coil is None or not coil_c else self.coil[1]):
                raise ValueError(f"{len(coil_c)} coil temperatures for a coil of {self.coil}")
        except (KeyError, TypeError, ValueError, IndexError, AttributeError) as exc:
            raise ValueError(f"table law state: not a chain of this law: {exc}") from None

        def put() -> None:
            self.window, self.bias, self._log = window, bias, log
            self._learned, self._doubted, self.coil_c = learned_last, doubted, coil_c
            (
                self.anchor,
                self._last_ring_c,
                self.rejections_in_row,
                self._flag_pending,
                self.last_dwell_end_s,
                self.mixture.last_update_s,
            ) = scalars

        return put

    def summary(self) -> dict[str, Any]:
        """Counts and the scale factor, for STATUS and reports."""
        s0, s1 = self.scale_factor_ppm
        sf0 = self.mixture.layout.sf0
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
            "scale_factor_sigma_ppm": math.sqrt(self.mixture.cov[sf0, sf0]) if self.accepted else SF_PRIOR_PPM,
            "scale_factor_applied": self.scale_factor_applied,
        }


#: the keys of the chain's state (``TableLaw._chain_state``)
CHAIN_FIELDS = frozenset(
    ("window", "bias", "outcomes", "anchor", "learned", "doubted", "coil_c", "last_ring_c", "rejections_in_row")
    + ("flag_pending", "last_dwell_end_s", "last_update_s", "anchors")
)


def _optional(value: Any) -> float | None:
    """A time or None, as a plain float."""
    return None if value is None else float(value)


def _plain(value: Any) -> Any:
    """A snapshot's value as plain values: an array as lists, a number as a float or an int, None as it is."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if value is None or isinstance(value, int):
        return value
    return float(value)


def _array_or(value: Any) -> Any:
    """Inverse of ``_plain`` for the estimate's snapshot: lists as an array, a number as a float."""
    if isinstance(value, list):
        return np.array(value, dtype=np.float64)
    return None if value is None else float(value)


def _number_like(current: Any, value: Any) -> int | float:
    """``value`` as the kind of number ``current`` is (a count an int, else a float)."""
    return int(value) if isinstance(current, int) else float(value)
