"""The readout (stage 3): the adaptive law (convergence, gain stability, gating, step/run, state) and ridge."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from fog_driver.compensation.numerics import dot
from fog_driver.compensation.readout import (
    AdaptiveLaw,
    AdaptiveLawParams,
    AdaptiveLawState,
    Standardizer,
    ridge_fit,
)


def _problem(seed: int, t: int, n: int, scale: float = 1.0, noise: float = 0.0):
    rng = np.random.default_rng(seed)
    x = rng.normal(0.0, scale, (t, n))
    w_true = rng.normal(0.0, 1.0, n)
    return x, x @ w_true + noise * rng.normal(size=t), w_true


# --- convergence ---------------------------------------------------------------------------------


def test_converges_to_the_true_weights_on_an_exact_linear_target():
    x, d, w_true = _problem(0, 3000, 6)
    law = AdaptiveLaw(AdaptiveLawParams(filter_time_s=2.0, memory_time_s=200.0, kappa=1.0), 6)
    y_hat = law.run(x, d)
    np.testing.assert_allclose(law.weights, w_true, rtol=0, atol=1e-9)
    assert np.abs(y_hat[-100:] - d[-100:]).max() < 1e-8  # the a-priori predictions are right too


def test_converges_to_the_exponentially_weighted_least_squares_fit():
    """Noisy target: W -> H^-1 I, checked against np.linalg.lstsq on the filtered regressors and targets
    with the law's exponential weights (filtered here independently, with the ZOH constants)."""
    t, n, ts, k, mem = 6000, 5, 1.0, 3.0, 1500.0
    x, d, _ = _problem(1, t, n, noise=0.5)
    law = AdaptiveLaw(AdaptiveLawParams(filter_time_s=k, memory_time_s=mem, kappa=1.5), n, ts)
    law.run(x, d)
    alpha, lam = math.exp(-ts / k), 1.0 / mem
    xf, df = np.zeros((t, n)), np.zeros(t)
    accx, accd = np.zeros(n), 0.0
    for j in range(t):
        accx = alpha * accx + (1 - alpha) * x[j]
        accd = alpha * accd + (1 - alpha) * d[j]
        xf[j], df[j] = accx, accd
    weights = np.sqrt(np.exp(-lam * ts * np.arange(t - 1, -1, -1)))
    w_ls = np.linalg.lstsq(xf * weights[:, None], df * weights, rcond=None)[0]
    np.testing.assert_allclose(law.least_squares_weights(), w_ls, rtol=1e-9, atol=1e-12)
    # W tracks the moving fit: its lag is the fit's drift over a few samples, tiny against the noise fit
    np.testing.assert_allclose(law.weights, w_ls, rtol=0, atol=1e-3)


def test_convergence_is_slow_along_weak_directions_of_h():
    """Ill-conditioned regressors (two nearly collinear features): the strong direction converges at
    once, the weak one with a time constant of trace(H) / (kappa lambda_min) samples."""
    rng = np.random.default_rng(2)
    s = rng.normal(size=4000)
    x = np.column_stack([s, s + 1e-2 * rng.normal(size=4000)])
    w_true = np.array([1.0, -1.0])
    law = AdaptiveLaw(AdaptiveLawParams(filter_time_s=0.0, memory_time_s=500.0, kappa=1.0), 2)
    law.run(x, x @ w_true)
    h = law.get_state().h
    lam = np.linalg.eigvalsh(h)
    assert np.trace(h) / lam[0] > 1e4  # a time constant of > 10,000 samples along the weak direction
    err = law.weights - w_true
    v = np.linalg.eigh(h)[1]
    strong, weak = abs(v[:, 1] @ err), abs(v[:, 0] @ err)
    assert strong < 1e-9 and weak > 0.1  # only the strong direction converged in 4000 samples


