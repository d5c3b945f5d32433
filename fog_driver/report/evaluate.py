"""``fog-driver evaluate``: the report a calibration engineer reads before trusting a model.

For a capture and a model: the per-second measured rate and the drift the
compensator applied (the same code as ``compensate``); over the static seconds
(table motion excluded, as when fitting; and the seconds in which a frame had no drift estimate, flagged
``uncompensated``, for every model: all are scored on the same seconds, and no NaN enters a figure): the
Allan deviation before and after
with its IEEE 952 read points (``allan.py``), and the RMS of 1-minute means of
the rate (mean removed); with ``--truth`` (a simulator truth file) the drift
residual against the true drift and the noise floor, and how honest the estimate's
``drift_sigma_dph`` is against the true error (``coverage.py``: the +-1.96-sigma band's
coverage, its sharpness, and whether it follows the error); the positioning table
when the capture holds positioning sequences.  Writes ``summary.json``,
``report.md``, PNG plots and the ADEV tables (``allan-<series>.csv``) into the output folder.

Every model is labelled by its file's stem and its kind, ``default (wesn)``; each ``--compare`` model is
applied to the capture too (its drift, drift RMS and Allan curve beside the main model's).

Short stretches (``stretch_warnings``): the Allan readings rest on the longest static stretch and the
drift RMS on the static 1-minute means; a stretch under ``SHORT_STRETCH_S`` (1 h) trusts taus only up to
a tenth of it (< 360 s, short of where a FOG's bias-instability minimum usually lies, 100 s to 1000 s
and more), and fewer than ``MIN_MINUTE_MEANS`` (30) one-minute means give an RMS whose own relative
standard error, about 1 / sqrt(2 (n - 1)), exceeds 13 % (50 % from 3 means).  Both are warnings
(``summary["warnings"]``, report.md, stderr), not errors.
"""

from __future__ import annotations

import json
import logging
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from ..compensation.fitting.data import FitConfig
from ..compensation.model import ModelFile
from ..errors import UsageError
from ..extras import missing_message
from ..flags import FLAG_EXTRAPOLATING
from ..lab.chamberlog import ChamberLog
from ..offline.chamber import chamber_log_and_warnings
from ..offline.compensate import compensate_capture
from ..offline.fit import load_capture
from ..sim.capture import truth_noise_dph
from .allan import FLICKER_FLOOR, AllanResult, allan, write_csv
from .coverage import coverage_figures, coverage_markdown, minute_errors, whole_minutes

EVALUATE_WARMUP_S = 120.0
#: The report's plots, in the order ``plot`` draws them.
PLOT_NAMES = ("temperatures.png", "drift.png", "allan.png")
SHORT_STRETCH_S = 3600.0
MIN_MINUTE_MEANS = 30


def model_label(path: str | Path, model_file: ModelFile) -> str:
    """How a model is named in every table and plot: its file's stem and its kind, ``default (wesn)``."""
    return f"{Path(path).stem} ({model_file.kind})"


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
    #: the drift each ``--compare`` model applied, by label
    compared_drift_dph: dict[str, np.ndarray] = field(default_factory=dict)
    #: the mean ``drift_sigma_dph`` of each second's frames (NaN where any frame had none, or no frame came)
    drift_sigma_dph: np.ndarray | None = None
    #: the capture's chamber log (``offline.chamber.find_chamber_log``), plotted beside the thermometers
    chamber: ChamberLog | None = None

    @property
    def rate_comp_dph(self) -> np.ndarray:
        return self.rate_raw_dph - self.drift_dph


