"""The iXblue STDBIN decoder (``fog_driver.formats.ixblue``): real telegrams, round trips, resync, fuzzing.

Real bytes: ``tests/data/ixblue/`` (provenance in its README): captures from iXblue's open-source
``ixblue_stdbin_decoder`` test datasets and ``ixblue_ins_stdbin_driver`` pcapng test captures.  The expected
numbers below are the ones the source's own test asserts (``test/stdbin_decoder.test.cc``), not numbers
computed with this decoder.
"""

from __future__ import annotations

import math
import os
import struct
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fog_driver.flags import SAMPLE_STARTUP
from fog_driver.formats.common import ImuSample
from fog_driver.formats.ixblue import (
    EXTNAV_BLOCK_LEN,
    MAX_TELEGRAM_LEN,
    MAX_UNVERIFIED_LEN,
    NAV_BLOCK_LEN,
    StdbinAnswer,
    StdbinDecoder,
    encode_stdbin,
    encode_stdbin_answer,
)

DATA = Path(__file__).parents[1] / "data" / "ixblue"


def _read(name: str) -> bytes:
    return (DATA / name).read_bytes()


def _pcap_udp_payloads(name: str) -> list[bytes]:
    """The UDP payloads of a pcapng capture (Ethernet / IPv4 / UDP, link type 1): enhanced packet blocks
    (type 6), payload after 14 + 20 + 8 header bytes."""
    raw = _read(name)
    payloads = []
    pos = 0
    while pos + 12 <= len(raw):
        block_type, block_len = struct.unpack_from("<II", raw, pos)
        if block_type == 6:
            captured = struct.unpack_from("<I", raw, pos + 20)[0]
            packet = raw[pos + 28 : pos + 28 + captured]
            assert packet[12:14] == b"\x08\x00" and packet[23] == 17  # IPv4, UDP
            payloads.append(packet[42:])
        pos += block_len
    return payloads


def _decode(data: bytes, chunks: list[int] | None = None, rate_hz: float | None = None):
    """Feed ``data`` split at ``chunks`` (cut offsets); return (events, counters dict, decoder)."""
    d = StdbinDecoder(rate_hz=rate_hz)
    events = []
    cuts = [0, *(chunks or []), len(data)]
    for a, b in zip(cuts, cuts[1:]):
        events += d.feed(data[a:b])
        c = d.counters
        assert c.bytes_in == c.bytes_in_frames + c.bytes_discarded + d.pending
    events += d.close()
    c = d.counters
    assert d.pending == 0 and c.bytes_in == c.bytes_in_frames + c.bytes_discarded
    return events, c.as_dict(), d


def _same_as_whole(data: bytes, chunks: list[int]) -> None:
    whole_events, whole_counters, _ = _decode(data)
    events, counters, _ = _decode(data, chunks)
    assert repr(events) == repr(whole_events)  # repr: NaN increments compare equal
    assert counters == whole_counters


def _approx(x: float) -> object:
    return pytest.approx(x, rel=1e-6, abs=1e-12)  # the source asserts EXPECT_FLOAT_EQ (4 float32 ulps)


def _ins_words(status: int) -> tuple[int, int, int, int]:
    return tuple((status >> (32 * k)) & 0xFFFFFFFF for k in range(4))  # type: ignore[return-value]


