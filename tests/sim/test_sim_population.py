"""The population of simulated instruments: the same seed gives the same instrument, every drawn
parameter stays inside its documented range (and the draws cover it), and the physics reach the capture."""

from __future__ import annotations

import math
import subprocess
import sys
import zlib

import numpy as np
import pytest
import yaml

from fog_driver.lab.profiles import load_profile
from fog_driver.protocol import decode_file
from fog_driver.samples.captures import read_provenance
from fog_driver.samples.stream import temperature_c_array
from fog_driver.sim import population
from fog_driver.sim.capture import read_truth, simulate_to_file
from fog_driver.sim.instrument import InstrumentConfig, Simulator
from fog_driver.sim.population import RANGES, draw_instrument
from fog_driver.sim.thermal import ThermalModel, ThermalParams

SEEDS = range(300)


@pytest.fixture(scope="module")
def drawn() -> list[InstrumentConfig]:
    return [draw_instrument(k) for k in SEEDS]


def _values(name: str, c: InstrumentConfig) -> list[float]:
    """The drawn values of RANGES entry ``name`` in one instrument config."""
    th, g, s = c.thermal, c.gyro, c.thermometers
    direct = {
        **{
            k: [getattr(th, k)]
            for k in (
                "tau_housing_s",
                "tau_top_s",
                "tau_bottom_s",
                "tau_ring_s",
                "tau_mount_s",
                "tau_bottom_mount_s",
                "self_heating_c",
                "top_heating_c",
            )
        },
        **{
            k: [getattr(g, k)]
            for k in (
                "shupe_dph_per_c_per_min",
                "gradient_dph_per_c",
                "radial_gradient_dph_per_c",
                "hysteresis_dph_per_c",
                "hysteresis_tau_s",
                "scale_factor_ppm",
                "scale_factor_ppm_per_c",
            )
        },
    }
    if name in direct:
        return direct[name]
    return {
        "coil_stages": [1 + len(th.coil_inner_lags_s)],
        "coil_lag_s": [*th.coil_inner_lags_s, th.tau_fiber_s],
        "sensor_lag_s": list(s.sensor_lags_s),
        "sensor_offset_c": list(s.offsets_c),
    }[name]


def test_the_same_seed_gives_the_same_instrument_and_another_seed_another():
    a, b = draw_instrument(17), draw_instrument(17)
    assert a == b and a.as_dict() == b.as_dict()
    assert a.serial == "FOG-POP-00017" and a.population_seed == 17
    assert draw_instrument(18).as_dict() != a.as_dict()
    # Through YAML, as a sidecar stores it: the same instrument again.
    from fog_driver.files.typed_mapping import dataclass_from_mapping

    again = dataclass_from_mapping(InstrumentConfig, yaml.safe_load(yaml.safe_dump(a.as_dict())), "test")
    assert again == a


def test_the_base_configuration_supplies_everything_not_drawn():
    base = InstrumentConfig(clock_ppm=-3.0)
    c = draw_instrument(4, base)
    assert c.clock_ppm == -3.0 and c.gyro.arw_deg_per_sqrt_h == base.gyro.arw_deg_per_sqrt_h
    assert c.thermal.tau_fiber_s != base.thermal.tau_fiber_s


@pytest.mark.parametrize(
    "name",
    [
        n
        for n in RANGES
        if n
        not in (
            "coil_weight_top",
            "coil_weight_bottom",
            "coil_weight_housing",
            "bias_curve_excursion_dph",
            "bias_curve_shape",
        )
    ],
)
def test_every_drawn_parameter_is_inside_its_range_and_the_draws_cover_it(name, drawn):
    r = RANGES[name]
    values = np.array([v for c in drawn for v in _values(name, c)])
    magnitude = np.abs(values) if r.signed else values
    assert magnitude.min() >= r.lo and magnitude.max() <= r.hi * (1 + 1e-12)
    span = (math.log(r.hi) - math.log(r.lo)) if r.log else (r.hi - r.lo)
    low_end = (np.log(magnitude.min()) - math.log(r.lo)) if r.log else (magnitude.min() - r.lo)
    high_end = (math.log(r.hi) - np.log(magnitude.max())) if r.log else (r.hi - magnitude.max())
    assert low_end < 0.1 * span and high_end < 0.1 * span, "the draws reach both ends of the range"
    if r.signed:
        assert 0.3 < (values < 0).mean() < 0.7, "both signs, about equally often"
    if name == "coil_stages":
        assert set(values.tolist()) == {1, 2, 3}