def per_second(
    capture: Path,
    model_file: ModelFile,
    *,
    force_model: bool = False,
    adapt=None,
    reference_rate_dph: float | None = None,
    progress: Callable[[int, int], None] | None = None,
    wire_format: str = "auto",
) -> Series:
    """Block-average the capture and the drift the compensator applied, per device second (adapting
    against ``reference_rate_dph`` when ``adapt``, an ``AdaptConfig``, is given); ``progress(bytes done,
    bytes in all)`` over its two passes (decoding, compensating)."""
    # 1-s blocks and the static mask (motion excluded); 2 min of warm-up is enough to evaluate
    size = Path(capture).stat().st_size if Path(capture).is_file() else 0
    data = load_capture(
        capture,
        FitConfig(warmup_s=EVALUATE_WARMUP_S),
        progress=None if progress is None else lambda done, _: progress(done, 2 * size),
        purpose="to evaluate",
        warmup_setting="evaluate's fixed warm-up",
        wire_format=wire_format,
    )
    # One row per device second, the seconds no frame arrived in (a link gap) included as NaN, not static:
    # row k is second k for the drift a model applied and for a truth file's rows too, whatever was lost.
    index = np.asarray(data.blocks.index, dtype=np.int64)
    n = int(index[-1]) + 1 if index.size else 0
    applied = drift_per_second(
        capture,
        model_file,
        n,
        force_model=force_model,
        adapt=adapt,
        reference_rate_dph=reference_rate_dph,
        progress=None if progress is None else lambda done: progress(size + done, 2 * size),
        wire_format=wire_format,
    )
    return Series(
        _on_grid(index, data.blocks.t_end_s, n, np.arange(1.0, n + 1.0)),
        _on_grid(index, data.blocks.rate_dph, n, np.nan),
        applied.drift_dph,
        _on_grid(index, data.blocks.temps_c, n, np.nan),
        _on_grid(index, data.static, n, False) & np.isfinite(applied.drift_dph),  # scored: static, estimated
        applied.extrapolating > 0,
        drift_sigma_dph=applied.drift_sigma_dph,
    )


def _on_grid(index: np.ndarray, values: np.ndarray, n: int, missing) -> np.ndarray:
    """``values`` (one per block present) on the grid of all ``n`` seconds, ``missing`` where none arrived."""
    values = np.asarray(values)
    grid = np.empty((n,) + values.shape[1:], dtype=values.dtype)
    grid[...] = missing if np.ndim(missing) == 0 else np.reshape(missing, (n,) + (1,) * (values.ndim - 1))
    grid[index] = values
    return grid


class Applied(NamedTuple):
    """What a model applied per device second (``drift_per_second``)."""

    #: the mean drift of the second's frames (0 where none came; NaN where a frame had no estimate: flagged
    #: ``uncompensated``)
    drift_dph: np.ndarray
    extrapolating: np.ndarray  #: how many of its frames were flagged extrapolating
    drift_sigma_dph: np.ndarray  #: the mean drift_sigma_dph of its frames (NaN where any is NaN, or none came)


def drift_per_second(
    capture: Path,
    model_file: ModelFile,
    n: int,
    *,
    force_model: bool = False,
    adapt=None,
    reference_rate_dph: float | None = None,
    model_name: str = "the model",
    progress: Callable[[int], None] | None = None,
    wire_format: str = "auto",
) -> Applied:
    """The mean drift a model applied in each of the capture's first ``n`` device seconds, how many of its
    frames were flagged extrapolating there, and their mean drift sigma (``progress(bytes decoded)``)."""
    sums: list[np.ndarray] = []
    sigmas: list[np.ndarray] = []
    counts: list[np.ndarray] = []
    flagged: list[np.ndarray] = []
    first = None
    for _, cols in compensate_capture(
        capture,
        model_file,
        force_model=force_model,
        model_name=model_name,
        adapt=adapt,
        reference_rate_dph=reference_rate_dph,
        progress=progress,
        wire_format=wire_format,
    ):
        if first is None:
            first = cols.t_s[0]
        second = np.floor(cols.t_s - first + 1e-9).astype(np.int64)
        sums.append(np.bincount(second, weights=cols.drift_dph))
        sigmas.append(np.bincount(second, weights=cols.drift_sigma_dph))  # NaN in, NaN out
        counts.append(np.bincount(second))
        flagged.append(np.bincount(second, weights=(cols.flags & FLAG_EXTRAPOLATING) != 0))
    drift = np.zeros(n)
    sigma = np.zeros(n)
    count = np.zeros(n)
    extrapolating = np.zeros(n)
    for s, g, c, e in zip(sums, sigmas, counts, flagged):
        m = min(len(s), n)
        drift[:m] += s[:m]
        sigma[:m] += g[:m]
        count[:m] += c[:m]
        extrapolating[:m] += e[:m]
    sigma[count == 0] = np.nan
    return Applied(drift / np.maximum(count, 1), extrapolating, sigma / np.maximum(count, 1))


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
    means, full = whole_minutes(x, mask)
    means = means[full]
    return float(np.sqrt(np.mean((means - means.mean()) ** 2))) if len(means) > 1 else float("nan")


