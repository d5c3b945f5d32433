"""Online adaptation of the readout (``compensation/adapt.py``): convergence with a reference, the gate,
the bias capture, the guards, state save/restore, step == run, and the static detector."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from fog_driver.compensation.adapt import (
    ADAPT_STATE_FORMAT,
    AdaptConfig,
    OnlineReadout,
    StaticDetector,
)
from fog_driver.compensation.numerics import dot
from fog_driver.compensation.readout import (
    AdaptiveLaw,
    AdaptiveLawParams,
    AdaptiveLawState,
)
from fog_driver.errors import InputFileError, OutputFileError
from fog_driver.flags import FLAG_ADAPTING, FLAG_GUARD
from fog_driver.modelfiles import load_readout_state, save_readout_state

W0 = np.array([0.5, -0.3, 0.2])  # the frozen (stored) weights
B0 = 0.1
W_TRUE = np.array([0.8, -0.1, 0.0])  # what the drift really is this run
EARTH_AND_BIAS = 20.0  # Earth rate + constant bias + this run's turn-on bias, deg/h


def _regressors(seed: int, t: int, n: int = 3, tau: float = 300.0) -> np.ndarray:
    """A fixed slow random process (unit-variance AR(1) per column), like temperature-driven regressors."""
    rng = np.random.default_rng(seed)
    a = np.exp(-1.0 / tau)
    e = rng.normal(size=(t, n)) * np.sqrt(1 - a * a)
    f = np.empty((t, n))
    acc = rng.normal(size=n)
    for k in range(t):
        acc = a * acc + e[k]
        f[k] = acc
    return f


def _problem(t: int, *, seed: int = 0, bias: float = EARTH_AND_BIAS, w_true=W_TRUE, b_true=B0, noise=0.2):
    """measured = reference (0) + bias + f . w_true + b_true + noise."""
    f = _regressors(seed, t)
    drift = dot(f, np.asarray(w_true)) + b_true
    measured = bias + drift + noise * np.random.default_rng(seed + 100).normal(size=t)
    return f, drift, measured


def _frozen(f: np.ndarray) -> np.ndarray:
    return dot(f, W0) + B0


# --- convergence with a reference -------------------------------------------------------------------


def test_adapting_with_a_reference_while_static_converges_to_the_true_weights():
    t = 12000
    f, drift, measured = _problem(t)
    r = OnlineReadout(W0, B0, AdaptConfig(), 1.0)
    est, flags = r.run(f, measured, 0.0, True)
    assert r.guards == 0 and not (flags & FLAG_GUARD).any()
    assert r.updates == t - r.bias_capture_blocks == t - 300
    np.testing.assert_allclose(r.weights, W_TRUE, rtol=0, atol=0.02)
    # The slopes: the adapted error (its mean removed: the offset is confounded with the run's bias,
    # see below) is a small fraction of the frozen model's error over the last stretch.
    tail = slice(-2000, None)
    err_adapted = (est - drift)[tail]
    err_frozen = (_frozen(f) - drift)[tail]
    assert err_frozen.std() > 0.3
    assert err_adapted.std() < 0.05 * err_frozen.std()
    # The offset: the adapted model plus the captured bias explains the measurement.
    assert abs(np.mean(est[tail] + r.bias_dph - measured[tail])) < 0.02


def test_a_paused_gate_keeps_w_and_reenabling_continues():
    f, _, measured = _problem(6000)
    r = OnlineReadout(W0, B0, AdaptConfig(), 1.0)
    r.run(f[:2000], measured[:2000], 0.0, True)
    w_mid = r.law.weights
    assert not np.array_equal(w_mid[:-1], W0)  # it has moved
    _, flags = r.run(f[2000:3000], measured[2000:3000], None, True)  # no reference for 1000 blocks
    np.testing.assert_array_equal(r.law.weights, w_mid)
    assert not flags.any()
    _, flags = r.run(f[3000:], measured[3000:], 0.0, True)
    assert (flags == FLAG_ADAPTING).all()
    np.testing.assert_allclose(r.weights, W_TRUE, rtol=0, atol=0.03)


# --- the gate -----------------------------------------------------------------------------------------


@pytest.mark.parametrize("reference,static", [(None, True), (0.0, False), (float("nan"), True), ("mixed", None)])
def test_gate_off_keeps_the_frozen_weights_while_the_sums_run(reference, static):
    t = 1500
    f, _, measured = _problem(t, seed=3)
    if reference == "mixed":  # a reference on odd blocks, static on even ones: never both
        reference = np.where(np.arange(t) % 2, 0.0, np.nan)
        static = np.arange(t) % 2 == 0
    r = OnlineReadout(W0, B0, AdaptConfig(bias_capture_s=0.0), 1.0)  # no capture: it would adapt at once
    est, flags = r.run(f, measured, reference, static)
    np.testing.assert_array_equal(r.law.weights, np.r_[W0, B0])
    np.testing.assert_array_equal(est, _frozen(f))
    assert not flags.any() and r.updates == 0 and r.gated_blocks == 0
    # H and I evolved exactly as in a law run with update=True on the same regressors and (neutral) targets
    law = AdaptiveLaw(AdaptConfig().law, 4, 1.0, AdaptiveLawState.zeros(4, np.r_[W0, B0]))
    law.run(np.column_stack([f, np.ones(t)]), _frozen(f), True)
    got, want = r.law.get_state(), law.get_state()
    assert np.abs(got.h).max() > 1.0
    np.testing.assert_array_equal(got.h, want.h)
    np.testing.assert_array_equal(got.i, want.i)
    np.testing.assert_array_equal(got.xf, want.xf)


def test_gate_on_does_adapt():
    """The counterpart of the gate-off test (same data): with a reference while static, W moves."""
    f, _, measured = _problem(1500, seed=3)
    r = OnlineReadout(W0, B0, AdaptConfig(bias_capture_s=0.0), 1.0)
    _, flags = r.run(f, measured - EARTH_AND_BIAS, 0.0, True)
    assert (flags == FLAG_ADAPTING).all() and r.updates == 1500
    assert not np.array_equal(r.law.weights, np.r_[W0, B0])


# --- the bias capture -----------------------------------------------------------------------------------


def test_the_bias_capture_removes_a_constant_bias():
    t = 4000
    bias = 50.0
    f, _, measured = _problem(t, seed=5, bias=bias, w_true=W0, b_true=B0)  # the frozen model is right
    r = OnlineReadout(W0, B0, AdaptConfig(), 1.0)
    est, flags = r.run(f, measured, 0.0, True)
    # W frozen exactly during the capture (300 gated blocks), adapting from the next block on
    assert not flags[:300].any() and (flags[300:] == FLAG_ADAPTING).all()
    np.testing.assert_array_equal(est[:301], _frozen(f)[:301])
    assert r.bias_count == 300 and abs(r.bias_dph - bias) < 0.05
    # the adapted model did not absorb the bias: it stays the frozen drift model
    np.testing.assert_allclose(r.law.weights, np.r_[W0, B0], rtol=0, atol=0.05)
    assert np.abs(est - _frozen(f)).max() < 0.1
    # without the capture the bias is a 50 deg/h innovation: the gate keeps it from the law, every block flagged
    r0 = OnlineReadout(W0, B0, AdaptConfig(bias_capture_s=0.0), 1.0)
    est0, flags0 = r0.run(f, measured, 0.0, True)
    assert r0.updates < 10 and r0.rejected > len(f) - 10 and (flags0[10:] & FLAG_GUARD).all()
    np.testing.assert_array_equal(est0, _frozen(f))


def test_the_capture_counts_gated_blocks_only():
    f, _, measured = _problem(1000, seed=6)
    static = np.arange(1000) >= 400  # not static for the first 400 blocks
    r = OnlineReadout(W0, B0, AdaptConfig(bias_capture_s=100.0), 1.0)
    _, flags = r.run(f, measured, 0.0, static)
    assert not flags[:500].any() and (flags[500:] == FLAG_ADAPTING).all()
    resid = measured[400:500] - _frozen(f)[400:500]
    assert r.bias_dph == pytest.approx(resid.mean(), abs=1e-12)


# --- guards ---------------------------------------------------------------------------------------------


def _adapted(t: int = 1000) -> tuple[OnlineReadout, np.ndarray, np.ndarray]:
    f, _, measured = _problem(t + 10, seed=7)
    r = OnlineReadout(W0, B0, AdaptConfig(), 1.0)
    r.run(f[:t], measured[:t], 0.0, True)
    assert r.updates > 0 and r.guards == 0
    return r, f, measured


def test_a_huge_target_is_kept_from_the_law_by_the_innovation_gate():
    r, f, measured = _adapted()
    assert not np.array_equal(r.law.weights, np.r_[W0, B0])  # it has adapted
    y, flags = r.step(f[1000], 1e6, 0.0, True)  # the gyro far from the reference: the table moved, say
    assert flags == FLAG_GUARD and r.rejected == 1 and r.updates == 1000 - 300
    assert y == _frozen(f[1000:1001])[0]
    # not learned, and what was learned before is dropped (the mismatch may have grown for a while)
    np.testing.assert_array_equal(r.law.weights, np.r_[W0, B0])
    assert np.abs(r.law.get_state().i).max() < 10  # the neutral target: nothing of the 1e6 in I
    y, flags = r.step(f[1001], measured[1001], 0.0, True)
    assert flags == FLAG_GUARD  # the filtered innovation still remembers the bad block: still refused
    assert r.gate_innovation_dph > r.gate_limit_dph


def test_a_runaway_reverts_to_the_frozen_weights_and_clears_what_the_law_had_learned():
    r, f, measured = _adapted()
    state = r.law.get_state()
    state.w = np.r_[W0, B0] + np.array([0.0, 0.0, 0.0, 5.0])  # 5 deg/h off: beyond the 2 deg/h runaway
    r.law.set_state(state)
    y, flags = r.step(f[1000], measured[1000], None, False)
    assert flags == FLAG_GUARD and r.guards == 1
    assert y == _frozen(f[1000:1001])[0]  # the frozen estimate, exactly
    np.testing.assert_array_equal(r.law.weights, np.r_[W0, B0])  # W reset (and not updated: gate off)
    # H and I cleared: kept, they would lead W straight back to the solution that ran away
    law = AdaptiveLaw(AdaptConfig().law, 4, 1.0)
    law.track(np.r_[f[1000], 1.0], float(np.r_[f[1000], 1.0] @ np.r_[W0, B0]))
    np.testing.assert_allclose(r.law.get_state().h, law.get_state().h, rtol=0, atol=1e-12)
    assert np.abs(r.law.get_state().i).max() < 1.0


def test_the_runaway_bound_comes_from_the_models_fit_residual():
    from fog_driver.compensation.adapt import RUNAWAY_MAX_DPH, RUNAWAY_MIN_DPH, runaway_for

    assert runaway_for(0.024) == pytest.approx(0.12)
    assert runaway_for(0.001) == RUNAWAY_MIN_DPH and runaway_for(1.0) == RUNAWAY_MAX_DPH
    assert runaway_for(None) == RUNAWAY_MAX_DPH and runaway_for(float("nan")) == RUNAWAY_MAX_DPH
    assert OnlineReadout(W0, B0, AdaptConfig(), 1.0, fit_residual_dph=0.024).runaway_dph == pytest.approx(0.12)
    assert OnlineReadout(W0, B0, AdaptConfig(runaway_dph=0.7), 1.0, fit_residual_dph=0.024).runaway_dph == 0.7


def test_a_non_finite_estimate_reverts_and_flags():
    r, f, measured = _adapted()
    state = r.law.get_state()
    state.w = np.full(4, 1e308)  # overflows to inf in the estimate
    r.law.set_state(state)
    y, flags = r.step(f[1000], measured[1000], 0.0, False)
    assert flags == FLAG_GUARD and y == _frozen(f[1000:1001])[0]
    np.testing.assert_array_equal(r.law.weights, np.r_[W0, B0])


def test_a_non_finite_w_after_an_update_is_reset_at_once():
    f, _, measured = _problem(600, seed=8)
    # a wildly unstable fixed gain: the first real update overflows W
    r = OnlineReadout(W0, B0, AdaptConfig(law=AdaptiveLawParams(fixed_gain=1e308), bias_capture_s=0.0), 1.0)
    r.run(f[:500], measured[:500], None, True)  # gate off: H and I build up, W stays
    y, flags = r.step(f[500], measured[500] + 1.0, 0.0, True)  # a plausible target (within the gate)
    assert flags == FLAG_ADAPTING | FLAG_GUARD and np.isfinite(y)
    np.testing.assert_array_equal(r.law.weights, np.r_[W0, B0])
    assert yaml.safe_load(yaml.safe_dump(r.get_state()))  # the state stays saveable


def test_non_finite_regressors_give_a_flagged_nan_and_leave_the_state_alone():
    r, _, measured = _adapted()
    before = r.get_state()
    y, flags = r.step(np.array([np.nan, 0.0, 0.0]), measured[1000], 0.0, True)
    assert np.isnan(y) and flags == FLAG_GUARD
    after = r.get_state()
    assert after.pop("blocks") == before.pop("blocks") + 1 and after == before


def test_a_non_finite_measurement_is_not_gated():
    r, f, _ = _adapted()
    w = r.law.weights
    _, flags = r.step(f[1000], float("nan"), 0.0, True)
    assert flags == 0
    np.testing.assert_array_equal(r.law.weights, w)


# --- state, step == run -----------------------------------------------------------------------------------


def _stream(t: int = 1500):
    """Block rates with a turntable move, a static detector deciding the gate, a reference throughout."""
    f, _, measured = _problem(t, seed=11)
    measured = measured.copy()
    measured[700:720] += 36000.0  # the table turns
    return f, measured


def _run_detected(readout: OnlineReadout, detector: StaticDetector, f, measured, lo, hi):
    out = []
    for k in range(lo, hi):
        static = detector.step(measured[k])
        out.append(readout.step(f[k], measured[k], 0.0, static))
    return out


@pytest.mark.determinism
def test_state_saved_and_restored_mid_stream_continues_bit_identically(tmp_path):
    f, measured = _stream()
    config = AdaptConfig(bias_capture_s=200.0)
    whole = OnlineReadout(W0, B0, config, 1.0)
    whole_detector = StaticDetector.from_config(config, 1.0)
    expected = _run_detected(whole, whole_detector, f, measured, 0, len(f))
    assert {fl for _, fl in expected} >= {0, FLAG_ADAPTING}
    for cut in (150, 262, 705, 1100):  # mid capture, right after it, mid move, adapting
        a = OnlineReadout(W0, B0, config, 1.0)
        da = StaticDetector.from_config(config, 1.0)
        got = _run_detected(a, da, f, measured, 0, cut)
        path = save_readout_state(a, tmp_path / f"state-{cut}.yaml", detector=da)
        b = OnlineReadout(W0, B0, config, 1.0)
        db = StaticDetector.from_config(config, 1.0)
        assert load_readout_state(b, path, detector=db) is not None
        assert b.get_state() == a.get_state() and db.to_dict() == da.to_dict()
        got += _run_detected(b, db, f, measured, cut, len(f))
        assert got == expected  # estimates (floats) and flags, exactly
        assert b.get_state() == whole.get_state()


def test_readout_state_round_trips_through_yaml_exactly():
    r, f, measured = _adapted()
    d = r.get_state()
    again = yaml.safe_load(yaml.safe_dump(d))
    assert again == d
    r2 = OnlineReadout(W0, B0, AdaptConfig(), 1.0, state=again)
    assert r2.get_state() == d
    a = [r.step(f[k], measured[k], 0.0, True) for k in range(1000, 1010)]
    b = [r2.step(f[k], measured[k], 0.0, True) for k in range(1000, 1010)]
    assert a == b


@pytest.mark.determinism
def test_step_equals_run_for_any_chunking():
    f, measured = _stream(1200)
    static = StaticDetector.from_config(AdaptConfig(), 1.0).run(measured)
    reference = np.where(np.arange(1200) % 300 < 250, 0.0, np.nan)
    config = AdaptConfig(bias_capture_s=100.0)
    stepper = OnlineReadout(W0, B0, config, 1.0)
    stepped = [
        stepper.step(f[k], measured[k], None if reference[k] != reference[k] else 0.0, static[k]) for k in range(1200)
    ]
    est = np.array([s[0] for s in stepped])
    flags = np.array([s[1] for s in stepped])
    assert (flags == FLAG_ADAPTING).sum() > 100
    for cuts in ([1200], [1, 2, 500, 1199, 1200], list(range(97, 1200, 97)) + [1200]):
        runner = OnlineReadout(W0, B0, config, 1.0)
        parts, lo = [], 0
        for hi in cuts:
            parts.append(runner.run(f[lo:hi], measured[lo:hi], reference[lo:hi], static[lo:hi]))
            lo = hi
        np.testing.assert_array_equal(np.concatenate([p[0] for p in parts]), est)
        np.testing.assert_array_equal(np.concatenate([p[1] for p in parts]), flags)
        assert runner.get_state() == stepper.get_state()


def test_reset_to_frozen_clears_the_laws_sums_keeps_the_bias_and_restarts_the_comparison():
    r, _, _ = _adapted()
    before = r.get_state()
    assert before["compare_windows"] > 0
    r.reset_to_frozen()
    after = r.get_state()
    assert after["law"]["w"] == [*W0.tolist(), B0]
    assert after["compare_weights"] == after["law"]["w"] and after["compare_windows"] == 0
    assert all(after[k] == 0 for k in after if k.startswith("compare_") and k != "compare_weights")
    keep = [k for k in before if k != "law" and not k.startswith("compare_")]
    assert {k: after[k] for k in keep} == {k: before[k] for k in keep}
    fresh = OnlineReadout(W0, B0, AdaptConfig(), 1.0).get_state()["law"]
    assert after["law"] == fresh


# --- state files -------------------------------------------------------------------------------------------


def test_state_file_errors_are_one_line_input_file_errors(tmp_path):
    r, _, _ = _adapted()
    good = save_readout_state(r, tmp_path / "state.yaml")
    doc = yaml.safe_load(good.read_text())
    assert doc["format"] == ADAPT_STATE_FORMAT and doc["schema_version"] == 1

    def variant(name: str, change) -> object:
        d = yaml.safe_load(good.read_text())
        change(d)
        p = tmp_path / name
        p.write_text(yaml.safe_dump(d))
        return p

    cases = {
        "missing": tmp_path / "nope.yaml",
        "garbage": tmp_path / "garbage.yaml",
        "format": variant("format.yaml", lambda d: d.update(format="something else")),
        "version": variant("version.yaml", lambda d: d.update(schema_version=99)),
        "rate": variant("rate.yaml", lambda d: d.update(sample_time_s=0.5)),
        "model": variant("model.yaml", lambda d: d["readout"]["frozen_weights"].__setitem__(0, 0.25)),
        "keys": variant("keys.yaml", lambda d: d["readout"].pop("bias_dph")),
        "law": variant("law.yaml", lambda d: d["readout"]["law"].update(w=[1.0, 2.0])),
        "count": variant("count.yaml", lambda d: d["readout"].update(updates=-1)),
        "detector": good,  # asked for a detector the file does not have
    }
    (tmp_path / "garbage.yaml").write_text("readout: [unclosed\n")
    fresh = OnlineReadout(W0, B0, AdaptConfig(), 1.0)
    untouched = fresh.get_state()
    for name, path in cases.items():
        detector = StaticDetector(30.0, 60) if name == "detector" else None
        with pytest.raises(InputFileError) as info:
            load_readout_state(fresh, path, detector=detector)
        assert "\n" not in str(info.value) and str(path) in str(info.value), name
        assert fresh.get_state() == untouched, name  # nothing half-loaded
    # a python object tag is never constructed
    (tmp_path / "evil.yaml").write_text("!!python/object/apply:os.system ['true']\n")
    with pytest.raises(InputFileError):
        load_readout_state(fresh, tmp_path / "evil.yaml")


def test_an_unwritable_state_file_is_an_output_file_error(tmp_path):
    r = OnlineReadout(W0, B0, AdaptConfig(), 1.0)
    with pytest.raises(OutputFileError):
        save_readout_state(r, tmp_path / "no-such-dir" / "state.yaml")


def test_config_validation_and_round_trip():
    c = AdaptConfig(runaway_dph=1.5, bias_capture_s=0.0)
    assert AdaptConfig.from_dict(yaml.safe_load(yaml.safe_dump(c.to_dict()))) == c
    for bad in (
        {"runaway_dph": 0.0},
        {"static_window_s": float("nan")},
        {"bias_capture_s": -1.0},
        {"static_threshold_dph": True},
        {"compare_window_s": 0.0},
        {"compare_window_s": float("inf")},
        {"compare_memory_windows": 0.5},
        {"compare_memory_windows": float("nan")},
        {"compare_min_windows": -1},
        {"compare_min_windows": 2.0},
        {"compare_min_windows": True},
    ):
        with pytest.raises(ValueError):
            AdaptConfig(**bad)
    with pytest.raises(ValueError):
        AdaptConfig.from_dict({"gain": 1.0})
    with pytest.raises(ValueError):
        OnlineReadout([1.0, np.nan], 0.0)
    with pytest.raises(ValueError):
        OnlineReadout(W0, B0).step(np.zeros(4), 0.0, 0.0, True)


# --- the static detector -------------------------------------------------------------------------------------


def test_static_detector_sees_a_turntable_move_and_settles_after_a_window():
    rng = np.random.default_rng(2)
    t, window = 600, 60
    rate = 9.7 + 0.2 * rng.normal(size=t)
    rate[200] += 25.0  # the move starts late in block 200: part of a block, still under the threshold
    rate[201:230] += 36000.0  # 10 deg/s
    rate[230] += 5000.0  # and ends early in block 230
    detector = StaticDetector.from_config(AdaptConfig(), 1.0)
    assert detector.window_blocks == window
    static = detector.run(rate)
    assert not static[: window - 1].any()  # the window fills first
    assert static[window - 1 : 201].all()  # static before the move (block 200's partial move is under 30 dph)
    assert not static[201 : 230 + window].any()  # moving, and for a window after its last block
    assert static[230 + window :].all()  # static again


def test_static_detector_refuses_non_finite_and_offsets():
    d = StaticDetector(30.0, 10)
    rates = [0.0] * 20 + [float("nan")] + [0.0] * 20 + [31.0] + [0.0] * 20 + [29.0] + [0.0] * 5
    s = d.run(np.array(rates))
    assert s[9:20].all() and not s[20:30].any() and s[30:41].all() and not s[41:51].any() and s[51:].all()
    # the threshold is on |rate - median|: 29 dph off is static, 31 is not
    # a constant offset is static (it is the median), however large
    assert StaticDetector(1.0, 5).run(np.full(8, 1e4))[4:].all()


def test_static_detector_state_round_trips_mid_stream():
    rng = np.random.default_rng(4)
    rate = rng.normal(size=300) * 20.0
    rate[100:110] = np.nan
    whole = StaticDetector(30.0, 25).run(rate)
    a = StaticDetector(30.0, 25)
    first = a.run(rate[:105])
    b = StaticDetector.from_dict(yaml.safe_load(yaml.safe_dump(a.to_dict())))
    np.testing.assert_array_equal(np.r_[first, b.run(rate[105:])], whole)
    with pytest.raises(ValueError):
        StaticDetector.from_dict({"threshold_dph": 30.0, "window_blocks": 2, "rates": [1.0, 2.0, 3.0]})


def test_begin_run_captures_the_new_bias_and_keeps_the_adapted_weights():
    f, _, measured = _problem(6000, seed=12)
    r = OnlineReadout(W0, B0, AdaptConfig(compare_window_s=60.0, compare_min_windows=3), 1.0)
    r.run(f[:3000], measured[:3000], 0.0, True)
    assert r.adapted_in_use  # the wrong frozen model: adapting has earned its place (short windows here)
    w_adapted = r.law.weights
    first_bias = r.bias_dph
    r.begin_run()  # switched off and on: a new turn-on bias, 7 deg/h higher
    est, flags = r.run(f[3000:], measured[3000:] + 7.0, 0.0, True)
    # the kept weights give the estimate from the first block (flagged adapting), W still during the capture
    assert (flags == FLAG_ADAPTING).all() and r.guards == 0 and r.updates == 3000 - 300 + 6000 - 3000 - 300
    np.testing.assert_array_equal(est[:301], dot(f[3000:3301], w_adapted[:-1]) + w_adapted[-1])
    assert abs(r.bias_dph - first_bias - 7.0) < 0.05  # the new bias (relative to the adapted model, as before)
    np.testing.assert_allclose(r.weights, W_TRUE, rtol=0, atol=0.02)


def test_restored_adapted_weights_are_flagged_even_without_a_reference():
    """A state restored with no reference given (a daemon with adapt_state but no adapt_reference_dph): the
    adapted weights give the estimate, so every block says so; the frozen weights' blocks are unflagged."""
    f, _, measured = _problem(4000, seed=13)
    r = OnlineReadout(W0, B0, AdaptConfig(compare_window_s=60.0, compare_min_windows=3), 1.0)
    r.run(f[:3000], measured[:3000], 0.0, True)
    assert r.adapted_in_use
    est, flags = r.run(f[3000:], measured[3000:], None, True)
    assert (flags == FLAG_ADAPTING).all()
    frozen = OnlineReadout(W0, B0, AdaptConfig(), 1.0)
    _, frozen_flags = frozen.run(f[3000:], measured[3000:], None, True)
    assert not frozen_flags.any()


