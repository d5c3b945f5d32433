"""Stage 3: the readout.  The paper's adaptive law (eq. 18-22, Na et al.'s parameter-estimation-error
law) and closed-form ridge regression.

The adaptive law, continuous form: ``k dXf/dt + Xf = X``, ``k dDf/dt + Df = D``,
``dH/dt = -l H + Xf Xf^T``, ``dI/dt = -l I + Xf Df`` (the paper prints ``Df Df^T``: wrong),
``M = H W - I``, ``dW/dt = -K M``.  Exact zero-order-hold discretization with sample time Ts::

    alpha = exp(-Ts / k),  beta = exp(-l Ts),  g = (1 - beta) / l      (1 - alpha, 1 - beta via expm1)
    Xf = alpha Xf + (1 - alpha) X            Df = alpha Df + (1 - alpha) D
    H  = beta H + g Xf Xf^T                  I  = beta I + g Xf Df
    M  = H W - I
    W  = W - Gamma (M + sigma W)             only when learning (``learn``, not ``track``)

X is the regressor vector (reservoir states plus whatever the caller appends: a constant 1, the
raw inputs; the law does not care), D the target (the drift).  ``k = filter_time_s`` (0: no
filter), ``1/l = memory_time_s``.  H and I are exponentially weighted sums of the filtered
regressors and targets, so ``W* = H^-1 I`` is the weighted least-squares fit over the last ~1/l
seconds, and the law is a gradient flow towards it: ``W - W*`` decays as ``(1 - Gamma H)^n``.

Gain.  Normalized (default): ``Gamma = kappa / (delta + trace H + n sigma)``, 0 < kappa < 2.  Since
``lambda_max(H + sigma) <= trace(H) + n sigma``, every eigenvalue of ``Gamma (H + sigma)`` is in
[0, kappa]: stable at any data scale (tested from 1e-3 to 1e3).  Fixed (``fixed_gain = K``, per
second): ``Gamma = Ts K``, stable only while ``Ts K (lambda_max(H) + sigma) < 2`` (tested on both
sides of the bound); H grows with the data scale squared and with the memory window, so a fixed
gain tuned on one data set can diverge on another.

Preconditioned (``precondition``, with the normalized gain): ``Gamma = kappa / n diag(1 / (H_ii + sigma
+ delta / n))``, one gain per direction: the same law on regressors standardized by their windowed
scale (``x_i / sqrt(H_ii)``), whose H has a unit diagonal and trace n, so it is stable for the same
kappa.  It equalizes the columns' scales, not their correlation.  The online readout (``OnlineReadout``)
does not use it by default (docs/decisions/2026-12-07-readout-preconditioning.md).

Convergence is per eigen-direction of H: along eigenvalue lambda_j the error shrinks by
``1 - Gamma lambda_j`` per step, i.e. with the normalized gain a time constant of
``trace(H) / (kappa lambda_j)`` samples.  Reservoir states driven by a few slow temperatures are
strongly correlated (H's condition number is easily 1e6 or more): the dominant directions converge
in a few samples, the weak ones effectively never.  The law then behaves like gradient descent
stopped early (an implicit ridge), not like the least-squares solution; compare with ``ridge_fit``.

sigma.  The paper tunes "sigma = 0.152" without defining it; the usual reading is sigma-modification
leakage, ``dW/dt = -K (M + sigma W)``.  Its fixed point is ``(H + sigma I) W = I``: a ridge penalty
on the windowed normal equations, in H's units (H ~ memory_time_s * mean(Xf^2)).  Default 0.

Predicting apart from learning: ``predict(x)`` is ``y_hat = W^T x`` with the state untouched; called
before ``learn(x, d)`` it is the honest a-priori prediction (d(n) not used yet).  ``learn`` advances Xf,
Df, H, I, then moves W; ``track`` advances Xf, Df, H, I with W held.  Xf, Df, H, I never depend on W, so
holding W (``track``) and learning again is seamless: the sums keep running and W then moves towards the
fit over the recent window.

Non-finite values: when x or d holds NaN or +-inf, ``learn`` and ``track`` change nothing (no filter, no
sums, no W step); ``predict`` is NaN when x is not finite.  In operation, with no measured drift, only
``predict``.

``run(x, d, learn)`` is ``predict`` then ``learn`` (or ``track`` where the mask is false) row by row, the
same private steps, so it is bit-identical to the single calls and to any chunks (tested).  The cost of
a step is the pipeline's adapting block in ``benchmarks/bench_model_step.py`` (an outer product and a
matrix-vector product of n features: O(n^2)).

Ridge regression, ``ridge_fit``: the closed form with an unpenalized intercept (X and y are centred
with the weighted means, the penalty applies to w only), solved as the least-squares problem
``[sqrt(sw) Xc; sqrt(alpha) I] w = [sqrt(sw) yc; 0]`` (``np.linalg.lstsq``: an SVD, no normal
equations, so no squared condition number).  ``Standardizer`` stores per-column means and scales
fitted on training data and applies them unchanged later.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from . import numerics
from .keys import require_known_keys

__all__ = ["AdaptiveLaw", "AdaptiveLawParams", "AdaptiveLawState", "Standardizer", "ridge_fit"]


def _is_real(x: Any) -> bool:
    return isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, bool) and math.isfinite(x)


@dataclass(frozen=True)
class AdaptiveLawParams:
    """Parameters of the adaptive law (validated; ``ValueError`` when out of range).

    * ``filter_time_s``: k, the first-order filter on X and D, >= 0 (0: no filter).  Small: it only
      has to take the edge off the 1-s noise of the target; both sides are filtered alike, so it
      does not bias the fit.
    * ``memory_time_s``: 1/l, the memory window of H and I, > 0.  It must span a real temperature
      excursion (tens of minutes), or H is rank-deficient and W barely moves.
    * ``kappa``: the normalized gain, 0 < kappa < 2 (1: the fastest for the dominant direction).
    * ``delta``: > 0, keeps ``Gamma`` finite while H is still 0, in H's units.
    * ``sigma``: >= 0, sigma-modification leakage (a ridge penalty in H's units); default 0.
    * ``fixed_gain``: K (1/s) for the paper's fixed gain ``Gamma = Ts K`` instead of the normalized
      one (the paper: 13.814); None for the normalized gain.
    """

    filter_time_s: float = 10.0
    memory_time_s: float = 1800.0
    kappa: float = 1.0
    delta: float = 1e-9
    sigma: float = 0.0
    fixed_gain: float | None = None
    precondition: bool = False

    def __post_init__(self) -> None:
        if not _is_real(self.filter_time_s) or self.filter_time_s < 0:
            raise ValueError(f"filter_time_s must be finite and >= 0, got {self.filter_time_s!r}")
        if not _is_real(self.memory_time_s) or not self.memory_time_s > 0:
            raise ValueError(f"memory_time_s must be finite and > 0, got {self.memory_time_s!r}")
        if not _is_real(self.kappa) or not 0.0 < self.kappa < 2.0:
            raise ValueError(f"kappa must be in (0, 2) (stability of the normalized gain), got {self.kappa!r}")
        if not _is_real(self.delta) or not self.delta > 0:
            raise ValueError(f"delta must be finite and > 0, got {self.delta!r}")
        if not _is_real(self.sigma) or self.sigma < 0:
            raise ValueError(f"sigma must be finite and >= 0, got {self.sigma!r}")
        if self.fixed_gain is not None and (not _is_real(self.fixed_gain) or not self.fixed_gain > 0):
            raise ValueError(f"fixed_gain must be None or finite and > 0, got {self.fixed_gain!r}")
        if not isinstance(self.precondition, bool) or self.precondition and self.fixed_gain is not None:
            raise ValueError("precondition must be true or false, and goes with the normalized gain only")

    def to_dict(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> AdaptiveLawParams:
        """Inverse of ``to_dict``; missing keys take their defaults, unknown keys are errors."""
        require_known_keys(cls, d, "adaptive law params")
        return cls(**d)


@dataclass(eq=False)
class AdaptiveLawState:
    """Everything the law carries between samples (float64): ``xf`` (n,), ``df``, ``h`` (n, n),
    ``i`` (n,), ``w`` (n,)."""

    xf: np.ndarray
    df: float
    h: np.ndarray
    i: np.ndarray
    w: np.ndarray

    @classmethod
    def zeros(cls, n_features: int, weights: np.ndarray | None = None) -> AdaptiveLawState:
        """The start: filters and sums at 0 (the paper's H(0) = 0, I(0) = 0), W = ``weights`` or 0
        (e.g. a ridge fit as the warm start)."""
        w = np.zeros(n_features) if weights is None else np.array(weights, dtype=np.float64)
        if w.shape != (n_features,) or not np.isfinite(w).all():
            raise ValueError(f"weights must be {n_features} finite numbers, got shape {w.shape}")
        return cls(np.zeros(n_features), 0.0, np.zeros((n_features, n_features)), np.zeros(n_features), w)

    @property
    def n_features(self) -> int:
        return len(self.w)

    def copy(self) -> AdaptiveLawState:
        return AdaptiveLawState(self.xf.copy(), self.df, self.h.copy(), self.i.copy(), self.w.copy())

    def to_dict(self) -> dict[str, Any]:
        """Plain (nested) lists of floats: safe for ``yaml.safe_dump``, exact."""
        return {
            "xf": self.xf.tolist(),
            "df": float(self.df),
            "h": self.h.tolist(),
            "i": self.i.tolist(),
            "w": self.w.tolist(),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> AdaptiveLawState:
        """Inverse of ``to_dict``; ``ValueError`` for missing or unknown keys, wrong shapes or bad values."""
        keys = {"xf", "df", "h", "i", "w"}
        if not isinstance(d, dict) or set(d) != keys:
            got = sorted(d) if isinstance(d, dict) else type(d).__name__
            raise ValueError(f"adaptive law state needs exactly the keys {sorted(keys)}, got {got}")
        try:
            a = {k: np.array(d[k], dtype=np.float64) for k in ("xf", "h", "i", "w")}
            df = float(d["df"])
        except (TypeError, ValueError) as exc:
            raise ValueError(f"adaptive law state: not numbers: {exc}") from None
        n = len(a["w"]) if a["w"].ndim == 1 else 0
        shapes = {"xf": (n,), "h": (n, n), "i": (n,), "w": (n,)}
        if n < 1 or any(a[k].shape != s for k, s in shapes.items()):
            raise ValueError(f"adaptive law state: inconsistent shapes { {k: v.shape for k, v in a.items()} }")
        if not all(np.isfinite(v).all() for v in a.values()) or not math.isfinite(df):
            raise ValueError("adaptive law state: values must be finite")
        return cls(a["xf"], df, a["h"], a["i"], a["w"])


class AdaptiveLaw:
    """The adaptive readout over a stream, predicting apart from learning: ``predict(x)`` is ``y_hat = W^T x``
    (the state untouched), ``learn(x, d)`` advances the sums and moves W, ``track(x, d)`` advances the sums
    with W held; ``run`` does the three over many rows, same state.
    """

    def __init__(
        self,
        params: AdaptiveLawParams | None,
        n_features: int,
        sample_time_s: float = 1.0,
        state: AdaptiveLawState | None = None,
    ) -> None:
        self.params = p = params if params is not None else AdaptiveLawParams()
        if isinstance(n_features, bool) or not isinstance(n_features, (int, np.integer)) or n_features < 1:
            raise ValueError(f"n_features must be an integer >= 1, got {n_features!r}")
        if not _is_real(sample_time_s) or not sample_time_s > 0:
            raise ValueError(f"sample_time_s must be finite and > 0, got {sample_time_s!r}")
        self.n_features = int(n_features)
        self.sample_time_s = ts = float(sample_time_s)
        lam = 1.0 / p.memory_time_s
        # Correctly rounded: the same coefficients on every machine (the C library's exp is not).
        self._alpha = numerics.exp_correctly_rounded(-ts / p.filter_time_s) if p.filter_time_s > 0 else 0.0
        self._one_minus_alpha = -numerics.expm1_correctly_rounded(-ts / p.filter_time_s) if p.filter_time_s > 0 else 1.0
        self._beta = numerics.exp_correctly_rounded(-lam * ts)
        self._g = -numerics.expm1_correctly_rounded(-lam * ts) / lam
        self._sigma = float(p.sigma)
        self._fixed = None if p.fixed_gain is None else ts * float(p.fixed_gain)
        self._kappa = float(p.kappa)
        self._norm_offset = float(p.delta) + self.n_features * self._sigma
        self._precondition = bool(p.precondition)
        self.set_state(state if state is not None else AdaptiveLawState.zeros(self.n_features))

    # --- state -----------------------------------------------------------------------------------

    def get_state(self) -> AdaptiveLawState:
        """A copy of the current state."""
        return AdaptiveLawState(self._xf.copy(), self._df, self._h.copy(), self._i.copy(), self._w.copy())

    def set_state(self, state: AdaptiveLawState) -> None:
        if state.n_features != self.n_features:
            raise ValueError(f"state has {state.n_features} features, the law has {self.n_features}")
        s = state.copy()
        self._xf, self._df, self._h, self._i, self._w = s.xf, float(s.df), s.h, s.i, s.w

    @property
    def weights(self) -> np.ndarray:
        """A copy of W, shape (n_features,)."""
        return self._w.copy()

    @property
    def weights_view(self) -> np.ndarray:
        """W itself, shape (n_features,), not a copy: to read without copying (``learn`` changes it in place)."""
        return self._w

    @property
    def gain(self) -> float:
        """Gamma as the next update would use it (from the current H)."""
        if self._fixed is not None:
            return self._fixed
        return self._kappa / (self._norm_offset + numerics.total(self._h.diagonal()))

    def least_squares_weights(self) -> np.ndarray:
        """``(H + sigma I)^-1 I``, where the law is heading (lstsq: minimum norm when H is singular)."""
        h = self._h + self._sigma * np.eye(self.n_features)
        return np.linalg.lstsq(h, self._i, rcond=None)[0]

    def predict(self, x: np.ndarray) -> float:
        """``W^T x``; the state is not touched."""
        return float(numerics.dot(np.asarray(x, dtype=np.float64), self._w))

    # --- predicting and learning ----------------------------------------------------------------

    def _row(self, x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, dtype=np.float64)
        if x.shape != (self.n_features,):
            raise ValueError(f"x must have shape ({self.n_features},), got {x.shape}")
        return x

    def _accumulate(self, x: np.ndarray, d: float) -> bool:
        """Xf, Df, H and I advance by (x, d); False (nothing changed) when x or d is not finite."""
        if not (math.isfinite(d) and math.isfinite(x.sum())):
            return False
        xf = self._xf
        xf *= self._alpha
        xf += self._one_minus_alpha * x
        self._df = df = self._alpha * self._df + self._one_minus_alpha * d
        o = np.outer(xf, xf)
        o *= self._g
        h = self._h
        h *= self._beta
        h += o
        i = self._i
        i *= self._beta
        i += (self._g * df) * xf
        return True

    def _move_weights(self) -> None:
        """W moves by ``-Gamma (M + sigma W)`` with ``M = H W - I`` from the current sums."""
        w, h = self._w, self._h
        m = numerics.matvec(h, w)
        m -= self._i
        if self._sigma:
            m += self._sigma * w
        if self._precondition:  # per direction: kappa / (n (H_ii + delta + sigma)), the standardized law
            m *= self._kappa / (self.n_features * (h.diagonal() + (self._norm_offset / self.n_features)))
        elif self._fixed is not None:
            m *= self._fixed
        else:
            m *= self._kappa / (self._norm_offset + numerics.total(h.diagonal()))
        w -= m

    def learn(self, x: np.ndarray, d: float) -> None:
        """One sample learned: Xf, Df, H and I advance by (x, d), then W moves (predict first for the a-priori
        estimate).  A non-finite x or d changes nothing."""
        if self._accumulate(self._row(x), float(d)):
            self._move_weights()

    def track(self, x: np.ndarray, d: float) -> None:
        """One sample followed with W held: Xf, Df, H and I advance by (x, d) as in ``learn``, W does not move
        (freezing and unfreezing is seamless).  A non-finite x or d changes nothing."""
        self._accumulate(self._row(x), float(d))

    def run(self, x: np.ndarray, d: np.ndarray, learn: np.ndarray | bool = True) -> np.ndarray:
        """Per row of ``x`` (T, n_features), in order: ``predict``, then ``learn`` where ``learn`` (a bool or a
        (T,) mask) is true, else ``track``, with the targets ``d`` (T,).  Returns the predictions (T,)."""
        x = np.asarray(x, dtype=np.float64)
        d = np.asarray(d, dtype=np.float64)
        if x.ndim != 2 or x.shape[1] != self.n_features or d.shape != (len(x),):
            raise ValueError(f"need x (T, {self.n_features}) and d (T,), got {x.shape} and {d.shape}")
        mask = np.broadcast_to(np.asarray(learn, dtype=bool), (len(x),)).tolist()
        dl = d.tolist()
        out = np.empty(len(x))
        for k in range(len(x)):
            out[k] = float(numerics.dot(x[k], self._w))
            if self._accumulate(x[k], dl[k]) and mask[k]:
                self._move_weights()
        return out


def ridge_fit(
    x: np.ndarray,
    y: np.ndarray,
    alpha: float,
    *,
    fit_intercept: bool = True,
    sample_weight: np.ndarray | None = None,
) -> tuple[np.ndarray, float]:
    """Minimize ``sum_i sw_i (y_i - b - x_i . w)^2 + alpha |w|^2`` over w and b (b NOT penalized).

    Rows with any non-finite value in x, y or the weight, or with weight 0, are dropped first.
    With ``fit_intercept`` X and y are centred with the weighted means and ``b = ymean - xmean . w``;
    without it b = 0.  ``alpha = 0`` is ordinary least squares (the minimum-norm solution when X is
    rank-deficient).  Returns ``(w, b)``: w of shape (n_features,), b a float.
    """
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    if x.ndim != 2 or y.shape != (len(x),):
        raise ValueError(f"need x (T, n) and y (T,), got {x.shape} and {y.shape}")
    if not _is_real(alpha) or alpha < 0:
        raise ValueError(f"alpha must be finite and >= 0, got {alpha!r}")
    sw = np.ones(len(x)) if sample_weight is None else np.asarray(sample_weight, dtype=np.float64)
    if sw.shape != (len(x),):
        raise ValueError(f"sample_weight must have shape ({len(x)},), got {sw.shape}")
    if (sw < 0).any():
        raise ValueError("sample_weight must be >= 0")
    keep = np.isfinite(x).all(axis=1) & np.isfinite(y) & np.isfinite(sw) & (sw > 0)
    if not keep.any():
        raise ValueError("ridge_fit: no row with finite values and a positive weight")
    x, y, sw = x[keep], y[keep], sw[keep]
    n = x.shape[1]
    if fit_intercept:
        total = sw.sum()
        xmean = (sw @ x) / total
        ymean = float(sw @ y) / total
        x = x - xmean
        y = y - ymean
    root = np.sqrt(sw)
    a = np.vstack([x * root[:, None], math.sqrt(alpha) * np.eye(n)])
    rhs = np.concatenate([y * root, np.zeros(n)])
    w = np.linalg.lstsq(a, rhs, rcond=None)[0]
    b = float(ymean - xmean @ w) if fit_intercept else 0.0
    return w, b


@dataclass(frozen=True, eq=False)
class Standardizer:
    """Per-column ``(x - mean) / scale``, fitted once on training data and stored unchanged."""

    mean: np.ndarray
    scale: np.ndarray

    def __post_init__(self) -> None:
        mean = np.array(self.mean, dtype=np.float64)
        scale = np.array(self.scale, dtype=np.float64)
        if mean.ndim != 1 or scale.shape != mean.shape or len(mean) < 1:
            raise ValueError(f"mean and scale must be equal-length vectors, got {mean.shape} and {scale.shape}")
        if not (np.isfinite(mean).all() and np.isfinite(scale).all() and (scale > 0).all()):
            raise ValueError("mean must be finite and scale finite and > 0")
        mean.flags.writeable = scale.flags.writeable = False
        object.__setattr__(self, "mean", mean)
        object.__setattr__(self, "scale", scale)

    @classmethod
    def fit(cls, x: np.ndarray) -> Standardizer:
        """Column means and standard deviations (ddof 0) over the finite values; a constant column gets
        scale 1 (it is only centred)."""
        x = np.asarray(x, dtype=np.float64)
        if x.ndim != 2:
            raise ValueError(f"need x (T, n), got {x.shape}")
        x = np.where(np.isfinite(x), x, np.nan)
        if np.isnan(x).all(axis=0).any():
            raise ValueError("Standardizer.fit: a column has no finite value")
        mean = np.nanmean(x, axis=0)
        std = np.nanstd(x, axis=0)
        return cls(mean, np.where(std > 0, std, 1.0))

    def transform(self, x: np.ndarray) -> np.ndarray:
        """``(x - mean) / scale``, for one row (n,) or many (T, n)."""
        return (np.asarray(x, dtype=np.float64) - self.mean) / self.scale

    def inverse_transform(self, z: np.ndarray) -> np.ndarray:
        return np.asarray(z, dtype=np.float64) * self.scale + self.mean

    def to_dict(self) -> dict[str, Any]:
        return {"mean": self.mean.tolist(), "scale": self.scale.tolist()}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Standardizer:
        if not isinstance(d, dict) or set(d) != {"mean", "scale"}:
            raise ValueError("a standardizer needs exactly the keys ['mean', 'scale']")
        try:
            return cls(np.array(d["mean"], dtype=np.float64), np.array(d["scale"], dtype=np.float64))
        except (TypeError, ValueError) as exc:
            raise ValueError(f"standardizer: {exc}") from None
