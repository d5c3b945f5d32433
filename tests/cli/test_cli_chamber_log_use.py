"""A capture with a chamber log beside it: ``fit`` says when the program did not run as designed, ``evaluate``
plots the set point and the air beside the gyro's thermometers."""

from __future__ import annotations

import datetime as _dt
import json
import shutil
from pathlib import Path

import numpy as np
import yaml
from cli_run import run_cli

from fog_driver.lab.chamberlog import ChamberLogWriter, LogHeader, LogRow, format_utc, read_chamber_log

DATA = Path(__file__).resolve().parents[1] / "data"
T0 = _dt.datetime(2026, 12, 7, 12, 0, tzinfo=_dt.UTC)


def _capture(tmp_path: Path) -> Path:
    for name in ("sim-short.bin", "sim-short.bin.yaml"):
        shutil.copy(DATA / name, tmp_path / name)
    return tmp_path / "sim-short.bin"


def _log(path: Path, t_s, program_c, air_c, device_t_s=None) -> None:
    with ChamberLogWriter(path, LogHeader("p", "0" * 64, "sim://", "run", None)) as log:
        for k, t in enumerate(t_s):
            device = None if device_t_s is None else float(device_t_s[k])
            utc = format_utc(T0 + _dt.timedelta(seconds=float(t)))
            log.write(
                LogRow(utc, float(t), device, float(program_c[k]), float(air_c[k]), "running", float(program_c[k]), 0)
            )


def _fit(tmp_path: Path, capture: Path):
    """``fit`` of ``capture`` (a polynomial, weak accepted: the capture is short): the model's path and the run."""
    (tmp_path / "fit.yaml").write_text("warmup_s: 30\n")
    out = tmp_path / "m.yaml"
    proc = run_cli(
        "fit",
        str(capture),
        "--config",
        str(tmp_path / "fit.yaml"),
        "--accept-weak-fit",
        "--kind",
        "polynomial",
        "--out",
        str(out),
    )
    assert proc.returncode == 0, proc.stderr
    return out, proc


def test_fit_of_a_capture_whose_chamber_ramped_at_half_the_designed_rate_warns_and_records_it(tmp_path):
    capture = _capture(tmp_path)
    t = np.arange(0.0, 7200.0, 30.0)
    program_c = np.minimum(20.0 + t / 60.0, 80.0)  # 1 degC/min to 80
    air_c = np.minimum(20.0 + t / 120.0, 80.0)  # the chamber managed 0.5 degC/min
    _log(tmp_path / "sim-short.chamber.csv", t, program_c, air_c)
    out, proc = _fit(tmp_path, capture)
    lines = [line for line in proc.stdout.splitlines() if "did not run its program as designed" in line]
    assert len(lines) == 1 and lines[0].startswith(f"warning: {capture}: the chamber")
    assert "ramps run at their rates" in lines[0]
    recorded = yaml.safe_load(out.read_text())["provenance"]["chamber_warnings"]
    assert recorded == [lines[0].removeprefix("warning: ")]


def test_fit_of_a_capture_whose_chamber_followed_its_program_says_nothing_of_it(tmp_path):
    capture = _capture(tmp_path)
    t = np.arange(0.0, 7200.0, 30.0)
    program_c = np.minimum(20.0 + t / 60.0, 80.0)
    _log(tmp_path / "sim-short.chamber.csv", t, program_c, program_c - 1.0)
    out, proc = _fit(tmp_path, capture)
    assert "chamber" not in proc.stdout
    assert "chamber_warnings" not in yaml.safe_load(out.read_text())["provenance"]


def test_evaluate_plots_the_chamber_beside_the_thermometers_on_the_device_time(tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from fog_driver.report.evaluate import Series, _plot_temperatures

    capture = _capture(tmp_path)
    named = tmp_path / "logs" / "chamber.csv"
    named.parent.mkdir()
    t = np.arange(0.0, 300.0, 10.0)
    device_t_s = 580.0 + t
    _log(named, t, np.full(t.size, 20.0), 20.0 + t / 1000.0, device_t_s)
    sidecar = tmp_path / "sim-short.bin.yaml"
    doc = yaml.safe_load(sidecar.read_text())
    doc["chamber_log"] = "logs/chamber.csv"
    sidecar.write_text(yaml.safe_dump(doc, sort_keys=False))
    model, _ = _fit(tmp_path, capture)
    proc = run_cli("evaluate", str(capture), "--model", str(model), "--out", str(tmp_path / "report"))
    assert proc.returncode == 0, proc.stderr
    summary = json.loads((tmp_path / "report" / "summary.json").read_text())
    assert summary["chamber_log"] == str(named)
    assert (tmp_path / "report" / "temperatures.png").stat().st_size > 0
    # the figure's lines: the chamber's on the device time axis, in minutes
    n = 3
    series = Series(
        np.arange(580.0, 580.0 + n),
        np.zeros(n),
        np.zeros(n),
        np.full((n, 3), 20.0),
        np.ones(n, bool),
        chamber=read_chamber_log(named),
    )
    fig = _plot_temperatures(plt, series, series.t_s / 60.0)
    lines = {line.get_label(): line for line in fig.axes[0].get_lines()}
    air = lines["chamber air (device time)"]
    np.testing.assert_allclose(air.get_xdata(), device_t_s / 60.0)
    np.testing.assert_allclose(air.get_ydata(), 20.0 + t / 1000.0)
    np.testing.assert_allclose(lines["chamber set point (device time)"].get_ydata(), 20.0)
    plt.close(fig)
