"""Start-up cost of config validation: the daemon's start, the config module, and the two candidate libraries.

    python -m benchmarks.bench_startup [--runs N]

Each figure is the median of N fresh interpreters (wall time, ms), so every import is paid in full:

- ``python -c pass``: the interpreter alone, the floor under every other line;
- ``import fog_driver.daemon.config``: the config module with everything it imports;
- ``load configs``: that import plus reading and validating every shipped config (the daemon's
  ``configs/default.yaml`` and ``configs/kvh-dsp1750.yaml``, the instrument's ``configs/sim/instrument.yaml``,
  the fit's ``configs/fit.yaml``) with the project's own loaders;
- ``fog-driver run``: from the process's start to its banner line (``... listening on ...``) on stdout, with
  ``configs/default.yaml``, a port that does not exist (the daemon retries it, so nothing waits on a device)
  and any free TCP port; then it is stopped with SIGTERM;
- ``msgspec`` and ``pydantic``: each library's import alone, timed inside a fresh interpreter before anything
  else; then, in the same interpreter after ``import fog_driver.daemon.config``, a schema of ``DriverConfig``
  and the validation of ``configs/default.yaml`` with it (``msgspec.convert`` of a ``Struct``; pydantic's
  ``TypeAdapter`` of the dataclass): together, the cost the library adds to the start.  A library that is
  not installed is reported as such.

Each line gives the median and the minimum of the wall time, and for the fresh processes the median CPU time
(user + system): on a busy shared machine the wall time waits for the neighbours, the CPU time much less.

No figure is asserted: the machines are shared and noisy, so the numbers are printed for a person to read.
"""

from __future__ import annotations

import argparse
import math
import os
import resource
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"

LOAD_CONFIGS = f"""
from fog_driver.daemon.config import load_config
from fog_driver.sim.instrument import load_instrument_config
from fog_driver.compensation.fitting.data import FitConfig
from fog_driver.files.typed_mapping import dataclass_from_mapping
from fog_driver.files.yamlio import read_yaml
for name in ("default.yaml", "kvh-dsp1750.yaml"):
    load_config({str(CONFIGS)!r} + "/" + name)
load_instrument_config({str(CONFIGS)!r} + "/sim/instrument.yaml")
fit_yaml = {str(CONFIGS)!r} + "/fit.yaml"
dataclass_from_mapping(FitConfig, read_yaml(fit_yaml, "fit config") or {{}}, fit_yaml)
"""

#: Two times inside one fresh interpreter, ms on stdout: the library's import alone (before anything of the
#: project's), then, after ``import fog_driver.daemon.config``, a schema of ``DriverConfig`` and one validation.
LIBRARY = {
    "msgspec": """
import time
t0 = time.perf_counter()
import msgspec
t1 = time.perf_counter()
import dataclasses, typing, yaml
import fog_driver.daemon.config as c
doc = yaml.safe_load(open({path!r}))
t2 = time.perf_counter()
def schema(cls):
    hints = typing.get_type_hints(cls)
    fields = [(f.name, (schema(hints[f.name]) if dataclasses.is_dataclass(hints[f.name]) else hints[f.name])
               | msgspec.UnsetType, msgspec.UNSET) for f in dataclasses.fields(cls)]
    return msgspec.defstruct(cls.__name__ + "Check", fields, forbid_unknown_fields=True)
msgspec.convert(doc or {{}}, schema(c.DriverConfig), strict=True)
print((t1 - t0) * 1e3, (time.perf_counter() - t2) * 1e3)
""",
    "pydantic": """
import time
t0 = time.perf_counter()
import pydantic
t1 = time.perf_counter()
import yaml
import fog_driver.daemon.config as c
doc = yaml.safe_load(open({path!r}))
t2 = time.perf_counter()
pydantic.TypeAdapter(c.DriverConfig).validate_python(doc or {{}})
print((t1 - t0) * 1e3, (time.perf_counter() - t2) * 1e3)
""",
}


