"""The wire protocol v1 codec: encoders, the streaming decoder, the batch decoder."""

from __future__ import annotations

import struct
import zlib

import numpy as np
import pytest
from framegen import (
    Piece,
    any_frame,
    assemble,
    assert_accounted,
    decode_in_chunks,
    frame_piece,
    garbage,
    identity_frames,
    sample_frames,
)
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fog_driver.protocol import (
    SAMPLE_FRAME_LEN,
    BatchDecoder,
    FrameDecoder,
    IdentityFrame,
    SampleFrame,
    UnknownFrame,
    concatenate,
    crc32,
    decode_bytes,
    decode_file,
    encode_event,
    encode_frame,
    encode_identity,
    encode_sample,
    iter_decode_file,
)


def sample(seq: int, t_us: int | None = None, dtheta: int = 0, status: int = 0) -> SampleFrame:
    return SampleFrame(0, seq % 65536, (seq * 1000 if t_us is None else t_us) % 2**32, dtheta, 5120, 5000, 4900, status)


def stream_of(events) -> tuple[bytes, list]:
    return assemble([frame_piece(e) for e in events])


def batch_equals_stream(data: bytes, sizes: list[int], final: bool) -> None:
    decoder, events = decode_in_chunks(data, sizes, close=final)
    batch = decode_bytes(data, final=final)
    assert batch.events() == events
    assert batch.counters == decoder.counters
    assert batch.pending == decoder.pending
    assert_accounted(decoder)


# --- CRC and encoders -------------------------------------------------------------------------


def test_crc_check_value():
    assert crc32(b"123456789") == 0xCBF43926


def test_sample_frame_layout_by_hand():
    frame = encode_sample(0x1234, 0x89ABCDEF, -2, -32768, 256, -256, 0x0014)
    assert len(frame) == SAMPLE_FRAME_LEN
    assert frame[:4] == b"\xaa\x55\x01\x12"
    assert frame[4:6] == b"\x34\x12"
    assert frame[6:10] == b"\xef\xcd\xab\x89"
    assert frame[10:14] == b"\xfe\xff\xff\xff"
    assert frame[14:20] == b"\x00\x80\x00\x01\x00\xff"
    assert frame[20:22] == b"\x14\x00"
    assert frame[22:] == struct.pack("<I", zlib.crc32(frame[2:22]))


def test_identity_frame_layout_by_hand():
    frame = encode_identity("FOG-1", 0x0102, 1000, 0.5)
    assert len(frame) == 32
    assert frame[:4] == b"\xaa\x55\x02\x18"
    assert frame[4:20] == b"FOG-1" + b"\0" * 11
    assert frame[20:24] == b"\x02\x01\xe8\x03"
    assert frame[24:28] == b"\x00\x00\x00\x3f"  # 0.5f little-endian


def test_encoder_rejects_what_cannot_be_sent():
    with pytest.raises(ValueError):
        encode_identity("X" * 17, 1, 1, 1.0)
    with pytest.raises(ValueError):
        encode_frame(0x7F, bytes(256))


@given(st.lists(any_frame, max_size=20))
def test_round_trip_any_frames(frames):
    data, truth = stream_of(frames)
    decoder, events = decode_in_chunks(data, [len(data) or 1])
    assert events == truth
    assert decoder.counters.bytes_discarded == 0
    assert decoder.counters.bytes_in_frames == len(data)


# --- splitting -------------------------------------------------------------------------------


def test_byte_at_a_time_equals_whole():
    frames = [sample(1), IdentityFrame(0, "FOG-A", 0x0102, 100, 0.25), sample(2), UnknownFrame(0, 0x7E, b"\xaa\x55")]
    data, truth = stream_of(frames)
    _, one_shot = decode_in_chunks(data, [len(data)])
    decoder, byte_wise = decode_in_chunks(data, [1])
    assert one_shot == byte_wise == truth
    assert decoder.counters.bytes_discarded == 0


