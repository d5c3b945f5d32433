"""The wavelet echo-state drift model (stage 2 reservoir + stage 3 readout), in two forms.

    x(n)  = reservoir(z(n), y(n-1))                       stage 2 (``reservoir.py``)
    f(n)  = [x(n), p(z(n))]   (p: polynomial features, the "linear path"; or [x(n)] alone)
    D_hat = w . f(n) + b                                 stage 3 weights (ridge, or the adaptive law)

Kinds (``fog-driver fit --kind``):

* ``paper``: the method as the paper writes it: one leak time scale, the
  paper's (un-normalized) leaky integrator, output feedback with teacher
  forcing while fitting, reservoir states only, the readout trained by the
  adaptive law on the stage-1 (AFLP) filtered drift.
* ``wesn`` (default for new models): what it takes to generalize to other
  thermal profiles (method.md, "Pitfalls"): normalized inputs, neurons with
  log-spaced time scales from 30 s to 2 h (the drift has a thermal memory of
  about an hour), a normalized leak (bounded states at every time scale), no
  feedback, the polynomial baseline's features beside the reservoir (a linear
  path that extrapolates), and ridge regression on standardized features with
  an unpenalized intercept.

Both start from rest at the first input (``start``): the reservoir is put at
its fixed point for that input, as if the instrument had been there for a
long time, so hours-long time scales have no start-up transient.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from .aflp import AflpFilter, AflpParams
from .polynomial import (
    N_POLY_FEATURES,
    cross_validated_alpha,
    dot_features,
    polynomial_features,
    standardized_ridge,
)
from .readout import AdaptiveLaw, AdaptiveLawParams
from .reservoir import (
    PSI_MAX,
    ReservoirMatrices,
    ReservoirParams,
    ReservoirState,
    WaveletReservoir,
    log_spaced_leaks,
    psi,
)

_SETTLE_ITERATIONS = 400


@dataclass(frozen=True)
class WesnConfig:
    n_neurons: int = 20
    seed: int = 7
    fastest_s: float = 30.0
    slowest_s: float = 7200.0
    single_leak_s: float | None = None  #: one time scale for every neuron (the paper's form)
    normalized_leak: bool = True
    input_scale: float = 0.1
    spectral_radius: float = 0.0
    translation_range: tuple[float, float] = (0.0, 0.0)
    dilation_range: tuple[float, float] = (1.0, 1.0)
    memory_channels: int | None = 3  #: the neurons see only the first inputs (the temperatures); None: all 8
    feedback_scale: float = 0.0
    linear_path: bool = True
    readout: str = "ridge"  #: "ridge" or "adaptive"
    #: Ridge penalty per row on standardized regressors; None: blocked cross-validation on the fit data
    #: (which, within one profile, picks penalties too small to extrapolate to another: not the default).
    ridge_alpha: float | None = 1e-3
    adaptive: AdaptiveLawParams = field(default_factory=lambda: AdaptiveLawParams(
        filter_time_s=10.0, memory_time_s=7200.0, kappa=1.0, delta=1e-6))  # fmt: skip
    adaptive_epochs: int = 3
    aflp_target: bool = False  #: fit to the stage-1 filtered drift instead of the raw one

    def reservoir_params(self, sample_time_s: float) -> ReservoirParams:
        leaks = (1.0 / self.single_leak_s if self.single_leak_s else
                 log_spaced_leaks(self.n_neurons, self.fastest_s, self.slowest_s))  # fmt: skip
        return ReservoirParams(
            n_neurons=self.n_neurons, n_inputs=8, sample_time_s=sample_time_s, leak_per_s=leaks,
            normalized_leak=self.normalized_leak, spectral_radius=self.spectral_radius, input_scale=self.input_scale,
            feedback_scale=self.feedback_scale, seed=self.seed, translation_range=self.translation_range,
            dilation_range=self.dilation_range,
        )  # fmt: skip

    def reservoir(self, sample_time_s: float) -> WaveletReservoir:
        params = self.reservoir_params(sample_time_s)
        matrices = ReservoirMatrices.draw(params)
        if self.memory_channels is not None:
            w_in = matrices.w_in.copy()
            w_in[:, self.memory_channels :] = 0.0
            matrices = replace(matrices, w_in=w_in)
        return WaveletReservoir(params, matrices)


#: The two forms' defaults.  ``wesn``: neurons near their linear regime (translation 0, dilation 1,
#: small inputs) that integrate the temperatures only, at 20 log-spaced time scales from 30 s to 2 h,
#: without recurrence: leaky memories of the thermal history, which is what the drift depends on
#: beyond the instantaneous inputs, and which extrapolate to other profiles (random mixtures of all
#: eight inputs, rates included, fit the training profile's staircase and do not; see the README's
#: accuracy section for both).
WESN_DEFAULTS = WesnConfig()
PAPER_DEFAULTS = WesnConfig(single_leak_s=60.0, normalized_leak=False, feedback_scale=0.2, linear_path=False,
                            readout="adaptive", aflp_target=True, input_scale=1.0, spectral_radius=0.9,
                            translation_range=(-1.0, 1.0), dilation_range=(1.0, 3.0), memory_channels=None)  # fmt: skip


class WesnModel:
    """``D_hat = w . [x, p(z)] + b`` over a wavelet reservoir; explicit state (reservoir x, last output)."""

    def __init__(self, kind: str, reservoir: WaveletReservoir, weights: np.ndarray, intercept: float,
                 linear_path: bool) -> None:  # fmt: skip
        self.kind = kind
        self.reservoir = reservoir
        self.weights = np.asarray(weights, dtype=np.float64)
        self.intercept = float(intercept)
        self.linear_path = bool(linear_path)
        expected = reservoir.params.n_neurons + (N_POLY_FEATURES if linear_path else 0)
        if self.weights.shape != (expected,):
            raise ValueError(f"{kind} model: {expected} weights expected, got {self.weights.shape}")

    # -- regressors --------------------------------------------------------------------------

    def regressors(self, x: np.ndarray, z: np.ndarray) -> np.ndarray:
        if not self.linear_path:
            return np.asarray(x)
        return np.concatenate((x, polynomial_features(z)), axis=-1)

    def _output(self, f: np.ndarray) -> np.ndarray:
        return dot_features(f, self.weights) + self.intercept

    # -- streaming ----------------------------------------------------------------------------

    def start(self, z: np.ndarray) -> None:
        """Put the reservoir at rest for input ``z``: its fixed point, with the output fed back."""
        settle(self.reservoir, np.asarray(z, dtype=np.float64), lambda x: float(self._output(self.regressors(x, z))))

    def regressors_step(self, z: np.ndarray) -> np.ndarray:
        """Advance the reservoir one block and return the regressor row f (``D_hat = f . w + b``).

        The caller then reports the estimate it used with ``feed_back`` (the output feedback);
        ``step`` is exactly these two with the stored weights."""
        z = np.asarray(z, dtype=np.float64)
        return self.regressors(self.reservoir.step(z), z)

    def feed_back(self, y: float) -> None:
        self.reservoir.set_feedback(y)

    def step(self, z: np.ndarray) -> float:
        y = float(self._output(self.regressors_step(z)))
        self.feed_back(y)
        return y

    def run(self, z: np.ndarray) -> np.ndarray:
        """``step`` over rows of ``z``; bit-identical (the same per-row reservoir steps and dot products)."""
        z = np.asarray(z, dtype=np.float64)
        if self.reservoir.params.feedback_scale == 0.0:
            x = self.reservoir.run(z)
            y = self._output(self.regressors(x, z))
            if len(y):
                self.reservoir.set_feedback(float(y[-1]))
            return y
        return np.array([self.step(row) for row in z])

    def get_state(self) -> dict:
        return self.reservoir.state.to_dict()

    def set_state(self, state: dict) -> None:
        self.reservoir.set_state(ReservoirState.from_dict(state))

    def reset(self) -> None:
        self.reservoir.reset()

    # -- model file ---------------------------------------------------------------------------

    def to_dict(self) -> dict:
        return {
            "reservoir": self.reservoir.to_dict(),
            "linear_path": self.linear_path,
            "weights": [float(v) for v in self.weights],
            "intercept": self.intercept,
        }

    @classmethod
    def from_dict_kind(cls, kind: str, d: dict) -> WesnModel:
        return cls(kind, WaveletReservoir.from_dict(d["reservoir"]), np.array(d["weights"], dtype=np.float64),
                   float(d["intercept"]), bool(d["linear_path"]))  # fmt: skip


class WesnKind(WesnModel):
    kind = "wesn"

    @classmethod
    def from_dict(cls, d: dict) -> WesnModel:
        return WesnModel.from_dict_kind("wesn", d)


class PaperKind(WesnModel):
    kind = "paper"

    @classmethod
    def from_dict(cls, d: dict) -> WesnModel:
        return WesnModel.from_dict_kind("paper", d)


def settle(reservoir: WaveletReservoir, z: np.ndarray, output) -> None:
    """The reservoir's state after holding input ``z`` (and feeding back ``output(x)``) for a long time.

    Normalized leak: the rest state solves ``x = Psi(v(x))``, a contraction under the echo-state
    condition, iterated to convergence.  Paper form: ``x = Psi(v(x)) / leak``, iterated the same
    way with damping, bounded by |x_i| <= e^-1/2 / leak_i.
    """
    p = reservoir.params
    m = reservoir.matrices
    leaks = p.leaks()
    scale = np.ones(p.n_neurons) if p.normalized_leak else 1.0 / leaks
    x = np.zeros(p.n_neurons)
    y = 0.0
    drive = m.w_in @ z - m.translation
    feedback = (m.w_back != 0).any()
    for _ in range(_SETTLE_ITERATIONS):
        v = (drive + m.w @ x + (m.w_back * y if feedback else 0.0)) / m.dilation
        new = np.clip(scale * psi(v), -PSI_MAX * scale, PSI_MAX * scale)
        x = 0.5 * x + 0.5 * new
        if feedback:
            y = output(x)
    reservoir.set_state(ReservoirState(x, y if feedback else 0.0))


def _capture_regressors(model: WesnModel, capture, normalizer, teacher: np.ndarray | None) -> np.ndarray:
    """Reservoir regressors over one capture, from rest at its first valid input as the compensator
    starts (rows before it are zeros: never fitted); feedback teacher-forced with ``teacher``."""
    z = normalizer.transform(np.where(np.isfinite(capture.inputs), capture.inputs, 0.0))
    first = first_valid_block(capture.inputs)
    model.reset()
    model.start(z[first])
    y_prev = None if teacher is None else np.r_[teacher[first], teacher[first:-1]]
    f = np.zeros((len(z), len(model.weights)))
    f[first:] = model.regressors(model.reservoir.run(z[first:], y_prev), z[first:])
    return f


def first_valid_block(inputs: np.ndarray) -> int:
    valid = np.flatnonzero(np.all(np.isfinite(inputs), axis=1))
    if not len(valid):
        raise ValueError("no block with valid inputs")
    return int(valid[0])


def _aflp_target(target: np.ndarray) -> np.ndarray:
    return AflpFilter(AflpParams()).run(target)


def fit_wesn(kind: str, defaults: WesnConfig, captures, normalizer, config) -> WesnModel:
    """Fit a WESN model of the given form to the captures (see the module docstring)."""
    wc = defaults
    reservoir = wc.reservoir(1.0 / config.model_rate_hz)
    n_features = wc.n_neurons + (N_POLY_FEATURES if wc.linear_path else 0)
    model = WesnModel(kind, reservoir, np.zeros(n_features), 0.0, wc.linear_path)
    xs, ys = [], []
    for c in captures:
        target = _aflp_target(c.target_dph) if wc.aflp_target else c.target_dph
        f = _capture_regressors(model, c, normalizer, target if wc.feedback_scale else None)
        xs.append(f[c.static])
        ys.append(target[c.static])
    x_fit = np.vstack(xs)
    y_fit = np.concatenate(ys)
    if wc.readout == "ridge":
        alpha = wc.ridge_alpha
        if alpha is None:
            alpha, _ = cross_validated_alpha(x_fit, y_fit)
        weights, intercept = standardized_ridge(x_fit, y_fit, alpha)
    else:
        weights, intercept = _adaptive_readout(x_fit, y_fit, wc, config)
    return WesnModel(kind, reservoir, weights, intercept, wc.linear_path)


def _adaptive_readout(x: np.ndarray, y: np.ndarray, wc: WesnConfig, config) -> tuple[np.ndarray, float]:
    """Stage 3 as the paper trains it: the adaptive law over the fit data (several passes), with a
    constant regressor for the intercept."""
    x1 = np.column_stack([x, np.ones(len(x))])
    law = AdaptiveLaw(wc.adaptive, x1.shape[1], 1.0 / config.model_rate_hz)
    for _ in range(wc.adaptive_epochs):
        law.run(x1, y, True)
    w = law.weights
    return w[:-1].copy(), float(w[-1])
