"""Loopback hardware-in-the-loop for other formats: the daemon as a process on a real pty, fed the simulator's
KVH and STDBIN bytes, and a stand-in KVH device that answers the setup commands sent on open.

Readiness comes from the daemon's "listening on" line and the DEVICE object (never from sleeps).
"""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from daemon_hil import Client, Daemon

from fog_driver.compensation.fitting.data import FitConfig
from fog_driver.lab.profiles import load_profile
from fog_driver.modelfiles import load_model, save_model
from fog_driver.offline.compensate import compensate_capture
from fog_driver.offline.fit import fit_model_file
from fog_driver.samples.sources import SampleSource, wire_settings_for
from fog_driver.samples.stream import Sample
from fog_driver.sim.capture import simulate_to_file
from fog_driver.sim.instrument import Simulator
from fog_driver.sim.kvh_device import FakeKvhDevice
from fog_driver.transport import PtyPair

pytestmark = pytest.mark.serial  # pty timing: run apart from the suite's parallel part


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
            # the WATCH is answered before a byte is written: a command is handled off the loop, and a sample
            # published before it took effect would never reach this client (a busy machine showed it)
            assert client.next("WATCH")["enable"] is True
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
    config = daemon_config(
        tmp_path,
        "kvh-a",
        model,
        rate_hz=100,
        rot_units="rad",
        temp_units="c_100",
        setup=["=TEMPUNITS,C_100", "=DR,100"],
    )
    with PtyPair() as pty, FakeKvhDevice(pty, rate_hz=100) as kvh:
        daemon = Daemon(tmp_path, pty.slave_path, "--config", str(config))
        try:
            client = Client(daemon.address)
            client.send('?WATCH={"enable":true};')
            client.wait_device("activated")  # reported once the setup has been answered
            handled = [kvh.commands.get(timeout=30) for _ in range(4)]
            assert [c.upper() for c in handled] == ["=CONFIG,1", "=TEMPUNITS,C_100", "=DR,100", "=CONFIG,0"]
            # The frames the device sent before the setup (whole degC) are captured, not decoded: every
            # published temperature is the C_100 word the device sends since.
            angles = [client.next("ANGLE") for _ in range(50)]
            assert [a["temps_c"] for a in angles] == [{"sensor": 25.0}] * 50, angles[:3]
            assert daemon.terminate() == 0
        finally:
            daemon.kill()
    own = sorted(daemon.capture_dir.glob("*.bin"))[0]
    sidecar = yaml.safe_load(Path(str(own) + ".yaml").read_text())
    events = [e for e in sidecar.get("events", []) if e.get("event") == "device_setup"]
    assert events and events[0]["sent"] == ["=CONFIG,1", "=TEMPUNITS,C_100", "=DR,100", "=CONFIG,0"]
    assert events[0]["bytes_not_decoded"] > 36  # frames sent before the setup, and the replies
    assert b"CONFIG,1" in own.read_bytes()  # nothing lost: the raw capture holds them
    # offline, the same bytes are skipped: `compensate` on the daemon's capture gives the published angles
    offline = {}
    for _, cols in compensate_capture(own, load_model(model)):
        offline.update(zip(cols.seq.tolist(), cols.angle_comp_arcsec.tolist()))
    assert [a["angle_arcsec"] for a in angles] == [offline[a["seq"]] for a in angles]


def test_record_sends_the_setup_and_its_capture_reads_as_the_daemon_reads_it(tmp_path):
    from fog_driver.cli import main

    config = daemon_config(
        tmp_path, "kvh-a", tmp_path / "unused.yaml", rate_hz=100, temp_units="c_100", setup=["=TEMPUNITS,C_100"]
    )
    out = tmp_path / "rec.bin"
    with PtyPair() as pty, FakeKvhDevice(pty, rate_hz=100) as kvh:
        # the device sends frames in whole degC until the setup changes it
        assert main(["record", pty.slave_path, "--config", str(config), "--duration", "1.5", "--out", str(out)]) == 0
        assert [c.upper() for c in [kvh.commands.get(timeout=5) for _ in range(3)]] == [
            "=CONFIG,1",
            "=TEMPUNITS,C_100",
            "=CONFIG,0",
        ]
    doc = yaml.safe_load((tmp_path / "rec.bin.yaml").read_text())
    (event,) = doc["events"]
    assert event["event"] == "device_setup" and event["at_byte"] == 0 and event["bytes_not_decoded"] > 0
    wire = wire_settings_for(out)
    from fog_driver.samples.sources import CaptureReader

    temps = [t for p in CaptureReader(out, wire).parts() for t in p.samples.t_top_c.tolist()]
    assert len(temps) > 50 and set(temps) == {25.0}  # none of the frames before the setup read as 0.25 degC
