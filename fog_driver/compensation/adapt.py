"""Online adaptation of the readout (stage 3 in operation): the adaptive law run from the stored weights,
gated by a reference, with guards.

Frozen or adapting.  A model file holds frozen weights: ``D_hat = f . w0 + b0`` over the model's regressor
row f (``regressors_step``).  ``OnlineReadout`` keeps running the adaptive law (``readout.AdaptiveLaw``)
over the regressors ``x = [f, 1]``, warm-started at ``W = [w0, b0]``, and returns ``D_hat = f . W[:-1] +
W[-1]`` (summed strictly left to right, ``numerics.dot``: while W equals the stored weights the estimate
is the frozen one bit for bit).

The target.  Online, the only measurement of the drift is the gyro itself: on a block where the input
rate is known (``reference_rate_dph``: the table's rate, 0 when it stands still; the Earth rate along a
vertical axis need not be in it, see below)::

    d = measured_rate_dph - reference_rate_dph - bias_dph

where ``bias_dph`` is everything constant the drift model does not model: the Earth-rate component, the
constant bias and this run's turn-on bias (different at every switch-on, unknown online; the fit removes
it per capture by centring the target).  It is captured first: over the first ``bias_capture_s`` of gated
blocks (below) the readout accumulates the mean of ``measured - reference - estimate`` (the estimate in
use, which is the frozen estimate on a first run: W does not move before the capture is complete); W is
not updated during the capture, and adaptation starts on the next gated block.  ``begin_run`` starts a
new capture (a restored state on a new switch-on: the turn-on bias is new, the adapted W is kept).  Without the capture,
the adapted intercept would absorb the run's bias (tens of deg/h), the output would stop being a drift and the
runaway guard would fire at once (tested).  A consequence to know: whatever error the frozen model makes
on average during the capture is taken as bias, so the adapted model learns the drift relative to the
frozen model's mean error over the capture (the drift's slopes are learned; its offset over the capture
is not observable from the gyro alone).  ``bias_capture_s = 0`` skips the capture (bias 0): for a
reference that already contains every constant.

The gate.  W is updated only on gated blocks: a reference is given AND the table is ``static`` (a known
input rate while nothing moves; ``StaticDetector`` tells it from the gyro itself) AND the measured rate is
finite.  On every other block the law tracks with W held (``AdaptiveLaw.track``: its filters and the sums
H, I go on, so re-enabling is seamless), with a neutral target: the current estimate ``W . x`` itself.  While W is
fixed the filtered neutral target is exactly ``W . Xf``, so those blocks add nothing to ``M = H W - I`` at
the current W: they carry no information and say "stay" (they still weigh in H, a mild pull towards the
W of that time for one memory window).  The same neutral target is used during the bias capture.

The innovation gate: the rate must match the reference.  A static detector sees only the spread of the
rate; a table that turns steadily or creeps while the reference says 0 looks static, and its rate would
be learned as drift.  So on a gated block after the capture the innovation ``d - frozen estimate`` goes
through an exponential mean over ``GATE_FILTER_S`` (120 s), and when that filtered
innovation is farther from 0 than the runaway bound plus ``innovation_sigmas`` (4) sigmas of its noise
(``gate_limit_dph``; the block noise from half the squared differences of successive gated rates over
``NOISE_MEMORY_S``, each capped at 25 times the estimate so far and at the static detector's threshold
squared so that a bad block cannot open the gate, through the same filter), the block is not learned (the neutral
target, as for an ungated block), is counted (``rejected``) and flagged ``FLAG_GUARD``, and W is reset to the frozen
weights as by a guard (what the law learned while the mismatch grew towards the bound is suspect too).
No drift the law may learn is that far from the frozen model: the gyro disagrees with the reference.  The filter starts
afresh after any ungated block.  A creep of a few deg/h is refused within seconds; one near the bound (0.2 deg/h on a
model with 0.024 deg/h of fit residual) within minutes; a slower one is learned, and the runaway guard
bounds what it does to the estimate.

Guards.  Before it is returned, the adapted estimate is checked against the frozen one: not finite, or
further than the runaway bound from it, and the frozen estimate is returned instead, the block is
flagged ``FLAG_GUARD`` and W is reset to the frozen weights with the law's accumulated information
cleared (``reset_to_frozen``: the filters, H and I start again from zero; kept, they would lead W straight
back to the solution that ran away).  A non-finite W after an update is reset the same way.  The
runaway bound is ``AdaptConfig.runaway_dph``, or by default ``runaway_for`` the model's fit residual:
5 times the 1-min RMS it left on its own fit data (0.12 deg/h for 0.024), within 0.05 to 2 deg/h: an
adapted model that departs from the frozen one by several times what the frozen one left on its data is
learning something else.  When the frozen estimate itself is not finite (non-finite regressors) there
is nothing to revert to: it is returned with ``FLAG_GUARD``, W untouched.  ``FLAG_ADAPTING`` marks a
block whose target updated W, and every block whose estimate is the adapted weights' rather than the
frozen ones' (also weights restored from a state file while no reference is given: the operator sees
which weights are in use).

The comparison guard: adapting must earn its place.  On a run the frozen model already fits, the law
chases the gyro's own slow noise and makes things worse; so on every gated update block both estimates'
errors against the target (``d - frozen``, ``d - adapted``) are summed over windows of
``compare_window_s``, each window's mean error is taken about that estimate's running mean of them (a
constant offset is not drift: the bias capture leaves the frozen estimate one, the adapted intercept
would remove it and seem better for it), and the window's gain, ``dev_frozen^2 - dev_adapted^2``, goes
into a running mean and mean square (memory ``compare_memory_windows``).  Both estimates see the same
gyro noise n in a window, so the gain is ``(e_f - e_a)(2 n + e_f + e_a)``: the noise enters it
linearly, with mean 0, and the mean gain is ``e_f^2 - e_a^2``.  The adapted weights are scored as they
were when the window opened, so the window is out of sample for them.  The adapted estimate is returned only when the
mean gain exceeds ``COMPARE_SIGMAS`` (1) standard error and ``(compare_min_gain r)^2`` (r: the model's fit residual; a
gain that is significant but smaller than that is the gyro's slow noise being chased;
``benchmarks/bench_population.py --adapt`` measures it), after ``compare_min_windows`` windows; otherwise the frozen
one is, and the law keeps adapting underneath (``adapted_in_use``).  A window's mean keeps the 1-s white
noise from swamping the comparison.

Order within ``step``: the estimate uses W and the comparison's verdict before this block's update (an
honest a-priori estimate, the law's ``predict``), then the guard, then the bias capture, then the law learns
(``learn``) or tracks with W held (``track``).  The readout's ``step`` keeps predicting and learning in one
call: the estimate it returns is the guard's and the gate's verdict on this same block.  ``run`` is ``step``
row by row.

State.  ``get_state`` / ``set_state`` give everything (the law's state, the bias capture, counters,
and the frozen weights, so a state is never restored into another model) as plain YAML-safe values;
floats round-trip exactly through ``yaml.safe_dump``, so a run saved and restored mid-stream continues bit
for bit (tested).  ``state_document`` / ``load_state_doc`` give a document with a format tag
(``modelfiles.save_readout_state`` / ``load_readout_state`` write and read it as a small YAML file
and a schema version (safe loading only, one-line ``InputFileError`` / ``OutputFileError``)), optionally
with a ``StaticDetector``'s state in the same document.
"""

