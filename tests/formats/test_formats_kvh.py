"""KVH DSP-1750 / 1760 / 1775 normal-mode decoder: real device bytes, round trips, framing, batch == streaming.

Where the layouts come from (see also ``fog_driver/formats/kvh.py``):

* Format A (36 bytes), CRC-32/MPEG-2 over the 32 bytes before it, status bits 0x77 = all valid, the
  11-byte BIT reply FE 81 00 AA with an 8-bit sum checksum: the real frames below, whose checks verify
  with an independent CRC, and the ROS ``kvh_driver`` test (``kvh_driver/test/kvhtest.cpp``, vendored in
  github.com/jtukpah/wildfire_hyperdrive_ssrr_2024); frame sizes 36/40/38/11/13 and headers also in KVH's
  own test script ``TestDspImu.pl`` (KVH Industries, 2014: ``NORMAL_FORMAT_{A,B,C}_SIZE``,
  ``FORMAT_BIT_{A,B}_SIZE``) and INSTINCT's ``KvhUartSensor.cpp`` (Univ. Stuttgart).
* Format B (40 bytes: A's fields with a u32 time tag after the accelerations): an open-source Format B
  parser (``datagram_parser.cpp``, OpenDLV-derived) and a Python Format B decoder in the keelson KVH
  connector.  No real Format B bytes were found.
* Format C (38 bytes: an f32 temperature/magnetometer word multiplexed by ``seq mod 4`` in place of the
  temperature, no time tag): the keelson KVH connector's notes, which cite OpenDLV's
  ``opendlv-device-imu-kvhp1775``.  No real Format C bytes were found; the vendor ICD itself was not
  available to check B and C against.
"""

from __future__ import annotations

import dataclasses
import math
import random
import struct
import zlib

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fog_driver.flags import SAMPLE_SENSOR_INVALID
from fog_driver.formats.common import FormatCounters
from fog_driver.formats.kvh import (
    KvhBitFrame,
    KvhDecoder,
    crc32_mpeg2,
    crc32_mpeg2_reference,
    crc32_mpeg2_rows,
    decode_kvh_batch,
    encode_kvh_bit_frame,
    encode_kvh_frame,
)

# REAL BYTES 1: a Format A frame from a DSP-1750, the input (32 bytes) and the expected CRC 0x4BFA34D8 of
# TEST(KVH_IMU_DRIVER, crc_calc) in the ROS kvh_driver package's kvh_driver/test/kvhtest.cpp (as vendored
# in github.com/jtukpah/wildfire_hyperdrive_ssrr_2024); the same 36 bytes are the "sample data" of several
# other KVH 1750 parsers and of a fake-device FIFO script.
REAL_A = bytes.fromhex("FE81FF55 37A96A6E 38586C1F B75BF862 BF803E78 BB650D28 3B0A37AC 77 3D 0028 4BFA34D8")
# REAL BYTES 2: a Format A frame (status 0x77, seq 0x47, 20 degC, accel z ~ +1 g: lying level) with its
# CRC 0x168D8B1D, from a "KVH VRV test" block of a Python IMU CRC helper found by content search of the
# public code index; the index did not name its repository, so treat this provenance as weaker than 1.
REAL_A2 = bytes.fromhex("FE81FF55 BC646C1E 3C3FF981 3B3C1E78 BC065FB7 BB2FBD79 3F7E9800 77 47 0014 168D8B1D")
# REAL BYTES 3: a BIT reply, TEST(KVH_IMU_DRIVER, crc_checksum) in the same kvhtest.cpp: header FE 81 00 AA,
# six result bytes, checksum 0x1E.
REAL_BIT = bytes.fromhex("FE8100AA 7F7F7E7B7F7F 1E")

ARCSEC_PER_RAD = 180 * 3600 / math.pi


def f32(hex4: str) -> float:
    """The big-endian IEEE single in four hex bytes, by numpy (independent of the decoder's struct path)."""
    return float(np.frombuffer(bytes.fromhex(hex4), dtype=">f4")[0])


def run(data: bytes, chunks: list[int] | None = None, **cfg) -> tuple[list, FormatCounters]:
    d = KvhDecoder(**cfg)
    events = []
    if chunks is None:
        events += d.feed(data)
    else:
        at = 0
        for n in chunks:
            events += d.feed(data[at : at + n])
            at += n
        events += d.feed(data[at:])
    events += d.close()
    c = d.counters
    assert c.bytes_in == c.bytes_in_frames + c.bytes_discarded + d.pending == len(data)
    return events, c


