"""The daemon's pipeline and control, without sockets: published angles equal offline compensation."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yaml
from service_in_process import offline
from sigma_stub import STUB_BASE_DPH, STUB_PERIOD, stub_sigma, stub_value

from fog_driver.daemon.config import DEFAULT_MODEL, DriverConfig
from fog_driver.daemon.service import ConfigError, Service
from fog_driver.flags import FLAG_NAMES
from fog_driver.modelfiles import load_model
from fog_driver.offline.compensate import compensate_capture

DATA = Path(__file__).resolve().parents[1] / "data"


def offline_sigmas(
    capture: Path, model_path: Path = DEFAULT_MODEL, column: str = "drift_sigma_dph", **settings
) -> list[float | None]:
    """The drift sigma (or another ``column``) of ``fog-driver compensate``, sample by sample: None where it is
    NaN (no estimate)."""
    parts = [cols for _, cols in compensate_capture(capture, load_model(model_path), **settings)]
    return [float(v) if math.isfinite(v) else None for cols in parts for v in getattr(cols, column)]


@pytest.fixture(scope="module")
def fitted_wesn(tmp_path_factory) -> Path:
    """A wesn fitted on the short capture: sim-faults.bin leaves its fit box, so its sigma moves."""
    from fog_driver.compensation.fitting.data import FitConfig
    from fog_driver.modelfiles import save_model
    from fog_driver.offline.fit import fit_model_file

    model_file, _ = fit_model_file(
        [DATA / "sim-short.bin"], kind="wesn", config=FitConfig(warmup_s=30.0), accept_weak=True
    )
    return save_model(tmp_path_factory.mktemp("wesn") / "wesn.yaml", model_file)


@pytest.mark.determinism
@pytest.mark.parametrize(
    "chunk, sigma", [(1, "default"), (97, "default"), (4096, "default"), (97, "fitted"), (97, "stub")]
)
def test_published_angles_equal_offline_compensation(chunk, sigma, monkeypatch, request):
    """``sigma``: the drift sigma of the shipped model, of a model fitted here (one that moves), or a known one
    per block (``sigma_stub``)."""
    if sigma == "stub":
        stub_sigma(monkeypatch)
    model = request.getfixturevalue("fitted_wesn") if sigma == "fitted" else DEFAULT_MODEL
    capture = DATA / "sim-faults.bin"
    service = Service(DriverConfig(model=str(model)), port="unused")
    data = capture.read_bytes()
    published = []
    for i in range(0, len(data), chunk):
        published += service.process(data[i : i + chunk])
    offline_angles_arcsec, offline_flags = offline(capture, model)
    assert [o["angle_arcsec"] for o in published] == offline_angles_arcsec
    # drift_sigma_dph: bit-identical where there is one, omitted (never NaN, never null) where there is none
    offline_sigma = offline_sigmas(capture, model)
    assert [o.get("drift_sigma_dph") for o in published] == offline_sigma
    assert offline_sigma[0] is None and sum(v is not None for v in offline_sigma) > 2900  # from the 2nd block
    # drift_dph likewise: omitted exactly where the offline drift is NaN (no estimate: flagged uncompensated)
    offline_drift = offline_sigmas(capture, model, "drift_dph")
    assert [o.get("drift_dph") for o in published] == offline_drift
    assert [o.get("drift_dph") is None for o in published] == ["uncompensated" in o["flags"] for o in published]
    assert offline_drift[0] is None and offline_drift[-1] is not None
    if sigma == "stub":
        assert {v for v in offline_sigma if v is not None} == {stub_value(j) for j in range(STUB_PERIOD)}
    if sigma == "fitted":
        assert len({v for v in offline_sigma if v is not None}) > 20  # it moves, and moves alike
    seqs = [o["seq"] for o in published]
    assert seqs == sorted(seqs) and len(seqs) == 2956
    first = published[0]
    assert first["class"] == "ANGLE" and set(first) >= {
        "seq",
        "t_s",
        "angle_arcsec",
        "angle_raw_arcsec",
        "rate_dph",
        "temps_c",
        "flags",
    }
    assert "drift_dph" not in first and "drift_sigma_dph" not in first and "uncompensated" in first["flags"]
    assert first["rate_dph"] == first["rate_raw_dph"] and first["angle_arcsec"] == first["angle_raw_arcsec"]
    assert any("gap" in o["flags"] for o in published)
    assert any(len(o["temps_c"]) < 3 for o in published)  # a faulted thermometer is omitted, never NaN
    # STATUS counts the published samples per flag, as the offline flags do
    expected = {name: int(np.count_nonzero(offline_flags & bit)) for bit, name in FLAG_NAMES.items()}
    assert service.status_object()["flagged"] == expected
    assert expected["gap"] > 0 and expected["thermometer_fault"] > 0 and expected["substituted"] > 0


def test_zero_and_bias_commands():
    service = Service(DriverConfig(), port="unused")
    data = (DATA / "sim-short.bin").read_bytes()
    half = len(data) // 2
    service.process(data[:half])
    assert service.control("ZERO", {}, 0) == {"class": "ZERO", "zeroed": True}
    after = service.process(data[half : half + 2600])  # 100 frames
    assert abs(after[0]["angle_arcsec"]) < 1.0 and abs(after[0]["angle_raw_arcsec"]) < 30.0
    assert service.status_object()["bias_captured"] is False
    started = service.control("BIAS", {"seconds": 5}, 0)  # answered at once; the result is an event later
    assert started == {"class": "BIAS", "state": "started", "capture_id": 1, "seconds": 5.0, "timeout_s": 35.0}
    assert service.control("BIAS", {"seconds": 5}, 0) == {
        "class": "ERROR",
        "message": "a bias capture is already running",
    }
    assert service.last_event is None and service.status_object()["bias_capture_target_s"] == 5.0
    service.process(data[half + 2600 :])
    result = service.last_event
    assert result["class"] == "BIAS" and result["state"] == "done" and result["capture_id"] == 1
    assert abs(result["bias_dph"] - 10.0) < 2.0  # Earth rate + bias at rest
    status = service.status_object()
    assert status["bias_captured"] is True and "bias_capture_target_s" not in status
    assert service.control("BIAS", {"seconds": 0}, 0)["class"] == "ERROR"
    assert service.control("NOPE", {}, 0)["class"] == "ERROR"
    assert service.control("ADAPT", {"enable": "yes"}, 0)["class"] == "ERROR"
    assert service.control("ADAPT", {"enable": True, "reference_dph": 0}, 0) == {
        "class": "ADAPT",
        "enable": True,
        "reference_dph": 0.0,
    }
    status = service.control("STATUS", {}, 0)
    assert status["adapting"] is True and status["adapted_in_use"] is False  # nothing has been compared yet
    assert service.control("SAVE", {}, 0)["class"] == "ERROR"  # no adapt_state configured


def test_a_bias_capture_keeps_the_drift_sigma_it_held_for_the_since_bias_form(monkeypatch):
    """sigma(t_b): the mean of the drift_sigma_dph of the samples the capture took, in the BIAS event and in
    STATUS from then on; absent before any capture, and when the capture's samples had none."""
    stub_sigma(monkeypatch)
    service = Service(DriverConfig(), port="unused")
    data = (DATA / "sim-short.bin").read_bytes()
    service.process(data[:20000])
    assert "bias_sigma_dph" not in service.status_object()
    service.control("BIAS", {"seconds": 5}, 0)
    after = service.process(data[20000:])
    done = service.last_event
    assert done["state"] == "done" and done["seconds"] >= 5.0
    taken = round(done["seconds"] / 0.1)  # the capture's samples: the first ones published after it started
    want = sum(o["drift_sigma_dph"] for o in after[:taken]) / taken
    assert done["bias_sigma_dph"] == pytest.approx(want, rel=1e-12)
    assert STUB_BASE_DPH < want < stub_value(STUB_PERIOD - 1)
    assert service.status_object()["bias_sigma_dph"] == done["bias_sigma_dph"]
    # The same capture while the model gives no sigma: the event and STATUS say nothing of one.
    monkeypatch.undo()
    stub_sigma(monkeypatch, none=True)
    plain = Service(DriverConfig(), port="unused")
    plain.process(data[:20000])
    plain.control("BIAS", {"seconds": 5}, 0)
    assert not any("drift_sigma_dph" in o for o in plain.process(data[20000:]))
    assert plain.last_event["state"] == "done" and "bias_sigma_dph" not in plain.last_event
    status = plain.status_object()
    assert status["bias_captured"] is True and "bias_sigma_dph" not in status