def test_the_preconditioned_law_is_the_law_on_standardized_regressors():
    """Columns of very different scales: the plain normalized gain leaves the small column's weight far
    off, the diagonal preconditioning (the law in standardized coordinates) converges on both; and it is
    stable at any scale, as the normalized gain."""
    rng = np.random.default_rng(3)
    x = rng.normal(size=(3000, 2)) * np.array([1.0, 1e-3])
    w_true = np.array([0.5, 300.0])
    d = x @ w_true
    params = AdaptiveLawParams(filter_time_s=0.0, memory_time_s=500.0, kappa=1.0)
    plain = AdaptiveLaw(params, 2)
    plain.run(x, d)
    pre = AdaptiveLaw(AdaptiveLawParams(filter_time_s=0.0, memory_time_s=500.0, kappa=1.0, precondition=True), 2)
    pre.run(x, d)
    assert abs(plain.weights[1] - 300.0) > 100.0
    np.testing.assert_allclose(pre.weights, w_true, rtol=1e-6)
    for scale in (1e-3, 1e3):
        big = AdaptiveLaw(AdaptiveLawParams(filter_time_s=0.0, memory_time_s=500.0, kappa=1.9, precondition=True), 2)
        big.run(x * scale, d)
        assert np.all(np.isfinite(big.weights)) and np.abs(big.weights * scale - w_true).max() < 1e-3 * 300


@pytest.mark.parametrize("scale", [1e-3, 1e-1, 1.0, 1e1, 1e3])
def test_normalized_gain_is_stable_at_any_data_scale(scale):
    x, d, w_true = _problem(3, 3000, 8, scale=scale)
    law = AdaptiveLaw(AdaptiveLawParams(filter_time_s=2.0, memory_time_s=300.0, kappa=1.9, delta=1e-12), 8)
    for chunk in np.array_split(np.arange(3000), 30):
        law.run(x[chunk], d[chunk])
        assert np.isfinite(law.weights).all() and np.abs(law.weights).max() < 100
    np.testing.assert_allclose(law.weights, w_true, rtol=0, atol=1e-6)
    assert law.gain * np.linalg.eigvalsh(law.get_state().h).max() <= 1.9


@pytest.mark.filterwarnings("ignore:overflow encountered", "ignore:invalid value encountered")
def test_fixed_gain_diverges_beyond_the_bound_and_converges_below_it():
    """Fixed Gamma = Ts K is stable only while Ts K lambda_max(H) < 2."""
    x, d, w_true = _problem(4, 3000, 4)
    p = AdaptiveLawParams(filter_time_s=1.0, memory_time_s=100.0)
    probe = AdaptiveLaw(p, 4)
    probe.run(x[:1500], d[:1500], learn=False)
    lam_max = float(np.linalg.eigvalsh(probe.get_state().h).max())  # H's size once the window is full
    below = AdaptiveLaw(AdaptiveLawParams(filter_time_s=1.0, memory_time_s=100.0, fixed_gain=1.0 / lam_max), 4)
    below.run(x, d)
    np.testing.assert_allclose(below.weights, w_true, atol=1e-6)
    above = AdaptiveLaw(AdaptiveLawParams(filter_time_s=1.0, memory_time_s=100.0, fixed_gain=2.5 / lam_max), 4)
    above.run(x, d)
    assert not np.all(np.abs(above.weights) < 1e6)  # blown up (or overflowed)
    assert above.gain * float(np.linalg.eigvalsh(probe.get_state().h).max()) > 2


def test_sigma_modification_is_a_ridge_penalty_on_the_window():
    x, d, _ = _problem(5, 4000, 3, noise=0.1)
    law = AdaptiveLaw(AdaptiveLawParams(filter_time_s=1.0, memory_time_s=400.0, kappa=1.0, sigma=50.0), 3)
    law.run(x, d)
    h, i = law.get_state().h, law.get_state().i
    # W tracks the slowly moving fixed point with a small lag: 3e-4 relative here
    np.testing.assert_allclose(law.weights, np.linalg.solve(h + 50.0 * np.eye(3), i), rtol=2e-3)
    assert np.linalg.norm(law.weights) < np.linalg.norm(np.linalg.solve(h, i))