def static_minutes(mask: np.ndarray) -> int:
    """The number of whole static minutes ``minute_rms`` averages."""
    return int(whole_minutes(np.zeros(len(mask)), mask)[1].sum())


def stretch_warnings(stretch_s: float, minutes: int) -> list[str]:
    """The short-stretch warnings (module docstring), one line each; [] when the data suffice."""
    out = []
    if stretch_s < SHORT_STRETCH_S:
        out.append(
            f"short stretch: {stretch_s:.0f} s of static data in a row (under {SHORT_STRETCH_S:.0f} s); "
            f"Allan readings above {stretch_s / 10:.0f} s untrusted, and a bias-instability minimum beyond "
            f"that cannot be reached"
        )
    if minutes < MIN_MINUTE_MEANS:
        out.append(
            f"drift RMS from {minutes} one-minute means is not reliable (under {MIN_MINUTE_MEANS}: its "
            f"relative standard error is about {100 / np.sqrt(2 * max(minutes - 1, 1)):.0f} %)"
        )
    return out


def evaluate(
    capture: Path,
    model_file: ModelFile,
    *,
    truth: dict[str, np.ndarray] | None = None,
    force_model: bool = False,
    capture_serial: str | None = None,
    label: str | None = None,
    compare: Mapping[str, ModelFile] | None = None,
    progress: Callable[[str], None] | None = None,
    wire_format: str = "auto",
) -> tuple[dict[str, Any], Series, dict[str, AllanResult]]:
    """The report's numbers: read points, drift RMS and ADEV tables of the raw rate, the rate compensated
    by ``model_file`` (named ``label``) and by each ``compare`` model (by label); ``progress(text)`` says
    which pass is running and how far it is.  ``force_model``: models fitted for another instrument serial
    are applied (``--force-model``); the summary records it with ``capture_serial`` (the capture's
    instrument, ``offline.compensate.check_model``), and report.md warns of each such model."""
    compare = dict(compare or {})
    label = label or model_file.kind
    passes = 1 + len(compare)

    def say(step: int, what: str):
        if progress is None:
            return None
        return lambda done, total: progress(f"evaluating {step}/{passes}: {what} {100.0 * done / max(total, 1):3.0f} %")

    series = per_second(
        capture,
        model_file,
        force_model=force_model,
        progress=say(1, f"decoding and compensating with {label}"),
        wire_format=wire_format,
    )
    size = Path(capture).stat().st_size if Path(capture).is_file() else 0
    for k, (name, other) in enumerate(compare.items(), start=2):
        step = say(k, f"compensating with {name}")
        series.compared_drift_dph[name] = drift_per_second(
            capture,
            other,
            len(series.t_s),
            force_model=force_model,
            model_name=f"model {name!r}",
            wire_format=wire_format,
            progress=None if step is None else lambda done, step=step: step(done, size),
        ).drift_dph
        series.static &= np.isfinite(series.compared_drift_dph[name])  # every series scored on the same seconds
    series.chamber, chamber_warnings = chamber_log_and_warnings(capture)
    stretch = longest_run(series.static)
    if stretch.stop - stretch.start < 64:
        raise UsageError(
            f"{capture}: the longest static stretch is {stretch.stop - stretch.start} s (the capture is "
            f"{len(series.t_s)} s, the first {EVALUATE_WARMUP_S:g} s excluded as warm-up); the Allan "
            f"deviation needs 64 s in a row"
        )
    rates = {"raw": series.rate_raw_dph, "compensated": series.rate_comp_dph}
    rates.update({name: series.rate_raw_dph - d for name, d in series.compared_drift_dph.items()})
    allans = {name: allan(rate[stretch]) for name, rate in rates.items()}
    summary: dict[str, Any] = {
        "capture": str(capture),
        "capture_serial": capture_serial,
        "force_model": force_model,
        "model": {
            "kind": model_file.kind,
            "label": label,
            "instrument_serial": model_file.instrument_serial,
            "created_utc": model_file.created_utc,
        },
        "compared": {name: {"kind": m.kind, "instrument_serial": m.instrument_serial} for name, m in compare.items()},
        "seconds": int(len(series.t_s)),
        "static_seconds": int(series.static.sum()),
        "allan_stretch_s": [int(stretch.start), int(stretch.stop)],
        "extrapolating_seconds": int(series.extrapolating.sum()),
        "static_minutes": static_minutes(series.static),
        "warnings": stretch_warnings(stretch.stop - stretch.start, static_minutes(series.static)) + chamber_warnings,
    }
    if series.chamber is not None and series.chamber.path is not None:
        summary["chamber_log"] = str(series.chamber.path)
    for name, rate in rates.items():
        summary[name] = {**allans[name].read_points(), "drift_rms_1min_dph": minute_rms(rate, series.static)}
    summary["allan"] = {name: a.table() for name, a in allans.items()}
    if truth is not None:
        n = min(len(truth["drift_dph"]), len(series.t_s))
        mask = series.static[:n]
        sigma = series.drift_sigma_dph if series.drift_sigma_dph is not None else np.full(n, np.nan)
        summary["truth"] = {
            "drift_rms_1min_dph": minute_rms(truth["drift_dph"][:n], mask),
            "residual_rms_1min_dph": minute_rms(truth["drift_dph"][:n] - series.drift_dph[:n], mask),
            "noise_floor_rms_1min_dph": minute_rms(truth_noise_dph(truth)[:n], mask),
            "sigma": coverage_figures(
                minute_errors(
                    series.drift_dph[:n],
                    truth["drift_dph"][:n],
                    sigma[:n],
                    mask,
                    series.extrapolating[:n] if series.extrapolating is not None else None,
                )
            ),
        }
    return summary, series, allans


