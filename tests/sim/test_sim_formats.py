"""The simulator speaks the KVH normal-mode formats: the bytes decode (with fog_driver's KVH decoder, which
real device frames test) to the simulator's own truth."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from fog_driver.formats.kvh import KvhDecoder
from fog_driver.formats.registry import sniff
from fog_driver.lab.profiles import load_profile
from fog_driver.samples.captures import read_provenance
from fog_driver.sim.faults import parse_fault_spec
from fog_driver.sim.instrument import Simulator


def decode(data: bytes, fmt: str, rate_hz: int):
    decoder = KvhDecoder(format=fmt, rot_format="delta", rot_units="rad", temp_units="c_100", rate_hz=rate_hz)
    return decoder.feed(data) + decoder.close(), decoder.counters


@pytest.mark.parametrize("fmt", ["a", "b", "c"])
def test_kvh_frames_decode_to_the_simulators_truth(fmt):
    sim = Simulator(load_profile("short-test"), rate_hz=200, seed=4, wire_format=f"kvh-{fmt}")
    block, data = sim.stream(3000)
    samples, counters = decode(data, fmt, 200)
    assert sniff(data).name == f"kvh-{fmt}"
    assert counters.sample_frames == 3000 and counters.bytes_discarded == 0 and counters.crc_errors == 0
    assert [s.seq for s in samples] == list(range(3000))  # 7-bit counter unwrapped
    true_arcsec = sum(block.components_arcsec.values())  # the frame's increment before any quantization
    z = np.array([s.dtheta_arcsec[2] for s in samples])
    np.testing.assert_allclose(z, true_arcsec, rtol=2e-7, atol=1e-9)  # float32 rad on the wire
    assert all(s.dtheta_arcsec[:2] == (0.0, 0.0) and not s.flags for s in samples)
    housing_c = block.t_raw[:, 2] / 256.0
    if fmt == "c":  # the multiplexed word: the temperature every fourth frame
        temps = np.array([s.temps_c.get("sensor", np.nan) for s in samples[::4]])
        np.testing.assert_allclose(temps, housing_c[::4], atol=0.005 + 1e-6)
    else:
        np.testing.assert_allclose([s.temps_c["sensor"] for s in samples], housing_c, atol=0.005 + 1e-9)


def test_dropped_kvh_frames_are_counted_from_the_sequence():
    sim = Simulator(
        load_profile("short-test"), rate_hz=100, seed=5, wire_format="kvh-a", faults=parse_fault_spec("drop=0.01")
    )
    block, data = sim.stream(5000)
    samples, counters = decode(data, "a", 100)
    assert counters.crc_errors == 0 and counters.sample_frames == len(samples) == len(data) // 36
    assert counters.missing_frames == 5000 - len(samples) > 0


def test_protocol_v1_is_the_default_and_stays_what_it_was():
    a = Simulator(load_profile("short-test"), rate_hz=100, seed=6)
    b = Simulator(load_profile("short-test"), rate_hz=100, seed=6, wire_format="fog-v1")
    assert a.stream(500)[1] == b.stream(500)[1]
    with pytest.raises(ValueError, match="the simulator speaks fog-v1, kvh-a, kvh-b, kvh-c, ixblue-stdbin, not 'nmea'"):
        Simulator(load_profile("short-test"), wire_format="nmea")


def test_simulate_format_records_it_and_the_other_commands_say_what_the_capture_is(tmp_path):
    capture = tmp_path / "kvh.bin"
    run = [sys.executable, "-m", "fog_driver"]
    done = subprocess.run(
        run
        + [
            "simulate",
            "--profile",
            "short-test",
            "--rate-hz",
            "10",
            "--duration",
            "120",
            "--format",
            "kvh-c",
            "--out",
            str(capture),
        ],
        capture_output=True,
        text=True,
    )
    assert done.returncode == 0, done.stderr
    sidecar = read_provenance(capture)
    assert sidecar["wire_format"] == "kvh-c" and sidecar["wire_settings"]["rot_units"] == "rad"
    inspected = subprocess.run(run + ["inspect", str(capture)], capture_output=True, text=True)
    assert inspected.returncode == 0 and "format        kvh-c: KVH" in inspected.stdout
    model = Path(__file__).resolve().parents[2] / "fog_driver" / "data" / "models" / "default.yaml"
    refused = subprocess.run(
        run + ["compensate", str(capture), "--model", str(model), "--out", str(tmp_path / "c.csv")],
        capture_output=True,
        text=True,
    )
    # the shipped model was fitted on protocol v1's three thermometers; a KVH unit has one: refused on one line
    assert refused.returncode == 64
    assert refused.stderr.strip().endswith(
        "kvh.bin's kvh-c frames carry sensor: it cannot be applied (fit a model on this instrument's captures)"
    )
