"""Choosing the calibration program (``fog-driver plan``, the built-in ``calibration``) on development instruments.

    python -m benchmarks.bench_plan [--instruments 12] [--first 0] [--designs NAME,NAME] [--rate-hz 10]
                                    [--workers 1] [--workdir DIR] [--reuse DIR] [--per-instrument]

Development instruments only (``dev``, seeds 0 ..; THE RULE in ``_harness.py``: no evaluation
seed set is ever used for a choice, so this script has no ``--set``).  Per instrument K
(``fog_driver.sim.population.draw_instrument``) and per candidate design: one run of the design's program
(run seed 10 K + 1, as ``bench_population.py``'s paper run: the same noise draws for every design), the
``wesn`` fitted on it (``fit_model_file([run], kind="wesn", config=FitConfig(), accept_weak=True)``) and
the polynomial fitted on the same run; both scored on a ``fast-ramps`` run (run seed 10 K + 4) and a
``soak-cycle`` run (10 K + 2), neither ever fitted on, as ``bench_population.py`` scores (static minutes
after the first ten, 1-minute means, each series' mean removed, the two runs pooled):

    r   = RMS of (D - D_hat + n)        the 1-min drift RMS the model leaves
    f   = RMS of n                      the noise floor
    e   = sqrt(max(r^2 - f^2, 0))       the excess drift

Printed per design, over the instruments: the median and the worst of the wesn's r / f and of its
excess over the polynomial's (e / e_poly, both fitted on the same run), the polynomial's r / f, the lag
interval (the largest over the smallest of the coil lags that explain the run within the noise of the best,
``provenance.selection.lags_explaining_equally_s``: 1 when the run pins the lag to one grid step), the
program's length and what ``identifiability_gaps`` says it leaves unidentified. Targets of issue 30 (on the
evaluation range, for the program chosen here): worst e / e_poly <= 1.0, worst r / f <= 2, median r / f <=
1.15. Figures are printed, never asserted.

The candidates (``CANDIDATES``), each adding one element the identifiability argument of
``fog_driver/lab/plan.py`` asks for, all within the paper's limits (-40..55 degC, 440 min) and a
chamber's 3 degC/min: ``paper`` (the paper's program: one rate, one direction per temperature,
15-minute soaks), ``cycle`` (every temperature crossed both ways, ramps at 3, 1.5 and 0.75 degC/min
in each direction, 15-degree plateaus), ``cycle+soaks`` (and soaks of a tenth of the run at both
extremes), ``calibration`` (and a rate that varies within the run: the return leg's ramps chained,
a closing sinusoid: the shipped design), ``coarse`` (the same with plateaus 30 degrees apart: half as
many transients, each ramp and hold twice as long against a long lag).  Captures are cached in
``--workdir``; ``--reuse DIR`` reads captures already simulated under ``bench_population.py``'s names
(``DIR/i<K>/<profile>-r<seed>-<rate>hz.bin``) without writing there.  One worker by default.

The figures of docs/explanation/accuracy.md ("The calibration program"): ``--instruments 24 --per-instrument``
(with ``--workers 2``, 57 minutes on the shared two-core machine, the captures cached).
"""

from __future__ import annotations

import argparse
import hashlib
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from benchmarks._harness import capture as population_capture
from benchmarks._harness import in_pool, instrument_seeds, kept_or_temporary, static_minutes_mask
from fog_driver.compensation.fitting.data import FitConfig
from fog_driver.lab.motion import MotionPlan
from fog_driver.lab.plan import DEFAULT_LIMITS, DESIGN, Design, design_program, identifiability_gaps
from fog_driver.lab.profiles import SimProfile, dump_profile, load_profile
from fog_driver.offline.fit import fit_model_file
from fog_driver.report.evaluate import minute_rms, per_second
from fog_driver.sim.capture import read_truth, truth_noise_dph