def _predict_then_learn(law: AdaptiveLaw, x: np.ndarray, d: float, learn: bool) -> float:
    """One sample by the single calls: the a-priori prediction, then learned (or tracked with W held)."""
    y = law.predict(x)
    if learn:
        law.learn(x, d)
    else:
        law.track(x, d)
    return y


def test_prediction_uses_the_weights_before_the_update():
    law = AdaptiveLaw(AdaptiveLawParams(filter_time_s=0.0), 2, state=AdaptiveLawState.zeros(2, [1.0, 2.0]))
    x = np.array([3.0, 4.0])
    assert law.predict(x) == 11.0
    law.learn(x, 100.0)
    assert not np.array_equal(law.weights, [1.0, 2.0])
    assert law.predict(np.array([1.0, 0.0])) == law.weights[0]


# --- gating --------------------------------------------------------------------------------------


@settings(max_examples=30)
@given(st.integers(0, 2**16), st.lists(st.booleans(), min_size=200, max_size=200))
def test_gating_freezes_w_only(seed, mask):
    x, d, _ = _problem(seed, 200, 4, noise=0.3)
    p = AdaptiveLawParams(filter_time_s=3.0, memory_time_s=50.0, sigma=0.01)
    start = AdaptiveLawState.zeros(4, np.random.default_rng(seed).normal(size=4))
    always, gated, frozen = (AdaptiveLaw(p, 4, state=start) for _ in range(3))
    always.run(x, d, True)
    gated.run(x, d, np.array(mask))
    y_frozen = frozen.run(x, d, False)
    for law in (gated, frozen):
        for name in ("xf", "h", "i"):
            assert getattr(law.get_state(), name).tobytes() == getattr(always.get_state(), name).tobytes()
        assert law.get_state().df == always.get_state().df
    assert frozen.weights.tobytes() == start.w.tobytes()
    # The prediction is W . x summed left to right (numerics.dot), equal to BLAS to rounding.
    assert y_frozen.tobytes() == np.array([dot(row, start.w) for row in x]).tobytes()
    np.testing.assert_allclose(y_frozen, x @ start.w, rtol=1e-13, atol=1e-13)


def test_unfreezing_is_seamless():
    """After a frozen stretch, W picks up the fit over the window that kept running during the freeze."""
    x, d, w_true = _problem(6, 2000, 3)
    law = AdaptiveLaw(AdaptiveLawParams(filter_time_s=1.0, memory_time_s=200.0), 3)
    law.run(x[:1500], d[:1500], False)
    assert not law.weights.any()
    law.run(x[1500:], d[1500:], True)
    np.testing.assert_allclose(law.weights, w_true, atol=1e-9)


# --- step, run, state ----------------------------------------------------------------------------


@settings(max_examples=40)
@pytest.mark.determinism
@given(
    st.integers(0, 2**16),
    st.lists(st.integers(0, 120), max_size=6),
    st.booleans(),
    st.floats(0.0, 1.0),
)
def test_run_equals_predict_then_learn_in_any_chunks(seed, cuts, fixed, nan_fraction):
    rng = np.random.default_rng(seed)
    x, d, _ = _problem(seed, 120, 5, noise=0.2)
    x[rng.random(120) < nan_fraction * 0.2, rng.integers(0, 5)] = np.nan
    d[rng.random(120) < nan_fraction * 0.2] = np.inf
    mask = rng.random(120) < 0.7
    p = AdaptiveLawParams(filter_time_s=2.0, memory_time_s=30.0, sigma=0.05, fixed_gain=0.01 if fixed else None)
    whole = AdaptiveLaw(p, 5).run(x, d, mask)
    one = AdaptiveLaw(p, 5)
    stepped = np.array([_predict_then_learn(one, x[k], d[k], mask[k]) for k in range(120)])
    chunked = AdaptiveLaw(p, 5)
    b = [0, *sorted(cuts), 120]
    parts = np.concatenate([chunked.run(x[i:j], d[i:j], mask[i:j]) for i, j in itertools.pairwise(b)])
    assert stepped.tobytes() == whole.tobytes() == parts.tobytes()
    assert chunked.get_state().to_dict() == one.get_state().to_dict()