def sig(event) -> object:
    """An event without what depends on its place in the stream (offset, unwrapped seq)."""
    if isinstance(event, KvhBitFrame):
        return (event.kind, event.results)
    return repr(dataclasses.replace(event, seq=None, offset=0))


def key(events: list) -> list[str]:
    return [repr(e) for e in events]  # repr: NaN compares equal to NaN


# --- CRC ---------------------------------------------------------------------------------------------------


def test_crc32_mpeg2_check_value():
    # The catalogue check value of CRC-32/MPEG-2 (reveng "CRC-32/MPEG-2": check=0x0376e6e7).
    assert crc32_mpeg2(b"123456789") == 0x0376E6E7
    assert crc32_mpeg2_reference(b"123456789") == 0x0376E6E7
    rows = np.frombuffer(b"123456789" * 3, dtype=np.uint8).reshape(3, 9)
    assert crc32_mpeg2_rows(rows).tolist() == [0x0376E6E7] * 3


def test_crc_of_the_real_frames_matches_what_they_carry():
    assert crc32_mpeg2(REAL_A[:32]) == 0x4BFA34D8 == int.from_bytes(REAL_A[32:], "big")
    assert crc32_mpeg2(REAL_A2[:32]) == int.from_bytes(REAL_A2[32:], "big")
    assert sum(REAL_BIT[:10]) % 256 == REAL_BIT[10] == 0x1E


@given(st.binary(max_size=64))
@settings(max_examples=60, deadline=None)
def test_fast_crc_equals_the_table_definition(data):
    assert crc32_mpeg2(data) == crc32_mpeg2_reference(data)


# --- real bytes --------------------------------------------------------------------------------------------


def test_real_format_a_frame_decodes():
    (s,), c = run(REAL_A, format="a", rot_format="rate", rot_units="rad", rate_hz=1000)
    assert c.sample_frames == 1 and c.bytes_in_frames == 36
    assert s.seq == 0x3D and s.status == 0x77 and s.flags == frozenset()
    assert s.temps_c == {"sensor": 0x28}  # whole degC
    rates = [f32("37A96A6E"), f32("38586C1F"), f32("B75BF862")]
    assert s.rate_dph == pytest.approx([r * ARCSEC_PER_RAD for r in rates], rel=1e-12)
    assert s.dtheta_arcsec == pytest.approx([r * ARCSEC_PER_RAD / 1000 for r in rates], rel=1e-12)
    assert s.from_rate and s.host_time and s.t_s is None
    assert s.extra["accel_x_g"] == f32("BF803E78")  # about -1 g: the unit lay on its side
    assert s.extra["accel_z_g"] == f32("3B0A37AC")


def test_second_real_frame_decodes_with_one_g_on_z():
    (s,), c = run(REAL_A2, rot_format="delta", rot_units="rad", rate_hz=1000)
    assert (s.seq, s.status, s.temps_c) == (0x47, 0x77, {"sensor": 20})
    assert s.extra["accel_z_g"] == f32("3F7E9800") == pytest.approx(0.9945, abs=1e-4)
    assert s.dtheta_arcsec[0] == pytest.approx(f32("BC646C1E") * ARCSEC_PER_RAD, rel=1e-12)


@pytest.mark.parametrize("at", [4, 29, 31, 35])
def test_real_frame_with_a_corrupted_byte_is_rejected(at):
    bad = bytearray(REAL_A)
    bad[at] ^= 0x01
    events, c = run(bytes(bad))
    assert events == [] and c.crc_errors == 1 and c.bytes_discarded == 36


def test_real_bit_reply_is_an_event_of_its_own():
    events, c = run(REAL_BIT + REAL_A)
    e = events[0]
    assert e == KvhBitFrame(0, 0xAA, bytes.fromhex("7F7F7E7B7F7F"))
    assert (c.other_frames, c.sample_frames, c.bytes_in_frames) == (1, 1, 47)
    bad = bytearray(REAL_BIT)
    bad[10] ^= 0xFF
    events, c = run(bytes(bad))
    assert events == [] and c.crc_errors == 1


def test_encoded_bit_replies_match_the_real_one_and_have_the_manual_lengths():
    assert encode_kvh_bit_frame(0xAA, REAL_BIT[4:10]) == REAL_BIT
    ext = encode_kvh_bit_frame(0xAB, bytes([0x7F] * 8))
    assert len(ext) == 13
    (e,), c = run(ext)
    assert e.kind == 0xAB and e.results == bytes([0x7F] * 8) and c.other_frames == 1


# --- round trips -------------------------------------------------------------------------------------------

GYRO = (0.5, -0.25, 2.0**-10)  # exactly representable in f32
ACCEL = (0.0, -0.125, 1.0)