from __future__ import annotations

import math
from typing import Any, cast

import numpy as np

from ..errors import InputFileError
from ..files.kinds import ADAPT_STATE_FORMAT
from ..flags import FLAG_ADAPTING, FLAG_GUARD
from . import numerics
from .adapt_config import AdaptConfig, StaticDetector, blocks_in, finite_number
from .adapt_state import (
    ADAPT_STATE_SCHEMA_VERSION,
    SIGMA_KEY,
    check_state_keys,
    checked_comparison,
    checked_gate,
    checked_sigma,
)
from .readout import AdaptiveLaw, AdaptiveLawState

__all__ = [
    "ADAPT_STATE_FORMAT",
    "ADAPT_STATE_SCHEMA_VERSION",
    "AdaptConfig",
    "OnlineReadout",
    "StaticDetector",
]

#: The adapted estimate is used when the comparison's mean gain exceeds this many standard errors (with
#: 300-s windows and 4 of them first; ``benchmarks/bench_population.py --adapt``;
#: docs/decisions/2026-12-07-rate-comparison-guard.md).
COMPARE_SIGMAS = 1.0


#: The runaway bound from the model (``runaway_for``): this many times its fit residual (the 1-min RMS the
#: model leaves on its fit data, the gyro's noise included), within [RUNAWAY_MIN_DPH, RUNAWAY_MAX_DPH].
RUNAWAY_FIT_RESIDUALS = 5.0
RUNAWAY_MIN_DPH = 0.05
RUNAWAY_MAX_DPH = 2.0
#: The innovation gate's filter (an exponential mean over this time): long enough that its noise (the
#: block noise / sqrt(2 GATE_FILTER_S / Ts): 0.011 deg/h for 0.17) leaves the bound close to the
#: runaway bound, so that a creep just above that bound is refused within minutes; a move or a fast
#: creep is refused within seconds all the same (a 2 deg/h creep crosses a 0.2 deg/h bound in 13 s).
GATE_FILTER_S = 120.0
#: The innovation's noise: an exponential mean of half the squared differences of successive gated
#: rates, over this time (the white noise of a block; a drift is smooth and does not enter it).
NOISE_MEMORY_S = 600.0


