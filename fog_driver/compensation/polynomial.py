"""The practitioner's baseline: polynomial regression of the drift on the same inputs.

On the standardized inputs z (``readout.Standardizer``), the regressors are::

    f = [z_1 .. z_8,  z_T1^2, z_T2^2, z_T3^2,  z_T1^3, z_T2^3, z_T3^3]      (14)
    D_hat = w . f + b

that is, a cubic in each temperature, linear in the rates and gradients: what
a calibration engineer fits today.  It has no memory, so ``step`` and ``run``
agree trivially; it is fitted by ridge regression with an unpenalized
intercept (``readout.ridge_fit``).
"""

from __future__ import annotations

import numpy as np

from .readout import ridge_fit

N_POLY_FEATURES = 14


def polynomial_features(z: np.ndarray) -> np.ndarray:
    """(n, 8) normalized inputs -> (n, 14) regressors; a single (8,) row gives (14,)."""
    z = np.asarray(z, dtype=np.float64)
    temps = z[..., :3]
    return np.concatenate((z, temps**2, temps**3), axis=-1)


def dot_features(f: np.ndarray, w: np.ndarray) -> np.ndarray:
    """``f . w`` for one row or many, summed strictly left to right over the features.

    Not BLAS: a matrix-vector product may sum in another order than a single
    dot product, and ``step`` (one row) must equal ``run`` (many) bit for bit.
    """
    f = np.asarray(f, dtype=np.float64)
    acc = f[..., 0] * w[0]
    for j in range(1, len(w)):
        acc = acc + f[..., j] * w[j]
    return acc


class PolynomialModel:
    """``D_hat = w . polynomial_features(z) + b``; stateless."""

    kind = "polynomial"

    def __init__(self, weights: np.ndarray, intercept: float) -> None:
        self.weights = np.asarray(weights, dtype=np.float64)
        self.intercept = float(intercept)
        if self.weights.shape != (N_POLY_FEATURES,):
            raise ValueError(f"a polynomial model has {N_POLY_FEATURES} weights, got {self.weights.shape}")

    @classmethod
    def fit(cls, z: np.ndarray, target: np.ndarray, alpha: float | None = None) -> PolynomialModel:
        """Ridge on standardized regressors; ``alpha`` None: chosen by blocked cross-validation."""
        f = polynomial_features(z)
        if alpha is None:
            alpha, _ = cross_validated_alpha(f, target)
        w, b = standardized_ridge(f, target, alpha)
        return cls(w, b)

    def start(self, z: np.ndarray) -> None:
        """No memory: nothing to settle."""

    def step(self, z: np.ndarray) -> float:
        return float(dot_features(polynomial_features(z), self.weights) + self.intercept)

    def run(self, z: np.ndarray) -> np.ndarray:
        return dot_features(polynomial_features(z), self.weights) + self.intercept

    # No memory: nothing to save or restore.
    def get_state(self) -> dict:
        return {}

    def set_state(self, state: dict) -> None:
        pass

    def reset(self) -> None:
        pass

    def to_dict(self) -> dict:
        return {"weights": [float(v) for v in self.weights], "intercept": self.intercept}

    @classmethod
    def from_dict(cls, d: dict) -> PolynomialModel:
        return cls(np.array(d["weights"], dtype=np.float64), float(d["intercept"]))


#: Ridge penalties tried by cross-validation, relative to the number of rows (standardized columns).
ALPHA_GRID = (1e-6, 3e-6, 1e-5, 3e-5, 1e-4, 3e-4, 1e-3, 3e-3, 1e-2)


def standardized_ridge(x: np.ndarray, y: np.ndarray, alpha: float) -> tuple[np.ndarray, float]:
    """Ridge on standardized columns (penalty ``alpha * rows``), weights folded back to raw columns."""
    mean = x.mean(axis=0)
    scale = x.std(axis=0)
    scale = np.where(scale > 1e-12, scale, 1.0)
    w_std, b_std = ridge_fit((x - mean) / scale, y, alpha * len(y))
    return w_std / scale, float(b_std - (mean / scale) @ w_std)


def cross_validated_alpha(x: np.ndarray, y: np.ndarray, folds: int = 5, average_rows: int = 60,
                          grid: tuple[float, ...] = ALPHA_GRID) -> tuple[float, dict[float, float]]:  # fmt: skip
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
            w, b = standardized_ridge(x[train], y[train], alpha)
            residual = y[lo:hi] - (x[lo:hi] @ w + b)
            m = len(residual) // average_rows * average_rows
            if m == 0:
                continue
            means = residual[:m].reshape(-1, average_rows).mean(axis=1)
            total += float(np.sum((means - means.mean()) ** 2))
            count += len(means)
        scores[alpha] = float(np.sqrt(total / count)) if count else float("inf")
    return min(scores, key=scores.get), scores
