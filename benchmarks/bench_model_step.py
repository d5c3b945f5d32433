"""The per-block cost of each drift model, and what the machine-independent arithmetic costs.

    python -m benchmarks.bench_model_step [--rate-hz 10] [--steps 3000] [--workdir DIR]

Fits every model kind on a simulated ``paper`` run (seed 1), then times, over the run's own
standardized inputs (the values a live daemon feeds):

* ``model step``: ``model.step(z)``, one model block (the target: <= 50 us);
* ``block``: ``Compensator._on_block``, everything the daemon does per model block (features,
  standardizer, model), frozen and adapting (the adaptive law on the model's regressors).

Each is timed twice in the same run: as shipped (fixed-order sums and the deterministic
``numerics.exp``, the same bits on every CPU) and with the platform's math patched in
(``np.exp``, BLAS products: what the code did before, and what differs between CPUs), so the
ratio says what determinism costs on this machine.  Best of 5 passes; figures are printed,
never asserted.
"""

from __future__ import annotations

import argparse
import contextlib
import time
from pathlib import Path

import numpy as np

from benchmarks._harness import kept_or_temporary
from fog_driver.compensation.adapt import AdaptConfig
from fog_driver.compensation.fitting.data import FitConfig
from fog_driver.compensation.pipeline import Compensator
from fog_driver.lab.profiles import load_profile
from fog_driver.offline.fit import fit_model_file, load_capture
from fog_driver.sim.capture import simulate_to_file
from fog_driver.sim.instrument import Simulator

KINDS = ("polynomial", "wesn", "paper", "pso-svr")
PASSES = 5


def best_us(fn, rows) -> float:
    """Best of PASSES passes over ``rows``, microseconds per call."""
    best = float("inf")
    for _ in range(PASSES):
        t0 = time.perf_counter()
        for row in rows:
            fn(row)
        best = min(best, (time.perf_counter() - t0) / len(rows))
    return best * 1e6


def time_model(model_file, z: np.ndarray) -> float:
    model = model_file.model
    model.reset()
    model.start(z[0])
    return best_us(model.step, z)


def time_blocks(model_file, blocks, adapt: bool) -> float:
    comp = Compensator(model_file, 0.1, AdaptConfig() if adapt else None, 0.0 if adapt else None)
    return best_us(comp._on_block, blocks)


@contextlib.contextmanager
def platform_math():
    """The platform's math in place of the machine-independent forms: ``np.exp`` for ``numerics.exp``,
    BLAS ``@`` for the fixed-order products, ``np.sum`` for the fixed-order sums."""
    try:
        from fog_driver.compensation import numerics
    except ImportError:  # the code before issue 9: it already is the platform's math
        yield False
        return
    platform = {
        "exp": np.exp,
        "matvec": np.matmul,
        "dot": np.matmul,
        "sum_last": lambda a: np.sum(a, axis=-1),
        "total": lambda v: float(np.sum(v)),
    }
    saved = {name: getattr(numerics, name) for name in platform}
    for name, fn in platform.items():
        setattr(numerics, name, fn)
    try:
        yield True
    finally:
        for name, fn in saved.items():
            setattr(numerics, name, fn)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rate-hz", type=int, default=10)
    parser.add_argument("--steps", type=int, default=3000, help="model blocks per timed pass")
    parser.add_argument("--workdir", type=Path, help="keep the simulated capture here (default: a temporary dir)")
    args = parser.parse_args()
    with kept_or_temporary(args.workdir) as workdir:
        workdir.mkdir(parents=True, exist_ok=True)
        capture = workdir / f"paper-s1-{args.rate_hz}hz.bin"
        if not capture.exists():
            simulate_to_file(Simulator(load_profile("paper"), rate_hz=args.rate_hz, seed=1), capture)
        data = load_capture(capture, FitConfig())
        first = int(np.flatnonzero(np.isfinite(data.inputs).all(axis=1))[0])
        rows = data.inputs[first : first + args.steps]
        blocks = [data.blocks.block(i) for i in range(first, first + len(rows))]
        models = {}
        for kind in KINDS:
            t0 = time.perf_counter()
            models[kind], _ = fit_model_file([capture], kind=kind, config=FitConfig(), accept_weak=True)
            print(f"fit {kind:10s} {time.perf_counter() - t0:5.1f} s")
        print(
            f"\n{len(rows)} model blocks of the paper run at {args.rate_hz} Hz, best of {PASSES} passes, us per block"
        )
        print(f"{'':26s} {'shipped':>9s} {'platform':>9s} {'ratio':>7s}")
        for kind in KINDS:
            mf = models[kind]
            z = mf.normalizer.transform(rows)
            for label, fn in (
                (f"model step, {kind}", lambda mf=mf, z=z: time_model(mf, z)),
                (f"block, {kind}", lambda mf=mf: time_blocks(mf, blocks, False)),
                (f"block adapting, {kind}", lambda mf=mf: time_blocks(mf, blocks, True)),
            ):
                if kind == "pso-svr" and "adapting" in label:
                    continue  # a kernel row of every support vector: not a readout to adapt in a daemon
                shipped = fn()
                with platform_math() as patched:
                    platform = fn() if patched else float("nan")
                target = "  (target <= 50 us)" if label.startswith("model step") else ""
                print(f"{label:26s} {shipped:9.1f} {platform:9.1f} {shipped / platform:6.2f}x{target}")


if __name__ == "__main__":
    from benchmarks._harness import run_main  # --update-readme: the documentation's block for this command

    run_main(main)
