"""Test helpers: build protocol streams whose frames and offsets are known exactly."""

from __future__ import annotations

from dataclasses import dataclass

from hypothesis import strategies as st

from fog_driver.protocol import (
    FrameDecoder,
    IdentityFrame,
    SampleFrame,
    UnknownFrame,
    encode_event,
)


@dataclass
class Piece:
    """A piece of a test stream: a frame (``event`` set) or garbage (``event`` None)."""

    data: bytes
    event: object | None = None


def assemble(pieces: list[Piece]) -> tuple[bytes, list]:
    """Concatenate pieces; return the bytes and the frame events with their true offsets."""
    out = bytearray()
    events = []
    for piece in pieces:
        if piece.event is not None:
            events.append(piece.event._replace(offset=len(out)))
        out += piece.data
    return bytes(out), events


def frame_piece(event) -> Piece:
    return Piece(encode_event(event), event)


def decode_in_chunks(data: bytes, sizes: list[int], close: bool = True) -> tuple[FrameDecoder, list]:
    """Feed ``data`` in chunks of the given sizes (cycled), then the rest; optionally close."""
    decoder = FrameDecoder()
    events = []
    i = 0
    k = 0
    while i < len(data):
        size = sizes[k % len(sizes)] if sizes else len(data)
        events += decoder.feed(data[i : i + size])
        i += size
        k += 1
    if close:
        events += decoder.close()
    return decoder, events


def assert_accounted(decoder: FrameDecoder) -> None:
    c = decoder.counters
    assert c.bytes_in == c.bytes_in_frames + c.bytes_discarded + decoder.pending


u16 = st.integers(0, 0xFFFF)
u32 = st.integers(0, 0xFFFFFFFF)
i16 = st.integers(-0x8000, 0x7FFF)
i32 = st.integers(-0x80000000, 0x7FFFFFFF)

sample_frames = st.builds(SampleFrame, st.just(0), u16, u32, i32, i16, i16, i16, u16)
identity_frames = st.builds(
    IdentityFrame,
    st.just(0),
    st.text(alphabet=st.characters(min_codepoint=0x21, max_codepoint=0x7E), max_size=16),
    u16,
    u16,
    # Only values a float32 holds exactly survive the wire unchanged.
    st.floats(width=32, allow_nan=False),
)
unknown_frames = st.builds(
    UnknownFrame,
    st.just(0),
    st.integers(0, 255).filter(lambda t: t not in (1, 2)),
    st.binary(max_size=40),
)
any_frame = st.one_of(sample_frames, sample_frames, sample_frames, identity_frames, unknown_frames)
# Garbage biased towards what hurts: sync bytes and plausible headers.
garbage = st.one_of(
    st.binary(min_size=1, max_size=40),
    st.sampled_from(
        [
            b"\xaa",
            b"\xaa\x55",
            b"\xaa\x55\x01",
            b"\xaa\x55\x01\x12",
            b"\xaa\x55\x02\x18",
            b"\xaa\x55\x7f\xff",
            b"\xaa\xaa\x55",
        ]
    ),
)


def with_identities(data: bytes, after_offset: int, **fields) -> bytes:
    """``data`` (a capture's bytes) with every IDENTITY frame at or after ``after_offset`` re-encoded with
    ``fields`` changed (``serial``, ``firmware``, ``rate_hz``, ``scale_arcsec_per_count``)."""
    from fog_driver.protocol import decode_bytes, encode_identity

    out = bytearray(data)
    for frame in decode_bytes(data).identities:
        if frame.offset >= after_offset:
            values = {
                "serial": frame.serial,
                "firmware": frame.firmware,
                "rate_hz": frame.rate_hz,
                "scale_arcsec_per_count": frame.scale_arcsec_per_count,
                **fields,
            }
            out[frame.offset : frame.offset + 32] = encode_identity(
                values["serial"], values["firmware"], values["rate_hz"], values["scale_arcsec_per_count"]
            )
    return bytes(out)