@pytest.mark.parametrize("fmt,length", [("a", 36), ("b", 40), ("c", 38)])
@pytest.mark.parametrize("units,k", [("deg", 3600.0), ("rad", 648000 / math.pi)])
def test_round_trip_delta(fmt, length, units, k):
    frame = encode_kvh_frame(fmt, GYRO, ACCEL, status=0x77, seq=8, temp=31, time_tag_us=123456)
    assert len(frame) == length and frame[:3] == b"\xfe\x81\xff"
    (s,), c = run(frame, format=fmt, rot_format="delta", rot_units=units, rate_hz=200)
    assert s.dtheta_arcsec == pytest.approx([g * k for g in GYRO], rel=1e-15)
    assert s.rate_dph == pytest.approx([g * k * 200 for g in GYRO], rel=1e-15)
    assert not s.from_rate and s.seq == 8
    assert (s.extra["accel_x_g"], s.extra["accel_y_g"], s.extra["accel_z_g"]) == ACCEL
    assert s.temps_c == {"sensor": 31.0}  # seq 8: C's mux slot 0 is the temperature
    if fmt == "b":
        assert s.extra["time_tag_us"] == 123456


@pytest.mark.parametrize("fmt", ["a", "b", "c"])
def test_round_trip_rate_deg_per_s(fmt):
    frame = encode_kvh_frame(fmt, (1.0, -2.0, 0.5), ACCEL, seq=4)
    (s,), _ = run(frame, rot_format="rate", rot_units="deg", rate_hz=1000)
    assert s.rate_dph == (3600.0, -7200.0, 1800.0)  # deg/s x 3600 = deg/h
    assert s.dtheta_arcsec == pytest.approx((3.6, -7.2, 1.8), rel=1e-15)  # deg/h / rate_hz = arcsec
    assert s.from_rate


def test_rate_without_rate_hz_gives_nan_increments():
    (s,), _ = run(encode_kvh_frame("a", GYRO, ACCEL), rot_format="rate")
    assert all(math.isnan(v) for v in s.dtheta_arcsec)


def test_temperature_in_hundredths():
    (s,), _ = run(encode_kvh_frame("a", GYRO, ACCEL, temp=-1234), temp_units="c_100")
    assert s.temps_c["sensor"] == pytest.approx(-12.34)


def test_format_c_mux_word_follows_the_sequence():
    frames = b"".join(encode_kvh_frame("c", GYRO, ACCEL, seq=q, temp=[25.5, 0.25, -0.5, 0.75][q]) for q in range(4))
    events, _ = run(frames)
    assert events[0].temps_c == {"sensor": 25.5}
    assert [e.extra.get(k) for e, k in zip(events[1:], ("mag_x_gauss", "mag_y_gauss", "mag_z_gauss"))] == [
        0.25,
        -0.5,
        0.75,
    ]
    assert all(e.temps_c == {} for e in events[1:])


@pytest.mark.parametrize("status,invalid", [(0x77, False), (0x07, False), (0x76, True), (0x73, True), (0x00, True)])
def test_a_cleared_gyro_valid_bit_flags_the_sample(status, invalid):
    (s,), _ = run(encode_kvh_frame("a", GYRO, ACCEL, status=status))
    assert (SAMPLE_SENSOR_INVALID in s.flags) is invalid and s.status == status


def test_format_filter_skips_the_other_headers():
    data = encode_kvh_frame("b", GYRO, ACCEL, seq=1) + encode_kvh_frame("a", GYRO, ACCEL, seq=2)
    events, c = run(data, format="a")
    assert [e.seq for e in events] == [2] and c.bytes_discarded == 40 and c.resyncs == 1


def test_seq_wraps_at_128_and_gaps_are_counted():
    data = b"".join(encode_kvh_frame("a", GYRO, ACCEL, seq=q) for q in (126, 127, 0, 3, 3))
    events, c = run(data)
    assert [e.seq for e in events] == [126, 127, 128, 131, 131]
    assert (c.seq_gaps, c.missing_frames, c.seq_repeats) == (1, 2, 1)


# --- framing -----------------------------------------------------------------------------------------------


