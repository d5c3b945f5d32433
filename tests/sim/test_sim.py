"""The instrument simulator: determinism, physics against its own truth, faults, the simulate CLI."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from fog_driver.lab.profiles import load_profile
from fog_driver.protocol import STATUS_STARTUP, STATUS_THERMOMETER_FAULT, decode_bytes, decode_file
from fog_driver.samples.captures import read_provenance
from fog_driver.samples.stream import SampleStream
from fog_driver.sim.capture import TRUTH_COLUMNS, read_truth, simulate_to_file
from fog_driver.sim.faults import parse_fault_spec
from fog_driver.sim.instrument import InstrumentConfig, Simulator, load_instrument_config

ROOT = Path(__file__).resolve().parents[2]
SHORT = ROOT / "configs" / "profiles" / "short-test.yaml"


def capture_bytes(sim: Simulator, frames: int, batch: int) -> bytes:
    return b"".join(data for _, data in sim.batches(batch, frames))


def per_second_rates(data: bytes, rate_hz: int) -> np.ndarray:
    """deg/h per device second from a capture's bytes, through the driver's own decoder and stream."""
    samples = SampleStream().run(decode_bytes(data))
    n = len(samples) // rate_hz * rate_hz
    return samples.dtheta_arcsec[:n].reshape(-1, rate_hz).sum(axis=1)


@pytest.fixture(scope="module")
def paper_run(tmp_path_factory) -> dict:
    """The whole paper profile at 4 Hz (physics and truth do not depend on the frame rate)."""
    out = tmp_path_factory.mktemp("paper") / "paper.bin"
    sim = Simulator(load_profile("paper"), rate_hz=4, seed=11)
    simulate_to_file(sim, out)
    return {"path": out, "truth": read_truth(out.with_suffix(".truth.csv")), "sim": sim}


# --- determinism -------------------------------------------------------------------------------


def test_same_seed_gives_the_same_bytes_whatever_the_batching():
    faults = parse_fault_spec("drop=0.01,flip=2e-4,garbage=0.3,thermo=0.2:1,disconnect=20:3+50:0.4")
    make = lambda seed: Simulator(load_profile(SHORT), rate_hz=20, seed=seed, faults=faults)  # noqa: E731
    reference = capture_bytes(make(4), 1600, 1600)
    for batch in (1, 7, 20, 333):
        assert capture_bytes(make(4), 1600, batch) == reference, batch
    assert capture_bytes(make(5), 1600, 1600) != reference


def test_rate_changes_noise_not_the_thermal_truth(tmp_path):
    a, b = tmp_path / "a.bin", tmp_path / "b.bin"
    simulate_to_file(Simulator(load_profile(SHORT), rate_hz=10, seed=2), a, duration_s=120)
    simulate_to_file(Simulator(load_profile(SHORT), rate_hz=50, seed=2), b, duration_s=120)
    ta, tb = read_truth(a.with_suffix(".truth.csv")), read_truth(b.with_suffix(".truth.csv"))
    for name in ("fiber_c", "drift_dph", "bias_instability_dph"):
        np.testing.assert_allclose(ta[name], tb[name], rtol=0, atol=1e-3)


# --- against truth -----------------------------------------------------------------------------


def test_capture_decodes_cleanly_and_counts_match_truth(paper_run):
    decoded = decode_file(paper_run["path"])
    c = decoded.counters
    sim, truth = paper_run["sim"], paper_run["truth"]
    assert (c.crc_errors, c.bytes_discarded, c.seq_gaps, c.length_errors) == (0, 0, 0, 0)
    assert c.sample_frames == sim.total_frames()
    assert c.identity_frames == len(truth["second"])
    assert c.t_us_wraps >= 1  # 440 min spans at least one 71.6-min wrap
    assert decoded.samples.seq[0] == sim.seq0 and decoded.samples.t_us[0] == sim.t_us0
    assert {i.serial for i in decoded.identities} == {"FOG-SIM-0001"}
    startup = (decoded.samples.status & STATUS_STARTUP) != 0
    assert startup.sum() == 2 * 4  # the first 2 s at 4 Hz
    measured = per_second_rates(paper_run["path"].read_bytes(), 4)
    full = truth["n_frames"] == 4
    np.testing.assert_allclose(measured, truth["measured_dph"][full][: len(measured)], atol=1e-6)
    provenance = read_provenance(paper_run["path"])
    assert provenance["seed"] == 11 and provenance["profile"] == "paper" and provenance["frames"] == c.sample_frames


def test_quantization_carries_the_remainder(paper_run):
    truth = paper_run["truth"]
    parts = ("input", "earth", "scale_factor_error", "constant_bias", "drift", "bias_instability", "rrw", "arw")
    true_total = sum(truth[f"{name}_dph"] for name in parts)
    # Per second the counts differ from the true angle by less than one count (0.01 arcsec) ...
    assert np.abs(truth["measured_dph"] - true_total).max() < 0.0101
    # ... and the differences never accumulate: the cumulative angle stays within one count.
    assert np.abs(np.cumsum(truth["measured_dph"] - true_total)).max() < 0.0101


def test_plateau_rate_std_matches_the_configured_arw():
    # The last 10 minutes of the paper's 55 degC hold (minutes 160 to 170).
    for arw in (0.003, 0.006):
        config = dataclasses.replace(
            InstrumentConfig(), gyro=dataclasses.replace(InstrumentConfig().gyro, arw_deg_per_sqrt_h=arw)
        )
        sim = Simulator(load_profile("paper"), config, rate_hz=10, seed=3)
        rates = per_second_rates(capture_bytes(sim, 170 * 60 * 10, 6000), 10)
        plateau = rates[160 * 60 : 170 * 60]
        predicted = arw * 60.0  # deg/h over 1 s
        assert abs(plateau.std() / predicted - 1.0) < 0.2, (arw, plateau.std(), predicted)


def test_drift_terms_fit_back_from_truth(paper_run):
    truth, g = paper_run["truth"], InstrumentConfig().gyro
    dtemp = truth["fiber_c"] - g.reference_temp_c
    fiber_rate_c_per_min = np.gradient(truth["fiber_c"]) * 60.0
    gradient = truth["top_c"] - truth["bottom_c"]
    features = np.column_stack([dtemp, dtemp**2, dtemp**3, fiber_rate_c_per_min, gradient])
    target = truth["drift_dph"] - truth["drift_hysteresis_dph"]
    coeffs, *_ = np.linalg.lstsq(features, target, rcond=None)
    expected = [*g.bias_temp_coeffs_dph, g.shupe_dph_per_c_per_min, g.gradient_dph_per_c]
    np.testing.assert_allclose(coeffs, expected, rtol=0.03)


def test_ramps_show_shupe_and_gradient_terms_in_the_measured_output(paper_run):
    """From the capture itself (per-second rates through the driver's decoder, not truth): the
    Shupe and gradient coefficients come back by least squares on the true temperatures."""
    truth, g = paper_run["truth"], InstrumentConfig().gyro
    measured = per_second_rates(paper_run["path"].read_bytes(), 4)
    m = len(measured)
    known = (
        truth["earth_dph"]
        + truth["constant_bias_dph"]
        + truth["drift_hysteresis_dph"]
        + truth["scale_factor_error_dph"]
    )
    y = measured - known[:m]
    dtemp = truth["fiber_c"][:m] - g.reference_temp_c
    rate = np.gradient(truth["fiber_c"])[:m] * 60.0  # degC per minute
    gradient = (truth["top_c"] - truth["bottom_c"])[:m]
    assert abs(np.corrcoef(rate, gradient)[0, 1]) < 0.9  # the two terms are separable on this profile
    features = np.column_stack([np.ones(m), dtemp, dtemp**2, dtemp**3, rate, gradient])
    coeffs, *_ = np.linalg.lstsq(features, y, rcond=None)
    assert coeffs[4] == pytest.approx(g.shupe_dph_per_c_per_min, rel=0.15)
    assert coeffs[5] == pytest.approx(g.gradient_dph_per_c, rel=0.15)
    ramps = np.abs(rate) > 0.5
    # The fiber keeps moving into each hold, so the term fades rather than stops: 3x, not more.
    assert np.abs(truth["drift_shupe_dph"][:m])[ramps].mean() > 3 * np.abs(truth["drift_shupe_dph"][:m])[~ramps].mean()


def test_thermal_model_lags_and_gradients(paper_run):
    truth = paper_run["truth"]
    t = truth["t_true_s"] / 60.0
    warm_up_end = (t > 28) & (t < 30)  # after 30 min of self-heating at 20 degC
    assert np.all(truth["housing_c"][warm_up_end] - truth["air_c"][warm_up_end] > 2.5)
    first_ramp = (t > 31) & (t < 35)  # 20 -> 25 degC at 1 degC/min
    ring_mean = 0.5 * (truth["top_c"] + truth["bottom_c"])
    assert np.all(truth["housing_c"][first_ramp] > ring_mean[first_ramp])  # heat flows inwards
    assert np.all(truth["fiber_c"][first_ramp] < ring_mean[first_ramp])  # the fiber lags the thermometers
    gradient = truth["top_c"] - truth["bottom_c"]
    hold = (t > 45) & (t < 50)
    assert np.abs(gradient[first_ramp]).max() > 2 * np.abs(gradient[hold] - gradient[hold].mean()).max()
    assert truth["air_c"].min() == pytest.approx(-40.0) and truth["air_c"].max() == pytest.approx(55.0)


# --- faults ------------------------------------------------------------------------------------


def test_faults_never_change_the_physics():
    spec = parse_fault_spec("drop=0.01,flip=1e-4,garbage=0.5")
    clean = decode_bytes(capture_bytes(Simulator(load_profile(SHORT), rate_hz=20, seed=8), 4000, 500))
    faulty = decode_bytes(capture_bytes(Simulator(load_profile(SHORT), rate_hz=20, seed=8, faults=spec), 4000, 500))
    assert clean.counters.sample_frames == 4000
    # Every frame that got through is exactly the clean instrument's frame with that seq.
    clean_by_seq = {int(q): i for i, q in enumerate(clean.samples.seq)}
    for name in ("dtheta_counts", "t_us", "t_top_raw", "status"):
        got = getattr(faulty.samples, name)
        want = getattr(clean.samples, name)[[clean_by_seq[int(q)] for q in faulty.samples.seq]]
        np.testing.assert_array_equal(got, want, err_msg=name)
    c = faulty.counters
    assert c.crc_errors > 0 and c.bytes_discarded > 0
    # Every frame between the first and last received is either received or counted missing.
    span = (int(faulty.samples.seq[-1]) - int(faulty.samples.seq[0])) % 65536 + 1
    assert c.sample_frames + c.missing_frames == span <= 4000
    assert 0.005 < c.missing_frames / 4000 < 0.05


def test_thermometer_faults_set_the_sentinel_and_the_status_bit():
    spec = parse_fault_spec("thermo=0.5:1")
    decoded = decode_bytes(capture_bytes(Simulator(load_profile(SHORT), rate_hz=20, seed=9, faults=spec), 2400, 999))
    s = decoded.samples
    sentinel = (s.t_top_raw == -32768) | (s.t_bottom_raw == -32768) | (s.t_housing_raw == -32768)
    flagged = (s.status & STATUS_THERMOMETER_FAULT) != 0
    np.testing.assert_array_equal(sentinel, flagged)
    assert 0.1 < sentinel.mean() < 0.6  # 0.5 faults/s lasting 1 s each, on one of three sensors
    assert decoded.counters.crc_errors == 0  # instrument faults, not link faults


def test_disconnect_cuts_the_link_mid_frame():
    spec = parse_fault_spec("disconnect=30:5")
    decoded = decode_bytes(capture_bytes(Simulator(load_profile(SHORT), rate_hz=20, seed=1, faults=spec), 1600, 128))
    seconds = (decoded.samples.seq.astype(np.int64) - decoded.samples.seq[0]) % 65536 / 20.0
    assert not np.any((seconds >= 30) & (seconds < 35))
    assert seconds.max() > 70
    c = decoded.counters
    assert (c.seq_gaps, c.missing_frames) == (1, 100)
    assert c.truncated_frames + c.crc_errors == 1 and c.bytes_discarded == 13  # half a frame went out


def test_fault_spec_errors_are_one_line():
    from fog_driver.errors import UsageError

    for text, needle in [
        ("drop", "expected name=value"),
        ("drop=x", "not a number"),
        ("flip=2", "probability"),
        ("wobble=1", "unknown fault"),
        ("disconnect=5", "START_S:DURATION_S"),
        ("disconnect=5:10+8:1", "overlap"),
        ("drop=0.1,drop=0.2", "twice"),
    ]:
        with pytest.raises(UsageError, match=needle):
            parse_fault_spec(text)
    assert parse_fault_spec("drop=0.1,thermo=0.2:3,disconnect=5:1").describe() == "drop=0.1,thermo=0.2:3,disconnect=5:1"
    assert not parse_fault_spec("none").any


# --- positioning -------------------------------------------------------------------------------


def test_positioning_angles_from_the_capture_match_the_turntable(tmp_path):
    out = tmp_path / "pos.bin"
    sim = Simulator(load_profile(ROOT / "configs" / "profiles" / "positioning.yaml"), rate_hz=200, seed=6)
    simulate_to_file(sim, out)
    stops = read_provenance(out)["positioning_stops"]
    assert len(stops) == 11 and [s["angle_deg"] for s in stops] == [36.0 * k for k in range(11)]
    measured = per_second_rates(out.read_bytes(), 200)  # arcsec per device second
    truth = read_truth(out.with_suffix(".truth.csv"))
    assert np.all(truth["input_dph"][: int(stops[0]["t_start_s"])] == 0)
    # Over whole device seconds from one dwell to the next, the capture's angle less every
    # non-input term (realized noise included, from truth) is the commanded step, to quantization.
    not_input = sum(
        truth[f"{n}_dph"]
        for n in ("earth", "scale_factor_error", "constant_bias", "drift", "bias_instability", "rrw", "arw")
    )
    for before, after in zip(stops, stops[1:]):
        s0 = int(0.5 * (before["t_start_s"] + before["t_end_s"]))
        s1 = int(0.5 * (after["t_start_s"] + after["t_end_s"]))
        sensed = measured[s0:s1].sum() - not_input[s0:s1].sum()
        assert sensed == pytest.approx((after["angle_deg"] - before["angle_deg"]) * 3600.0, abs=0.02)
        assert truth["angle_deg"][s1 - 1] == pytest.approx(after["angle_deg"], abs=1e-9)
        # Without that help, the raw move angle is off only by Earth, bias, drift and noise.
        assert abs(measured[s0:s1].sum() - 129600.0) < 20.0 * (s1 - s0)


# --- configuration and CLI ---------------------------------------------------------------------


def test_shipped_instrument_config_lists_the_defaults():
    assert load_instrument_config(ROOT / "configs" / "sim" / "instrument.yaml") == InstrumentConfig()
    shipped = yaml.safe_load((ROOT / "configs" / "sim" / "instrument.yaml").read_text())
    assert set(shipped) == {f.name for f in dataclasses.fields(InstrumentConfig)}


@pytest.mark.parametrize(
    "text, needle",
    [
        ("gyro: {arw: 1}\n", "unknown key 'arw'"),
        ("gyro: {arw_deg_per_sqrt_h: fast}\n", "expected a finite number"),
        ("thermal: {tau_housing_s: -1}\n", "tau_housing_s must be > 0"),
        ("thermal: {cold_start: 1}\n", "expected true or false"),
        ("serial: FOG-SERIAL-NUMBER-TOO-LONG\n", "at most 16"),
        ("- 1\n", "expected a mapping"),
    ],
)
def test_bad_instrument_config_is_a_one_line_error(tmp_path, text, needle):
    from fog_driver.errors import InputFileError

    path = tmp_path / "i.yaml"
    path.write_text(text)
    with pytest.raises(InputFileError, match=needle):
        load_instrument_config(path)


def run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "fog_driver", *args], capture_output=True, text=True, timeout=300)


def test_simulate_cli_writes_capture_sidecar_and_truth(tmp_path):
    out = tmp_path / "run.bin"
    proc = run_cli(
        "simulate",
        "--profile",
        str(SHORT),
        "--out",
        str(out),
        "--rate-hz",
        "50",
        "--seed",
        "7",
        "--duration",
        "60",
        "--faults",
        "drop=0.001",
    )
    assert proc.returncode == 0, proc.stderr
    assert "3,000 frames" in proc.stdout
    provenance = read_provenance(out)
    assert provenance["seed"] == 7 and provenance["rate_hz"] == 50 and provenance["faults"] == "drop=0.001"
    assert provenance["model"]["gyro"]["arw_deg_per_sqrt_h"] == 0.003
    truth_lines = out.with_suffix(".truth.csv").read_text().splitlines()
    assert truth_lines[1] == ",".join(TRUTH_COLUMNS) and len(truth_lines) == 2 + 60
    again = tmp_path / "again.bin"
    run_cli(
        "simulate",
        "--profile",
        str(SHORT),
        "--out",
        str(again),
        "--rate-hz",
        "50",
        "--seed",
        "7",
        "--duration",
        "60",
        "--faults",
        "drop=0.001",
    )
    assert again.read_bytes() == out.read_bytes()
    inspected = run_cli("inspect", "--json", str(out))
    assert '"serial": "FOG-SIM-0001"' in inspected.stdout


@pytest.mark.parametrize(
    "args, status, needle",
    [
        (["--profile", "nope.yaml", "--out", "x.bin"], 65, "no such profile file"),
        (["--out", "x.bin", "--faults", "drop=7"], 64, "probability"),
        (["--out", "x.txt"], 64, "must end in .bin"),
        ([], 64, "exactly one of --out"),
        (["--out", "x.bin", "--instrument", "nope.yaml"], 65, "no such instrument config"),
    ],
)
def test_simulate_cli_errors(tmp_path, args, status, needle):
    proc = subprocess.run(
        [sys.executable, "-m", "fog_driver", "simulate", *args],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=60,
    )
    assert proc.returncode == status, proc.stderr
    assert needle in proc.stderr and "Traceback" not in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1


# --- recorded frames for tests -----------------------------------------------------------------

DATA = ROOT / "tests" / "data"


def _fixture_module():
    sys.path.insert(0, str(DATA))
    try:
        import make_fixtures
    finally:
        sys.path.remove(str(DATA))
    return make_fixtures


@pytest.mark.parametrize("name", ["sim-short", "sim-faults"])
def test_simulated_fixtures_match_their_generator(tmp_path, name):
    result = _fixture_module().make_sim(name, tmp_path)
    assert result.capture.read_bytes() == (DATA / f"{name}.bin").read_bytes()
    assert result.truth.read_text() == (DATA / f"{name}.truth.csv").read_text()
    for suffix in (".bin", ".truth.csv", ".bin.yaml"):
        assert (DATA / f"{name}{suffix}").stat().st_size < 1 << 20


@pytest.mark.parametrize("name", ["sim-short", "sim-faults"])
def test_simulated_fixture_through_the_replay_url_decodes_as_the_file_does(name):
    import threading

    from fog_driver.protocol import FrameDecoder
    from fog_driver.transport import PortReader

    path = DATA / f"{name}.bin"
    decoder = FrameDecoder()
    events = []
    received = bytearray()
    for chunk in PortReader(f"replay://{path}?rate=20000&unplug=1", reconnect=False).chunks(threading.Event()):
        received += chunk
        events += decoder.feed(chunk)
    events += decoder.close()
    whole = decode_file(path)
    assert bytes(received) == path.read_bytes()
    assert events == whole.events() and decoder.counters == whole.counters
    truth = read_truth(DATA / f"{name}.truth.csv")
    assert len(truth["second"]) == 300
    if name == "sim-faults":
        assert whole.counters.crc_errors > 0 and whole.counters.missing_frames > 0
    else:
        assert whole.counters.bytes_discarded == 0 and whole.counters.sample_frames == 3000


# --- thermal model and thermometers ------------------------------------------------------------


def test_thermal_discretisation_matches_a_fine_integration():
    from fog_driver.sim.thermal import ThermalModel, ThermalParams

    params = ThermalParams()
    model = ThermalModel(params, 1.0, 0.0)
    minutes = 90
    air_mid = (np.arange(minutes * 60) + 0.5) / 60.0  # a 1 degC/min ramp, sampled at step mid-points
    coarse = model.run(air_mid)[-1]
    a, bu, c = (np.array(x) for x in params.system())
    x = np.zeros(5)
    dt = 0.05  # independent reference: RK4 on a 20x finer grid with the exact ramp input
    f = lambda x, t: a @ x + bu * (t / 60.0) + c  # noqa: E731
    for k in range(int(minutes * 60 / dt)):
        t = k * dt
        k1 = f(x, t)
        k2 = f(x + 0.5 * dt * k1, t + 0.5 * dt)
        k3 = f(x + 0.5 * dt * k2, t + 0.5 * dt)
        k4 = f(x + dt * k3, t + dt)
        x = x + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    np.testing.assert_allclose(coarse, x, atol=1e-6)


def test_warm_start_is_the_powered_equilibrium():
    from fog_driver.sim.thermal import ThermalModel, ThermalParams

    params = ThermalParams(cold_start=False)
    equilibrium = params.equilibrium(20.0)
    assert equilibrium[0] == pytest.approx(20.0 + params.self_heating_c)  # housing: air + self-heating
    assert equilibrium[4] == pytest.approx(20.0)  # the mount is not heated
    held = ThermalModel(params, 1.0, 20.0).run(np.full(3600, 20.0))
    np.testing.assert_allclose(held[-1], equilibrium, atol=1e-9)
    cold = ThermalModel(ThermalParams(), 1.0, 20.0).run(np.full(6 * 3600, 20.0))
    assert cold[0, 0] - 20.0 < 0.01 and cold[-1] == pytest.approx(equilibrium, abs=1e-3)


def test_thermometer_lag_and_noise_options():
    def readings(**thermometers):
        config = dataclasses.replace(
            InstrumentConfig(), thermometers=dataclasses.replace(InstrumentConfig().thermometers, **thermometers)
        )
        sim = Simulator(load_profile(SHORT), config, rate_hz=10, seed=4)
        block = sim.frames(10 * 600)  # 10 minutes: the 2 degC/min ramp starts at minute 5
        return block.t_raw[:, 2] / 256.0, block.truth_temps_c["housing_c"]

    quiet, housing = readings(noise_c=0.0, offset_sigma_c=0.0)
    np.testing.assert_allclose(quiet, housing, atol=0.5 / 256 + 0.05 * 0.1)  # 1/256 rounding, 10 Hz hold
    lagged, _ = readings(noise_c=0.0, offset_sigma_c=0.0, lag_s=60.0)
    ramp = slice(10 * 480, 10 * 600)
    assert np.all(lagged[ramp] < quiet[ramp] - 0.1)  # warming: a lagged sensor reads low
    noisy, _ = readings(noise_c=0.05, offset_sigma_c=0.0)
    assert (noisy - quiet)[: 10 * 240].std() == pytest.approx(0.05, rel=0.15)
