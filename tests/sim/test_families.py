"""The physics families (fog_driver.sim.families): each term against an independent computation, the draws,
the development population unchanged, and the output independent of how the run is chunked."""

from __future__ import annotations

import dataclasses
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from fog_driver.lab.profiles import load_profile
from fog_driver.sim.capture import TRUTH_COLUMNS, read_provenance, read_truth, truth_rows
from fog_driver.sim.families import FAMILIES, FAMILY_RANGES, FamilyPhysics, FamilyTerm, draw_family
from fog_driver.sim.instrument import InstrumentConfig, Simulator
from fog_driver.sim.population import draw_instrument

ROOT = Path(__file__).resolve().parents[2]


def _nodes(housing, top, bottom, fiber, mount) -> np.ndarray:
    return np.column_stack(
        [np.broadcast_to(np.asarray(v, dtype=float), np.shape(fiber)) for v in (housing, top, bottom, fiber, mount)]
    )


def test_memory_family_on_a_triangle_wave_follows_a_hand_written_play_operator():
    width, bias = 4.0, 0.1
    physics = FamilyPhysics(
        "memory", {"play_width_c": width, "play_bias_dph": bias, "memory_tau_s": 3600.0, "memory_dph_per_c": 0.0}
    )
    up = np.arange(0.0, 10.0, 0.5)
    x = np.concatenate([up, 10.0 - up, up])  # 0 -> 10 -> 0 -> 10
    expected_play = np.concatenate(
        [np.maximum(0.0, up - 2.0), np.minimum(8.0, 10.0 - up + 2.0), np.maximum(2.0, up - 2.0)]
    )
    term = FamilyTerm(physics, 1.0)
    out = term.run(_nodes(0.0, 0.0, 0.0, x, 0.0), np.zeros(len(x)), np.zeros(len(x)))
    np.testing.assert_allclose(out, bias / (width / 2) * (expected_play - x), atol=1e-12)


def test_memory_family_slow_memory_under_a_held_step_decays_exponentially():
    tau = 7200.0
    physics = FamilyPhysics(
        "memory", {"play_width_c": 1e-9, "play_bias_dph": 0.0, "memory_tau_s": tau, "memory_dph_per_c": 0.01}
    )
    fiber = np.r_[0.0, np.full(3000, 5.0)]
    out = FamilyTerm(physics, 1.0).run(_nodes(0.0, 0.0, 0.0, fiber, 0.0), np.zeros(3001), np.zeros(3001))
    k = np.arange(1, 3001)
    np.testing.assert_allclose(out[1:], 0.01 * 5.0 * np.exp(-k / tau), rtol=1e-9)


def _layered(layers: int, tau_d: float, beta: float = 0.0) -> FamilyTerm:
    weights = tuple([1.0 / layers] * layers)
    physics = FamilyPhysics(
        "layered",
        {"diffusion_tau_s": tau_d, "shupe_dph_per_c_per_min": 0.2, "shupe_beta_per_c": beta},
        weights,
    )
    return FamilyTerm(physics, 1.0)


def test_layered_coil_reaches_the_linear_steady_state_between_its_faces():
    term = _layered(10, 600.0)
    layers = [0.0] * 10
    for _ in range(20_000):
        layers = term.diffuse(layers, 3.0, 13.0)
    np.testing.assert_allclose(layers, [3.0 + 10.0 * (i + 1) / 11 for i in range(10)], atol=1e-9)


def test_layered_coil_step_response_matches_the_analytic_series():
    n, tau_d = 16, 1800.0
    term = _layered(n, tau_d)
    x = np.arange(1, n + 1) / (n + 1)
    layers = [0.0] * n
    for step in range(1, 901):  # the outer face steps to 1 degC at t = 0
        layers = term.diffuse(layers, 0.0, 1.0)
        if step in (90, 300, 900):
            t = step / tau_d
            series = x + sum(
                2.0 / (m * math.pi) * (-1) ** m * np.sin(m * math.pi * x) * math.exp(-((m * math.pi) ** 2) * t)
                for m in range(1, 400)
            )
            np.testing.assert_allclose(layers, series, atol=0.01)


