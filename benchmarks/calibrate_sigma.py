"""Calibrating ``drift_sigma_dph``'s three factors on development instruments (``compensation.uncertainty``).

    python -m benchmarks.calibrate_sigma --first 0 --instruments 24 --workdir /tmp/pop

Per development instrument K (``--first`` .. ``--first + --instruments - 1`` of the ``dev`` set; never an
evaluation set: see THE RULE of ``_harness.py``), the wesn is fitted on its ``paper`` run, as
``bench_population.py`` does (same captures, same cache layout), and applied to three scoring runs:
``soak-cycle``, ``steps-moves`` and a hot soak 10 degC above the fit program's hottest (``hot_soak``: the
minutes that leave the fit box).  For every static minute after the first ten it records the error
``e`` (the 1-min mean of estimate - true drift, both about their means over the run's static minutes)
and the three parts of sigma unscaled (the spread s, the residual r, the box term d R: one compensation
per part, the other factors set to 0).  Then the factors ``k_s, k_r, k_b`` are chosen by the largest
Gaussian likelihood of the pooled errors,

    maximize  sum_m  -log sigma_m - e_m^2 / (2 sigma_m^2),   sigma_m^2 = k_s^2 s_m^2 + k_r^2 r_m^2 + k_b^2 (d R)_m^2

on a grid, and the coverage of the +-1.96 sigma band is printed; then the same for a common factor c on
the spread and the residual (``COMMON_SCALES``, the box's factor 1).  Figures are printed, never asserted.

The shipped factors (``compensation.uncertainty``) and the runs that chose them:
docs/decisions/2026-12-07-uncertainty-factors.md.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np

from benchmarks._harness import capture, in_pool, instrument_seeds, resolve_profile, static_minutes_mask
from benchmarks.bench_population import beyond_profile
from fog_driver.compensation.fitting.data import FitConfig
from fog_driver.compensation.fitting.uncertainty import model_error_dph
from fog_driver.modelfiles import load_model, save_model
from fog_driver.offline.fit import fit_model_file
from fog_driver.report.coverage import MinuteErrors, coverage_figures, minute_errors
from fog_driver.report.evaluate import drift_per_second
from fog_driver.sim.capture import read_truth

PARTS = ("spread", "residual", "box")
SCORE = ("soak-cycle", "steps-moves", "hot-soak")
#: The paper program's run beyond its range: up at 1 degC/min to 10 degC above its hottest (55 degC), 120 min
#: there, back down; 30 min held at 20 degC before and after.
COMMON_SCALES = (0.7, 0.75, 0.8, 0.85, 0.9)


def hot_soak(fit_profile: str):
    """The fit program's run beyond its range: up at 1 degC/min to 10 degC above its hottest, 120 min there, back
    down, 30 min held before and after (named ``hot-soak`` for the paper program, as the captures it cached)."""
    name = "hot-soak" if fit_profile == "paper" else f"hot-soak-{fit_profile}"
    return beyond_profile(resolve_profile(fit_profile), soak_min=120.0, hold_min=30.0, name=name)


def instrument(seed: int, workdir: Path, fit_profile: str = "paper") -> dict:
    fit_run = capture(workdir, seed, fit_profile, 10 * seed + 1, 10)
    cached = workdir / f"i{seed}" / ("wesn-sigma.yaml" if fit_profile == "paper" else f"wesn-sigma-{fit_profile}.yaml")
    if cached.exists():
        model = load_model(cached)
    else:
        model, _ = fit_model_file([fit_run], kind="wesn", config=FitConfig(), accept_weak=True)
        save_model(cached, model)
    prov = model.provenance  # r as the fit makes it today, also for a model cached by an earlier version
    minutes = sum(c["static_blocks"] for c in prov["captures"]) // 60
    r = model_error_dph(prov["metrics"]["after, wesn"]["fit"], prov["noise_floor_1min_dph"]["fit"], minutes)
    spec = dataclasses.replace(model.sigma_spec, residual_dph=r)
    out: dict = {"seed": seed, "err": [], "parts": [], "extra": [], "run": [], "n_candidates": len(spec.candidates)}
    for i, profile in enumerate(SCORE):
        path = capture(
            workdir, seed, hot_soak(fit_profile) if profile == "hot-soak" else profile, 10 * seed + 2 + i, 10
        )
        truth = read_truth(path.with_suffix(".truth.csv"))
        n = len(truth["drift_dph"]) // 60 * 60
        static = static_minutes_mask(truth, n)
        parts = []
        for k in range(3):  # each part alone (its factor 1, the others 0); minutes of its sigma^2
            scales = dict(zip(("spread_scale", "residual_scale", "box_scale"), np.eye(3)[k]))
            mf = dataclasses.replace(model, uncertainty=dataclasses.replace(spec, **scales))
            applied = drift_per_second(path, mf, n)
            parts.append(
                minute_errors(
                    applied.drift_dph, truth["drift_dph"], applied.drift_sigma_dph**2, static, applied.extrapolating > 0
                )
            )
        out["err"].append(parts[0].error_dph)  # the same drift in each: the factors change the sigma only
        out["parts"].append(np.array([p.sigma_dph for p in parts]))
        out["extra"].append(parts[0].extrapolating)
        out["run"].append(np.full(len(parts[0]), i))
    return {k: (np.concatenate(v, axis=-1) if isinstance(v, list) else v) for k, v in out.items()}


def choose(results: list[dict]) -> tuple[float, float, float]:
    err = np.concatenate([r["err"] for r in results])
    parts = np.concatenate([r["parts"] for r in results], axis=1)
    best, best_ll = (1.0, 1.0, 1.0), -np.inf
    grid = np.r_[0.0, np.geomspace(0.05, 20, 40)]
    for ks in grid:
        for kr in grid:
            for kb in grid:
                var = ks**2 * parts[0] + kr**2 * parts[1] + kb**2 * parts[2]
                if (var <= 0).any():
                    continue
                ll = float(np.sum(-0.5 * np.log(var) - err**2 / (2 * var)))
                if ll > best_ll:
                    best, best_ll = (float(ks), float(kr), float(kb)), ll
    return best


def report(results: list[dict], k: tuple[float, float, float]) -> None:
    """The factors' coverage figures (``fog_driver.report.coverage``, as ``bench_population.py`` reports them)."""
    ks, kr, kb = k
    print(f"factors: spread {ks:.3g}, residual {kr:.3g}, box {kb:.3g}")
    runs = []
    for r in results:
        sigma = np.sqrt(ks**2 * r["parts"][0] + kr**2 * r["parts"][1] + kb**2 * r["parts"][2])
        runs.append((MinuteErrors(r["err"], sigma, r["extra"]), r["run"]))
    main_runs = [m.only(run < 2) for m, run in runs]  # soak-cycle and steps-moves
    per = [coverage_figures(m) for m in main_runs]
    pooled = coverage_figures(MinuteErrors.pooled(main_runs))
    everything = MinuteErrors.pooled(m for m, _ in runs)
    outside = coverage_figures(everything.only(everything.extrapolating))
    hot = coverage_figures(MinuteErrors.pooled(m.only(run == 2) for m, run in runs))
    cover = [f["coverage"] for f in per]
    print(
        f"coverage pooled (soak-cycle, steps-moves) {100 * pooled['coverage']:.1f} %; per instrument "
        f"min {100 * min(cover):.1f} %, >= 80 % on {sum(c >= 0.8 for c in cover)} of {len(cover)}; top-sigma quarter "
        f"{100 * pooled['top_quarter']['coverage']:.1f} %; extrapolating minutes (all runs) "
        f"{100 * outside['coverage']:.1f} % of {outside['minutes_with_sigma']}; hot soak {100 * hot['coverage']:.1f} %"
    )
    print(
        f"median sigma / RMS error {pooled['sharpness']:.2f}; top/bottom-quarter RMS error ratio, median over "
        f"instruments {np.median([f['top_bottom_error_ratio'] for f in per]):.2f}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--first", type=int, default=0)
    parser.add_argument("--instruments", type=int, default=24)
    parser.add_argument("--workdir", type=Path, required=True)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument(
        "--fit-profile",
        default="paper",
        help="the program each wesn is fitted on (default paper); several, comma-separated, are pooled: each "
        "instrument's fit on each program counts as one instrument",
    )
    args = parser.parse_args()
    t0 = time.perf_counter()
    seeds = instrument_seeds("dev", args.first, args.instruments)
    programs = args.fit_profile.split(",")
    jobs = [(seed, program) for program in programs for seed in seeds]
    results = list(
        in_pool(instrument, args.workers, [s for s, _ in jobs], [args.workdir] * len(jobs), [p for _, p in jobs])
    )
    print(f"dev instruments {seeds[0]}..{seeds[-1]}, fitted on {args.fit_profile}  [{time.perf_counter() - t0:.0f} s]")
    print("candidates per model: " + ", ".join(str(r["n_candidates"]) for r in results))
    report(results, (1.0, 1.0, 1.0))
    k = choose(results)
    report(results, k)
    for c in COMMON_SCALES:  # the shipped choice: one common factor on the spread and the residual, box 1
        report(results, (c, c, 1.0))
    np.savez(
        args.workdir / f"sigma_parts-{'+'.join(programs)}.npz",
        **{f"{k}_{p}_{r['seed']}": r[k] for (_, p), r in zip(jobs, results) for k in r if k != "seed"},
    )


if __name__ == "__main__":
    main()
