"""Several captures of one instrument fitted together: each capture its own intercept (fixed effects),
checked against the simulator's truth on a run none of them is.

Each capture's target is its rate less its own static mean: that mean holds the run's turn-on bias
and also the run's mean drift, which differs between a hot and a cold run.  One intercept for all
would make the temperature terms explain that difference (measured: 0.10 deg/h left on a third run
against 0.008 with one intercept per capture), and splitting one run in two made the model worse
than none."""

from __future__ import annotations

import dataclasses
import functools
import re
from pathlib import Path

import numpy as np
import pytest

from fog_driver.cli import main
from fog_driver.compensation.blocks import BlockColumns
from fog_driver.compensation.features import FeatureExtractor
from fog_driver.compensation.fitting import fit
from fog_driver.compensation.fitting.data import CaptureData, FitConfig, block_noise_dph, motion_mask, static_mask
from fog_driver.modelfiles import load_model
from fog_driver.offline import fit as offline_fit
from fog_driver.offline.fit import fit_model_file, load_capture
from fog_driver.report.evaluate import minute_rms, per_second
from fog_driver.sim.capture import read_truth

PROFILES = Path(__file__).resolve().parents[2] / "configs" / "profiles"
HOT = "name: hot\nstart_c: 20\nsegments:\n" + "".join(
    f"  - {s}\n"
    for s in (
        "hold: {duration_min: 30}",
        "ramp: {rate_c_per_min: 1, target_c: 30}",
        "hold: {duration_min: 15}",
        "ramp: {rate_c_per_min: 1, target_c: 40}",
        "hold: {duration_min: 15}",
        "ramp: {rate_c_per_min: 1, target_c: 55}",
        "hold: {duration_min: 15}",
        "ramp: {rate_c_per_min: 2, target_c: 20}",
        "hold: {duration_min: 15}",
    )
)
COLD = (
    HOT.replace("name: hot", "name: cold")
    .replace("target_c: 30", "target_c: 0")
    .replace("target_c: 40", "target_c: -20")
    .replace("target_c: 55", "target_c: -40")
)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """One simulated instrument at 1 Hz: the paper run, a hot and a cold run, and a soak-cycle run to score on."""
    d = tmp_path_factory.mktemp("multi")
    (d / "hot.yaml").write_text(HOT)
    (d / "cold.yaml").write_text(COLD)
    for name, profile, seed in (
        ("paper", "paper", 1),
        ("hot", str(d / "hot.yaml"), 11),
        ("cold", str(d / "cold.yaml"), 12),
        ("soak", str(PROFILES / "soak-cycle.yaml"), 3),
    ):
        assert (
            main(
                [
                    "simulate",
                    "--profile",
                    profile,
                    "--seed",
                    str(seed),
                    "--rate-hz",
                    "1",
                    "--out",
                    str(d / f"{name}.bin"),
                ]
            )
            == 0
        )
    return d


def truth_residual(model_file, run: Path) -> float:
    """1-min RMS of the true drift left after the model on ``run`` (static minutes past the first 10)."""
    truth = read_truth(run.with_suffix(".truth.csv"))
    series = per_second(run, model_file)
    n = min(len(series.drift_dph), len(truth["drift_dph"]))
    mask = truth["input_dph"][:n] == 0.0
    mask[:600] = False
    return minute_rms(truth["drift_dph"][:n] - series.drift_dph[:n], mask)


def fit_paths(paths, kind):
    model_file, _ = fit_model_file(paths, kind=kind, config=FitConfig())
    return model_file


@functools.cache
def paper_residual(runs: Path, kind: str) -> float:
    """The paper run's own fit of ``kind`` scored on the soak run (several tests compare with it: fitted once)."""
    return truth_residual(fit_paths([runs / "paper.bin"], kind), runs / "soak.bin")


@functools.cache
def raw_residual(runs: Path) -> float:
    """No compensation at all, scored on the soak run."""
    return truth_residual(_zero_model(fit_paths([runs / "paper.bin"], "polynomial")), runs / "soak.bin")


@pytest.mark.parametrize("kind", ["polynomial", "wesn"])
def test_a_hot_and_a_cold_run_fitted_together_do_as_well_as_one_run_over_both(runs, kind):
    whole = paper_residual(runs, kind)
    pair = truth_residual(fit_paths([runs / "hot.bin", runs / "cold.bin"], kind), runs / "soak.bin")
    assert pair <= 1.5 * whole + 0.002, (pair, whole)


def test_a_hot_and_a_cold_run_fitted_together_get_their_own_offsets_in_the_svr(runs, monkeypatch):
    """The RBF kernel has no column for a capture's intercept: its offsets are backfitted (measured on soak:
    0.077 deg/h, the paper run alone 0.067, without the offsets 0.111)."""
    from fog_driver.compensation.fitting import svr

    pair = truth_residual(fit_paths([runs / "hot.bin", runs / "cold.bin"], "pso-svr"), runs / "soak.bin")
    monkeypatch.setattr(svr, "OFFSET_PASSES", 0)
    pooled = truth_residual(fit_paths([runs / "hot.bin", runs / "cold.bin"], "pso-svr"), runs / "soak.bin")
    assert pair < 0.8 * pooled, (pair, pooled)


