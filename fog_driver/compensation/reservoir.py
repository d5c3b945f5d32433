"""Stage 2: the wavelet echo-state reservoir, paper eq. 8-11, discretized with the sample time.

Continuous form ``dx/dt = -leak x + Psi(v)``, ``leak = 1 - a`` (the paper's eq. 8 prints ``+(1-a)X``:
a sign typo, the integrator must leak).  Explicit Euler with sample time ``Ts``, per neuron i with
dilation ``s_i`` and translation ``t_i``::

    z    = Win u(n) + W x(n-1) + Wback y(n-1)                  (the Wback term only when Wback != 0)
    v    = (z - t) / s
    Psi(v) = v exp(-v^2 / 2)                                   max |Psi| = e^-1/2, max |Psi'| = 1
    x(n) = (1 - Ts leak) x(n-1) + Ts Psi(v)                    paper form (``normalized_leak=False``)
    x(n) = (1 - Ts leak) x(n-1) + Ts leak Psi(v)               normalized form (``normalized_leak=True``)

with ``0 < Ts leak_i <= 1``.  Writing the step with ``Ts`` makes a model behave the same at any
sample rate (the matrices never depend on ``Ts``; tested: 1 s against 0.1 s).  ``leak`` is one rate
for all neurons (the paper) or one per neuron (several time scales, e.g. ``log_spaced_leaks(20, 30,
7200)``: every neuron a low-pass of its own wavelet input, from 30 s to 2 h).

Bounds (free invariants, tested).  From any state inside the bound the state stays inside:
paper form ``|x_i| <= e^-1/2 / leak_i`` (the steady state of a constant input is ``Psi(v) / leak``,
so neurons with long time constants have LARGE states: 0.61 * 7200 = 4,400 for a 2-h neuron, and
their recurrent input ``W x`` then pushes every wavelet far into its flat tails); normalized form
``|x_i| <= e^-1/2`` for every time scale (steady state ``Psi(v)``).  Prefer the normalized form with
several time scales; the paper form is kept to reproduce the paper.

Echo-state condition.  ``W`` is scaled so that ``||W|| max(1/s_i) = spectral_radius < 1`` with
``||W||`` the LARGER of the spectral norm and the maximum absolute row sum (so the method's
``||W||_2 max(1/s_i) < 1`` holds, and so does its infinity-norm twin).  What it guarantees (by the
mean value theorem, per neuron, with ``|Psi'| <= 1``): two states driven by the same inputs approach
each other, ``||xa(n) - xb(n)||_inf <= c^n ||xa(0) - xb(0)||_inf``, with

    c = max_i (1 - Ts leak_i + Ts g_i sum_j |W_ij| / s_i),   g_i = leak_i (normalized) or 1 (paper)

(``WaveletReservoir.contraction_bound``).  For the normalized form ``c < 1`` for ANY leaks: the
echo-state property holds unconditionally.  For the paper form ``c < 1`` needs
``sum_j |W_ij| / s_i < leak_i``: with leaks below ~1/s and the usual ``spectral_radius`` the bound
says nothing, and in practice the paper form then does NOT forget: with one leak of 1/300 or 1/30 per s
and ``spectral_radius`` 0.9, two reservoirs started from different states and driven by the same
7-hour input still differ by O(1) at the end, and the same signal sampled at 1 s and 0.1 s gives
O(1) different states (the paper form is equivalent to the normalized one with ``W / leak``, a
recurrent gain of hundreds).  Its states depend on the initial state and on the sample rate, not
only on the inputs: tested, and the reason the normalized form is the default.  The paper form is
kept to reproduce the paper; with a ``spectral_radius`` below its smallest leak (in 1/s), so that
``contraction_bound < 1``, it is an echo-state network too.

Slow neurons remember their initial state for their own time constant: with leaks down to 1/7200
per s, a state started at 0 needs hours to forget it.  Start fitting and operation from the same
initial state (0 at power-on) or from a stored state, never from 0 in the middle of a run.

Matrices.  Drawn from ONE seed, each from its own child generator
(``np.random.SeedSequence(seed).spawn(5)``: 0 ``w_in``, 1 ``w``, 2 ``w_back``, 3 ``dilation``,
4 ``translation``), so changing how one matrix is drawn never changes another::

    w_in        uniform(-input_scale, input_scale), dense, (n_neurons, n_inputs)
    w           uniform(-1, 1) where uniform(0, 1) < density, then scaled as above, (n_neurons, n_neurons)
    w_back      uniform(-feedback_scale, feedback_scale), (n_neurons,)   all 0 when feedback_scale = 0
    dilation    uniform(dilation_range), (n_neurons,)
    translation uniform(translation_range), (n_neurons,)

The scaling uses LAPACK (``np.linalg.norm(W, 2)``), whose last bits may differ between machines: a
model file therefore stores the matrices themselves (``to_dict``: plain lists of floats, exact), and
a reservoir loaded from it never redraws.

Feedback.  ``step(u, y_prev)`` takes ``y(n-1)``: while fitting, the measured drift of the previous
sample (teacher forcing); in operation, the model's own previous output (``run_closed_loop``, or the
compensator does the same step by step: ``x = step(u)``, ``y = readout(x)``, ``set_feedback(y)``).
With ``feedback_scale = 0`` the feedback term is not computed at all: ``y_prev`` is irrelevant, even
NaN (tested).

Cascade (``ReservoirParams.chain_from``).  A neuron may also integrate another neuron's previous
state, linearly and beside its wavelet: ``x_i(n) = (1 - Ts leak_i) x_i(n-1) + Ts leak_i (Psi(v_i) +
x_c(n-1))``.  The ring form builds a coil of two or three first-order stages in series from it
(normalized form only, acyclic; the bound on |x_i| grows by e^-1/2 per stage upstream).  It adds an
elementwise multiply and add per step, so ``run`` keeps its fast path and its bits.

Non-finite values.  When the new state would not be finite (a NaN or inf input, a non-finite
``y_prev`` with feedback on, or an overflow from absurd inputs), the step is skipped: the state is
left exactly as it was and the held state is returned.  The pipeline should never feed NaN (the
features hold the last good thermometer reading); this is defence, not a gap model.

Machine-independent.  ``W_in u`` and ``W x`` are summed strictly left to right and ``Psi`` uses
``numerics.exp`` (no BLAS, no CPU-specific exp), so a stored reservoir gives the same states, to the
bit, on every CPU (``numerics``; tested by ``tests/compensation/test_numerics.py`` and the golden outputs).

``step`` and ``run`` share one update (``_advance``), so ``run`` is bit-identical to repeated
``step`` and to running in any chunks (tested).  Without recurrence and feedback (the ring form)
``run`` computes every row's wavelet input at once with the same elementwise operations and steps
only the leak row by row (``_run_feedforward``): the same bits with one numpy call per operation
over all rows instead of one per row, which is what fitting (one run per candidate lag) spends its
time on.  A step is a fixed chain of numpy calls on n neurons, so for small n its cost is numpy's
per-call overhead, not n (``benchmarks/bench_model_step.py`` measures it).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields
from typing import Any, cast

import numpy as np

from . import numerics
from .keys import require_known_keys

__all__ = [
    "PSI_MAX",
    "ReservoirMatrices",
    "ReservoirParams",
    "ReservoirState",
    "WaveletReservoir",
    "log_spaced_leaks",
    "psi",
]

#: max |Psi(z)| = Psi(1) = e^-1/2.
PSI_MAX = numerics.exp_correctly_rounded(-0.5)

# Child generators of SeedSequence(seed).spawn(_N_CHILDREN), by matrix.  Append new matrices at the end.
_CHILD = {"w_in": 0, "w": 1, "w_back": 2, "dilation": 3, "translation": 4}
_N_CHILDREN = 5


def psi(z: np.ndarray) -> np.ndarray:
    """The mother wavelet ``Psi(z) = z exp(-z^2 / 2)``, exactly as the reservoir computes it (with the
    machine-independent ``numerics.exp``)."""
    e = z * z
    e *= -0.5
    e = numerics.exp(e)
    e *= z
    return e


def log_spaced_leaks(n_neurons: int, fastest_s: float = 30.0, slowest_s: float = 7200.0) -> tuple[float, ...]:
    """Per-neuron leak rates ``1 / tau`` (1/s) with ``tau`` log-spaced from ``fastest_s`` to ``slowest_s``."""
    if not (_is_real(fastest_s) and _is_real(slowest_s) and 0 < fastest_s <= slowest_s):
        raise ValueError(f"need 0 < fastest_s <= slowest_s, got {fastest_s!r}, {slowest_s!r}")
    if n_neurons == 1:
        return (1.0 / fastest_s,)
    taus = np.geomspace(fastest_s, slowest_s, n_neurons)
    return tuple(float(1.0 / tau) for tau in taus)


def _is_real(x: Any) -> bool:
    return isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, bool) and math.isfinite(x)


def _is_int(x: Any) -> bool:
    return isinstance(x, (int, np.integer)) and not isinstance(x, bool)


def _range(name: str, value: Any, positive: bool = False) -> tuple[float, float]:
    try:
        lo, hi = value
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a pair (low, high), got {value!r}") from None
    if not (_is_real(lo) and _is_real(hi) and lo <= hi) or (positive and not lo > 0):
        raise ValueError(f"{name} must be finite with low <= high{' and low > 0' if positive else ''}, got {value!r}")
    return float(lo), float(hi)


#: The largest reservoir a fit makes: the paper's 20 neurons (``wesn.PAPER_DEFAULTS``; the ring form has at most
#: 1 + 3 history + 2 coil stages).  A model file with more is refused (``model_checks.check_model_counts``).
MAX_NEURONS = 20


@dataclass(frozen=True)
class ReservoirParams:
    """How to build a reservoir (validated; ``ValueError`` when out of range).

    * ``n_neurons`` (the paper: 20; a model file at most ``MAX_NEURONS``), ``n_inputs`` (8: three temperatures, their
      rates, two gradients).
    * ``sample_time_s``: Ts, the model rate's sample time (1 s in the pipeline).
    * ``leak_per_s``: leak = 1 - a, one value for all neurons (the paper) or a tuple, one per neuron;
      each ``0 < Ts leak <= 1``.  A list (from YAML) is stored as a tuple.
    * ``normalized_leak``: True (default) for ``x += Ts leak (-x + Psi)`` (``|x_i| <= e^-1/2`` at
      every time scale, and the echo-state property for any leaks); False for the paper's
      ``x += Ts (-leak x + Psi)`` (``|x_i| <= e^-1/2 / leak_i``, growing with the time constant; with
      leaks below 1/s it needs ``spectral_radius`` below the smallest leak to forget its initial
      state, see the module docstring).
    * ``spectral_radius``: the target for ``||W|| max(1/s_i)``, in [0, 1) (see the module docstring
      for which norm: the larger of the 2-norm and the infinity norm).
    * ``input_scale``: ``w_in`` entries uniform in +-input_scale (inputs should be standardized).
    * ``feedback_scale``: ``w_back`` entries uniform in +-feedback_scale; 0 disables the feedback.
    * ``density``: fraction of nonzero entries of ``w``, in [0, 1].
    * ``dilation_range``: s_i uniform in it, low > 0; ``translation_range``: t_i uniform in it.
    * ``seed``: the one seed every matrix is drawn from.
    * ``chain_from``: a linear cascade beside the wavelets, ``x_i(n) = (1 - Ts leak_i) x_i(n-1) +
      Ts leak_i (Psi(v_i) + x_c(n-1))`` with ``c = chain_from[i]`` (-1: no upstream neuron): the ring
      form's coil of several first-order stages in series (``wesn.WesnConfig.reservoir``).  The
      upstream state is the previous sample's (one sample of delay against time constants of
      minutes), so a row's update stays elementwise.  The cascade must be acyclic; it keeps the
      echo-state property (its matrix is triangular with the decays on the diagonal) although
      ``contraction_bound`` (an infinity-norm bound) reaches 1 for a chained neuron.
    """

    n_neurons: int = 20
    n_inputs: int = 8
    sample_time_s: float = 1.0
    leak_per_s: float | tuple[float, ...] = 1.0 / 300.0
    normalized_leak: bool = True
    spectral_radius: float = 0.9
    input_scale: float = 1.0
    feedback_scale: float = 0.0
    density: float = 0.2
    dilation_range: tuple[float, float] = (1.0, 3.0)
    translation_range: tuple[float, float] = (-1.0, 1.0)
    seed: int = 0
    #: Linear cascade: ``chain_from[i]`` is the neuron whose previous state neuron i also integrates, -1 for
    #: none; () for no cascade (see the class docstring).  Normalized form only; acyclic.
    chain_from: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        for name in ("n_neurons", "n_inputs"):
            if not _is_int(getattr(self, name)) or getattr(self, name) < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {getattr(self, name)!r}")
        if not _is_real(self.sample_time_s) or not self.sample_time_s > 0:
            raise ValueError(f"sample_time_s must be finite and > 0, got {self.sample_time_s!r}")
        leak = self.leak_per_s
        if isinstance(leak, (list, tuple, np.ndarray)):
            if len(leak) != self.n_neurons or not all(_is_real(v) for v in leak):
                raise ValueError(f"leak_per_s: need {self.n_neurons} finite numbers (one per neuron), got {leak!r}")
            object.__setattr__(self, "leak_per_s", tuple(float(v) for v in leak))
        elif _is_real(leak):
            object.__setattr__(self, "leak_per_s", float(leak))
        else:
            raise ValueError(f"leak_per_s must be a number or one number per neuron, got {leak!r}")
        for v in self.leaks():
            if not 0.0 < v * self.sample_time_s <= 1.0:
                raise ValueError(
                    f"leak_per_s: need 0 < sample_time_s * leak <= 1, got leak {v!r} at Ts {self.sample_time_s!r}"
                )
        if not isinstance(self.normalized_leak, bool):
            raise ValueError(f"normalized_leak must be true or false, got {self.normalized_leak!r}")
        if not _is_real(self.spectral_radius) or not 0.0 <= self.spectral_radius < 1.0:
            raise ValueError(f"spectral_radius must be in [0, 1) (echo-state condition), got {self.spectral_radius!r}")
        for name in ("input_scale", "feedback_scale"):
            if not _is_real(getattr(self, name)) or getattr(self, name) < 0:
                raise ValueError(f"{name} must be finite and >= 0, got {getattr(self, name)!r}")
        if not _is_real(self.density) or not 0.0 <= self.density <= 1.0:
            raise ValueError(f"density must be in [0, 1], got {self.density!r}")
        object.__setattr__(self, "dilation_range", _range("dilation_range", self.dilation_range, positive=True))
        object.__setattr__(self, "translation_range", _range("translation_range", self.translation_range))
        if not _is_int(self.seed) or self.seed < 0:
            raise ValueError(f"seed must be an integer >= 0, got {self.seed!r}")
        object.__setattr__(self, "seed", int(self.seed))
        chain = self.chain_from
        if (
            not isinstance(chain, (list, tuple))
            or (chain and len(chain) != self.n_neurons)
            or not all(_is_int(c) and -1 <= c < self.n_neurons and c != i for i, c in enumerate(chain))
        ):
            raise ValueError(
                f"chain_from: need () or {self.n_neurons} neuron indices (-1 for none, never the neuron "
                f"itself), got {chain!r}"
            )
        chain = tuple(int(c) for c in chain)
        if chain and not self.normalized_leak:
            raise ValueError("chain_from needs the normalized leak")
        if any(chain_depth(chain, i) is None for i in range(len(chain))):
            raise ValueError(f"chain_from: the cascade must not loop, got {chain!r}")
        object.__setattr__(self, "chain_from", chain)

    def leaks(self) -> np.ndarray:
        """The leak rate of each neuron, shape (n_neurons,)."""
        if isinstance(self.leak_per_s, tuple):
            return np.array(self.leak_per_s, dtype=np.float64)
        return np.full(self.n_neurons, float(self.leak_per_s))

    def to_dict(self) -> dict[str, Any]:
        """Plain ints, floats, bools and lists: safe for ``yaml.safe_dump``, exact.  No cascade: no
        ``chain_from`` key (the file of a reservoir without one is as before the cascade existed)."""
        d: dict[str, Any] = {}
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name == "chain_from":
                if v:
                    d[f.name] = list(v)
                continue
            d[f.name] = [float(x) for x in v] if isinstance(v, tuple) else v
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ReservoirParams:
        """Inverse of ``to_dict``; missing keys take their defaults, unknown keys are errors."""
        require_known_keys(cls, d, "reservoir params")
        d = {k: tuple(v) if isinstance(v, list) else v for k, v in d.items()}
        return cls(**d)


def chain_depth(chain: Sequence[int], i: int) -> int | None:
    """How many neurons lie upstream of neuron i in the cascade ``chain`` (None: a loop)."""
    depth = 0
    while chain and chain[i] >= 0:
        i, depth = chain[i], depth + 1
        if depth > len(chain):
            return None
    return depth


@dataclass(frozen=True, eq=False)
class ReservoirMatrices:
    """The drawn matrices (float64): ``w_in`` (N, M), ``w`` (N, N), ``w_back`` (N,), ``dilation`` (N,) > 0,
    ``translation`` (N,)."""

    w_in: np.ndarray
    w: np.ndarray
    w_back: np.ndarray
    dilation: np.ndarray
    translation: np.ndarray

    def __post_init__(self) -> None:
        arrays = {f.name: np.array(getattr(self, f.name), dtype=np.float64) for f in fields(self)}
        n = arrays["dilation"].shape[0] if arrays["dilation"].ndim == 1 else -1
        m = arrays["w_in"].shape[1] if arrays["w_in"].ndim == 2 else -1
        shapes = {"w_in": (n, m), "w": (n, n), "w_back": (n,), "dilation": (n,), "translation": (n,)}
        if n < 1 or m < 1 or any(arrays[k].shape != s for k, s in shapes.items()):
            raise ValueError(f"reservoir matrices: inconsistent shapes { {k: a.shape for k, a in arrays.items()} }")
        if not all(np.isfinite(a).all() for a in arrays.values()):
            raise ValueError("reservoir matrices: values must be finite")
        if not (arrays["dilation"] > 0).all():
            raise ValueError("reservoir matrices: dilations must be > 0")
        for k, a in arrays.items():
            a.flags.writeable = False
            object.__setattr__(self, k, a)

    @classmethod
    def draw(cls, params: ReservoirParams) -> ReservoirMatrices:
        """Draw every matrix from ``params.seed`` (deterministic; see the module docstring)."""
        n, m = params.n_neurons, params.n_inputs
        rng = {
            k: np.random.default_rng(c) for k, c in zip(_CHILD, np.random.SeedSequence(params.seed).spawn(_N_CHILDREN))
        }
        w_in = rng["w_in"].uniform(-1.0, 1.0, (n, m)) * params.input_scale
        w_back = rng["w_back"].uniform(-1.0, 1.0, n) * params.feedback_scale
        dilation = rng["dilation"].uniform(*params.dilation_range, n)
        translation = rng["translation"].uniform(*params.translation_range, n)
        mask = rng["w"].random((n, n)) < params.density
        w = np.where(mask, rng["w"].uniform(-1.0, 1.0, (n, n)), 0.0)
        norm = max(float(np.linalg.norm(w, 2)), float(np.abs(w).sum(axis=1).max()))
        if norm > 0:
            w *= params.spectral_radius * float(dilation.min()) / norm
        return cls(w_in, w, w_back, dilation, translation)

    @property
    def n_neurons(self) -> int:
        return self.w.shape[0]

    @property
    def n_inputs(self) -> int:
        return self.w_in.shape[1]

    def echo_state_gain(self) -> float:
        """``||W||_2 max(1/s_i)``: the method's echo-state condition is that this is < 1."""
        return float(np.linalg.norm(self.w, 2)) / float(self.dilation.min())

    def to_dict(self) -> dict[str, Any]:
        """Nested lists of Python floats (exact through ``yaml.safe_dump``/``safe_load``)."""
        return {f.name: getattr(self, f.name).tolist() for f in fields(self)}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ReservoirMatrices:
        keys = {f.name for f in fields(cls)}
        if not isinstance(d, dict) or set(d) != keys:
            got = sorted(d) if isinstance(d, dict) else type(d).__name__
            raise ValueError(f"reservoir matrices need exactly the keys {sorted(keys)}, got {got}")
        try:
            return cls(**{k: np.array(d[k], dtype=np.float64) for k in keys})
        except (TypeError, ValueError) as exc:
            raise ValueError(f"reservoir matrices: {exc}") from None


