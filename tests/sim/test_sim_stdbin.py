"""The simulator speaks iXblue STDBIN: its telegrams decode (with fog_driver's STDBIN decoder, which iXblue's
own recorded telegrams test) to the simulator's own truth, for any batching, with every link fault."""

from __future__ import annotations

import struct
import subprocess
import sys

import numpy as np
import pytest

from fog_driver.formats.common import ImuSample
from fog_driver.formats.ixblue import StdbinDecoder, encode_stdbin
from fog_driver.formats.registry import sniff
from fog_driver.lab.profiles import load_profile
from fog_driver.samples.captures import read_provenance
from fog_driver.sim.faults import parse_fault_spec
from fog_driver.sim.instrument import STDBIN_VERSION, Simulator
from fog_driver.sim.serve import required_baud, serve

TELEGRAM_LEN = 67  # v5 header 27 + attitude 12 + rotation rate 12 + temperatures 12 + checksum 4


def stdbin_sim(rate_hz: int = 100, seed: int = 4, faults: str = "none", profile: str = "short-test") -> Simulator:
    return Simulator(
        load_profile(profile), rate_hz=rate_hz, seed=seed, wire_format="ixblue-stdbin", faults=parse_fault_spec(faults)
    )


def decode(data: bytes, rate_hz: int, splits: tuple[int, ...] = ()) -> tuple[list[ImuSample], object]:
    """Decode ``data`` fed in pieces cut at ``splits``."""
    decoder = StdbinDecoder(rate_hz=rate_hz)
    events = []
    for lo, hi in zip((0, *splits), (*splits, len(data))):
        events += decoder.feed(data[lo:hi])
    events += decoder.close()
    return [e for e in events if isinstance(e, ImuSample)], decoder.counters


def truth_arcsec(block) -> np.ndarray:
    return sum(block.components_arcsec.values())  # the frame's increment before any quantization


