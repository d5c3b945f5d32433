"""The wavelet echo-state drift model (stage 2 reservoir + stage 3 readout), in two forms.

    x(n)  = reservoir(z(n), y(n-1))                       stage 2 (``reservoir.py``)
    f(n)  = [x(n), p(z(n))]   (p: polynomial features, the "linear path"; or [x(n)] alone)
    D_hat = w . f(n) + b                                 stage 3 weights (ridge, or the adaptive law)

Kinds (``fog-driver fit --kind``):

* ``paper``: the method as the paper writes it: one leak time scale, the
  paper's (un-normalized) leaky integrator, output feedback with teacher
  forcing while fitting, reservoir states only, the readout trained by the
  adaptive law on the stage-1 (AFLP) filtered drift.
* ``wesn``: the ring form, what it takes to generalize to coils whose thermal behaviour nobody wrote
  down, on a population of simulated instruments (``fog_driver.sim.population``;
  ``benchmarks/bench_population.py``), scored on profiles never fitted on.  Wavelet
  neurons near their linear regime (translation 0, dilation 1, small inputs, normalized leak, no
  recurrence, no feedback) that integrate the ring mean R (in degC, ``ring_weights_for``): the "coil
  neuron" at the coil's lag, as one first-order stage or as two or three equal stages in series
  (``ReservoirParams.chain_from``: a coil is a distributed thermal body, heat reaches the fiber's
  inner layers through its outer ones), whose powers 2..4 enter the readout (the bias is a smooth but
  not necessarily cubic function of the coil's temperature), and three at 30 min, 1 h and 2 h
  (thermal history); beside them the levels R, top-bottom gradient and housing offset
  (``polynomial.level_features``) and the coil's own rate (``WesnModel.coil_rate_of``), which
  carries its Shupe and radial-gradient terms.  The coil's rate, ``(R - x) / tau``, is in the span
  of R and the coil neuron already, but only as a small difference of two large weights, which the
  ridge penalty shrinks: given as a regressor of its own, the penalty leaves it alone.  No ring rate
  is given (a ring rate lets a fit fake a wrong coil lag on slow ramps, which then fails on fast
  ones).  Ridge regression on standardized regressors with an unpenalized intercept.

  Fitting it (its structure chosen from the data): ``fitting.wesn``.

Both start from rest at the first input (``start``): the reservoir is put at
its fixed point for that input, as if the instrument had been there for a
long time, so hours-long time scales have no start-up transient.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .. import numerics
from ..readout import AdaptiveLawParams
from ..reservoir import (
    PSI_MAX,
    ReservoirMatrices,
    ReservoirParams,
    ReservoirState,
    WaveletReservoir,
    log_spaced_leaks,
    psi,
)
from .polynomial import (
    N_LEVEL_FEATURES,
    N_PHYSICAL_FEATURES,
    N_POLY_FEATURES,
    level_features,
    physical_features,
    polynomial_features,
)

_SETTLE_ITERATIONS = 400
#: The coil neuron's candidate lags: 60 s to 87 min, 25 % apart (a coil's lags, 2 to 25 min each and up
#: to three in series, and the ring's own lag behind its thermometers).
COIL_LAG_GRID_S = tuple(round(60.0 * 1.25**k, 1) for k in range(21))
#: Linear paths: name -> (feature function, count), or None.
_LINEAR_PATHS = {
    "none": None,
    "polynomial": (polynomial_features, N_POLY_FEATURES),
    "physical": (physical_features, N_PHYSICAL_FEATURES),
    "levels": (level_features, N_LEVEL_FEATURES),
}


def n_regressors(
    n_neurons: int, linear_path: str, state_powers: int, max_power: int = 3, coil_rate: bool = False, n_inputs: int = 8
) -> int:
    """Regressors of a WESN: neurons, powers, the coil's rate, and the linear path on ``n_inputs`` inputs."""
    path = _LINEAR_PATHS[linear_path]
    linear = path[0](np.zeros(n_inputs)).shape[-1] if path else 0
    return n_neurons + (max_power - 1) * state_powers + int(coil_rate) + linear