def test_every_split_point_and_every_pair_of_split_points():
    data, truth = stream_of([sample(7, dtheta=-123), IdentityFrame(0, "S", 0x0101, 1000, 1.5), sample(8)])
    for i in range(len(data) + 1):
        d = FrameDecoder()
        events = d.feed(data[:i]) + d.feed(data[i:])
        assert events == truth, i
        assert_accounted(d)
        assert d.pending == 0
    first = SAMPLE_FRAME_LEN + 32  # the pairs over the first two frames cover every within-frame split
    for i in range(first + 1):
        for j in range(i, first + 1):
            d = FrameDecoder()
            events = d.feed(data[:i]) + d.feed(data[i:j]) + d.feed(data[j:])
            assert events == truth, (i, j)


def test_events_are_returned_as_soon_as_a_frame_completes():
    frame = encode_sample(3, 3000, 1, 1, 1, 1)
    d = FrameDecoder()
    for i, byte in enumerate(frame[:-1]):
        assert d.feed(bytes([byte])) == []
        assert d.pending == i + 1
    assert len(d.feed(frame[-1:])) == 1
    assert d.pending == 0


# --- corruption ------------------------------------------------------------------------------


def test_garbage_prefix_is_discarded_and_counted():
    prefix = bytes(range(0x20, 0x60)) + b"\xaa"  # ends on half a sync
    data, truth = assemble([Piece(prefix)] + [frame_piece(sample(i)) for i in range(3)])
    decoder, events = decode_in_chunks(data, [5])
    assert events == truth
    assert decoder.counters.bytes_discarded == len(prefix)
    assert decoder.counters.resyncs == 1


def test_false_sync_inside_a_payload_is_not_a_frame_boundary():
    # dtheta = 0x12_01_55_AA puts "AA 55 01 12" (a plausible SAMPLE header) inside the payload.
    tricky = sample(1, dtheta=0x120155AA)
    assert b"\xaa\x55\x01\x12" in encode_sample(*tricky[1:])[4:]
    data, truth = stream_of([sample(0), tricky, sample(2)])
    decoder, events = decode_in_chunks(data, [1])
    assert events == truth
    assert decoder.counters.crc_errors == 0 and decoder.counters.bytes_discarded == 0


def test_false_sync_inside_a_corrupted_frame_is_rejected():
    tricky = encode_sample(1, 1000, 0x120155AA, 0, 0, 0)
    corrupted = tricky[:4] + bytes([tricky[4] ^ 0x01]) + tricky[5:]
    data, truth = assemble([frame_piece(sample(0)), Piece(corrupted), frame_piece(sample(2)), frame_piece(sample(3))])
    decoder, events = decode_in_chunks(data, [7])
    assert events == truth
    c = decoder.counters
    assert c.crc_errors == 2  # the corrupted frame's own sync and the false one inside it
    assert c.bytes_discarded == len(corrupted)
    assert c.seq_gaps == 1 and c.missing_frames == 1


def test_bad_crc_loses_exactly_that_frame():
    good = [encode_sample(*sample(i)[1:]) for i in range(4)]
    bad = good[1][:-1] + bytes([good[1][-1] ^ 0x80])
    data = good[0] + bad + good[2] + good[3]
    decoder, events = decode_in_chunks(data, [3])
    assert [e.seq for e in events] == [0, 2, 3]
    c = decoder.counters
    assert (c.crc_errors, c.bytes_discarded, c.resyncs) == (1, SAMPLE_FRAME_LEN, 1)


def test_known_type_with_wrong_length_discards_one_byte_not_len_bytes():
    # A SAMPLE header claiming 200 bytes must not make the decoder skip the frames behind it.
    header = b"\xaa\x55\x01\xc8"
    data, truth = assemble([Piece(header)] + [frame_piece(sample(i)) for i in range(3)])
    decoder, events = decode_in_chunks(data, [64])
    assert events == truth
    assert decoder.counters.length_errors == 1
    assert decoder.counters.bytes_discarded == len(header)