def test_coil_coupling_and_the_bias_curve_follow_their_rules(drawn):
    excursions = []
    span = np.linspace(*population.BIAS_CURVE_SPAN_C, 1001)
    for c in drawn:
        w = np.array(c.thermal.coil_coupling)
        assert w.min() >= 0 and abs(w.sum() - 1) < 1e-12
        raw = w / w[0] * 1.0  # ratios of the raw weights are kept by the normalization
        assert 0.2 / 1.0 <= raw[1] <= 1.0 / 0.2 and w[2] / w[0] <= 0.4 / 0.2
        coeffs = c.gyro.bias_temp_coeffs_dph
        assert len(coeffs) == 4 and c.gyro.reference_temp_c == 20.0
        curve = c.gyro.bias_vs_temperature_dph(span)
        excursions.append(curve.max() - curve.min())
    r = RANGES["bias_curve_excursion_dph"]
    excursions = np.array(excursions)
    assert excursions.min() >= r.lo * (1 - 1e-9) and excursions.max() <= r.hi * (1 + 1e-9)
    assert excursions.min() < 0.4 and excursions.max() > 1.6
    # The shape is not a cubic: the quartic term matters in some instruments.
    assert max(abs(c.gyro.bias_temp_coeffs_dph[3]) * 50**4 for c in drawn) > 0.1


def test_bad_instrument_seeds_are_refused():
    for bad in (-1, population.MAX_INSTRUMENT_SEED + 1, 1.5, True, "3"):
        with pytest.raises(ValueError, match="instrument seed"):
            draw_instrument(bad)


def test_the_coil_stages_lag_the_fiber_behind_its_boundary():
    """One stage: the fiber follows the boundary with tau_fiber_s; more stages lag it further, and the rate
    the drift model uses is the fiber temperature's derivative."""
    air = np.r_[np.full(600, 20.0), 20.0 + np.arange(1, 4 * 3600 + 1) / 240.0]  # 0.25 degC/min for 4 hours
    lags = []
    for inner in ((), (300.0,), (300.0, 600.0)):
        p = ThermalParams(coil_inner_lags_s=inner, cold_start=False)
        x = ThermalModel(p, 1.0, 20.0).run(air)
        boundary = p.boundary_c(x)
        lag = float(boundary[-1] - x[-1, 3])
        # A chain of lags on a ramp lags it by the boundary's rate times their sum (the rate is nearly steady).
        assert lag == pytest.approx(float(np.gradient(boundary)[-2]) * (240.0 + sum(inner)), rel=0.03)
        lags.append(lag)
        rate = p.fiber_rate_c_per_s(x)
        np.testing.assert_allclose(rate[100:-1], np.gradient(x[:, 3])[100:-1], rtol=2e-3, atol=1e-6)
    assert lags[0] < lags[1] < lags[2]


def _documented_draws(seed: int, name: str, n: int) -> list[float]:
    """Instrument ``seed``'s ``n`` values of RANGES entry ``name`` by the module's rule, computed here: the stream
    keyed by (seed, CRC-32 of the name) gives (value, sign) uniform pairs, each value uniform or log-uniform in
    its range."""
    r = RANGES[name]
    u = np.random.default_rng(np.random.SeedSequence([seed, zlib.crc32(name.encode())])).random(2 * n)
    if r.log:
        values = np.exp(math.log(r.lo) + u[0::2] * (math.log(r.hi) - math.log(r.lo)))
    else:
        values = r.lo + u[0::2] * (r.hi - r.lo)
    return np.where(r.signed & (u[1::2] < 0.5), -values, values).tolist()


def _first_order_lags(u: np.ndarray, taus_s: list[float], dt_s: float = 1.0) -> np.ndarray:
    """``u`` through first-order lags in series (time constants ``taus_s``, outermost first), each stage started
    where the first input is (an instrument at one temperature at power-on), stepped exactly for an input held
    over each ``dt_s``: the lagged series, one value per input, before that input's step."""
    stages = [float(u[0])] * len(taus_s)
    gains = [1.0 - math.exp(-dt_s / tau) for tau in taus_s]
    out = np.empty(len(u))
    for n, x in enumerate(u.tolist()):
        out[n] = stages[-1]
        for i, gain in enumerate(gains):
            stages[i] += gain * (x - stages[i])
            x = stages[i]
    return out


