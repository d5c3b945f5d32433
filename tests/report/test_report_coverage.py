"""The honesty of drift_sigma_dph against a truth (fog_driver.report.coverage), and evaluate --truth reporting it."""

from __future__ import annotations

import math
import statistics
from pathlib import Path

import numpy as np
import pytest

from fog_driver.report.coverage import (
    BAND_Z,
    MinuteErrors,
    coverage_figures,
    coverage_markdown,
    format_coverage,
    minute_errors,
)

ROOT = Path(__file__).resolve().parents[2]


def _reference(estimate, truth, sigma, static, flagged):
    """The figures by plain loops, from the issue's words: per whole static minute the mean of (estimate -
    truth) about its mean over the static minutes, the mean sigma; the quarters by the percentiles of the
    finite sigmas (statistics.quantiles, inclusive: numpy's linear percentile)."""
    minutes = []
    for m in range(len(estimate) // 60):
        sl = range(60 * m, 60 * m + 60)
        if all(static[k] for k in sl):
            minutes.append(
                (
                    sum(estimate[k] - truth[k] for k in sl) / 60,
                    sum(sigma[k] for k in sl) / 60,
                    any(flagged[k] for k in sl),
                )
            )
    mean = sum(e for e, _, _ in minutes) / len(minutes)
    rows = [(e - mean, s, x) for e, s, x in minutes if not math.isnan(s)]

    def rms(es):
        return math.sqrt(sum(e * e for e in es) / len(es))

    def cov(rs):
        return sum(abs(e) <= 1.96 * s for e, s, _ in rs) / len(rs) if rs else None

    sig = [s for _, s, _ in rows]
    q1, _, q3 = statistics.quantiles(sig, n=4, method="inclusive")
    top = [r for r in rows if r[1] >= q3]
    bottom = [r for r in rows if r[1] <= q1]
    return {
        "static_minutes": len(minutes),
        "minutes_with_sigma": len(rows),
        "coverage": cov(rows),
        "error_rms_1min_dph": rms([e for e, _, _ in rows]),
        "sigma_median_dph": statistics.median(sig),
        "sharpness": statistics.median(sig) / rms([e for e, _, _ in rows]),
        "top_coverage": cov(top),
        "top_minutes": len(top),
        "ratio": rms([e for e, _, _ in top]) / rms([e for e, _, _ in bottom]),
        "extrapolating_minutes": sum(x for _, _, x in rows),
        "extrapolating_coverage": cov([r for r in rows if r[2]]),
    }


def _series(seed=3, minutes=90):
    """A constructed per-second series: a drift, an estimate whose error grows with a sigma that varies,
    table motion in some minutes, NaN sigma in a few, a flagged stretch and a trailing part-minute."""
    rng = np.random.default_rng(seed)
    n = minutes * 60 + 37
    t = np.arange(n)
    truth = 0.2 * np.sin(t / 900.0)
    sigma = np.repeat(0.002 + 0.02 * rng.random(minutes + 1), 60)[:n]
    estimate = truth + 0.7 + np.repeat(rng.normal(0.0, 1.0, minutes + 1), 60)[:n] * sigma + rng.normal(0, 0.01, n)
    static = np.ones(n, dtype=bool)
    static[:120] = False  # warm-up
    static[30 * 60 + 10 : 31 * 60 + 5] = False  # a move across a minute boundary: minutes 30 and 31 out
    sigma[50 * 60 + 7] = np.nan  # minute 50 has no sigma
    sigma[: 60 * 4] = np.nan  # nor the first four
    flagged = np.zeros(n, dtype=bool)
    flagged[70 * 60 + 59 : 75 * 60] = True  # minutes 70..74 flagged (70 by its last second)
    return estimate, truth, sigma, static, flagged


def test_figures_equal_a_plain_computation_of_the_issues_definition():
    estimate, truth, sigma, static, flagged = _series()
    got = coverage_figures(minute_errors(estimate, truth, sigma, static, flagged))
    want = _reference(estimate, truth, sigma, static, flagged)
    assert got["static_minutes"] == want["static_minutes"] == 90 - 2 - 2  # warm-up and the move
    assert got["minutes_with_sigma"] == want["minutes_with_sigma"] == 86 - 3  # minutes 2, 3 and 50
    for key in ("coverage", "error_rms_1min_dph", "sigma_median_dph", "sharpness"):
        assert got[key] == pytest.approx(want[key], rel=1e-12), key
    assert got["top_quarter"]["coverage"] == pytest.approx(want["top_coverage"], rel=1e-12)
    assert got["top_quarter"]["minutes"] == want["top_minutes"]
    assert got["top_bottom_error_ratio"] == pytest.approx(want["ratio"], rel=1e-12)
    assert got["extrapolating"]["minutes"] == 5
    assert got["extrapolating"]["coverage"] == pytest.approx(want["extrapolating_coverage"], rel=1e-12)
    assert 0.0 < got["coverage"] < 1.0 and got["top_bottom_error_ratio"] > 1.5  # the series is built so


def test_a_hand_made_run_gives_the_counts_by_hand():
    """Eight static minutes, the estimate's error in each a constant; its mean (0.5) is removed first."""
    per_minute_error = np.array([0.5, 0.5, 1.5, -0.5, 0.5, 0.5, 2.5, -1.5])  # about the mean: 0 0 1 -1 0 0 2 -2
    per_minute_sigma = np.array([0.1, 0.1, 0.6, 0.6, 0.1, 0.1, 1.0, 0.5])
    estimate = np.repeat(per_minute_error, 60)
    got = coverage_figures(
        minute_errors(estimate, np.zeros_like(estimate), np.repeat(per_minute_sigma, 60), np.ones(480, bool))
    )
    # |err| <= 1.96 sigma: 0,0 yes; 1 <= 1.176 yes; 1 <= 1.176 yes; 0,0 yes; 2 <= 1.96 no; 2 <= 0.98 no
    assert got["coverage"] == pytest.approx(6 / 8)
    assert got["error_rms_1min_dph"] == pytest.approx(math.sqrt(10 / 8))
    assert got["sigma_median_dph"] == pytest.approx(0.3)  # sorted 0.1 0.1 0.1 0.1 0.5 0.6 0.6 1.0
    # the 75th percentile of the sigmas is 0.6: minutes 2, 3, 6 (errors 1, -1, 2; coverage 2 of 3);
    # the 25th is 0.1: minutes 0, 1, 4, 5 (errors 0): the ratio has nothing to divide by
    top = got["top_quarter"]
    assert (top["minutes"], top["coverage"]) == (3, pytest.approx(2 / 3))
    assert top["error_rms_1min_dph"] == pytest.approx(math.sqrt(6 / 3)) and top["sigma_median_dph"] == pytest.approx(
        0.6
    )
    assert got["bottom_quarter"]["error_rms_1min_dph"] == 0.0 and got["top_bottom_error_ratio"] is None
    assert "(the top-sigma quarter 66.7 %; none extrapolating)" in format_coverage(got)
    assert got["extrapolating"] == {
        "minutes": 0,
        "coverage": None,
        "error_rms_1min_dph": None,
        "sigma_median_dph": None,
    }


def test_a_constant_sigma_carries_no_information_ratio_one():
    estimate, truth, sigma, static, flagged = _series(seed=5)
    got = coverage_figures(minute_errors(estimate, truth, np.full(len(truth), 0.01), static, flagged))
    assert got["top_quarter"]["minutes"] == got["bottom_quarter"]["minutes"] == got["minutes_with_sigma"]
    assert got["top_bottom_error_ratio"] == 1.0


def test_no_finite_sigma_says_so_instead_of_numbers():
    estimate, truth, _, static, flagged = _series()
    got = coverage_figures(minute_errors(estimate, truth, np.full(len(truth), np.nan), static, flagged))
    assert got["minutes_with_sigma"] == 0 and got["static_minutes"] == 86
    assert "coverage" not in got and "sharpness" not in got
    assert "no finite drift_sigma_dph" in got["note"]
    assert format_coverage(got).startswith("uncertainty: no finite drift_sigma_dph in the 86 static minutes")
    assert coverage_markdown(got)[0].endswith(
        "no finite drift_sigma_dph in the 86 static minutes: the model gives no uncertainty, so its coverage "
        "cannot be reported."
    )


def test_pooled_runs_are_their_minutes_together_each_about_its_own_mean():
    a = minute_errors(*_series(seed=1))
    b = minute_errors(*_series(seed=2, minutes=80))
    pooled = MinuteErrors.pooled([a, b])
    assert len(pooled) == len(a) + len(b)
    assert abs(a.error_dph.mean()) < 1e-12 and abs(b.error_dph.mean()) < 1e-12
    fin = np.isfinite(pooled.sigma_dph)
    inside = np.abs(pooled.error_dph[fin]) <= BAND_Z * pooled.sigma_dph[fin]
    assert coverage_figures(pooled)["coverage"] == pytest.approx(inside.mean())


def test_the_line_and_the_table_carry_the_figures():
    got = coverage_figures(minute_errors(*_series()))
    top, outside = got["top_quarter"], got["extrapolating"]
    assert format_coverage(got) == (
        f"uncertainty: the +-1.96-sigma band covers {100 * got['coverage']:.1f} % of 83 static minutes (the "
        f"top-sigma quarter {100 * top['coverage']:.1f} %; extrapolating {100 * outside['coverage']:.1f} % of 5); "
        f"median sigma {got['sharpness']:.2f}x the error's RMS; the error's RMS on the top-sigma quarter "
        f"{got['top_bottom_error_ratio']:.2f}x that on the bottom quarter"
    )
    lines = coverage_markdown(got)
    assert "3 static minutes had no sigma." in lines[0]
    assert lines[4] == (
        f"| all with a sigma | 83 | {100 * got['coverage']:.1f} % | {got['error_rms_1min_dph']:.4f} | "
        f"{got['sigma_median_dph']:.4f} |"
    )
    assert lines[5].startswith(f"| the quarter with the largest sigma | {top['minutes']} |")
    assert lines[7].startswith(f"| flagged extrapolating | 5 | {100 * outside['coverage']:.1f} % |")


# -- evaluate --truth, with a compensator whose sigma is set per block ---------------------------------


def _sigma_of_block(index: int) -> float:
    return 0.004 * (1 + index // 60 % 5)  # steps once a minute: 0.004 .. 0.020 deg/h


@pytest.fixture(scope="module")
def short_run(tmp_path_factory):
    from fog_driver.lab.profiles import load_profile
    from fog_driver.sim.capture import simulate_to_file
    from fog_driver.sim.instrument import Simulator

    capture = tmp_path_factory.mktemp("coverage") / "run.bin"
    sim = Simulator(load_profile(ROOT / "configs" / "profiles" / "short-test.yaml"), rate_hz=10, seed=7)
    simulate_to_file(sim, capture)
    return capture


def _evaluate(capture, monkeypatch, sigma_of_block):
    from fog_driver.compensation.pipeline import Compensator
    from fog_driver.daemon.config import DEFAULT_MODEL
    from fog_driver.modelfiles import load_model
    from fog_driver.report.evaluate import evaluate
    from fog_driver.sim.capture import read_truth

    original = Compensator._on_block

    def on_block(self, block):
        original(self, block)
        self.sigma_dph = sigma_of_block(block.index)  # the sigma the next block's frames carry

    monkeypatch.setattr(Compensator, "_on_block", on_block)
    truth = read_truth(capture.with_suffix(".truth.csv"))
    return evaluate(capture, load_model(DEFAULT_MODEL), truth=truth), truth


def test_evaluate_reports_the_coverage_of_the_sigma_the_compensator_carried(short_run, monkeypatch, tmp_path):
    from fog_driver.report.evaluate import write_report

    (summary, series, allans), truth = _evaluate(short_run, monkeypatch, _sigma_of_block)
    n = len(series.t_s)
    # each second's frames carry the sigma set when the block before closed; the first second has none
    assert math.isnan(series.drift_sigma_dph[0])
    assert series.drift_sigma_dph[1:n] == pytest.approx([_sigma_of_block(k - 1) for k in range(1, n)])
    sigma = [math.nan] + [_sigma_of_block(k - 1) for k in range(1, n)]
    flagged = series.extrapolating[:n]
    want = _reference(series.drift_dph[:n], truth["drift_dph"][:n], sigma, series.static[:n], flagged)
    got = summary["truth"]["sigma"]
    assert got["static_minutes"] == want["static_minutes"] == summary["static_minutes"] >= 15
    assert got["minutes_with_sigma"] == want["minutes_with_sigma"]
    for key in ("coverage", "error_rms_1min_dph", "sigma_median_dph", "sharpness"):
        assert got[key] == pytest.approx(want[key], rel=1e-9), key
    assert got["top_bottom_error_ratio"] == pytest.approx(want["ratio"], rel=1e-9)
    report = write_report(tmp_path / "out", summary, series, allans, None).read_text()
    assert "\n".join(coverage_markdown(got)) in report
    assert f"| all with a sigma | {got['minutes_with_sigma']} | {100 * got['coverage']:.1f} % |" in report


def test_evaluate_without_a_sigma_says_so_in_the_report(short_run, monkeypatch, tmp_path):
    from fog_driver.report.evaluate import write_report

    (summary, series, allans), _ = _evaluate(short_run, monkeypatch, lambda index: math.nan)
    assert summary["truth"]["sigma"]["minutes_with_sigma"] == 0
    report = write_report(tmp_path / "out", summary, series, allans, None).read_text()
    assert "against its sigma (the 1-min mean of drift_sigma_dph" in report
    assert "no finite drift_sigma_dph in the" in report


def test_the_command_prints_the_coverage_line(short_run, monkeypatch, tmp_path, capsys):
    import json

    from fog_driver.cli import main
    from fog_driver.compensation.pipeline import Compensator
    from fog_driver.daemon.config import DEFAULT_MODEL

    original = Compensator._on_block

    def on_block(self, block):
        original(self, block)
        self.sigma_dph = _sigma_of_block(block.index)

    monkeypatch.setattr(Compensator, "_on_block", on_block)
    out = tmp_path / "rep"
    truth = str(short_run.with_suffix(".truth.csv"))
    assert main(["evaluate", str(short_run), "--model", str(DEFAULT_MODEL), "--out", str(out), "--truth", truth]) == 0
    sigma = json.loads((out / "summary.json").read_text())["truth"]["sigma"]
    assert sigma["minutes_with_sigma"] > 0
    assert format_coverage(sigma) in capsys.readouterr().out.splitlines()
