"""The wavelet echo-state reservoir (stage 2): invariants, determinism, step/run equality, rate independence."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from fog_driver.compensation.reservoir import (
    PSI_MAX,
    ReservoirMatrices,
    ReservoirParams,
    ReservoirState,
    WaveletReservoir,
    log_spaced_leaks,
    psi,
)


def _inputs(seed: int, n: int, m: int, scale: float = 1.0) -> np.ndarray:
    return np.random.default_rng(seed).normal(0.0, scale, (n, m))


@st.composite
def params_strategy(draw, normalized=None, feedback=True):
    n = draw(st.integers(1, 25))
    m = draw(st.integers(1, 9))
    ts = draw(st.sampled_from([0.1, 0.5, 1.0, 2.0]))
    if draw(st.booleans()):
        leak = tuple(draw(st.lists(st.floats(1e-4, 1.0 / ts), min_size=n, max_size=n)))
    else:
        leak = draw(st.floats(1e-4, 1.0 / ts))
    lo = draw(st.floats(0.05, 5.0))
    return ReservoirParams(
        n_neurons=n,
        n_inputs=m,
        sample_time_s=ts,
        leak_per_s=leak,
        normalized_leak=draw(st.booleans()) if normalized is None else normalized,
        spectral_radius=draw(st.floats(0.0, 0.99)),
        input_scale=draw(st.floats(0.0, 10.0)),
        feedback_scale=draw(st.floats(0.0, 2.0)) if feedback else 0.0,
        density=draw(st.floats(0.0, 1.0)),
        dilation_range=(lo, lo * draw(st.floats(1.0, 5.0))),
        translation_range=(-1.0, draw(st.floats(-1.0, 3.0))),
        seed=draw(st.integers(0, 2**32)),
    )


# --- the wavelet and the free invariants ----------------------------------------------------------


@pytest.mark.filterwarnings("ignore:overflow encountered")
def test_psi_maximum_and_slope():
    z = np.linspace(-10, 10, 200_001)
    p = psi(z.copy())
    assert np.abs(p).max() == pytest.approx(PSI_MAX, rel=1e-9)
    assert p[np.argmax(p)] == pytest.approx(math.exp(-0.5)) and z[np.argmax(p)] == pytest.approx(1.0, abs=1e-4)
    assert np.abs(np.diff(p) / np.diff(z)).max() <= 1.0  # max |Psi'| = Psi'(0) = 1
    assert psi(np.array([1e200, -1e200, 1e5]))[0] == 0.0  # the tails underflow to 0, never NaN


@settings(max_examples=60)
@given(params_strategy(), st.floats(1e-3, 1e6), st.integers(0, 2**16))
def test_state_stays_inside_the_free_bound(params, scale, seed):
    """paper form |x_i| <= e^-1/2 / leak_i, normalized |x_i| <= e^-1/2, for inputs of any size."""
    res = WaveletReservoir(params)
    u = _inputs(seed, 300, params.n_inputs, scale)
    y = np.random.default_rng(seed + 1).normal(0, scale, 300)
    x = res.run(u, y)
    bound = PSI_MAX if params.normalized_leak else PSI_MAX / params.leaks()
    assert np.all(np.abs(x) <= bound * (1 + 1e-12))
    np.testing.assert_array_equal(res.bounds, np.broadcast_to(bound, (params.n_neurons,)))


def test_paper_form_states_grow_with_the_time_constant_normalized_do_not():
    leaks = log_spaced_leaks(20, 30.0, 7200.0)
    u = np.tile(_inputs(0, 1, 8), (30_000, 1))  # a constant input: every neuron settles to Psi(v) / leak or Psi(v)
    paper = WaveletReservoir(ReservoirParams(leak_per_s=leaks, spectral_radius=0.0, normalized_leak=False)).run(u)[-1]
    norm = WaveletReservoir(ReservoirParams(leak_per_s=leaks, spectral_radius=0.0, normalized_leak=True)).run(u)[-1]
    np.testing.assert_allclose(paper * np.array(leaks), norm, rtol=1e-3, atol=1e-12)
    assert np.abs(paper).max() > 100 * np.abs(norm).max()


# --- matrices: echo-state condition, determinism, independence --------------------------------------


@settings(max_examples=100)
@given(params_strategy())
def test_echo_state_condition_holds_for_any_seed(params):
    mat = ReservoirMatrices.draw(params)
    gain2 = np.linalg.norm(mat.w, 2) / mat.dilation.min()
    gain_inf = np.abs(mat.w).sum(axis=1).max() / mat.dilation.min()
    assert gain2 < 1 and gain_inf < 1
    # Relative to the target, and below the normal floats relative to the smallest normal one: a subnormal target
    # (2.2e-311 was drawn) has too few bits to be hit relatively (it missed by 10 subnormal steps, 2e-12).
    assert max(gain2, gain_inf) <= params.spectral_radius * (1 + 1e-12) + 1e-12 * np.finfo(float).tiny
    assert mat.echo_state_gain() == pytest.approx(gain2)
    assert mat.dilation.min() >= params.dilation_range[0] and mat.dilation.max() <= params.dilation_range[1]


def test_the_larger_norm_is_set_to_the_target():
    mat = ReservoirMatrices.draw(ReservoirParams(spectral_radius=0.9, seed=3))
    gain = max(np.linalg.norm(mat.w, 2), np.abs(mat.w).sum(axis=1).max()) / mat.dilation.min()
    assert gain == pytest.approx(0.9, rel=1e-12)


def test_same_seed_same_matrices_different_seed_different():
    a, b = ReservoirMatrices.draw(ReservoirParams(seed=7)), ReservoirMatrices.draw(ReservoirParams(seed=7))
    c = ReservoirMatrices.draw(ReservoirParams(seed=8))
    for name in ("w_in", "w", "w_back", "dilation", "translation"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
        if name != "w_back":  # all zeros with the default feedback_scale = 0
            assert not np.array_equal(getattr(a, name), getattr(c, name))


def test_each_matrix_has_its_own_random_stream():
    """Changing how one matrix is drawn never changes another (one child generator per matrix)."""
    base = ReservoirMatrices.draw(ReservoirParams(seed=5))
    more_feedback = ReservoirMatrices.draw(ReservoirParams(seed=5, feedback_scale=0.5))
    denser = ReservoirMatrices.draw(ReservoirParams(seed=5, density=0.9))
    bigger_inputs = ReservoirMatrices.draw(ReservoirParams(seed=5, input_scale=2.0))
    for other in (more_feedback, denser, bigger_inputs):
        np.testing.assert_array_equal(other.dilation, base.dilation)
        np.testing.assert_array_equal(other.translation, base.translation)
    np.testing.assert_array_equal(more_feedback.w, base.w)
    np.testing.assert_array_equal(more_feedback.w_in, base.w_in)
    np.testing.assert_array_equal(denser.w_in, base.w_in)
    np.testing.assert_array_equal(bigger_inputs.w, base.w)
    np.testing.assert_array_equal(bigger_inputs.w_in, 2.0 * base.w_in)
    assert np.count_nonzero(denser.w) > 2 * np.count_nonzero(base.w)
    assert np.count_nonzero(more_feedback.w_back) == 20


def test_matrices_are_read_only():
    mat = ReservoirMatrices.draw(ReservoirParams())
    with pytest.raises(ValueError):
        mat.w[0, 0] = 1.0


# --- step, run, chunks, closed loop ----------------------------------------------------------------


@pytest.mark.determinism
@settings(max_examples=40)
@given(params_strategy(), st.lists(st.integers(0, 60), max_size=6), st.integers(0, 2**16))
def test_run_equals_repeated_step_in_any_chunks(params, cuts, seed):
    u = _inputs(seed, 60, params.n_inputs, 3.0)
    y = np.random.default_rng(seed).normal(0, 1, 60)
    whole = WaveletReservoir(params).run(u, y)
    one = WaveletReservoir(params)
    stepped = np.array([one.step(u[k], y[k]) for k in range(60)])
    chunked = WaveletReservoir(params)
    bounds = [0, *sorted(cuts), 60]
    parts = [chunked.run(u[a:b], y[a:b]) for a, b in itertools.pairwise(bounds)]
    assert stepped.tobytes() == whole.tobytes()
    assert np.concatenate(parts).tobytes() == whole.tobytes()
    assert chunked.get_state().x.tobytes() == one.get_state().x.tobytes() == whole[-1].tobytes()


@settings(max_examples=25)
@given(params_strategy(), st.integers(0, 80), st.integers(0, 2**16))
def test_closed_loop_equals_the_hand_written_loop_and_resumes_from_state(params, cut, seed):
    u = _inputs(seed, 80, params.n_inputs)
    w_out = np.random.default_rng(seed).normal(0, 0.3, params.n_neurons + params.n_inputs)

    def readout(x, row):
        return float(w_out @ np.concatenate([x, row]))

    x_all, y_all = WaveletReservoir(params).run_closed_loop(u, readout)
    by_hand, ys = WaveletReservoir(params), []
    for row in u:
        x = by_hand.step(row)
        ys.append(readout(x, row))
        by_hand.set_feedback(ys[-1])
    assert np.array(ys).tobytes() == y_all.tobytes()
    first = WaveletReservoir(params)
    x1, y1 = first.run_closed_loop(u[:cut], readout)
    resumed = WaveletReservoir(params, state=ReservoirState.from_dict(first.get_state().to_dict()))
    x2, y2 = resumed.run_closed_loop(u[cut:], readout)
    assert np.concatenate([x1, x2]).tobytes() == x_all.tobytes()
    assert np.concatenate([y1, y2]).tobytes() == y_all.tobytes()


def test_run_without_feedback_values_uses_the_stored_one():
    params = ReservoirParams(feedback_scale=0.5)
    u = _inputs(0, 50, 8)
    a = WaveletReservoir(params)
    a.set_feedback(0.7)
    b = WaveletReservoir(params)
    assert a.run(u).tobytes() == b.run(u, np.full(50, 0.7)).tobytes()


def test_zero_feedback_scale_makes_y_prev_irrelevant():
    params = ReservoirParams(feedback_scale=0.0, leak_per_s=log_spaced_leaks(20), normalized_leak=True)
    u = _inputs(1, 400, 8)
    base = WaveletReservoir(params).run(u, np.zeros(400))
    for y in (np.random.default_rng(2).normal(0, 1e6, 400), np.full(400, np.nan), np.full(400, np.inf)):
        assert WaveletReservoir(params).run(u, y).tobytes() == base.tobytes()
    with_feedback = WaveletReservoir(
        ReservoirParams(feedback_scale=0.5, leak_per_s=log_spaced_leaks(20), normalized_leak=True)
    )
    assert not np.array_equal(with_feedback.run(u, np.zeros(400)), with_feedback.run(u, np.ones(400)))


@pytest.mark.filterwarnings("ignore:overflow encountered", "ignore:invalid value encountered")
def test_non_finite_input_holds_the_state():
    params = ReservoirParams(feedback_scale=0.5)
    res = WaveletReservoir(params)
    u = _inputs(3, 20, 8)
    res.run(u[:10], np.zeros(10))
    before = res.get_state()
    for bad_u, bad_y in (
        (np.full(8, np.nan), 0.0),
        (np.r_[np.inf, np.zeros(7)], 0.0),
        (u[10], np.nan),
        (np.full(8, 1e308), 0.0),
    ):
        x = res.step(bad_u, bad_y)
        assert x.tobytes() == before.x.tobytes() and res.get_state().y == before.y
    clean = WaveletReservoir(params, state=before)
    assert res.run(u[10:], np.zeros(10)).tobytes() == clean.run(u[10:], np.zeros(10)).tobytes()


@pytest.mark.determinism
@pytest.mark.filterwarnings("ignore:overflow encountered", "ignore:invalid value encountered")
@pytest.mark.parametrize("normalized", [True, False])
def test_feedforward_run_equals_steps_with_bad_rows_among_good_ones(normalized):
    """Without recurrence and feedback (the ring form) ``run`` computes every row's wavelet input at once:
    the same bits as stepping, bad rows skipped the same way, the same state (x and y) afterwards."""
    params = ReservoirParams(
        spectral_radius=0.0,
        feedback_scale=0.0,
        leak_per_s=log_spaced_leaks(6, 60, 7200),
        n_neurons=6,
        normalized_leak=normalized,
        seed=4,
    )
    assert not WaveletReservoir(params)._recurrent
    u = _inputs(5, 300, 8, 2.0)
    u[[3, 150]] = np.nan
    u[77, 2], u[200, 5], u[201] = np.inf, -np.inf, 1e300
    y = np.random.default_rng(6).normal(0, 1, 300)
    y[299] = np.nan  # irrelevant without feedback, but stored as the last y used
    for y_prev in (y, None):
        whole, one = WaveletReservoir(params), WaveletReservoir(params)
        ran = whole.run(u, y_prev)
        stepped = np.array([one.step(u[k], None if y_prev is None else y_prev[k]) for k in range(300)])
        assert ran.tobytes() == stepped.tobytes()
        assert whole.get_state().x.tobytes() == one.get_state().x.tobytes()
        assert str(whole.get_state().y) == str(one.get_state().y)
        assert np.isfinite(ran).all() and ran[3].tobytes() == ran[2].tobytes()  # a bad row holds the state


def test_step_returns_a_copy():
    res = WaveletReservoir(ReservoirParams())
    x = res.step(np.ones(8), 0.0)
    x[:] = 1e9
    assert np.abs(res.x).max() < 1.0


# --- model file and state -----------------------------------------------------------------------


def test_model_round_trip_through_yaml_is_exact():
    params = ReservoirParams(leak_per_s=log_spaced_leaks(20), normalized_leak=True, feedback_scale=0.2, seed=11)
    res = WaveletReservoir(params)
    u, y = _inputs(4, 500, 8), np.random.default_rng(4).normal(0, 1, 500)
    res.run(u[:100], y[:100])
    text = yaml.safe_dump({"reservoir": res.to_dict(), "state": res.get_state().to_dict()})
    doc = yaml.safe_load(text)
    loaded = WaveletReservoir.from_dict(doc["reservoir"], ReservoirState.from_dict(doc["state"]))
    assert loaded.params == params
    for name in ("w_in", "w", "w_back", "dilation", "translation"):
        assert getattr(loaded.matrices, name).tobytes() == getattr(res.matrices, name).tobytes()
    assert loaded.run(u[100:], y[100:]).tobytes() == res.run(u[100:], y[100:]).tobytes()


def test_to_dict_holds_plain_python_values_only():
    d = WaveletReservoir(ReservoirParams(leak_per_s=log_spaced_leaks(20))).to_dict()

    def walk(v):
        if isinstance(v, dict):
            return all(isinstance(k, str) and walk(x) for k, x in v.items())
        if isinstance(v, list):
            return all(walk(x) for x in v)
        return type(v) in (int, float, bool, str)

    assert walk(d)
    assert type(d["matrices"]["w"][0][0]) is float


def test_loaded_matrices_are_never_redrawn():
    res = WaveletReservoir(ReservoirParams(seed=1))
    d = res.to_dict()
    d["params"]["seed"] = 2  # the stored matrices win over the seed
    loaded = WaveletReservoir.from_dict(d)
    assert loaded.matrices.w.tobytes() == res.matrices.w.tobytes()


def test_reset_and_state():
    res = WaveletReservoir(ReservoirParams(feedback_scale=0.3))
    first = res.run(_inputs(0, 30, 8), np.ones(30))
    res.reset()
    assert not res.get_state().x.any() and res.get_state().y == 0.0
    assert res.run(_inputs(0, 30, 8), np.ones(30)).tobytes() == first.tobytes()


@pytest.mark.parametrize(
    "kwargs",
    [
        {"leak_per_s": 2.0},  # Ts leak > 1
        {"leak_per_s": 0.0},
        {"leak_per_s": (0.1, 0.2)},  # not one per neuron
        {"spectral_radius": 1.0},
        {"density": 1.5},
        {"dilation_range": (0.0, 1.0)},
        {"dilation_range": (2.0, 1.0)},
        {"n_neurons": 0},
        {"sample_time_s": -1.0},
        {"feedback_scale": -0.1},
        {"normalized_leak": "yes"},
    ],
)
def test_bad_params_are_rejected(kwargs):
    with pytest.raises(ValueError):
        ReservoirParams(**kwargs)


def test_params_from_dict_rejects_unknown_keys_and_matrices_must_match_params():
    with pytest.raises(ValueError, match="unknown"):
        ReservoirParams.from_dict({"neurons": 3})
    mat = ReservoirMatrices.draw(ReservoirParams(n_neurons=5))
    with pytest.raises(ValueError, match="neurons"):
        WaveletReservoir(ReservoirParams(n_neurons=6), mat)


def test_leak_tuple_from_a_list_and_log_spacing():
    leaks = log_spaced_leaks(20, 30.0, 7200.0)
    assert leaks[0] == pytest.approx(1 / 30) and leaks[-1] == pytest.approx(1 / 7200)
    assert ReservoirParams(leak_per_s=list(leaks)).leak_per_s == leaks
    assert ReservoirParams.from_dict(ReservoirParams(leak_per_s=leaks).to_dict()) == ReservoirParams(leak_per_s=leaks)


# --- rate independence and fading memory ----------------------------------------------------------


def _continuous_run(params: ReservoirParams, ts: float, duration_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Sample the same smooth input and feedback signals at ``ts``; states at t = ts, 2 ts, ..."""
    p = ReservoirParams(**{**params.__dict__, "sample_time_s": ts})
    n = round(duration_s / ts)
    t = ts * np.arange(1, n + 1)
    periods = np.linspace(150.0, 1500.0, p.n_inputs)
    u = 1.5 * np.sin(2 * np.pi * t[:, None] / periods + np.arange(p.n_inputs))
    y_prev = 0.5 * np.cos(2 * np.pi * (t - ts) / 700.0)
    return t, WaveletReservoir(p).run(u, y_prev)


