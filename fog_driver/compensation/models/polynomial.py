"""The practitioner's baseline: polynomial regression of the drift on the same inputs.

On the standardized inputs z = [T1 T2 T3 dT1 dT2 dT3 G12 G13] (``readout.Standardizer``),
in a well-conditioned physical basis::

    R = (T1 + T2) / 2      ring mean (the fiber sits in the ring: T_fiber ~ R - tau dR/dt)
    dR = (dT1 + dT2) / 2   ring rate (the Shupe term)
    G = G12                ring top - bottom gradient
    H = T3 - R             housing offset from the ring;   dT3: housing rate
    f = [R, R^2, R^3, dR, R dR, R^2 dR, G, H, dT3]                                  (9)
    D_hat = w . f + b

a cubic in the ring temperature with the cross terms a lagged fiber
temperature produces, linear in the gradients and rates: what a calibration
engineer fits today.  (A cubic in each of T1, T2, T3 fits the same physics
but its regressors are nearly collinear: two fits to runs differing only in
white noise then disagree by 2x on another profile.)  No memory, so ``step``
and ``run`` agree trivially; fitted by ridge regression with an unpenalized
intercept (``readout.ridge_fit``).
"""

from __future__ import annotations

import numpy as np

from .. import numerics
from ..features import channels_of
from ..readout import ridge_fit


def _basis(z: np.ndarray) -> tuple[np.ndarray, np.ndarray, list[np.ndarray], list[np.ndarray]]:
    """R, dR, the levels after R ([G, H] for three channels) and the rates after dR ([dT3]), as columns.

    Three channels (8 inputs): as the module docstring.  Two (5 inputs ``[T1 T2 dT1 dT2 G12]``): R, dR, G.
    One (2 inputs ``[T dT]``, a KVH's one sensor): R = T, dR = dT, nothing else."""
    z = np.asarray(z, dtype=np.float64)
    n = channels_of(z.shape[-1])
    if n == 1:
        return z[..., 0:1], z[..., 1:2], [], []
    r = 0.5 * (z[..., 0:1] + z[..., 1:2])
    dr = 0.5 * (z[..., n : n + 1] + z[..., n + 1 : n + 2])
    if n == 2:
        return r, dr, [z[..., 4:5]], []
    return r, dr, [z[..., 6:7], z[..., 2:3] - r], [z[..., 5:6]]


def n_poly_features(n_inputs: int = 8) -> int:
    """Regressors ``polynomial_features`` makes of ``n_inputs`` inputs: 9 (three channels), 7 (two), 6 (one)."""
    return {3: 9, 2: 7, 1: 6}[channels_of(n_inputs)]


N_POLY_FEATURES = n_poly_features()


def polynomial_features(z: np.ndarray) -> np.ndarray:
    """(n, 8) standardized inputs -> (n, 9) regressors; a single (8,) row gives (9,) (fewer channels: fewer,
    ``_basis``)."""
    r, dr, levels, rates = _basis(z)
    return np.concatenate((r, r * r, r * r * r, dr, r * dr, r * r * dr, *levels, *rates), axis=-1)


N_LEVEL_FEATURES = 3


def level_features(z: np.ndarray) -> np.ndarray:
    """The levels of the same basis, ``[R, G, H]``: no rates (the ring form's linear path; its coil
    neuron supplies the coil's own rate, ``(R - x) / tau``, and rates of the ring would only let a
    fit fake a wrong coil lag on slow ramps)."""
    r, _, levels, _ = _basis(z)
    return np.concatenate((r, *levels), axis=-1)


N_PHYSICAL_FEATURES = 5


def physical_features(z: np.ndarray) -> np.ndarray:
    """The linear part of the same basis, ``[R, G, H, dR, dT3]`` (the WESN's linear path: its
    neurons supply the fiber temperature's nonlinearity and the thermal history)."""
    r, dr, levels, rates = _basis(z)
    return np.concatenate((r, *levels, dr, *rates), axis=-1)


class Memoryless:
    """For drift models without memory: ``step`` and ``run`` are pure functions of the inputs, so
    there is no feedback to take and no state to save, restore or reset."""

    def feed_back(self, y: float) -> None:
        """The estimate actually used (no feedback in this model)."""

    def get_state(self) -> dict:
        return {}

    def set_state(self, state: dict) -> None:
        pass

    def reset(self) -> None:
        pass