def report_file_names(compared: list[str]) -> list[str]:
    """The files ``write_report`` writes into its folder, with ``compared`` the labels of the ``--compare``
    models: report.md, summary.json, the plots and an ADEV table per series."""
    series = ["raw", "compensated", *compared]
    return ["report.md", "summary.json", *PLOT_NAMES, *(csv_name(name) for name in series)]


def other_instruments(summary: dict[str, Any]) -> list[tuple[str, str]]:
    """(label, serial) of every model in the report fitted for another instrument than the capture's (applied
    with ``--force-model``); [] when the capture's serial is unknown."""
    serial = summary.get("capture_serial")
    if serial is None:
        return []
    model = summary["model"]
    models = [(model.get("label", model["kind"]), model["instrument_serial"])]
    models += [(name, m["instrument_serial"]) for name, m in summary.get("compared", {}).items()]
    return [(label, s) for label, s in models if s != serial]


def series_names(summary: dict[str, Any]) -> list[str]:
    """The summary's series in order: raw, compensated, then each compared model's label."""
    return ["raw", "compensated", *summary.get("compared", {})]


def series_title(summary: dict[str, Any], name: str) -> str:
    """A column title: "raw", "compensated, default (wesn)", "m-default (polynomial)"."""
    if name == "compensated":
        return f"compensated, {summary['model'].get('label', summary['model']['kind'])}"
    return name


def csv_name(name: str) -> str:
    """``allan-<series>.csv``: the series name with anything but letters, digits, '-' and '_' as '-'."""
    return "allan-" + re.sub(r"[^A-Za-z0-9_-]+", "-", name).strip("-") + ".csv"