@pytest.mark.parametrize(
    "params",
    [
        ReservoirParams(leak_per_s=log_spaced_leaks(20, 30.0, 900.0), feedback_scale=0.3, seed=2),
        ReservoirParams(leak_per_s=1 / 120, spectral_radius=0.99, feedback_scale=0.3, seed=2),
        # the paper form is rate independent when it is an echo-state network (contraction_bound < 1)
        ReservoirParams(
            leak_per_s=log_spaced_leaks(20, 30.0, 900.0),
            normalized_leak=False,
            spectral_radius=1e-3,
            feedback_scale=0.3,
            seed=2,
        ),
    ],
)
def test_the_same_signal_at_1_s_and_0_1_s_gives_the_same_states(params):
    """Explicit Euler is first order: the global error is C Ts.  Against a 0.1 s reference (error
    0.1 C) the 1 s run is off by ~0.9 C and a 0.5 s run by ~0.4 C: the ratio must be ~2.25, which
    shows the difference IS the discretization error (a model that ignored Ts would be off by O(1),
    not by an error that halves with the step).  Size: Euler's local error is Ts^2/2 |x''| with
    |x''| ~ leak^2 |x| for a neuron of leak ``leak``, and it is forgotten at the rate ``leak``, so the
    global error is ~ Ts leak / 2 of the state's range: 1.7 % for the fastest neuron here (30 s) at
    Ts = 1 s (measured 2.6 %, ratio 2.26): checked against 5 %."""
    assert WaveletReservoir(params).contraction_bound < 1
    duration = 3000.0
    _, ref = _continuous_run(params, 0.1, duration)
    _, coarse = _continuous_run(params, 1.0, duration)
    _, mid = _continuous_run(params, 0.5, duration)
    ref_at_1 = ref[9::10]  # t = 1, 2, 3, ... s
    ref_at_05 = ref[4::5]
    scale = np.abs(ref).max(axis=0)
    err_1 = (np.abs(coarse - ref_at_1) / scale).max()
    err_05 = (np.abs(mid - ref_at_05) / scale).max()
    assert err_1 < 0.05
    assert 1.8 < err_1 / err_05 < 2.8
    # without Ts in the update (Ts taken as 1 at 10 Hz) the states would be far apart: not rate independent
    wrong = WaveletReservoir(params).run(
        1.5 * np.sin(2 * np.pi * np.arange(1, 30001)[:, None] * 0.1 / np.linspace(150.0, 1500.0, 8) + np.arange(8)),
        0.5 * np.cos(2 * np.pi * np.arange(30000) * 0.1 / 700.0),
    )[9::10]
    assert (np.abs(wrong - ref_at_1) / scale).max() > 10 * err_1