def _env() -> dict[str, str]:
    """This checkout first on the path, so the figures are this tree's."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH", "")]))
    return env


def children_cpu_ms() -> float:
    """User + system CPU time of every waited-for child so far, ms."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return (usage.ru_utime + usage.ru_stime) * 1e3


def wall_ms(code: str) -> tuple[float, float]:
    """Wall time and CPU time of ``python -c code`` in a fresh interpreter, ms."""
    cpu0, t0 = children_cpu_ms(), time.perf_counter()
    subprocess.run([sys.executable, "-c", code], check=True, env=_env(), stdout=subprocess.DEVNULL)
    return (time.perf_counter() - t0) * 1e3, children_cpu_ms() - cpu0


def inner_ms(code: str) -> list[float] | None:
    """The times (ms) a fresh interpreter prints (None: the library is not installed)."""
    done = subprocess.run([sys.executable, "-c", code], env=_env(), capture_output=True, text=True)
    if done.returncode != 0:
        if "ModuleNotFoundError" in done.stderr:
            return None
        raise RuntimeError(done.stderr.strip().splitlines()[-1])
    return [float(v) for v in done.stdout.split()]


def run_banner_ms() -> tuple[float, float]:
    """``fog-driver run`` from the process's start to its banner on stdout, ms; then SIGTERM.  With the CPU time
    of its whole life (ms), the few ms between the banner and its stop included."""
    cpu0 = children_cpu_ms()
    wall = math.nan
    with tempfile.TemporaryDirectory() as tmp:
        command = [
            sys.executable,
            "-m",
            "fog_driver",
            "run",
            "--config",
            str(CONFIGS / "default.yaml"),
            "--port",
            str(Path(tmp) / "no-such-tty"),
            "--listen",
            "127.0.0.1:0",
            "--capture-dir",
            str(Path(tmp) / "captures"),
        ]
        t0 = time.perf_counter()
        proc = subprocess.Popen(
            command, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, cwd=tmp
        )
        try:
            assert proc.stdout is not None
            for line in proc.stdout:
                if "listening on" in line:
                    wall = (time.perf_counter() - t0) * 1e3
                    break
            else:
                raise RuntimeError(f"fog-driver run exited ({proc.wait()}) before its banner")
        finally:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
    return wall, children_cpu_ms() - cpu0


def spread(values: list[float]) -> str:
    """``median (min)`` in ms: the median a person compares; the minimum, the least disturbed by neighbours."""
    return f"{statistics.median(values):8.1f} ms (min {min(values):7.1f})"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=9, help="fresh interpreters per figure (default 9)")
    args = parser.parse_args(argv)
    default = str(CONFIGS / "default.yaml")
    rows: list[tuple[str, str]] = []
    for label, measure in (
        ("python -c pass", lambda: wall_ms("pass")),
        ("import fog_driver.daemon.config", lambda: wall_ms("import fog_driver.daemon.config")),
        ("  + load and validate the shipped configs", lambda: wall_ms(LOAD_CONFIGS)),
        ("fog-driver run, start to banner", run_banner_ms),
    ):
        results = [measure() for _ in range(args.runs)]
        cpu = statistics.median(r[1] for r in results)
        rows.append((label, f"{spread([r[0] for r in results])}  cpu {cpu:7.1f} ms"))
    for name, code in LIBRARY.items():
        results = [inner_ms(code.format(path=default)) for _ in range(args.runs)]
        if any(r is None for r in results):
            rows.append((f"{name}: not installed", ""))
            continue
        rows.append((f"{name}: import alone (in-process)", spread([r[0] for r in results if r])))
        rows.append((f"{name}: DriverConfig schema + validate default.yaml", spread([r[1] for r in results if r])))
    print(f"start-up, median of {args.runs} fresh interpreters ({sys.executable}, Python {sys.version.split()[0]})")
    for label, figure in rows:
        print(f"  {label:<52} {figure}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
