"""How long the README's walkthrough takes: each command's wall time, as a range over repetitions.

Runs the README's marked walkthrough blocks (``readme_walkthrough.py``) in a new temporary directory
per repetition, in this Python's environment (the install lines are skipped: they time the package
index, not fog_driver), plus the commands the README quotes a time for outside the walkthrough (the
``pso-svr`` fit, the paper's experiment).  Prints, per command, the fastest and the slowest of the
repetitions; the README's timings are this range::

    python -m benchmarks.bench_walkthrough [--repeat N] [--update-readme]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

from benchmarks import readme_walkthrough as walkthrough
from benchmarks._harness import run_main

ROOT = Path(__file__).resolve().parents[1]
#: Commands the README gives a time for outside the walkthrough, run after it in the same directory: as shown,
#: and as run (a benchmark from the repository's top).
EXTRA = {
    "fog-driver fit chamber.bin --kind pso-svr --validate check.bin --out svr.yaml": (
        "fog-driver fit chamber.bin --kind pso-svr --validate check.bin --out svr.yaml"
    ),
    "python -m benchmarks.paper_experiment": f"cd {ROOT} && python -m benchmarks.paper_experiment",
}
READY_TIMEOUT_S = 60.0
LINE_TIMEOUT_S = 1800.0


def one_pass(directory: Path, venv_bin: Path) -> dict[str, float]:
    """Wall seconds per command for one run of the walkthrough (and EXTRA) in ``directory``."""
    env = walkthrough.environment(directory, venv_bin)
    times: dict[str, float] = {}
    background = None
    try:
        for step in walkthrough.all_steps():
            if step.kind == "output":  # what a command printed: nothing to run
                continue
            if step.kind == "stop":
                status = background.stop(READY_TIMEOUT_S)
                if status != 0:
                    raise SystemExit(f"{background.command!r} exited {status}")
                background = None
            elif step.kind == "background":
                start = time.perf_counter()
                background = walkthrough.Background(step.commands[0], directory, env)
                background.read_until(step.ready_text, READY_TIMEOUT_S)
                times[f"{step.commands[0].split('#')[0].strip()}  (until ready)"] = time.perf_counter() - start
            else:
                for command in step.commands:
                    if walkthrough.INSTALL.match(command):
                        continue
                    times[command.split("#")[0].strip()] = _timed(command, directory, env)
        for shown, command in EXTRA.items():
            times[shown] = _timed(command, directory, env)
    finally:
        if background is not None:
            background.kill()
    return times


def _timed(command: str, directory: Path, env: dict[str, str]) -> float:
    start = time.perf_counter()
    done = walkthrough.run_line(command, directory, env, LINE_TIMEOUT_S)
    elapsed = time.perf_counter() - start
    if done.returncode != 0:
        raise SystemExit(f"{command!r} exited {done.returncode}: {done.stderr.strip()[-500:]}")
    return elapsed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3, help="repetitions (default 3)")
    args = parser.parse_args()
    venv_bin = Path(sys.executable).parent
    runs = []
    for _ in range(args.repeat):
        with tempfile.TemporaryDirectory(prefix="fog-walkthrough-") as tmp:
            runs.append(one_pass(Path(tmp), venv_bin))
    width = max(len(c) for c in runs[0])
    print(f"{'command':<{width}}  wall s, fastest to slowest of {args.repeat}")
    for command in runs[0]:
        seconds = [run[command] for run in runs]
        print(f"{command:<{width}}  {min(seconds):5.1f} to {max(seconds):5.1f}")


if __name__ == "__main__":
    run_main(main)