def test_bad_model_is_a_config_error(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("format: something\n")
    with pytest.raises(ConfigError) as info:
        Service(DriverConfig(model=str(bad)), port="unused")
    assert info.value.exit_status == 78


def test_samples_before_the_first_identity_are_kept_and_compensated():
    from fog_driver.protocol import decode_bytes

    data = (DATA / "sim-short.bin").read_bytes()
    first_identity = decode_bytes(data).identities[1].offset  # skip the start-of-run IDENTITY
    service = Service(DriverConfig(), port="unused")
    # Without the start-of-run IDENTITY, the first second's samples wait for the next one...
    assert service.process(data[32:first_identity]) == []
    assert len(service.samples_before_identity) == 10
    # ...and are compensated, in order, as soon as it arrives; then the samples after it.
    published = service.process(data[first_identity : first_identity + 32])
    assert len(published) == 10 and not service.samples_before_identity
    published += service.process(data[first_identity + 32 : first_identity + 32 + 26])
    assert len(published) == 11
    assert [o["seq"] for o in published] == list(range(published[0]["seq"], published[0]["seq"] + 11))
    assert np.all(np.isfinite([o["angle_arcsec"] for o in published]))


def test_reload_config_applies_live_settings_and_keeps_the_rest(tmp_path):
    from fog_driver.compensation.fitting.data import FitConfig
    from fog_driver.modelfiles import save_model
    from fog_driver.offline.fit import fit_model_file

    model_file, _ = fit_model_file(
        [DATA / "sim-short.bin"], kind="polynomial", config=FitConfig(warmup_s=30.0), accept_weak=True
    )
    other = save_model(tmp_path / "poly.yaml", model_file)
    service = Service(DriverConfig(listen="127.0.0.1:2999"), port="unused")
    service.process((DATA / "sim-short.bin").read_bytes()[:5000])
    angle_before = service.compensator.angle_comp_arcsec
    result = service.reload_config(
        DriverConfig(model=str(other), listen="0.0.0.0:1", adapt_reference_dph=0.0, token="a-long-token")
    )
    assert result["class"] == "RELOAD" and result["model"] == "polynomial"
    assert service.config.listen == "127.0.0.1:2999"  # needs a restart: kept
    assert service.config.token == "a-long-token" and service.config.model == str(other)
    assert service.compensator.reference_rate_dph == 0.0
    assert service.compensator.angle_comp_arcsec == angle_before  # the angle carries on
    assert service.version_object()["model"] == "polynomial"


@pytest.mark.parametrize("cut", [7000, 45000])
def test_reloading_the_same_model_mid_run_changes_nothing_published(cut):
    """?RELOAD or SIGHUP of an unchanged model: the smoothers, the reservoir's memory and the adaptation
    carry on, so every later ANGLE is what the daemon would have published without it (the review found a
    permanent 0.61" offset and 0.12 deg/h transients when the pipeline restarted)."""
    from fog_driver.modelfiles import load_model

    data = (DATA / "sim-faults.bin").read_bytes()
    steady = Service(DriverConfig(), port="unused")
    expected = steady.process(data)
    service = Service(DriverConfig(), port="unused")
    before = service.process(data[:cut])
    service.reload_model(load_model(service.config.model_path))
    after = service.process(data[cut:])
    assert len(before) + len(after) == len(expected)
    assert before + after == expected


def test_reloading_another_model_keeps_the_block_grid_and_the_smoothers(tmp_path):
    from fog_driver.compensation.fitting.data import FitConfig
    from fog_driver.offline.fit import fit_model_file

    model_file, _ = fit_model_file(
        [DATA / "sim-short.bin"], kind="polynomial", config=FitConfig(warmup_s=30.0), accept_weak=True
    )
    data = (DATA / "sim-faults.bin").read_bytes()
    service = Service(DriverConfig(), port="unused")
    service.process(data[:20000])
    features, averager = service.compensator.features.get_state(), service.compensator.averager.get_state()
    service.reload_model(model_file)
    assert service.compensator.model_file is model_file
    # everything but the substitutes' offsets, which the other model's coupling gives another meaning
    offsets = ("offset", "anchor_offset")
    now = {k: v for k, v in service.compensator.features.get_state().items() if k not in offsets}
    assert yaml.safe_dump(now) == yaml.safe_dump({k: v for k, v in features.items() if k not in offsets})  # NaN-aware
    assert service.compensator.averager.get_state() == averager


def test_a_start_that_fails_on_its_capture_directory_leaves_nothing_listening(tmp_path):
    """The capture directory is checked after the hub listens: a file there failed the start with the hub
    still serving its port (a daemon half started, in the test process or a service manager's view)."""
    import socket

    from fog_driver.errors import OutputFileError

    blocker = tmp_path / "captures"
    blocker.write_text("a file, not a directory")
    service = Service(DriverConfig(listen="127.0.0.1:0", capture_dir=str(blocker)), port="replay:///nonexistent.bin")
    with pytest.raises(OutputFileError, match="not a directory"):
        service.start()
    assert not service.hub.running
    host, port = service.hub.address
    with pytest.raises(ConnectionRefusedError):
        socket.create_connection((host, port), timeout=5).close()
