"""fog-driver evaluate: Allan read points against the simulator, the report folder, errors."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from fog_driver.daemon.config import DEFAULT_MODEL
from fog_driver.report.allan import allan

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT / "tests" / "data"


def test_allan_read_points_on_synthetic_white_noise():
    rng = np.random.default_rng(0)
    arw = 0.003  # deg/sqrt(h): 1-s std of 0.18 deg/h
    result = allan(rng.normal(0.0, arw * 60.0, 20000))
    assert result.arw_deg_per_rt_h == pytest.approx(arw, rel=0.03)
    assert result.bias_instability_tau_s <= 2000  # read within a tenth of the record


def test_evaluate_measures_the_simulators_arw_within_10_percent(tmp_path):
    from fog_driver.lab.profiles import load_profile
    from fog_driver.sim.capture import simulate_to_file
    from fog_driver.sim.instrument import Simulator

    capture = tmp_path / "run.bin"
    simulate_to_file(
        Simulator(load_profile(ROOT / "configs" / "profiles" / "short-test.yaml"), rate_hz=20, seed=4), capture
    )
    out = tmp_path / "report"
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "fog_driver",
            "evaluate",
            str(capture),
            "--model",
            str(DEFAULT_MODEL),
            "--out",
            str(out),
            "--json",
            "--truth",
            str(capture.with_suffix(".truth.csv")),
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(proc.stdout)
    assert summary == json.loads((out / "summary.json").read_text())
    for side in ("raw", "compensated"):
        assert set(summary[side]) >= {"arw_deg_per_rt_h", "bias_instability_dph", "drift_rms_1min_dph"}
    assert summary["raw"]["arw_deg_per_rt_h"] == pytest.approx(0.003, rel=0.10)  # the configured ARW
    assert summary["truth"]["residual_rms_1min_dph"] < summary["truth"]["drift_rms_1min_dph"]
    for name in ("temperatures.png", "drift.png", "allan.png"):
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and (out / name).stat().st_size > 10000
    report = (out / "report.md").read_text()
    assert "angle random walk" in report and "![allan](allan.png)" in report
    assert "No positioning sequences in this capture: the table is skipped." in report
    again = subprocess.run(
        [
            sys.executable,
            "-m",
            "fog_driver",
            "evaluate",
            str(capture),
            "--model",
            str(DEFAULT_MODEL),
            "--out",
            str(out),
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert again.returncode == 73 and "refusing to overwrite" in again.stderr


def test_missing_extra_is_a_one_line_hint(monkeypatch):
    import builtins

    from fog_driver.errors import UsageError
    from fog_driver.report import allan as allan_module

    real_import = builtins.__import__

    def no_allantools(name, *args, **kwargs):
        if name == "allantools":
            raise ImportError("No module named 'allantools'")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_allantools)
    with pytest.raises(UsageError, match=r"in the project's virtual environment: pip install -e '\.\[report\]'"):
        allan_module.allan(np.zeros(100))


def test_evaluate_refuses_another_instruments_model(tmp_path):
    import yaml

    doc = yaml.safe_load(DEFAULT_MODEL.read_text())
    doc["instrument_serial"] = "FOG-OTHER-0001"
    other = tmp_path / "other.yaml"
    other.write_text(yaml.safe_dump(doc))
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "fog_driver",
            "evaluate",
            str(DATA / "sim-short.bin"),
            "--model",
            str(other),
            "--out",
            str(tmp_path / "r"),
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 64 and "FOG-OTHER-0001" in proc.stderr and "Traceback" not in proc.stderr


def test_a_link_gap_never_shifts_the_seconds_against_the_drift_or_the_truth(tmp_path):
    """The series held one row per second that had frames, the drift and the truth one row per device second:
    after a 15-min link gap every later second was compared with the drift of 900 s later (the compensated
    1-min drift RMS read 0.128 deg/h against 0.027 without the gap, the truth residual 0.157 against 0.016).
    Now the seconds without frames are rows of their own (NaN, not static): the gap changes the figures only
    by the minutes it removes."""
    from fog_driver.lab.profiles import load_profile
    from fog_driver.modelfiles import load_model
    from fog_driver.report.evaluate import evaluate, per_second
    from fog_driver.sim.capture import read_truth, simulate_to_file
    from fog_driver.sim.faults import parse_fault_spec
    from fog_driver.sim.instrument import Simulator

    model = load_model(DEFAULT_MODEL)
    summaries = {}
    for name, faults in (("clean", ""), ("gap", "disconnect=3000:900")):
        capture = tmp_path / f"{name}.bin"
        sim = Simulator(
            load_profile(ROOT / "configs" / "profiles" / "fast-ramps.yaml"),
            rate_hz=10,
            seed=2,
            faults=parse_fault_spec(faults) if faults else None,
        )
        simulate_to_file(sim, capture, duration_s=7200)
        summaries[name], series, _ = evaluate(capture, model, truth=read_truth(capture.with_suffix(".truth.csv")))
        assert len(series.t_s) == len(series.drift_dph) == 7200
    series = per_second(tmp_path / "gap.bin", model)
    lost = np.isnan(series.rate_raw_dph)
    assert lost[3001:3900].all() and not lost[:3000].any() and not lost[3901:].any()
    assert not series.static[lost].any()
    clean, gap = summaries["clean"], summaries["gap"]
    assert gap["compensated"]["drift_rms_1min_dph"] == pytest.approx(
        clean["compensated"]["drift_rms_1min_dph"], rel=0.25
    )
    assert gap["truth"]["residual_rms_1min_dph"] < 1.5 * clean["truth"]["residual_rms_1min_dph"]


def test_the_drift_plot_draws_every_curve_on_one_baseline_with_its_legend_clear_of_the_data():
    """Before: the raw and compensated rates had the raw rate's median removed and the drift estimates none
    (the estimate ran 10 deg/h away from the rate it explains), and the legend sat on the curves."""
    pytest.importorskip("matplotlib")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from fog_driver.report.evaluate import Series, _plot_drift

    n = 3600
    t = np.arange(1.0, n + 1.0)
    drift = 0.5 * np.sin(t / 600.0) + 0.3  # the temperature drift, with a mean of its own
    series = Series(
        t_s=t,
        rate_raw_dph=10.0 + drift,  # Earth rate and bias, plus the drift
        drift_dph=drift - 0.3,  # an estimate right but for its constant
        temps_c=np.full((n, 3), 20.0),
        static=np.ones(n, dtype=bool),
        compared_drift_dph={"other": 0.5 * drift},
    )
    fig = _plot_drift(plt, series, t / 60.0, {"compensated": "compensated, m (wesn)", "other": "other"})
    try:
        fig.canvas.draw()
        (ax,) = fig.axes
        curves = {
            line.get_label(): np.asarray(line.get_ydata()) for line in ax.get_lines() if line.get_label()[0] != "_"
        }
        assert sorted(curves) == sorted(
            [
                "raw rate",
                "estimated drift, compensated, m (wesn)",
                "estimated drift, other",
                "compensated rate, compensated, m (wesn)",
                "compensated rate, other",
            ]
        )
        for label, y in curves.items():
            assert abs(np.median(y)) < 1e-9, label  # each on the baseline: its median over the static minutes
        # where the model is right, its estimate lies on the raw rate and the compensated rate on 0
        np.testing.assert_allclose(curves["estimated drift, compensated, m (wesn)"], curves["raw rate"], atol=1e-9)
        np.testing.assert_allclose(curves["compensated rate, compensated, m (wesn)"], 0.0, atol=1e-9)
        renderer = fig.canvas.get_renderer()
        (legend,) = fig.legends
        assert not legend.get_window_extent(renderer).overlaps(ax.get_window_extent(renderer))
    finally:
        plt.close(fig)