@dataclass
class ReservoirState:
    """``x``: the neuron states x(n), shape (N,); ``y``: the feedback value the next step uses when
    ``step`` is given none (the last ``set_feedback``; 0 at the start)."""

    x: np.ndarray
    y: float = 0.0

    @classmethod
    def zeros(cls, n_neurons: int) -> ReservoirState:
        return cls(np.zeros(n_neurons), 0.0)

    def to_dict(self) -> dict[str, Any]:
        return {"x": [float(v) for v in self.x], "y": float(self.y)}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ReservoirState:
        if not isinstance(d, dict) or set(d) != {"x", "y"}:
            raise ValueError(f"reservoir state needs exactly the keys ['x', 'y'], got {d!r:.80}")
        try:
            x = np.array([float(v) for v in d["x"]], dtype=np.float64)
            y = float(d["y"])
        except (TypeError, ValueError) as exc:
            raise ValueError(f"reservoir state: not numbers: {exc}") from None
        if len(x) < 1 or not np.isfinite(x).all() or not math.isfinite(y):
            raise ValueError("reservoir state: x must be a non-empty list of finite numbers and y finite")
        return cls(x, y)


class WaveletReservoir:
    """The reservoir over a stream of inputs: ``step`` one sample, ``run`` many, same state.

    ``WaveletReservoir(params)`` draws the matrices from ``params.seed``;
    ``WaveletReservoir(params, matrices)`` uses stored ones (a model file; ``params`` then supplies
    Ts, the leaks and the form, and must agree with the matrices' shapes).
    """

    def __init__(
        self,
        params: ReservoirParams | None = None,
        matrices: ReservoirMatrices | None = None,
        state: ReservoirState | None = None,
    ) -> None:
        self.params = params if params is not None else ReservoirParams()
        self.matrices = matrices if matrices is not None else ReservoirMatrices.draw(self.params)
        if (self.matrices.n_neurons, self.matrices.n_inputs) != (self.params.n_neurons, self.params.n_inputs):
            raise ValueError(
                f"matrices are {self.matrices.n_neurons} neurons x {self.matrices.n_inputs} inputs, "
                f"params say {self.params.n_neurons} x {self.params.n_inputs}"
            )
        ts = float(self.params.sample_time_s)
        leaks = self.params.leaks()
        mat = self.matrices
        self._w_in, self._w, self._w_back = mat.w_in, mat.w, mat.w_back
        self._t, self._s = mat.translation, mat.dilation
        self._feedback = bool((mat.w_back != 0).any())
        self._recurrent = bool((mat.w != 0).any())  # W = 0 (the ring form): W x is 0, not computed
        self._decay = 1.0 - ts * leaks  # (1 - Ts leak), per neuron
        self._gain = ts * leaks if self.params.normalized_leak else np.full(self.params.n_neurons, ts)
        chain = self.params.chain_from
        self._chained = any(c >= 0 for c in chain)
        if self._chained:  # x_c(n-1) for chained neurons; unchained ones read themselves, times 0
            self._chain_src = np.array([c if c >= 0 else i for i, c in enumerate(chain)])
            self._chain_gain = np.where(np.array(chain) >= 0, self._gain, 0.0)
        self._last_wavelet = np.zeros(self.params.n_neurons)
        self.set_state(state if state is not None else ReservoirState.zeros(self.params.n_neurons))

    # --- state -----------------------------------------------------------------------------------

    def get_state(self) -> ReservoirState:
        """A copy of the current state."""
        return ReservoirState(self._x.copy(), self._y)

    def set_state(self, state: ReservoirState) -> None:
        x = np.array(state.x, dtype=np.float64)
        if x.shape != (self.params.n_neurons,):
            raise ValueError(f"state has shape {x.shape}, the reservoir has {self.params.n_neurons} neurons")
        self._x, self._y = x, float(state.y)

    def reset(self) -> None:
        """Back to x = 0 and feedback 0."""
        self.set_state(ReservoirState.zeros(self.params.n_neurons))

    def set_feedback(self, y: float) -> None:
        """The value ``step`` feeds back at the next sample when called without ``y_prev``."""
        self._y = float(y)

    @property
    def x(self) -> np.ndarray:
        return self._x.copy()

    def wavelet_of(self, z: np.ndarray, neuron: int) -> np.ndarray:
        """``Psi((w_in,i . z - t_i) / s_i)`` of one neuron for one input row (M,) or many (T, M): what it
        integrates without recurrence and feedback, the same bits as a step computes (sums left to right)."""
        v = numerics.dot(z, self._w_in[neuron])
        v = v - self._t[neuron]
        v = v / self._s[neuron]
        return psi(np.asarray(v, dtype=np.float64))

    @property
    def last_wavelet(self) -> np.ndarray:
        """``Psi(v)`` of the last ``step`` (or of the last row ``run`` stepped one at a time), before the leak's
        gain: what each neuron integrated.  For a readout that needs it (``wesn.WesnModel.coil_rate_of``)."""
        return self._last_wavelet

    @property
    def bounds(self) -> np.ndarray:
        """The invariant bound on |x_i|: ``e^-1/2 / leak_i`` (paper form) or ``e^-1/2`` (normalized), times
        one plus the number of neurons upstream in a cascade."""
        if self.params.normalized_leak:
            chain = self.params.chain_from
            # validated chains have no loop: chain_depth is never None here
            return np.array([PSI_MAX * (1 + cast(int, chain_depth(chain, i))) for i in range(self.params.n_neurons)])
        return PSI_MAX / self.params.leaks()

    @property
    def contraction_bound(self) -> float:
        """c of ``||xa(n) - xb(n)||_inf <= c^n ||xa(0) - xb(0)||_inf``; < 1 guarantees the echo-state property."""
        row = np.abs(self._w).sum(axis=1) / self._s
        chain = self._chain_gain if self._chained else 0.0
        return float((self._decay + self._gain * row + chain).max())

    # --- stepping --------------------------------------------------------------------------------

    def _activation(self, z: np.ndarray) -> np.ndarray:
        """``Ts g_i Psi((z_i - t_i) / s_i)`` for a row z (n_neurons,) or many rows (T, n_neurons)."""
        v = z - self._t
        v /= self._s
        p = psi(v)
        if p.ndim == 1:  # a step: kept for ``last_wavelet`` (a run's rows are not kept)
            self._last_wavelet = p
        return p * self._gain

    def _advance(self, u: np.ndarray, y: float) -> bool:
        """One Euler step from ``self._x``; False (and nothing changed) when the result is not finite."""
        x = self._x
        z = numerics.matvec(self._w_in, u)
        if self._recurrent:
            z += numerics.matvec(self._w, x)
        if self._feedback:
            z += self._w_back * y
        new = self._decay * x
        new += self._activation(z)
        if self._chained:
            new += self._chain_gain * x[self._chain_src]
        if not math.isfinite(new.sum()):
            return False
        self._x = new
        return True

    def _run_feedforward(self, inputs: np.ndarray, ys: list[float] | None, out: np.ndarray) -> None:
        """``run`` without recurrence and feedback (the ring form): the wavelet input of a row does not
        depend on the state, so it is computed for all rows at once with the same elementwise operations
        as ``_advance`` (``W_in u`` summed over the inputs in the same order), and only the leak is
        stepped row by row: bit-identical to ``_advance`` row by row, one numpy call per operation for all rows."""
        products = inputs.T[:, :, None] * self._w_in.T[:, None, :]  # (n_inputs, T, n_neurons)
        drive = self._activation(numerics.sum_first(products))  # (T, n_neurons)
        if len(inputs) and self._leak_columns(drive, out):
            self._x = out[-1].copy()
            if ys is not None:
                self._y = ys[-1]
            return
        x, last_ok = self._x, None
        chained = self._chained
        chain_gain: Any = self._chain_gain if chained else None
        chain_src: Any = self._chain_src if chained else None
        for k in range(len(inputs)):
            new = self._decay * x
            new += drive[k]
            if chained:
                new += chain_gain * x[chain_src]
            if math.isfinite(new.sum()):
                x, last_ok = new, k
            out[k] = x
        self._x = x
        if ys is not None and last_ok is not None:
            self._y = ys[last_ok]

    def _leak_columns(self, drive: np.ndarray, out: np.ndarray) -> bool:
        """The leak of ``_run_feedforward`` stepped neuron by neuron instead of row by row, in Python floats:
        the same IEEE operations in the same order (``(decay_i x_i + drive_i) + chain_gain_i x_src``, each
        rounded, no fused multiply-add), so bit-identical, and without numpy's per-row call overhead.  A
        neuron's source in the cascade is stepped before it.  Fills ``out`` and returns True when every row
        is finite with a finite sum (no row would have been held); else False, and the caller steps rows."""
        n = self.params.n_neurons
        x0 = self._x.tolist()
        decay = np.broadcast_to(self._decay, (n,)).tolist()
        chained = self._chained
        src = self._chain_src.tolist() if chained else list(range(n))
        gain = self._chain_gain.tolist() if chained else [0.0] * n
        columns: list[list[float] | None] = [None] * n
        order = sorted(range(n), key=lambda i: cast(int, chain_depth(self.params.chain_from, i)) if chained else 0)
        for i in order:
            a, g, x = decay[i], gain[i], x0[i]
            ds = drive[:, i].tolist()
            if not chained:
                columns[i] = [x := a * x + d for d in ds]
            elif src[i] == i:  # unchained in a cascade: its own x, times 0 (as the row step adds it)
                columns[i] = [x := a * x + d + g * x for d in ds]
            else:
                upstream = cast(list, columns[src[i]])
                previous = [x0[src[i]], *upstream[:-1]]
                columns[i] = [x := a * x + d + g * s for d, s in zip(ds, previous)]
        out[:] = np.array(columns).T
        peak = float(np.abs(out).max())
        return math.isfinite(peak) and peak * n < 1e300  # finite, and no row's sum can overflow

    def step(self, u: Sequence[float] | np.ndarray, y_prev: float | None = None) -> np.ndarray:
        """x(n) from u(n), shape (n_inputs,), and the feedback y(n-1) (default: the stored one).

        Returns a copy of the new state (the held state when the step is skipped).
        """
        u = np.asarray(u, dtype=np.float64)
        if u.shape != (self.params.n_inputs,):
            raise ValueError(f"u must have shape ({self.params.n_inputs},), got {u.shape}")
        y = self._y if y_prev is None else float(y_prev)
        if self._advance(u, y):
            self._y = y
        return self._x.copy()

    def run(self, inputs: np.ndarray, y_prev: np.ndarray | None = None) -> np.ndarray:
        """States for each row of ``inputs`` (T, n_inputs); ``y_prev`` (T,) is y(n-1) for each row
        (teacher forcing), or None for the stored feedback value throughout.  Returns (T, n_neurons)."""
        inputs = np.asarray(inputs, dtype=np.float64)
        if inputs.ndim != 2 or inputs.shape[1] != self.params.n_inputs:
            raise ValueError(f"inputs must have shape (T, {self.params.n_inputs}), got {inputs.shape}")
        n = len(inputs)
        if y_prev is not None:
            y_prev = np.asarray(y_prev, dtype=np.float64)
            if y_prev.shape != (n,):
                raise ValueError(f"y_prev must have shape ({n},), got {y_prev.shape}")
        out = np.empty((n, self.params.n_neurons))
        ys = y_prev.tolist() if y_prev is not None else None
        if not (self._recurrent or self._feedback):
            self._run_feedforward(inputs, ys, out)
            return out
        for k in range(n):
            y = self._y if ys is None else ys[k]
            if self._advance(inputs[k], y):
                self._y = y
            out[k] = self._x
        return out

    def run_closed_loop(
        self, inputs: np.ndarray, readout: Callable[[np.ndarray, np.ndarray], float]
    ) -> tuple[np.ndarray, np.ndarray]:
        """Operation: each step feeds back the model's own previous output.

        For each row: ``x = step(u)`` (with the stored feedback), ``y = readout(x, u)``,
        ``set_feedback(y)``.  ``readout`` gets the new state and the input row (to build regressors
        such as ``[x, 1, u]``).  Returns the states (T, n_neurons) and the outputs (T,).
        Identical to the same loop written by hand, in any chunks.
        """
        inputs = np.asarray(inputs, dtype=np.float64)
        states = np.empty((len(inputs), self.params.n_neurons))
        outputs = np.empty(len(inputs))
        for k in range(len(inputs)):
            x = self.step(inputs[k])
            y = float(readout(x, inputs[k]))
            self.set_feedback(y)
            states[k], outputs[k] = x, y
        return states, outputs

    # --- model file ------------------------------------------------------------------------------

    def to_dict(self) -> dict[str, Any]:
        """``{"params": ..., "matrices": ...}``: plain values, exact (the state is separate: ``state.to_dict()``)."""
        return {"params": self.params.to_dict(), "matrices": self.matrices.to_dict()}

    @classmethod
    def from_dict(cls, d: dict[str, Any], state: ReservoirState | None = None) -> WaveletReservoir:
        """A reservoir from ``to_dict``'s output, with the stored matrices (never redrawn)."""
        if not isinstance(d, dict) or set(d) != {"params", "matrices"}:
            raise ValueError("a reservoir needs exactly the keys ['matrices', 'params']")
        return cls(ReservoirParams.from_dict(d["params"]), ReservoirMatrices.from_dict(d["matrices"]), state)
