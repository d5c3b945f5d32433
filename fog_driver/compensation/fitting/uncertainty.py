"""The model file's ``uncertainty`` section, from what the fit knows (``compensation.uncertainty``).

r^2 = max(rms^2 - n^2, 0) + rms^2 sqrt(2 / N)
                                     the model's 1-min error on its data, the white noise taken out,
                                     plus the standard error of that mean square (N whole static
                                     minutes): an error the data cannot tell from 0 is not 0.  rms: the
                                     1-min RMS the model leaves (the report's "after" row, on the
                                     validation captures when there are any), n: the noise floor of
                                     1-min means on the same data
candidates                           the ring wesn's candidate structures (``wesn.tied_coils``)
R                                    the range of the fit target's 1-min means (``domain``)
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

from ..domain import InputDomain
from ..uncertainty import FALLBACK_SCALE, SigmaCalibration, UncertaintySpec, target_range_of
from .report import FitReport


def model_error_dph(rms_dph: float, floor_dph: float, minutes: int) -> float:
    """r (module docstring) from the 1-min RMS a model leaves, the noise floor on the same data and the
    number of whole static minutes; 0 when the RMS is not a number."""
    if not math.isfinite(rms_dph):
        return 0.0
    floor = floor_dph if math.isfinite(floor_dph) else 0.0
    excess = max(rms_dph * rms_dph - floor * floor, 0.0)
    return math.sqrt(excess + rms_dph * rms_dph * math.sqrt(2.0 / max(minutes, 1)))


def report_error_dph(report: FitReport, kind: str, fit_minutes: int, validate_minutes: int) -> float:
    """``model_error_dph`` of the report's "after" row for ``kind``: on the validation captures when the
    report has them (``validate_minutes`` of them), else on the fit data (``fit_minutes``)."""
    by_name = {what: (fit_v, val_v) for what, fit_v, val_v in report.rows}
    fit_v, val_v = by_name[f"after, {kind}"]
    floor_fit, floor_val = report.noise_floor if report.noise_floor is not None else (math.nan, None)
    if val_v is not None and floor_val is not None and validate_minutes > 0:
        return model_error_dph(val_v, floor_val, validate_minutes)
    return model_error_dph(fit_v, floor_fit, fit_minutes)


def uncertainty_for(model: Any, r_dph: float, domain: InputDomain) -> UncertaintySpec:
    """The ``uncertainty`` section of a fitted model whose error is ``r_dph``: with its candidate
    structures when the fit made them (the ring wesn: ``sigma_kind: candidates``, even when none tied: the
    data pinned it), else ``sigma_kind: residual``."""
    candidates = getattr(model, "candidates", None)
    if candidates is None or getattr(model, "selection", None) is None:
        return UncertaintySpec("residual", r_dph, target_range_of(domain))
    return UncertaintySpec(
        "candidates", r_dph, target_range_of(domain), candidates=tuple(c.to_dict() for c in candidates)
    )


def with_calibration(spec: UncertaintySpec, calibration: SigmaCalibration) -> UncertaintySpec:
    """``spec`` carrying the fit's calibration; a fit that could not calibrate (``method: none``) gets the
    fall-back's factors (``uncertainty.FALLBACK_SCALE``) on the spread and the residual."""
    scale = spec.spread_scale if calibration.calibrated else FALLBACK_SCALE
    residual = spec.residual_scale if calibration.calibrated else FALLBACK_SCALE
    return dataclasses.replace(spec, calibration=calibration, spread_scale=scale, residual_scale=residual)
