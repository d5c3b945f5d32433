"""The practitioner's baseline: polynomial regression of the drift on the same inputs.

On the normalized inputs z (``features.Normalizer``), the regressors are::

    f = [z_1 .. z_8,  z_T1^2, z_T2^2, z_T3^2,  z_T1^3, z_T2^3, z_T3^3]      (14)
    D_hat = w . f + b

that is, a cubic in each temperature, linear in the rates and gradients: what
a calibration engineer fits today.  It has no memory, so ``step`` and ``run``
agree trivially; it is fitted by ridge regression with an unpenalized
intercept.
"""

from __future__ import annotations

import numpy as np

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


def ridge(x: np.ndarray, y: np.ndarray, alpha: float) -> tuple[np.ndarray, float]:
    """Ridge regression with the intercept never penalized: centre, solve, then ``b = ybar - xbar . w``.

    Solved as least squares on ``[Xc; sqrt(alpha) I] w = [yc; 0]`` (no normal equations).
    """
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    x_mean = x.mean(axis=0)
    y_mean = float(y.mean())
    xc = x - x_mean
    yc = y - y_mean
    n_features = x.shape[1]
    a = np.vstack((xc, np.sqrt(alpha) * np.eye(n_features)))
    rhs = np.concatenate((yc, np.zeros(n_features)))
    w, *_ = np.linalg.lstsq(a, rhs, rcond=None)
    return w, y_mean - float(x_mean @ w)


class PolynomialModel:
    """``D_hat = w . polynomial_features(z) + b``; stateless."""

    kind = "polynomial"

    def __init__(self, weights: np.ndarray, intercept: float) -> None:
        self.weights = np.asarray(weights, dtype=np.float64)
        self.intercept = float(intercept)
        if self.weights.shape != (N_POLY_FEATURES,):
            raise ValueError(f"a polynomial model has {N_POLY_FEATURES} weights, got {self.weights.shape}")

    @classmethod
    def fit(cls, z: np.ndarray, target: np.ndarray, alpha: float = 1e-3) -> PolynomialModel:
        w, b = ridge(polynomial_features(z), target, alpha * len(target))
        return cls(w, b)

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
