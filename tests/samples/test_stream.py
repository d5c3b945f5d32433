"""Frames -> samples: unwrapping, units, scale-factor choice, gap markers, step == run."""

from __future__ import annotations

import math

import numpy as np
import pytest
from framegen import assemble, frame_piece, sample_frames
from hypothesis import given, settings
from hypothesis import strategies as st

from fog_driver.protocol import IdentityFrame, SampleArrays, SampleFrame, decode_bytes
from fog_driver.samples.stream import SampleBlock, SampleStream


def frame(seq: int, t_us: int, dtheta: int = 10, temps=(5120, 5000, 4900), status: int = 0) -> SampleFrame:
    return SampleFrame(0, seq % 65536, t_us % 2**32, dtheta, *temps, status)


def identity(scale: float, serial: str = "FOG-1") -> IdentityFrame:
    return IdentityFrame(0, serial, 0x0102, 100, scale)


def test_units_and_sentinel():
    s = SampleStream(default_scale_arcsec_per_count=0.5)
    out = s.step(frame(1, 2_000_000, dtheta=-7, temps=(-32768, 256 * 25 + 128, -256 * 40), status=0x4))
    assert out.dtheta_arcsec == -3.5
    assert math.isnan(out.t_top_c)
    assert out.t_bottom_c == 25.5
    assert out.t_housing_c == -40.0
    assert out.t_s == 2.0
    assert out.status == 0x4
    assert out.missing_before == 0 and not out.gap


def test_scale_default_then_identity_then_change():
    s = SampleStream(default_scale_arcsec_per_count=2.0)
    assert s.step(frame(0, 0, dtheta=3)).dtheta_arcsec == 6.0
    assert s.step(identity(0.25)) is None
    assert s.step(frame(1, 1000, dtheta=3)).dtheta_arcsec == 0.75
    s.step(identity(0.5))
    assert s.step(frame(2, 2000, dtheta=3)).dtheta_arcsec == 1.5
    assert s.identity_changes == 2


def test_configured_override_beats_identity():
    s = SampleStream(default_scale_arcsec_per_count=2.0, scale_override_arcsec_per_count=0.1)
    s.step(identity(0.25))
    # Held at float32 precision, like the instrument's own scale: increments stay exact.
    assert s.step(frame(0, 0, dtheta=10)).dtheta_arcsec == 10 * float(np.float32(0.1))
    assert s.scale_arcsec_per_count == float(np.float32(0.1))


def test_seq_and_time_unwrap_across_wraps():
    s = SampleStream()
    seqs = [65534, 65535, 0, 1]
    times = [2**32 - 2_000_000, 2**32 - 1_000_000, 0, 1_000_000]
    out = [s.step(frame(q, t)) for q, t in zip(seqs, times)]
    assert [o.seq for o in out] == [65534, 65535, 65536, 65537]
    assert np.diff([o.t_s for o in out]).tolist() == [1.0, 1.0, 1.0]
    assert out[0].t_s == (2**32 - 2_000_000) / 1e6


def test_gap_marker_counts_missing_frames():
    s = SampleStream()
    out = [s.step(frame(q, q * 1000)) for q in (10, 11, 15, 16, 16)]
    assert [o.missing_before for o in out] == [0, 0, 3, 0, 0]
    assert [o.seq for o in out] == [10, 11, 15, 16, 16]  # a repeat keeps its number: never decreasing
    assert out[2].gap


def test_gap_over_the_seq_wrap():
    s = SampleStream()
    out = [s.step(frame(q, i * 1000)) for i, q in enumerate((65533, 2))]
    assert out[1].missing_before == 4  # 65534, 65535, 0, 1
    assert out[1].seq == 65538


def _events_with_identities(frames, identity_at, scales):
    pieces = []
    for k, f in enumerate(frames):
        if k in identity_at:
            pieces.append(frame_piece(identity(scales[identity_at.index(k)])))
        pieces.append(frame_piece(f))
    return assemble(pieces)


def _assert_blocks_equal(a: SampleBlock, b: SampleBlock) -> None:
    for name in SampleBlock.__dataclass_fields__:
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
        assert getattr(a, name).dtype == getattr(b, name).dtype, name


@settings(max_examples=150)
@given(
    st.lists(sample_frames, min_size=0, max_size=40),
    st.lists(st.integers(0, 39), max_size=4, unique=True),
    st.lists(st.floats(0.0625, 8.0, width=32), min_size=4, max_size=4),
    st.lists(st.integers(0, 45), max_size=4),
    st.one_of(st.none(), st.floats(1e-3, 1.0)),
)
@pytest.mark.determinism
def test_step_and_run_agree_for_any_split(frames, identity_at, scales, cuts, override):
    data, events = _events_with_identities(frames, sorted(identity_at), scales)
    stepped = SampleStream(0.75, override)
    reference = SampleBlock.from_samples(stepped.step_all(events))

    batch = SampleStream(0.75, override)
    _assert_blocks_equal(batch.run(decode_bytes(data)), reference)
    assert batch.identity_changes == stepped.identity_changes

    # run() over arbitrary pieces continues exactly where the last piece stopped.
    pieces_stream = SampleStream(0.75, override)
    bounds = sorted({0, len(events), *(min(c, len(events)) for c in cuts)})
    parts = []
    for lo, hi in zip(bounds, bounds[1:]):
        piece = events[lo:hi]
        samples = [e for e in piece if isinstance(e, SampleFrame)]
        ids = [e for e in piece if isinstance(e, IdentityFrame)]
        parts.append(pieces_stream.run_arrays(SampleArrays.from_frames(samples), ids))
    if parts:
        joined = SampleBlock.concatenate(parts)
        _assert_blocks_equal(joined, reference)


def test_block_round_trip_and_indexing():
    s = SampleStream()
    samples = [s.step(frame(i, i * 10_000)) for i in range(5)]
    block = SampleBlock.from_samples(samples)
    assert len(block) == 5
    assert [block.sample(i) for i in range(5)] == samples
    assert len(SampleBlock.from_samples([])) == 0