#: name -> the design (None: the paper's program, the built-in profile ``paper``)
CANDIDATES: dict[str, Design | None] = {
    "paper": None,
    "cycle": Design(name="cycle", long_soaks=False, varying_rate=False),
    "cycle+soaks": Design(name="cycle+soaks", varying_rate=False),
    "calibration": DESIGN,
    "coarse": Design(name="coarse", plateau_step_c=30.0),
}
SCORE_PROFILES = {"fast-ramps": 4, "soak-cycle": 2}  #: scoring profile -> run seed offset (10 K + offset)
FIT_RUN_OFFSET = 1


def candidate_profile(name: str) -> SimProfile:
    design = CANDIDATES[name]
    if design is None:
        return load_profile(name)
    return SimProfile(design.name, design_program(DEFAULT_LIMITS, design).chamber, MotionPlan.static(), "bench_plan")


def capture(workdir: Path, reuse: Path | None, seed: int, name: str, run_seed: int, rate_hz: int) -> Path:
    """Instrument ``seed``'s run of profile or candidate ``name``: from ``reuse`` when there under
    ``bench_population.py``'s name (not a candidate design: its program may have changed), else cached in
    ``workdir`` by ``bench_population.capture``, a candidate under its name and a hash of its program."""
    if name in CANDIDATES and CANDIDATES[name] is not None:
        profile = candidate_profile(name)
        digest = hashlib.sha256(dump_profile(profile).encode()).hexdigest()[:8]
        return population_capture(workdir, seed, replace(profile, name=f"{name}-{digest}"), run_seed, rate_hz)
    reused = reuse / f"i{seed}" / f"{name}-r{run_seed}-{rate_hz}hz.bin" if reuse is not None else None
    if reused is not None and reused.exists():
        return reused
    return population_capture(workdir, seed, name, run_seed, rate_hz)


def score_instrument(seed: int, designs: tuple[str, ...], rate_hz: int, workdir: Path, reuse: Path | None) -> dict:
    """Per design: fit the wesn and the polynomial on instrument ``seed``'s run of it; score both on the
    scoring runs (module docstring)."""
    runs = []
    for profile, offset in SCORE_PROFILES.items():
        path = capture(workdir, reuse, seed, profile, 10 * seed + offset, rate_hz)
        truth = read_truth(path.with_suffix(".truth.csv"))
        runs.append((path, truth, truth_noise_dph(truth)))
    result: dict = {"seed": seed, "r": {}, "fit_s": {}}
    floor_sq, raw_sq = [], []
    for _path, truth, noise in runs:
        n = len(truth["drift_dph"])
        mask = static_minutes_mask(truth, n)
        floor_sq.append(minute_rms(noise, mask) ** 2)
        raw_sq.append(minute_rms(truth["drift_dph"] + noise, mask) ** 2)
    result["r"]["floor"] = float(np.sqrt(np.mean(floor_sq)))
    result["r"]["raw"] = float(np.sqrt(np.mean(raw_sq)))
    for design in designs:
        fit_run = capture(workdir, reuse, seed, design, 10 * seed + FIT_RUN_OFFSET, rate_hz)
        for kind in ("wesn", "polynomial"):
            t0 = time.perf_counter()
            model, _ = fit_model_file([fit_run], kind=kind, config=FitConfig(), accept_weak=True)
            result["fit_s"][design, kind] = time.perf_counter() - t0
            sq = []
            for path, truth, noise in runs:
                series = per_second(path, model)
                n = min(len(series.drift_dph), len(truth["drift_dph"]))
                mask = static_minutes_mask(truth, n)
                sq.append(minute_rms(truth["drift_dph"][:n] - series.drift_dph[:n] + noise[:n], mask) ** 2)
            result["r"][design, kind] = float(np.sqrt(np.mean(sq)))
            if kind == "wesn":
                sel = model.provenance.get("selection") or getattr(model.model, "selection", None) or {}
                result.setdefault("lag_s", {})[design] = sel.get("coil_lag_s", float("nan"))
                tied = sel.get("lags_explaining_equally_s") or [float("nan")]
                result.setdefault("lag_span", {})[design] = max(tied) / min(tied)
    return result


def excess(r: float, f: float) -> float:
    return float(np.sqrt(max(r * r - f * f, 0.0)))