# Expected values: ixblue/ixblue_stdbin_decoder test/stdbin_decoder.test.cc, the tests named per entry.
REAL_CASES = {
    # TEST(StdBinDecoder, WeCanParseV2Protocol)
    "log_STDBIN_V2.log": dict(
        attitude=(209.982, 0.016, 0.206),
        rate_dps=(0.001287996, 0.0010229985, 0.0026694948),
        accel=(-0.00034000012, 0.000035000077, 0.000055000033),
        sensor=(0, 0),
        ins=(0x12, 0x30000, 0x4000000, 0x200),
        temps=(26.158884, 26.158884, 158.65643),
    ),
    # TEST(StdBinDecoder, WeCanParseV3Protocol) (asserts on the first telegram of the log)
    "log_STDBIN_V3.log": dict(
        attitude=(0.0, 0.809, -0.521),
        rate_dps=(-0.0013599998, -0.0021450005, -0.000024999996),
        accel=(-0.0004, -0.00059999997, -0.07685006),
        sensor=(0x0, 0x100),
        ins=(0x81013112, 0x1003011, 0x4000100, 0x200),
        temps=(28.700487, 37.533264, 47.899994),
    ),
    # TEST(StdBinDecoder, WeCanParseV4Protocol)
    "log_STDBIN_V4.log": dict(
        attitude=(357.428, -0.04, 0.178),
        rate_dps=(-0.0061404924, -0.00091849366, 0.0024884976),
        accel=(0.00004, 0.00040999975, 0.0007599999),
        sensor=(0, 0),
        ins=(0x12, 0x30000, 0x4000000, 0x200),
        temps=(25.993078, 25.993078, 158.65643),
    ),
    # TEST(StdBinDecoder, WeCanParseV5Protocol)
    "log_STDBIN_V5.log": dict(
        attitude=(357.404, -0.04, 0.178),
        rate_dps=(-0.006139992, -0.0009184938, 0.0024874974),
        accel=None,
        sensor=(0, 0),
        ins=(0x12, 0x30000, 0x4000000, 0x200),
        temps=(25.993126, 25.993126, 158.65643),
    ),
}
ALL_LOGS = [*REAL_CASES, "log_STDBIN_V3_old.log"]
PCAPS = ["stdbin_V2_2Hz.pcapng", "stdbin_V3_2Hz.pcapng", "stdbin_V5_2Hz.pcapng"]


@pytest.mark.parametrize("name", list(REAL_CASES))
def test_real_telegram_decodes_to_the_values_the_vendor_test_asserts(name):
    data = _read(name)
    expected = REAL_CASES[name]
    events, counters, _ = _decode(data, rate_hz=2.0)
    assert counters["crc_errors"] == counters["length_errors"] == counters["bytes_discarded"] == 0
    s = events[0]
    assert (s.extra["heading_deg"], s.extra["roll_deg"], s.extra["pitch_deg"]) == tuple(
        map(_approx, expected["attitude"])
    )
    assert s.from_rate and not s.host_time
    assert s.rate_dph == tuple(_approx(r * 3600.0) for r in expected["rate_dps"])
    # no previous telegram: the increment is rate x 1 / rate_hz
    assert s.dtheta_arcsec == tuple(_approx(r * 3600.0 * 0.5) for r in expected["rate_dps"])
    if expected["accel"] is not None:
        assert (s.extra["accel_x_mps2"], s.extra["accel_y_mps2"], s.extra["accel_z_mps2"]) == tuple(
            map(_approx, expected["accel"])
        )
    assert (s.extra["sensor_status_1"], s.extra["sensor_status_2"]) == expected["sensor"]
    assert _ins_words(s.status) == expected["ins"]
    # INS algorithm status word 1 bit 1 is ALIGNMENT (ixblue_stdbin_decoder INSAlgorithmStatus::Status1)
    assert (SAMPLE_STARTUP in s.flags) == bool(expected["ins"][0] >> 1 & 1)
    assert s.temps_c == {
        "fog": _approx(expected["temps"][0]),
        "accelerometer": _approx(expected["temps"][1]),
        "board": _approx(expected["temps"][2]),
    }
    # header time and counter, at the offsets the vendor's own test vectors annotate (MinimalV2NavFrame.h:
    # validity time then counter, the last 8 header bytes: 21 (v2), 25 (v3), 27 (v4, v5) header bytes)
    header_len = {2: 21, 3: 25, 4: 27, 5: 27}[data[2]]
    time_raw, counter = struct.unpack(">II", data[header_len - 8 : header_len])
    assert s.t_s == pytest.approx(time_raw * 1e-4) and s.seq == counter
    if data[2] >= 3:  # the tests assert rawRotationRateVesselFrame 0, 0, 0 (extended navigation, v3+)
        assert (s.extra["raw_rate_x_dph"], s.extra["raw_rate_y_dph"], s.extra["raw_rate_z_dph"]) == (0, 0, 0)
    else:
        assert "raw_rate_x_dph" not in s.extra