def runaway_for(fit_residual_dph: float | None) -> float:
    """The adapted estimate's largest allowed departure from the frozen one, deg/h: ``RUNAWAY_FIT_RESIDUALS``
    times the model's fit residual, clipped to [``RUNAWAY_MIN_DPH``, ``RUNAWAY_MAX_DPH``];
    ``RUNAWAY_MAX_DPH`` when the model file does not say (made before fit metrics were recorded)."""
    if fit_residual_dph is None or not finite_number(fit_residual_dph) or fit_residual_dph <= 0:
        return RUNAWAY_MAX_DPH
    return min(max(RUNAWAY_FIT_RESIDUALS * float(fit_residual_dph), RUNAWAY_MIN_DPH), RUNAWAY_MAX_DPH)


class ComparisonGuard:
    """The comparison guard's running figures (module docstring), shared by the rate path and the table's
    (``table.TableLaw``): each window's (or interval's) mean errors of the frozen and the adapted estimate
    in, the verdict out.  The host has ``config`` (an ``AdaptConfig``) and ``_min_gain``."""

    config: AdaptConfig
    runaway_dph: float
    _min_gain: float
    #: the standard errors the mean gain must exceed (``COMPARE_SIGMAS`` for the rate path)
    compare_sigmas: float = COMPARE_SIGMAS
    compare_windows: int
    compare_gain: float
    compare_gain_sq: float
    compare_level_frozen_dph: float
    compare_level_adapted_dph: float
    compare_dev_sq_adapted_dph2: float

    def _set_bounds(self, fit_residual_dph: float | None) -> None:
        """``runaway_dph`` (the config's, else ``runaway_for`` the model's fit residual) and the comparison's
        least gain, ``(compare_min_gain r)^2`` with r = ``runaway_dph / RUNAWAY_FIT_RESIDUALS``."""
        configured = self.config.runaway_dph
        self.runaway_dph = float(configured if configured is not None else runaway_for(fit_residual_dph))
        self._min_gain = (self.config.compare_min_gain * self.runaway_dph / RUNAWAY_FIT_RESIDUALS) ** 2

    def _compare_memory(self) -> float:
        """The comparison's memory, in windows (the config's)."""
        return float(self.config.compare_memory_windows)

    def _add_window(self, error_frozen: float, error_adapted: float) -> None:
        """One window's mean errors: the gain about their running levels into the running mean and mean square
        (plain means until the memory is full, then exponential)."""
        memory = self._compare_memory()
        weight = 1.0 / min(self.compare_windows + 1, memory)
        if self.compare_windows:  # errors about their own running level: a constant offset is no drift
            gain = (error_frozen - self.compare_level_frozen_dph) ** 2 - (
                error_adapted - self.compare_level_adapted_dph
            ) ** 2
            gain_weight = 1.0 / min(self.compare_windows, memory)
            self.compare_gain += gain_weight * (gain - self.compare_gain)
            self.compare_gain_sq += gain_weight * (gain * gain - self.compare_gain_sq)
            dev = (error_adapted - self.compare_level_adapted_dph) ** 2
            self.compare_dev_sq_adapted_dph2 += gain_weight * (dev - self.compare_dev_sq_adapted_dph2)
        self.compare_level_frozen_dph += weight * (error_frozen - self.compare_level_frozen_dph)
        self.compare_level_adapted_dph += weight * (error_adapted - self.compare_level_adapted_dph)
        self.compare_windows += 1

    def _gain_and_error(self) -> tuple[float, float] | None:
        """The recent windows' mean gain (the frozen estimate's squared error less the adapted one's) and its
        standard error; None before ``compare_min_windows`` windows."""
        if self.compare_windows < max(3, self.config.compare_min_windows):
            return None
        n = min(self.compare_windows - 1, self._compare_memory())  # windows that gave a gain
        variance = max(self.compare_gain_sq - self.compare_gain**2, 0.0)
        return self.compare_gain, math.sqrt(variance / n)

    def _comparison_passes(self) -> bool:
        """Over the recent windows the adapted estimate's squared error was smaller than the frozen one's by
        more than ``compare_sigmas`` standard errors of that gain, and by more than the least gain worth
        having (``AdaptConfig.compare_min_gain``)."""
        g = self._gain_and_error()
        return g is not None and g[0] > max(self.compare_sigmas * g[1], self._min_gain)

    def _comparison_fails(self) -> bool:
        """The other way round: over the recent windows the adapted estimate's squared error was larger than the
        frozen one's by more than ``compare_sigmas`` standard errors of that gain."""
        g = self._gain_and_error()
        return g is not None and g[0] < -self.compare_sigmas * g[1]


