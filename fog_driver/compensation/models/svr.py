"""The paper's comparator: support-vector regression with PSO-chosen hyperparameters (``pso-svr``).

The paper compares its WESN with a "PSO-SVM": a support-vector regression of the drift on the same
standardized inputs z = [T1 T2 T3 dT1 dT2 dT3 G12 G13] (``readout.Standardizer``), RBF kernel,
its hyperparameters found by particle swarm optimization::

    D_hat(z) = sum_i a_i exp(-gamma |z - sv_i|^2) + b

Fitting (``fitting.svr.fit_pso_svr``) needs scikit-learn's ``SVR`` (an optional extra, imported inside the fit);
prediction is plain numpy over the stored support vectors, so a model file compensates anywhere.

* Rows: 1-minute averages of the standardized inputs and of the target over whole static minutes
  of each capture (minutes aligned with the capture's first block, as ``fit.minute_rms``): a few
  hundred rows for the paper's 440-minute run.  An SVR on every 1-s block would be slow, and its
  support vectors (most rows, with a small epsilon) would bloat the model file.  A capture too short
  for 30 such rows (a test fixture) is averaged over shorter windows (``window_blocks``).
* Hyperparameters: C in [1e-2, 1e3], gamma in [1e-3, 1e1], epsilon in [1e-4, 1e-1] deg/h, searched
  in log10 space by ``pso_minimize`` (seeded: deterministic), minimizing the blocked cross-validation
  error: 3 contiguous folds of the minute rows (another part of the thermal run, so the score rewards
  extrapolation), the RMS of the held-out residual, each fold's mean removed (a bias is not drift).
  The final SVR is fitted on all rows with the best point.  Several captures: each target was centred
  on its own capture's mean, so each capture gets its own offset (y_k = f(z) + a_k, a_0 = 0), found by
  backfitting ``OFFSET_PASSES`` times at the chosen point (f refitted on y - a, a_k the mean of capture
  k's residual): an RBF kernel has no column to give an intercept per capture.  Search fits are capped at 30,000 libsvm
  iterations (large C with large gamma can take millions; such a fit is scored as it stands) and the
  swarm is evaluated on 2 threads (libsvm releases the GIL; the result does not depend on it): about
  14 s for the paper's 440-minute capture on 2 cores.
* No memory: ``step`` and ``run`` agree trivially; ``run`` is bit-identical to repeated ``step``
  (the same per-row arithmetic: squared distances summed over the 8 inputs in order, the kernel
  row weighted and summed strictly left to right, as ``numerics.dot``).
* Adapting: an SVR is linear in its dual coefficients, so the model exposes the kernel row
  ``k_i(z) = exp(-gamma |z - sv_i|^2)`` as its regressors (``regressors_step``), ``weights`` =
  the dual coefficients and ``intercept`` = b: the compensator's online readout
  (``adapt.OnlineReadout``, which the daemon always builds) then works unchanged, and while it does
  not update its estimate is this model's ``step`` bit for bit.  Adapting moves the dual
  coefficients over the fixed support vectors; the law's state is (n_sv + 1)^2 numbers, so an
  adaptation state file for a model with hundreds of support vectors is megabytes.
"""

from __future__ import annotations

import math

import numpy as np

from .. import numerics
from .polynomial import Memoryless

_CHUNK_FLOATS = 1 << 20  #: ``run`` works in chunks of rows whose differences (rows x n_sv x 8) fit in 8 MB

# -- the model ---------------------------------------------------------------------------------------


