"""What a model was fitted on, and what the compensator does outside it.

A drift model is a regression: inside the range of its fit data it interpolates, outside it
extrapolates, and a polynomial in standardized inputs extrapolates without bound
(docs/decisions/2026-12-07-fit-box-and-checks.md).  So the model file stores the
box of every input over the fit's static blocks and a bound on the estimate, and in operation::

    m_k      = margin_k * (high_k - low_k)                   (per input, a multiple of the fit's span)
    u_k'     = min(max(u_k, low_k - m_k), high_k + m_k)      the input the model sees
    D_hat'   = min(max(D_hat, -limit), limit),   limit = estimate_limit_dph

A block whose input left the widened box, or whose estimate was clipped, is flagged
``FLAG_EXTRAPOLATING``; inside the box the model sees its inputs unchanged (bit for bit).

The margins (``MARGINS``): the temperatures T1, T2, T3 enter every model through nonlinear terms
(the bias curve's square and cube, the coil neuron's powers), which are not to be trusted beyond
the fit's range: 10 % of its span.  The rates and the two gradients enter linearly (the Shupe term
on the coil's rate, the gradient terms), so beyond the fit's range they extrapolate along a line,
which is the physics and holds well past it (a paper-profile fit heats at 0.3 degC/min and is good
on 1-3 degC/min ramps): 200 % of their span on each side, so that only rates no chamber run
resembles, or a fault, are clamped.

``estimate_limit_dph`` is ``ESTIMATE_LIMIT_FACTOR`` times the range (max - min) of the fit target's
1-minute means over the static blocks: no thermal state the fit saw drove the drift further than
that range from its mean, and a model that claims three times as much is extrapolating, not
measuring.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from .features import INPUT_NAMES, channels_of, input_names

#: The widening of the fit box on each side, in multiples of the fit data's span of that input
#: (module docstring): T1, T2, T3, then the three rates and the two gradients.
LEVEL_MARGIN = 0.1
LINEAR_MARGIN = 2.0
MARGINS = (LEVEL_MARGIN,) * 3 + (LINEAR_MARGIN,) * 5


def margins_for(n_inputs: int) -> tuple[float, ...]:
    """``MARGINS`` for an input vector of ``n_inputs`` (``features.input_names``: the temperatures first)."""
    n = channels_of(n_inputs)
    return (LEVEL_MARGIN,) * n + (LINEAR_MARGIN,) * (n_inputs - n)


#: The estimate's bound, in multiples of the range of the fit target's 1-minute means.
ESTIMATE_LIMIT_FACTOR = 3.0


@dataclass(frozen=True)
class InputDomain:
    """The fit data's box of the inputs (raw units: degC, degC/min; ``names``, 8 for three temperature
    channels), its margins, and the estimate's bound."""

    low: tuple[float, ...]
    high: tuple[float, ...]
    estimate_limit_dph: float
    margin: tuple[float, ...] = MARGINS
    names: tuple[str, ...] = INPUT_NAMES
    if TYPE_CHECKING:  # set in __post_init__, not a field
        _bounds: tuple[np.ndarray, np.ndarray] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        low = tuple(float(v) for v in self.low)
        high = tuple(float(v) for v in self.high)
        margin = tuple(float(v) for v in self.margin)
        n = len(self.names)
        if len(low) != n or len(high) != n or len(margin) != n:
            raise ValueError(f"the domain needs {n} lows, highs and margins")
        if not all(math.isfinite(a) and math.isfinite(b) and a <= b for a, b in zip(low, high)):
            raise ValueError("the domain's lows and highs must be finite, low <= high")
        if not all(math.isfinite(m) and m >= 0 for m in margin):
            raise ValueError("the domain's margins must be finite and >= 0")
        if not (math.isfinite(self.estimate_limit_dph) and self.estimate_limit_dph > 0):
            raise ValueError(f"estimate_limit_dph must be finite and > 0, got {self.estimate_limit_dph!r}")
        object.__setattr__(self, "low", low)
        object.__setattr__(self, "high", high)
        object.__setattr__(self, "margin", margin)
        lo, hi, m = np.array(low), np.array(high), np.array(margin)
        span = hi - lo
        bounds = (lo - m * span, hi + m * span)
        for b in bounds:
            b.flags.writeable = False
        object.__setattr__(self, "_bounds", bounds)

    @classmethod
    def from_fit(
        cls, inputs: np.ndarray, minute_means_dph: np.ndarray, names: tuple[str, ...] = INPUT_NAMES
    ) -> InputDomain:
        """The box of the fit's (rows, 8) raw inputs (finite values) and the bound from its target's
        1-minute means.  A target with no spread (a model of nothing) still gets a positive bound."""
        x = np.asarray(inputs, dtype=np.float64)
        x = np.where(np.isfinite(x), x, np.nan)
        means = np.asarray(minute_means_dph, dtype=np.float64)
        spread = float(np.ptp(means)) if len(means) else 0.0
        return cls(
            tuple(np.nanmin(x, axis=0)),
            tuple(np.nanmax(x, axis=0)),
            ESTIMATE_LIMIT_FACTOR * max(spread, 1e-3),
            margins_for(len(names)),
            tuple(names),
        )

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(lower, upper): the box widened by the margin, the inputs are clamped to."""
        return self._bounds

    def clamp(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray | np.bool_]:
        """``(u', outside)`` for one row (8,) or many (T, 8): u clamped to the widened box, and whether
        (per row) any input was outside it.  NaN stays NaN (and is not "outside")."""
        lower, upper = self._bounds
        u = np.asarray(u, dtype=np.float64)
        clamped = np.minimum(np.maximum(u, lower), upper)
        outside = ((u < lower) | (u > upper)).any(axis=-1)
        return clamped, outside

    def bound(self, estimate_dph: float) -> tuple[float, bool]:
        """``(D_hat', clipped)``: the estimate clipped to +-``estimate_limit_dph``."""
        limit = self.estimate_limit_dph
        if -limit <= estimate_dph <= limit or estimate_dph != estimate_dph:
            return estimate_dph, False
        return math.copysign(limit, estimate_dph), True

    def bound_many(self, estimates_dph: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``bound`` of many estimates (the same values, elementwise)."""
        limit = self.estimate_limit_dph
        e = np.asarray(estimates_dph, dtype=np.float64)
        clipped = np.abs(e) > limit
        return np.where(clipped, np.copysign(limit, e), e), clipped

    def outside_names(self, u: np.ndarray) -> list[str]:
        """The inputs of one row outside the widened box (for messages)."""
        lower, upper = self._bounds
        return [name for name, v, a, b in zip(self.names, u, lower, upper) if v < a or v > b]

    def to_dict(self) -> dict[str, Any]:
        return {
            "inputs": list(self.names),
            "low": list(self.low),
            "high": list(self.high),
            "margin": list(self.margin),
            "estimate_limit_dph": float(self.estimate_limit_dph),
        }

    @classmethod
    def from_dict(cls, doc: dict) -> InputDomain:
        if not isinstance(doc, dict):
            raise ValueError("the domain must be a mapping")
        names = doc.get("inputs", list(INPUT_NAMES))
        if not isinstance(names, list) or not all(isinstance(v, str) for v in names):
            raise ValueError("the domain's inputs must be a list of names")
        n = channels_of(len(names))  # the names must be those of some temperature channels
        channels = tuple(v[2:-2] if v.startswith("t_") and v.endswith("_c") else "" for v in names[:n])
        if not all(channels) or list(input_names(channels)) != list(names):
            raise ValueError(
                f"the domain's inputs must be named as a model's inputs ({', '.join(INPUT_NAMES)} for protocol v1)"
            )
        for key in ("low", "high", "margin"):
            if not isinstance(doc.get(key), list) or not all(
                isinstance(v, (int, float)) and not isinstance(v, bool) for v in doc[key]
            ):
                raise ValueError(f"the domain's {key!r} must be a list of numbers")
        limit = doc.get("estimate_limit_dph")
        if not isinstance(limit, (int, float)) or isinstance(limit, bool):
            raise ValueError("the domain's 'estimate_limit_dph' must be a number")
        return cls(tuple(doc["low"]), tuple(doc["high"]), float(limit), tuple(doc["margin"]), tuple(names))
