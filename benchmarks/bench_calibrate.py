"""``fog-driver calibrate`` against the simulated lab for as long as a short calibration (issue 48's target: at 100 Hz
for 10 minutes, no frame lost and the chamber log complete).

    python -m benchmarks.bench_calibrate [--minutes 10] [--scheme espec]

Serves the instrument at 100 Hz on a pty and a chamber on ``--scheme``'s protocol (``fog-driver simulate --serve
pty --chamber-serve``), runs ``fog-driver calibrate`` on them with a program of ``--minutes`` (ramps of 1 degC/min
up and down around 20 degC, holds between), and prints what ``fog-driver inspect --json`` finds in the capture
(frames, CRC errors, missing frames) and in the chamber log (rows by state, program time covered, the largest
distance of a read-back set point from the program, the air's lag), with calibrate's CPU and the simulator's own
account. Figures are printed, never asserted.
"""

from __future__ import annotations

import argparse
import json
import re
import resource
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

import numpy as np

from fog_driver.lab.chamberlog import read_chamber_log
from fog_driver.lab.profiles import load_profile

OPTIONS = {"espec": "", "thermotron": "?range=-70:180", "simserv": "", "watlow-f4t": ""}


def program_text(minutes: float) -> str:
    """Holds and 1 degC/min ramps filling ``minutes``: a quarter held, a quarter up, a quarter held, a quarter down."""
    quarter_s = minutes * 60 / 4
    rise_c = quarter_s / 60.0
    return (
        f"name: bench-{minutes:g}min\nstart_c: 20\nsegments:\n- hold: {{duration_s: {quarter_s:g}}}\n"
        f"- ramp: {{rate_c_per_min: 1, target_c: {20 + rise_c:g}}}\n- hold: {{duration_s: {quarter_s:g}}}\n"
        f"- ramp: {{rate_c_per_min: 1, target_c: 20}}\n"
    )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--minutes", type=float, default=10.0)
    parser.add_argument("--scheme", choices=sorted(OPTIONS), default="espec")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        work = Path(folder)
        (work / "p.yaml").write_text(program_text(args.minutes))
        link = str(work / "sim.tty")
        lab = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "fog_driver",
                "simulate",
                "--serve",
                "pty",
                "--rate-hz",
                "100",
                "--link",
                link,
                "--chamber-serve",
                f"{args.scheme}://127.0.0.1:0?start_c=20",
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        assert lab.stdout is not None
        url = re.sub(r"\?.*", "", lab.stdout.readline().split()[-1]) + OPTIONS[args.scheme]
        lab.stdout.readline()  # the pty is served
        wall0_s = time.monotonic()
        calibrate = subprocess.run(
            [
                sys.executable,
                "-m",
                "fog_driver",
                "calibrate",
                link,
                "--chamber",
                url,
                "--profile",
                str(work / "p.yaml"),
                "--out",
                str(work / "run.bin"),
            ],
            capture_output=True,
            text=True,
        )
        wall_s = time.monotonic() - wall0_s
        calibrate_cpu_s = resource.getrusage(resource.RUSAGE_CHILDREN)
        lab.terminate()
        lab_out, _ = lab.communicate()
        if calibrate.returncode != 0:
            print(f"calibrate failed ({calibrate.returncode}): {calibrate.stderr.strip()}")
            return 1
        inspect = subprocess.run(
            [sys.executable, "-m", "fog_driver", "inspect", "--json", str(work / "run.bin")],
            capture_output=True,
            text=True,
            check=True,
        )
        report = json.loads(inspect.stdout)
        log = read_chamber_log(work / "run.chamber.csv")
        program = load_profile(str(work / "p.yaml")).chamber
    states = Counter(row.state for row in log.rows)
    running = [row for row in log.rows if row.state == "running"]
    t_s = np.array([row.t_s for row in running])
    off_c = np.abs(np.array([row.setpoint_c for row in running]) - program.air_temp_c(t_s)).max()
    lag_c = np.abs(np.array([row.air_c for row in running]) - np.array([row.setpoint_c for row in running])).max()
    steps_expected = int(program.duration_s) + 1
    cpu_s = calibrate_cpu_s.ru_utime + calibrate_cpu_s.ru_stime
    print(f"calibrate against the simulated lab ({args.scheme}, 100 Hz), a {args.minutes:g}-min program:")
    print(f"  wall time             {wall_s:.1f} s")
    print(
        f"  capture               {report['sample_frames']:,} sample frames, {report['crc_errors']} CRC errors, "
        f"{report['missing_frames']} missing, {report['seq_gaps']} sequence gaps"
    )
    print(
        f"  chamber log           {len(running)} running rows of {steps_expected} steps, program time "
        f"{t_s[0]:g} to {t_s[-1]:g} s; states {dict(sorted(states.items()))}"
    )
    print(f"  set point off program {off_c:.3f} degC at most; air from set point {lag_c:.2f} degC at most")
    print(f"  calibrate's CPU       {cpu_s:.1f} s over {wall_s:.0f} s = {100 * cpu_s / wall_s:.2f} % of a core")
    print(f"  simulator             {lab_out.strip().splitlines()[-1] if lab_out.strip() else ''}")
    return 0


if __name__ == "__main__":
    from benchmarks._harness import run_main  # --update-readme: the documentation's block for this command

    run_main(main)
