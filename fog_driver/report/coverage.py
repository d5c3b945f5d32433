"""How honest the drift's uncertainty is: ``drift_sigma_dph`` against a simulator's true drift.

The error the sigma describes, per whole static minute ``m`` (a minute all of whose 60 seconds are static and
have an estimate: a second with a frame flagged ``uncompensated`` has a NaN estimate, and its minute is not
scored)::

    e_m     = mean over minute m of (D_hat - D)          D_hat the estimate, D the true drift (deg/h)
    err_m   = e_m - mean of e over the static minutes    both taken relative to their means over the run
    sigma_m = mean over minute m of drift_sigma_dph      (held per 1-s model block: the mean of the
                                                          minute's block values; NaN if any is NaN)

Over the static minutes with a finite ``sigma_m`` (``coverage_figures``)::

    coverage     = fraction of minutes with |err_m| <= 1.96 sigma_m       (the +-1.96-sigma band; 95 % if honest)
    sharpness    = median(sigma_m) / RMS(err_m)       near 1: the band is as wide as the error, not padded
    top quarter  = the minutes with sigma_m >= its 75th percentile: their coverage and RMS(err_m)
    bottom       = the minutes with sigma_m <= its 25th percentile: their RMS(err_m)
    ratio        = RMS(err) top quarter / RMS(err) bottom quarter     (> 1: the sigma follows the error;
                                                                        a constant sigma gives exactly 1)
    extrapolating = the coverage on the minutes in which any frame was flagged ``extrapolating``

Ties belong to both sides of a percentile, so a constant sigma puts every minute in both quarters.  Pooling
runs or instruments (``MinuteErrors.pooled``) concatenates their minutes, each run's error taken about its
own run's mean.  ``fog-driver evaluate --truth`` and ``benchmarks/bench_population.py`` use these same
functions.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

#: The half-width of the band, in sigmas: a normal error lies within it 95 % of the time.
BAND_Z = 1.96
#: Fewer minutes with a sigma than this give no quarter figures.
MIN_QUARTER_MINUTES = 4
#: How the per-minute sigma is formed, as the reports say it.
SIGMA_PER_MINUTE = "the 1-min mean of drift_sigma_dph, held per 1-s block: the mean of the minute's 60 values"


def whole_minutes(x: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The means of ``x`` over its whole minutes (seconds ``60 m .. 60 m + 59``), and which minutes are
    entirely within ``mask`` (the static ones); a trailing part-minute is dropped."""
    n = len(x) // 60 * 60
    means = np.asarray(x[:n], dtype=float).reshape(-1, 60).mean(axis=1)
    return means, np.asarray(mask[:n], dtype=bool).reshape(-1, 60).all(axis=1)


@dataclass(frozen=True)
class MinuteErrors:
    """One run's (or a pool's) static minutes: the error, the sigma and the extrapolating flag of each."""

    error_dph: np.ndarray  #: err_m (module docstring), deg/h
    sigma_dph: np.ndarray  #: sigma_m, deg/h; NaN where the minute has no sigma
    extrapolating: np.ndarray  #: bool: a frame of the minute was flagged extrapolating

    @classmethod
    def pooled(cls, parts: Iterable[MinuteErrors]) -> MinuteErrors:
        """The minutes of several runs together (each error already about its own run's mean)."""
        parts = list(parts)
        if not parts:
            return cls(np.zeros(0), np.zeros(0), np.zeros(0, dtype=bool))
        return cls(
            np.concatenate([p.error_dph for p in parts]),
            np.concatenate([p.sigma_dph for p in parts]),
            np.concatenate([p.extrapolating for p in parts]),
        )

    def only(self, keep: np.ndarray) -> MinuteErrors:
        """The minutes where ``keep`` is true."""
        return MinuteErrors(self.error_dph[keep], self.sigma_dph[keep], self.extrapolating[keep])

    def __len__(self) -> int:
        return len(self.error_dph)


def minute_errors(
    estimate_dph: np.ndarray,
    truth_drift_dph: np.ndarray,
    sigma_dph: np.ndarray,
    static: np.ndarray,
    extrapolating: np.ndarray | None = None,
) -> MinuteErrors:
    """The static minutes' errors and sigmas (module docstring) from per-second series of equal length: the
    estimate, the true drift, the sigma (NaN where there was none) and the static and extrapolating seconds."""
    n = min(len(estimate_dph), len(truth_drift_dph), len(sigma_dph), len(static))
    error, full = whole_minutes(np.asarray(estimate_dph[:n], float) - truth_drift_dph[:n], static[:n])
    full &= np.isfinite(error)  # a minute with a second without an estimate is not scored (module docstring)
    sigma, _ = whole_minutes(sigma_dph[:n], static[:n])
    flagged = np.zeros(n, dtype=bool) if extrapolating is None else np.asarray(extrapolating[:n], dtype=bool)
    n_min = len(full) * 60
    outside = flagged[:n_min].reshape(-1, 60).any(axis=1)
    error = error[full]
    if error.size:
        error = error - error.mean()
    return MinuteErrors(error, sigma[full], outside[full])


def _rms(x: np.ndarray) -> float | None:
    return float(np.sqrt(np.mean(x * x))) if x.size else None


def _covered(m: MinuteErrors) -> float | None:
    """The fraction of ``m``'s minutes within the band; None with no minute."""
    return float(np.mean(np.abs(m.error_dph) <= BAND_Z * m.sigma_dph)) if len(m) else None