@dataclass(frozen=True)
class WesnConfig:
    n_neurons: int = 20  #: random (paper) form only; the ring form has 1 + len(history_s)
    seed: int = 7
    single_leak_s: float | None = None  #: random form: one time scale for every neuron (the paper)
    fastest_s: float = 30.0  #: random form without single_leak_s: log-spaced time scales
    slowest_s: float = 7200.0
    normalized_leak: bool = True
    input_scale: float = 0.1
    spectral_radius: float = 0.0
    translation_range: tuple[float, float] = (0.0, 0.0)
    dilation_range: tuple[float, float] = (1.0, 1.0)
    ring_input: bool = True  #: every neuron integrates the ring mean R = (T1 + T2) / 2 only
    fiber_lag_grid_s: tuple[float, ...] = COIL_LAG_GRID_S  #: the coil neuron's candidate lags
    coil_orders: tuple[int, ...] = (1, 2, 3)  #: the coil's candidate numbers of equal stages in series
    coil_rate: bool = True  #: ring form: the coil's own rate joins the regressors (``WesnModel.coil_rate_of``)
    history_s: tuple[float, ...] = (1800.0, 3600.0, 7200.0)
    #: The history neurons' ridge penalty, as a multiple of the others' (module docstring: the prior).
    history_penalty: float = 100.0
    state_powers: int = 1  #: the coil neuron's powers 2..max_power join the regressors
    max_power: int = 4
    feedback_scale: float = 0.0
    linear_path: str = "levels"
    readout: str = "ridge"  #: "ridge" or "adaptive"
    #: Ridge penalty per row on standardized regressors; None: chosen from ``ridge_alpha_grid`` by blocked
    #: cross-validation on the fit data.
    ridge_alpha: float | None = None
    ridge_alpha_grid: tuple[float, ...] = (3e-6, 1e-5, 3e-5)
    adaptive: AdaptiveLawParams = field(
        default_factory=lambda: AdaptiveLawParams(filter_time_s=10.0, memory_time_s=7200.0, kappa=1.0, delta=1e-6)
    )
    adaptive_epochs: int = 3
    aflp_target: bool = False  #: fit to the stage-1 filtered drift instead of the raw one

    def reservoir(
        self,
        sample_time_s: float,
        fiber_lag_s: float | None = None,
        coil_order: int = 1,
        ring_weights: tuple[float, ...] = (0.5, 0.5),
        n_inputs: int = 8,
    ) -> WaveletReservoir:
        """The ring form (``ring_input``): neuron 0, the coil, lags R by ``fiber_lag_s``, the history neurons
        1..H by ``history_s``; no recurrence, translation 0, dilation 1: each neuron a leaky memory of R near
        Psi's linear regime.  Each neuron's input is ``input_scale (w_top z_top + w_bottom z_bottom)``
        on the standardized thermometers, ``ring_weights`` (w_top, w_bottom): ``ring_weights_for`` makes
        it the ring mean in degC, whatever the two thermometers' spreads.  ``coil_order`` m > 1: the
        coil is m equal first-order stages in series, each of ``fiber_lag_s / m`` (the same mean
        delay), the first m - 1 appended as neurons H+1..H+m-1 (outermost first) and the last one
        neuron 0 (``ReservoirParams.chain_from``), with u the ring input above:

            s_1(n) = (1 - Ts m / tau) s_1(n-1) + (Ts m / tau) Psi(u(n)),   s_k: the same of s_(k-1)(n-1)

        A one-channel format (``n_inputs`` 2, ``ring_weights`` (1,)): its one temperature is the ring.
        The random form: matrices drawn from ``seed`` (the paper's reservoir)."""
        if self.ring_input:
            lag = fiber_lag_s if fiber_lag_s is not None else self.fiber_lag_grid_s[0]
            if isinstance(coil_order, bool) or not isinstance(coil_order, int) or not 1 <= coil_order <= 3:
                raise ValueError(f"coil_order must be 1, 2 or 3, got {coil_order!r}")
            h = len(self.history_s)
            stage = lag / coil_order
            lags = (stage, *self.history_s, *([stage] * (coil_order - 1)))
            n = len(lags)
            chain: tuple[int, ...] = ()
            if coil_order > 1:  # stage k (neuron h+k) integrates stage k-1; the coil (neuron 0) the last one
                chain = tuple([n - 1] + [-1] * h + [-1] + [h + k for k in range(1, coil_order - 1)])
            params = ReservoirParams(
                n_neurons=n,
                n_inputs=n_inputs,
                sample_time_s=sample_time_s,
                leak_per_s=tuple(1.0 / t for t in lags),
                normalized_leak=True,
                spectral_radius=0.0,
                input_scale=self.input_scale,
                seed=self.seed,
                translation_range=(0.0, 0.0),
                dilation_range=(1.0, 1.0),
                chain_from=chain,
            )
            w_in = np.zeros((n, n_inputs))
            for k, weight in enumerate(ring_weights):
                w_in[:, k] = weight * self.input_scale
            if coil_order > 1:
                w_in[0] = 0.0  # the coil is driven by its inner stage only
            matrices = ReservoirMatrices(w_in, np.zeros((n, n)), np.zeros(n), np.ones(n), np.zeros(n))
            return WaveletReservoir(params, matrices)
        leaks = (
            1.0 / self.single_leak_s
            if self.single_leak_s
            else log_spaced_leaks(self.n_neurons, self.fastest_s, self.slowest_s)
        )
        params = ReservoirParams(
            n_neurons=self.n_neurons,
            n_inputs=n_inputs,
            sample_time_s=sample_time_s,
            leak_per_s=leaks,
            normalized_leak=self.normalized_leak,
            spectral_radius=self.spectral_radius,
            input_scale=self.input_scale,
            feedback_scale=self.feedback_scale,
            seed=self.seed,
            translation_range=self.translation_range,
            dilation_range=self.dilation_range,
        )
        return WaveletReservoir(params)