def format_bias_instability(points: dict) -> str:
    """``0.00812 deg/h (floor at 256 s)`` or ``< 0.00812 deg/h (minimum not reached: upper bound)``."""
    value = points["bias_instability_dph"]
    if points["bias_instability_bound"] == "upper bound":
        return f"< {value:.5f} deg/h (minimum not reached: upper bound)"
    return f"{value:.5f} deg/h (floor at {points['bias_instability_tau_s']:g} s)"


def _reading(value: float | None, fmt: str) -> str:
    return "not reached" if value is None else format(value, fmt)


def plot(
    series: Series, allans: dict[str, AllanResult], out_dir: Path, titles: Mapping[str, str] | None = None
) -> list[Path]:
    """The report's PNGs (matplotlib, Agg: no display needed); ``titles``: each series' legend name."""
    # matplotlib's own warnings (its font cache not saved on a full disk, say) are not the report's: errors only
    logging.getLogger("matplotlib").setLevel(logging.ERROR)
    try:
        import matplotlib  # optional extra: report

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt  # optional extra: report
    except ImportError:
        raise UsageError(missing_message("report", "the report's plots", ["matplotlib"])) from None
    titles = dict(titles or {})
    minutes = series.t_s / 60.0
    figures = (
        _plot_temperatures(plt, series, minutes),
        _plot_drift(plt, series, minutes, titles),
        _plot_allan(plt, allans, titles),
    )
    return [_save(figure, out_dir / name) for figure, name in zip(figures, PLOT_NAMES)]


def chamber_minutes(log: ChamberLog, first_t_s: float) -> tuple[np.ndarray, str]:
    """Where a chamber log's rows go on the report's time axis (device minutes), and what that axis is for them:
    ``device_t_s`` (the gyro's device time of the last frame at each row, ``calibrate``'s and the daemon's logs)
    where the log has it, rows without it left out; else (a ``chamber run`` log) the host time, its first row at
    the capture's first second (``first_t_s``): the two clocks are aligned at the start only."""
    device = log.device_t_s
    if np.isfinite(device).any():
        return device / 60.0, "device time"
    host = log.utc_s
    return (host - host[0] + first_t_s) / 60.0, "host time, aligned at the start"


def _plot_temperatures(plt: Any, series: Series, minutes: np.ndarray) -> Any:
    """The three thermometers over the run, and the chamber's set point and air where the capture has a chamber
    log (``chamber_minutes``: on the device time axis)."""
    fig, ax = plt.subplots(figsize=(9, 4))
    for k, name in enumerate(("ring top", "ring bottom", "housing")):
        ax.plot(minutes, series.temps_c[:, k], label=name, lw=1)
    log = series.chamber
    if log is not None and log.rows:
        x, axis = chamber_minutes(log, float(series.t_s[0]) if len(series.t_s) else 0.0)
        ax.plot(x, log.setpoint_c, label=f"chamber set point ({axis})", lw=1, ls="--", color="0.35")
        ax.plot(x, log.air_c, label=f"chamber air ({axis})", lw=1, color="0.1")
    ax.set(xlabel="time, min", ylabel="temperature, degC", title="Thermometers")
    ax.grid(alpha=0.3)
    ax.legend()
    return fig


def _plot_drift(plt: Any, series: Series, minutes: np.ndarray, titles: dict[str, str]) -> Any:
    """The raw rate's static 1-min means, each model's estimated drift and the rate it leaves, on one baseline:
    each curve less its own median over the static minutes (the raw rate's holds Earth rate and the bias, which
    no temperature model estimates), so a drift estimate lies on the raw rate where it is right and the
    compensated rate stays at 0.  The legend sits below the axes, clear of the data."""
    n = len(series.t_s) // 60 * 60
    mm = minutes[:n].reshape(-1, 60).mean(axis=1)

    def per_min(x: np.ndarray) -> np.ndarray:
        return x[:n].reshape(-1, 60).mean(axis=1)

    static_min = series.static[:n].reshape(-1, 60).all(axis=1)

    def on_baseline(x: np.ndarray) -> np.ndarray:
        return x - (np.nanmedian(x[static_min]) if static_min.any() else 0.0)

    fig, ax = plt.subplots(figsize=(9, 5.5), layout="constrained")
    ax.plot(mm[static_min], on_baseline(per_min(series.rate_raw_dph))[static_min], ".", ms=3, label="raw rate")
    drifts = {"compensated": series.drift_dph, **series.compared_drift_dph}
    for name, drift in drifts.items():
        ax.plot(mm, on_baseline(per_min(drift)), lw=1.5, label=f"estimated drift, {titles.get(name, name)}")
    for name, drift in drifts.items():
        comp = on_baseline(per_min(series.rate_raw_dph - drift))
        ax.plot(mm[static_min], comp[static_min], ".", ms=3, label=f"compensated rate, {titles.get(name, name)}")
    ax.axhline(0.0, color="0.5", lw=0.8)
    ax.set(
        xlabel="time, min",
        ylabel="deg/h, less each curve's static median",
        title="Drift before and after compensation (1-min means of the static minutes)",
    )
    ax.grid(alpha=0.3)
    fig.legend(loc="outside lower center", ncol=2, fontsize=8)
    return fig