def test_state_round_trip_through_yaml_is_exact():
    x, d, _ = _problem(7, 400, 6, noise=0.3)
    p = AdaptiveLawParams(filter_time_s=5.0, memory_time_s=60.0)
    law = AdaptiveLaw(p, 6)
    law.run(x[:200], d[:200])
    doc = yaml.safe_load(yaml.safe_dump({"params": p.to_dict(), "state": law.get_state().to_dict()}))
    loaded = AdaptiveLaw(AdaptiveLawParams.from_dict(doc["params"]), 6, state=AdaptiveLawState.from_dict(doc["state"]))
    assert loaded.params == p
    assert loaded.run(x[200:], d[200:]).tobytes() == law.run(x[200:], d[200:]).tobytes()
    assert loaded.weights.tobytes() == law.weights.tobytes()


def test_state_is_copied_in_and_out():
    start = AdaptiveLawState.zeros(3)
    law = AdaptiveLaw(AdaptiveLawParams(), 3, state=start)
    law.learn(np.ones(3), 1.0)
    assert not start.h.any() and not start.xf.any()  # the caller's state object is untouched
    w = law.weights
    w[:] = 99.0
    assert not (law.weights == 99.0).any()


@pytest.mark.parametrize("bad", [{"xf": [1.0]}, {"h": [[1.0]]}, {"w": [math.nan, 0.0]}])
def test_bad_state_is_rejected(bad):
    d = {**AdaptiveLawState.zeros(2).to_dict(), **bad}
    with pytest.raises(ValueError):
        AdaptiveLawState.from_dict(d)
    with pytest.raises(ValueError):
        AdaptiveLawState.from_dict({**AdaptiveLawState.zeros(2).to_dict(), "extra": 1})


@pytest.mark.parametrize(
    "kwargs",
    [
        {"kappa": 2.0},
        {"kappa": 0.0},
        {"memory_time_s": 0.0},
        {"filter_time_s": -1.0},
        {"delta": 0.0},
        {"sigma": -1.0},
        {"fixed_gain": 0.0},
        {"fixed_gain": math.inf},
        {"precondition": 1},
        {"precondition": True, "fixed_gain": 1.0},
    ],
)
def test_bad_params_are_rejected(kwargs):
    with pytest.raises(ValueError):
        AdaptiveLawParams(**kwargs)


# --- non-finite values ---------------------------------------------------------------------------


@pytest.mark.parametrize("which", ["x_nan", "x_inf", "d_nan", "d_inf"])
def test_non_finite_sample_is_skipped_entirely(which):
    x, d, _ = _problem(8, 60, 4, noise=0.1)
    law = AdaptiveLaw(AdaptiveLawParams(filter_time_s=2.0, memory_time_s=30.0), 4)
    law.run(x[:50], d[:50])
    before = law.get_state().to_dict()
    xi, di = x[50].copy(), float(d[50])
    if which.startswith("x"):
        xi[2] = np.nan if which == "x_nan" else -np.inf
    else:
        di = np.nan if which == "d_nan" else np.inf
    y = law.predict(xi)
    law.learn(xi, di)
    assert law.get_state().to_dict() == before
    if which.startswith("x"):
        assert not math.isfinite(y)
    else:
        assert y == law.predict(x[50])  # the prediction is still given when only the target is missing
    clean = AdaptiveLaw(law.params, 4, state=AdaptiveLawState.from_dict(before))
    assert law.run(x[51:], d[51:]).tobytes() == clean.run(x[51:], d[51:]).tobytes()


