"""The simulator: generating captures, and serving a live stream in real time.

    python -m benchmarks.bench_sim [--serve-seconds S] [--rate-hz R] [--skip-generate]

(a) Generation: the ``paper`` profile (440 minutes) at 100 Hz to a capture file
    (with its sidecar and truth file, as ``fog-driver simulate --out`` writes it;
    target <= 20 s), then the first hour of it at 1 kHz.  Wall time and frames/s.

(b) Serving: ``serve_pty`` streams R Hz (default 1 kHz) in real time for S
    seconds (default 20) to a pty whose reader is a separate process (so its CPU is
    not counted).  The serving process's CPU seconds / wall seconds as % of one
    core (target <= 10 %), late writes, dropped bytes, and the bytes the reader got.
    Baseline in the same run: the same loop and pty, but the bytes are
    pre-generated (the loop only sleeps on the schedule and writes), so the ratio
    is the price of computing the instrument live.

No assertions: it prints figures.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from fog_driver.console import configure_logging
from fog_driver.lab.profiles import load_profile
from fog_driver.protocol import SAMPLE_FRAME_LEN, decode_bytes
from fog_driver.sim.capture import simulate_to_file
from fog_driver.sim.faults import FaultSpec
from fog_driver.sim.instrument import Simulator
from fog_driver.sim.serve import PtyServer, ServeStats, serve_pty

# The reader: opens the pty (through the link) raw, says "ready", reads until the pty is unplugged.
READER = """
import os, sys
fd = os.open(sys.argv[1], os.O_RDONLY | os.O_NOCTTY)
print("ready", flush=True)
n = 0
while True:
    try:
        data = os.read(fd, 65536)
    except OSError:
        break
    if not data:
        break
    n += len(data)
print(n, flush=True)
"""


class Pregenerated:
    """Looks like a ``Simulator`` to ``serve`` but hands out slices of bytes made beforehand."""

    def __init__(self, sim: Simulator, frames: int) -> None:
        self.rate_hz = sim.rate_hz
        self.period_true_s = sim.period_true_s
        self.profile = sim.profile
        self.faults = FaultSpec()
        self._frames = frames
        self.data = b"".join(data for _, data in sim.batches(10 * sim.rate_hz, frames))
        # Frame k's bytes end where its SAMPLE frame ends (IDENTITY frames go with the next sample).
        self._ends = [0, *(decode_bytes(self.data).samples.offset + SAMPLE_FRAME_LEN).tolist()]
        self.next_frame = 0

    def total_frames(self) -> int:
        return self._frames

    def stream(self, n: int) -> tuple[None, bytes]:
        k = self.next_frame
        self.next_frame += n
        return None, self.data[self._ends[k] : self._ends[k + n]]


def serve_to_reader(sim, seconds: float, link: Path) -> tuple[ServeStats, int]:
    """``serve_pty`` for ``seconds`` with a reader process on the link; (stats, bytes the reader got)."""
    reader: list[subprocess.Popen] = []

    def on_ready(server: PtyServer) -> None:
        proc = subprocess.Popen([sys.executable, "-c", READER, str(server.link)], stdout=subprocess.PIPE, text=True)
        reader.append(proc)
        assert proc.stdout.readline().strip() == "ready"

    try:
        stats = serve_pty(sim, link=link, duration_s=seconds, on_ready=on_ready)
        received = int(reader[0].stdout.readline())
        reader[0].wait(30)
    finally:
        for proc in reader:
            if proc.poll() is None:
                proc.kill()
    return stats, received


def print_serving(label: str, stats: ServeStats, received: int) -> None:
    pct = 100.0 * stats.process_cpu_s / stats.wall_s
    print(
        f"{label:<28} {stats.process_cpu_s:6.2f} s CPU / {stats.wall_s:6.2f} s wall = {pct:5.2f} % of one core;  "
        f"{stats.late_writes} late writes, {stats.dropped_bytes} bytes dropped, "
        f"{received:,} of {stats.bytes:,} bytes received"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--serve-seconds", type=float, default=20.0, help="real-time serving run length (default 20)")
    parser.add_argument("--rate-hz", type=int, default=1000, help="serving rate (default 1000)")
    parser.add_argument("--skip-generate", action="store_true", help="skip (a), the capture generation timings")
    args = parser.parse_args()
    configure_logging(0)  # warnings only (a stall would be one)
    paper = load_profile("paper")

    with tempfile.TemporaryDirectory() as tmp:
        tmp_path = Path(tmp)
        if not args.skip_generate:
            for rate, duration_s, label in (
                (100, None, "paper at 100 Hz, whole"),
                (1000, 3600.0, "paper at 1 kHz, 1st hour"),
            ):
                sim = Simulator(paper, rate_hz=rate, seed=0)
                t0 = time.perf_counter()
                result = simulate_to_file(sim, tmp_path / f"paper-{rate}.bin", duration_s=duration_s)
                dt = time.perf_counter() - t0
                print(
                    f"generate {label:<25} {result.frames:>10,} frames  {result.bytes / 1e6:6.1f} MB  "
                    f"{dt:6.1f} s  {result.frames / dt:>10,.0f} frames/s"
                )

        seconds = args.serve_seconds
        frames = round(seconds * args.rate_hz)
        print(f"serving {seconds:g} s at {args.rate_hz} Hz in real time to a pty read by another process")
        live = Simulator(paper, rate_hz=args.rate_hz, seed=0)
        stats, received = serve_to_reader(live, seconds, tmp_path / "live.tty")
        print_serving("live simulator", stats, received)
        canned = Pregenerated(Simulator(paper, rate_hz=args.rate_hz, seed=0), frames)
        base, base_received = serve_to_reader(canned, seconds, tmp_path / "canned.tty")
        print_serving("baseline: pre-generated", base, base_received)
        print(f"live CPU / baseline CPU {stats.process_cpu_s / base.process_cpu_s:10.1f} x")


if __name__ == "__main__":
    from benchmarks._harness import run_main  # --update-readme: the documentation's block for this command

    run_main(main)