class SvrModel(Memoryless):
    """``D_hat = sum_i a_i exp(-gamma |z - sv_i|^2) + b`` over stored support vectors; stateless."""

    kind = "pso-svr"

    def __init__(
        self,
        support_vectors: np.ndarray,
        dual_coef: np.ndarray,
        intercept: float,
        gamma: float,
        C: float | None = None,
        epsilon: float | None = None,
        cv_rms_dph: float | None = None,
        average_s: float | None = None,
    ) -> None:
        self.support_vectors = np.ascontiguousarray(support_vectors, dtype=np.float64)
        self.dual_coef = np.ascontiguousarray(dual_coef, dtype=np.float64)
        self.intercept = float(intercept)
        self.gamma = float(gamma)
        self.C = None if C is None else float(C)
        self.epsilon = None if epsilon is None else float(epsilon)
        self.cv_rms_dph = None if cv_rms_dph is None else float(cv_rms_dph)
        self.average_s = None if average_s is None else float(average_s)
        sv = self.support_vectors
        if sv.ndim != 2 or sv.shape[1] not in (8, 5, 2) or sv.shape[0] < 1:
            raise ValueError(
                f"a pso-svr model needs support vectors of shape (n >= 1, 8, 5 or 2 inputs), got {sv.shape}"
            )
        self.n_inputs = sv.shape[1]
        if self.dual_coef.shape != (sv.shape[0],):
            raise ValueError(f"a pso-svr model needs {sv.shape[0]} dual coefficients, got {self.dual_coef.shape}")
        if not (np.all(np.isfinite(sv)) and np.all(np.isfinite(self.dual_coef)) and math.isfinite(self.intercept)):
            raise ValueError("a pso-svr model's support vectors, dual coefficients and intercept must be finite")
        if not (math.isfinite(self.gamma) and self.gamma > 0):
            raise ValueError(f"a pso-svr model's gamma must be finite and > 0, got {self.gamma!r}")
        self._neg_gamma = -self.gamma
        self._sv_by_input = np.ascontiguousarray(sv.T)  # (8, n_sv)
        self._chunk_rows = max(1, _CHUNK_FLOATS // (self.n_inputs * len(sv)))

    @property
    def weights(self) -> np.ndarray:
        """The readout's weights on ``regressors_step``'s kernel row: the dual coefficients."""
        return self.dual_coef

    @property
    def n_support(self) -> int:
        return len(self.dual_coef)

    # -- arithmetic shared by step and run ---------------------------------------------------------

    def kernel_rows(self, z: np.ndarray) -> np.ndarray:
        """(m, 8) standardized inputs -> (m, n_sv) kernel rows ``exp(-gamma |z - sv_i|^2)``.

        The squared distance is summed over the 8 inputs in order, elementwise, and the exponential is
        ``numerics.exp``: the same operations for one row as for many, the same bits on every CPU."""
        d = np.asarray(z, dtype=np.float64).T[:, :, None] - self._sv_by_input[:, None, :]  # (8, m, n_sv)
        d *= d
        acc = numerics.sum_first(d)
        acc *= self._neg_gamma
        return numerics.exp(acc)

    def _predict(self, z: np.ndarray) -> np.ndarray:
        """(m, 8) -> (m,): the kernel rows weighted by the dual coefficients, summed strictly left to
        right (``numerics.dot``), plus b."""
        return numerics.dot(self.kernel_rows(z), self.dual_coef) + self.intercept

    # -- the DriftModel interface --------------------------------------------------------------------

    def start(self, z: np.ndarray) -> None:
        """No memory: nothing to settle."""

    def regressors_step(self, z: np.ndarray) -> np.ndarray:
        """The regressor row for one block: the kernel row (n_sv,); the estimate is ``k . weights + intercept``."""
        return self.kernel_rows(np.asarray(z, dtype=np.float64).reshape(1, self.n_inputs))[0]

    def step(self, z: np.ndarray) -> float:
        return float(self._predict(np.asarray(z, dtype=np.float64).reshape(1, self.n_inputs))[0])

    def run(self, z: np.ndarray) -> np.ndarray:
        z = np.asarray(z, dtype=np.float64).reshape(-1, self.n_inputs)
        out = np.empty(len(z))
        for lo in range(0, len(z), self._chunk_rows):
            out[lo : lo + self._chunk_rows] = self._predict(z[lo : lo + self._chunk_rows])
        return out

    # -- model file ----------------------------------------------------------------------------------

    def to_dict(self) -> dict:
        return {
            "gamma": self.gamma,
            "intercept": self.intercept,
            "C": self.C,
            "epsilon": self.epsilon,
            "cv_rms_dph": self.cv_rms_dph,
            "average_s": self.average_s,
            "dual_coef": [float(v) for v in self.dual_coef],
            "support_vectors": [[float(v) for v in row] for row in self.support_vectors],
        }

    @classmethod
    def from_dict(cls, d: dict) -> SvrModel:
        def optional(key: str) -> float | None:
            v = d.get(key)
            return None if v is None else float(v)

        sv = d["support_vectors"]
        if not isinstance(sv, list) or not all(isinstance(row, list) for row in sv):
            raise ValueError("pso-svr: support_vectors must be a list of rows")
        return cls(
            np.array(sv, dtype=np.float64),
            np.array(d["dual_coef"], dtype=np.float64),
            float(d["intercept"]),
            float(d["gamma"]),
            optional("C"),
            optional("epsilon"),
            optional("cv_rms_dph"),
            optional("average_s"),
        )

    @classmethod
    def from_sklearn(
        cls,
        svr,
        C: float | None = None,
        epsilon: float | None = None,
        cv_rms_dph: float | None = None,
        average_s: float | None = None,
    ) -> SvrModel:
        """From a fitted ``sklearn.svm.SVR`` with an RBF kernel and a numeric gamma."""
        if svr.kernel != "rbf":
            raise ValueError(f"only an RBF kernel is supported, got {svr.kernel!r}")
        return cls(
            svr.support_vectors_,
            svr.dual_coef_[0],
            float(svr.intercept_[0]),
            float(svr._gamma),
            C,
            epsilon,
            cv_rms_dph,
            average_s,
        )
