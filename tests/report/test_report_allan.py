"""The Allan analysis against closed forms (IEEE 952, NIST SP 1065): intervals, read points, trust limit,
the ADEV table, and evaluate's short-stretch warning, compared models and progress."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from fog_driver.daemon.config import DEFAULT_MODEL
from fog_driver.report.allan import TABLE_COLUMNS, allan, read_csv, write_csv

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT / "tests" / "data"
N_1S_DPH = 0.18  #: white rate noise of 1-s means, deg/h: N = 0.18 / 60 = 0.003 deg/sqrt(h)


def test_white_noise_adev_is_sigma_over_sqrt_tau_within_its_interval_at_the_nominal_rate():
    """White FM of std s per 1-s mean: ADEV(tau) = s / sqrt(tau) exactly (the mean of m independent values).
    Across seeds the 68.3 % interval must cover it near its nominal rate, neither much less (too narrow:
    a wrong noise type or EDF) nor all the time (uselessly wide)."""
    covered = []
    for seed in range(20):
        r = allan(np.random.default_rng(seed).normal(0.0, N_1S_DPH, 7200))
        truth = N_1S_DPH / np.sqrt(r.tau_s)
        inside = (r.lo_dph <= truth) & (truth <= r.hi_dph)
        covered.append(inside[r.trusted].mean())
        assert np.all(r.lo_dph < r.sigma_dph) and np.all(r.sigma_dph < r.hi_dph)
        assert r.arw_deg_per_rt_h == pytest.approx(N_1S_DPH / 60.0, rel=0.03)
        assert r.rrw_dph_per_rt_h is None and r.rate_ramp_dph_per_h is None and r.quantization_arcsec is None
    assert 0.55 <= np.mean(covered) <= 0.85
    assert min(covered) >= 0.3


def test_the_trust_limit_is_a_tenth_of_the_record_and_the_table_has_every_column():
    r = allan(np.random.default_rng(0).normal(0.0, N_1S_DPH, 3000))
    assert np.array_equal(r.trusted, r.tau_s <= 300.0) and r.tau_s.max() > 300.0  # longer taus tabulated, not read
    assert r.bias_instability_tau_s <= 300.0
    rows = r.table()
    assert [list(row) for row in rows] == [list(TABLE_COLUMNS)] * len(r.tau_s)
    assert [row["n_pairs"] for row in rows] == [3000 - 2 * int(t) + 1 for t in r.tau_s]  # overlapping pairs


def test_a_rate_random_walk_reads_K():
    """Rate random walk K (deg/h/sqrt(h)): ADEV = K sqrt(tau / 3), read at tau = 3 s on the +1/2 line."""
    k_dph_per_rt_h = 0.05
    step = k_dph_per_rt_h / 60.0  # per 1-s step, deg/h (K in deg/h/sqrt(s))
    r = allan(np.cumsum(np.random.default_rng(3).normal(0.0, step, 36000)))
    assert r.rrw_dph_per_rt_h == pytest.approx(k_dph_per_rt_h, rel=0.15)
    assert r.arw_deg_per_rt_h is None  # no white region in a pure random walk


def test_a_rate_ramp_reads_R_and_white_noise_still_reads_N():
    """Rate ramp R (deg/h/h): ADEV = R tau / sqrt(2), read at tau = sqrt(2) s on the +1 line."""
    r_dph_per_h = 2.0
    t_s = np.arange(36000.0)
    r = allan(r_dph_per_h / 3600.0 * t_s + np.random.default_rng(5).normal(0.0, N_1S_DPH, len(t_s)))
    assert r.rate_ramp_dph_per_h == pytest.approx(r_dph_per_h, rel=0.05)
    assert r.arw_deg_per_rt_h == pytest.approx(N_1S_DPH / 60.0, rel=0.03)
    assert r.regions["arw"][1] < r.regions["rate_ramp"][0]


def test_quantization_reads_Q():
    """White angle noise of std Q arcsec (quantization): ADEV = sqrt(3) Q / tau; with the rate in deg/h
    and tau in s, Q = ADEV(sqrt 3 s) in arcsec."""
    q_arcsec = 1.0
    angle = np.random.default_rng(7).normal(0.0, q_arcsec, 20001)
    r = allan(np.diff(angle))  # deg/h * 1 s = arcsec per 1-s step
    assert r.quantization_arcsec == pytest.approx(q_arcsec, rel=0.05)


def test_a_curve_still_falling_gives_an_upper_bound_not_a_floor():
    """White noise falls at every tau: the minimum over the trusted taus is at the last one, and the
    bias instability can only be bounded.  White noise plus a rate random walk has a true minimum,
    at tau = sqrt(3) N / K, ADEV^2 = 2 N K / sqrt(3)."""
    falling = allan(np.random.default_rng(1).normal(0.0, N_1S_DPH, 20000))
    assert falling.bias_instability_bound == "upper bound" and not falling.minimum_reached
    assert falling.bias_instability_tau_s == falling.tau_s[falling.trusted][-1]

    n, k = N_1S_DPH, 0.0005  # deg/h sqrt(s), deg/h / sqrt(s)
    rng = np.random.default_rng(2)
    rate = rng.normal(0.0, n, 40000) + np.cumsum(rng.normal(0.0, k, 40000))
    bowl = allan(rate)
    assert bowl.bias_instability_bound == "floor"
    tau_min = math.sqrt(3.0) * n / k  # ~620 s
    assert tau_min / 2.5 <= bowl.bias_instability_tau_s <= tau_min * 2.5
    sigma_min = math.sqrt(2.0 * n * k / math.sqrt(3.0))
    assert bowl.sigma_dph.min() == pytest.approx(sigma_min, rel=0.25)


def test_the_csv_round_trips_the_table(tmp_path):
    r = allan(np.random.default_rng(0).normal(0.0, N_1S_DPH, 5000))
    path = write_csv(tmp_path / "allan-raw.csv", r)
    assert path.read_text().splitlines()[0] == ",".join(TABLE_COLUMNS)
    assert read_csv(path) == r.table()


def _evaluate(
    tmp_path, *extra: str, capture: Path = DATA / "sim-short.bin"
) -> tuple[subprocess.CompletedProcess, Path]:
    out = tmp_path / "rep"
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
            *extra,
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    return proc, out


def test_a_short_capture_warns_and_compared_models_get_their_own_columns(tmp_path):
    """sim-short.bin is 300 s: its Allan stretch is 180 s after the warm-up, 3 one-minute means."""
    other = tmp_path / "other.yaml"
    other.write_bytes(DEFAULT_MODEL.read_bytes())
    proc, out = _evaluate(tmp_path, "--compare", str(other))
    summary = json.loads(proc.stdout)
    start, stop = summary["allan_stretch_s"]
    warnings = summary["warnings"]
    assert any(
        w.startswith(f"short stretch: {stop - start} s") and f"above {(stop - start) / 10:.0f} s untrusted" in w
        for w in warnings
    )
    assert any(f"from {summary['static_minutes']} one-minute means is not reliable" in w for w in warnings)
    for w in warnings:
        assert f"warning: {w}" in proc.stderr
        assert f"**Warning: {w}.**" in (out / "report.md").read_text()
    # the compared model: its own drift RMS and Allan table, labelled by stem and kind
    assert summary["model"]["label"] == "default (wesn)" and list(summary["compared"]) == ["other (wesn)"]
    assert summary["other (wesn)"] == summary["compensated"]  # the same model under another name
    assert summary["allan"]["other (wesn)"] == summary["allan"]["compensated"]
    for name in ("raw", "compensated", "other (wesn)"):
        assert read_csv(out / f"allan-{name.replace(' (', '-').rstrip(')')}.csv") == summary["allan"][name]
    assert "| | raw | compensated, default (wesn) | other (wesn) |" in (out / "report.md").read_text()


def test_the_short_stretch_thresholds():
    """Under 1 h of stretch, or under 30 one-minute means, a warning each; 2 h and 120 means: none."""
    from fog_driver.report.evaluate import stretch_warnings

    assert stretch_warnings(7200.0, 120) == []
    assert len(stretch_warnings(300.0, 3)) == 2 and "3 one-minute means" in stretch_warnings(300.0, 3)[1]
    assert len(stretch_warnings(3599.0, 30)) == 1 and len(stretch_warnings(3600.0, 29)) == 1


def test_evaluate_reports_its_progress_in_percent():
    from fog_driver.modelfiles import load_model
    from fog_driver.report.evaluate import evaluate

    model = load_model(DEFAULT_MODEL)
    seen: list[str] = []
    evaluate(
        DATA / "sim-short.bin", model, label="default (wesn)", compare={"other (wesn)": model}, progress=seen.append
    )
    first = [t for t in seen if t.startswith("evaluating 1/2: decoding and compensating with default (wesn)")]
    second = [t for t in seen if t.startswith("evaluating 2/2: compensating with other (wesn)")]
    assert first and second and seen.index(second[0]) > seen.index(first[-1])
    percents = [float(t.rsplit(" ", 2)[-2]) for t in first]  # decoding is the first half, compensating the second
    assert percents == sorted(percents) and percents[0] == pytest.approx(50.0, abs=1) and percents[-1] == 100.0