def test_the_vendor_v3_log_is_17_consecutive_telegrams():
    events, counters, _ = _decode(_read("log_STDBIN_V3.log"))
    assert counters["sample_frames"] == 17 and counters["bytes_discarded"] == 0
    assert counters["seq_gaps"] == counters["seq_repeats"] == 0
    assert [e.seq for e in events] == list(range(events[0].seq, events[0].seq + 17))


def test_vendor_handmade_vectors_minimal_frame_bad_checksum_bad_version():
    """ixblue_stdbin_decoder test/datasets/MinimalV2NavFrame.h and errors/BadCheckSum.h,
    errors/BadNavProtocolVersion.h (hand-made by the vendor, used by TestStdBinDecoderErrorRecovery):
    the minimal frame (attitude only, valid checksum 0x0572) is a valid telegram without a rate block."""
    minimal = bytes(
        b"IX\x02" + bytes.fromhex("00000001 00000000 0025 00000005 00000123 0000a03f 0000c0bf cdcc4841 00000572")
    )
    bad_checksum = minimal[:-4] + bytes(4)
    bad_version = b"IX\x00" + minimal[3:-4] + bytes.fromhex("00000570")
    events, counters, _ = _decode(bad_checksum + bad_version + minimal)
    assert events == []  # no rate block: no sample
    assert counters["other_frames"] == 1 and counters["crc_errors"] == 1
    assert counters["version_errors"] == 1 and counters["resyncs"] == 1
    assert counters["bytes_in_frames"] == len(minimal)


def test_a_real_telegram_with_a_corrupted_checksum_is_rejected_and_the_next_recovered():
    v2 = _read("log_STDBIN_V2.log")
    v4 = _read("log_STDBIN_V4.log")
    corrupted = v2[:-1] + bytes([v2[-1] ^ 0x01])
    events, counters, _ = _decode(corrupted + v4)
    assert counters["crc_errors"] == 1 and counters["sample_frames"] == 1
    assert counters["bytes_discarded"] == len(v2) and counters["resyncs"] == 1
    assert events[0].extra["heading_deg"] == _approx(357.428)  # WeCanParseV4Protocol
    # a flipped data byte, too
    flipped = bytearray(v2)
    flipped[100] ^= 0x40
    assert _decode(bytes(flipped))[1]["crc_errors"] == 1


@pytest.mark.parametrize("name", ALL_LOGS)
def test_every_single_cut_and_byte_by_byte_of_a_real_capture_gives_the_same_result(name):
    data = _read(name)
    if len(data) > 2000:  # the 17-telegram log: its first two telegrams, every cut (the rest below)
        data = data[: _telegram_bounds(data)[2]]
    for cut in range(1, len(data)):
        _same_as_whole(data, [cut])
    _same_as_whole(_read(name), list(range(1, len(_read(name)))))


def _telegram_bounds(data: bytes) -> list[int]:
    """Start offsets of consecutive telegrams (and the end), walking the size fields (v3 layout: size at
    offset 15)."""
    bounds = [0]
    while bounds[-1] < len(data):
        p = bounds[-1]
        assert data[p : p + 3] == b"IX\x03"
        bounds.append(p + struct.unpack_from(">H", data, p + 15)[0])
    return bounds


def test_every_cut_inside_each_telegram_of_the_17_telegram_log():
    data = _read("log_STDBIN_V3.log")
    bounds = _telegram_bounds(data)
    for k in range(1, len(bounds) - 1):
        lo, hi = bounds[k - 1], bounds[min(k + 1, len(bounds) - 1)]
        window = data[lo:hi]
        for cut in range(bounds[k] - lo + 1, hi - lo):
            _same_as_whole(window, [cut])


