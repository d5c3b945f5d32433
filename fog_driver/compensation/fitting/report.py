"""The fit's report: the drift each model leaves, applied as the compensator applies it, before and after,
on the fit data and the validation data, and the noise floor beside them.

    RMS_1min = sqrt(mean((m_k - mean m)^2)),  m_k the 1-minute means of the residual over whole static minutes
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..domain import InputDomain
from ..readout import Standardizer
from .choice import describe
from .data import CaptureData, block_noise_dph, first_valid_block, static_minute_means


def minute_rms(residual_dph: np.ndarray, mask: np.ndarray, model_rate_hz: float = 1.0) -> float:
    """RMS of 1-minute averages of a residual over the usable blocks, its mean removed (a bias is not drift)."""
    means = static_minute_means(residual_dph, mask, model_rate_hz)
    if not len(means):
        return float("nan")
    return float(np.sqrt(np.mean((means - means.mean()) ** 2)))


def applied_prediction(
    model, capture: CaptureData, normalizer: Standardizer, domain: InputDomain | None = None
) -> np.ndarray:
    """The drift the compensator would apply in each block: the model's output from the block before,
    the model started at rest at the first valid input (as ``Compensator`` does), its inputs clamped to
    ``domain`` and its output bounded by it (as ``Compensator`` does)."""

    u = np.where(np.isfinite(capture.inputs), capture.inputs, 0.0)
    if domain is not None:
        u, _ = domain.clamp(u)
    z = normalizer.transform(u)
    first = first_valid_block(capture.inputs)
    model.reset()
    model.start(z[first])
    out = np.zeros(len(z))
    out[first:] = model.run(z[first:])
    if domain is not None:
        out, _ = domain.bound_many(out)
    return np.r_[0.0, out[:-1]]


#: The marker on a report row whose model leaves more drift than no compensation.
WORSE_MARKER = "WORSE than uncompensated"


@dataclass
class FitReport:
    """Drift RMS of 1-minute averages (usable blocks, mean removed), deg/h.

    A model row that leaves more than the "before compensation" row in a column is marked
    ``WORSE_MARKER`` (``worse``).  ``noise_floor`` (fit data, validate data or None): the white noise of
    the 1-s blocks over sqrt(60) (``noise_floor_dph``), what the 1-minute RMS of a perfect model still
    holds on measured data, in expectation (a few minutes, or a model fitted to them, can show less)."""

    rows: list[tuple[str, float, float | None]]  #: (what, on fit data, on validate data)
    noise_floor: tuple[float, float | None] | None = None
    #: the model choice on the fit's own validation split (``choice.choose``), when the fit made one
    choice: dict[str, Any] | None = None
    #: how the fit calibrated ``drift_sigma_dph`` (``sigma_calibration.describe``), once it has
    sigma_line: str | None = None

    @property
    def noise_1min_dph(self) -> float | None:
        """The gyro's white noise at 1 min on the fit data (``noise_floor_dph``), or None when unknown."""
        value = self.noise_floor[0] if self.noise_floor is not None else None
        return value if value is not None and math.isfinite(value) else None

    def lines(self) -> list[str]:
        """The lines after the table: the noise at 1 min, and the model choice with its margin."""
        out = []
        if self.noise_1min_dph is not None:
            out.append(
                f"noise_1min_dph: {self.noise_1min_dph:.4f} deg/h: the gyro's white noise at 1 min on the fit data "
                f"(in the model file, and in the daemon's STATUS)"
            )
        if self.choice is not None:
            out.append(describe(self.choice))
        if self.sigma_line is not None:
            out.append(self.sigma_line)
        return out

    def worse(self) -> dict[str, list[str]]:
        """For each model row worse than no compensation: the columns ("fit", "validate") where it is."""
        before = self.rows[0]
        out: dict[str, list[str]] = {}
        for what, fit_value, validate_value in self.rows[1:]:
            cols = [
                col
                for col, v, b in (("fit", fit_value, before[1]), ("validate", validate_value, before[2]))
                if v is not None and b is not None and v > b
            ]
            if cols:
                out[what] = cols
        return out

    def format(self) -> str:
        has_validate = any(v is not None for _, _, v in self.rows)
        header = f"{'1-min drift RMS, deg/h':34s} {'fit data':>10s}" + (f" {'validate':>10s}" if has_validate else "")
        lines = [header]
        worse = self.worse()
        rows = list(self.rows)
        if self.noise_floor is not None:
            rows.append(("noise floor (white, 1-min means)", *self.noise_floor))
        for what, fit_value, validate_value in rows:
            line = f"{what:34s} {fit_value:10.4f}"
            if has_validate:
                line += f" {validate_value:10.4f}" if validate_value is not None else f" {'':>10s}"
            if what in worse:
                where = " and ".join("validation" if c == "validate" else "fit data" for c in worse[what])
                line += f"  {WORSE_MARKER} ({where})"
            lines.append(line)
        return "\n".join(lines)

    def floor_note(self) -> str | None:
        """The line that says what the noise floor means for the table."""
        if self.noise_floor is None:
            return None
        fit_floor, validate_floor = self.noise_floor
        also = f", {validate_floor:.4f} on the validation data" if validate_floor is not None else ""
        return (
            f"noise floor of 1-min means: {fit_floor:.4f} deg/h on the fit data{also}: the gyro's white noise, "
            f"which no model removes; differences between models well below it are not meaningful on measured "
            f"data (evaluate --truth scores against the true drift)"
        )