def test_stdbin_telegrams_decode_to_the_simulators_truth():
    sim = stdbin_sim(rate_hz=200)
    block, data = sim.stream(3000)
    samples, counters = decode(data, 200)
    assert sniff(data).name == "ixblue-stdbin"
    assert len(data) == 3000 * TELEGRAM_LEN and data[:3] == b"IX" + bytes((STDBIN_VERSION,))
    assert counters.sample_frames == 3000 and counters.bytes_discarded == 0 and counters.crc_errors == 0
    assert counters.blocks_skipped == 0 and counters.unknown_blocks == 0
    # The counter is the frame's sequence on 32 bits: protocol v1's seq in its low 16 bits, no gaps.
    seq = np.array([s.seq for s in samples])
    assert seq[0] == sim.seq0 and np.array_equal(np.diff(seq), np.ones(2999)) and counters.seq_gaps == 0
    assert np.array_equal(seq % 65536, block.seq)
    # Device time: the t_us clock in 100-us steps, one period apart.
    t_s = np.array([s.t_s for s in samples])
    assert t_s[0] == pytest.approx(sim.t_us0 // 100 * 1e-4, abs=1e-9)
    np.testing.assert_allclose(np.diff(t_s), 1 / 200, atol=1e-9)
    # Rate (deg/s float32 on the wire) x the validity-time step = the frame's increment.
    z = np.array([s.dtheta_arcsec[2] for s in samples])
    np.testing.assert_allclose(z, truth_arcsec(block), rtol=2e-7, atol=1e-9)
    np.testing.assert_allclose([s.rate_dph[2] for s in samples], truth_arcsec(block) * 200, rtol=2e-7, atol=1e-7)
    assert all(s.dtheta_arcsec[:2] == (0.0, 0.0) and s.rate_dph[:2] == (0.0, 0.0) and not s.flags for s in samples)
    # Temperatures: fog = ring top, accelerometer = ring bottom, board = housing, exact (1/256 degC in float32).
    for channel, column in (("fog", 0), ("accelerometer", 1), ("board", 2)):
        assert np.array_equal([s.temps_c[channel] for s in samples], block.t_raw[:, column] / 256.0), channel
    assert len({tuple(s.temps_c.values()) for s in samples[:200]}) > 1  # the readings move


def test_the_vectorized_telegrams_are_encode_stdbin_byte_for_byte():
    sim = stdbin_sim(rate_hz=100, faults="thermo=2:0.5")  # faulted (NaN) temperatures included
    sim.frames(100)
    block = sim.frames(400)
    rows = sim.encode(block)
    assert rows.shape == (400, TELEGRAM_LEN) and rows.dtype == np.uint8
    assert (block.t_raw == -32768).any()
    for i in range(400):
        k = block.k0 + i
        time_100us = sim.stdbin_time_100us(k)
        step_s = (time_100us - sim.stdbin_time_100us(k - 1)) * 1e-4
        temps = [np.nan if v == -32768 else v / 256.0 for v in block.t_raw[i].tolist()]
        expected = encode_stdbin(
            STDBIN_VERSION,
            counter=sim.seq0 + k,
            validity_time_100us=int(time_100us),
            attitude_deg=(float(block.angle_deg[i]) % 360.0, 0.0, 0.0),
            rotation_rate_dps=(0.0, 0.0, float(truth_arcsec(block)[i]) / 3600.0 / step_s),
            temperatures_c=tuple(temps),
        )
        assert rows[i].tobytes() == expected, i


def test_counter_and_validity_time_wrap_as_the_format_wraps():
    sim = stdbin_sim(rate_hz=100)
    # A run started 5 s before the validity time's 2^32 x 100 us wrap and 10 s before the counter's 2^32.
    sim.t_us0 = (2**32 - 50_000) * 100 + 37
    sim.seq0 = 2**32 - 1000
    block, data = sim.stream(2000)
    raw_time = np.array([struct.unpack_from(">I", data, i * TELEGRAM_LEN + 19)[0] for i in range(2000)])
    raw_counter = np.array([struct.unpack_from(">I", data, i * TELEGRAM_LEN + 23)[0] for i in range(2000)])
    assert raw_time[499] == 2**32 - 1 - 99 and raw_time[500] == 0  # wrapped on the wire
    assert raw_counter[999] == 2**32 - 1 and raw_counter[1000] == 0
    samples, counters = decode(data, 100)
    assert counters.time_wraps == 1 and counters.seq_gaps == 0 and counters.sample_frames == 2000
    assert [s.seq for s in samples] == list(range(2**32 - 1000, 2**32 + 1000))  # unwrapped
    np.testing.assert_allclose(np.diff([s.t_s for s in samples]), 0.01, atol=1e-9)
    np.testing.assert_allclose([s.dtheta_arcsec[2] for s in samples], truth_arcsec(block), rtol=2e-7, atol=1e-9)


def test_a_rate_10_khz_is_no_multiple_of_carries_the_uneven_time_steps_exactly():
    sim = stdbin_sim(rate_hz=30)
    block, data = sim.stream(600)
    samples, _ = decode(data, 30)
    steps = np.round(np.diff([s.t_s for s in samples]) * 1e4)
    assert set(steps.tolist()) == {333.0, 334.0}
    # From the second telegram on the decoder multiplies by the step the rate was divided by.
    np.testing.assert_allclose([s.dtheta_arcsec[2] for s in samples[1:]], truth_arcsec(block)[1:], rtol=2e-7, atol=1e-9)


def test_heading_is_the_turntable_angle():
    sim = stdbin_sim(rate_hz=10, profile="positioning")
    sim.frames(14_900)  # 1490 s: the positioning sequence (1500 s .. 2198 s) starts
    block, data = sim.stream(7100)
    samples, _ = decode(data, 10)
    heading = np.array([s.extra["heading_deg"] for s in samples])
    np.testing.assert_allclose(heading, np.mod(block.angle_deg, 360.0).astype(np.float32), rtol=0, atol=0)
    values, counts = np.unique(heading, return_counts=True)
    assert np.allclose(values[counts >= 500], np.arange(0, 360, 36), atol=1e-3)  # 60-s dwells after 36-deg moves
    assert heading[-1] == 0.0  # a full turn
    assert all(s.extra["roll_deg"] == s.extra["pitch_deg"] == 0.0 for s in samples)


@pytest.mark.parametrize("faults", ["none", "drop=0.01,garbage=0.5,flip=1e-5,thermo=0.5:1,disconnect=7:1.5"])
def test_any_batching_gives_the_same_bytes_and_any_split_the_same_samples(faults):
    whole = stdbin_sim(faults=faults).stream(2500)[1]
    sim = stdbin_sim(faults=faults)
    pieces = b"".join(sim.stream(n)[1] for n in (1, 7, 99, 100, 393, 1, 1000, 899))
    assert pieces == whole
    reference, reference_counters = decode(whole, 100)
    for splits in ((1,), (33, 34, 35), (TELEGRAM_LEN * 500 + 19, TELEGRAM_LEN * 1200 + 66, len(whole) - 1)):
        samples, counters = decode(whole, 100, splits)
        assert list(map(repr, samples)) == list(map(repr, reference)), splits  # repr: NaN temperatures compare
        assert counters == reference_counters, splits


def test_dropped_telegrams_are_counter_gaps():
    sim = stdbin_sim(faults="drop=0.01")
    block, data = sim.stream(5000)
    samples, counters = decode(data, 100)
    assert counters.crc_errors == 0 and counters.sample_frames == len(samples) == len(data) // TELEGRAM_LEN
    assert counters.missing_frames == 5000 - len(samples) > 0 and counters.seq_gaps > 0
    k = np.array([s.seq for s in samples]) - sim.seq0
    # Each sample is its frame's: the rate is the frame's, times the step from the last telegram received.
    np.testing.assert_allclose([s.rate_dph[2] for s in samples], truth_arcsec(block)[k] * 100, rtol=2e-7, atol=1e-7)


def test_link_faults_cost_telegrams_never_wrong_values():
    sim = stdbin_sim(faults="garbage=2,flip=2e-5,disconnect=10:2+30:0.5")
    block, data = sim.stream(5000)
    samples, counters = decode(data, 100)
    assert counters.crc_errors > 0 and counters.bytes_discarded > 0 and counters.resyncs > 0
    assert 4000 < len(samples) < 5000 - 250  # the 2.5 s cut at least
    k = np.array([s.seq for s in samples]) - sim.seq0
    assert not ((k >= 1000) & (k < 1200)).any() and not ((k >= 3000) & (k < 3050)).any()
    np.testing.assert_allclose([s.rate_dph[2] for s in samples], truth_arcsec(block)[k] * 100, rtol=2e-7, atol=1e-7)
    assert np.array_equal([s.temps_c["board"] for s in samples], block.t_raw[k, 2] / 256.0)


def test_garbage_bursts_carry_false_stdbin_headers_and_cost_nothing():
    sim = stdbin_sim(faults="garbage=5")
    block, data = sim.stream(3000)
    samples, counters = decode(data, 100)
    # 'IX', a known version: the decoder reads such a header, and the checksum or the size refuses it (a size
    # that the blocks do not give, or, with a block of unknown size, one above MAX_UNVERIFIED_LEN)
    assert counters.crc_errors > 5 and counters.length_errors > 100 and counters.bytes_discarded > 0
    assert [s.seq for s in samples] == list(range(sim.seq0, sim.seq0 + 3000))
    np.testing.assert_allclose([s.dtheta_arcsec[2] for s in samples], truth_arcsec(block), rtol=2e-7, atol=1e-9)


def test_a_faulted_thermometer_reads_nan():
    sim = stdbin_sim(faults="thermo=0.5:1")
    block, data = sim.stream(3000)
    samples, _ = decode(data, 100)
    temps = np.array([[s.temps_c[c] for c in ("fog", "accelerometer", "board")] for s in samples])
    invalid = block.t_raw == -32768
    assert invalid.any() and np.array_equal(np.isnan(temps), invalid)
    assert np.array_equal(temps[~invalid], block.t_raw[~invalid] / 256.0)


def test_serve_streams_the_same_telegrams():
    out: list[bytes] = []
    serve(stdbin_sim(faults="drop=0.01"), out.append, duration_s=3.0, speed=1000.0)
    assert b"".join(out) == stdbin_sim(faults="drop=0.01").stream(300)[1]


def test_the_line_speed_a_served_stream_needs_counts_its_telegrams():
    sim = stdbin_sim(rate_hz=1000)
    assert sim.frame_len_bytes == TELEGRAM_LEN == len(sim.stream(1)[1])
    assert required_baud(sim) == 1000 * TELEGRAM_LEN * 10  # 8N1, no IDENTITY frames
    for fmt, frame_len in (("kvh-a", 36), ("kvh-b", 40), ("kvh-c", 38)):
        kvh = Simulator(load_profile("short-test"), rate_hz=1000, wire_format=fmt)
        assert kvh.frame_len_bytes == frame_len == len(kvh.stream(1)[1]) and required_baud(kvh) == frame_len * 10_000
    v1 = Simulator(load_profile("short-test"), rate_hz=1000)
    assert required_baud(v1, speed=2.0) == (1000 * 26 + 32) * 10 * 2


def test_stdbin_refuses_a_rate_its_time_cannot_stamp():
    with pytest.raises(ValueError, match="at most 10000 telegrams/s"):
        stdbin_sim(rate_hz=10_001)
    stdbin_sim(rate_hz=10_000)


def test_simulate_format_ixblue_stdbin_writes_a_capture_inspect_reads(tmp_path):
    capture = tmp_path / "x.bin"
    run = [sys.executable, "-m", "fog_driver"]
    done = subprocess.run(
        run
        + [
            "simulate",
            "--profile",
            "short-test",
            "--format",
            "ixblue-stdbin",
            "--duration",
            "5",
            "--out",
            str(capture),
        ],
        capture_output=True,
        text=True,
    )
    assert done.returncode == 0, done.stderr
    assert capture.stat().st_size == 500 * TELEGRAM_LEN
    sidecar = read_provenance(capture)
    assert sidecar["wire_format"] == "ixblue-stdbin"
    assert sidecar["wire_settings"] == {
        "rate_hz": 100,
        "version": 5,
        "temperature_channels": {"fog": "top", "accelerometer": "bottom", "board": "housing"},
    }
    inspected = subprocess.run(run + ["inspect", str(capture)], capture_output=True, text=True)
    assert inspected.returncode == 0, inspected.stderr
    assert "format        ixblue-stdbin: iXblue" in inspected.stdout
    assert "frames        500 samples, 0 other" in inspected.stdout and "temp fog" in inspected.stdout
