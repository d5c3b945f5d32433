"""Stage 1: the adaptive forward linear prediction filter (AFLP), paper eq. 5-7.

Per model-rate sample n (1 Hz in the pipeline), with the input vector of the
N previous samples ``R(n) = [r(n-1) ... r(n-N)]``::

    D_hat(n) = Phi(n)^T R(n)                                output: the prediction from the past
    e(n)     = r(n) - D_hat(n)                              a-priori error
    Ke2(n)   = lam Ke2(n-1)  + (1-lam) e(n)^2
    Ki2(n)   = lam Ki2(n-1)  + (1-lam) r(n-i)^2             i = 1..N
    Kei(n)   = lam Kei(n-1)  + (1-lam) e(n) r(n-i)
    Pi(n)    = Kei(n) / sqrt(Ke2(n) Ki2(n) + tiny)          correlation estimate, |Pi| <= 1
    L(n)     = mean_i |Pi(n)|                               (``fixed_step`` replaces it by a constant)
    eps(n)   = L(n) / (delta + R(n)^T R(n))
    Phi(n+1) = Phi(n) + eps(n) e(n) R(n)

``lam`` is ``AflpParams.forgetting``.  ``L`` is in [0, 1], so every update is an
NLMS step inside its stability range (0 < mu < 2); the filter is a normalized
LMS whose step size follows how much of the error the past samples still
explain: large while the predictor is wrong, small once the error is
uncorrelated with the inputs.  With ``fixed_step = mu`` it *is* plain NLMS
(tested against an independent implementation).

|Pi| <= 1 is Cauchy-Schwarz for the three exponentially weighted sums (same
weights, all started at zero); ``Pi`` is also clamped to [-1, 1] so that
rounding can never push ``L`` above 1.

Warm-up: the filter starts with ``Phi = 0`` and an all-zero history, so before
N samples have been seen ``R(n)`` holds zeros in place of the samples not seen
yet, and the first outputs are 0.  The step factor L settles within a few
memories 1 / (1 - lam) (a few hundred samples at 0.99); the static-noise
figures below skip the first 1000 samples.

What the output is on static data (measured; ``tests/compensation/test_compensation_aflp.py``).
The output is a prediction, so how much noise it removes depends on the level
of the input, not only on its noise:

* zero-mean white noise (B0 and Earth rate removed): the best predictor is ~0
  and the output std is the misadjustment of the adaptive weights, set by L,
  i.e. by ``forgetting``: std ratio in/out 3.4 (lam 0.95), 4.0 (0.97), 5.5 (0.99);
* the same noise plus a slow drift (0.05 deg/h, 1-h sinusoid), std about the
  true drift: 3.35 (0.97), 4.1 (0.99): the paper's 0.176 -> 0.044 deg/h;
* about a large mean (B0 left in) the predictor must average, ``sum Phi = 1``,
  and an average of N white samples has std sigma / sqrt(N): the ratio is
  below sqrt(10) = 3.16 for N = 10 whatever lam (2.1 measured at 0.99; the
  zero warm-up also leaves unequal weights that the tiny normalized step
  along the noise directions, ~L sigma^2 / (N c^2), never evens out).  Remove
  B0 first, as the method says (r = D + N).

The default ``forgetting = 0.99`` reproduces the paper's ratio of 4 on the
static case with drift; 0.97 reproduces the ratio on drift-free noise
(docs/decisions/2026-12-07-aflp-forgetting.md).

Non-finite input (NaN, +-inf) is treated as a missing sample: the output is
the prediction ``Phi(n)^T R(n)`` (which never depends on r(n)), and the state
is left exactly as it was (no update, the history does not advance).  The
pipeline never feeds NaN; this is defence, not a gap model.

``step(r)`` and ``run(r)`` share one update (``_advance``) on plain Python
floats, so ``run`` is bit-identical to repeated ``step`` and to any split of
the input into chunks (tested).  The state converts to and from plain lists
and floats (``AflpState.to_dict`` / ``from_dict``) for the YAML model file,
exactly (float64 values round-trip through ``repr``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["AflpFilter", "AflpParams", "AflpState"]


@dataclass(frozen=True)
class AflpParams:
    """Parameters of the AFLP filter (validated; ``ValueError`` when out of range).

    * ``order``: N, the number of past samples predicting the next (the paper: 10).
    * ``forgetting``: lam of the correlation estimates, 0 < lam < 1.  The method
      asks for 0.9 < lam < 1 (memory ``1 / (1 - lam)`` of 10 samples or more);
      smaller values are accepted for experiments.  Larger lam: smaller steps
      once converged (a quieter output on static data), slower tracking.
    * ``delta``: regularizer of the NLMS normalization ``delta + R^T R``, > 0,
      in the input's units squared ((deg/h)^2 in the pipeline).  Negligible for
      N = 10; for very small orders (N = 1..3) ``R^T R`` is often near 0 and a
      tiny delta lets single steps kick Phi far away (plain NLMS alike;
      docs/decisions/2026-12-07-aflp-forgetting.md): use a delta of the order
      of N x the input variance.
    * ``tiny``: added under the square root of ``Pi``'s denominator, > 0, so that
      0 / 0 (no error or no input yet) gives ``Pi = 0``.
    * ``fixed_step``: when set, ``L(n)`` is this constant mu, 0 < mu < 2: plain
      NLMS (the test oracle, and an ablation of the adaptive step).
    """

    order: int = 10
    forgetting: float = 0.99
    delta: float = 1e-9
    tiny: float = 1e-30
    fixed_step: float | None = None

    def __post_init__(self) -> None:
        if isinstance(self.order, bool) or not isinstance(self.order, (int, np.integer)) or self.order < 1:
            raise ValueError(f"order must be an integer >= 1, got {self.order!r}")
        if not _is_real(self.forgetting) or not 0.0 < self.forgetting < 1.0:
            raise ValueError(f"forgetting must be in (0, 1) (the method uses 0.9..1), got {self.forgetting!r}")
        if not _is_real(self.delta) or not 0.0 < self.delta < math.inf:
            raise ValueError(f"delta must be finite and > 0, got {self.delta!r}")
        if not _is_real(self.tiny) or not 0.0 < self.tiny < math.inf:
            raise ValueError(f"tiny must be finite and > 0, got {self.tiny!r}")
        if self.fixed_step is not None and (not _is_real(self.fixed_step) or not 0.0 < self.fixed_step < 2.0):
            raise ValueError(f"fixed_step must be None or in (0, 2) (NLMS stability), got {self.fixed_step!r}")


def _is_real(x: Any) -> bool:
    return isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, bool) and math.isfinite(x)


@dataclass
class AflpState:
    """Everything the filter carries from one sample to the next (float64 arrays).

    * ``phi``: Phi(n), the predictor weights for the next sample, shape (N,);
    * ``history``: R(n) for the next sample, ``[r(n-1) ... r(n-N)]``, shape (N,);
      zeros in place of samples not seen yet;
    * ``ke2``: Ke2, the error power; ``ki2``: Ki2 per lag, (N,); ``kei``: Kei per lag, (N,);
    * ``samples``: how many (finite) samples have updated the state.
    """

    phi: np.ndarray
    history: np.ndarray
    ke2: float
    ki2: np.ndarray
    kei: np.ndarray
    samples: int

    @classmethod
    def zeros(cls, order: int) -> AflpState:
        z = np.zeros(order)
        return cls(z.copy(), z.copy(), 0.0, z.copy(), z.copy(), 0)

    @property
    def order(self) -> int:
        return len(self.phi)

    def correlations(self, tiny: float = AflpParams.tiny) -> np.ndarray:
        """Pi of the last update, ``Kei / sqrt(Ke2 Ki2 + tiny)`` clamped to [-1, 1], shape (N,)."""
        return np.array(_correlations(self.ke2, self.ki2.tolist(), self.kei.tolist(), tiny))

    def to_dict(self) -> dict[str, Any]:
        """Plain lists, floats and an int (no numpy scalars): safe for ``yaml.safe_dump``, exact."""
        return {
            "phi": [float(v) for v in self.phi],
            "history": [float(v) for v in self.history],
            "ke2": float(self.ke2),
            "ki2": [float(v) for v in self.ki2],
            "kei": [float(v) for v in self.kei],
            "samples": int(self.samples),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> AflpState:
        """Inverse of ``to_dict``; ``ValueError`` for missing or unknown keys, wrong lengths or bad values."""
        keys = {"phi", "history", "ke2", "ki2", "kei", "samples"}
        if not isinstance(d, dict) or set(d) != keys:
            got = sorted(d) if isinstance(d, dict) else type(d).__name__
            raise ValueError(f"AFLP state needs exactly the keys {sorted(keys)}, got {got}")
        try:
            arrays = {k: np.array([float(v) for v in d[k]], dtype=np.float64) for k in ("phi", "history", "ki2", "kei")}
            ke2 = float(d["ke2"])
        except (TypeError, ValueError) as exc:
            raise ValueError(f"AFLP state: not a list of numbers: {exc}") from None
        samples = d["samples"]
        order = len(arrays["phi"])
        if order < 1 or any(len(a) != order for a in arrays.values()):
            raise ValueError(
                f"AFLP state: phi, history, ki2 and kei must have one equal length >= 1, got "
                f"{ {k: len(a) for k, a in arrays.items()} }"
            )
        if not all(np.isfinite(a).all() for a in arrays.values()) or not math.isfinite(ke2):
            raise ValueError("AFLP state: values must be finite")
        if ke2 < 0 or (arrays["ki2"] < 0).any():
            raise ValueError("AFLP state: ke2 and ki2 are powers, they must be >= 0")
        if isinstance(samples, bool) or not isinstance(samples, int) or samples < 0:
            raise ValueError(f"AFLP state: samples must be an integer >= 0, got {samples!r}")
        return cls(arrays["phi"], arrays["history"], ke2, arrays["ki2"], arrays["kei"], samples)


def _correlations(ke2: float, ki2: list[float], kei: list[float], tiny: float) -> list[float]:
    return [min(1.0, max(-1.0, kei[i] / math.sqrt(ke2 * ki2[i] + tiny))) for i in range(len(ki2))]


class AflpFilter:
    """The AFLP filter over a stream of samples: ``step`` one, ``run`` many, same state.

    ``step(r)`` returns ``D_hat(n) = Phi(n)^T R(n)``, the prediction of r(n) from
    the N samples before it (computed before the update), then updates the
    state with r(n).  ``run(r)`` does the same for each element in turn.
    """

    def __init__(self, params: AflpParams | None = None, state: AflpState | None = None) -> None:
        self.params = params if params is not None else AflpParams()
        self._lam = float(self.params.forgetting)
        self._one_minus_lam = 1.0 - self._lam
        self._delta = float(self.params.delta)
        self._tiny = float(self.params.tiny)
        self._fixed = None if self.params.fixed_step is None else float(self.params.fixed_step)
        self._load(state if state is not None else AflpState.zeros(self.params.order))

    def _load(self, state: AflpState) -> None:
        if state.order != self.params.order:
            raise ValueError(f"state has order {state.order}, the filter's is {self.params.order}")
        # Plain Python lists of floats: the same float64 values, updated one by one without numpy's per-call
        # overhead (a sample touches N values; ``benchmarks/bench_accuracy.py`` runs the filter).
        self._phi = [float(v) for v in state.phi]
        self._hist = [float(v) for v in state.history]
        self._ki2 = [float(v) for v in state.ki2]
        self._kei = [float(v) for v in state.kei]
        self._ke2 = [float(state.ke2)]  # a one-element list so ``_advance`` can update it in place
        self._samples = int(state.samples)

    def get_state(self) -> AflpState:
        """A copy of the current state (changing it does not change the filter)."""
        return AflpState(
            np.array(self._phi),
            np.array(self._hist),
            self._ke2[0],
            np.array(self._ki2),
            np.array(self._kei),
            self._samples,
        )

    def set_state(self, state: AflpState) -> None:
        """The filter continues from ``state`` (``get_state``'s; ``ValueError`` for another order)."""
        self._load(state)

    def reset(self) -> None:
        """Back to the initial all-zero state."""
        self._load(AflpState.zeros(self.params.order))

    def correlations(self) -> np.ndarray:
        """Pi(n) of the last update, shape (N,), each in [-1, 1] (zeros before any update)."""
        return np.array(_correlations(self._ke2[0], self._ki2, self._kei, self._tiny))

    def step_factor(self) -> float:
        """L(n) of the last update: ``fixed_step`` if set, else mean |Pi(n)|, in [0, 1]."""
        if self._fixed is not None:
            return self._fixed
        l_sum = 0.0
        for p in _correlations(self._ke2[0], self._ki2, self._kei, self._tiny):
            l_sum += abs(p)
        return l_sum / len(self._phi)

    def step(self, r: float) -> float:
        """One sample in, ``D_hat(n)`` out (see the module docstring); non-finite r: no update."""
        return self._advance(float(r))

    def run(self, r: np.ndarray) -> np.ndarray:
        """``step`` over each element of a 1-D array, in order; bit-identical to stepping one by one."""
        x = np.asarray(r, dtype=np.float64)
        if x.ndim != 1:
            raise ValueError(f"run takes a 1-D array, got shape {x.shape}")
        advance = self._advance
        return np.array([advance(v) for v in x.tolist()], dtype=np.float64)

    def _advance(self, r: float) -> float:
        # The one implementation of the update, on plain floats (see the module docstring).
        phi, hist, ki2, kei = self._phi, self._hist, self._ki2, self._kei
        n = len(phi)
        d_hat = 0.0
        for i in range(n):
            d_hat += phi[i] * hist[i]
        if not math.isfinite(r):
            return d_hat
        lam, oml, tiny = self._lam, self._one_minus_lam, self._tiny
        e = r - d_hat
        ke2 = lam * self._ke2[0] + oml * (e * e)
        self._ke2[0] = ke2
        rr = 0.0
        l_sum = 0.0
        for i in range(n):
            h = hist[i]
            rr += h * h
            k2 = lam * ki2[i] + oml * (h * h)
            ki2[i] = k2
            k = lam * kei[i] + oml * (e * h)
            kei[i] = k
            p = abs(k / math.sqrt(ke2 * k2 + tiny))
            l_sum += p if p < 1.0 else 1.0  # noqa: FURB136 (min() is a call: slower in this loop)
        level = self._fixed if self._fixed is not None else l_sum / n
        g = level / (self._delta + rr) * e
        for i in range(n):
            phi[i] += g * hist[i]
        hist.pop()
        hist.insert(0, r)
        self._samples += 1
        return d_hat
