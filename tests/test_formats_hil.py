"""Loopback hardware-in-the-loop for other formats: the daemon as a process on a real pty, fed the simulator's
KVH and STDBIN bytes, and a stand-in KVH device that answers the setup commands sent on open.

Readiness comes from the daemon's "listening on" line and the DEVICE object (never from sleeps).
"""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from test_daemon_hil import Client, Daemon

from fog_driver.compensation.apply import compensate_capture
from fog_driver.compensation.fit import FitConfig, fit_model_file
from fog_driver.compensation.model import load_model, save_model
from fog_driver.sim.capture import simulate_to_file
from fog_driver.sim.instrument import Simulator
from fog_driver.sim.kvh_device import FakeKvhDevice
from fog_driver.sim.profiles import load_profile
from fog_driver.sources import SampleSource, wire_settings_for
from fog_driver.stream import Sample
from fog_driver.transport import PtyPair


def daemon_config(tmp_path: Path, fmt: str, model: Path, **device) -> Path:
    path = tmp_path / "fog.yaml"
    path.write_text(yaml.safe_dump({"format": fmt, "model": str(model), "device": device}))
    return path


@pytest.mark.determinism
@pytest.mark.parametrize("fmt", ["kvh-a", "kvh-c", "ixblue-stdbin"])
def test_pty_daemon_on_another_format_publishes_every_sample_and_replays_bit_identically(fmt, tmp_path):
    sim = Simulator(load_profile("short-test"), rate_hz=10, seed=8, wire_format=fmt)
    capture = simulate_to_file(sim, tmp_path / "sim.bin", duration_s=900).capture
    wire = wire_settings_for(capture)
    # a model fitted on this format's temperature channels (protocol v1's shipped model has other ones)
    fitted, _ = fit_model_file([capture], kind="polynomial", config=FitConfig(warmup_s=30.0), accept_weak=True)
    model = save_model(tmp_path / "model.yaml", fitted)
    device = {k: v for k, v in wire.sidecar_fields()["wire_settings"].items() if k != "axis"}
    config = daemon_config(tmp_path, fmt, model, **device)
    data = capture.read_bytes()
    n_samples = sum(isinstance(s, Sample) for s in SampleSource(wire).feed(data))
    with PtyPair() as pty:
        daemon = Daemon(tmp_path, pty.slave_path, "--config", str(config), "--model", str(model))
        try:
            client = Client(daemon.address)
            client.send('?WATCH={"enable":true};')
            client.wait_device("activated")
            pty.write(data)
            received = [client.next("ANGLE") for _ in range(n_samples)]
            status = client.next("STATUS")
            while status["frames"] < n_samples:
                status = client.next("STATUS")
            assert status["crc_errors"] == 0
            assert daemon.terminate() == 0
        finally:
            daemon.kill()
    assert [o["seq"] for o in received] == list(range(received[0]["seq"], received[0]["seq"] + n_samples))
    channels = {"sensor"} if fmt.startswith("kvh") else {"fog", "accelerometer", "board"}
    assert set(received[-1]["temps_c"]) == channels
    assert daemon.raw_capture() == data  # nothing lost
    sidecars = sorted(daemon.capture_dir.glob("*.bin.yaml"))
    doc = yaml.safe_load(sidecars[0].read_text())
    assert doc["wire_format"] == fmt and doc["wire_settings"]["rate_hz"] == 10
    # replay determinism: `compensate` on the daemon's own capture (its sidecar says the format) gives the same
    own = sorted(daemon.capture_dir.glob("*.bin"))[0]
    offline = {}
    for _, cols in compensate_capture(own, load_model(model)):
        offline.update(zip(cols.seq.tolist(), cols.angle_comp_arcsec.tolist()))
    assert [o["angle_arcsec"] for o in received] == [offline[o["seq"]] for o in received]


def test_setup_commands_reach_a_kvh_device_on_open_and_its_frames_are_published(tmp_path):
    sim = Simulator(load_profile("short-test"), rate_hz=10, seed=2, wire_format="kvh-a")
    capture = simulate_to_file(sim, tmp_path / "fit.bin", duration_s=900).capture
    fitted, _ = fit_model_file([capture], kind="polynomial", config=FitConfig(warmup_s=30.0), accept_weak=True)
    model = save_model(tmp_path / "kvh.yaml", fitted)
    config = daemon_config(tmp_path, "kvh-a", model, rate_hz=100, rot_units="rad", temp_units="c_100",
                           setup=["=TEMPUNITS,C_100", "=DR,100"])  # fmt: skip
    with PtyPair() as pty, FakeKvhDevice(pty, rate_hz=100) as kvh:
        daemon = Daemon(tmp_path, pty.slave_path, "--config", str(config))
        try:
            client = Client(daemon.address)
            client.send('?WATCH={"enable":true};')
            client.wait_device("activated")  # reported once the setup has been answered
            handled = [kvh.commands.get(timeout=30) for _ in range(4)]
            assert [c.upper() for c in handled] == ["=CONFIG,1", "=TEMPUNITS,C_100", "=DR,100", "=CONFIG,0"]
            angles = [client.next("ANGLE") for _ in range(50)]
            assert all(a["temps_c"] == {"sensor": 25.0} for a in angles)  # the C_100 word the device now sends
            assert daemon.terminate() == 0
        finally:
            daemon.kill()
    sidecar = yaml.safe_load(sorted(daemon.capture_dir.glob("*.bin.yaml"))[0].read_text())
    events = [e for e in sidecar.get("events", []) if e.get("event") == "device_setup"]
    assert events and events[0]["sent"] == ["=CONFIG,1", "=TEMPUNITS,C_100", "=DR,100", "=CONFIG,0"]
