"""How often a wrong table angle is learned: a lie at every dwell in turn (issue 32).

    python -m benchmarks.bench_table_lies [--set dev|eval5|...] [--first K] [--instruments N] [--sigmas 5]
                                          [--workers 2] [--workdir DIR]

Per instrument K of a set (the seed ranges and THE RULE of ``_harness.py``): the default model fitted on its
paper run and the positioning run ``table-run`` with its table log, as in ``bench_table.py``.  The table law's
inputs (its blocks, the dwells it observes and the breaks, in order) are recorded once from the compensator
adapting from the true log; the law alone, replayed from its state before the first block, gives the same
outcomes (checked).  Then, for every dwell the law learned but the first five and the last, and for both signs,
the law is replayed with that dwell's angle off by ``--sigmas`` sigmas of its interval's innovation (the sigma the
honest run reported for it, as ``bench_table.py``'s lie).  Printed per instrument and in all: the lies tried, the
lies not rejected (learned, through their own interval or an interval around them), and the honest dwells next to
a lie (the one before, the one after) that were rejected although the honest run learned them.  Figures are
printed, never asserted.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from benchmarks._harness import FIT_PROFILE, FIT_RUN, capture, instrument_arguments, over_instruments
from benchmarks.bench_table import TABLE_RUN, per_second, read_table_log, table_profile
from fog_driver.cli.calibration import DEFAULT_FIT_KIND
from fog_driver.compensation.adapt import AdaptConfig
from fog_driver.compensation.fitting.data import FitConfig
from fog_driver.compensation.table import TableLaw, TableOutcome
from fog_driver.dwells import Dwell
from fog_driver.offline.fit import fit_model_file
from fog_driver.sim.capture import read_truth
from fog_driver.sim.tablelog import lie

SKIP_FIRST = 5  #: learned dwells left out at the start (the bias capture, the law's first intervals)


@contextlib.contextmanager
def recording(log: list[Dwell]) -> Iterator[dict[str, Any]]:
    """While in the block, every ``TableLaw``'s ``block``, ``observe`` (as the dwell's index in ``log``),
    ``_break`` and ``begin_run`` calls are recorded in order (``"events"``), and the law's state before the first
    of them is kept (``"law"``)."""
    out: dict[str, Any] = {"events": []}
    names = ("block", "observe", "_break", "begin_run")
    originals = {name: getattr(TableLaw, name) for name in names}

    def wrap(name: str) -> Any:
        def call(self: TableLaw, *args: Any) -> Any:
            if "law" not in out:
                if name == "_break":  # the constructor's own break, before any input
                    return originals[name](self, *args)
                out["law"] = copy.deepcopy(self)
            out["events"].append((name, log.index(args[0]) if name == "observe" else args))
            return originals[name](self, *args)

        return call

    for name in names:
        setattr(TableLaw, name, wrap(name))
    try:
        yield out
    finally:
        for name, original in originals.items():
            setattr(TableLaw, name, original)


def replay(law0: TableLaw, events: list[tuple[str, Any]], dwells: list[Dwell]) -> dict[int, TableOutcome]:
    """The law from ``law0`` through ``events`` with ``dwells`` for the log: each dwell's outcome, by index (as
    the law holds it at the end: the neighbours' judgement may have changed it since)."""
    law = copy.deepcopy(law0)
    order = []
    for name, args in events:
        if name == "observe":
            law.observe(dwells[args])
            order.append(args)
        else:
            getattr(law, name)(*args)
    outcomes = list(law.outcomes)
    assert len(outcomes) == len(order), "more outcomes than dwells observed"
    return dict(zip(order, outcomes))


def lies_of(seed: int, sigmas: float, workdir: Path) -> dict[str, Any]:
    fit_run = capture(workdir, seed, FIT_PROFILE, 10 * seed + FIT_RUN, 10)
    model_file, _ = fit_model_file(
        [fit_run], kind=DEFAULT_FIT_KIND, config=FitConfig(), fall_back=True, accept_weak=True
    )
    path = capture(workdir, seed, table_profile(), 10 * seed + TABLE_RUN, 10)
    n = len(read_truth(path.with_suffix(".truth.csv"))["second"])
    log = read_table_log(path.with_suffix(".table.csv"))
    with recording(log) as rec:
        _, _, comp = per_second(path, model_file, n, adapt=AdaptConfig(), table_dwells=log)
    assert comp is not None and comp.table is not None
    honest = replay(rec["law"], rec["events"], log)
    live = [o.status for o in comp.table.outcomes]
    assert [honest[i].status for i in sorted(honest)] == live, f"instrument {seed}: the replay differs from the run"
    learned = [i for i in sorted(honest) if honest[i].status == "learned"]
    tried = escaped = blamed = 0
    for k in learned[SKIP_FIRST:-1]:
        for sign in (1.0, -1.0):
            lied = lie(log, k, sign * sigmas * honest[k].sigma_arcsec / 3600.0)
            out = replay(rec["law"], rec["events"], lied)
            tried += 1
            escaped += out[k].status != "rejected"
            blamed += sum(
                out[j].status == "rejected" for j in (k - 1, k + 1) if j in out and honest[j].status == "learned"
            )
    return {
        "seed": seed,
        "dwells": len(log),
        "learned": len(learned),
        "tried": tried,
        "escaped": escaped,
        "blamed": blamed,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    instrument_arguments(parser, instruments=12)
    parser.add_argument("--sigmas", type=float, default=5.0)
    args = parser.parse_args()
    t0 = time.perf_counter()
    seeds, results = over_instruments(args, lies_of, args.sigmas)
    print(
        f"set {args.set}: {len(seeds)} instruments from {seeds[0]}, lies of {args.sigmas:g} sigmas, "
        f"{time.perf_counter() - t0:.0f} s"
    )
    for x in results:
        print(
            f"  {x['seed']:6d} dwells {x['dwells']} learned {x['learned']}: {x['tried']} lies, "
            f"{x['escaped']} not rejected, {x['blamed']} honest neighbours rejected"
        )
    tried = sum(x["tried"] for x in results)
    escaped = sum(x["escaped"] for x in results)
    blamed = sum(x["blamed"] for x in results)
    print(
        f"lies not rejected   {escaped} of {tried} ({100 * escaped / max(tried, 1):.2f} %); honest neighbours "
        f"rejected {blamed} ({100 * blamed / max(tried, 1):.2f} % of lies)"
    )


if __name__ == "__main__":
    main()
