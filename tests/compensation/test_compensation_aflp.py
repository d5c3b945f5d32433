"""Stage 1, the adaptive forward linear prediction filter: equations, oracles, the paper's figure."""

import itertools
import math

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from fog_driver.compensation.aflp import AflpFilter, AflpParams, AflpState

ARW_1S_DPH = 0.176  # the paper's 1-s standard deviation of a static gyro, deg/h


def _same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


def _same_state(a: AflpState, b: AflpState) -> bool:
    return a.to_dict() == b.to_dict() and all(
        _same_bits(x, y) for x, y in ((a.phi, b.phi), (a.history, b.history), (a.ki2, b.ki2), (a.kei, b.kei))
    )


def _reference_aflp(
    r: np.ndarray, order: int, lam: float, delta: float = 1e-9, tiny: float = 1e-30, fixed_step: float | None = None
) -> tuple[np.ndarray, np.ndarray, list[float]]:
    """The method page's equations, written out with numpy vectors (an independent implementation)."""
    phi, big_r = np.zeros(order), np.zeros(order)
    ke2, ki2, kei = 0.0, np.zeros(order), np.zeros(order)
    out, levels = [], []
    for x in r:
        d_hat = float(np.dot(phi, big_r))
        e = x - d_hat
        ke2 = lam * ke2 + (1 - lam) * e**2
        ki2 = lam * ki2 + (1 - lam) * big_r**2
        kei = lam * kei + (1 - lam) * e * big_r
        pi = kei / np.sqrt(ke2 * ki2 + tiny)
        level = fixed_step if fixed_step is not None else float(np.mean(np.abs(pi)))
        phi = phi + level / (delta + np.dot(big_r, big_r)) * e * big_r
        big_r = np.concatenate(([x], big_r[:-1]))
        out.append(d_hat)
        levels.append(level)
    return np.array(out), phi, levels


# --- 1. step == run == any chunking; state round trip --------------------------------------------

finite = st.floats(-1e3, 1e3, allow_nan=False, allow_subnormal=False)
samples = st.lists(st.one_of(finite, finite, finite, finite, st.just(math.nan)), max_size=120)
params = st.builds(
    AflpParams,
    order=st.integers(1, 12),
    forgetting=st.floats(0.5, 0.999),
    fixed_step=st.one_of(st.none(), st.floats(0.01, 1.9)),
)


@pytest.mark.determinism
@settings(max_examples=150)
@given(params, samples, st.lists(st.integers(0, 120), max_size=6))
def test_run_equals_step_for_any_chunking(p, values, cuts):
    r = np.array(values, dtype=np.float64)
    stepped = AflpFilter(p)
    one_by_one = np.array([stepped.step(v) for v in r], dtype=np.float64)

    whole = AflpFilter(p)
    at_once = whole.run(r)

    chunked = AflpFilter(p)
    edges = [0, *sorted(c for c in cuts if c <= len(r)), len(r)]
    pieces = np.concatenate([chunked.run(r[a:b]) for a, b in itertools.pairwise(edges)])

    assert _same_bits(at_once, one_by_one)
    assert _same_bits(pieces, one_by_one)
    assert _same_state(whole.get_state(), stepped.get_state()) and _same_state(chunked.get_state(), stepped.get_state())
    assert whole.get_state().samples == int(np.isfinite(r).sum())


@pytest.mark.determinism
@settings(max_examples=60)
@given(params, samples, st.integers(0, 120))
def test_state_saved_mid_stream_through_yaml_continues_identically(p, values, cut):
    r = np.array(values, dtype=np.float64)
    cut = min(cut, len(r))
    uninterrupted = AflpFilter(p).run(r)

    first = AflpFilter(p)
    head = first.run(r[:cut])
    saved = first.get_state().to_dict()
    text = yaml.safe_dump({"aflp": saved})  # what a model file does; no numpy scalar may reach it
    restored = AflpState.from_dict(yaml.safe_load(text)["aflp"])
    tail = AflpFilter(p, restored).run(r[cut:])

    assert _same_bits(np.concatenate([head, tail]), uninterrupted)
    assert _same_state(restored, first.get_state())
    assert all(type(v) is float for key in ("phi", "history", "ki2", "kei") for v in saved[key])
    assert type(saved["ke2"]) is float and type(saved["samples"]) is int


