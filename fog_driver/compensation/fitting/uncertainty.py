"""The model file's ``uncertainty`` section, from what the fit knows (``compensation.uncertainty``).

r = sqrt(max(rms_fit^2 - n^2, 0))     the model's 1-min error on its data, the white noise taken out:
                                     rms_fit the 1-min RMS it leaves there (the report's "after" row,
                                     on the validation captures when there are any), n the noise floor
                                     of 1-min means on the same data
candidates                           the ring wesn's candidate structures (``wesn.tied_coils``)
R                                    the range of the fit target's 1-min means (``domain``)
"""

from __future__ import annotations

import math
from typing import Any

from ..domain import InputDomain
from ..uncertainty import UncertaintySpec, target_range_of
from .report import FitReport


def model_error_dph(report: FitReport, kind: str) -> float:
    """r (module docstring): on the validation captures when the report has them, else on the fit data."""
    by_name = {what: (fit_v, val_v) for what, fit_v, val_v in report.rows}
    fit_v, val_v = by_name[f"after, {kind}"]
    floor_fit, floor_val = report.noise_floor if report.noise_floor is not None else (0.0, None)
    rms, floor = (val_v, floor_val) if val_v is not None and floor_val is not None else (fit_v, floor_fit)
    if not (math.isfinite(rms) and math.isfinite(floor)):
        return 0.0 if not math.isfinite(rms) else float(rms)
    return math.sqrt(max(rms * rms - floor * floor, 0.0))


def uncertainty_for(model: Any, kind: str, report: FitReport, domain: InputDomain) -> UncertaintySpec:
    """The ``uncertainty`` section of a model fitted as ``kind``: with its candidate structures when the fit
    made them (the ring wesn: ``sigma_kind: candidates``, even when none tied: the data pinned it), else
    ``sigma_kind: residual``."""
    r = model_error_dph(report, kind)
    candidates = getattr(model, "candidates", None)
    if candidates is None or getattr(model, "selection", None) is None:
        return UncertaintySpec("residual", r, target_range_of(domain))
    return UncertaintySpec("candidates", r, target_range_of(domain), candidates=tuple(c.to_dict() for c in candidates))
