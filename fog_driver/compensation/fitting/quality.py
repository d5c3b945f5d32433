"""Whether a fit's data can support its model: the checks every fit runs, and what they found.

A regression fitted on data that cannot determine it still returns numbers, and on its own data they
look excellent, and off it they can be anything (docs/decisions/2026-12-07-fit-box-and-checks.md).
So every fit measures its data against documented minima, and a fit that fails one
is refused unless the user accepts a weak fit (``fog-driver fit --accept-weak-fit``), which the
model file then records:

=====================  ===============================================================  ==========
check                  what is measured                                                 limit
=====================  ===============================================================  ==========
``duration``           static fit time, all captures together, minutes                  >= 30
``ring_span``          span (max - min) of the ring mean (T1 + T2) / 2, degC             >= 5
``rate_span``          span of the ring mean's rate (dT1/dt + dT2/dt) / 2, degC/min     >= 0.2
``target_range``       range of the fit target's 1-minute means, deg/h                  <= 20
``condition``          condition number of the data in the physical basis, standardized  <= 1e8
``fit_residual``       1-min drift RMS after the model on its fit data, vs before        < before
``validation``         the same on ``--validate`` captures (when given), vs before       < before
=====================  ===============================================================  ==========

Why these: a thermal drift model is a function of temperature and its rate, so the data must move
both over a range worth modelling (5 degC, 0.2 degC/min: a few times the thermometers' resolution
and drift of their offsets, and a tenth of a chamber's usual ramp), for long enough to average the
gyro's white noise below its drift (30 min of 1-minute means); a FOG's thermal drift spans a few
deg/h at most, so a target range of 20 deg/h means motion or a fault in the fit data, not drift; a
condition number above 1e8 leaves the weights to the penalty, not the data.  The condition is the
data's, measured in the physical basis every kind is built on (the polynomial's: the ring temperature
to the cube, its rate and their products, the gradients); a model's own regressors may be collinear by
design (the wesn's coil rate beside the coil and the ring), which its penalty handles: their condition
number is recorded beside the checks (``model_condition``), for information.  A model worse than no
compensation on its own fit data or on a validation run is no model to deploy.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

MIN_FIT_MINUTES = 30.0
MIN_RING_SPAN_C = 5.0
MIN_RATE_SPAN_C_PER_MIN = 0.2
MAX_TARGET_RANGE_DPH = 20.0
MAX_CONDITION = 1e8


@dataclass(frozen=True)
class Check:
    name: str
    value: float
    limit: float
    passed: bool
    message: str  #: what failing means, for the user (empty when passed)


@dataclass(frozen=True)
class FitQuality:
    checks: tuple[Check, ...]

    @property
    def failed(self) -> list[Check]:
        return [c for c in self.checks if not c.passed]

    def format(self) -> str:
        return format_checks(self.to_dict(False))

    def to_dict(self, accepted_weak: bool) -> dict:
        doc: dict[str, Any] = {
            "checks": {
                c.name: {"value": float(c.value), "limit": float(c.limit), "passed": bool(c.passed)}
                for c in self.checks
            }
        }
        if self.failed:
            doc["weak"] = [c.message for c in self.failed]
            doc["accepted_weak"] = bool(accepted_weak)
        return doc


#: Each check's unit and the way its limit goes (the value must be ``>=``, ``<=`` or ``<`` the limit), for
#: ``format_checks``; the module docstring's table.
CHECK_UNITS = {
    "duration": (">=", "min"),
    "ring_span": (">=", "degC"),
    "rate_span": (">=", "degC/min"),
    "target_range": ("<=", "deg/h"),
    "condition": ("<=", ""),
    "fit_residual": ("<", "deg/h"),
    "validation": ("<", "deg/h"),
}


def format_checks(doc: dict) -> str:
    """The fit-quality section of ``fog-driver fit``'s report, from ``FitQuality.to_dict``: each check's value
    and its limit with their unit, the limit with the way it goes (``CHECK_UNITS``; the residual checks' limit
    is the drift before compensation)."""
    lines = [f"{'fit checks':34s} {'value':>10s} {'':9s}limit"]
    for name, c in doc["checks"].items():
        relation, unit = CHECK_UNITS.get(name, ("", ""))
        limit = f"{relation} {c['limit']:.4g} {unit}".strip()
        lines.append(f"{name:34s} {c['value']:10.4g} {unit:8s} {limit:20s} {'ok' if c['passed'] else 'FAILS'}")
    return "\n".join(lines)


def condition_number(x: np.ndarray) -> float:
    """The 2-norm condition number of the columns of ``x`` centred and scaled to unit deviation (the
    problem the ridge solves); constant columns are left out (they carry no information)."""
    x = np.asarray(x, dtype=np.float64)
    if not len(x):
        return float("inf")
    std = x.std(axis=0)
    keep = std > 0
    if not keep.any():
        return float("inf")
    z = (x[:, keep] - x[:, keep].mean(axis=0)) / std[keep]
    s = np.linalg.svd(z, compute_uv=False)
    return float(s[0] / s[-1]) if s[-1] > 0 else float("inf")


def _check(name: str, value: float, limit: float, passed: bool, message: str) -> Check:
    return Check(name, float(value), float(limit), bool(passed), "" if passed else message)


def assess(
    static_minutes: float,
    ring_c: np.ndarray,
    ring_rate_c_per_min: np.ndarray,
    target_minute_means: np.ndarray,
    condition: float | None,
    fit_before_after: tuple[float, float],
    validate_before_after: tuple[float, float] | None,
) -> FitQuality:
    """The checks of the module docstring, from the fit's measured quantities."""
    ring_span = float(np.ptp(ring_c)) if len(ring_c) else 0.0
    rate_span = float(np.ptp(ring_rate_c_per_min)) if len(ring_rate_c_per_min) else 0.0
    target_range = float(np.ptp(target_minute_means)) if len(target_minute_means) else 0.0
    checks = [
        _check(
            "duration",
            static_minutes,
            MIN_FIT_MINUTES,
            static_minutes >= MIN_FIT_MINUTES,
            f"only {static_minutes:.1f} min of static fit data (at least {MIN_FIT_MINUTES:g} needed): too short to "
            f"average the gyro's noise below its drift",
        ),
        _check(
            "ring_span",
            ring_span,
            MIN_RING_SPAN_C,
            ring_span >= MIN_RING_SPAN_C,
            f"the ring temperature spans only {ring_span:.2f} degC (at least {MIN_RING_SPAN_C:g} needed): the model "
            f"would extrapolate at any other temperature",
        ),
        _check(
            "rate_span",
            rate_span,
            MIN_RATE_SPAN_C_PER_MIN,
            rate_span >= MIN_RATE_SPAN_C_PER_MIN,
            f"the ring temperature's rate spans only {rate_span:.3f} degC/min (at least {MIN_RATE_SPAN_C_PER_MIN:g} "
            f"needed): its rate terms are unidentified",
        ),
        _check(
            "target_range",
            target_range,
            MAX_TARGET_RANGE_DPH,
            target_range <= MAX_TARGET_RANGE_DPH,
            f"the fit target's 1-minute means span {target_range:.1f} deg/h (a thermal drift spans at most "
            f"{MAX_TARGET_RANGE_DPH:g}): the table moved, or the gyro faulted, during the fit data",
        ),
    ]
    if condition is not None:
        checks.append(
            _check(
                "condition",
                condition,
                MAX_CONDITION,
                condition <= MAX_CONDITION,
                f"the data's condition number is {condition:.3g} (at most {MAX_CONDITION:g}): they do not "
                f"determine the weights",
            )
        )
    before, after = fit_before_after
    checks.append(
        _check(
            "fit_residual",
            after,
            before,
            after < before,
            f"on its own fit data the model leaves {after:.4f} deg/h, more than the {before:.4f} before compensation",
        )
    )
    if validate_before_after is not None:
        before, after = validate_before_after
        checks.append(
            _check(
                "validation",
                after,
                before,
                after < before,
                f"on the validation captures the model leaves {after:.4f} deg/h, more than the "
                f"{before:.4f} with no compensation",
            )
        )
    return FitQuality(tuple(checks))