def summarize(results: list[dict], designs: tuple[str, ...]) -> None:
    print(
        f"{'design':14s} {'min':>5s} {'wesn r / floor':>20s} {'wesn e / poly e':>20s} {'poly r / floor':>20s}"
        f" {'lag interval':>20s}  unidentified by the program"
    )
    print(f"{'':14s} {'':>5s}" + f" {'median':>10s}{'worst':>10s}" * 4)
    for design in designs:
        floor = np.array([x["r"]["floor"] for x in results])
        wesn = np.array([x["r"][design, "wesn"] for x in results])
        poly = np.array([x["r"][design, "polynomial"] for x in results])
        ex = np.array([excess(w, f) / max(excess(p, f), 1e-12) for w, p, f in zip(wesn, poly, floor)])
        span = np.array([x["lag_span"][design] for x in results])
        chamber = candidate_profile(design).chamber
        gaps = identifiability_gaps(chamber)
        print(
            f"{design:14s} {chamber.duration_s / 60:5.0f} {np.median(wesn / floor):9.3f}x{(wesn / floor).max():9.3f}x "
            f"{np.median(ex):9.2f}x{ex.max():9.2f}x {np.median(poly / floor):9.3f}x{(poly / floor).max():9.3f}x "
            f"{np.median(span):9.2f}x{span.max():9.2f}x  " + ("; ".join(g.what for g in gaps) or "nothing")
        )
    raw = np.array([x["r"]["raw"] / x["r"]["floor"] for x in results])
    print(f"\nraw 1-min drift RMS / floor: median {np.median(raw):.2f}x, range {raw.min():.2f}..{raw.max():.2f}x")
    print("targets (issue 30, evaluation range): worst e / e_poly <= 1.0x; r / floor worst <= 2x, median <= 1.15x")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--instruments", type=int, default=12, help="how many development instruments")
    parser.add_argument("--first", type=int, default=0, help="start this many instruments into the dev set")
    parser.add_argument("--designs", default=",".join(CANDIDATES), help=f"of {', '.join(CANDIDATES)}")
    parser.add_argument("--rate-hz", type=int, default=10, help="frame rate of the simulated runs")
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--workdir", type=Path, help="cache the simulated captures here (default: a temporary dir)")
    parser.add_argument("--reuse", type=Path, help="read captures of built-in and configs/ profiles from here")
    parser.add_argument("--per-instrument", action="store_true", help="print each instrument's figures")
    args = parser.parse_args()
    designs = tuple(d.strip() for d in args.designs.split(",") if d.strip())
    unknown = [d for d in designs if d not in CANDIDATES]
    if unknown:
        parser.error(f"unknown designs {', '.join(unknown)} (known: {', '.join(CANDIDATES)})")
    seeds = instrument_seeds("dev", args.first, args.instruments)
    with kept_or_temporary(args.workdir) as workdir:
        t0 = time.perf_counter()
        n = len(seeds)
        results = []
        for x in in_pool(
            score_instrument, args.workers, seeds, [designs] * n, [args.rate_hz] * n, [workdir] * n, [args.reuse] * n
        ):
            results.append(x)
            if args.per_instrument:
                print(
                    f"instrument {x['seed']:3d}: floor {x['r']['floor']:.4f} raw {x['r']['raw']:.4f} "
                    + " ".join(
                        f"{d} {x['r'][d, 'wesn']:.4f}/{x['r'][d, 'polynomial']:.4f} "
                        f"(lag {x['lag_s'][d]:g} s, x{x['lag_span'][d]:.2f})"
                        for d in designs
                    ),
                    flush=True,
                )
        print(
            f"\ndev set: {len(seeds)} instruments (seeds {seeds[0]}..{seeds[-1]}); each design's run fitted "
            f"(wesn and polynomial), scored on {' and '.join(SCORE_PROFILES)} at {args.rate_hz} Hz  "
            f"[{time.perf_counter() - t0:.0f} s]\n"
        )
        summarize(results, designs)


if __name__ == "__main__":
    from benchmarks._harness import run_main  # --update-readme: the documentation's block for this command

    run_main(main)