def test_unknown_type_is_skipped_and_counted():
    data, truth = stream_of([sample(0), UnknownFrame(0, 0x7E, b"future payload"), sample(1)])
    decoder, events = decode_in_chunks(data, [2])
    assert events == truth
    c = decoder.counters
    assert (c.unknown_frames, c.sample_frames, c.bytes_discarded, c.seq_gaps) == (1, 2, 0, 0)


def test_truncated_tail_is_pending_then_discarded_at_close():
    whole = b"".join(encode_sample(*sample(i)[1:]) for i in range(3))
    data = whole + encode_sample(*sample(3)[1:])[:11]
    d = FrameDecoder()
    events = d.feed(data)
    assert len(events) == 3
    assert d.pending == 11
    assert_accounted(d)
    assert d.close() == []
    assert d.pending == 0
    assert d.counters.truncated_frames >= 1
    assert d.counters.bytes_discarded == 11
    assert_accounted(d)


def test_close_recovers_frames_behind_a_false_header_that_never_completes():
    # "AA 55 7F FF" announces 263 bytes; the stream ends before that, with a real frame inside.
    data = b"\xaa\x55\x7f\xff" + encode_sample(*sample(5)[1:])
    d = FrameDecoder()
    assert d.feed(data) == []
    assert d.pending == len(data)
    events = d.close()
    assert [e.seq for e in events] == [5]
    assert d.counters.bytes_discarded == 4


def test_seq_and_t_us_wrap_without_gaps():
    frames = [sample(s, t_us=t) for s, t in zip((65534, 65535, 0, 1), (2**32 - 2000, 2**32 - 1000, 0, 1000))]
    decoder, events = decode_in_chunks(stream_of(frames)[0], [26])
    c = decoder.counters
    assert [e.seq for e in events] == [65534, 65535, 0, 1]
    assert (c.seq_gaps, c.missing_frames, c.t_us_wraps) == (0, 0, 1)


def test_dropped_frames_are_counted_across_the_seq_wrap():
    seqs = [65530, 65531, 65535, 3, 4]  # 3 missing before 65535, 3 missing (0, 1, 2) before 3
    decoder, _ = decode_in_chunks(stream_of([sample(s) for s in seqs])[0], [100])
    assert (decoder.counters.seq_gaps, decoder.counters.missing_frames) == (2, 6)


def test_repeated_seq_is_a_repeat_not_a_gap():
    decoder, _ = decode_in_chunks(stream_of([sample(1), sample(1), sample(2)])[0], [100])
    c = decoder.counters
    assert (c.seq_repeats, c.seq_gaps, c.missing_frames) == (1, 0, 0)


def test_feed_after_close_is_an_error_but_close_is_idempotent():
    d = FrameDecoder()
    d.close()
    assert d.close() == []
    with pytest.raises(RuntimeError):
        d.feed(b"x")


# --- properties ------------------------------------------------------------------------------

chunk_sizes = st.lists(st.integers(1, 80), min_size=1, max_size=12)


@settings(max_examples=300, suppress_health_check=[HealthCheck.too_slow])
@given(st.binary(max_size=600), chunk_sizes)
def test_any_bytes_never_raise_and_every_byte_is_accounted(data, sizes):
    decoder, events = decode_in_chunks(data, sizes, close=False)
    assert_accounted(decoder)
    assert decoder.pending <= 262  # never more than one maximal frame minus a byte
    decoder.close()
    assert_accounted(decoder)
    assert decoder.pending == 0


