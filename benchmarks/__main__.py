"""Every benchmark whose figures the documents quote, in one place: ``python -m benchmarks`` runs the quick ones
one after another and rewrites their blocks (``--update-readme``); the long ones are named here with their run
time and rewrite their own blocks when run (their command plus ``--update-readme``).

    python -m benchmarks [--list] [--only KEY_PREFIX,...]

Each entry is a block's name (``benchmarks._harness.block_key``: the script's file name and its arguments) and
about how long it runs on an idle 2-core machine.  ``--list`` prints both lists and runs nothing; ``--only``
runs the quick entries whose names start with one of the prefixes.  A benchmark that fails stops the run
(its block is left as it was: a block is written only after its benchmark succeeded).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from typing import NamedTuple

from benchmarks._harness import ROOT, command_of


class Entry(NamedTuple):
    key: str  #: the block's name: ``bench_x.py ARGS``
    run_s: float  #: about how long it runs on an idle 2-core machine
    needs: str = ""  #: what it needs beyond the test extra, if anything


#: Seconds, or a few minutes: ``python -m benchmarks`` runs these.
QUICK = (
    Entry("bench_decode.py", 15),
    Entry("bench_kvh_decode.py", 20),
    Entry("bench_sim.py", 30),
    Entry("bench_model_step.py", 60),
    Entry("paper_experiment.py", 30),
    Entry("bench_accuracy.py --skip-1khz", 90),
    Entry("bench_daemon.py --seconds 20 --stress-seconds 0 --baseline-seconds 0 --frames 0 --oneshot-frames 0", 40),
    Entry("bench_formats_daemon.py", 150),
)
#: Run one at a time, by hand, on a quiet machine: ``python -m benchmarks.bench_x ARGS --update-readme``.
LONG = (
    Entry("bench_inspect.py --frames 26400000", 90, "2 GB of memory (the one-shot baseline) and 700 MB of disk"),
    Entry("bench_daemon.py --frames 10000000", 420),
    Entry("bench_web.py", 120, "Chromium (Playwright drives it)"),
    Entry("bench_web_load.py", 150),
    Entry("bench_formats_daemon.py --candidates --pairs 4", 200),
    Entry("bench_network_reconnect.py", 240, "socat and ser2net"),
    Entry("bench_walkthrough.py", 300),
    Entry("bench_chamber.py --seconds 60 --serve espec", 65),
    Entry("bench_chamber.py --seconds 60 --serve watlow-f4t", 65),
    Entry("bench_calibrate.py --minutes 10", 620),
    Entry("bench_thermo_fault.py", 220),
    Entry("bench_thermo_fault.py --fault stuck", 220),
    Entry("paper_experiment.py --instruments 24", 550),
    Entry("bench_adapt_creep.py --set eval3", 410),
    Entry("bench_adapt_creep.py --set eval2", 840),
    Entry("bench_population.py --set eval6 --compare-programs --per-instrument", 740),
    Entry("bench_population.py --adapt", 1290),
    Entry("bench_population.py --set dev --kinds auto --fit-profile paper", 200),
    Entry("bench_population.py --set dev --kinds auto --fit-profile calibration", 200),
    Entry("bench_population.py --set families-eval --kinds auto --family memory --fit-profile paper", 300),
    Entry("bench_population.py --set families-eval --kinds auto --family memory --fit-profile calibration", 300),
    Entry("bench_population.py --set families-eval --kinds auto --family layered --fit-profile paper", 300),
    Entry("bench_population.py --set families-eval --kinds auto --family layered --fit-profile calibration", 300),
    Entry("bench_population.py --set families-eval --kinds auto --family stress --fit-profile paper", 300),
    Entry("bench_population.py --set families-eval --kinds auto --family stress --fit-profile calibration", 300),
    Entry("bench_population.py --set families-eval --kinds auto --family correlated --fit-profile paper", 300),
    Entry("bench_population.py --set families-eval --kinds auto --family correlated --fit-profile calibration", 300),
    Entry("bench_population.py --set eval4 --compare-programs --per-instrument", 2600),
    Entry("bench_population.py --set eval4 --kinds polynomial,wesn,auto --per-instrument", 2680),
    Entry("bench_plan.py --instruments 24 --per-instrument", 3440),
    Entry("bench_table.py --instruments 24 --creeps 0.2,2,20 --days 3", 1210),
    Entry("bench_table.py --instruments 24 --creeps= --days 3", 860),
    Entry("bench_table.py --first 24 --creeps= --days 3", 1100),
    Entry("bench_table.py --set eval14 --instruments 24 --creeps 0.2,2,20 --days 3", 1330),
)


def _duration(seconds: float) -> str:
    return f"{seconds:.0f} s" if seconds < 120 else f"{seconds / 60:.0f} min"


def listing() -> str:
    """Both lists, with each entry's command, run time and needs."""
    lines = []
    for title, entries in (("quick (python -m benchmarks)", QUICK), ("long (each by hand)", LONG)):
        lines.append(f"{title}:")
        width = max(len(command_of(e.key)) for e in entries)
        for e in entries:
            needs = f"  needs {e.needs}" if e.needs else ""
            lines.append(f"  {command_of(e.key):<{width}}  {_duration(e.run_s):>7}{needs}")
    return "\n".join(lines)


def run(entry: Entry) -> float:
    """One benchmark with ``--update-readme``, from the repository's top; its wall seconds (``SystemExit`` when
    it fails)."""
    script, *arguments = entry.key.split()
    command = [sys.executable, "-m", "benchmarks." + script.removesuffix(".py"), *arguments, "--update-readme"]
    start = time.perf_counter()
    done = subprocess.run(command, cwd=ROOT)
    if done.returncode != 0:
        raise SystemExit(f"benchmarks: {command_of(entry.key)} exited {done.returncode}; its block is unchanged")
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(prog="python -m benchmarks", description=__doc__.splitlines()[0])
    parser.add_argument("--list", action="store_true", help="print the quick and the long benchmarks, run nothing")
    parser.add_argument("--only", default="", help="comma-separated prefixes of the quick entries to run")
    args = parser.parse_args()
    if args.list:
        print(listing())
        return
    prefixes = tuple(p.strip() for p in args.only.split(",") if p.strip())
    chosen = [e for e in QUICK if not prefixes or e.key.startswith(prefixes)]
    if not chosen:
        parser.error(f"--only {args.only!r} names no quick benchmark")
    times = [(e, run(e)) for e in chosen]
    print("\nbenchmarks: blocks rewritten", file=sys.stderr)
    for e, seconds in times:
        print(f"  {command_of(e.key)}  {seconds:.0f} s", file=sys.stderr)


if __name__ == "__main__":
    main()