# --- the comparison guard: adapting must earn its place ------------------------------------------------


def test_over_an_exact_frozen_model_the_adapted_estimate_is_never_used():
    """The frozen model is the drift exactly: the law still moves W (it chases the noise), but the guard
    never returns its estimate, so adapting costs nothing."""
    f, drift, measured = _problem(20000, w_true=W0, b_true=B0, noise=0.2)
    r = OnlineReadout(W0, B0, AdaptConfig(bias_capture_s=300.0))
    est, flags = r.run(f, measured, 0.0, True)
    assert r.updates > 0 and not np.array_equal(r.weights, W0)  # W moved underneath
    assert est.tobytes() == _frozen(f).tobytes()  # ... and every estimate returned is the frozen one
    assert not r.adapted_in_use and r.compare_windows == (20000 - 300) // int(r.config.compare_window_s)
    assert (flags & FLAG_ADAPTING).any()  # the blocks still say that W is adapting


def test_over_a_wrong_frozen_model_the_adapted_estimate_takes_over_once_it_does_better():
    f, drift, measured = _problem(20000, w_true=W_TRUE, noise=0.2)
    config = AdaptConfig(bias_capture_s=300.0)
    r = OnlineReadout(W0, B0, config)
    est, _ = r.run(f, measured, 0.0, True)
    assert r.adapted_in_use
    frozen = _frozen(f)
    switched = int(np.flatnonzero(est != frozen)[0])
    min_blocks = 300 + config.compare_min_windows * int(config.compare_window_s)  # 1-s blocks
    assert switched >= min_blocks  # never before the bias capture and the minimum windows
    late = slice(switched + 3000, None)
    offset = (drift - est)[late].mean()  # the bias capture fixes the offset; the slopes are what adapting learns
    assert np.std(drift[late] - est[late] - offset) < 0.5 * np.std(
        drift[late] - frozen[late] - (drift - frozen)[late].mean()
    )