@pytest.mark.parametrize("name", PCAPS)
def test_real_2hz_udp_captures_consecutive_telegrams_half_a_second_apart(name):
    payloads = _pcap_udp_payloads(name)
    version = int(name[8])
    assert all(p[:3] == b"IX" + bytes([version]) for p in payloads)
    stream = b"".join(payloads)
    events, counters, _ = _decode(stream)
    assert counters["sample_frames"] == len(payloads) == len(events)
    assert counters["bytes_in_frames"] == len(stream)
    assert counters["seq_gaps"] == counters["seq_repeats"] == 0
    for prev, s in zip(events, events[1:]):
        assert s.seq == prev.seq + 1
        assert s.t_s - prev.t_s == pytest.approx(0.5, abs=2e-4)  # 2 Hz, per the file name
        dt_s = s.t_s - prev.t_s
        assert s.dtheta_arcsec == tuple(pytest.approx(r * dt_s) for r in s.rate_dph)
    assert all(math.isnan(x) for x in events[0].dtheta_arcsec)  # no rate_hz, no previous telegram
    _same_as_whole(stream, list(range(1, len(stream))))


# --- encoder round trips, resync, false headers --------------------------------------------------------


def _f32(x: float) -> float:
    return struct.unpack(">f", struct.pack(">f", x))[0]


@pytest.mark.parametrize("version", [2, 3, 4, 5])
def test_encode_decode_round_trip_each_version(version):
    skip_nav = {2: bytes(range(16)), 7: bytes(21), 30: bytes(12)}
    extnav = {} if version == 2 else {0: bytes(12), 2: struct.pack(">3f", 0.25, 0.5, -1.0), 6: bytes(16)}
    external = {0: bytes(5), 1: bytes(46), 27: bytes(12)}
    telegrams = [
        encode_stdbin(
            version,
            counter=2**32 - 2 + k,
            validity_time_100us=2**32 - 5000 + 1000 * k,  # wraps between telegram 0..4 and 5
            attitude_deg=(10.0 + k, -1.5, 0.25),
            rotation_rate_dps=(0.5 * k, -0.25, 1.0),
            acceleration_mps2=(0.0, 0.0, 9.75),
            sensor_status=(1, 2),
            ins_algorithm_status=(0b10 if k == 0 else 0b01, 3, 4, 5),
            ahrs_algorithm_status=7,
            temperatures_c=(25.5, 30.25, 40.0),
            nav_blocks=skip_nav,
            extnav_blocks=extnav,
            external_blocks=external,
        )
        for k in range(8)
    ]
    events, counters, _ = _decode(b"".join(telegrams), rate_hz=10.0)
    assert len(events) == 8 and counters["sample_frames"] == 8
    assert counters["time_wraps"] == 1 and counters["seq_gaps"] == 0
    assert counters["blocks_skipped"] == 8 * (len(skip_nav) + len(extnav) - (version > 2) + len(external))
    for k, s in enumerate(events):
        assert s.seq == 2**32 - 2 + k
        assert s.t_s == pytest.approx((2**32 - 5000 + 1000 * k) * 1e-4)
        assert s.rate_dph == (0.5 * k * 3600, -0.25 * 3600, 3600.0)
        dt_s = 0.1  # 1000 x 100 us, and 1 / rate_hz for the first
        assert s.dtheta_arcsec == pytest.approx(tuple(r * dt_s for r in s.rate_dph))
        assert s.extra["heading_deg"] == 10.0 + k and s.extra["pitch_deg"] == 0.25
        assert s.extra["accel_z_mps2"] == 9.75 and s.extra["ahrs_algorithm_status"] == 7.0
        assert (s.extra["sensor_status_1"], s.extra["sensor_status_2"]) == (1.0, 2.0)
        assert _ins_words(s.status) == ((0b10 if k == 0 else 0b01), 3, 4, 5)
        assert s.flags == (frozenset({SAMPLE_STARTUP}) if k == 0 else frozenset())
        assert s.temps_c == {"fog": 25.5, "accelerometer": 30.25, "board": 40.0}
        if version > 2:
            assert (s.extra["raw_rate_x_dph"], s.extra["raw_rate_z_dph"]) == (0.25 * 3600, -3600.0)
    # each sample's offset is where its telegram starts in the stream (it was once a block's offset inside the
    # telegram), here after a little garbage and at any split
    garbage = b"\x00IX\x07"
    data = garbage + b"".join(telegrams)
    starts = [len(garbage) + sum(len(t) for t in telegrams[:k]) for k in range(8)]
    for chunks in ([], [3, 50, 51, len(data) - 7]):
        events, _, _ = _decode(data, chunks, rate_hz=10.0)
        assert [s.offset for s in events] == starts