def mixed_stream(rng: random.Random, n: int = 12) -> tuple[bytes, list[tuple[int, int]]]:
    """Frames of all kinds with garbage between some; returns the bytes and (offset, length) of each frame."""
    out = bytearray()
    spans = []
    for i in range(n):
        if rng.random() < 0.3:
            out += bytes(rng.randrange(256) for _ in range(rng.randrange(1, 9)))
        kind = rng.choice("aabcX")
        g = tuple(rng.uniform(-1e-3, 1e-3) for _ in range(3))
        if kind == "X":
            frame = encode_kvh_bit_frame(0xAA, bytes([0x7F] * 6))
        else:
            frame = encode_kvh_frame(kind, g, ACCEL, seq=i % 128, temp=rng.randrange(-40, 80), time_tag_us=i)
        spans.append((len(out), len(frame)))
        out += frame
    return bytes(out), spans


def test_every_split_point_and_byte_by_byte_give_the_same_result():
    data, spans = mixed_stream(random.Random(1))
    data = b"\x81\xfe\x81\xff" + data + b"\xfe\x81\xff\x55\x00"  # a false start and a truncated tail
    ref_events, ref_c = run(data)
    assert ref_c.sample_frames + ref_c.other_frames == len(spans) and ref_c.truncated_frames == 1
    for cut in range(len(data) + 1):
        events, c = run(data, [cut])
        assert key(events) == key(ref_events) and c == ref_c, cut
    events, c = run(data, [1] * len(data))
    assert key(events) == key(ref_events) and c == ref_c


def test_one_byte_resync_after_a_bad_crc_recovers_every_other_frame():
    frames = [encode_kvh_frame("a", GYRO, ACCEL, seq=q) for q in range(10)]
    bad = bytearray(frames[3])
    bad[20] ^= 0x40
    data = b"".join(frames[:3]) + bytes(bad) + b"".join(frames[4:])
    events, c = run(data)
    assert [e.seq for e in events] == [0, 1, 2, 4, 5, 6, 7, 8, 9]
    assert (c.crc_errors, c.bytes_discarded, c.resyncs, c.seq_gaps, c.missing_frames) == (1, 36, 1, 1, 1)


def test_a_false_header_inside_the_data():
    (false_float,) = struct.unpack(">f", b"\xfe\x81\xff\x55")
    frame = encode_kvh_frame("a", (false_float, 0.0, 0.0), ACCEL, seq=1)
    assert frame.find(b"\xfe\x81\xff\x55", 1) == 4
    events, c = run(frame + encode_kvh_frame("a", GYRO, ACCEL, seq=2))
    assert [e.seq for e in events] == [1, 2] and c.crc_errors == 0  # inside a valid frame: never looked at
    events, c = run(frame[2:] + encode_kvh_frame("a", GYRO, ACCEL, seq=2))  # joined mid-frame
    assert [e.seq for e in events] == [2] and c.crc_errors == 1 and c.resyncs == 1


@st.composite
def hostile_streams(draw):
    rng = random.Random(draw(st.integers(0, 2**32 - 1)))
    data, spans = mixed_stream(rng, draw(st.integers(0, 10)))
    data = bytearray(data)
    touched = set()
    for _ in range(draw(st.integers(0, 3))):  # bit flips
        if data:
            at = rng.randrange(len(data))
            data[at] ^= 1 << rng.randrange(8)
            touched |= {i for i, (o, n) in enumerate(spans) if o <= at < o + n}
    inserts = []  # false sample headers between frames (a false BIT header would pass its 8-bit sum 1 in 256)
    for _ in range(draw(st.integers(0, 3))):
        gap = rng.randrange(len(spans) + 1)
        inserts.append((gap, bytes.fromhex(rng.choice(["FE81FF55", "FE81FF56", "FE81FF57", "FE81", "FE"]))))
    out = bytearray(data[: spans[0][0]] if spans else b"")  # the garbage before the first frame
    kept = []
    for i, (o, n) in enumerate(spans):
        out += b"".join(b for g, b in inserts if g == i)
        if i not in touched:
            kept.append(bytes(data[o : o + n]))
        out += data[o : o + n]
        if i + 1 < len(spans):
            out += data[o + n : spans[i + 1][0]]
        else:
            out += data[o + n :]
    out += b"".join(b for g, b in inserts if g == len(spans))
    if not spans:
        out += data
    cuts = draw(st.lists(st.integers(0, 40), max_size=8))
    return bytes(out), kept, cuts


@given(hostile_streams())
@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
def test_fuzz_never_raises_accounts_exactly_and_recovers_untouched_frames(case):
    data, kept, cuts = case
    events, c = run(data, cuts)
    whole, c_whole = run(data)
    assert key(events) == key(whole) and c == c_whole
    got = iter([sig(e) for e in events])
    for frame in kept:  # every untouched frame decoded, in order (a subsequence of the events)
        (alone,) = KvhDecoder().feed(frame)
        assert any(sig(alone) == g for g in got)
    batch = decode_kvh_batch(data)
    assert key(batch.events()) == key(whole) and batch.counters == c_whole