def test_a_state_saved_before_the_comparison_existed_still_loads():
    f, _, measured = _problem(2000)
    r = OnlineReadout(W0, B0, AdaptConfig(bias_capture_s=60.0))
    r.run(f, measured, 0.0, True)
    state = r.get_state()
    old = {k: v for k, v in state.items() if not k.startswith("compare_")}
    again = OnlineReadout(W0, B0, AdaptConfig(bias_capture_s=60.0))
    again.set_state(old)
    assert again.compare_windows == 0 and again.get_state()["law"] == state["law"]
    again.set_state(state)
    assert again.get_state() == state
    with pytest.raises(ValueError, match="the comparison needs all of"):
        again.set_state({**old, "compare_windows": 3})
    with pytest.raises(ValueError, match="compare_gain_sq"):
        again.set_state({**state, "compare_gain_sq": -1.0})
    n = len(state["compare_weights"])
    for key, bad in (
        ("compare_weights", [0.0] * (n - 1)),
        ("compare_weights", [float("nan")] * n),
        ("compare_weights", "abc"),
        ("compare_blocks", -1),
        ("compare_windows", True),
        ("compare_gain", float("inf")),
        ("compare_level_frozen_dph", "1.0"),
    ):
        with pytest.raises(ValueError, match=key):
            again.set_state({**state, key: bad})
        assert again.get_state() == state  # a refused state leaves the readout as it was


