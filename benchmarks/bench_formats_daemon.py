"""The daemon on other instruments' frame formats: does it keep up with a 1 kHz IMU at under 20 % of a core?

    python -m benchmarks.bench_formats_daemon [--quick] [--seconds S] [--tick-ms MS] [--warmup-s S]
    python -m benchmarks.bench_formats_daemon --candidates [--pairs N] [--seconds S]

Runs, each ``--seconds`` (default 20; ``--quick``: 5): fog-v1 at 1 kHz (the baseline), kvh-a and
ixblue-stdbin at 1 kHz, and kvh-a at 2560 Hz (what a KVH link at 921600 baud carries of Format A).

Method
------
Per format, beforehand and not timed: a polynomial model is fitted on a 900 s simulated capture of that
format (profile ``short-test``, seed 2; at ``FIT_RATE_HZ``: the model runs on 1 Hz block means of the
format's own temperature channels, so the device rate of its capture does not matter, and fitting a
non-fog-v1 capture at 1 kHz takes about a minute here), and a config written with ``format:``, ``model:``
and ``device:`` (the simulator's ``wire_settings`` from the capture's sidecar, at the run's rate).
Then, as ``benchmarks/bench_daemon.py``'s live runs (its helpers, imported): the frames are made by the
simulator (``short-test``, seed 1, the format's wire bytes), the daemon is started on a pty with
``--config FILE``, one watching client in a process of its own (``?WATCH={"enable":true};``), the frames
are paced into the pty master in real time (every ``--tick-ms``, one write of every frame due), and
measured: samples received by the client against sent (seq unwrapped; none may be lost), the daemon's
CPU (utime + stime from /proc) as % of one core over the run after ``--warmup-s`` (2 s), its VmRSS at
the end, and the client's p99 latency from the write to the line's arrival.  The CPU of each run is also
printed as a ratio to fog-v1 at 1 kHz measured in the same run.

``--candidates``: what the uncertainty's candidate structures cost the daemon.  fog-v1 at 1 kHz with the
shipped model (a ``wesn`` whose ``uncertainty`` section holds its candidates, each stepped once per model
block), against the same model with the candidates removed (``sigma_kind: residual``, the model as it ran
before the uncertainty existed), alternating ``--pairs`` times (default 3) in the same run; prints each run
and the mean difference of the CPU, with candidates minus without, in percentage points of a core.

Exits non-zero only when a sample was lost: the CPU figures are reported, never asserted (the machines
are shared).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

import yaml

from benchmarks.bench_daemon import LIVE_PROFILE, LiveResult, add_pacing_options, live_run
from fog_driver.compensation.fitting.data import FitConfig
from fog_driver.daemon.config import DEFAULT_MODEL
from fog_driver.lab.profiles import load_profile
from fog_driver.modelfiles import load_model, save_model
from fog_driver.offline.fit import fit_model_file
from fog_driver.samples.sources import wire_settings_for
from fog_driver.sim.capture import simulate_to_file
from fog_driver.sim.instrument import Simulator

FIT_RATE_HZ = 10
FIT_SECONDS = 900
BASELINE = ("fog-v1", 1000)
RUNS = [BASELINE, ("kvh-a", 1000), ("ixblue-stdbin", 1000), ("kvh-a", 2560)]


def fit_for(fmt: str, tmp: Path) -> tuple[Path, dict]:
    """A polynomial model fitted on a simulated capture of ``fmt``, and that capture's device settings."""
    sim = Simulator(load_profile(str(LIVE_PROFILE)), rate_hz=FIT_RATE_HZ, seed=2, wire_format=fmt)
    capture = simulate_to_file(sim, tmp / f"fit-{fmt}.bin", duration_s=FIT_SECONDS).capture
    fitted, _ = fit_model_file([capture], kind="polynomial", config=FitConfig(warmup_s=30.0), accept_weak=True)
    model = save_model(tmp / f"model-{fmt}.yaml", fitted)
    settings = wire_settings_for(capture).sidecar_fields().get("wire_settings", {})
    return model, {k: v for k, v in settings.items() if k != "axis"}


def write_config(tmp: Path, fmt: str, rate_hz: int, model: Path, device: dict) -> Path:
    doc: dict = {"format": fmt, "model": str(model)}
    if fmt != "fog-v1":  # protocol v1's frames say their rate
        doc["device"] = {**device, "rate_hz": rate_hz}
    path = tmp / f"{fmt}-{rate_hz}.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def line(fmt: str, r: LiveResult, base_cpu: float | None) -> str:
    c = r.clients[0]
    ratio = f"{r.cpu_pct / base_cpu:4.2f}x fog-v1" if base_cpu else "  (baseline) "
    vm_end = r.pacing.rss_end[0]
    return (
        f"  {fmt:14s} {r.rate_hz:5d} Hz  sent {c.written:7,}  received {c.unique:7,}  lost {c.lost:3d}  "
        f"CPU {r.cpu_pct:5.1f} % of a core  {ratio}  RSS {vm_end:5.1f} MB  p99 {c.pct(99):5.2f} ms"
    )


