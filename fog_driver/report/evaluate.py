"""``fog-driver evaluate``: the report a calibration engineer reads before trusting a model.

For a capture and a model: the per-second measured rate and the drift the
compensator applied (the same code as ``compensate``); over the static seconds
(table motion excluded, as when fitting): the Allan deviation before and after
with its IEEE 952 read points (``allan.py``), and the RMS of 1-minute means of
the rate (mean removed); with ``--truth`` (a simulator truth file) the drift
residual against the true drift and the noise floor; the positioning table
when the capture holds positioning sequences.  Writes ``summary.json``,
``report.md`` and PNG plots into the output folder.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..compensation.apply import compensate_capture
from ..compensation.domain import FLAG_EXTRAPOLATING
from ..compensation.fit import FitConfig, load_capture
from ..compensation.model import ModelFile
from ..errors import UsageError
from ..extras import missing_message
from ..sim.capture import truth_noise_dph
from .allan import AllanResult, allan

EVALUATE_WARMUP_S = 120.0


@dataclass
class Series:
    """Per-device-second series of a capture (index = second since the first sample)."""

    t_s: np.ndarray
    rate_raw_dph: np.ndarray
    drift_dph: np.ndarray
    temps_c: np.ndarray  #: (n, 3)
    static: np.ndarray
    #: seconds in which a frame was flagged ``extrapolating`` (the model outside its fit range)
    extrapolating: np.ndarray | None = None

    @property
    def rate_comp_dph(self) -> np.ndarray:
        return self.rate_raw_dph - self.drift_dph


def per_second(capture: Path, model_file: ModelFile, *, force: bool = False, adapt=None,
               reference_rate_dph: float | None = None) -> Series:  # fmt: skip
    """Block-average the capture and the drift the compensator applied, per device second (adapting
    against ``reference_rate_dph`` when ``adapt``, an ``AdaptConfig``, is given)."""
    # 1-s blocks and the static mask (motion excluded); 2 min of warm-up is enough to evaluate
    data = load_capture(capture, FitConfig(warmup_s=EVALUATE_WARMUP_S), purpose="to evaluate",
                        warmup_setting="evaluate's fixed warm-up")  # fmt: skip
    sums: list[np.ndarray] = []
    counts: list[np.ndarray] = []
    flagged: list[np.ndarray] = []
    first = None
    for _, cols in compensate_capture(capture, model_file, force=force, model_name="the model", adapt=adapt,
                                      reference_rate_dph=reference_rate_dph):  # fmt: skip
        if first is None:
            first = cols.t_s[0]
        second = np.floor(cols.t_s - first + 1e-9).astype(np.int64)
        sums.append(np.bincount(second, weights=cols.drift_dph))
        counts.append(np.bincount(second))
        flagged.append(np.bincount(second, weights=(cols.flags & FLAG_EXTRAPOLATING) != 0))
    n = len(data.blocks)
    drift = np.zeros(n)
    count = np.zeros(n)
    extrapolating = np.zeros(n)
    for s, c, e in zip(sums, counts, flagged):
        m = min(len(s), n)
        drift[:m] += s[:m]
        count[:m] += c[:m]
        extrapolating[:m] += e[:m]
    drift = drift / np.maximum(count, 1)
    return Series(data.blocks.t_end_s, data.blocks.rate_dph, drift, data.blocks.temps_c, data.static, extrapolating > 0)


def longest_run(mask: np.ndarray) -> slice:
    """The longest stretch of consecutive True values."""
    best, start, best_slice = 0, None, slice(0, 0)
    for i, v in enumerate(np.r_[mask, False]):
        if v and start is None:
            start = i
        elif not v and start is not None:
            if i - start > best:
                best, best_slice = i - start, slice(start, i)
            start = None
    return best_slice


def minute_rms(x: np.ndarray, mask: np.ndarray) -> float:
    """RMS of the means of whole static minutes, their mean removed."""
    n = len(x) // 60 * 60
    full = mask[:n].reshape(-1, 60).all(axis=1)
    means = x[:n].reshape(-1, 60).mean(axis=1)[full]
    return float(np.sqrt(np.mean((means - means.mean()) ** 2))) if len(means) > 1 else float("nan")


def evaluate(capture: Path, model_file: ModelFile, *, truth: dict[str, np.ndarray] | None = None,
             force: bool = False) -> tuple[dict[str, Any], Series, dict[str, AllanResult]]:  # fmt: skip
    series = per_second(capture, model_file, force=force)
    stretch = longest_run(series.static)
    if stretch.stop - stretch.start < 64:
        raise UsageError(f"{capture}: the longest static stretch is {stretch.stop - stretch.start} s (the capture is "
                         f"{len(series.t_s)} s, the first {EVALUATE_WARMUP_S:g} s excluded as warm-up); the Allan "
                         f"deviation needs 64 s in a row")  # fmt: skip
    allans = {"raw": allan(series.rate_raw_dph[stretch]), "compensated": allan(series.rate_comp_dph[stretch])}
    summary: dict[str, Any] = {
        "capture": str(capture),
        "model": {"kind": model_file.kind, "instrument_serial": model_file.instrument_serial,
                  "created_utc": model_file.created_utc},  # fmt: skip
        "seconds": int(len(series.t_s)),
        "static_seconds": int(series.static.sum()),
        "allan_stretch_s": [int(stretch.start), int(stretch.stop)],
        "extrapolating_seconds": int(series.extrapolating.sum()),
    }
    for name, rate in (("raw", series.rate_raw_dph), ("compensated", series.rate_comp_dph)):
        a = allans[name]
        summary[name] = {
            "arw_deg_sqrt_h": a.arw_deg_sqrt_h,
            "bias_instability_dph": a.bias_instability_dph,
            "bias_instability_tau_s": a.bias_instability_tau_s,
            "drift_rms_1min_dph": minute_rms(rate, series.static),
        }
    if truth is not None:
        n = min(len(truth["drift_dph"]), len(series.t_s))
        mask = series.static[:n]
        summary["truth"] = {
            "drift_rms_1min_dph": minute_rms(truth["drift_dph"][:n], mask),
            "residual_rms_1min_dph": minute_rms(truth["drift_dph"][:n] - series.drift_dph[:n], mask),
            "noise_floor_rms_1min_dph": minute_rms(truth_noise_dph(truth)[:n], mask),
        }
    return summary, series, allans


def plot(series: Series, allans: dict[str, AllanResult], out_dir: Path) -> list[Path]:
    """The report's PNGs (matplotlib, Agg: no display needed)."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise UsageError(missing_message("report", "the report's plots", ["matplotlib"])) from None
    minutes = series.t_s / 60.0
    paths = []

    fig, ax = plt.subplots(figsize=(9, 4))
    for k, name in enumerate(("ring top", "ring bottom", "housing")):
        ax.plot(minutes, series.temps_c[:, k], label=name, lw=1)
    ax.set(xlabel="time, min", ylabel="temperature, degC", title="Thermometers")
    ax.grid(alpha=0.3)
    ax.legend()
    paths.append(_save(fig, out_dir / "temperatures.png"))

    n = len(series.t_s) // 60 * 60
    mm = minutes[:n].reshape(-1, 60).mean(axis=1)

    def per_min(x: np.ndarray) -> np.ndarray:
        return x[:n].reshape(-1, 60).mean(axis=1)

    static_min = series.static[:n].reshape(-1, 60).all(axis=1)
    raw = per_min(series.rate_raw_dph)
    comp = per_min(series.rate_comp_dph)
    offset = np.median(raw[static_min]) if static_min.any() else 0.0
    fig, ax = plt.subplots(figsize=(9, 4))
    ax.plot(mm[static_min], raw[static_min] - offset, ".", ms=3, label="raw rate (1-min means, median removed)")
    ax.plot(mm, per_min(series.drift_dph), lw=1.5, label="estimated drift")
    ax.plot(mm[static_min], comp[static_min] - offset, ".", ms=3, label="compensated rate (same offset)")
    ax.set(xlabel="time, min", ylabel="deg/h", title="Drift before and after compensation (static minutes)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    paths.append(_save(fig, out_dir / "drift.png"))

    fig, ax = plt.subplots(figsize=(6.5, 5))
    for name, a in allans.items():
        line = ax.loglog(a.tau_s, a.sigma_dph, "o-", ms=3, label=name)[0]
        ax.loglog([1.0], [a.arw_deg_sqrt_h * 60.0], "s", color=line.get_color(), ms=8, mfc="none")
        ax.loglog([a.bias_instability_tau_s], [a.bias_instability_dph * 0.664], "D", color=line.get_color(), ms=8,
                  mfc="none")  # fmt: skip
    ax.set(xlabel="tau, s", ylabel="Allan deviation, deg/h",
           title="Allan deviation (squares: ARW read at 1 s; diamonds: bias-instability floor)")  # fmt: skip
    ax.title.set_fontsize(9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    paths.append(_save(fig, out_dir / "allan.png"))
    return paths


def _save(fig, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    import matplotlib.pyplot as plt

    plt.close(fig)
    return path


def markdown(summary: dict[str, Any], plots: list[Path], positioning_md: str | None) -> str:
    raw, comp = summary["raw"], summary["compensated"]
    lines = [
        f"# Compensation report: {Path(summary['capture']).name}",
        "",
        f"Model: `{summary['model']['kind']}` for {summary['model']['instrument_serial']} "
        f"(fitted {summary['model']['created_utc']}). {summary['seconds']:,} s of data, "
        f"{summary['static_seconds']:,} s static (table motion excluded). The model ran outside its fit range "
        f"(inputs clamped or estimate clipped) for {summary['extrapolating_seconds']:,} s.",
        "",
        "| | raw | compensated |",
        "|---|---|---|",
        f"| angle random walk, deg/sqrt(h) | {raw['arw_deg_sqrt_h']:.5f} | {comp['arw_deg_sqrt_h']:.5f} |",
        f"| bias instability, deg/h | {raw['bias_instability_dph']:.5f} | {comp['bias_instability_dph']:.5f} |",
        f"| drift RMS of 1-min means, deg/h | {raw['drift_rms_1min_dph']:.4f} | {comp['drift_rms_1min_dph']:.4f} |",
        "",
    ]
    if "truth" in summary:
        t = summary["truth"]
        lines += [
            "Against the simulator's truth (1-min means, deg/h): true drift "
            f"{t['drift_rms_1min_dph']:.4f}, residual after compensation {t['residual_rms_1min_dph']:.4f}, "
            f"noise floor {t['noise_floor_rms_1min_dph']:.4f}.",
            "",
        ]
    lines += ["## Positioning accuracy", "", positioning_md or "No positioning sequences in this capture: the table is skipped.", ""]
    lines += ["## Plots", ""] + [f"![{p.stem}]({p.name})" for p in plots] + [""]
    return "\n".join(lines)


def write_report(out_dir: Path, summary: dict[str, Any], series: Series, allans, positioning_md: str | None) -> Path:
    out_dir.mkdir(parents=True, exist_ok=True)
    plots = plot(series, allans, out_dir)
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    report = out_dir / "report.md"
    report.write_text(markdown(summary, plots, positioning_md))
    return report