def test_a_drawn_instrument_is_simulated_with_its_physics(tmp_path):
    """The capture of instrument K is the same every time, and its truth shows the drawn coil: the fiber lags
    the coil's boundary by the drawn stages, and the thermometers carry the drawn offsets."""
    k = next(k for k in SEEDS if len(draw_instrument(k).thermal.coil_inner_lags_s) == 2)
    config = draw_instrument(k)
    lags_s = [*config.thermal.coil_inner_lags_s, config.thermal.tau_fiber_s]
    offsets_c = config.thermometers.offsets_c
    assert lags_s == pytest.approx(_documented_draws(k, "coil_lag_s", 3), rel=1e-12)
    assert list(offsets_c) == pytest.approx(_documented_draws(k, "sensor_offset_c", 3), rel=1e-12)
    profile = load_profile("configs/profiles/short-test.yaml")
    paths = [
        simulate_to_file(Simulator(profile, config, rate_hz=10, seed=3), tmp_path / f"p{i}.bin").capture
        for i in range(2)
    ]
    assert paths[0].read_bytes() == paths[1].read_bytes()
    side = read_provenance(paths[0])
    assert side["model"]["population_seed"] == k and side["instrument"]["serial"] == config.serial
    truth = read_truth(paths[0].with_suffix(".truth.csv"))
    default = simulate_to_file(Simulator(profile, rate_hz=10, seed=3), tmp_path / "d.bin").capture
    assert read_truth(default.with_suffix(".truth.csv"))["fiber_c"].tolist() != truth["fiber_c"].tolist()
    assert np.isfinite(truth["drift_dph"]).all() and truth["drift_dph"].std() > 0
    # The fiber is the coil's boundary (the drawn coupling of the ring's top, bottom and the housing) through the
    # drawn stages, stepped here on the truth's seconds: within 0.03 degC over the ramp, where a tenth more or
    # less on every stage, or their sum as one stage, is more than 0.3 degC off.
    top, bottom, housing = config.thermal.coil_coupling
    boundary_c = top * truth["top_c"] + bottom * truth["bottom_c"] + housing * truth["housing_c"]
    assert np.abs(_first_order_lags(boundary_c, lags_s) - truth["fiber_c"]).max() < 0.03
    for wrong_s in ([v * 0.9 for v in lags_s], [v * 1.1 for v in lags_s], [sum(lags_s)]):
        assert np.abs(_first_order_lags(boundary_c, wrong_s) - truth["fiber_c"]).max() > 0.3
    # Each thermometer reads its node through its drawn lag plus its drawn offset: over the run, the frames'
    # readings less the lagged truth average to the offset within five sigmas of the per-run part.
    samples = decode_file(paths[0]).samples
    second = np.repeat(truth["second"].astype(int), truth["n_frames"].astype(int))
    assert len(second) == len(samples.t_top_raw)
    readings = (samples.t_top_raw, samples.t_bottom_raw, samples.t_housing_raw)
    for node, raw, lag_s, offset_c in zip(
        ("top_c", "bottom_c", "housing_c"), readings, config.thermometers.lags(), offsets_c
    ):
        read_c = np.bincount(second, weights=temperature_c_array(raw)) / np.bincount(second)
        lagged_c = _first_order_lags(truth[node], [lag_s])
        assert float(np.mean(read_c - lagged_c)) == pytest.approx(offset_c, abs=5 * population.PER_RUN_OFFSET_SIGMA_C)