@st.composite
def damaged_streams(draw):
    """Valid frames, damaged by bit flips, inserted garbage and dropped frames; returns the truth too."""
    n = draw(st.integers(1, 25))
    # Starts near the wrap points half the time, so seq and t_us wraps are exercised often.
    seq0 = draw(st.one_of(st.integers(65536 - 25, 65535), st.integers(0, 65535)))
    t0 = draw(st.one_of(st.integers(2**32 - 25 * 997, 2**32 - 1), st.integers(0, 2**32 - 1)))
    frames = []
    for k in range(n):
        kind = draw(st.sampled_from(["s", "s", "s", "s", "i", "u"]))
        if kind == "s":
            f = draw(sample_frames)._replace(seq=(seq0 + k) % 65536, t_us=(t0 + 997 * k) % 2**32)
        elif kind == "i":
            f = draw(identity_frames)
        else:
            f = UnknownFrame(0, draw(st.integers(3, 255)), draw(st.binary(max_size=30)))
        frames.append(f)
    keep = [not draw(st.booleans()) if draw(st.integers(0, 9)) == 0 else True for _ in frames]
    pieces = []
    for f, kept in zip(frames, keep):
        if draw(st.integers(0, 4)) == 0:
            pieces.append(Piece(draw(garbage)))
        if kept:
            pieces.append(frame_piece(f))
    data, truth = assemble(pieces)
    flips = draw(st.lists(st.tuples(st.integers(0, max(0, len(data) - 1)), st.integers(0, 7)), max_size=4))
    buf = bytearray(data)
    for pos, bit in flips if data else []:
        buf[pos] ^= 1 << bit
    touched = {i for i, (a, b) in enumerate(zip(data, buf)) if a != b}  # two flips of one bit cancel
    untouched = [e for e in truth if not any(e.offset <= p < e.offset + len(encode_event(e)) for p in touched)]
    return bytes(buf), untouched


@settings(max_examples=300, suppress_health_check=[HealthCheck.too_slow])
@given(damaged_streams(), chunk_sizes)
def test_every_frame_the_damage_did_not_touch_is_recovered(case, sizes):
    data, untouched = case
    decoder, events = decode_in_chunks(data, sizes)
    assert events == untouched
    assert_accounted(decoder)


@settings(max_examples=300, suppress_health_check=[HealthCheck.too_slow])
@given(damaged_streams(), chunk_sizes, st.booleans(), st.integers(0, 40))
def test_batch_decode_equals_streaming_decode(case, sizes, final, cut):
    data, _ = case
    batch_equals_stream(data[: max(0, len(data) - cut)], sizes, final)


@settings(max_examples=200)
@given(st.binary(max_size=400), chunk_sizes, st.booleans())
def test_batch_decode_equals_streaming_decode_on_random_bytes(data, sizes, final):
    batch_equals_stream(data, sizes, final)


def test_batch_decode_with_a_valid_frame_hidden_inside_another():
    # An unknown-type frame whose payload is a whole SAMPLE frame: the scan accepts the outer
    # frame and never sees the inner one; the batch path must choose the same.
    inner = encode_sample(9, 9000, 1, 2, 3, 4)
    data = encode_sample(8, 8000, 0, 0, 0, 0) + encode_frame(0x7E, inner) + encode_sample(10, 10000, 0, 0, 0, 0)
    batch_equals_stream(data, [1], True)
    events = decode_bytes(data).events()
    assert [type(e).__name__ for e in events] == ["SampleFrame", "UnknownFrame", "SampleFrame"]
    # With the outer frame's sync destroyed, the inner frame is found instead.
    broken = data[:SAMPLE_FRAME_LEN] + b"\x00" + data[SAMPLE_FRAME_LEN + 1 :]
    batch_equals_stream(broken, [5], True)
    assert [e.seq for e in decode_bytes(broken).events()] == [8, 9, 10]


def test_batch_decode_columns_match_frames():
    frames = [sample(i, dtheta=(-1) ** i * i * 1000, status=i) for i in range(50)]
    data, truth = stream_of(frames)
    batch = decode_bytes(data)
    np.testing.assert_array_equal(batch.samples.seq, [f.seq for f in truth])
    np.testing.assert_array_equal(batch.samples.dtheta_counts, [f.dtheta_counts for f in truth])
    np.testing.assert_array_equal(batch.samples.offset, np.arange(50) * SAMPLE_FRAME_LEN)
    assert batch.samples.dtheta_counts.dtype == np.int32