@settings(max_examples=40)
@given(params_strategy(normalized=True), st.integers(0, 2**16))
def test_normalized_form_contracts_for_any_leaks(params, seed):
    """Two initial states under the same inputs: ||xa(n) - xb(n)||_inf <= c^n ||xa(0) - xb(0)||_inf, c < 1."""
    rng = np.random.default_rng(seed)
    a = WaveletReservoir(params, state=ReservoirState(rng.uniform(-PSI_MAX, PSI_MAX, params.n_neurons)))
    b = WaveletReservoir(params, state=ReservoirState(rng.uniform(-PSI_MAX, PSI_MAX, params.n_neurons)))
    c = a.contraction_bound
    assert c < 1
    d0 = np.abs(a.get_state().x - b.get_state().x).max()
    u, y = _inputs(seed, 200, params.n_inputs, 2.0), rng.normal(0, 1, 200)
    diff = np.abs(a.run(u, y) - b.run(u, y)).max(axis=1)
    assert np.all(diff <= c ** np.arange(1, 201) * d0 * (1 + 1e-9) + 1e-15)


def test_paper_form_bound_needs_leaks_above_the_recurrent_gain():
    fast = WaveletReservoir(ReservoirParams(leak_per_s=1.0, spectral_radius=0.9, normalized_leak=False))
    slow = WaveletReservoir(ReservoirParams(leak_per_s=1 / 300, spectral_radius=0.9, normalized_leak=False))
    normalized = WaveletReservoir(ReservoirParams(leak_per_s=1 / 300, spectral_radius=0.9, normalized_leak=True))
    assert fast.contraction_bound <= 0.9 + 1e-12
    assert slow.contraction_bound > 1  # the guarantee is void (the module docstring says why)
    assert normalized.contraction_bound < 1