@given(st.binary(max_size=300), st.lists(st.integers(0, 50), max_size=6))
@settings(max_examples=100, deadline=None)
def test_random_bytes_never_raise(data, cuts):
    events, c = run(data, cuts)
    batch = decode_kvh_batch(data)
    assert key(batch.events()) == key(events) and batch.counters == c


# --- batch == streaming ------------------------------------------------------------------------------------


@pytest.mark.parametrize("cfg", [{}, {"format": "a"}, {"format": "c", "rot_format": "rate", "rate_hz": 400}])
def test_batch_equals_streaming(cfg):
    rng = random.Random(7)
    data, _ = mixed_stream(rng, 200)
    data = bytearray(data)
    for at in rng.sample(range(len(data)), 15):
        data[at] ^= 0x10
    tail = encode_kvh_frame(cfg.get("format") or "a", GYRO, ACCEL)[:20]  # a frame cut off by the end
    data = REAL_A + bytes(data) + REAL_BIT + tail
    events, c = run(bytes(data), **cfg)
    batch = decode_kvh_batch(bytes(data), **cfg)
    assert batch.counters == c and key(batch.events()) == key(events)
    assert c.crc_errors > 0 and c.truncated_frames == 1


def test_batch_on_overlapping_valid_frames_matches_the_sequential_choice():
    # A valid BIT reply hidden inside a valid sample frame's float words: the streaming decoder takes the
    # sample frame and never looks inside it; the batch path must not count or take the inner one.
    bit = encode_kvh_bit_frame(0xAA, bytes(6))
    g = struct.unpack(">3f", bit + b"\x00")
    frame = encode_kvh_frame("a", g, ACCEL, seq=1)
    data = frame + frame[4:]  # the second copy starts with the BIT reply
    events, c = run(data)
    batch = decode_kvh_batch(data)
    assert batch.counters == c and key(batch.events()) == key(events)
    assert c.other_frames == 1 and c.sample_frames == 1


def test_zlib_is_not_what_the_device_uses():
    # guards against a "simplification" to zlib.crc32: the real frame's CRC is not the ISO-HDLC CRC-32
    assert zlib.crc32(REAL_A[:32]) != int.from_bytes(REAL_A[32:], "big")


def test_delta_without_rate_hz_gives_nan_rates_and_bad_settings_are_refused():
    (s,), _ = run(encode_kvh_frame("a", GYRO, ACCEL), rot_format="delta", rot_units="deg")
    assert s.dtheta_arcsec == (1800.0, -900.0, 3600 * 2.0**-10) and all(math.isnan(r) for r in s.rate_dph)
    for bad in ({"format": "d"}, {"rot_format": "angle"}, {"rot_units": "grad"}, {"temp_units": "f"}, {"rate_hz": 0}):
        with pytest.raises(ValueError):
            KvhDecoder(**bad)


def test_a_sequence_byte_above_127_is_taken_modulo_128():
    data = encode_kvh_frame("a", GYRO, ACCEL, seq=127) + encode_kvh_frame("a", GYRO, ACCEL, seq=128 + 0)
    events, c = run(data)
    assert [e.seq for e in events] == [127, 128] and c.seq_gaps == 0
    assert key(decode_kvh_batch(data).events()) == key(events)


@pytest.mark.parametrize("fmt", ["a", "b", "c"])
def test_the_vector_encoder_writes_the_bytes_of_the_frame_encoder(fmt):
    from fog_driver.formats.kvh import encode_kvh_frames

    rng = np.random.default_rng(3)
    n = 50
    gyro = rng.normal(0, 1e-5, (n, 3)).astype(np.float32)
    accel = rng.normal(0, 1, (n, 3)).astype(np.float32)
    status = rng.integers(0, 256, n)
    seq = rng.integers(0, 1000, n)
    temp = rng.integers(-4000, 8000, n) if fmt != "c" else rng.normal(30, 5, n).astype(np.float32)
    tag = rng.integers(0, 2**32, n)
    rows = encode_kvh_frames(fmt, gyro, accel, status, seq, temp, tag if fmt == "b" else None)
    for k in range(n):
        one = encode_kvh_frame(
            fmt,
            tuple(map(float, gyro[k])),
            tuple(map(float, accel[k])),
            int(status[k]),
            int(seq[k]) % 128,
            float(temp[k]) if fmt == "c" else int(temp[k]),
            time_tag_us=int(tag[k]) if fmt == "b" else 0,
        )
        assert rows[k].tobytes() == one