def test_simulate_takes_an_instrument_seed(tmp_path):
    out = tmp_path / "pop.bin"
    cmd = [
        sys.executable,
        "-m",
        "fog_driver",
        "simulate",
        "--profile",
        "configs/profiles/short-test.yaml",
        "--rate-hz",
        "5",
        "--duration",
        "60",
        "--instrument-seed",
        "42",
        "--out",
        str(out),
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    side = read_provenance(out)
    assert side["instrument"]["serial"] == "FOG-POP-00042"
    assert side["model"] == draw_instrument(42).as_dict()
    bad = subprocess.run(
        cmd[:-4] + ["--instrument-seed", "-2", "--out", str(tmp_path / "x.bin")],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert bad.returncode == 2 and "seed must be >= 0" in bad.stderr and "Traceback" not in bad.stderr


def test_the_drawn_scale_factor_error_reaches_the_truth(tmp_path):
    """s(Tf) = (s0 + s1 (Tf - 20)) 1e-6 with the drawn offset and slope: the truth's scale-factor term is
    s times the true input (table and Earth), second by second, against the truth's own fiber temperature."""
    k = next(k for k in SEEDS if draw_instrument(k).gyro.scale_factor_ppm < -30)
    config = draw_instrument(k)
    g = config.gyro
    assert 5 <= abs(g.scale_factor_ppm) <= 50 and 0.1 <= g.scale_factor_ppm_per_c <= 1.0
    profile = load_profile("configs/profiles/short-test.yaml")
    capture = simulate_to_file(Simulator(profile, config, rate_hz=10, seed=3), tmp_path / "sf.bin").capture
    truth = read_truth(capture.with_suffix(".truth.csv"))
    s = (g.scale_factor_ppm + g.scale_factor_ppm_per_c * (truth["fiber_c"] - 20.0)) * 1e-6
    expected = s * (truth["input_dph"] + truth["earth_dph"])
    np.testing.assert_allclose(truth["scale_factor_error_dph"], expected, rtol=1e-4, atol=1e-9)
    assert np.abs(truth["scale_factor_error_dph"]).max() > 30e-6 * truth["earth_dph"].min()


def test_the_simulator_writes_a_table_log_of_its_dwells_with_the_tables_true_angles(tmp_path):
    """``run.table.csv``: the dwells of the motion in device time, the format ``evaluate --reference`` reads
    (the same stops as the sidecar's), and under a creep the table's true angle at each dwell's start and
    end, as the truth's own angle column has it."""
    from fog_driver.dwells import read_table_log
    from fog_driver.lab.motion import Creep, MotionPlan, Positioning
    from fog_driver.lab.profiles import SimProfile
    from fog_driver.lab.program import ChamberProfile, Hold
    from fog_driver.report.positioning import stops_from_sidecar

    seq = Positioning(start_s=60.0, moves=6, step_deg=[36.0, -72.0, 10.0], dwell_s=20.0)
    creep = Creep(rate_dph=720.0, start_s=100.0, stop_s=170.0)  # 0.2 deg/s: far above the gyro's noise
    profile = SimProfile(
        "creeping", ChamberProfile("creeping", 20.0, (Hold(seq.end_s + 30.0),)), MotionPlan((seq, creep)), "test"
    )
    config = draw_instrument(7)
    result = simulate_to_file(Simulator(profile, config, rate_hz=10, seed=3), tmp_path / "c.bin")
    assert result.table_log == tmp_path / "c.table.csv" and result.table_log.is_file()
    assert read_provenance(result.capture)["table_log"] == "c.table.csv"
    logged = read_table_log(result.table_log)
    assert [(s.t_start_s, s.t_end_s, s.angle_deg) for s in logged] == [
        (s.t_start_s, s.t_end_s, s.angle_deg) for s in stops_from_sidecar(result.capture)
    ]
    rows = result.table_log.read_text().splitlines()
    assert rows[1] == "t_start_s,t_end_s,angle_deg,angle_end_deg" and len(rows) == 2 + seq.moves + 1
    ends = [float(r.split(",")[3]) for r in rows[2:]]
    truth = read_truth(result.truth)
    ppm = 1.0 + config.clock_ppm * 1e-6
    plan = profile.motion
    for stop, end in zip(logged, ends):  # the plan's true angles, which the truth's angle column also has
        # (the log's times are rounded to the microsecond: 0.2 deg/s moves 2e-7 deg in that)
        assert stop.angle_deg == pytest.approx(float(plan.angle_deg(stop.t_start_s / ppm)), abs=1e-6)
        assert end == pytest.approx(float(plan.angle_deg(stop.t_end_s / ppm)), abs=1e-6)
        inside = (truth["second"] + 1 > stop.t_start_s) & (truth["second"] + 1 < stop.t_end_s)
        t_true = (truth["second"][inside] + 0.9) / ppm  # the second's last frame (10 Hz), k / rate / ppm
        np.testing.assert_allclose(truth["angle_deg"][inside], plan.angle_deg(t_true), rtol=0, atol=1e-7)  # 7 places
    turned = [end - s.angle_deg for s, end in zip(logged, ends)]
    assert max(turned) > 0.05 and min(turned) == 0.0  # dwells under the creep turned, the others did not
    # a profile without dwells writes none
    static = SimProfile("still", ChamberProfile("still", 20.0, (Hold(30.0),)), MotionPlan(()), "test")
    assert simulate_to_file(Simulator(static, config, rate_hz=10, seed=3), tmp_path / "s.bin").table_log is None
    assert not (tmp_path / "s.table.csv").exists()
