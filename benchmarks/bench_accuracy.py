"""Compensation accuracy against simulator truth, and compensation speed.

    python -m benchmarks.bench_accuracy [--rate-hz 100] [--skip-1khz] [--workdir DIR]

Protocol (issue 4): fit each model kind on the ``paper`` profile (seed 1), then
compensate runs of DIFFERENT profiles with other seeds and score the drift
estimates against the truth file:

* ``fast-ramps`` (seed 2): the development profile: the models' fixed settings
  (ridge penalties) were chosen looking at it, so it flatters them;
* ``soak-cycle`` (seed 3): written after those choices and never used to tune
  anything: the honest held-out figure.

Per test run, over whole minutes after the first 10 (start-up), with each
series' mean removed (a constant is a bias, not drift), deg/h:

    before       RMS of 1-min means of the true drift D
    residual     RMS of 1-min means of D - D_hat   (D_hat: the estimate compensate applied)
    noise floor  RMS of 1-min means of the non-thermal noise (bias instability + RRW + ARW + quantization)

Targets: residual <= 25 % of before (>= 75 % reduction); the WESN's residual
<= 80 % of the polynomial's; residual <= 2 x the noise floor.  Also: stage 1
(AFLP) alone lowers the 1-s std of static data >= 3x; a model fitted at
100 Hz applied to a 1 kHz capture of the same run gives drift estimates
within 2 % RMS of the 100 Hz ones; compensate on a 440-min 100 Hz capture
<= 10 s end to end; a model step <= 50 us.  Also printed: frozen against adapting online
(``AdaptConfig()`` defaults, reference rate 0) on the runs a model was not fitted on.  Figures are
printed, never asserted.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks._harness import kept_or_temporary
from fog_driver.compensation.adapt import AdaptConfig
from fog_driver.compensation.aflp import AflpFilter, AflpParams
from fog_driver.compensation.fitting.data import FitConfig
from fog_driver.lab.profiles import load_profile
from fog_driver.modelfiles import load_model, save_model
from fog_driver.offline.fit import fit_model_file, load_capture
from fog_driver.report.evaluate import per_second
from fog_driver.sim.capture import read_truth, simulate_to_file, truth_noise_dph
from fog_driver.sim.instrument import Simulator

ROOT = Path(__file__).resolve().parents[1]

KINDS = ("polynomial", "wesn", "paper", "pso-svr")  # pso-svr: the paper's comparator (the svr extra)
TESTS = (("fast-ramps", 2, "development"), ("soak-cycle", 3, "held out"))
SKIP_MINUTES = 10


def simulate(workdir: Path, profile: str, seed: int, rate_hz: int) -> Path:
    out = workdir / f"{profile}-s{seed}-{rate_hz}hz.bin"
    if not out.exists():
        source = profile if profile in ("paper",) else ROOT / "configs" / "profiles" / f"{profile}.yaml"
        simulate_to_file(Simulator(load_profile(source), rate_hz=rate_hz, seed=seed), out)
    return out


def per_second_drift(capture: Path, model_path: Path, adapt: AdaptConfig | None = None) -> np.ndarray:
    """The drift applied in each device second (``evaluate.per_second``; with ``adapt``: adapting online
    against a known rate of 0, as ``compensate --adapt-reference 0``)."""
    reference = None if adapt is None else 0.0
    return per_second(capture, load_model(model_path), adapt=adapt, reference_rate_dph=reference).drift_dph


def minute_rms(x: np.ndarray) -> float:
    n = len(x) // 60 * 60
    m = x[:n].reshape(-1, 60).mean(axis=1)[SKIP_MINUTES:]
    return float(np.sqrt(np.mean((m - m.mean()) ** 2)))


#: the plain causal smoother stage 1 is compared with: an exponential average of this time constant
EMA_TAU_S = 15.0


def stage1_figures(capture: Path) -> dict[str, float]:
    """Stage 1 in the paper's setup: one AFLP over the whole static run, the run's mean (B0) removed;
    the 1-s RMS of its output about the simulator's true drift, against the input's, past the first
    10 minutes (the filter's warm-up), and the same for a plain causal EMA (``EMA_TAU_S``).  Also the
    earlier figure, for the record: each 15-min plateau's own mean removed, a fresh filter per plateau,
    std in / std out about the plateau's trend (the zero-mean white-noise case, where predicting 0 wins)."""
    data = load_capture(capture, FitConfig())
    truth = read_truth(capture.with_suffix(".truth.csv"))
    n = min(len(data.target_dph), len(truth["drift_dph"]))
    r = data.blocks.rate_dph[:n] - data.blocks.rate_dph[:n].mean()
    drift = np.asarray(truth["drift_dph"][:n], dtype=float)
    drift = drift - drift.mean()
    aflp = AflpFilter(AflpParams()).run(r)
    alpha = 1.0 - np.exp(-1.0 / EMA_TAU_S)
    ema = np.empty(n)
    level = r[0]
    for i, x in enumerate(r):
        level += alpha * (x - level)
        ema[i] = level

    def rms_about_truth(x: np.ndarray) -> float:
        e = (x - drift)[600:]
        return float(np.sqrt(np.mean((e - e.mean()) ** 2)))

    def detrended(x: np.ndarray) -> np.ndarray:
        t = np.arange(len(x))
        return x - np.polyval(np.polyfit(t, x, 1), t)

    before, after = [], []
    for plateau in load_profile("paper").chamber.plateaus():
        lo, hi = int(plateau.t_start_s), int(plateau.t_end_s)
        if lo < 600 or hi > n or hi - lo < 900:
            continue
        x = data.target_dph[lo:hi] - data.target_dph[lo:hi].mean()
        before.append(detrended(x[-600:]))
        after.append(detrended(AflpFilter(AflpParams()).run(x)[-600:]))
    return {
        "input": rms_about_truth(r),
        "aflp": rms_about_truth(aflp),
        "ema": rms_about_truth(ema),
        "plateau_ratio": float(np.concatenate(before).std() / np.concatenate(after).std()),
    }


def model_step_us(model_path: Path) -> float:
    model_file = load_model(model_path)
    model = model_file.model
    z = np.zeros(8)
    model.start(z)
    n = 3000
    rng = np.random.default_rng(0).normal(0, 1, (n, 8))
    t0 = time.perf_counter()
    for row in rng:
        model.step(row)
    return (time.perf_counter() - t0) / n * 1e6


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rate-hz", type=int, default=100)
    parser.add_argument("--skip-1khz", action="store_true", help="skip the 1 kHz consistency check (slow)")
    parser.add_argument("--workdir", type=Path, help="keep simulated captures here (default: a temporary dir)")
    args = parser.parse_args()
    with kept_or_temporary(args.workdir) as workdir:
        workdir.mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()
        fit_capture = simulate(workdir, "paper", 1, args.rate_hz)
        tests = [(name, seed, role, simulate(workdir, name, seed, args.rate_hz)) for name, seed, role in TESTS]
        print(
            f"simulated at {args.rate_hz} Hz: paper (seed 1) for fitting; "
            + ", ".join(f"{n} (seed {s}, {r})" for n, s, r, _ in tests)
            + f"  [{time.perf_counter() - t0:.0f} s]"
        )
        models = {}
        for kind in KINDS:
            t0 = time.perf_counter()
            model_file, _ = fit_model_file([fit_capture], kind=kind, config=FitConfig(), accept_weak=True)
            models[kind] = save_model(workdir / f"{kind}.yaml", model_file)
            print(f"fit {kind:10s} {time.perf_counter() - t0:5.1f} s")

        print()
        print(
            f"{'1-min drift RMS, deg/h':28s} {'before':>8s} {'noise':>8s} "
            + " ".join(f"{k:>10s}" for k in KINDS)
            + "   reduction (wesn)  wesn/poly  wesn/noise"
        )
        for name, _seed, role, capture in tests:
            truth = read_truth(capture.with_suffix(".truth.csv"))
            before = minute_rms(truth["drift_dph"])
            floor = minute_rms(truth_noise_dph(truth))
            residual = {}
            for kind in KINDS:
                drift = per_second_drift(capture, models[kind])
                n = min(len(drift), len(truth["drift_dph"]))
                residual[kind] = minute_rms(truth["drift_dph"][:n] - drift[:n])
            w, p = residual["wesn"], residual["polynomial"]
            print(
                f"{name + ' (' + role + ')':28s} {before:8.4f} {floor:8.4f} "
                + " ".join(f"{residual[k]:10.4f}" for k in KINDS)
                + f"   {100 * (1 - w / before):6.1f} % (>= 75)   {w / p:5.2f} (<= 0.8)  {w / floor:5.2f} (<= 2)"
            )
        print()
        st = stage1_figures(fit_capture)
        print(
            f"stage 1 alone, the paper's setup (one filter over the paper run, its mean removed), 1-s RMS about the "
            f"true drift: input {st['input']:.3f}, AFLP order 10 {st['aflp']:.3f} ({st['input'] / st['aflp']:.2f} x "
            f"lower), EMA {EMA_TAU_S:g} s {st['ema']:.3f} ({st['input'] / st['ema']:.2f} x lower); the paper: 4 x "
            f"(0.176 -> 0.044 deg/h); per-plateau fresh filters, std about each plateau's trend: "
            f"{st['plateau_ratio']:.2f} x"
        )

        if not args.skip_1khz:
            name, seed, _ = TESTS[0]
            t0 = time.perf_counter()
            fast = simulate(workdir, name, seed, 1000)
            d100 = per_second_drift(tests[0][3], models["wesn"])
            d1k = per_second_drift(fast, models["wesn"])
            n = min(len(d100), len(d1k))
            rel = float(np.sqrt(np.mean((d1k[:n] - d100[:n]) ** 2)) / np.sqrt(np.mean(d100[:n] ** 2)))
            print(
                f"wesn fitted at {args.rate_hz} Hz applied to a 1 kHz capture of the same {name} run: drift estimates "
                f"differ by {100 * rel:.3f} % RMS (target <= 2 %)  [{time.perf_counter() - t0:.0f} s]"
            )

        # Two runs of one instrument fitted together (the paper run and the faster fast-ramps run) pin the
        # coil's lag, which one paper run can leave ambiguous; scored on the held-out soak-cycle run.
        t0 = time.perf_counter()
        pair, _ = fit_model_file([fit_capture, tests[0][3]], kind="wesn", config=FitConfig(), accept_weak=True)
        pair_path = save_model(workdir / "wesn-paper+fast.yaml", pair)
        fit_s = time.perf_counter() - t0
        truth = read_truth(tests[1][3].with_suffix(".truth.csv"))
        drift = per_second_drift(tests[1][3], pair_path)
        n = min(len(drift), len(truth["drift_dph"]))
        print(
            f"wesn fitted on paper + fast-ramps together (coil lag {pair.provenance['selection']['coil_lag_s']:g} s, "
            f"{fit_s:.1f} s), on soak-cycle: {minute_rms(truth['drift_dph'][:n] - drift[:n]):.4f} deg/h; "
            f"fitted on paper alone (coil lag {load_model(models['wesn']).provenance['selection']['coil_lag_s']:g} s): "
            "see the table"
        )

        # Adapting online (compensate --adapt-reference 0, the defaults) against frozen, on the runs each
        # model was not fitted on: the comparison guard should keep a good model's estimate, and let the
        # adapted one in where the frozen model is wrong.
        for label, model_path, runs in (
            ("wesn paper + fast-ramps", pair_path, tests[1:]),
            ("wesn paper alone", models["wesn"], tests),
        ):
            for name, _seed, _role, capture in runs:
                truth = read_truth(capture.with_suffix(".truth.csv"))
                scores = []
                for adapt in (None, AdaptConfig()):
                    drift = per_second_drift(capture, model_path, adapt)
                    n = min(len(drift), len(truth["drift_dph"]))
                    scores.append(minute_rms(truth["drift_dph"][:n] - drift[:n]))
                print(
                    f"adapting (--adapt-reference 0), {label}, on {name}: {scores[0]:.4f} frozen -> "
                    f"{scores[1]:.4f} deg/h adapting"
                )

        paper_100 = fit_capture
        cmd = [
            sys.executable,
            "-m",
            "fog_driver",
            "compensate",
            str(paper_100),
            "--model",
            str(models["wesn"]),
            "--out",
            str(workdir / "paper.csv"),
            "--force",
        ]
        t0 = time.perf_counter()
        subprocess.run(cmd, check=True, capture_output=True)
        wall = time.perf_counter() - t0
        print(
            f"fog-driver compensate, 440-min paper capture at {args.rate_hz} Hz, wesn model: {wall:.1f} s end to end "
            f"(target <= 10 s)"
        )
        for kind in KINDS:
            print(f"model step, {kind:10s} {model_step_us(models[kind]):6.1f} us (target <= 50 us)")


if __name__ == "__main__":
    from benchmarks._harness import run_main  # --update-readme: the documentation's block for this command

    run_main(main)