# --- ridge ---------------------------------------------------------------------------------------


def _ridge_reference(x, y, alpha, sw=None):
    """Independent: lstsq on [X 1] with a penalty block [sqrt(alpha) I, 0] (the intercept column unpenalized)."""
    t, n = x.shape
    sw = np.ones(t) if sw is None else sw
    r = np.sqrt(sw)
    a = np.vstack(
        [np.column_stack([x, np.ones(t)]) * r[:, None], np.column_stack([math.sqrt(alpha) * np.eye(n), np.zeros(n)])]
    )
    sol = np.linalg.lstsq(a, np.concatenate([y * r, np.zeros(n)]), rcond=None)[0]
    return sol[:n], sol[n]


@settings(max_examples=60)
@given(st.integers(0, 2**16), st.floats(0.0, 1e3), st.integers(1, 8), st.booleans())
def test_ridge_matches_the_augmented_least_squares_problem(seed, alpha, n, weighted):
    rng = np.random.default_rng(seed)
    x = rng.normal(3.0, 2.0, (50, n))
    y = x @ rng.normal(size=n) + 7.0 + rng.normal(size=50)
    sw = rng.uniform(0.1, 3.0, 50) if weighted else None
    w, b = ridge_fit(x, y, alpha, sample_weight=sw)
    w_ref, b_ref = _ridge_reference(x, y, alpha, sw)
    np.testing.assert_allclose(w, w_ref, rtol=1e-8, atol=1e-10)
    assert b == pytest.approx(b_ref, rel=1e-8, abs=1e-9)


@settings(max_examples=60)
@given(st.integers(0, 2**16), st.floats(0.0, 1e4), st.floats(-1e4, 1e4))
def test_ridge_intercept_is_not_penalized(seed, alpha, shift):
    rng = np.random.default_rng(seed)
    x = rng.normal(0.0, 1.0, (40, 3)) + rng.normal(0, 5, 3)
    y = x @ np.array([1.0, -2.0, 0.5]) + rng.normal(size=40)
    w, b = ridge_fit(x, y, alpha)
    w2, b2 = ridge_fit(x, y + shift, alpha)
    np.testing.assert_allclose(w2, w, rtol=1e-9, atol=1e-9 * (1 + abs(shift)))
    assert b2 == pytest.approx(b + shift, rel=1e-9, abs=1e-9 * (1 + abs(shift)))


def test_ridge_huge_alpha_gives_the_mean_not_zero():
    rng = np.random.default_rng(9)
    x, y = rng.normal(size=(100, 2)), 42.0 + rng.normal(size=100)
    w, b = ridge_fit(x, y, 1e12)
    assert np.abs(w).max() < 1e-9 and b == pytest.approx(y.mean())


def test_ridge_alpha_zero_is_ordinary_least_squares():
    x, y, _ = _problem(10, 80, 4, noise=0.3)
    y = y + 2.5
    w, b = ridge_fit(x, y, 0.0)
    sol = np.linalg.lstsq(np.column_stack([x, np.ones(80)]), y, rcond=None)[0]
    np.testing.assert_allclose(np.r_[w, b], sol, rtol=1e-10, atol=1e-12)
    w_small, b_small = ridge_fit(x, y, 1e-10)
    np.testing.assert_allclose(np.r_[w_small, b_small], sol, rtol=1e-8, atol=1e-10)
    w0, b0 = ridge_fit(x, y, 0.0, fit_intercept=False)
    np.testing.assert_allclose(w0, np.linalg.lstsq(x, y, rcond=None)[0], rtol=1e-10)
    assert b0 == 0.0


