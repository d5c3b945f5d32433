"""The chamber runner over real time (issue 48's targets): the lateness of the set-point writes and the host's CPU.

    python -m benchmarks.bench_chamber [--seconds 10] [--step-s 1] [--chamber URL | --serve SCHEME]

Runs a ramp (1 degC/min from 20 degC, as long as ``--seconds``) through ``fog_driver.lab.runner.run_program`` on
the host's clock, a set point every ``--step-s``, against an in-process chamber (its air following the set point
with a 60-s lag, answering at once) or the controller ``--chamber`` names (``sim://`` for the simulated lab's),
or the simulated lab's chamber served by another process on ``--serve``'s protocol (``espec``, ``thermotron``,
``simserv``, ``watlow-f4t``: the driver's whole path over loopback TCP, the server's CPU not counted),
logging to a temporary chamber log.  Printed: the steps, the write's lateness after its due time (median, p99,
worst), the process's CPU time per step and as a share of a core over the run's wall time, and the largest
distance of a written set point from the program at its program time.  Figures are printed, never asserted
(targets: p99 lateness <= 100 ms at 1-s steps; at most 1 % of a core).
"""

from __future__ import annotations

import argparse
import math
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from fog_driver.lab.chamberlog import ChamberLogWriter, LogHeader, program_sha256, read_chamber_log
from fog_driver.lab.controllers.base import ChamberController, ChamberRange, ChamberStatus
from fog_driver.lab.program import ChamberProfile, Ramp
from fog_driver.lab.runner import RunOptions, SystemClock, run_program


class InProcessChamber:
    """A chamber in memory: its air lags the set point (first order, ``lag_s``), on the host's clock."""

    url = "in-process://chamber"
    address = "in-process:chamber"
    resolution_c = 0.1

    def __init__(self, air_c: float = 20.0, lag_s: float = 60.0) -> None:
        self.air_c, self.setpoint_c, self.lag_s = air_c, air_c, lag_s
        self._at_s = time.monotonic()

    def _follow(self) -> None:
        now_s = time.monotonic()
        self.air_c += (self.setpoint_c - self.air_c) * (1.0 - math.exp(-(now_s - self._at_s) / self.lag_s))
        self._at_s = now_s

    def connect(self) -> None:
        return None

    def close(self) -> None:
        return None

    def safe_stop(self) -> None:
        return None

    def read_air_c(self) -> float:
        self._follow()
        return self.air_c

    def read_setpoint_c(self) -> float:
        return self.setpoint_c

    def write_setpoint_c(self, setpoint_c: float) -> None:
        self._follow()
        self.setpoint_c = setpoint_c

    def read_range_c(self) -> ChamberRange:
        return ChamberRange(-70.0, 180.0)

    def read_status(self) -> ChamberStatus:
        return ChamberStatus("constant")


def open_chamber(url: str | None) -> ChamberController:
    if url is None:
        return InProcessChamber()
    from fog_driver.cli.lab import open_chamber as open_url

    controller = open_url(url, None)
    controller.connect()
    return controller


SERVE_OPTIONS = {"espec": "", "thermotron": "?range=-70:180", "simserv": "", "watlow-f4t": ""}

SERVER = """
import sys, threading
from fog_driver.sim.chamber import ChamberParams, SimChamber, StartedClock
from fog_driver.sim.chamber_serve import serve_chamber
clock = StartedClock(1.0); clock.start()
with serve_chamber(sys.argv[1] + "://127.0.0.1:0", SimChamber(clock, ChamberParams(start_c=20.0))) as server:
    print(server.url, flush=True)
    sys.stdin.read()
"""


def serve(scheme: str) -> tuple[subprocess.Popen, str]:
    """The simulated chamber served by a child process on ``scheme``'s protocol; its URL is its first line."""
    child = subprocess.Popen(
        [sys.executable, "-c", SERVER, scheme], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    assert child.stdout is not None
    return child, child.stdout.readline().strip() + SERVE_OPTIONS[scheme]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=10.0, help="the run's length, s of real time")
    parser.add_argument("--step-s", type=float, default=1.0)
    parser.add_argument("--chamber", metavar="URL", help="a controller instead of the in-process chamber")
    parser.add_argument("--serve", choices=sorted(SERVE_OPTIONS), help="the simulated chamber served on a protocol")
    args = parser.parse_args()
    server = None
    if args.serve:
        server, args.chamber = serve(args.serve)
    program = ChamberProfile("bench", 20.0, (Ramp(1.0, 20.0 + args.seconds / 60.0),))
    controller = open_chamber(args.chamber)
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "chamber.csv"
        log = ChamberLogWriter(path, LogHeader(program.name, program_sha256(program), controller.url, "bench", None))
        cpu0_s, wall0_s = time.process_time(), time.monotonic()
        result = run_program(
            controller,
            program,
            log,
            options=RunOptions(step_s=args.step_s),
            clock=SystemClock(),
            stop=threading.Event(),
        )
        cpu_s, wall_s = time.process_time() - cpu0_s, time.monotonic() - wall0_s
        log.close()
        rows = [r for r in read_chamber_log(path).rows if r.state == "running"]
    controller.close()
    if server is not None:
        server.communicate("")
    lateness_ms = np.array(result.lateness_s) * 1e3
    off_c = max(abs(r.setpoint_c - float(program.air_temp_c(np.array([r.t_s]))[0])) for r in rows)  # read back
    print(f"chamber runner, {args.step_s:g}-s steps over {wall_s:.1f} s against {controller.url}:")
    print(f"  steps                 {len(lateness_ms)}")
    print(
        f"  write lateness        median {np.median(lateness_ms):.2f} ms, p99 {np.percentile(lateness_ms, 99):.2f} ms,"
        f" worst {lateness_ms.max():.2f} ms"
    )
    print(
        f"  host CPU              {cpu_s / len(lateness_ms) * 1e3:.3f} ms a step,"
        f" {100 * cpu_s / wall_s:.3f} % of a core"
    )
    print(f"  set point off program {off_c:.3f} degC at most (resolution {controller.resolution_c:g} degC)")


if __name__ == "__main__":
    from benchmarks._harness import run_main  # --update-readme: the documentation's block for this command

    run_main(main)