def test_encoder_rejects_what_the_format_cannot_carry():
    with pytest.raises(ValueError):
        encode_stdbin(6, counter=0, validity_time_100us=0)
    with pytest.raises(ValueError):
        encode_stdbin(2, counter=0, validity_time_100us=0, extnav_blocks={0: bytes(12)})
    with pytest.raises(ValueError):
        encode_stdbin(3, counter=0, validity_time_100us=0, nav_blocks={5: bytes(11)})
    with pytest.raises(ValueError):
        encode_stdbin(3, counter=0, validity_time_100us=0, external_blocks={23: bytes(4)})  # size unknown


def _telegram(k: int, version: int = 3) -> bytes:
    return encode_stdbin(
        version,
        counter=k,
        validity_time_100us=100 * k,
        rotation_rate_dps=(float(k), -float(k), 0.5),
        temperatures_c=(20.0, 21.0, 22.0),
        external_blocks={9: b"IX\x03" + bytes(9)},  # a false header inside the data
    )


def test_one_byte_resync_after_a_bad_checksum_recovers_every_untouched_telegram():
    telegrams = [_telegram(k, 2 + k % 4) for k in range(12)]
    stream = bytearray(b"".join(telegrams))
    starts = [sum(map(len, telegrams[:k])) for k in range(12)]
    for k in (1, 5, 6, 10):  # corrupt telegrams 1, 5, 6 and 10 (one byte inside each)
        stream[starts[k] + len(telegrams[k]) // 2] ^= 0xFF
    events, counters, _ = _decode(bytes(stream))
    assert [round(e.rate_dph[0] / 3600) for e in events] == [0, 2, 3, 4, 7, 8, 9, 11]
    assert counters["crc_errors"] == 4 and counters["resyncs"] == 3
    assert counters["seq_gaps"] == 3 and counters["missing_frames"] == 4


def test_false_ix_inside_data_and_between_telegrams_is_skipped():
    a, b = _telegram(1), _telegram(2)
    false = b"IX\x03" + struct.pack(">III", 0x20, 0, 0) + struct.pack(">H", 25 + 12 + 4) + bytes(8)
    events, counters, _ = _decode(a + false + b"IXIX\x09" + b + b"I")
    assert [e.seq for e in events] == [1, 2]
    # the false header is well formed but fails the checksum; 'IXI' and 'IX\x09' carry unknown versions
    assert counters["crc_errors"] == 1 and counters["version_errors"] == 2
    assert counters["truncated_frames"] == 0  # the lone trailing 'I' is no header: discarded at close
    assert counters["bytes_discarded"] == len(false) + 5 + 1


@settings(max_examples=int(os.environ.get("IXBLUE_FUZZ_EXAMPLES", "60")), suppress_health_check=[HealthCheck.too_slow])
@given(
    versions=st.lists(st.sampled_from([2, 3, 4, 5]), min_size=1, max_size=6),
    garbage=st.lists(st.binary(max_size=40), min_size=7, max_size=7),
    false_headers=st.lists(st.booleans(), min_size=7, max_size=7),
    flips=st.lists(st.tuples(st.integers(0, 10**6), st.integers(1, 255)), max_size=4),
    cuts=st.lists(st.integers(0, 10**6), max_size=8),
    tail=st.binary(max_size=30),
)
def test_fuzz_never_raises_accounts_every_byte_recovers_untouched_telegrams(
    versions, garbage, false_headers, flips, cuts, tail
):
    pieces: list[tuple[bytes, int | None]] = []  # (bytes, telegram index or None)
    for k, version in enumerate(versions):
        g = garbage[k] + (b"IX" + bytes([version]) if false_headers[k] else b"")
        pieces.append((g, None))
        pieces.append((_telegram(k + 1, version), k + 1))
        if version >= 3 and k % 2:  # an answer telegram now and then
            pieces.append((encode_stdbin_answer(version, b"answer %d" % k), -(k + 1)))
    pieces.append((tail, None))
    stream = bytearray(b"".join(p for p, _ in pieces))
    touched: set[int] = set()  # telegram indices (answers: negative) a flip hit
    for at, mask in flips:
        if stream:
            i = at % len(stream)
            stream[i] ^= mask
            start = 0
            for p, k in pieces:
                if k is not None and start <= i < start + len(p):
                    touched.add(abs(k))
                start += len(p)
    data = bytes(stream)
    events, counters, _ = _decode(data, sorted({c % (len(data) + 1) for c in cuts}))
    whole, whole_counters, _ = _decode(data)
    assert repr(events) == repr(whole) and counters == whole_counters
    recovered = {round(e.rate_dph[0] / 3600) for e in events if isinstance(e, ImuSample)}
    answers = {e.payload for e in events if isinstance(e, StdbinAnswer)}
    assert {p[5:-4] for p, k in pieces if k is not None and k < 0 and -k not in touched} <= answers
    assert {k for _, k in pieces if k is not None and k > 0} - touched <= recovered


def test_block_size_tables_agree_with_the_navigation_size_field_of_real_v4_v5_telegrams():
    """The v4/v5 header's navigation-size field (offset 15, 16 bits) of the real captures equals the
    navigation + extended-navigation blocks their masks announce, by the size tables."""
    for name in ("log_STDBIN_V4.log", "log_STDBIN_V5.log"):
        data = _read(name)
        nav_mask, extnav_mask = struct.unpack_from(">II", data, 3)
        nav_size = struct.unpack_from(">H", data, 15)[0]
        blocks = sum(NAV_BLOCK_LEN[b] for b in range(31) if nav_mask >> b & 1)
        blocks += sum(EXTNAV_BLOCK_LEN[b] for b in range(7) if extnav_mask >> b & 1)
        assert blocks == nav_size


def _with_checksum(body: bytes) -> bytes:
    return body + struct.pack(">I", sum(body) & 0xFFFFFFFF)


def _resized(telegram: bytes, extra_block: bytes, external_bit: int | None = None) -> bytes:
    """A v3 telegram with ``extra_block`` appended before the checksum, its size field (offset 15) and
    checksum fixed, and ``external_bit`` (if any) set in the external mask (offset 11)."""
    body = bytearray(telegram[:-4] + extra_block)
    struct.pack_into(">H", body, 15, len(body) + 4)
    if external_bit is not None:
        mask = struct.unpack_from(">I", body, 11)[0] | 1 << external_bit
        struct.pack_into(">I", body, 11, mask)
    return _with_checksum(bytes(body))


def test_a_size_field_larger_than_the_announced_blocks_is_impossible_even_with_a_valid_checksum():
    good = _telegram(3)
    too_long = _resized(good, bytes(4))
    events, counters, _ = _decode(too_long + good)
    assert [e.seq for e in events] == [3]
    # length errors: the telegram itself, and the false 'IX' of its depth block met while hunting
    assert counters["length_errors"] == 2 and counters["bytes_discarded"] == len(too_long)


def test_a_bit_of_unknown_size_is_allowed_when_the_size_leaves_room_for_it():
    # external-data bit 23 is not known to the reference decoder: its block size is unknown
    base = encode_stdbin(3, counter=9, validity_time_100us=0, rotation_rate_dps=(1.0, 2.0, 3.0))
    roomy = _resized(base, bytes(6), external_bit=23)
    no_room = _resized(base, b"", external_bit=23)
    events, counters, _ = _decode(no_room + roomy)
    assert [e.rate_dph for e in events] == [(3600.0, 7200.0, 10800.0)]
    assert counters["unknown_blocks"] == 1 and counters["length_errors"] == 1


def test_a_false_header_of_unknown_size_does_not_hold_a_live_stream_back():
    # a header with a bit of unknown size can only be checked by its checksum: one that claims 65,535 bytes
    # would make a live decoder wait for that many before the next telegram came out (seconds at 100 Hz)
    base = encode_stdbin(3, counter=9, validity_time_100us=0, rotation_rate_dps=(1.0, 2.0, 3.0))
    false = bytearray(_resized(base, bytes(6), external_bit=23))
    size_at = 15  # v3: "IX", version, three 4-byte masks, then the telegram size
    struct.pack_into(">H", false, size_at, MAX_TELEGRAM_LEN)
    good = [
        encode_stdbin(3, counter=k, validity_time_100us=100 * k, rotation_rate_dps=(1.0, 2.0, 3.0))
        for k in range(10, 14)
    ]
    decoder = StdbinDecoder()
    decoder.feed(bytes(false[:40]))
    for k, telegram in zip(range(10, 14), good):  # fed as they arrive: each comes out at once
        assert [e.seq for e in decoder.feed(telegram)][-1:] == [k]
    assert decoder.counters.length_errors >= 1 and MAX_UNVERIFIED_LEN < MAX_TELEGRAM_LEN


def test_validity_time_a_small_step_back_is_not_a_wrap_and_uses_the_nominal_period():
    a = encode_stdbin(2, counter=1, validity_time_100us=5000, rotation_rate_dps=(1.0, 0.0, 0.0))
    b = encode_stdbin(2, counter=2, validity_time_100us=4990, rotation_rate_dps=(1.0, 0.0, 0.0))
    events, counters, _ = _decode(a + b, rate_hz=50.0)
    assert [e.t_s for e in events] == [pytest.approx(0.5), pytest.approx(0.499)]
    assert counters["time_wraps"] == 0
    assert events[1].dtheta_arcsec[0] == pytest.approx(3600.0 / 50.0)  # no positive step: 1 / rate_hz


# ixblue_stdbin_decoder test/datasets/MinimalV3AnsFrame.h (vendor test vector; TEST(StdBinDecoder,
# WeCanParseAnAnswerFrame) expects the payload de ad be ef) and errors/BadAnswerProtocolVersion.h
MINIMAL_V3_ANSWER = b"AN\x03\x00\x0d\xde\xad\xbe\xef\x00\x00\x03\xd7"
BAD_ANSWER_VERSION = b"AN\x00\x00\x0d\xde\xad\xbe\xef\x00\x00\x03\xd4"


def test_vendor_answer_frame_and_recovery_after_a_bad_answer_version():
    events, counters, _ = _decode(BAD_ANSWER_VERSION + MINIMAL_V3_ANSWER)
    assert events == [StdbinAnswer(3, bytes.fromhex("deadbeef"))]
    assert counters["answer_frames"] == counters["other_frames"] == 1
    assert counters["version_errors"] == 1 and counters["resyncs"] == 1
    assert counters["bytes_discarded"] == len(BAD_ANSWER_VERSION)
    for cut in range(1, len(MINIMAL_V3_ANSWER)):
        _same_as_whole(BAD_ANSWER_VERSION + MINIMAL_V3_ANSWER, [len(BAD_ANSWER_VERSION) + cut])


def test_answer_encoder_round_trip_between_navigation_telegrams():
    stream = _telegram(1) + encode_stdbin_answer(5, b"$PIXSE,CONFIG") + _telegram(2)
    events, counters, _ = _decode(stream)
    assert [type(e) for e in events] == [ImuSample, StdbinAnswer, ImuSample]
    assert events[1] == StdbinAnswer(5, b"$PIXSE,CONFIG")
    with pytest.raises(ValueError):
        encode_stdbin_answer(2, b"")