def test_ridge_weights_of_zero_drop_rows_and_integer_weights_repeat_them():
    x, y, _ = _problem(11, 60, 3, noise=0.5)
    sw = np.ones(60)
    sw[::3] = 0.0
    np.testing.assert_allclose(
        ridge_fit(x, y, 2.0, sample_weight=sw)[0], ridge_fit(x[sw > 0], y[sw > 0], 2.0)[0], rtol=1e-10
    )
    counts = np.random.default_rng(0).integers(1, 4, 60)
    w_rep, b_rep = ridge_fit(np.repeat(x, counts, axis=0), np.repeat(y, counts), 2.0)
    w_w, b_w = ridge_fit(x, y, 2.0, sample_weight=counts.astype(float))
    np.testing.assert_allclose(w_w, w_rep, rtol=1e-10)
    assert b_w == pytest.approx(b_rep, rel=1e-10)


def test_ridge_skips_non_finite_rows():
    x, y, _ = _problem(12, 50, 3, noise=0.5)
    x2, y2 = x.copy(), y.copy()
    x2[3, 1], y2[7], x2[9, 0] = np.nan, np.inf, -np.inf
    keep = np.ones(50, bool)
    keep[[3, 7, 9]] = False
    w, b = ridge_fit(x2, y2, 1.0)
    w_ref, b_ref = ridge_fit(x[keep], y[keep], 1.0)
    np.testing.assert_allclose(w, w_ref, rtol=1e-12)
    assert b == pytest.approx(b_ref, rel=1e-12)
    with pytest.raises(ValueError, match="no row"):
        ridge_fit(np.full((3, 2), np.nan), np.ones(3), 1.0)
    with pytest.raises(ValueError):
        ridge_fit(x, y, -1.0)
    with pytest.raises(ValueError):
        ridge_fit(x, y, 1.0, sample_weight=-np.ones(50))


def test_ridge_is_sound_on_ill_conditioned_columns():
    """No normal equations: nearly collinear columns at alpha = 0 still give the least-squares fit."""
    rng = np.random.default_rng(13)
    s = rng.normal(size=500)
    x = np.column_stack([s, s + 1e-7 * rng.normal(size=500), rng.normal(size=500)])
    y = x @ np.array([1.0, 1.0, 2.0]) + 1e-3 * rng.normal(size=500)
    w, b = ridge_fit(x, y, 0.0)
    resid = y - x @ w - b
    ref = np.linalg.lstsq(np.column_stack([x, np.ones(500)]), y, rcond=None)[0]
    assert np.sum(resid**2) <= np.sum((y - np.column_stack([x, np.ones(500)]) @ ref) ** 2) * (1 + 1e-6)


# --- standardizer --------------------------------------------------------------------------------


def test_standardizer_fit_apply_and_round_trip():
    rng = np.random.default_rng(14)
    x = rng.normal([1.0, -5.0, 100.0], [0.1, 2.0, 30.0], (500, 3))
    x = np.column_stack([x, np.full(500, 7.0)])  # a constant column: centred only
    x[10, 1] = np.nan
    std = Standardizer.fit(x)
    z = std.transform(x)
    np.testing.assert_allclose(np.nanmean(z, axis=0), 0.0, atol=1e-12)
    np.testing.assert_allclose(np.nanstd(z, axis=0)[:3], 1.0, rtol=1e-12)
    assert std.scale[3] == 1.0 and not z[:, 3].any()
    np.testing.assert_allclose(std.inverse_transform(z), x, rtol=1e-12)
    loaded = Standardizer.from_dict(yaml.safe_load(yaml.safe_dump(std.to_dict())))
    assert loaded.mean.tobytes() == std.mean.tobytes() and loaded.scale.tobytes() == std.scale.tobytes()
    assert loaded.transform(x[5]).tobytes() == z[5].tobytes()
    with pytest.raises(ValueError):
        Standardizer(np.zeros(2), np.array([1.0, 0.0]))
    with pytest.raises(ValueError):
        Standardizer.fit(np.full((4, 1), np.nan))