def _plot_allan(plt: Any, allans: dict[str, AllanResult], titles: dict[str, str]) -> Any:
    """The Allan deviations with their 68 % intervals, the points read (ARW, bias instability) and the fitted
    lines; past the trust limit hollow, dashed and faded."""
    fig, ax = plt.subplots(figsize=(7.5, 6))
    for name, a in allans.items():
        ok = a.trusted
        err = np.vstack([a.sigma_dph - a.lo_dph, a.hi_dph - a.sigma_dph])
        bi = a.bias_instability_dph
        reading = f"B {bi:.4f} deg/h" if a.minimum_reached else f"B < {bi:.4f} deg/h: minimum not reached, upper bound"
        line = ax.errorbar(
            a.tau_s[ok],
            a.sigma_dph[ok],
            yerr=err[:, ok],
            fmt="o-",
            ms=3,
            capsize=2,
            lw=1,
            label=f"{titles.get(name, name)} ({reading})",
        )
        color = line[0].get_color()
        tail = np.flatnonzero(ok)[-1:].tolist() + np.flatnonzero(~ok).tolist()
        if (~ok).any():  # past the trust limit: hollow, dashed, faded; never read
            ax.errorbar(
                a.tau_s[tail],
                a.sigma_dph[tail],
                yerr=err[:, tail],
                fmt="o--",
                ms=4,
                mfc="none",
                capsize=2,
                lw=1,
                color=color,
                alpha=0.45,
            )
        if a.arw_deg_per_rt_h is not None:
            ax.plot([1.0], [a.arw_deg_per_rt_h * 60.0], "s", color=color, ms=9, mfc="none")
        if a.minimum_reached:
            ax.plot([a.bias_instability_tau_s], [bi * FLICKER_FLOOR], "D", color=color, ms=9, mfc="none")
        else:
            ax.plot([a.bias_instability_tau_s], [bi * FLICKER_FLOOR], "v", color=color, ms=10, mfc="none")
        for region, (t0, t1) in a.regions.items():
            if region == "arw":
                continue
            taus = np.geomspace(t0, t1, 8)
            ax.loglog(taus, a.line_dph(region, taus), ":", color=color, lw=2)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set(
        xlabel="tau, s",
        ylabel="Allan deviation, deg/h",
        title="Allan deviation with 68 % intervals; hollow, dashed: tau above a tenth of the stretch (not read)\n"
        "squares: ARW read at 1 s; diamonds: bias-instability floor; triangles: its upper bound\n"
        "(minimum not reached); dotted: the fitted RRW, rate-ramp and quantization lines",
    )
    ax.title.set_fontsize(8)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    return fig


def _save(fig, path: Path) -> Path:
    if fig.get_layout_engine() is None:  # the drift plot lays itself out (its legend below the axes)
        fig.tight_layout()
    fig.savefig(path, dpi=110)
    import matplotlib.pyplot as plt  # optional extra: report (loaded by plot already)

    plt.close(fig)
    return path


