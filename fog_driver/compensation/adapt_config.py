"""The online adaptation's settings (``AdaptConfig``) and the gyro's own static detector (``StaticDetector``):
what ``adapt.OnlineReadout`` and the compensator are built from (a leaf: numbers in, settings out).

Static: a block is static when the last ``static_window_s`` of block rates (this one included) all lie
within ``static_threshold_dph`` of their median: the table stands still, whatever the drift does.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from .keys import require_known_keys
from .readout import AdaptiveLawParams


def finite_number(x: Any) -> bool:
    """A real number (not a bool), finite."""
    return isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, bool) and math.isfinite(x)


def _default_law() -> AdaptiveLawParams:
    # Drift in deg/h at 1 Hz: 10 s takes the edge off the 1-s noise, one hour of memory spans a thermal
    # excursion, kappa 0.5 is half the fastest stable step (smoother than 1 against the target's noise).
    return AdaptiveLawParams(filter_time_s=10.0, memory_time_s=3600.0, kappa=0.5, delta=1e-6)


@dataclass(frozen=True)
class AdaptConfig:
    """Online adaptation settings (validated; ``ValueError`` when out of range).

    * ``law``: the adaptive law's parameters.
    * ``runaway_dph``: an adapted estimate further than this from the frozen one is a runaway; None (the
      default): ``runaway_for`` the model's own fit residual.
    * ``innovation_sigmas``: the innovation gate (module docstring): a filtered innovation beyond the
      runaway bound plus this many of its noise sigmas is not learned.
    * ``static_threshold_dph``, ``static_window_s``: the gyro's own static detector (``StaticDetector``).
    * ``bias_capture_s``: gated time spent capturing the run's bias before W may move (0: no capture).
    * ``warmup_s``: for the compensator's gate: blocks before it (rate smoother and instrument start-up)
      are never gated, as in fitting (``FitConfig.warmup_s``).
    * ``compare_window_s``, ``compare_memory_windows``, ``compare_min_windows``: the comparison guard
      (module docstring): windows of gated time over which the frozen and the adapted estimates' mean
      errors are compared, the memory of their running mean squares (in windows), and how many windows
      must have been seen before the adapted estimate may be used.
    * ``compare_min_gain``: the comparison's mean gain must also exceed ``(compare_min_gain r)^2``, r the
      model's fit residual as the runaway bound has it (``runaway_dph / RUNAWAY_FIT_RESIDUALS``): the
      adapted estimate is used only where it removes an error of at least that fraction of what the
      frozen model left on its fit data, not the gyro's slow noise that a significant but tiny gain is.
    """

    law: AdaptiveLawParams = field(default_factory=_default_law)
    runaway_dph: float | None = None
    innovation_sigmas: float = 4.0
    static_threshold_dph: float = 30.0
    static_window_s: float = 60.0
    bias_capture_s: float = 300.0
    warmup_s: float = 300.0
    compare_window_s: float = 300.0
    compare_memory_windows: float = 12.0
    compare_min_windows: int = 4
    compare_min_gain: float = 0.5

    def __post_init__(self) -> None:
        if not isinstance(self.law, AdaptiveLawParams):
            raise ValueError(f"law must be AdaptiveLawParams, got {type(self.law).__name__}")
        if self.runaway_dph is not None and (not finite_number(self.runaway_dph) or not self.runaway_dph > 0):
            raise ValueError(f"runaway_dph must be finite and > 0 (or null: from the model), got {self.runaway_dph!r}")
        for name in ("innovation_sigmas", "static_threshold_dph", "static_window_s", "compare_window_s"):
            v = getattr(self, name)
            if not finite_number(v) or not v > 0:
                raise ValueError(f"{name} must be finite and > 0, got {v!r}")
        for name in ("bias_capture_s", "warmup_s"):
            v = getattr(self, name)
            if not finite_number(v) or v < 0:
                raise ValueError(f"{name} must be finite and >= 0, got {v!r}")
        if not finite_number(self.compare_min_gain) or self.compare_min_gain < 0:
            raise ValueError(f"compare_min_gain must be finite and >= 0, got {self.compare_min_gain!r}")
        if not finite_number(self.compare_memory_windows) or not self.compare_memory_windows >= 1:
            raise ValueError(f"compare_memory_windows must be finite and >= 1, got {self.compare_memory_windows!r}")
        if (
            isinstance(self.compare_min_windows, bool)
            or not isinstance(self.compare_min_windows, int)
            or (self.compare_min_windows < 0)
        ):
            raise ValueError(f"compare_min_windows must be an integer >= 0, got {self.compare_min_windows!r}")

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {f.name: getattr(self, f.name) for f in fields(self)}
        d["law"] = self.law.to_dict()
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> AdaptConfig:
        """Inverse of ``to_dict``; missing keys take their defaults, unknown keys are errors."""
        require_known_keys(cls, d, "adapt config")
        values = dict(d)
        if "law" in values:
            values["law"] = AdaptiveLawParams.from_dict(values["law"])
        return cls(**values)


def blocks_in(seconds: float, sample_time_s: float) -> int:
    """The blocks of ``sample_time_s`` in ``seconds``, rounded to the nearest."""
    return int(round(seconds / sample_time_s))


class StaticDetector:
    """Is the table static?  From the gyro's own block rates, causally, with explicit state.

    ``step(rate_dph)`` is True when the last ``window_blocks`` block rates (this one included) are all
    finite and all within ``threshold_dph`` of their median; False until the window has filled.  A
    turntable move makes every window that contains one of its blocks non-static (the median is the
    static rate, the moving blocks are far from it), so the detector turns static again a full window
    after the move's last block.  Causal: the first block of a move counts as static when it moved
    for so short a part of the block that its mean rate is still within the threshold.
    """

    def __init__(self, threshold_dph: float, window_blocks: int, rates: list[float] | None = None) -> None:
        if not finite_number(threshold_dph) or not threshold_dph > 0:
            raise ValueError(f"threshold_dph must be finite and > 0, got {threshold_dph!r}")
        if isinstance(window_blocks, bool) or not isinstance(window_blocks, (int, np.integer)) or window_blocks < 1:
            raise ValueError(f"window_blocks must be an integer >= 1, got {window_blocks!r}")
        self.threshold_dph = float(threshold_dph)
        self.window_blocks = int(window_blocks)
        self._rates: deque[float] = deque(maxlen=self.window_blocks)
        if rates is not None:
            if len(rates) > self.window_blocks:
                raise ValueError(f"{len(rates)} rates for a window of {self.window_blocks} blocks")
            self._rates.extend(float(r) for r in rates)

    @classmethod
    def from_config(cls, config: AdaptConfig, sample_time_s: float) -> StaticDetector:
        return cls(config.static_threshold_dph, max(1, blocks_in(config.static_window_s, sample_time_s)))

    def step(self, rate_dph: float) -> bool:
        self._rates.append(float(rate_dph))
        if len(self._rates) < self.window_blocks:
            return False
        window = np.fromiter(self._rates, dtype=np.float64, count=self.window_blocks)
        if not np.isfinite(window).all():
            return False
        return bool(np.all(np.abs(window - np.median(window)) <= self.threshold_dph))

    def run(self, rate_dph: np.ndarray) -> np.ndarray:
        """``step`` over many block rates."""
        return np.array([self.step(r) for r in np.asarray(rate_dph, dtype=np.float64).tolist()], dtype=bool)

    def to_dict(self) -> dict[str, Any]:
        """Plain values (NaN rates are ``.nan`` in YAML): safe for ``yaml.safe_dump``, exact."""
        return {
            "threshold_dph": self.threshold_dph,
            "window_blocks": self.window_blocks,
            "rates": [float(r) for r in self._rates],
        }

    def get_state(self) -> dict[str, Any]:
        """The detector's state: ``to_dict``'s document (its settings and the window's rates)."""
        return self.to_dict()

    def set_state(self, state: dict[str, Any]) -> None:
        """The detector continues from ``get_state``'s document; ``ValueError`` (nothing changed) for a bad one
        or one with other settings."""
        found = StaticDetector.from_dict(state)
        if (found.threshold_dph, found.window_blocks) != (self.threshold_dph, self.window_blocks):
            raise ValueError("the static detector's settings differ from the state's")
        self._rates = found._rates

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> StaticDetector:
        keys = {"threshold_dph", "window_blocks", "rates"}
        if not isinstance(d, dict) or set(d) != keys:
            got = sorted(d) if isinstance(d, dict) else type(d).__name__
            raise ValueError(f"static detector state needs exactly the keys {sorted(keys)}, got {got}")
        rates = d["rates"]
        if not isinstance(rates, list) or not all(
            isinstance(r, (int, float)) and not isinstance(r, bool) for r in rates
        ):
            raise ValueError("static detector state: 'rates' must be a list of numbers")
        return cls(d["threshold_dph"], d["window_blocks"], rates)