@pytest.mark.parametrize(
    "params",
    [
        ReservoirParams(leak_per_s=log_spaced_leaks(20, 30.0, 1800.0), normalized_leak=True, feedback_scale=0.3),
        ReservoirParams(leak_per_s=1 / 60, normalized_leak=True),
        ReservoirParams(leak_per_s=1.0, feedback_scale=0.3, normalized_leak=False),
        ReservoirParams(leak_per_s=log_spaced_leaks(20, 30.0, 900.0), spectral_radius=1e-3, normalized_leak=False),
    ],
)
def test_echo_state_property_different_initial_states_converge(params):
    rng = np.random.default_rng(0)
    bound = WaveletReservoir(params).bounds
    a = WaveletReservoir(params, state=ReservoirState(rng.uniform(-1, 1, 20) * bound))
    b = WaveletReservoir(params, state=ReservoirState(rng.uniform(-1, 1, 20) * bound))
    t = np.arange(20_000)
    u = np.sin(2 * np.pi * t[:, None] / np.linspace(300, 3000, 8)) + 0.1 * rng.normal(size=(20_000, 8))
    y = 0.2 * np.sin(2 * np.pi * t / 1000.0)
    diff = np.abs(a.run(u, y) - b.run(u, y)).max(axis=1)
    assert diff[-1] < 1e-6 * diff[0]
    assert diff[-1] <= diff[0] * a.contraction_bound**20_000 * (1 + 1e-9) + 1e-15