def test_layered_coil_term_is_the_weighted_layer_rate_with_a_temperature_dependent_coefficient():
    term = _layered(6, 900.0, beta=0.01)
    n = 200
    bottom = np.full(n, 20.0)
    housing = np.r_[20.0, np.full(n - 1, 30.0)]
    out = term.run(_nodes(housing, 0.0, bottom, np.zeros(n), 0.0), np.zeros(n), np.zeros(n))
    ref = _layered(6, 900.0, beta=0.01)
    t = ref.layer_profile(20.0, 20.0)
    expected = []
    for h in housing.tolist():
        new = ref.diffuse(t, 20.0, h)
        rate = sum((a - b) / 6 for a, b in zip(new, t))
        expected.append(0.2 * (1 + 0.01 * (sum(new) / 6 - 20.0)) * 60.0 * rate)
        t = new
    np.testing.assert_allclose(out, expected, rtol=1e-12, atol=1e-15)
    assert out[1:50].max() > 0.0


def test_stress_family_creep_under_a_held_difference_decays_exponentially():
    tau = 3600.0
    physics = FamilyPhysics(
        "stress",
        {
            "creep_tau_s": tau,
            "stress_dph_per_c": 0.05,
            "radial_quadratic_dph_per_c2": 0.02,
            "warmup_heating_c": 2.0,
            "warmup_tau_s": 900.0,
        },
    )
    n = 5000
    mount = np.r_[0.0, np.full(n - 1, 4.0)]  # mount - housing steps to 4 degC and holds
    boundary = np.full(n, 1.5)  # Tc - Tf = 1.5 degC
    out = FamilyTerm(physics, 1.0).run(_nodes(0.0, 0.0, 0.0, np.zeros(n), mount), np.zeros(n), boundary)
    k = np.arange(n - 1)
    np.testing.assert_allclose(out[1:], 0.05 * 4.0 * np.exp(-k / tau) + 0.02 * 1.5**2, rtol=1e-9)
    heat = FamilyTerm(physics, 1.0).heat_c(np.array([0.0, 900.0, 1e6]))
    np.testing.assert_allclose(heat, [0.0, 2.0 * (1 - math.exp(-1)), 2.0])


def _correlated_series(rate_c_per_s: float, n: int, seed: int) -> tuple[np.ndarray, FamilyPhysics]:
    physics = FamilyPhysics("correlated", {"tau_s": 300.0, "sigma_dph": 0.02, "rate_gain_min_per_c": 3.0})
    term = FamilyTerm(physics, 1.0, np.random.default_rng(seed))
    return term.run(np.zeros((n, 5)), np.full(n, rate_c_per_s), np.zeros(n)), physics


def test_correlated_family_has_the_gauss_markov_variance_and_correlation_time():
    b, p = _correlated_series(0.0, 200_000, 1)
    assert np.var(b) == pytest.approx(p.params["sigma_dph"] ** 2, rel=0.15)
    lag = int(p.params["tau_s"])
    corr = np.corrcoef(b[:-lag], b[lag:])[0, 1]
    assert corr == pytest.approx(math.exp(-1.0), abs=0.05)


def test_correlated_family_drive_grows_with_the_fiber_rate():
    rate = 1.0 / 60.0  # 1 degC/min: variance x (1 + 3 * 1)
    still, p = _correlated_series(0.0, 200_000, 2)
    ramping, _ = _correlated_series(rate, 200_000, 3)
    gain = 1.0 + p.params["rate_gain_min_per_c"] * 60.0 * rate
    assert np.var(ramping) == pytest.approx(gain * p.params["sigma_dph"] ** 2, rel=0.15)
    assert np.var(ramping) / np.var(still) == pytest.approx(gain, rel=0.2)


@pytest.mark.parametrize("family", FAMILIES)
def test_family_draws_are_reproducible_and_within_their_ranges(family):
    for seed in range(40):
        physics = draw_family(family, seed)
        assert physics == draw_family(family, seed)
        for name, value in physics.params.items():
            r = FAMILY_RANGES[family][name]
            assert r.lo <= abs(value) <= r.hi if r.signed else r.lo <= value <= r.hi
        if family == "layered":
            assert 6 <= len(physics.layer_weights) <= 16
            assert sum(abs(w) for w in physics.layer_weights) == pytest.approx(1.0)
    assert draw_family(family, 1) != draw_family(family, 2)