def noise_floor_dph(captures: list[CaptureData], rate_hz: float) -> float:
    """The white-noise floor of 1-minute means, deg/h: ``block_noise_dph`` of each capture's static blocks
    (1.4826 MAD of first differences / sqrt(2)) over sqrt(blocks a minute), pooled as an RMS."""
    per_minute = 60.0 * rate_hz
    values = [block_noise_dph(c.blocks.rate_dph[c.static]) / math.sqrt(per_minute) for c in captures if c.static.any()]
    return float(np.sqrt(np.mean(np.square(values)))) if values else float("nan")


def _pooled_minute_rms(captures: list[CaptureData], residuals: list[np.ndarray], rate_hz: float) -> float:
    values = [minute_rms(r, c.static, rate_hz) for c, r in zip(captures, residuals)]
    values = [v for v in values if v == v]
    return float(np.sqrt(np.mean(np.square(values)))) if values else float("nan")


def report_for(
    models: dict[str, object],
    normalizer: Standardizer,
    fit_data: list[CaptureData],
    validate: list[CaptureData],
    rate_hz: float,
    domain: InputDomain | None = None,
    progress: Callable[[str], None] | None = None,
) -> FitReport:
    """Drift RMS before and after each model, on the fit data and the validation data (each model applied
    as the compensator applies it: inputs clamped to ``domain``, estimates bounded), and the noise floor."""
    runs = len(models) * (len(fit_data) + len(validate))
    done = [0]

    def rms_after(name, model, captures, where):
        if not captures:
            return None
        residuals = []
        for c in captures:
            if progress is not None:
                progress(f"{where} {name} on {c.path.name} ({100 * done[0] / runs:.0f} %)")
            done[0] += 1
            residuals.append(c.target_dph - applied_prediction(model, c, normalizer, domain))
        return _pooled_minute_rms(captures, residuals, rate_hz)

    before_fit = _pooled_minute_rms(fit_data, [c.target_dph for c in fit_data], rate_hz)
    before_val = _pooled_minute_rms(validate, [c.target_dph for c in validate], rate_hz) if validate else None
    rows: list[tuple[str, float, float | None]] = [("before compensation", before_fit, before_val)]
    for name, model in models.items():
        rows.append(
            (
                f"after, {name}",
                rms_after(name, model, fit_data, "applying"),
                rms_after(name, model, validate, "validating"),
            )
        )
    floor = (noise_floor_dph(fit_data, rate_hz), noise_floor_dph(validate, rate_hz) if validate else None)
    return FitReport(rows, floor)