def test_paper_form_without_the_echo_state_property_depends_on_rate_and_initial_state():
    """Not a requirement but a warning, pinned: the paper's form with a slow leak and the usual
    recurrent gain (contraction_bound > 1) is chaotic: the same signal at 1 s and 0.1 s, or from two
    initial states, gives O(1) different states (relative to each neuron's range)."""
    params = ReservoirParams(
        leak_per_s=log_spaced_leaks(20, 30.0, 900.0),
        normalized_leak=False,
        spectral_radius=0.9,
        feedback_scale=0.3,
        seed=2,
    )
    assert WaveletReservoir(params).contraction_bound > 1
    _, ref = _continuous_run(params, 0.1, 3000.0)
    _, coarse = _continuous_run(params, 1.0, 3000.0)
    assert (np.abs(coarse - ref[9::10]) / np.abs(ref).max(axis=0)).max() > 0.5


# --- the linear cascade (the ring form's coil of several stages) ------------------------------------


def _cascade(order: int, stage_s: float, ts: float = 0.1, n_inputs: int = 1) -> WaveletReservoir:
    """Neuron 0 driven by the wavelet, neurons 1..order-1 each integrating the one before."""
    chain = tuple([-1] + list(range(order - 1)))
    params = ReservoirParams(
        n_neurons=order,
        n_inputs=n_inputs,
        sample_time_s=ts,
        leak_per_s=1.0 / stage_s,
        spectral_radius=0.0,
        chain_from=chain if order > 1 else (),
        translation_range=(0.0, 0.0),
        dilation_range=(1.0, 1.0),
    )
    w_in = np.zeros((order, n_inputs))
    w_in[0, 0] = 1.0
    zeros = np.zeros(order)
    return WaveletReservoir(params, ReservoirMatrices(w_in, np.zeros((order, order)), zeros, np.ones(order), zeros))


