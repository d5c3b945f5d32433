"""`fog-driver inspect` on a paper-sized capture: wall time and peak memory.

    python -m benchmarks.bench_inspect [--frames N] [--keep PATH]

Writes a capture of N SAMPLE frames (default 2,640,000: the paper's 440-minute
profile at 100 Hz; 26,400,000 is the same run at 1 kHz) to a temporary file,
then runs, each in a fresh process so peak RSS is its own:

* ``inspect``: the CLI, decoding and summarizing block by block;
* baseline: reading the whole file and decoding it in one ``decode_bytes`` call.

Prints wall time, frames/s and peak RSS of each, and their ratios.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.bench_decode import make_capture

ROOT = Path(__file__).resolve().parents[1]

# Peak RSS from VmHWM: per address space, reset at exec (ru_maxrss keeps the forking parent's peak).
PEAK_KB = "int(next(l for l in open('/proc/self/status') if l.startswith('VmHWM')).split()[1])"

ONE_SHOT = """
import sys, time
from pathlib import Path
from fog_driver.protocol import decode_bytes
t0 = time.perf_counter()
d = decode_bytes(Path(sys.argv[1]).read_bytes())
print(time.perf_counter() - t0, d.counters.sample_frames, PEAK_KB)
""".replace("PEAK_KB", PEAK_KB)

INSPECT = """
import sys, time
from fog_driver.cli import main
t0 = time.perf_counter()
status = main(["inspect", "--json", sys.argv[1]])
print(time.perf_counter() - t0, status, PEAK_KB, file=sys.stderr)
""".replace("PEAK_KB", PEAK_KB)

IDLE = "import fog_driver.cli; print(PEAK_KB)".replace("PEAK_KB", PEAK_KB)


def run(code: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, check=True, cwd=ROOT)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=2_640_000)
    parser.add_argument("--keep", type=Path, help="write the capture here and keep it")
    args = parser.parse_args()

    with tempfile.TemporaryDirectory() as tmp:
        path = args.keep or Path(tmp) / "bench.bin"
        t0 = time.perf_counter()
        data, _ = make_capture(args.frames)
        path.write_bytes(data)
        size_mb = len(data) / 1e6
        del data
        print(f"capture: {args.frames:,} SAMPLE frames, {size_mb:.1f} MB (written in {time.perf_counter() - t0:.1f} s)")

        idle_kb = int(run(IDLE).stdout)
        proc = run(INSPECT, str(path))
        t_inspect, status, rss_inspect_kb = proc.stderr.split()[-3:]
        report = json.loads(proc.stdout)
        assert report["sample_frames"] == args.frames and report["crc_errors"] == 0, report
        t_shot, n_shot, rss_shot_kb = run(ONE_SHOT, str(path)).stdout.split()
        assert int(n_shot) == args.frames

    t_inspect, t_shot = float(t_inspect), float(t_shot)
    print(f"interpreter + imports          peak RSS {int(idle_kb) / 1e3:7.0f} MB")
    print(
        f"inspect (block by block)      {t_inspect:6.2f} s  {args.frames / t_inspect:>12,.0f} frames/s  "
        f"peak RSS {int(rss_inspect_kb) / 1e3:7.0f} MB"
    )
    print(
        f"baseline: one-shot decode     {t_shot:6.2f} s  {args.frames / t_shot:>12,.0f} frames/s  "
        f"peak RSS {int(rss_shot_kb) / 1e3:7.0f} MB"
    )
    print(f"inspect peak RSS / capture size   {int(rss_inspect_kb) / 1e3 / size_mb:.2f} x")
    print(f"baseline peak RSS / capture size  {int(rss_shot_kb) / 1e3 / size_mb:.2f} x")


if __name__ == "__main__":
    from benchmarks._harness import run_main  # --update-readme: the documentation's block for this command

    run_main(main)
