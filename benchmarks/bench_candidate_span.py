"""How much of the frozen model's error its candidate structures span, against the truth (issue 32).

    python -m benchmarks.bench_candidate_span [--set dev|eval5|...] [--first K] [--instruments N] [--workers 2]
                                              [--workdir DIR] [--per-instrument]

Per instrument K of a set (the seed ranges and THE RULE of ``_harness.py``): the default model fitted on its
paper run and the positioning run ``table-run``, as in ``bench_table.py``.  The model file keeps the candidate
structures of its fit (the coils that explain the fit data within the noise of the chosen one, ``uncertainty``);
each is run on the same capture as the model, and its drift's departure from the model's, ``d_c = D_c -
D_hat``, is a regressor.  The frozen model's error against the simulator's truth, ``e = D_true - D_hat`` (1-min
means, no noise, the minutes ``bench_table.py`` scores), is fitted by least squares on them and a constant,

    e ~ sum_c a_c d_c + b

the coefficients taken on one half of the scored minutes and applied to the other, both ways.  Printed: the RMS
of e about its mean within each half, and what is left of it with the other half's coefficients.  This is an
oracle (the truth gives the coefficients, not the table's intervals): it bounds what a table law modelling the
correction on the candidates' departures could reach, with a handful of coefficients where the law's shape now has
one per regressor.  Figures are printed, never asserted.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import time
from pathlib import Path

import numpy as np

from benchmarks._harness import FIT_PROFILE, FIT_RUN, capture, instrument_arguments, over_instruments
from benchmarks.bench_table import TABLE_RUN, per_second, scored_mask, table_profile
from fog_driver.cli.calibration import DEFAULT_FIT_KIND
from fog_driver.compensation.fitting.data import FitConfig
from fog_driver.dwells import read_table_log
from fog_driver.offline.fit import fit_model_file
from fog_driver.report.coverage import whole_minutes
from fog_driver.sim.capture import read_truth


def span_instrument(seed: int, rate_hz: int, workdir: Path) -> dict:
    fit_run = capture(workdir, seed, FIT_PROFILE, 10 * seed + FIT_RUN, rate_hz)
    model_file, _ = fit_model_file(
        [fit_run], kind=DEFAULT_FIT_KIND, config=FitConfig(), fall_back=True, accept_weak=True
    )
    path = capture(workdir, seed, table_profile(), 10 * seed + TABLE_RUN, rate_hz)
    truth = read_truth(path.with_suffix(".truth.csv"))
    n = len(truth["second"])
    mask = scored_mask(read_table_log(path.with_suffix(".table.csv")), n)
    frozen, _, _ = per_second(path, model_file, n)
    departures = []
    for candidate in model_file.candidate_models():
        as_model = dataclasses.replace(model_file, model=candidate, uncertainty=None)
        drift, _, _ = per_second(path, as_model, n)
        departures.append(drift - frozen)
    e_minutes, scored = whole_minutes(truth["drift_dph"][:n] - frozen, mask)
    e = e_minutes[scored]
    x = np.column_stack([*(whole_minutes(d, mask)[0][scored] for d in departures), np.ones(len(e))])
    half = len(e) // 2
    parts = (slice(0, half), slice(half, None))
    left, before = [], []
    for fit, apply in (parts, parts[::-1]):
        coef, *_ = np.linalg.lstsq(x[fit], e[fit], rcond=None)
        left.append(e[apply] - x[apply] @ coef)
        before.append(e[apply])
    return {
        "seed": seed,
        "candidates": len(departures),
        "frozen": math.sqrt(sum(float(np.var(b)) * len(b) for b in before) / len(e)),
        "left": math.sqrt(sum(float(np.var(v)) * len(v) for v in left) / len(e)),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    instrument_arguments(parser, instruments=24)
    parser.add_argument("--rate-hz", type=int, default=10)
    parser.add_argument("--per-instrument", action="store_true")
    args = parser.parse_args()
    t0 = time.perf_counter()
    seeds, results = over_instruments(args, span_instrument, args.rate_hz)
    print(f"set {args.set}: {len(seeds)} instruments from {seeds[0]}, {time.perf_counter() - t0:.0f} s")
    if args.per_instrument:
        for x in results:
            print(
                f"  {x['seed']:6d} {x['candidates']} candidates: frozen error {x['frozen']:.4f} deg/h, "
                f"left {x['left']:.4f} ({x['left'] / x['frozen']:.2f}x)"
            )
    ratio = np.array([x["left"] / x["frozen"] for x in results])
    print(
        f"frozen model's error (1-min, no noise) median {np.median([x['frozen'] for x in results]):.4f} deg/h; "
        f"left with the other half's coefficients median {np.median([x['left'] for x in results]):.4f} deg/h; "
        f"ratio median {np.median(ratio):.2f}x, worst {ratio.max():.2f}x"
    )


if __name__ == "__main__":
    main()
