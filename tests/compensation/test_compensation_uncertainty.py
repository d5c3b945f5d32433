"""drift_sigma_dph (``compensation.uncertainty``): each part against an independent computation, the model
file's section, and a finite sigma wherever there is an estimate."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from fog_driver.compensation.adapt import AdaptConfig, OnlineReadout
from fog_driver.compensation.domain import InputDomain
from fog_driver.compensation.fitting.data import FitConfig
from fog_driver.compensation.fitting.uncertainty import model_error_dph
from fog_driver.compensation.model import MODEL_KINDS, model_file_from_doc
from fog_driver.compensation.pipeline import Compensator
from fog_driver.compensation.uncertainty import UncertaintySpec, box_distance
from fog_driver.flags import FLAG_UNCOMPENSATED
from fog_driver.offline.fit import fit_model_file
from fog_driver.protocol import decode_file
from fog_driver.samples.stream import SampleBlock, SampleStream

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT / "tests" / "data"


@pytest.fixture(scope="module")
def samples() -> SampleBlock:
    return SampleStream().run(decode_file(DATA / "sim-short.bin"))


@pytest.fixture(scope="module")
def wesn():
    """A ring wesn of sim-short, with two candidate structures put in (the short run itself pins one lag)."""
    model_file, _ = fit_model_file(
        [DATA / "sim-short.bin"], kind="wesn", config=FitConfig(warmup_s=30.0), accept_weak=True
    )
    doc = model_file.model.to_dict()
    candidates = []
    for factor in (0.8, 1.3):  # the same structure, other weights: another explanation of the data
        c = dict(doc, weights=[factor * w for w in doc["weights"]], intercept=doc["intercept"] * factor)
        candidates.append(c)
    spec = dataclasses.replace(model_file.sigma_spec, candidates=tuple(candidates))
    return dataclasses.replace(model_file, uncertainty=spec)


def only(model_file, **scales):
    spec = model_file.sigma_spec
    zero = {"spread_scale": 0.0, "residual_scale": 0.0, "box_scale": 0.0}
    return dataclasses.replace(model_file, uncertainty=dataclasses.replace(spec, **{**zero, **scales}))


def test_the_spread_part_is_the_rms_of_the_candidates_about_the_estimate(wesn, samples):
    """sigma with only k_s = 1: sqrt(mean_c (D_c - D_hat)^2), D_c from a compensator with candidate c as its model."""
    sigma = Compensator(only(wesn, spread_scale=1.0), 0.1).run(samples).drift_sigma_dph
    # the spread is of the model's outputs before the estimate's bound clips them (the clipped estimate is
    # flagged extrapolating): the references run without the bound
    unbounded = dataclasses.replace(wesn, domain=dataclasses.replace(wesn.domain, estimate_limit_dph=1e9))
    main = Compensator(unbounded, 0.1).run(samples).drift_dph
    others = []
    for doc in wesn.sigma_spec.candidates:
        model = MODEL_KINDS[wesn.kind].from_dict(doc)
        mf = dataclasses.replace(unbounded, model=model, uncertainty=UncertaintySpec("residual", 0.0, 0.0))
        others.append(Compensator(mf, 0.1).run(samples).drift_dph)
    expected = np.sqrt(np.mean([(d - main) ** 2 for d in others], axis=0))
    has = np.isfinite(sigma)  # NaN before the first estimate
    assert has.sum() > 0.9 * len(sigma) and np.isfinite(expected[has]).all()
    np.testing.assert_array_equal(np.isfinite(expected), has)  # no sigma exactly where no estimate
    assert expected[has].max() > 0.001  # the candidates do differ
    np.testing.assert_allclose(sigma[has], expected[has], rtol=1e-9, atol=1e-12)


def test_the_residual_part_is_constant_and_the_parts_add_in_quadrature(wesn, samples):
    spec = dataclasses.replace(wesn.sigma_spec, residual_dph=0.007, spread_scale=1.7, residual_scale=2.0, box_scale=0.0)
    parts = {
        "spread": Compensator(only(wesn, spread_scale=1.7), 0.1).run(samples).drift_sigma_dph,
        "residual": Compensator(only(dataclasses.replace(wesn, uncertainty=spec), residual_scale=2.0), 0.1)
        .run(samples)
        .drift_sigma_dph,
    }
    whole = Compensator(dataclasses.replace(wesn, uncertainty=spec), 0.1).run(samples).drift_sigma_dph
    has = np.isfinite(whole)
    np.testing.assert_array_equal(parts["residual"][has], np.full(has.sum(), 0.014))
    np.testing.assert_allclose(whole[has], np.hypot(parts["spread"][has], 0.014), rtol=1e-12)


def test_the_box_part_grows_with_the_distance_from_the_fit_box():
    domain = InputDomain((0.0, 0.0, 0.0, -1, -1, -1, -1, -1), (10.0, 20.0, 10.0, 1, 1, 1, 1, 1), 3.0)
    assert box_distance(domain, [5, 5, 5, 0, 0, 0, 0, 0]) == 0.0
    assert box_distance(domain, [12, 5, 5, 0, 0, 0, 0, 0]) == pytest.approx(0.2)
    assert box_distance(domain, [5, -10, 5, 0, 0, 0, 0, 0]) == pytest.approx(0.5)
    assert box_distance(domain, [5, 5, 5, 9, 9, 9, 9, 9]) == 0.0  # rates extrapolate along a line: not here
    assert box_distance(domain, [math.nan, 5, 5, 0, 0, 0, 0, 0]) == 0.0


def test_outside_the_fit_box_the_sigma_grows_by_the_box_part(wesn, samples):
    """The same capture with every thermometer 30 degC hotter than the fit saw: the box part is
    k_b d R with d from the fit box (the model sees the clamped inputs; its flags say extrapolating)."""
    hot = dataclasses.replace(
        samples, t_top_c=samples.t_top_c + 30, t_bottom_c=samples.t_bottom_c + 30, t_housing_c=samples.t_housing_c + 30
    )
    cols = Compensator(only(wesn, box_scale=2.0), 0.1).run(hot)
    domain = wesn.domain
    d = max(
        (float(np.nanmax(t)) - hi) / (hi - lo)
        for t, lo, hi in zip((hot.t_top_c, hot.t_bottom_c, hot.t_housing_c), domain.low, domain.high)
    )
    has = np.isfinite(cols.drift_sigma_dph)
    assert d > 0.5
    r_range = domain.estimate_limit_dph / 3.0
    assert cols.drift_sigma_dph[has].max() == pytest.approx(2.0 * d * r_range, rel=0.05)
    inside = Compensator(only(wesn, box_scale=2.0), 0.1).run(samples).drift_sigma_dph
    assert np.nanmedian(inside) == 0.0 and np.nanmax(inside) < 0.1 * cols.drift_sigma_dph[has].max()


def test_no_estimate_no_sigma_and_a_finite_sigma_with_every_estimate(wesn):
    """Thermometer faults (NaN, stuck, spikes): wherever a frame carries an estimate, its sigma is finite."""
    faulty = SampleStream().run(decode_file(DATA / "sim-faults.bin"))
    cols = Compensator(wesn, 0.1).run(faulty)
    estimated = (cols.flags & FLAG_UNCOMPENSATED) == 0
    assert estimated.any() and (~estimated).any()
    assert np.isfinite(cols.drift_sigma_dph[estimated]).all() and (cols.drift_sigma_dph[estimated] > 0).all()
    assert np.isnan(cols.drift_sigma_dph[~estimated & (cols.drift_dph == 0)]).all()


def test_the_model_file_keeps_the_section_and_a_file_without_one_warns(wesn):
    doc = wesn.to_doc()
    again = model_file_from_doc(doc, "m.yaml")
    assert again.sigma_spec == wesn.sigma_spec and again.sigma_spec.candidates == wesn.sigma_spec.candidates
    assert not any("candidate" in w for w in again.warnings("m.yaml"))
    del doc["uncertainty"]
    old = model_file_from_doc(doc, "old.yaml")
    assert old.sigma_spec.sigma_kind == "residual" and old.sigma_spec.residual_dph == old.fit_residual_dph
    assert any("no candidate structures" in w and "refit" in w for w in old.warnings("old.yaml"))
    bad = wesn.to_doc()
    bad["uncertainty"]["candidates"] = [{"weights": [1.0]}]
    with pytest.raises(Exception, match="corrupt model|uncertainty"):
        model_file_from_doc(bad, "bad.yaml")
    bad = wesn.to_doc()
    bad["uncertainty"]["residual_dph"] = float("nan")
    with pytest.raises(Exception, match="residual_dph"):
        model_file_from_doc(bad, "bad.yaml")


def test_a_polynomial_fit_has_a_residual_sigma_and_says_so():
    model_file, _ = fit_model_file(
        [DATA / "sim-short.bin"], kind="polynomial", config=FitConfig(warmup_s=30.0), accept_weak=True
    )
    assert model_file.sigma_spec.sigma_kind == "residual" == model_file.provenance["sigma_kind"]
    assert model_file.sigma_spec.residual_dph > 0
    # sim-short is too short for held-out stretches: the fall-back rule, and the fit says so
    assert model_file.sigma_spec.calibration is not None and model_file.sigma_spec.calibration.method == "none"
    assert any("not calibrated on its own data" in w for w in model_file.warnings("p.yaml"))


def test_the_model_error_is_never_zero_and_takes_out_the_noise():
    # r^2 = max(rms^2 - n^2, 0) + rms^2 sqrt(2 / N)
    assert model_error_dph(0.05, 0.03, 200) == pytest.approx(math.sqrt(0.05**2 - 0.03**2 + 0.05**2 * 0.1))
    assert model_error_dph(0.02, 0.03, 200) == pytest.approx(0.02 * math.sqrt(0.1))
    assert model_error_dph(float("nan"), 0.03, 200) == 0.0


def test_the_adapted_sigma_comes_from_the_laws_window_statistics():
    """sigma_a^2 = max(mean (e_a - level)^2 - noise_var / window_blocks, 0), after two windows."""
    readout = OnlineReadout(np.array([1.0, -0.5]), 0.1, AdaptConfig(), 1.0)
    assert readout.adapted_sigma_dph == 0.0
    readout.compare_windows = 3
    readout.compare_dev_sq_adapted_dph2 = 0.0004
    readout.gate_noise_var_dph2 = 0.03
    window = AdaptConfig().compare_window_s
    assert readout.adapted_sigma_dph == pytest.approx(math.sqrt(0.0004 - 0.03 / window))
    state = readout.get_state()
    again = OnlineReadout(np.array([1.0, -0.5]), 0.1, AdaptConfig(), 1.0, state=state)
    assert again.compare_dev_sq_adapted_dph2 == 0.0004
    del state["compare_dev_sq_adapted_dph2"]  # a state saved before it existed
    assert OnlineReadout(np.array([1.0, -0.5]), 0.1, AdaptConfig(), 1.0, state=state).adapted_sigma_dph >= 0.0


def _joined(parts):
    from fog_driver.compensation.pipeline import CompensatedColumns

    return CompensatedColumns(
        *(np.concatenate([getattr(p, f) for p in parts]) for f in CompensatedColumns.__dataclass_fields__)
    )


@pytest.mark.determinism
@pytest.mark.parametrize("adapting", [False, True])
def test_run_takes_the_candidates_in_runs_and_gives_the_bits_of_step(wesn, adapting):
    """``Compensator.run`` steps the candidate structures after its block loop, in runs of blocks
    (``DriftUncertainty.defer``): the sigmas, the flags and the candidates' states are step's, bit for bit,
    in any chunks, across thermometer faults and a gap long enough to restart the pipeline at rest."""
    from fog_driver.compensation.pipeline import MAX_GAP_S

    faulty = SampleStream().run(decode_file(DATA / "sim-faults.bin"))
    half = len(faulty) // 2
    t_s = faulty.t_s.copy()
    t_s[half:] += MAX_GAP_S + 3600.0  # a gap past MAX_GAP_S: the pipeline and the candidates restart at rest
    samples = dataclasses.replace(faulty, t_s=t_s)
    adapt = AdaptConfig(warmup_s=5.0, bias_capture_s=10.0, static_window_s=5.0) if adapting else None
    extra = {"adapt": adapt, "reference_rate_dph": 0.0} if adapting else {}
    stepper = Compensator(wesn, 0.1, **extra)
    reference = [stepper.step(samples.sample(i)) for i in range(len(samples))]
    assert len(stepper.uncertainty.candidates) == 2
    sigmas = np.array([r.drift_sigma_dph for r in reference])
    assert np.isfinite(sigmas).sum() > 0.8 * len(sigmas) and np.nanmin(sigmas) >= 0
    for cuts in (
        [len(samples)],
        [1, 777, half, half + 3, len(samples)],
        [*range(401, len(samples), 997), len(samples)],
    ):
        runner = Compensator(wesn, 0.1, **extra)
        lo, parts = 0, []
        for hi in cuts:
            parts.append(
                runner.run(
                    dataclasses.replace(
                        samples, **{f: getattr(samples, f)[lo:hi] for f in SampleBlock.__dataclass_fields__}
                    )
                )
            )
            lo = hi
        joined = _joined(parts)
        assert [repr(joined.sample(i)) for i in range(len(samples))] == [repr(r) for r in reference]
        assert runner.uncertainty.get_state() == stepper.uncertainty.get_state()
        assert runner.uncertainty._deferred is None