def test_one_intercept_for_all_captures_would_fail_the_same_check(runs, monkeypatch):
    """The check above can fail: with every capture's rows in one group the hot + cold polynomial is far off
    (measured 0.097 deg/h against 0.013 for the paper run alone and 0.007 for hot + cold done right)."""
    whole = paper_residual(runs, "polynomial")
    monkeypatch.setattr(
        fit, "capture_groups", lambda captures: np.zeros(sum(int(c.static.sum()) for c in captures), int)
    )
    pooled = truth_residual(fit_paths([runs / "hot.bin", runs / "cold.bin"], "polynomial"), runs / "soak.bin")
    assert pooled > 3 * whole, (pooled, whole)


def piece(capture: CaptureData, lo: int, hi: int, config: FitConfig) -> CaptureData:
    """Blocks lo..hi of a capture as a capture of their own (its target centred on its own static mean),
    as if the run had been recorded in pieces."""
    b = capture.blocks
    blocks = BlockColumns(
        b.index[lo:hi] - lo,
        b.t_end_s[lo:hi] - b.t_end_s[lo] + 1.0,
        b.n_samples[lo:hi],
        b.rate_dph[lo:hi],
        b.temps_c[lo:hi],
        b.flags[lo:hi],
    )
    inputs, input_flags = FeatureExtractor(config.features).run(blocks.temps_c)
    static = static_mask(blocks, input_flags, config)
    target = blocks.rate_dph - blocks.rate_dph[static].mean()
    return CaptureData(
        capture.path,
        capture.sha256,
        capture.serial,
        capture.frame_period_s,
        blocks,
        inputs,
        input_flags,
        static,
        target,
    )


@pytest.mark.parametrize("kind", ["polynomial", "wesn"])
@pytest.mark.parametrize("pieces", [2, 3])
def test_a_run_split_in_pieces_fits_as_well_as_the_whole_run(runs, pieces, kind, monkeypatch):
    """(With one intercept for all, the polynomial leaves 0.13 and 0.17 deg/h here: worse than 2 pieces' 0.011.)"""
    config = FitConfig()
    whole_capture = load_capture(runs / "paper.bin", config)
    whole = paper_residual(runs, kind)
    raw = raw_residual(runs)
    n = len(whole_capture.blocks)
    cuts = np.linspace(0, n, pieces + 1).astype(int)
    parts = [piece(whole_capture, a, b, config) for a, b in zip(cuts[:-1], cuts[1:])]
    monkeypatch.setattr(offline_fit, "load_capture", lambda path, cfg, *_, **__: parts[int(str(path))])
    split = truth_residual(fit_paths([str(k) for k in range(pieces)], kind), runs / "soak.bin")
    # a wesn fitted on pieces shorter than 250 min may not try a cascade or the longest lags, and its
    # history neurons restart with each piece: it is held to 2x the whole run (measured 0.0100 vs 0.0061)
    factor = 1.3 if kind == "polynomial" else 2.0
    assert split <= factor * whole + 0.002 and split < 0.1 * raw, (split, whole, raw)


def _zero_model(model_file):
    """The same model file with zero weights: no compensation."""
    model_file.model.weights = np.zeros_like(model_file.model.weights)
    model_file.model.intercept = 0.0
    return model_file


# -- motion in the fit data: detected, not assumed absent -------------------------------------------------


def _with_motion(capture: CaptureData, add_dph: np.ndarray, config: FitConfig) -> CaptureData:
    """The capture with ``add_dph`` added to its block rates (the table turning or creeping), re-masked."""
    b = capture.blocks
    blocks = BlockColumns(b.index, b.t_end_s, b.n_samples, b.rate_dph + add_dph, b.temps_c, b.flags)
    static = static_mask(blocks, capture.input_flags, config)
    target = blocks.rate_dph - blocks.rate_dph[static].mean()
    return CaptureData(
        capture.path,
        capture.sha256,
        capture.serial,
        capture.frame_period_s,
        blocks,
        capture.inputs,
        capture.input_flags,
        static,
        target,
    )


@pytest.mark.parametrize(
    "what, rate_dph, seconds",
    [
        ("a 40-s turn at 10 deg/s", 36000.0, 40),
        ("a 10-min turn at 10 deg/s", 36000.0, 600),
        ("a 30-min creep at 14.4 deg/h", 14.4, 1800),
        ("a 3-min creep at 3 deg/h", 3.0, 180),
    ],
)
def test_steady_motion_and_slow_creeps_in_fit_data_are_not_fitted(runs, what, rate_dph, seconds):
    """The old detector (rate against a 61-s running median) passed every one of these as static."""
    config = FitConfig()
    clean = load_capture(runs / "paper.bin", config)
    t = np.arange(len(clean.blocks))
    moving = (t >= 13200) & (t < 13200 + seconds)
    moved = _with_motion(clean, np.where(moving, rate_dph, 0.0), config)
    assert not (moved.static & moving).any(), what
    assert (moved.static != clean.static).sum() <= seconds + 2 * 60 + 2 * 450  # the motion, margins, envelope edges