class OnlineReadout(ComparisonGuard):
    """The adaptive law over ``[f, 1]`` from the frozen weights, gated, guarded (see the module docstring).

    ``step(f, measured_rate_dph, reference_rate_dph, static) -> (estimate_dph, flags)``.
    """

    def __init__(
        self,
        frozen_weights: np.ndarray,
        frozen_intercept: float,
        config: AdaptConfig | None = None,
        sample_time_s: float = 1.0,
        state: dict[str, Any] | None = None,
        fit_residual_dph: float | None = None,
    ) -> None:
        self.config = config if config is not None else AdaptConfig()
        w0 = np.array(frozen_weights, dtype=np.float64)
        if w0.ndim != 1 or len(w0) < 1 or not np.isfinite(w0).all():
            raise ValueError(f"frozen_weights must be a vector of finite numbers, got shape {w0.shape}")
        if not finite_number(frozen_intercept):
            raise ValueError(f"frozen_intercept must be finite, got {frozen_intercept!r}")
        w0.flags.writeable = False
        self.frozen_weights = w0
        self.frozen_intercept = float(frozen_intercept)
        self.n_features = len(w0)  #: F, the model's regressors (the law has F + 1: the constant)
        self._w_frozen = np.append(w0, self.frozen_intercept)
        self._law = AdaptiveLaw(self.config.law, self.n_features + 1, sample_time_s)
        self.sample_time_s = self._law.sample_time_s
        self.bias_capture_blocks = blocks_in(self.config.bias_capture_s, self.sample_time_s)
        self._set_bounds(fit_residual_dph)
        self._runaway = self.runaway_dph
        # the innovation's filter: GATE_FILTER_S; the noise's memory: NOISE_MEMORY_S
        self._gate_a = 1.0 - numerics.exp_correctly_rounded(-self._law.sample_time_s / GATE_FILTER_S)
        self._noise_a = 1.0 - numerics.exp_correctly_rounded(-self._law.sample_time_s / NOISE_MEMORY_S)
        # an exponential mean of white noise of variance v has variance v a / (2 - a)
        self._gate_gain = math.sqrt(self._gate_a / (2.0 - self._gate_a))
        self._compare_window_blocks = max(1, blocks_in(self.config.compare_window_s, sample_time_s))
        self._x = np.empty(self.n_features + 1)
        self._x[-1] = 1.0
        self._start()
        if state is not None:
            self.set_state(state)

    def _start(self) -> None:
        self._law.set_state(AdaptiveLawState.zeros(self.n_features + 1, weights=self._w_frozen))
        self.bias_sum_dph = 0.0
        self.bias_count = 0
        self.bias_dph: float | None = None
        self.begin_run()
        self.blocks = 0
        self.used_adapted = False  # the last block's estimate came from the adapted weights (not state: per block)
        self.gated_blocks = 0
        self.updates = 0
        self.guards = 0
        self.rejected = 0  # gated blocks the innovation gate kept from the law
        self.gate_noise_var_dph2 = 0.0
        self.gate_last_rate_dph: float | None = None
        self.gate_innovation_dph = 0.0
        self._reset_comparison()

    def _reset_comparison(self) -> None:
        self._compare_w = self._law.weights_view.copy()  # the adapted weights when the open window began
        self.compare_blocks = 0  # gated update blocks in the open window
        self.compare_sum_frozen_dph = 0.0  # sums of (d - frozen estimate) and (d - adapted estimate) in it
        self.compare_sum_adapted_dph = 0.0
        self.compare_gain = 0.0  # running mean, and mean square, of a window's gain: frozen error^2 - adapted error^2
        self.compare_gain_sq = 0.0
        self.compare_level_frozen_dph = 0.0  # running means of the windows' mean errors (their constant part)
        self.compare_level_adapted_dph = 0.0
        self.compare_windows = 0
        self.compare_dev_sq_adapted_dph2 = 0.0  # running mean square of the adapted windows' errors about their level

    @property
    def adapted_sigma_dph(self) -> float:
        """The adapted estimate's error, from the law's own innovation statistics: the running mean square of
        the comparison windows' mean errors of the adapted weights (``d - adapted``, out of sample, about
        their running level: the bias is not error), less the gyro's white noise over a window::

            sigma_a^2 = max(mean (e_a - level_a)^2 - noise_var / window_blocks, 0)

        (``compare_window_s`` means, 5 min by default: the adapted error is a slow drift, the same at 1 min).
        0 before two windows have closed."""
        if self.compare_windows < 2:
            return 0.0
        noise = self.gate_noise_var_dph2 / self._compare_window_blocks
        return math.sqrt(max(self.compare_dev_sq_adapted_dph2 - noise, 0.0))

    @property
    def adapted_in_use(self) -> bool:
        """The comparison guard's verdict: over the recent windows the adapted estimate's squared error was
        smaller than the frozen one's by more than ``COMPARE_SIGMAS`` standard errors of that gain, and by
        more than the least gain worth having (``AdaptConfig.compare_min_gain``)."""
        return self._comparison_passes()

    # -- inspection --------------------------------------------------------------------------------

    @property
    def law(self) -> AdaptiveLaw:
        """The live adaptive law (for inspection; change it through this class only)."""
        return self._law

    @property
    def weights(self) -> np.ndarray:
        """A copy of the adapted weights on f, shape (F,)."""
        return self._law.weights_view[:-1].copy()

    @property
    def intercept(self) -> float:
        return float(self._law.weights_view[-1])

    @property
    def adapting(self) -> bool:
        """True once the bias is captured: gated blocks update W."""
        return self.bias_dph is not None

    def frozen_estimate(self, f: np.ndarray) -> float:
        return float(numerics.dot(f, self.frozen_weights) + self.frozen_intercept)

    def begin_run(self) -> None:
        """A new run of the instrument (switched off and on: a new turn-on bias): capture the bias again.
        W (as adapted so far), the filters, H and I and the counters are kept; W does not move until the new
        capture is complete."""
        self.bias_sum_dph = 0.0
        self.bias_count = 0
        self.bias_dph = None if self.bias_capture_blocks else 0.0

    def reset_to_frozen(self) -> None:
        """W back to the frozen weights, and the law's accumulated information (its filters, H and I) cleared:
        kept, it would lead W straight back to the solution that ran away.  The bias and the counters are
        kept.  The comparison guard starts over (its evidence was about weights that are gone): the frozen
        estimate is returned until the adapted one has earned its place again."""
        self._law.set_state(AdaptiveLawState.zeros(self.n_features + 1, weights=self._w_frozen))
        self._reset_comparison()

    # -- stepping ----------------------------------------------------------------------------------

    def step(
        self, f: np.ndarray, measured_rate_dph: float, reference_rate_dph: float | None, static: bool
    ) -> tuple[float, int]:
        """One model block: the estimate to use (deg/h) and its flags (``FLAG_ADAPTING``, ``FLAG_GUARD``).

        ``f``: the model's regressor row (F,); ``measured_rate_dph``: the block's mean measured rate;
        ``reference_rate_dph``: the known input rate, or None (NaN counts as None); ``static``: the table
        is static (e.g. ``StaticDetector``).  The caller feeds the returned estimate back to the model.
        """
        f = np.asarray(f, dtype=np.float64)
        if f.shape != (self.n_features,):
            raise ValueError(f"f must have shape ({self.n_features},), got {f.shape}")
        measured = float(measured_rate_dph)
        reference = None if reference_rate_dph is None else float(reference_rate_dph)
        return self._advance(f, measured, reference, bool(static))

    def _advance(self, f: np.ndarray, measured: float, reference: float | None, static: bool) -> tuple[float, int]:
        # Overflow and NaN are what the guards are for: no RuntimeWarning on the way to them.
        with np.errstate(over="ignore", invalid="ignore"):
            return self._advance_guarded(f, measured, reference, static)

    def _advance_guarded(
        self, f: np.ndarray, measured: float, reference: float | None, static: bool
    ) -> tuple[float, int]:
        self.blocks += 1
        self.used_adapted = False
        flags = 0
        y_frozen = float(numerics.dot(f, self.frozen_weights) + self.frozen_intercept)
        w = self._law.weights_view  # the law's live W (updated in place by the law)
        y = float(numerics.dot(f, w[:-1]) + w[-1])
        if not math.isfinite(y_frozen):  # non-finite regressors: nothing to revert to, nothing to learn
            return y_frozen, FLAG_GUARD
        use_adapted = self.adapted_in_use  # the comparison's verdict so far: a priori, like the estimate
        if not math.isfinite(y) or abs(y - y_frozen) > self._runaway:
            self.reset_to_frozen()
            self.guards += 1
            flags |= FLAG_GUARD
            y = y_frozen
        x = self._x
        x[:-1] = f
        gated = static and reference is not None and math.isfinite(reference) and math.isfinite(measured)
        update = False
        d = y  # the neutral target: no information, "stay"
        if gated:
            reference = cast(float, reference)  # gated: a finite reference
            self.gated_blocks += 1
            if self.gate_last_rate_dph is not None:  # the block noise, from successive gated rates, winsorized
                step = measured - self.gate_last_rate_dph
                var = self.gate_noise_var_dph2
                cap = min(25.0 * var if var > 0 else math.inf, self.config.static_threshold_dph**2)
                self.gate_noise_var_dph2 += self._noise_a * (min(0.5 * step * step, cap) - var)
            self.gate_last_rate_dph = measured
            if self.bias_dph is None:
                self.bias_sum_dph += measured - reference - y  # W is fixed during a capture: y is frozen on a first run
                self.bias_count += 1
                if self.bias_count >= self.bias_capture_blocks:
                    self.bias_dph = self.bias_sum_dph / self.bias_count
            else:
                target = measured - reference - self.bias_dph
                self.gate_innovation_dph += self._gate_a * (target - y_frozen - self.gate_innovation_dph)
                if abs(self.gate_innovation_dph) <= self.gate_limit_dph:
                    d = target
                    update = True
                    self._compare(f, d, y_frozen)
                else:  # the gyro disagrees with the reference by more than any drift the law may learn:
                    self.rejected += 1  # what the law learned as the mismatch grew is suspect too
                    flags |= FLAG_GUARD
                    self.reset_to_frozen()
                    use_adapted = False
                    y = y_frozen
                    d = y
        else:  # the gate starts afresh after any block it did not see
            self.gate_last_rate_dph = None
            self.gate_innovation_dph = 0.0
        if update:
            self._law.learn(x, d)
            self.updates += 1
            flags |= FLAG_ADAPTING
            if not np.isfinite(self._law.weights_view).all():
                self.reset_to_frozen()
                self.guards += 1
                flags |= FLAG_GUARD
        else:
            self._law.track(x, d)
        if use_adapted and y != y_frozen:  # the adapted weights' estimate is in use (restored ones too)
            flags |= FLAG_ADAPTING
            self.used_adapted = True
            return y, flags
        return y_frozen, flags

    @property
    def gate_limit_dph(self) -> float:
        """The innovation gate's bound: the runaway bound plus ``innovation_sigmas`` sigmas of the filtered
        innovation's noise (the block noise through the target filter)."""
        sigma = math.sqrt(self.gate_noise_var_dph2) * self._gate_gain
        return self._runaway + self.config.innovation_sigmas * sigma

    def _compare(self, f: np.ndarray, d: float, y_frozen: float) -> None:
        """One gated block's errors into the comparison window: the frozen estimate's, and the adapted
        weights' as they were when the window opened (so the window is out of sample for them: weights that
        learned from a window's noise would otherwise seem to predict it); a full window's gain into the
        running mean and mean square (``compare_memory_windows`` of memory)."""
        if self.compare_blocks == 0:
            self._compare_w = self._law.weights_view.copy()
        w = self._compare_w
        self.compare_blocks += 1
        self.compare_sum_frozen_dph += d - y_frozen
        self.compare_sum_adapted_dph += d - float(numerics.dot(f, w[:-1]) + w[-1])
        if self.compare_blocks < self._compare_window_blocks:
            return
        error_frozen = self.compare_sum_frozen_dph / self.compare_blocks
        error_adapted = self.compare_sum_adapted_dph / self.compare_blocks
        self._add_window(error_frozen, error_adapted)
        self.compare_blocks = 0
        self.compare_sum_frozen_dph = self.compare_sum_adapted_dph = 0.0

    def run(
        self,
        f: np.ndarray,
        measured_rate_dph: np.ndarray,
        reference_rate_dph: np.ndarray | float | None,
        static: np.ndarray | bool,
    ) -> tuple[np.ndarray, np.ndarray]:
        """``step`` for each row of ``f`` (T, F); ``reference_rate_dph`` a (T,) array (NaN: none), a float or
        None; ``static`` a (T,) mask or a bool.  Returns the estimates (T,) and flags (T,) int64."""
        f = np.asarray(f, dtype=np.float64)
        measured = np.asarray(measured_rate_dph, dtype=np.float64)
        if f.ndim != 2 or f.shape[1] != self.n_features or measured.shape != (len(f),):
            raise ValueError(f"need f (T, {self.n_features}) and measured (T,), got {f.shape} and {measured.shape}")
        t = len(f)
        ref = np.full(t, np.nan) if reference_rate_dph is None else np.asarray(reference_rate_dph, dtype=np.float64)
        refs = np.broadcast_to(ref, (t,)).tolist()
        statics = np.broadcast_to(np.asarray(static, dtype=bool), (t,)).tolist()
        ml = measured.tolist()
        out = np.empty(t)
        out_flags = np.zeros(t, dtype=np.int64)
        for k in range(t):
            out[k], out_flags[k] = self._advance(f[k], ml[k], refs[k], statics[k])
        return out, out_flags

    # -- state -------------------------------------------------------------------------------------

    def get_state(self) -> dict[str, Any]:
        """Everything the readout carries between blocks, as plain YAML-safe values (exact)."""
        return {
            "n_features": self.n_features,
            "frozen_weights": [float(v) for v in self.frozen_weights],
            "frozen_intercept": self.frozen_intercept,
            "law": self._law.get_state().to_dict(),
            "bias_sum_dph": float(self.bias_sum_dph),
            "bias_count": int(self.bias_count),
            "bias_dph": None if self.bias_dph is None else float(self.bias_dph),
            "blocks": int(self.blocks),
            "gated_blocks": int(self.gated_blocks),
            "updates": int(self.updates),
            "guards": int(self.guards),
            "compare_blocks": int(self.compare_blocks),
            "compare_sum_frozen_dph": float(self.compare_sum_frozen_dph),
            "compare_sum_adapted_dph": float(self.compare_sum_adapted_dph),
            "compare_gain": float(self.compare_gain),
            "compare_gain_sq": float(self.compare_gain_sq),
            "compare_windows": int(self.compare_windows),
            "compare_weights": [float(v) for v in self._compare_w],
            "compare_level_frozen_dph": float(self.compare_level_frozen_dph),
            "compare_level_adapted_dph": float(self.compare_level_adapted_dph),
            "gate_noise_var_dph2": float(self.gate_noise_var_dph2),
            "gate_last_rate_dph": None if self.gate_last_rate_dph is None else float(self.gate_last_rate_dph),
            "gate_innovation_dph": float(self.gate_innovation_dph),
            "rejected": int(self.rejected),
            SIGMA_KEY: float(self.compare_dev_sq_adapted_dph2),
        }

    def set_state(self, d: dict[str, Any]) -> None:
        """Inverse of ``get_state``.  ``ValueError`` for missing or unknown keys, bad values, or a state
        saved for other frozen weights (another model); the readout is unchanged then."""
        check_state_keys(d)
        gate = checked_gate(d)
        sigma_sq = checked_sigma(d)
        compare, weights = checked_comparison(d, self.n_features)
        if d["n_features"] != self.n_features or isinstance(d["n_features"], bool):
            raise ValueError(f"adaptation state is for {d['n_features']!r} features, the model has {self.n_features}")
        try:
            w0 = np.array(d["frozen_weights"], dtype=np.float64)
            b0 = float(d["frozen_intercept"])
        except (TypeError, ValueError) as exc:
            raise ValueError(f"adaptation state: frozen weights are not numbers: {exc}") from None
        if (
            w0.shape != self.frozen_weights.shape
            or not np.array_equal(w0, self.frozen_weights)
            or b0 != self.frozen_intercept
        ):
            raise ValueError("adaptation state was saved for another model (its frozen weights differ)")
        law = AdaptiveLawState.from_dict(d["law"])
        if law.n_features != self.n_features + 1:
            raise ValueError(f"adaptation state: the law has {law.n_features} weights, expected {self.n_features + 1}")
        counts = {k: d[k] for k in ("bias_count", "blocks", "gated_blocks", "updates", "guards")}
        for k, v in counts.items():
            if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                raise ValueError(f"adaptation state: {k!r} must be an integer >= 0, got {v!r}")
        if not finite_number(d["bias_sum_dph"]):
            raise ValueError(f"adaptation state: 'bias_sum_dph' must be a finite number, got {d['bias_sum_dph']!r}")
        bias = d["bias_dph"]
        if bias is not None and not finite_number(bias):
            raise ValueError(f"adaptation state: 'bias_dph' must be a finite number or null, got {bias!r}")
        self._law.set_state(law)
        self.bias_sum_dph = float(d["bias_sum_dph"])
        self.bias_dph = None if bias is None else float(bias)
        self.bias_count, self.blocks, self.gated_blocks, self.updates, self.guards = (int(v) for v in counts.values())
        self.rejected, self.gate_noise_var_dph2, self.gate_last_rate_dph, self.gate_innovation_dph = 0, 0.0, None, 0.0
        if gate:
            self.rejected = int(gate["rejected"])
            self.gate_noise_var_dph2 = float(gate["gate_noise_var_dph2"])
            last = gate["gate_last_rate_dph"]
            self.gate_last_rate_dph = None if last is None else float(last)
            self.gate_innovation_dph = float(gate["gate_innovation_dph"])
        self._reset_comparison()
        for k, v in compare.items():
            if k == "compare_weights":
                self._compare_w = cast(np.ndarray, weights)  # given with the comparison
            else:
                setattr(self, k, v if k in ("compare_blocks", "compare_windows") else float(v))
        self.compare_dev_sq_adapted_dph2 = sigma_sq

    def state_document(
        self, detector: StaticDetector | None = None, pipeline: dict[str, Any] | None = None
    ) -> dict[str, Any]:
        """The state (and a static detector's, and the compensator's ``pipeline`` state, if given) as a
        document of plain values, what ``modelfiles.save_readout_state`` writes (a snapshot: later steps do
        not change it)."""
        doc: dict[str, Any] = {
            "format": ADAPT_STATE_FORMAT,
            "schema_version": ADAPT_STATE_SCHEMA_VERSION,
            "sample_time_s": self.sample_time_s,
            "config": self.config.to_dict(),  # for information: the state is loaded whatever the config
            "readout": self.get_state(),
        }
        if detector is not None:
            doc["static_detector"] = detector.to_dict()
        if pipeline is not None:
            doc["pipeline"] = pipeline
        return doc

    def load_state_doc(
        self, doc: dict[str, Any], where: str, detector: StaticDetector | None = None
    ) -> StaticDetector | None:
        """Restore the state from ``state_document``'s document (``where`` names it in errors); a corrupt one,
        or one for another model, is a one-line ``InputFileError`` (and nothing is changed).  Returns the
        document's static detector (None if it has none); with ``detector`` given its window is restored in
        place and the document must have one with the same settings."""
        if doc.get("sample_time_s") != self.sample_time_s:
            raise InputFileError(
                f"{where}: adaptation state for sample time {doc.get('sample_time_s')!r} s, "
                f"the readout runs at {self.sample_time_s!r} s"
            )
        try:
            found = StaticDetector.from_dict(doc["static_detector"]) if "static_detector" in doc else None
            if detector is not None:
                if found is None:
                    raise ValueError("no static detector state in the file")
                if (found.threshold_dph, found.window_blocks) != (detector.threshold_dph, detector.window_blocks):
                    raise ValueError("the static detector's settings differ from the file's")
            if "readout" not in doc:
                raise ValueError("missing 'readout'")
            self.set_state(doc["readout"])
        except ValueError as exc:
            raise InputFileError(f"{where}: corrupt adaptation state: {exc}") from None
        if detector is not None and found is not None:
            detector.set_state(found.get_state())
        return found