#: The two forms' defaults.  ``wesn``: the ring form (module docstring); ``paper``: the reservoir as the
#: paper writes it, with random matrices over all eight inputs.
WESN_DEFAULTS = WesnConfig()
PAPER_DEFAULTS = WesnConfig(
    ring_input=False,
    single_leak_s=60.0,
    normalized_leak=False,
    feedback_scale=0.2,
    linear_path="none",
    state_powers=0,
    readout="adaptive",
    aflp_target=True,
    input_scale=1.0,
    spectral_radius=0.9,
    translation_range=(-1.0, 1.0),
    dilation_range=(1.0, 3.0),
)


class WesnModel:
    """``D_hat = w . f + b`` over a wavelet reservoir; explicit state (reservoir x, last output).

    The regressors f: the neuron states x; the squares and cubes of the first ``state_powers``
    neurons; and a linear path on the inputs: ``"polynomial"`` (the baseline's 9 features),
    ``"physical"`` (its 5 linear ones) or ``"none"``.
    """

    def __init__(
        self,
        kind: str,
        reservoir: WaveletReservoir,
        weights: np.ndarray,
        intercept: float,
        linear_path: str = "none",
        state_powers: int = 0,
        max_power: int = 3,
        coil_rate: bool = False,
    ) -> None:
        self.kind = kind
        self.reservoir = reservoir
        self.weights = np.asarray(weights, dtype=np.float64)
        self.intercept = float(intercept)
        if linear_path not in _LINEAR_PATHS:
            raise ValueError(f"{kind} model: linear_path must be one of {sorted(_LINEAR_PATHS)}, got {linear_path!r}")
        self.linear_path = linear_path
        self.state_powers = int(state_powers)
        if not 0 <= self.state_powers <= reservoir.params.n_neurons:
            raise ValueError(f"{kind} model: state_powers must be 0..{reservoir.params.n_neurons}")
        if isinstance(max_power, bool) or not isinstance(max_power, int) or not 2 <= max_power <= 6:
            raise ValueError(f"{kind} model: max_power must be an integer 2..6, got {max_power!r}")
        self.max_power = max_power
        if not isinstance(coil_rate, bool):
            raise ValueError(f"{kind} model: coil_rate must be true or false, got {coil_rate!r}")
        if coil_rate and ((reservoir.matrices.w != 0).any() or (reservoir.matrices.w_back != 0).any()):
            raise ValueError(
                f"{kind} model: coil_rate needs a reservoir without recurrence or feedback (the ring form)"
            )
        self.coil_rate = coil_rate
        chain = reservoir.params.chain_from
        self._coil_source = chain[0] if chain else -1
        self._coil_leak = float(reservoir.params.leaks()[0])
        self._ring_form = not (reservoir.matrices.w != 0).any() and not (reservoir.matrices.w_back != 0).any()
        #: How the fit chose the structure (lag, penalty, scores), for the model file's provenance; None when loaded.
        self.selection: dict | None = None
        #: The structures the fit data cannot tell from this one (``fitting.wesn.tied_coils``), fitted alike;
        #: the model file keeps them in its ``uncertainty`` section, not here.  Empty when loaded.
        self.candidates: list[WesnModel] = []
        expected = n_regressors(
            reservoir.params.n_neurons, linear_path, self.state_powers, max_power, coil_rate, reservoir.params.n_inputs
        )
        if self.weights.shape != (expected,):
            raise ValueError(f"{kind} model: {expected} weights expected, got {self.weights.shape}")

    # -- regressors --------------------------------------------------------------------------

    def regressors(self, x: np.ndarray, z: np.ndarray, coil_wavelet: float | None = None) -> np.ndarray:
        """f for states x and inputs z (one row or many); ``coil_wavelet``: the coil's wavelet input for
        this one row when the caller has it (``regressors_step``), else computed from z."""
        parts = [np.asarray(x)]
        if self.state_powers:
            p = parts[0][..., : self.state_powers]
            power = p
            for _ in range(2, self.max_power + 1):  # p^k = p^(k-1) p, left to right
                power = power * p
                parts.append(power)
        if self.coil_rate:
            parts.append(self.coil_rate_of(parts[0], z, coil_wavelet)[..., None])
        path = _LINEAR_PATHS[self.linear_path]
        if path is not None:
            parts.append(path[0](z))
        return np.concatenate(parts, axis=-1) if len(parts) > 1 else parts[0]

    def coil_rate_of(self, x: np.ndarray, z: np.ndarray, coil_wavelet: float | None = None) -> np.ndarray:
        """The coil neuron's own rate of change (1/s, in its units), ``dx_0/dt = leak_0 (d - x_0)``, where d
        is what it integrates: its upstream stage's state (a cascade) or its wavelet input
        ``Psi((w_in,0 . z - t_0) / s_0)``.  The Shupe and radial-gradient terms are the coil's rate:
        the readout could form it from x_0 and its input, but only as a small difference of two large,
        nearly equal weights, which the ridge penalty shrinks (docs/decisions/2026-12-07-wesn-ring-form.md); as
        its own regressor it costs the penalty nothing."""
        upstream: np.ndarray | float
        if self._coil_source >= 0:
            upstream = x[..., self._coil_source]
        elif coil_wavelet is not None:  # the same bits as below: the reservoir computed it from the same z
            upstream = coil_wavelet
        else:
            upstream = self.reservoir.wavelet_of(z, 0)
        return (upstream - x[..., 0]) * self._coil_leak

    def _output(self, f: np.ndarray) -> np.ndarray:
        return numerics.dot(f, self.weights) + self.intercept

    # -- streaming ----------------------------------------------------------------------------

    def start(self, z: np.ndarray) -> None:
        """Put the reservoir at rest for input ``z``: its fixed point, with the output fed back."""
        settle(self.reservoir, np.asarray(z, dtype=np.float64), lambda x: float(self._output(self.regressors(x, z))))

    def coil_lag(self) -> tuple[float, int] | None:
        """The coil the fit found, ``(stage time s, number of equal stages m)`` (mean delay ``m`` stages), for the
        ring form; None for a random reservoir (no coil neuron)."""
        if not self._ring_form or not self._coil_leak > 0:
            return None
        stages, chain, i = 1, self.reservoir.params.chain_from, 0
        while chain and chain[i] >= 0 and stages <= len(chain):
            i = chain[i]
            stages += 1
        return 1.0 / self._coil_leak, stages

    def regressors_step(self, z: np.ndarray) -> np.ndarray:
        """Advance the reservoir one block and return the regressor row f (``D_hat = f . w + b``).

        The caller then reports the estimate it used with ``feed_back`` (the output feedback);
        ``step`` is exactly these two with the stored weights."""
        z = np.asarray(z, dtype=np.float64)
        x = self.reservoir.step(z)
        wavelet = self.reservoir.last_wavelet[0] if self.coil_rate and self._coil_source < 0 else None
        return self.regressors(x, z, wavelet)

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
        return self.reservoir.get_state().to_dict()

    def set_state(self, state: dict) -> None:
        self.reservoir.set_state(ReservoirState.from_dict(state))

    def reset(self) -> None:
        self.reservoir.reset()

    # -- model file ---------------------------------------------------------------------------

    def to_dict(self) -> dict:
        return {
            "reservoir": self.reservoir.to_dict(),
            "linear_path": self.linear_path,
            "state_powers": self.state_powers,
            "max_power": self.max_power,
            **({"coil_rate": True} if self.coil_rate else {}),
            "weights": [float(v) for v in self.weights],
            "intercept": self.intercept,
        }

    @classmethod
    def from_dict_kind(cls, kind: str, d: dict) -> WesnModel:
        return cls(
            kind,
            WaveletReservoir.from_dict(d["reservoir"]),
            np.array(d["weights"], dtype=np.float64),
            float(d["intercept"]),
            str(d["linear_path"]),
            int(d.get("state_powers", 0)),
            d.get("max_power", 3),
            d.get("coil_rate", False),
        )


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
    drive = numerics.matvec(m.w_in, z) - m.translation
    feedback = (m.w_back != 0).any()
    chain = np.array(p.chain_from if p.chain_from else [-1] * p.n_neurons)
    chained = chain >= 0  # a cascade's rest: each stage at its upstream's state plus its own wavelet
    for _ in range(_SETTLE_ITERATIONS):
        v = (drive + numerics.matvec(m.w, x) + (m.w_back * y if feedback else 0.0)) / m.dilation
        new = np.clip(scale * psi(v), -PSI_MAX * scale, PSI_MAX * scale)
        if chained.any():
            new = new + np.where(chained, x[np.where(chained, chain, 0)], 0.0)
        x = 0.5 * x + 0.5 * new
        if feedback:
            y = output(x)
    reservoir.set_state(ReservoirState(x, y if feedback else 0.0))
