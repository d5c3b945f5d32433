"""The table law's state: what it learned and the run's own chain, as plain YAML-safe values (exact), and the
checks a state passes.

What it learned (``learned_part``: the adaptation document's ``table``): the frozen weights and intercept it was learned
against and its shape regressors' kind, the sums, the estimate and its covariance, the regressors' gram and the
evidence (``ARRAYS``), the noise, the innovation calibration and the comparison (``FLOATS``), and the counters
(``COUNTS``).  A state saved by an earlier version lacks the keys of ``ADDED``, which start from their value there.

The run's own chain, under ``CHAIN_KEY``: the ring of blocks, the bias capture, the anchor, the interval learned
last and the one rejected last (while the judge may still undo them), the outcome log, the coil's temperature, the
time of the last dwell and of the last interval learned, and the pending flags (``law.TableLaw.get_state``).  A
state without it (what it learned alone) is restored as a new run: the bias captured again, a new chain.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from ...dwells import Dwell
from .estimate import PRIOR_SCALES, SHAPE_REGRESSORS
from .window import Anchor

__all__ = [
    "ARRAYS",
    "CHAIN_KEY",
    "COUNTS",
    "FLOATS",
    "MIXTURE_KEYS",
    "anchor_from",
    "anchor_state",
    "checked_state",
    "dwell_from",
    "dwell_state",
    "learned_part",
    "state_of",
]

#: The key of the run's own chain in a state (module docstring); the other keys are what the law learned.
CHAIN_KEY = "chain"

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


def learned_part(state: dict[str, Any]) -> dict[str, Any]:
    """What the law learned, of its state (``get_state``): every key but the chain's (``CHAIN_KEY``), as the
    adaptation document keeps it."""
    return {k: v for k, v in state.items() if k != CHAIN_KEY}


def anchor_state(a: Anchor) -> list[Any]:
    """An anchor as plain values: its summary, then its other fields in order."""
    return [np.asarray(a.summary).tolist(), float(a.angle_arcsec), *(int(v) for v in a[2:])]


def anchor_from(values: list[Any], width: int) -> Anchor:
    """Inverse of ``anchor_state`` for a ring's rows of ``width``; ``ValueError`` for values that are not one."""
    summary, angle, *ints = values
    row = np.array(summary, dtype=np.float64)
    if row.shape != (width,) or len(ints) != 4:
        raise ValueError(f"not an anchor on rows of {width}: {values!r}")
    return Anchor(row, float(angle), *(int(v) for v in ints))


def dwell_state(d: Dwell) -> list[float | None]:
    """A dwell as plain values: its fields in order."""
    end = None if d.angle_end_deg is None else float(d.angle_end_deg)
    return [float(d.t_start_s), float(d.t_end_s), float(d.angle_deg), end]


def dwell_from(values: list[Any]) -> Dwell:
    """Inverse of ``dwell_state``; ``ValueError`` for values that are not a dwell."""
    t_start_s, t_end_s, angle_deg, angle_end_deg = values
    return Dwell(
        float(t_start_s), float(t_end_s), float(angle_deg), None if angle_end_deg is None else float(angle_end_deg)
    )


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
