"""The readout's adaptation state as a document: its format tag, its keys, and the checks of the optional parts
(a leaf of ``adapt``: dicts in, checked values or ``ValueError`` out).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .adapt_config import finite_number

ADAPT_STATE_SCHEMA_VERSION = 1


#: The readout's state (``OnlineReadout.get_state``): every key required.
STATE_KEYS = (
    "n_features",
    "frozen_weights",
    "frozen_intercept",
    "law",
    "bias_sum_dph",
    "bias_count",
    "bias_dph",
    "blocks",
    "gated_blocks",
    "updates",
    "guards",
)


#: The comparison guard's state (states saved before it existed load without it: a fresh comparison).
COMPARE_KEYS = (
    "compare_blocks",
    "compare_sum_frozen_dph",
    "compare_sum_adapted_dph",
    "compare_gain",
    "compare_gain_sq",
    "compare_windows",
    "compare_weights",
    "compare_level_frozen_dph",
    "compare_level_adapted_dph",
)


#: Gate state (states saved before the gate existed load without it: a fresh gate).
GATE_KEYS = ("gate_noise_var_dph2", "gate_last_rate_dph", "gate_innovation_dph", "rejected")


#: The adapted estimate's error statistic (``OnlineReadout.adapted_sigma_dph``); absent in states saved before it.
SIGMA_KEY = "compare_dev_sq_adapted_dph2"


def checked_sigma(d: dict[str, Any]) -> float:
    """The state's ``SIGMA_KEY`` (0 when absent), checked: a finite number >= 0."""
    v = d.get(SIGMA_KEY, 0.0)
    if not (finite_number(v) and v >= 0):
        raise ValueError(f"adaptation state: {SIGMA_KEY!r} must be a finite number >= 0, got {v!r}")
    return float(v)


def check_state_keys(d: Any) -> None:
    """``ValueError`` unless ``d`` is a dict with every key of ``STATE_KEYS`` and no key but those, the
    comparison's (``COMPARE_KEYS``) and the gate's (``GATE_KEYS``)."""
    optional = set(COMPARE_KEYS) | set(GATE_KEYS) | {SIGMA_KEY}
    if not isinstance(d, dict) or not set(STATE_KEYS) <= set(d) <= set(STATE_KEYS) | optional:
        got = sorted(d) if isinstance(d, dict) else type(d).__name__
        raise ValueError(
            f"adaptation state needs exactly the keys {sorted(STATE_KEYS)} (and the comparison's "
            f"{sorted(COMPARE_KEYS)} and the gate's {sorted(GATE_KEYS)}), got {got}"
        )


def checked_gate(d: dict[str, Any]) -> dict[str, Any]:
    """The innovation gate's part of a state (``GATE_KEYS``; empty in states saved before it existed), checked:
    all or none of its keys, a variance >= 0, finite numbers, a count >= 0."""
    gate = {k: d[k] for k in GATE_KEYS if k in d}
    if gate and set(gate) != set(GATE_KEYS):
        raise ValueError(f"adaptation state: the gate needs all of {sorted(GATE_KEYS)}")
    if gate:
        if not (finite_number(gate["gate_noise_var_dph2"]) and gate["gate_noise_var_dph2"] >= 0):
            raise ValueError("adaptation state: 'gate_noise_var_dph2' must be a finite number >= 0")
        if not finite_number(gate["gate_innovation_dph"]):
            raise ValueError("adaptation state: 'gate_innovation_dph' must be a finite number")
        if gate["gate_last_rate_dph"] is not None and not finite_number(gate["gate_last_rate_dph"]):
            raise ValueError("adaptation state: 'gate_last_rate_dph' must be a finite number or null")
        if isinstance(gate["rejected"], bool) or not isinstance(gate["rejected"], int) or gate["rejected"] < 0:
            raise ValueError("adaptation state: 'rejected' must be an integer >= 0")
    return gate


def checked_comparison(d: dict[str, Any], n_features: int) -> tuple[dict[str, Any], np.ndarray | None]:
    """The comparison guard's part of a state (``COMPARE_KEYS``; empty in states saved before it existed),
    checked, and its weights (``n_features`` + 1 finite numbers; None without the part)."""
    compare = {k: d[k] for k in COMPARE_KEYS if k in d}
    if compare and set(compare) != set(COMPARE_KEYS):
        raise ValueError(f"adaptation state: the comparison needs all of {sorted(COMPARE_KEYS)}")
    for k in ("compare_blocks", "compare_windows"):
        if k in compare and (isinstance(compare[k], bool) or not isinstance(compare[k], int) or compare[k] < 0):
            raise ValueError(f"adaptation state: {k!r} must be an integer >= 0, got {compare[k]!r}")
    weights: np.ndarray | None = None
    if compare:
        try:
            weights = np.array(compare.get("compare_weights", []), dtype=np.float64)
        except (TypeError, ValueError):
            weights = np.zeros(0)
        if weights.shape != (n_features + 1,) or not np.isfinite(weights).all():
            raise ValueError(f"adaptation state: 'compare_weights' must be {n_features + 1} finite numbers")
    for k in (
        "compare_sum_frozen_dph",
        "compare_sum_adapted_dph",
        "compare_gain",
        "compare_gain_sq",
        "compare_level_frozen_dph",
        "compare_level_adapted_dph",
    ):
        if k in compare and not (finite_number(compare[k]) and (k != "compare_gain_sq" or compare[k] >= 0)):
            raise ValueError(
                f"adaptation state: {k!r} must be a finite number (>= 0 for a mean square), got {compare[k]!r}"
            )
    return compare, weights