@pytest.mark.parametrize("order", [1, 2, 3])
def test_a_cascade_steps_like_m_first_order_lags_in_series(order):
    """The step response of m equal stages of time constant T is the Erlang one,
    ``1 - exp(-t/T) sum_{k<m} (t/T)^k / k!`` (closed form of the continuous cascade; Euler at Ts = T/1000
    and the one-sample delay per stage stay within 2e-3 of it)."""
    stage_s, ts = 100.0, 0.1
    res = _cascade(order, stage_s, ts)
    level = float(psi(np.array([0.3]))[0])
    x = res.run(np.full((6000, 1), 0.3))  # 600 s
    t = ts * np.arange(1, 6001) / stage_s
    erlang = 1.0 - np.exp(-t) * sum(t**k / math.factorial(k) for k in range(order))
    assert np.abs(x[:, order - 1] / level - erlang).max() < 2e-3
    assert x[-1, order - 1] / level > 0.9 * erlang[-1]


@pytest.mark.determinism
@pytest.mark.parametrize("cuts", [(1,), (7, 300), (2999,)])
def test_a_cascade_runs_as_it_steps_in_any_chunks(cuts):
    """A cascade keeps ``run`` on its fast path (no recurrence): the same bits as ``step``, chunks alike."""
    res = _cascade(3, 40.0, 1.0, n_inputs=8)
    assert not res._recurrent and res._chained
    u = _inputs(3, 3000, 8)
    u[100] = np.nan  # a skipped row holds every stage
    one = _cascade(3, 40.0, 1.0, 8)
    stepped = np.array([one.step(row) for row in u])
    pieces, start = [], 0
    for cut in (*cuts, len(u)):
        pieces.append(res.run(u[start:cut]))
        start = cut
    assert np.vstack(pieces).tobytes() == stepped.tobytes()
    assert res.get_state().x.tobytes() == one.get_state().x.tobytes()
    assert stepped[100].tobytes() == stepped[99].tobytes()