def _bytes(config: InstrumentConfig, chunks: list[int], grid_block_steps: int = 600) -> tuple[bytes, Simulator]:
    sim = Simulator(load_profile("paper"), config, rate_hz=2, seed=5, grid_block_steps=grid_block_steps)
    return b"".join(sim.stream(n)[1] for n in chunks), sim


def test_an_instrument_without_a_family_is_drawn_and_simulated_as_before():
    base = draw_instrument(7)
    assert base.family is None and "family" not in base.as_dict()
    assert set(base.as_dict()) == {f.name for f in dataclasses.fields(InstrumentConfig)} - {"family"}
    with_family = draw_instrument(7, family="memory")
    assert dataclasses.replace(with_family, family=None) == base  # the same instrument K underneath
    assert with_family.as_dict()["family"]["name"] == "memory"
    stripped, _ = _bytes(dataclasses.replace(with_family, family=None), [2400])
    plain, sim = _bytes(base, [2400])
    assert stripped == plain and "drift_family_dph" not in sim._grid.data
    assert _bytes(with_family, [2400])[0] != plain


@pytest.mark.parametrize("family", FAMILIES)
def test_a_family_instrument_streams_the_same_bytes_however_the_run_is_chunked(family):
    config = draw_instrument(4, family=family)
    whole, sim_a = _bytes(config, [3000])
    pieces, sim_b = _bytes(config, [1, 777, 1222, 1000])
    assert whole == pieces
    _, sim_c = _bytes(config, [3000], grid_block_steps=7)  # another grid block: the family's term is the same
    n = 1500
    np.testing.assert_array_equal(sim_c._grid.data["drift_family_dph"][:n], sim_a._grid.data["drift_family_dph"][:n])


def test_the_truth_drift_of_a_family_instrument_holds_the_family_term():
    sim = Simulator(load_profile("paper"), draw_instrument(4, family="stress"), rate_hz=2, seed=5)
    block = sim.frames(2 * 1200)
    rows = truth_rows(block, 2, sim.config.scale_f32)
    col = {name: rows[:, i] for i, name in enumerate(TRUTH_COLUMNS)}
    parts = sum(col[f"drift_{p}_dph"] for p in ("bias_temp", "shupe", "gradient", "hysteresis"))
    family = np.add.reduceat(block.components_arcsec["drift_family"], np.arange(0, 2400, 2))  # arcsec per 1 s
    np.testing.assert_allclose(col["drift_dph"] - parts, family, atol=1e-9)
    assert np.abs(family).max() > 0.01


def test_simulate_adds_a_family_to_a_population_instrument_and_refuses_it_alone(tmp_path):
    """``simulate --instrument-seed K --family NAME`` writes instrument K with the family's physics (the sidecar
    holds the same configuration ``draw_instrument`` makes, the truth's drift the family's term); ``--family`` without
    ``--instrument-seed`` is a usage error on one line."""
    out = tmp_path / "fam.bin"
    cmd = [sys.executable, "-m", "fog_driver", "simulate", "--profile", "configs/profiles/short-test.yaml"]
    cmd += ["--rate-hz", "5", "--duration", "60", "--instrument-seed", "7", "--family", "layered", "--out", str(out)]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr
    assert read_provenance(out)["model"] == draw_instrument(7, family="layered").as_dict()
    truth = read_truth(out.with_suffix(".truth.csv"))
    parts = sum(truth[f"drift_{p}_dph"] for p in ("bias_temp", "shupe", "gradient", "hysteresis"))
    assert np.abs(truth["drift_dph"] - parts).max() > 1e-6  # the family's term, beyond the population's four
    alone = [*cmd[:8], "--family", "layered", "--out", str(tmp_path / "x.bin")]
    bad = subprocess.run(alone, capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert bad.returncode == 64 and "--instrument-seed" in bad.stderr and "Traceback" not in bad.stderr
    assert len(bad.stderr.strip().splitlines()) == 1
