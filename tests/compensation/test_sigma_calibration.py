"""Each fit calibrates its own drift_sigma_dph on held-out stretches (``fitting.sigma_calibration``): the
held-out errors against an independent refit, the variance fit and the conformal scale against known
answers, the selection keeping what predicts and nothing else, the run-time rule against its formula, the
model file's section, and the fall-back."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fog_driver.compensation.fitting import sigma_calibration as sc
from fog_driver.compensation.fitting.data import FitConfig
from fog_driver.compensation.model import model_file_from_doc
from fog_driver.compensation.pipeline import Compensator
from fog_driver.compensation.uncertainty import (
    SIGMA_FEATURES,
    DriftUncertainty,
    SigmaCalibration,
    UncertaintySpec,
    box_distance,
)
from fog_driver.errors import InputFileError
from fog_driver.offline.fit import fit_model_file
from fog_driver.protocol import decode_file
from fog_driver.samples.stream import SampleStream

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT / "tests" / "data"
N_FEATURES = len(SIGMA_FEATURES)


def held(features: np.ndarray, error: np.ndarray, stretches: int, noise: float = 0.0) -> sc.HeldOut:
    stretch = np.arange(len(error)) * stretches // len(error)
    return sc.HeldOut(error, features, stretch, noise, 30.0)


def features_with(columns: dict[int, np.ndarray], n: int) -> np.ndarray:
    f = np.zeros((n, N_FEATURES))
    f[:, 0] = 1.0
    for j, v in columns.items():
        f[:, j] = v
    return f


def test_the_variance_fit_recovers_known_weights_beside_the_noise():
    rng = np.random.default_rng(1)
    n = 40_000
    x = rng.uniform(0.0, 2.0, n)
    f = features_with({2: x * x}, n)[:, [0, 2]]
    truth = np.array([0.5, 2.0])
    noise = 0.7
    e = rng.standard_normal(n) * np.sqrt(noise**2 + f @ truth)
    c = sc.fit_variance(f, e * e, noise**2)
    assert c == pytest.approx(truth, rel=0.08)


def test_the_non_negative_solution_is_exact_on_a_case_with_a_negative_least_squares_weight():
    a = np.array([[1.0, 0.0], [1.0, 1.0], [1.0, 2.0]])
    b = np.array([2.0, 1.0, 0.0])  # least squares would give a negative slope
    c = sc._nnls(a, b)
    assert c[1] == 0.0 and c[0] == pytest.approx(1.0)  # the best constant alone: the mean


def test_a_feature_that_predicts_the_held_out_error_is_kept_and_one_that_does_not_gets_no_weight():
    rng = np.random.default_rng(2)
    n = 1600
    rate = rng.uniform(0.0, 2.0, n)
    useless = rng.uniform(0.0, 1.0, n)
    e = rng.standard_normal(n) * np.sqrt(0.01**2 + (0.02 * rate) ** 2)
    f = features_with({2: rate * rate, 4: useless * useless}, n)
    calibration, evidence = sc.calibrate(held(f, e, 16), -10.0, 40.0, residual_dph=0.01)
    assert calibration.calibrated
    assert calibration.weights[2] > 0 and calibration.weights[4] == 0.0
    assert evidence["evidence"]["rate"]["kept"] and not evidence["evidence"]["warm"]["kept"]
    assert evidence["features"] == ["constant", "rate"]  # no candidates here: no spread to carry it
    assert "spread" not in evidence["evidence"]


def test_the_spread_and_the_residual_carry_the_sigma_in_their_own_proportion_scaled_by_the_held_out_error():
    """Held-out errors whose variance is 2.25 (r^2 + s^2): the constant and the spread get the weights
    2.25 r^2 and 2.25, with k near 1, so that the band is k sqrt(2.25 (r^2 + s^2)) = 1.5 sqrt(r^2 + s^2)."""
    rng = np.random.default_rng(5)
    n = 6400
    r = 0.01
    s = rng.uniform(0.0, 0.03, n)
    e = rng.standard_normal(n) * 1.5 * np.sqrt(r * r + s * s)
    f = features_with({1: s * s}, n)
    calibration, evidence = sc.calibrate(held(f, e, 16), -10.0, 40.0, residual_dph=r)
    w, k = np.array(calibration.weights), calibration.scale
    assert w[1] * k * k == pytest.approx(2.25, rel=0.12)
    assert w[0] / w[1] == pytest.approx(r * r, rel=1e-9)
    assert evidence["evidence"]["spread"]["kept"] and evidence["evidence"]["spread"]["gain_per_stretch"] > 0


def test_the_box_term_is_beside_the_scale_not_in_it():
    """Errors that are large only outside the refit's box, as large as the box term says: the scale stays set
    by the errors inside it."""
    rng = np.random.default_rng(6)
    n = 3200
    d2 = np.where(np.arange(n) % 8 == 0, 0.25, 0.0)  # an eighth of the windows half a span outside
    box_dph = 0.2
    e = rng.standard_normal(n) * np.sqrt(0.01**2 + box_dph**2 * d2)
    f = features_with({5: d2}, n)
    with_box, _ = sc.calibrate(held(f, e, 16), -10.0, 40.0, residual_dph=0.01, box_dph=box_dph)
    without, _ = sc.calibrate(held(f, e, 16), -10.0, 40.0, residual_dph=0.01, box_dph=0.0)
    inside = math.sqrt(with_box.weights[0]) * with_box.scale
    assert inside == pytest.approx(0.01, rel=0.15)
    assert math.sqrt(without.weights[0]) * without.scale > 2 * inside
    assert with_box.weights[5] == 0.0


def test_the_conformal_scale_restores_a_band_that_was_made_too_narrow():
    rng = np.random.default_rng(3)
    n = 4000
    v = rng.uniform(0.5, 2.0, n)
    e = rng.standard_normal(n) * np.sqrt(v) * 1.8  # the errors are 1.8x the variance model's sigma
    k = sc.conformal_scale(held(np.ones((n, 1)), e, 10), v)
    assert k == pytest.approx(1.8, rel=0.06)
    assert np.mean(np.abs(e) <= sc.Z95 * k * np.sqrt(v)) >= sc.COVERAGE


def test_fewer_than_eight_stretches_fall_back_and_say_why():
    f = features_with({}, 70)
    calibration, evidence = sc.calibrate(held(f, np.linspace(-1, 1, 70) * 0.01, 7), 0.0, 1.0)
    assert calibration.method == "none" and "7 held-out stretches" in calibration.reason
    assert evidence["method"] == "none"


@pytest.mark.parametrize("minutes", [300, 480, 800])
def test_held_out_errors_come_from_a_refit_that_never_saw_the_stretch(minutes):
    """A bump confined to one stretch, which no regressor explains: the held-out error there is the bump, as an
    independent least-squares refit without the stretch and its guard gives it.  The stretches are half an
    hour each (300, 480 min: 10, 16 of them) or 16 longer ones (800 min)."""
    rate_hz = 1.0
    n = minutes * 60
    t = np.arange(n)
    x = np.column_stack([np.sin(t / 3000.0), np.cos(t / 2100.0)])
    y = 0.3 * x[:, 0] - 0.2 * x[:, 1] + 0.05
    stretch_blocks = max(int(sc.MIN_STRETCH_S * rate_hz), n // sc.STRETCHES)
    count = n // stretch_blocks
    assert count == {300: 10, 480: 16, 800: 16}[minutes]
    bump = (t >= 3 * stretch_blocks) & (t < 4 * stretch_blocks)
    y = y + 0.04 * bump
    inputs = np.zeros((n, 8))
    inputs[:, 0] = inputs[:, 1] = 20.0 + 10.0 * np.sin(t / 5000.0)
    capture = SimpleNamespace(static=np.ones(n, bool), target_dph=y, inputs=inputs)
    model = SimpleNamespace(candidates=[])
    bounds = SigmaCalibration("none", ring_low_c=10.0, ring_high_c=30.0)
    out = sc.held_out_minutes(model, [x], 1e-9, None, [capture], None, FitConfig(), bounds, 0.0)
    assert out.stretches == count
    # the reference: per stretch, plain least squares with an intercept without the stretch and its guard,
    # the mean of its residual over the stretch's first whole window
    guard = int(sc.GUARD_S * rate_hz)
    a = np.column_stack([x, np.ones(n)])
    reference = []
    for k in range(count):
        lo, hi = k * stretch_blocks, (k + 1) * stretch_blocks
        train = ~((t >= lo - guard) & (t < hi + guard))
        coef, *_ = np.linalg.lstsq(a[train], y[train], rcond=None)
        first_minute = -(-lo // 60)
        reference.append((y - a @ coef)[first_minute * 60 : (first_minute + sc.WINDOW_MIN) * 60].mean())
    reference = np.array(reference)
    firsts = np.array([np.flatnonzero(out.stretch == k)[0] for k in range(count)])
    # the capture's mean over its held-out windows is removed from every window: compare about the means
    got = out.error_dph[firsts]
    np.testing.assert_allclose(got - got.mean(), reference - reference.mean(), atol=2e-4)
    assert reference[3] - np.delete(reference, 3).mean() == pytest.approx(0.04, abs=0.01)  # the unseen bump


def test_the_run_time_rule_is_the_formula(tmp_path):
    domain = SimpleNamespace(low=(10.0, 10.0, 10.0), high=(30.0, 30.0, 30.0), names=tuple("abcdefgh"))
    calibration = SigmaCalibration("held-out-stretches", (1e-4, 2.0, 3e-4, 5e-5, 7e-5, 4e-3), 1.3, 10.0, 30.0, 8, 55.0)
    spec = UncertaintySpec("candidates", 0.01, 0.5, calibration=calibration)
    unc = DriftUncertainty(spec, [], domain)
    for u, drifts, estimate in (
        ([20.0, 22.0, 21.0, 0.5, 0.7, 0.1, -2.0, -1.0], [0.11, 0.09], 0.1),
        ([35.0, 36.0, 30.0, -1.5, -1.1, 0.0, -1.0, 5.0], [0.3], 0.2),  # beyond the box, hot
        ([5.0, 4.0, 8.0, 2.0, 2.5, 0.0, 1.0, -3.0], [], 0.0),  # cold, outside
    ):
        ring, rate = (u[0] + u[1]) / 2, (u[3] + u[4]) / 2
        p = min(max((ring - 10.0) / 20.0, 0.0), 1.0)
        s2 = float(np.mean([(d - estimate) ** 2 for d in drifts])) if drifts else 0.0
        d = box_distance(domain, u)
        w = calibration.weights
        v = w[0] + w[1] * s2 + w[2] * rate**2 + w[3] * (1 - p) ** 2 + w[4] * p**2 + w[5] * d**2
        expected = math.sqrt(1.3**2 * v + (spec.box_scale * 0.5 * d) ** 2)
        assert unc.sigma_of(drifts, u, estimate) == pytest.approx(expected, rel=1e-12)
        f = calibration.features(s2, ring, rate, d)
        assert float(f @ np.array(w)) == pytest.approx(v, rel=1e-12)


@pytest.fixture(scope="module")
def short_fit():
    model_file, _ = fit_model_file(
        [DATA / "sim-short.bin"], kind="wesn", config=FitConfig(warmup_s=30.0), accept_weak=True
    )
    return model_file


def test_a_short_run_cannot_calibrate_and_gets_the_conservative_rule_with_a_warning(short_fit):
    calibration = short_fit.uncertainty.calibration
    assert calibration is not None and calibration.method == "none"
    assert short_fit.uncertainty.spread_scale == 1.0 and short_fit.uncertainty.residual_scale == 1.0
    assert any("not calibrated on its own data" in line for line in short_fit.warnings("m.yaml"))
    assert short_fit.provenance["sigma_calibration"]["method"] == "none"


def test_an_older_model_file_keeps_todays_rule_with_a_warning(short_fit):
    doc = short_fit.to_doc()
    del doc["uncertainty"]["calibration"]
    older = model_file_from_doc(doc, "m.yaml")
    assert older.sigma_spec.calibration is None
    assert any("older fog-driver" in line for line in older.warnings("old.yaml"))


def calibrated(model_file):
    calibration = SigmaCalibration("held-out-stretches", (1e-4, 1.5, 2e-4, 1e-5, 3e-5, 1e-3), 1.1, 15.0, 35.0, 8, 55.0)
    return dataclasses.replace(
        model_file, uncertainty=dataclasses.replace(model_file.uncertainty, calibration=calibration)
    )


def test_the_calibration_round_trips_through_the_model_file_and_bad_values_are_refused(short_fit):
    model_file = calibrated(short_fit)
    again = model_file_from_doc(model_file.to_doc(), "m.yaml")
    assert again.uncertainty.calibration == model_file.uncertainty.calibration
    for bad in (
        {"weights": {"constant": -1.0}},
        {"weights": {"constant": 1e-4, "temperature": 1.0}},
        {"scale": float("nan")},
        {"ring_c": [30.0, 10.0]},
        {"colour": "red"},
    ):
        doc = model_file.to_doc()
        doc["uncertainty"]["calibration"].update(bad)
        with pytest.raises(InputFileError, match="calibration"):
            model_file_from_doc(doc, "m.yaml")


def test_step_and_run_give_the_same_calibrated_sigma_bit_for_bit(short_fit):
    model_file = calibrated(short_fit)
    doc = model_file.model.to_dict()
    candidates = tuple(dict(doc, weights=[f * w for w in doc["weights"]]) for f in (0.9, 1.2))
    model_file = dataclasses.replace(
        model_file, uncertainty=dataclasses.replace(model_file.uncertainty, candidates=candidates)
    )
    samples = SampleStream().run(decode_file(DATA / "sim-short.bin"))
    run = Compensator(model_file, 0.1).run(samples).drift_sigma_dph
    stepper = Compensator(model_file, 0.1)
    step = np.array([stepper.step(samples.sample(i)).drift_sigma_dph for i in range(len(samples))])
    assert np.isfinite(run[np.isfinite(run)]).all() and np.isfinite(run).sum() > 100
    np.testing.assert_array_equal(run, step)
    flat = dataclasses.replace(
        model_file,
        uncertainty=dataclasses.replace(
            model_file.uncertainty,
            calibration=dataclasses.replace(model_file.uncertainty.calibration, weights=(1e-4, 0, 0, 0, 0, 0)),
        ),
    )
    assert np.nanstd(Compensator(flat, 0.1).run(samples).drift_sigma_dph) < np.nanstd(run)  # the features act


@settings(max_examples=60, deadline=None)
@given(
    stretches=st.integers(8, 20),
    per=st.integers(2, 12),
    scale=st.sampled_from([0.0, 1e-9, 1e-3, 1.0]),
    residual=st.sampled_from([0.0, 1e-6, 0.01]),
    box_dph=st.sampled_from([0.0, 0.5]),
    noise=st.sampled_from([0.0, 0.003, 0.1]),
    seed=st.integers(0, 2**16),
)
def test_any_held_out_windows_give_finite_non_negative_weights_and_a_bounded_scale(
    stretches, per, scale, residual, box_dph, noise, seed
):
    """Whatever the held-out windows hold (errors of exactly 0, a residual of 0, noise far above the error, features
    constant or wild), the calibration is finite: weights >= 0, the scale within its limits, the box weight 0."""
    rng = np.random.default_rng(seed)
    n = stretches * per
    f = np.abs(rng.standard_normal((n, N_FEATURES))) ** rng.integers(1, 4)
    f[:, 0] = 1.0
    f[:, 5] = np.where(rng.random(n) < 0.2, f[:, 5], 0.0)
    e = scale * rng.standard_normal(n) * np.sqrt(1.0 + f[:, 2])
    calibration, evidence = sc.calibrate(held(f, e, stretches, noise), -10.0, 40.0, residual, box_dph)
    w = np.array(calibration.weights)
    assert calibration.calibrated and np.isfinite(w).all() and (w >= 0).all() and w[5] == 0.0
    lo, hi = sc.SCALE_LIMITS
    assert lo <= calibration.scale <= hi
    assert math.isfinite(evidence["median_sigma_dph"]) and evidence["features"][:2] == ["constant", "spread"]