@pytest.mark.determinism
@pytest.mark.parametrize("chain", [(), (2, -1, 1, -1, 3), (-1, 0, -1, 2, 3)])
def test_a_clean_ring_form_run_takes_the_column_path_and_gives_the_step_bits(chain, monkeypatch):
    """Finite rows run the leak neuron by neuron (``_leak_columns``): sources stepped before the neurons that
    integrate them, whatever their index, and unchained neurons among chained ones (with their ``+ 0 x``):
    the same bits as stepping, from any state, in any chunks."""
    params = ReservoirParams(
        n_neurons=5,
        spectral_radius=0.0,
        feedback_scale=0.0,
        leak_per_s=log_spaced_leaks(5, 30, 3000),
        chain_from=chain,
        seed=11,
    )
    taken = []
    real = WaveletReservoir._leak_columns
    monkeypatch.setattr(
        WaveletReservoir, "_leak_columns", lambda self, d, o: taken.append(real(self, d, o)) or taken[-1]
    )
    u = _inputs(7, 2000, 8, 2.0)
    start = ReservoirState(np.random.default_rng(8).normal(0.0, 0.3, 5), 0.0)
    res, one = WaveletReservoir(params, state=start), WaveletReservoir(params, state=start)
    stepped = np.array([one.step(row) for row in u])
    ran = np.vstack([res.run(u[a:b]) for a, b in ((0, 1), (1, 777), (777, 2000))])
    assert taken == [True, True, True]
    assert ran.tobytes() == stepped.tobytes()
    assert res.get_state().x.tobytes() == one.get_state().x.tobytes()