def test_state_property_is_a_copy_and_reset_restarts():
    r = np.random.default_rng(3).standard_normal(300)
    f = AflpFilter()
    first = f.run(r)
    s = f.get_state()
    s.phi[:] = 1e6  # must not reach the filter
    s.history[:] = 1e6
    assert not _same_state(s, f.get_state())
    f.reset()
    assert _same_state(f.get_state(), AflpState.zeros(10))
    assert _same_bits(f.run(r), first)


def test_warm_up_history_holds_zeros_until_order_samples_seen():
    f = AflpFilter(AflpParams(order=4))
    assert f.step(5.0) == 0.0  # no past: the prediction is 0
    f.step(6.0)
    assert f.get_state().history.tolist() == [6.0, 5.0, 0.0, 0.0]
    f.run(np.array([7.0, 8.0, 9.0]))
    assert f.get_state().history.tolist() == [9.0, 8.0, 7.0, 6.0]
    assert f.get_state().samples == 5


# --- 2. the equations, and the NLMS oracle --------------------------------------------------------


@pytest.mark.parametrize("mu", [0.05, 0.5, 1.5])
def test_fixed_step_is_plain_nlms(mu):
    rng = np.random.default_rng(11)
    r = np.cumsum(rng.standard_normal(2000)) * 0.01 + rng.standard_normal(2000)
    # independent NLMS: Phi += mu e R / (delta + R.R), the prediction made before the update
    phi, big_r, expected = np.zeros(10), np.zeros(10), []
    for x in r:
        y = float(phi @ big_r)
        phi = phi + mu * (x - y) * big_r / (1e-9 + big_r @ big_r)
        big_r = np.roll(big_r, 1)
        big_r[0] = x
        expected.append(y)
    f = AflpFilter(AflpParams(fixed_step=mu))
    np.testing.assert_allclose(f.run(r), expected, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(f.get_state().phi, phi, rtol=1e-9, atol=1e-12)
    # and the adaptive step is really something else
    assert not np.allclose(AflpFilter(AflpParams()).run(r), expected, rtol=1e-3)


@pytest.mark.parametrize(("order", "lam"), [(10, 0.99), (3, 0.95), (1, 0.9)])
def test_adaptive_filter_follows_the_method_equations(order, lam):
    rng = np.random.default_rng(order)
    r = 0.3 * np.sin(np.arange(1500) / 50) + ARW_1S_DPH * rng.standard_normal(1500)
    expected, phi, levels = _reference_aflp(r, order, lam)
    f = AflpFilter(AflpParams(order=order, forgetting=lam))
    got = []
    for x in r:
        got.append(f.step(x))
    np.testing.assert_allclose(got, expected, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(f.get_state().phi, phi, rtol=1e-9, atol=1e-12)
    assert f.step_factor() == pytest.approx(levels[-1], rel=1e-9)


# --- 3. |Pi| <= 1 and L in [0, 1] -------------------------------------------------------------


@settings(max_examples=100)
@given(
    st.integers(1, 12),
    st.floats(0.5, 0.999),
    st.lists(
        st.one_of(st.floats(-1e6, 1e6, allow_nan=False, allow_subnormal=False), st.sampled_from([0.0, 1.0, -1.0])),
        max_size=150,
    ),
)
def test_correlations_are_bounded_by_one(order, lam, values):
    f = AflpFilter(AflpParams(order=order, forgetting=lam))
    for v in values:
        f.step(v)
        s = f.get_state()
        # Cauchy-Schwarz on the state itself (same weights, all started at 0), before any clamping
        assert np.all(s.kei**2 <= s.ke2 * s.ki2 * (1 + 1e-9) + 1e-300)
        pi = f.correlations()
        assert np.all(np.abs(pi) <= 1.0)
        np.testing.assert_array_equal(pi, s.correlations())
        assert 0.0 <= f.step_factor() <= 1.0


def test_step_factor_is_large_while_wrong_and_small_once_converged():
    rng = np.random.default_rng(5)
    r = ARW_1S_DPH * rng.standard_normal(6000)
    r[3000:] += 2.0  # the predictor is suddenly wrong
    f = AflpFilter()
    levels = []
    for x in r:
        f.step(x)
        levels.append(f.step_factor())
    levels = np.array(levels)
    before, after = np.median(levels[2000:3000]), np.median(levels[5000:])
    assert before < 0.1 and after < 0.1
    assert levels[3000:3020].max() > 4 * max(before, after)  # ~0.05 -> ~0.23 within 5 samples


# --- 4. an AR(2) process: the predictor converges to the true coefficients -----------------------


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_converges_to_the_ar2_predictor(seed):
    a1, a2, n, order = 1.2, -0.5, 20000, 10
    rng = np.random.default_rng(seed)
    v = rng.standard_normal(n)
    r = np.zeros(n)
    for k in range(2, n):
        r[k] = a1 * r[k - 1] + a2 * r[k - 2] + v[k]
    f = AflpFilter(AflpParams(order=order))
    phis = []
    predictions = []
    for x in r:
        predictions.append(f.step(x))
        phis.append(f.get_state().phi)
    phi_late = np.mean(phis[n // 2 :], axis=0)  # the adaptive weights fluctuate: average the second half
    # independent reference: least squares on the same data
    lagged = np.column_stack([r[order - 1 - i : n - 1 - i] for i in range(order)])
    phi_ls = np.linalg.lstsq(lagged, r[order:], rcond=None)[0]
    assert np.abs(phi_ls - [a1, a2, *([0.0] * (order - 2))]).max() < 0.05  # the reference is right
    assert np.abs(phi_late - phi_ls).max() < 0.06
    e = r - np.array(predictions)
    assert np.var(e[n // 2 :]) / np.var(v[n // 2 :]) < 1.1  # a-priori error ~ the innovation
    assert np.var(e[n // 2 :]) < 0.5 * np.var(r[n // 2 :])  # far better than predicting 0


# --- 5. the paper's figure: static gyro, 0.176 deg/h 1-s std --------------------------------------


def _static_gyro(seed: int, n: int = 5000, drift_amplitude_dph: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """1-Hz rate of a static gyro with B0 and Earth rate removed: a slow drift (1-h sinusoid) + white noise."""
    t_s = np.arange(n)
    drift = drift_amplitude_dph * np.sin(2 * np.pi * t_s / 3600 + 1.0)
    return drift + ARW_1S_DPH * np.random.default_rng(seed).standard_normal(n), drift


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_static_output_std_falls_like_the_paper(seed):
    # The paper's figure: std of the filtered static output vs the raw one, 0.176 -> 0.044 deg/h.
    # Measured about the true slow drift, so a filter that lagged or lost the drift would be
    # penalized: this is the noise removed, not the signal.  With the default forgetting 0.99 the
    # ratio is ~4.1 (3.95..4.31 over 20 seeds); 5.5 on drift-free noise.
    r, drift = _static_gyro(seed)
    out = AflpFilter().run(r)
    warm = slice(1000, None)
    input_std = np.std((r - drift)[warm])
    output_std = np.std((out - drift)[warm])
    assert input_std == pytest.approx(ARW_1S_DPH, rel=0.05)
    assert input_std / output_std >= 3.0
    assert abs(np.mean((out - drift)[warm])) < 0.01  # no bias: the drift itself passes


def test_forgetting_trades_smoothing_against_step_size():
    r, _ = _static_gyro(0, drift_amplitude_dph=0.0)
    ratios = [ARW_1S_DPH / np.std(AflpFilter(AflpParams(forgetting=lam)).run(r)[1000:]) for lam in (0.95, 0.97, 0.99)]
    assert ratios[0] < ratios[1] < ratios[2]
    assert ratios[1] == pytest.approx(4.0, rel=0.1)  # 0.97 matches 0.176 -> 0.044 on drift-free noise


def test_large_mean_caps_the_noise_reduction_below_sqrt_order():
    # A limit of the method, not of the code: about a large mean (B0 or Earth rate left in) the
    # predictor must average (sum Phi = 1), and an average of N white samples has std sigma/sqrt(N).
    # So 4x with N = 10 is only possible on zero-mean input: remove B0 first.
    r = 10.0 + ARW_1S_DPH * np.random.default_rng(0).standard_normal(5000)
    f = AflpFilter()
    out = f.run(r)
    ratio = np.std(r[1000:]) / np.std(out[1000:])
    assert 1.5 < ratio < math.sqrt(10)
    assert f.get_state().phi.sum() == pytest.approx(1.0, abs=0.01)


# --- 6. a step in the input -------------------------------------------------------------------


@pytest.mark.parametrize(("seed", "step_dph"), [(0, 2.0), (1, -2.0), (2, 2.0), (3, 0.5)])
def test_output_follows_a_step_within_twenty_samples(seed, step_dph):
    # Measured over 30 seeds (2 deg/h): the prediction is within 25 % of the new level from
    # 7-9 samples after the step (13 at worst), and every later 50-sample mean within 5 %.
    r = ARW_1S_DPH * np.random.default_rng(seed).standard_normal(5000)
    r[3000:] += step_dph
    out = AflpFilter().run(r)
    err = (out[3000:] - step_dph) / abs(step_dph)
    if abs(step_dph) >= 1.0:
        assert np.all(np.abs(err[20:]) < 0.25)
    block_means = np.abs(err[20:1970].reshape(-1, 50).mean(axis=1))
    assert block_means.max() < (0.05 if abs(step_dph) >= 1.0 else 0.15)
    assert np.abs(err[:3]).min() > 0.5  # it is a prediction from the past: it cannot jump at once


# --- NaN and non-finite input -----------------------------------------------------------------


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_sample_is_skipped(bad):
    rng = np.random.default_rng(9)
    r = rng.standard_normal(400)
    f = AflpFilter()
    f.run(r[:200])
    before = f.get_state()
    prediction = float(np.dot(before.phi, before.history))
    assert f.step(bad) == prediction  # the prediction from the past, as for any sample
    assert _same_state(f.get_state(), before)  # and nothing else changed
    with_gap = np.concatenate([r[:200], [bad], r[200:]])
    out = AflpFilter().run(with_gap)
    assert np.isfinite(out).all()
    assert _same_bits(np.delete(out, 200), AflpFilter().run(r))  # as if the sample never came


# --- 7. invalid parameters and states -----------------------------------------------------------


@pytest.mark.parametrize(
    "kwargs",
    [
        {"order": 0},
        {"order": -1},
        {"order": 2.0},
        {"order": True},
        {"forgetting": 0.0},
        {"forgetting": 1.0},
        {"forgetting": 1.5},
        {"forgetting": math.nan},
        {"delta": 0.0},
        {"delta": -1e-9},
        {"delta": math.inf},
        {"tiny": 0.0},
        {"tiny": math.nan},
        {"fixed_step": 0.0},
        {"fixed_step": 2.0},
        {"fixed_step": -0.1},
        {"fixed_step": math.nan},
    ],
)
def test_invalid_params_raise(kwargs):
    with pytest.raises(ValueError):
        AflpParams(**kwargs)


def test_invalid_states_raise():
    good = AflpState.zeros(3).to_dict()
    for bad in (
        {**good, "phi": [0.0, 0.0]},
        {**good, "ke2": -1.0},
        {**good, "ki2": [0.0, -1.0, 0.0]},
        {**good, "kei": [0.0, math.nan, 0.0]},
        {**good, "samples": -1},
        {**good, "samples": 1.5},
        {**good, "extra": 1},
        {k: v for k, v in good.items() if k != "history"},
        {**good, "phi": ["a", 0.0, 0.0]},
    ):
        with pytest.raises(ValueError):
            AflpState.from_dict(bad)
    with pytest.raises(ValueError):
        AflpFilter(AflpParams(order=4), AflpState.zeros(3))
    with pytest.raises(ValueError):
        AflpFilter().run(np.zeros((2, 2)))