def markdown(summary: dict[str, Any], plots: list[Path], positioning_md: str | None, tables: list[Path] = ()) -> str:
    names = series_names(summary)
    cols = [summary[n] for n in names]
    model = summary["model"]
    lines = [
        f"# Compensation report: {Path(summary['capture']).name}",
        "",
        f"Model: `{model.get('label', model['kind'])}` for {model['instrument_serial']} "
        f"(fitted {model['created_utc']}). {summary['seconds']:,} s of data, "
        f"{summary['static_seconds']:,} s static (table motion excluded). The model ran outside its fit range "
        f"(inputs clamped or estimate clipped) for {summary['extrapolating_seconds']:,} s.",
        "",
    ]
    others = other_instruments(summary)
    if others:
        fitted = ", ".join(f"`{label}` for {serial}" for label, serial in others)
        lines += [
            f"**Warning: models of another instrument, applied with --force-model to this capture of "
            f"{summary['capture_serial']}: {fitted}.**",
            "",
        ]
    for warning in summary.get("warnings", []):
        lines += [f"**Warning: {warning}.**", ""]
    start, stop = summary["allan_stretch_s"]
    raw = summary["raw"]
    lines += [
        f"Allan deviation over the longest static stretch, {start:,} s to {stop:,} s ({stop - start:,} s): read "
        f'only at tau <= {raw["trusted_tau_max_s"]:g} s (a tenth of it); "not reached": the curve shows no '
        "region of that slope there (IEEE 952 read points, `fog_driver/report/allan.py`).",
        "",
        "| | " + " | ".join(series_title(summary, n) for n in names) + " |",
        "|---|" + "---|" * len(names),
        "| angle random walk N, deg/sqrt(h) | "
        + " | ".join(_reading(c["arw_deg_per_rt_h"], ".5f") for c in cols)
        + " |",
        "| bias instability B | " + " | ".join(format_bias_instability(c) for c in cols) + " |",
        "| rate random walk K, deg/h/sqrt(h) | "
        + " | ".join(_reading(c["rrw_dph_per_rt_h"], ".5f") for c in cols)
        + " |",
        "| rate ramp R, deg/h/h | " + " | ".join(_reading(c["rate_ramp_dph_per_h"], ".5f") for c in cols) + " |",
        "| quantization Q, arcsec | " + " | ".join(_reading(c["quantization_arcsec"], ".4f") for c in cols) + " |",
        f"| drift RMS of {summary.get('static_minutes', 0)} 1-min means, deg/h | "
        + " | ".join(f"{c['drift_rms_1min_dph']:.4f}" for c in cols)
        + " |",
        "",
    ]
    if tables:
        lines += [
            "The full ADEV tables (tau, ADEV, 68 % interval, pairs, EDF, noise type, trusted): "
            + ", ".join(f"[{p.name}]({p.name})" for p in tables)
            + ".",
            "",
        ]
    if "truth" in summary:
        t = summary["truth"]
        lines += [
            "Against the simulator's truth (1-min means, deg/h): true drift "
            f"{t['drift_rms_1min_dph']:.4f}, residual after compensation {t['residual_rms_1min_dph']:.4f}, "
            f"noise floor {t['noise_floor_rms_1min_dph']:.4f}.",
            "",
            *coverage_markdown(t["sigma"]),
            "",
        ]
    lines += [
        "## Positioning accuracy",
        "",
        positioning_md or "No positioning sequences in this capture: the table is skipped.",
        "",
    ]
    lines += ["## Plots", ""] + [f"![{p.stem}]({p.name})" for p in plots] + [""]
    return "\n".join(lines)


def write_report(out_dir: Path, summary: dict[str, Any], series: Series, allans, positioning_md: str | None) -> Path:
    """report.md, summary.json, the plots and ``allan-<series>.csv`` for every series into ``out_dir``."""
    out_dir.mkdir(parents=True, exist_ok=True)
    titles = {n: series_title(summary, n) for n in allans}
    plots = plot(series, allans, out_dir, titles)
    tables = [write_csv(out_dir / csv_name(name), a) for name, a in allans.items()]
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    report = out_dir / "report.md"
    report.write_text(markdown(summary, plots, positioning_md, tables))
    return report
