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
white noise then disagree on another profile; docs/decisions/2026-12-07-polynomial-ring-cubic.md.)
No memory, so ``step``
and ``run`` agree trivially; fitted by ridge regression with an unpenalized
intercept (``fitting.ridge.standardized_ridge``).
"""

from __future__ import annotations

import numpy as np

from .. import numerics
from ..features import channels_of
from ..fitting.ridge import cross_validated_alpha, standardized_ridge


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

    def coil_lag(self) -> tuple[float, int] | None:
        """No coil: a model without memory has no lag to find."""
        return None


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
