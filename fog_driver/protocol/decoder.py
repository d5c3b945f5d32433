"""The sans-IO streaming frame decoder (h11 style: bytes in, events out).

``FrameDecoder.feed(chunk)`` accepts bytes of any size and returns the events
completed by them; ``close()`` marks the end of the stream and resolves what
is still pending.  No I/O, no clock, never raises on data, never hangs.

Resynchronisation follows protocol v1 exactly: at a sync ``AA 55`` a known type
with the wrong length, or any frame whose CRC does not match, costs ONE byte
and the hunt for the next sync resumes; the length field is never trusted
before the CRC has verified it.  Every byte fed is accounted for::

    bytes_in == bytes_in_frames + bytes_discarded + pending

The decision at a sync position depends only on the bytes from that position
on, and is taken as soon as enough of them have arrived, so the events and
counters after any byte sequence do not depend on how it was split into chunks.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import asdict, dataclass

from .hunting import HuntingDecoder
from .sequence import Unwrapper, count_seq_step
from .wire import (
    CRC_LEN,
    HEADER_LEN,
    KNOWN_PAYLOAD_LEN,
    OVERHEAD_LEN,
    SEQ_MODULUS,
    SYNC,
    SYNC0,
    TYPE_IDENTITY,
    TYPE_SAMPLE,
    Event,
    SampleFrame,
    UnknownFrame,
    parse_identity_payload,
)

_SAMPLE_UNPACK_FROM = struct.Struct("<HIihhhH").unpack_from
_CRC_UNPACK_FROM = struct.Struct("<I").unpack_from


@dataclass
class DecoderCounters:
    """What the decoder has seen.  All counts are cumulative over the stream."""

    bytes_in: int = 0  #: bytes fed
    bytes_in_frames: int = 0  #: bytes inside CRC-valid frames (any type)
    bytes_discarded: int = 0  #: bytes dropped while hunting for sync
    sample_frames: int = 0
    identity_frames: int = 0
    unknown_frames: int = 0  #: CRC-valid frames of an unknown type (skipped)
    crc_errors: int = 0  #: sync positions whose complete frame failed the CRC
    length_errors: int = 0  #: sync positions with a known type but the wrong length
    truncated_frames: int = 0  #: sync positions cut off by the end of the stream
    resyncs: int = 0  #: valid frames preceded by discarded bytes (sync re-acquired)
    seq_gaps: int = 0  #: SAMPLE frames whose seq is not the previous seq + 1
    missing_frames: int = 0  #: SAMPLE frames the seq gaps skipped over
    seq_repeats: int = 0  #: SAMPLE frames repeating the previous seq
    t_us_wraps: int = 0  #: SAMPLE frames whose t_us is below the previous one

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


def seq_step(seq: int, previous_seq: int) -> int:
    """Frames from ``previous_seq`` to ``seq`` on the 16-bit counter: ``(seq - prev) mod 2^16``.

    1 is the normal step, 0 a repeated frame, k > 1 means k - 1 frames are missing.
    """
    return (seq - previous_seq) % SEQ_MODULUS


class FrameDecoder(HuntingDecoder[Event, DecoderCounters]):
    """Streaming protocol v1 decoder.

    >>> from fog_driver.protocol import encode_sample
    >>> d = FrameDecoder()
    >>> frame = encode_sample(7, 1000, -3, 5120, 5120, 5120)
    >>> d.feed(frame[:10]), len(d.feed(frame[10:]))
    ([], 1)
    """

    def __init__(self) -> None:
        super().__init__(DecoderCounters())
        self._seq = Unwrapper(SEQ_MODULUS)
        self._seq_step = self._seq.step  # bound once: called for every frame
        self._last_t_us: int | None = None

    def _find(self, buf: bytearray, pos: int) -> int:
        return buf.find(SYNC, pos)

    def _may_begin(self, byte: int) -> bool:
        return byte == SYNC0  # a lone trailing 0xAA may be the first half of a sync

    def _judge(self, buf: bytearray, pos: int, end: int, final: bool) -> int | None:
        c = self.counters
        if end - pos < HEADER_LEN:
            return self._short(final)
        payload_len = buf[pos + 3]
        expected_len = KNOWN_PAYLOAD_LEN.get(buf[pos + 2])
        if expected_len is not None and payload_len != expected_len:
            c.length_errors += 1
            return 0
        frame_len = OVERHEAD_LEN + payload_len
        if end - pos < frame_len:
            return self._short(final)
        crc_at = pos + HEADER_LEN + payload_len
        if zlib.crc32(buf[pos + 2 : crc_at]) != _CRC_UNPACK_FROM(buf, crc_at)[0]:
            c.crc_errors += 1
            return 0
        return frame_len

    def _emit(self, buf: bytearray, pos: int, n: int, events: list[Event]) -> None:
        c = self.counters
        offset = self._base + pos
        frame_type = buf[pos + 2]
        frame: Event
        if frame_type == TYPE_SAMPLE:
            frame = SampleFrame(offset, *_SAMPLE_UNPACK_FROM(buf, pos + HEADER_LEN))
            self._count_sample(frame.seq, frame.t_us)
            c.sample_frames += 1
        elif frame_type == TYPE_IDENTITY:
            frame = parse_identity_payload(offset, bytes(buf[pos + HEADER_LEN : pos + n - CRC_LEN]))
            c.identity_frames += 1
        else:
            frame = UnknownFrame(offset, frame_type, bytes(buf[pos + HEADER_LEN : pos + n - CRC_LEN]))
            c.unknown_frames += 1
        events.append(frame)

    def _count_sample(self, seq: int, t_us: int) -> None:
        d = self._seq_step(seq)
        if d != 1:  # (tested here: the call only on a gap or a repeat, off the per-frame path)
            count_seq_step(self.counters, d)
        # t_us is not unwrapped here, only its wraps counted, as ``Unwrapper`` counts them (a reading below
        # the one before); inline: this runs once per frame.
        last = self._last_t_us
        if last is not None and t_us < last:
            self.counters.t_us_wraps += 1
        self._last_t_us = t_us