class PolynomialModel(Memoryless):
    """``D_hat = w . polynomial_features(z) + b``; stateless."""

    kind = "polynomial"

    def __init__(self, weights: np.ndarray, intercept: float) -> None:
        self.weights = np.asarray(weights, dtype=np.float64)
        self.intercept = float(intercept)
        if self.weights.shape not in ((9,), (7,), (6,)):
            raise ValueError(
                f"a polynomial model has 9 weights (three channels), 7 (two) or 6 (one), got {self.weights.shape}"
            )

    @classmethod
    def fit(
        cls, z: np.ndarray, target: np.ndarray, alpha: float | None = None, groups: np.ndarray | None = None
    ) -> PolynomialModel:
        """Ridge on standardized regressors (one intercept per capture, ``groups``); ``alpha`` None: chosen by
        blocked cross-validation."""
        f = polynomial_features(z)
        if alpha is None:
            alpha, _ = cross_validated_alpha(f, target, groups=groups)
        w, b = standardized_ridge(f, target, alpha, groups=groups)
        return cls(w, b)

    def start(self, z: np.ndarray) -> None:
        """No memory: nothing to settle."""

    def regressors_step(self, z: np.ndarray) -> np.ndarray:
        """The regressor row f for one block (the estimate is ``f . weights + intercept``)."""
        return polynomial_features(z)

    def step(self, z: np.ndarray) -> float:
        return float(numerics.dot(polynomial_features(z), self.weights) + self.intercept)

    def run(self, z: np.ndarray) -> np.ndarray:
        return numerics.dot(polynomial_features(z), self.weights) + self.intercept

    def to_dict(self) -> dict:
        return {"weights": [float(v) for v in self.weights], "intercept": self.intercept}

    @classmethod
    def from_dict(cls, d: dict) -> PolynomialModel:
        return cls(np.array(d["weights"], dtype=np.float64), float(d["intercept"]))


#: Ridge penalties tried by cross-validation, relative to the number of rows (standardized columns).
ALPHA_GRID = (1e-6, 3e-6, 1e-5, 3e-5, 1e-4, 3e-4, 1e-3, 3e-3, 1e-2)


def standardized_ridge(
    x: np.ndarray, y: np.ndarray, alpha: float, penalty: np.ndarray | None = None, groups: np.ndarray | None = None
) -> tuple[np.ndarray, float]:
    """Ridge on standardized columns (penalty ``alpha * rows``), weights folded back to raw columns.

    ``penalty``: a multiplier per column (default 1): column j's standardized weight is penalized by
    ``alpha * rows * penalty[j]`` (solved by scaling the column by ``1 / sqrt(penalty[j])``).
    ``groups``: the capture each row comes from (0..K-1).  Each capture gets its own intercept (its
    target was centred on its own mean, which holds its own turn-on bias and its own mean drift), fitted
    as nearly unpenalized indicator columns and then dropped; the intercept returned is capture 0's.
    """
    if groups is not None and np.ptp(groups) > 0:
        labels = np.unique(groups)
        indicators = (np.asarray(groups)[:, None] == labels[None, 1:]).astype(np.float64)
        penalty = np.r_[np.ones(x.shape[1]) if penalty is None else penalty, np.full(len(labels) - 1, 1e-8)]
        w, b = standardized_ridge(np.column_stack([x, indicators]), y, alpha, penalty)
        return w[: x.shape[1]], b
    mean = x.mean(axis=0)
    scale = x.std(axis=0)
    scale = np.where(scale > 1e-12, scale, 1.0)
    if penalty is not None:
        scale = scale * np.sqrt(np.asarray(penalty, dtype=np.float64))
    w_std, b_std = ridge_fit((x - mean) / scale, y, alpha * len(y))
    return w_std / scale, float(b_std - (mean / scale) @ w_std)


def cross_validated_alpha(
    x: np.ndarray,
    y: np.ndarray,
    folds: int = 5,
    average_rows: int = 60,
    grid: tuple[float, ...] = ALPHA_GRID,
    penalty: np.ndarray | None = None,
    groups: np.ndarray | None = None,
) -> tuple[float, dict[float, float]]:
    """The penalty with the smallest blocked cross-validation error.

    Rows are in time order; each fold is a contiguous stretch (another part of the thermal run,
    so the score rewards extrapolation, not interpolation).  The error is the RMS of the held-out
    residual averaged over ``average_rows`` rows (1 minute at 1 Hz), its mean removed per fold:
    averaging lets the slow model error show through the white sensor noise.
    """
    edges = np.linspace(0, len(y), folds + 1).astype(int)
    scores: dict[float, float] = {}
    for alpha in grid:
        total = 0.0
        count = 0
        for lo, hi in zip(edges[:-1], edges[1:]):
            train = np.r_[0:lo, hi : len(y)]
            w, b = standardized_ridge(x[train], y[train], alpha, penalty, None if groups is None else groups[train])
            residual = y[lo:hi] - (x[lo:hi] @ w + b)  # a capture's own offset: removed with the fold's mean below
            m = len(residual) // average_rows * average_rows
            if m == 0:
                continue
            means = residual[:m].reshape(-1, average_rows).mean(axis=1)
            total += float(np.sum((means - means.mean()) ** 2))
            count += len(means)
        scores[alpha] = float(np.sqrt(total / count)) if count else float("inf")
    return min(scores, key=scores.get), scores