def test_a_gain_below_the_least_worth_having_keeps_the_frozen_estimate():
    """The frozen model is slightly wrong: adapting gains, significantly, but less than the least gain set
    (``compare_min_gain`` times the fit residual, squared): the frozen estimate stays in use; with no
    least gain the adapted one is used."""
    w_close = W0 + np.array([0.02, 0.0, 0.0])
    f, _, measured = _problem(6000, seed=21, w_true=w_close, noise=0.05)
    plain = OnlineReadout(
        W0,
        B0,
        AdaptConfig(compare_window_s=60.0, compare_min_windows=3, compare_min_gain=0.0),
        1.0,
        fit_residual_dph=0.05,
    )
    plain.run(f, measured, 0.0, True)
    strict = OnlineReadout(
        W0, B0, AdaptConfig(compare_window_s=60.0, compare_min_windows=3), 1.0, fit_residual_dph=0.05
    )
    _, flags = strict.run(f, measured, 0.0, True)
    assert plain.adapted_in_use and plain.compare_gain > 0
    assert strict._min_gain == pytest.approx((0.5 * 0.05) ** 2)
    assert plain.compare_gain < strict._min_gain and not strict.adapted_in_use
    with pytest.raises(ValueError):
        AdaptConfig(compare_min_gain=-1.0)