def candidates_run(args: argparse.Namespace) -> int:
    """``--candidates`` (module docstring); returns the samples lost."""
    shipped = load_model(DEFAULT_MODEL)
    spec = shipped.sigma_spec
    lost = 0
    with tempfile.TemporaryDirectory(prefix="bench-candidates-") as tmp:
        tmp_path = Path(tmp)
        bare = dataclasses.replace(shipped, uncertainty=dataclasses.replace(spec, sigma_kind="residual", candidates=()))
        models = {
            f"with {len(spec.candidates)} candidates": DEFAULT_MODEL,
            "without candidates": save_model(tmp_path / "bare.yaml", bare),
        }
        print(f"the shipped model ({shipped.kind}, {len(spec.candidates)} candidates) at 1 kHz, fog-v1", flush=True)
        cpu: dict[str, list[float]] = {label: [] for label in models}
        for _ in range(args.pairs):
            for label, model in models.items():
                config = write_config(tmp_path, "fog-v1", 1000, model, {})
                r = live_run(
                    "fog-v1",
                    1000,
                    args.seconds,
                    args.tick_ms / 1e3,
                    args.warmup_s,
                    1,
                    daemon_args=("--config", str(config)),
                )
                print(line(label, r, None).replace("  (baseline) ", ""), flush=True)
                cpu[label].append(r.cpu_pct)
                lost += r.clients[0].lost
    with_c, without = cpu.values()
    differences = [a - b for a, b in zip(with_c, without)]
    spread = statistics.stdev(differences) / len(differences) ** 0.5 if len(differences) > 1 else float("nan")
    print(
        f"CPU with candidates minus without: {statistics.mean(differences):+.2f} percentage points of a core "
        f"(standard error {spread:.2f}, {len(differences)} pairs); the target: within 1"
    )
    return lost


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="a short run: 5 s each")
    parser.add_argument("--seconds", type=float, default=20.0, help="length of each run (default 20)")
    add_pacing_options(parser, warmup_s=2.0)
    parser.add_argument(
        "--candidates", action="store_true", help="the shipped model with and without its candidates (docstring)"
    )
    parser.add_argument("--pairs", type=int, default=3, help="--candidates: runs of each (default 3)")
    args = parser.parse_args()
    if args.quick:
        args.seconds = 5.0
    if args.candidates:
        if candidates_run(args):
            sys.exit("samples lost")
        return
    print(
        f"daemon on other frame formats: {os.cpu_count()} cores, Python {platform.python_version()}, "
        f"{args.seconds:g} s per run, writer tick {args.tick_ms:g} ms, CPU after a {args.warmup_s:g} s warm-up, "
        f"one watching client{' (--quick)' if args.quick else ''}",
        flush=True,
    )
    wall0 = time.monotonic()
    lost = 0
    notes = []
    with tempfile.TemporaryDirectory(prefix="bench-formats-") as tmp:
        tmp_path = Path(tmp)
        fitted = {fmt: fit_for(fmt, tmp_path) for fmt in dict.fromkeys(fmt for fmt, _ in RUNS)}
        base_cpu = None
        for fmt, rate in RUNS:
            model, device = fitted[fmt]
            config = write_config(tmp_path, fmt, rate, model, device)
            r = live_run(
                fmt,
                rate,
                args.seconds,
                args.tick_ms / 1e3,
                args.warmup_s,
                1,
                wire_format=fmt,
                daemon_args=("--config", str(config)),
            )
            print(line(fmt, r, base_cpu), flush=True)
            if (fmt, rate) == BASELINE:
                base_cpu = r.cpu_pct
            lost += r.clients[0].lost
            threads = ", ".join(f"{name} {pct:.1f}" for name, pct in r.cpu_threads if pct >= 0.05)
            notes.append(f"{fmt} {rate} Hz: daemon CPU % by thread: {threads}; daemon exit {r.exit_code}")
    for note in notes:
        print(note)
    print(f"target: under 20 % of a core at 1 kHz, nothing lost; total wall time {time.monotonic() - wall0:.0f} s")
    if lost:
        sys.exit(f"{lost} samples lost")


if __name__ == "__main__":
    from benchmarks._harness import run_main  # --update-readme: the documentation's block for this command

    run_main(main)
