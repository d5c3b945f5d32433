"""benchmarks/bench_population.py's issue-30 parts on constructed results: the run beyond the fit range, the run
seeds, and the PASS/MISS lines of the choice, the uncertainty and the program comparison."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks import bench_population as bench
from fog_driver.lab.profiles import load_profile
from fog_driver.report.coverage import MinuteErrors


def test_the_run_beyond_the_fit_range_soaks_10_degc_above_the_programs_hottest():
    beyond = bench.beyond_profile(load_profile("paper"))  # the paper program's hottest: 55 degC, from 20
    assert beyond.name == "beyond-paper" and beyond.motion.duration_s == 0.0  # static
    t = np.arange(0.0, beyond.duration_s + 1.0)
    air = beyond.chamber.air_temp_c(t)
    assert air.max() == 65.0 and air[0] == air[-1] == 20.0
    assert (air == 65.0).sum() == 60 * 60 + 1  # the 60-min soak (both ends)
    assert beyond.duration_s == (20 + 45 + 60 + 45 + 20) * 60.0
    assert np.abs(np.diff(air)).max() == pytest.approx(1.0 / 60.0)  # 1 degC/min


def test_run_seeds_keep_the_cached_runs_and_give_other_profiles_their_own():
    assert bench.score_run_seeds(("soak-cycle", "steps-moves")) == {"soak-cycle": 2, "steps-moves": 3}
    assert bench.score_run_seeds(("steps-moves", "chamber-cycle")) == {"steps-moves": 3, "chamber-cycle": 4}
    assert bench.score_run_seeds(("a", "steps-moves", "b")) == {"a": 7, "steps-moves": 3, "b": 8}


def _verdicts(text: str) -> list[str]:
    return [line.strip()[:4] for line in text.splitlines() if line.strip()[:4] in ("PASS", "MISS")]


def test_the_choice_is_judged_at_the_median_and_the_worst_against_the_better_per_instrument(capsys):
    # floor 1; (polynomial, wesn, auto): the better of the two per instrument is 1.0, 1.2, 2.0
    rows = [(1.0, 1.5, 1.0), (1.3, 1.2, 1.3), (3.0, 2.0, 2.05)]
    results = [
        {"seed": k, "r": {"floor": 1.0, "polynomial": p, "wesn": w, "auto": a}} for k, (p, w, a) in enumerate(rows)
    ]
    bench.summarize_choice(results)
    out = capsys.readouterr().out
    # auto: median 1.3, worst 2.05; the better: median 1.2, worst 2.0: 1.3 > 1.26 misses, 2.05 <= 2.1 passes
    assert _verdicts(out) == ["MISS", "PASS"]
    assert "1.300x <= 1.05 x 1.200x = 1.260x" in out and "2.050x <= 1.05 x 2.000x = 2.100x" in out
    assert "it left over 5 % more than the better on 1: 1" in out


def _minutes(rng, n, scale, extrapolating=0):
    """n minutes whose sigma is ``scale`` times the error's size (1.0: honest), the first ``extrapolating``
    flagged; half of the sigmas 1, half 3, the errors drawn with them."""
    sigma = np.repeat([0.01, 0.03], n // 2)
    error = rng.normal(0.0, 1.0, len(sigma)) * sigma
    flagged = np.arange(len(sigma)) < extrapolating
    return MinuteErrors(error, sigma * scale, flagged)


def test_the_uncertainty_targets_read_the_pooled_and_per_instrument_figures(capsys):
    rng = np.random.default_rng(1)
    results = [
        {
            "seed": k,
            "minutes": {"auto": _minutes(rng, 400, 1.0)},
            "beyond": {
                "minutes": {"auto": _minutes(rng, 100, 1.0, extrapolating=40)},
                "r": {"floor": 1.0, "auto": 1.2},
            },
        }
        for k in range(3)
    ]
    bench.summarize_coverage(results, ("auto",))
    out = capsys.readouterr().out
    pooled = MinuteErrors.pooled(x["minutes"]["auto"] for x in results)
    covered = np.mean(np.abs(pooled.error_dph) <= 1.96 * pooled.sigma_dph)
    assert f"pooled coverage {100 * covered:.1f} % within 92.0 %..98.0 %" in out
    assert "on the 120 extrapolating minutes" in out  # the beyond runs' 40 each
    assert (
        "300 static minutes, 120 of them flagged extrapolating (auto); 1-min RMS / floor there, median: auto 1.20x"
        in out
    )
    # honest, informative sigmas: every target met (the error's RMS on the top quarter about 3x the bottom's)
    assert _verdicts(out) == ["PASS"] * 6
    padded = [{**x, "minutes": {"auto": _minutes(rng, 400, 2.0)}} for x in results]
    bench.summarize_coverage(padded, ("auto",))
    out = capsys.readouterr().out
    assert _verdicts(out)[0] == "MISS" and _verdicts(out)[4] == "MISS"  # covers ~100 %; sigma 2x the error


def test_no_sigma_is_a_miss_that_says_why(capsys):
    nan = MinuteErrors(np.zeros(10), np.full(10, np.nan), np.zeros(10, bool))
    results = [
        {"seed": 0, "minutes": {"auto": nan}, "beyond": {"minutes": {"auto": nan}, "r": {"floor": 1.0, "auto": 1.0}}}
    ]
    bench.summarize_coverage(results, ("auto",))
    out = capsys.readouterr().out
    assert "auto         no finite drift_sigma_dph in the 10 static minutes" in out
    assert "MISS auto gives no finite drift_sigma_dph: no coverage to judge" in out


def test_the_program_targets_are_autos_fitted_on_the_program(capsys):
    def r(poly, auto):
        return {"floor": 1.0, "polynomial": poly, "auto": auto}

    # excess e = sqrt(r^2 - 1): the program's auto 1.1 and 1.9 against its polynomial 1.5 and 1.8
    results = [
        {
            "r": r(1.5, 1.1),
            "fit_s": {"polynomial": 1, "auto": 2},
            "against": {"r": r(2.0, 1.3), "fit_s": {"polynomial": 1, "auto": 2}},
        },
        {
            "r": r(1.8, 1.9),
            "fit_s": {"polynomial": 1, "auto": 2},
            "against": {"r": r(2.0, 2.5), "fit_s": {"polynomial": 1, "auto": 2}},
        },
    ]
    bench.summarize_programs(results, "calibration", "paper")
    out = capsys.readouterr().out
    worst = np.sqrt(1.9**2 - 1) / np.sqrt(1.8**2 - 1)
    assert f"MISS worst excess {worst:.2f}x the polynomial's fitted on the same run, <= 1x" in out
    assert "PASS worst 1-min RMS 1.90x the floor, <= 2x" in out
    assert "MISS median 1-min RMS 1.50x the floor, <= 1.15x" in out
    assert "auto         paper" in out and "auto         calibration" in out