def test_a_clean_chamber_run_loses_no_block_to_the_motion_detector(runs):
    """A thermal drift is not motion: on the paper run only the warm-up is excluded."""
    config = FitConfig()
    capture = load_capture(runs / "paper.bin", config)
    assert not motion_mask(capture.blocks.rate_dph, config).any()
    assert capture.static.sum() == (capture.blocks.t_end_s > config.warmup_s).sum()


def test_block_noise_is_the_white_noise_sigma():
    rng = np.random.default_rng(7)
    drift = np.cumsum(rng.normal(0, 0.001, 20000))  # a slow wander
    rate = drift + rng.normal(0, 0.25, 20000)
    rate[5000:5040] += 36000.0  # a turn
    assert block_noise_dph(rate) == pytest.approx(0.25, rel=0.05)


def test_fit_reports_the_blocks_excluded_for_motion(runs, capsys):
    """A 40-s turn at 10 deg/s in the paper run (which once fitted into a 424 deg/h model with exit 0)."""
    paper = (PROFILES / "paper.yaml").read_text().split("\nmotion:")[0]
    (runs / "turn.yaml").write_text(
        paper.rstrip() + "\nmotion:\n  kind: constant_rate\n  rate_dps: 10\n  start_s: 13200\n  stop_s: 13240\n"
    )
    assert (
        main(
            [
                "simulate",
                "--profile",
                str(runs / "turn.yaml"),
                "--seed",
                "1",
                "--rate-hz",
                "1",
                "--out",
                str(runs / "turn.bin"),
            ]
        )
        == 0
    )
    capsys.readouterr()
    assert main(["fit", str(runs / "turn.bin"), "--kind", "polynomial", "--out", str(runs / "turn-model.yaml")]) == 0
    out = capsys.readouterr().out
    found = re.search(r"note: (\d+) blocks of table motion were found and not fitted", out)
    assert found and 40 <= int(found[1]) <= 42, out
    turned = truth_residual(load_model(runs / "turn-model.yaml"), runs / "soak.bin")
    clean = paper_residual(runs, "polynomial")
    assert turned < 1.2 * clean + 0.002, (turned, clean)


# -- the bias step test ----------------------------------------------------------------------------------


def with_step(capture: CaptureData, minute: int, step_dph: float) -> CaptureData:
    t_min = np.arange(len(capture.target_dph)) / 60.0
    return dataclasses.replace(capture, target_dph=capture.target_dph + np.where(t_min >= minute, step_dph, 0.0))


def test_a_bias_step_in_the_fit_data_is_found_where_and_as_big_as_it_is(runs):
    paper = load_capture(runs / "paper.bin", FitConfig())
    normalizer = fit.fit_normalizer([paper])
    clean = fit.bias_step_scan([paper], normalizer, 1.0)
    assert fit.bias_step_warning(clean._asdict() | {"capture": "paper.bin"}) is None
    stepped = fit.bias_step_scan([with_step(paper, 220, 0.1)], normalizer, 1.0)
    assert stepped.capture == 0 and abs(stepped.minute - 220) <= 10
    assert stepped.step_dph == pytest.approx(0.1, abs=0.02) and stepped.share > clean.share
    warning = fit.bias_step_warning(stepped._asdict() | {"capture": "paper.bin"})
    assert warning.startswith("the fit data hold a bias step of +0.") and "minute 2" in warning
    assert "thermometer" not in warning
    one = fit.bias_step_warning(stepped._asdict() | {"capture": "paper.bin"}, n_channels=1)
    assert "drift that one thermometer cannot follow" in one and one.startswith(warning[:40])


def test_the_step_test_names_the_capture_that_holds_the_step(runs):
    hot, cold = (load_capture(runs / f"{name}.bin", FitConfig()) for name in ("hot", "cold"))
    normalizer = fit.fit_normalizer([hot, cold])
    step = fit.bias_step_scan([hot, with_step(cold, 90, -0.15)], normalizer, 1.0)
    assert step.capture == 1 and abs(step.minute - 90) <= 10 and step.step_dph == pytest.approx(-0.15, abs=0.03)


def test_the_fit_records_the_step_test_in_the_model_file(runs):
    model_file, _ = fit_model_file([runs / "paper.bin"], kind="polynomial", config=FitConfig())
    step = model_file.provenance["fit_quality"]["bias_step"]
    assert step["capture"] == "paper.bin" and abs(step["step_dph"]) < fit.STEP_WARN_DPH