def test_batch_decode_of_nothing():
    for data in (b"", b"\xaa", b"\xaa\x55"):
        for final in (True, False):
            batch_equals_stream(data, [1], final)


@settings(max_examples=300, suppress_health_check=[HealthCheck.too_slow])
@given(damaged_streams(), chunk_sizes, st.lists(st.integers(0, 120), max_size=6), st.booleans())
def test_batch_decoder_fed_in_blocks_equals_streaming_decoder(case, sizes, cuts, final):
    data, _ = case
    decoder, events = decode_in_chunks(data, sizes, close=final)
    batch = BatchDecoder()
    bounds = sorted({0, len(data), *(min(c * 7, len(data)) for c in cuts)})
    parts = [batch.decode(data[lo:hi]) for lo, hi in zip(bounds, bounds[1:])]
    if final:
        parts.append(batch.decode(b"", final=True))
    joined = concatenate(parts)
    assert joined.events() == events
    assert batch.counters == decoder.counters
    assert joined.counters == decoder.counters
    assert batch.pending == decoder.pending


def test_decode_file_in_small_blocks_equals_one_shot(tmp_path):
    data = (
        b"".join(
            [
                b"\x00\xaa",
                *(encode_sample(i, i * 1000, i, 1, 2, 3) for i in range(200)),
                encode_identity("F", 1, 2, 3.0),
            ]
        )
        * 3
        + b"\xaa\x55\x01"
    )
    path = tmp_path / "c.bin"
    path.write_bytes(data)
    whole = decode_bytes(data)
    for block in (1, 25, 26, 1000, 1 << 20):
        part = decode_file(path, block_bytes=block)
        assert part.events() == whole.events(), block
        assert part.counters == whole.counters, block
    seen = []
    list(iter_decode_file(path, block_bytes=100, on_block=seen.append))
    assert b"".join(seen) == data


def test_batch_decoder_refuses_data_after_the_final_block():
    batch = BatchDecoder()
    batch.decode(b"abc", final=True)
    with pytest.raises(RuntimeError):
        batch.decode(b"")


def test_large_input_decoded_in_pieces_equals_streaming():
    # decode_bytes splits inputs over 1 MiB into pieces internally; put damage right at the seams.
    import random

    rng = random.Random(7)
    frames = [encode_sample(i, i * 1000, rng.randrange(-5000, 5000), 1, 2, 3) for i in range(100_000)]
    data = bytearray(b"".join(frames))
    for seam in (1 << 20, 2 << 20):
        for delta in (-30, -13, -1, 0, 2, 25):
            data[seam + delta] ^= 0x40
        data[seam + 100 : seam + 100] = b"\xaa\x55\x7f\xff\xaa"  # a false long header just past the seam
    data = bytes(data)
    assert len(data) > (2 << 20) + 200
    decoder, events = decode_in_chunks(data, [4096])
    batch = decode_bytes(data)
    assert batch.counters == decoder.counters
    assert batch.counters.crc_errors > 0
    np.testing.assert_array_equal(batch.samples.offset, [e.offset for e in events if isinstance(e, SampleFrame)])
    np.testing.assert_array_equal(batch.samples.seq, [e.seq for e in events if isinstance(e, SampleFrame)])
    np.testing.assert_array_equal(
        batch.samples.dtheta_counts, [e.dtheta_counts for e in events if isinstance(e, SampleFrame)]
    )


@settings(max_examples=50)
@given(st.lists(sample_frames, max_size=30))
def test_vectorized_encoder_equals_scalar_encoder(frames):
    from fog_driver.protocol import encode_sample_frames

    columns = [np.array([f[i] for f in frames], dtype=np.int64) for i in range(1, 8)]
    encoded = encode_sample_frames(*columns)
    assert encoded.shape == (len(frames), SAMPLE_FRAME_LEN)
    assert encoded.tobytes() == b"".join(encode_sample(*f[1:]) for f in frames)