def _ratio(a: float | None, b: float | None) -> float | None:
    return None if a is None or b is None or b <= 0.0 else a / b


def _group(m: MinuteErrors) -> dict[str, Any]:
    """A group of minutes: how many, the band's coverage, the error's RMS and the median sigma (None: none)."""
    return {
        "minutes": len(m),
        "coverage": _covered(m),
        "error_rms_1min_dph": _rms(m.error_dph),
        "sigma_median_dph": float(np.median(m.sigma_dph)) if len(m) else None,
    }


def coverage_figures(minutes: MinuteErrors) -> dict[str, Any]:
    """Coverage, sharpness and how the sigma follows the error (module docstring) over the minutes with a
    finite sigma; plain numbers (None where a figure has no minute), or, with no finite sigma at all, the
    counts and a ``note`` saying so instead of numbers."""
    finite = np.isfinite(minutes.sigma_dph)
    m = minutes.only(finite)
    out: dict[str, Any] = {
        "band_z": BAND_Z,
        "sigma_per_minute": SIGMA_PER_MINUTE,
        "static_minutes": len(minutes),
        "minutes_with_sigma": len(m),
    }
    if not len(m):
        out["note"] = (
            f"no finite drift_sigma_dph in the {len(minutes)} static minutes: the model gives no uncertainty, "
            "so its coverage cannot be reported"
        )
        return out
    whole = _group(m)
    del whole["minutes"]
    out.update(whole, sharpness=_ratio(whole["sigma_median_dph"], whole["error_rms_1min_dph"]))
    if len(m) >= MIN_QUARTER_MINUTES:
        top = _group(m.only(m.sigma_dph >= np.quantile(m.sigma_dph, 0.75)))
        bottom = _group(m.only(m.sigma_dph <= np.quantile(m.sigma_dph, 0.25)))
        out["top_quarter"], out["bottom_quarter"] = top, bottom
        out["top_bottom_error_ratio"] = _ratio(top["error_rms_1min_dph"], bottom["error_rms_1min_dph"])
    else:
        out["top_quarter"] = out["bottom_quarter"] = out["top_bottom_error_ratio"] = None
    out["extrapolating"] = _group(m.only(m.extrapolating))
    return out


def _pct(x: float | None) -> str:
    return "-" if x is None else f"{100 * x:.1f} %"


def _num(x: float | None, fmt: str) -> str:
    return "-" if x is None else format(x, fmt)


def format_coverage(figures: dict[str, Any]) -> str:
    """One line of ``coverage_figures``, as ``evaluate`` prints it."""
    if "note" in figures:
        return f"uncertainty: {figures['note']}"
    top, outside = figures["top_quarter"], figures["extrapolating"]
    detail = [] if top is None else [f"the top-sigma quarter {_pct(top['coverage'])}"]
    detail.append(
        f"extrapolating {_pct(outside['coverage'])} of {outside['minutes']}"
        if outside["minutes"]
        else "none extrapolating"
    )
    return (
        f"uncertainty: the +-{figures['band_z']:g}-sigma band covers {_pct(figures['coverage'])} of "
        f"{figures['minutes_with_sigma']} static minutes ({'; '.join(detail)}); median sigma "
        f"{_num(figures['sharpness'], '.2f')}x the error's RMS; the error's RMS on the top-sigma quarter "
        f"{_num(figures['top_bottom_error_ratio'], '.2f')}x that on the bottom quarter"
    )


def coverage_markdown(figures: dict[str, Any]) -> list[str]:
    """``coverage_figures`` as report.md's lines: a sentence, and a table by group of minutes."""
    head = (
        "Uncertainty of the drift estimate against the truth: each static minute's error (the 1-min mean of "
        "estimate - true drift, about its mean over the run) against its sigma "
        f"({figures['sigma_per_minute']})"
    )
    if "note" in figures:
        return [f"{head}: {figures['note']}."]
    lines = [
        f"{head}. The +-{figures['band_z']:g}-sigma band should cover about 95 % of the minutes; the median sigma "
        f"is {_num(figures['sharpness'], '.2f')}x the error's RMS (near 1: honest, not padded); the error's RMS on "
        f"the quarter with the largest sigma is {_num(figures['top_bottom_error_ratio'], '.2f')}x that on the "
        "quarter with the smallest (above 1: the sigma follows the error).",
    ]
    if figures["minutes_with_sigma"] < figures["static_minutes"]:
        lines[0] += f" {figures['static_minutes'] - figures['minutes_with_sigma']} static minutes had no sigma."
    lines += [
        "",
        f"| minutes | count | +-{figures['band_z']:g}-sigma coverage | error RMS, deg/h | median sigma, deg/h |",
        "|---|---:|---:|---:|---:|",
    ]
    rows = [("all with a sigma", {**figures, "minutes": figures["minutes_with_sigma"]})]
    if figures["top_quarter"] is not None:
        rows += [("the quarter with the largest sigma", figures["top_quarter"])]
        rows += [("the quarter with the smallest sigma", figures["bottom_quarter"])]
    rows += [("flagged extrapolating", figures["extrapolating"])]
    for name, g in rows:
        lines.append(
            f"| {name} | {g['minutes']} | {_pct(g['coverage'])} | {_num(g['error_rms_1min_dph'], '.4f')} | "
            f"{_num(g['sigma_median_dph'], '.4f')} |"
        )
    return lines