def test_a_cascade_stays_inside_its_bound_and_forgets_its_start():
    res = _cascade(3, 30.0, 1.0)
    assert res.bounds.tolist() == pytest.approx([PSI_MAX, 2 * PSI_MAX, 3 * PSI_MAX])
    a, b = _cascade(3, 30.0, 1.0), _cascade(3, 30.0, 1.0)
    b.set_state(ReservoirState(np.array([0.6, -1.2, 1.8])))
    u = _inputs(8, 3000, 1, 3.0)
    xa, xb = a.run(u), b.run(u)
    assert (np.abs(xa) <= res.bounds).all() and (np.abs(xb) <= res.bounds + 1e-12).all()
    assert np.abs(xa[-1] - xb[-1]).max() < 1e-9  # triangular with decays < 1: the echo-state property


@pytest.mark.parametrize(
    "chain",
    [(0, -1), (1, 0), (-1, 2), (-1, 0.5), (-1,), (-1, True)],
)
def test_bad_cascades_are_rejected(chain):
    """A stage of itself, a loop, an index out of range, a non-integer, the wrong length."""
    with pytest.raises(ValueError, match="chain_from"):
        ReservoirParams(n_neurons=2, chain_from=chain)


def test_a_cascade_needs_the_normalized_leak_and_round_trips_its_file():
    with pytest.raises(ValueError, match="normalized"):
        ReservoirParams(n_neurons=2, chain_from=(-1, 0), normalized_leak=False)
    res = _cascade(3, 50.0, 1.0)
    d = yaml.safe_load(yaml.safe_dump(res.to_dict()))
    assert d["params"]["chain_from"] == [-1, 0, 1]
    loaded = WaveletReservoir.from_dict(d)
    assert loaded.params == res.params
    u = _inputs(2, 200, 1)
    assert loaded.run(u).tobytes() == res.run(u).tobytes()
    assert "chain_from" not in _cascade(1, 50.0, 1.0).to_dict()["params"]  # no cascade: the file as before
