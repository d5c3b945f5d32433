"""The table law's state: what it learned, as plain YAML-safe values (exact), and the checks a state passes.

Saved: the frozen weights and intercept it was learned against and its shape regressors' kind, the sums, the
estimate and its covariance, the regressors' gram and the evidence (``ARRAYS``), the noise, the innovation
calibration and the comparison (``FLOATS``), and the counters (``COUNTS``).  Not the run's own chain (the ring of
blocks, the bias, the anchor): a restored law starts a new run.  A state saved by an earlier version lacks the
keys of ``ADDED``, which start from their value there.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from .estimate import PRIOR_SCALES, SHAPE_REGRESSORS

__all__ = ["ARRAYS", "COUNTS", "FLOATS", "MIXTURE_KEYS", "checked_state", "state_of"]

ARRAYS = ("h", "i", "delta", "cov", "gram", "evidence")
FLOATS = (
    "gram_weight",
    "noise_var_dph2",
    "calibration_sum",
    "calibration_n",
    "compare_gain",
    "compare_gain_sq",
    "compare_level_frozen_dph",
    "compare_level_adapted_dph",
    "compare_dev_sq_adapted_dph2",
)
COUNTS = (
    "noise_dwells",
    "accepted",
    "rejected",
    "refused",
    "skipped",
    "guards",
    "clamped_blocks",
    "compare_windows",
)
#: the keys held by the law's estimate (``estimate.MixtureLaw``); the others by the table law itself
MIXTURE_KEYS = frozenset(
    ("h", "i", "delta", "cov", "gram", "evidence", "gram_weight", "noise_var_dph2", "calibration_sum")
    + ("calibration_n", "noise_dwells")
)
#: keys a state saved by an earlier version lacks, and what they start from
ADDED: dict[str, Callable[[], Any]] = {
    "evidence": lambda: [0.0] * len(PRIOR_SCALES),
    "clamped_blocks": lambda: 0,
    "shape": lambda: SHAPE_REGRESSORS,
}


def state_of(
    frozen_weights: np.ndarray, frozen_intercept: float, shape: str, value: Callable[[str], Any]
) -> dict[str, Any]:
    """The state (module docstring), each key's value from ``value(key)``."""
    d: dict[str, Any] = {
        "frozen_weights": [float(v) for v in frozen_weights],
        "frozen_intercept": frozen_intercept,
        "shape": shape,
    }
    d.update({k: np.asarray(value(k)).tolist() for k in ARRAYS})
    d.update({k: float(value(k)) for k in FLOATS})
    d.update({k: int(value(k)) for k in COUNTS})
    return d


def checked_state(
    d: dict[str, Any], frozen_weights: np.ndarray, frozen_intercept: float, shape: str, n_shape: int
) -> dict[str, Any]:
    """The values of state ``d`` to set (``ARRAYS``, ``FLOATS``, ``COUNTS``), for a law with these frozen
    weights, shape regressors and their count; ``ValueError`` for missing or unknown keys, bad values, or a
    state learned against other frozen weights (another model) or on other shape regressors."""
    keys = {"frozen_weights", "frozen_intercept", "shape", *ARRAYS, *FLOATS, *COUNTS}
    if isinstance(d, dict) and keys - set(d) <= set(ADDED) and set(d) <= keys:
        d = {**{k: make() for k, make in ADDED.items() if k not in d}, **d}  # saved by an earlier version
    if not isinstance(d, dict) or set(d) != keys:
        got = sorted(d) if isinstance(d, dict) else type(d).__name__
        raise ValueError(f"table law state needs exactly the keys {sorted(keys)}, got {got}")
    try:
        w0 = np.array(d["frozen_weights"], dtype=np.float64)
        arrays = {k: np.array(d[k], dtype=np.float64) for k in ARRAYS}
        floats = {k: float(d[k]) for k in FLOATS}
        b0 = float(d["frozen_intercept"])
    except (TypeError, ValueError) as exc:
        raise ValueError(f"table law state: not numbers: {exc}") from None
    if w0.shape != frozen_weights.shape or not np.array_equal(w0, frozen_weights) or b0 != frozen_intercept:
        raise ValueError("table law state was learned against another model (its frozen weights differ)")
    if d["shape"] != shape:
        raise ValueError(
            f"table law state was learned on the {d['shape']!r} shape regressors, this law's are {shape!r}"
            " (saved by an earlier version, or with the model file's candidates removed or added)"
        )
    n = n_shape
    shapes = {
        "h": (n + 3, n + 3),
        "i": (n + 3,),
        "delta": (n + 3,),
        "cov": (n + 3, n + 3),
        "gram": (n + 1, n + 1),
        "evidence": (len(PRIOR_SCALES),),
    }
    for k, size in shapes.items():
        if arrays[k].shape != size or not np.isfinite(arrays[k]).all():
            raise ValueError(f"table law state: {k} must be {size} finite numbers")
    if not all(math.isfinite(v) or (k == "noise_var_dph2" and math.isnan(v)) for k, v in floats.items()):
        raise ValueError("table law state: values must be finite")
    counts = {k: d[k] for k in COUNTS}
    if any(isinstance(v, bool) or not isinstance(v, int) or v < 0 for v in counts.values()):
        raise ValueError("table law state: counts must be integers >= 0")
    return {**arrays, **floats, **counts}
