"""Batch decoding of captures into numpy arrays, whole or block by block.

``decode_bytes(data)``, and ``BatchDecoder`` fed the same bytes in blocks of
any size, give exactly what ``FrameDecoder`` gives for the same bytes fed in
any chunks (tested as properties): the same frames at the same offsets and the
same counters.  Within a block it gets there without a Python loop per
frame:

1. every sync position ``p`` (``AA 55``) is a candidate; its verdict depends
   only on the bytes from ``p`` on: valid, CRC error, length error, or cut off
   by the end of the data (then it blocks, or, with ``final=True``, counts as
   a truncated frame and is discarded like a bad one);
2. the SAMPLE-typed candidates' payloads are gathered in one indexing call
   (through a stride-1 structured view of the bytes) and their CRCs computed
   together, by linearity (``crc.PairTables``);
   the few others use ``zlib``;
3. the streaming scan accepts a valid frame and jumps over it, so a candidate
   inside an accepted frame is never looked at: the accepted frames are the
   greedy, start-ordered, non-overlapping choice among valid candidates, which
   is every valid candidate except where intervals overlap (resolved by a
   short loop over those few: ``greedy.greedy_accept``);
4. rejected candidates outside accepted frames are the decoder's CRC and
   length errors; gaps between accepted frames are its discarded bytes.
"""

from __future__ import annotations

import zlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import BinaryIO

import numpy as np

from ..errors import InputFileError
from .crc import iso_hdlc_tables
from .decoder import DecoderCounters
from .greedy import greedy_accept
from .sequence import Unwrapper, count_seq_steps
from .wire import (
    HEADER_LEN,
    IDENTITY_PAYLOAD_LEN,
    OVERHEAD_LEN,
    SAMPLE_PAYLOAD_LEN,
    SEQ_MODULUS,
    SYNC0,
    SYNC1,
    T_US_MODULUS,
    TYPE_IDENTITY,
    TYPE_SAMPLE,
    Event,
    IdentityFrame,
    SampleFrame,
    UnknownFrame,
    parse_identity_payload,
)

#: The fields of a SAMPLE payload, in wire order: (name, little-endian numpy type).
_PAYLOAD_FIELDS: tuple[tuple[str, str], ...] = (
    ("seq", "<u2"),
    ("t_us", "<u4"),
    ("dtheta_counts", "<i4"),
    ("t_top_raw", "<i2"),
    ("t_bottom_raw", "<i2"),
    ("t_housing_raw", "<i2"),
    ("status", "<u2"),
)
#: Packed little-endian layout of a SAMPLE payload (18 bytes).
SAMPLE_PAYLOAD_DTYPE = np.dtype(list(_PAYLOAD_FIELDS))
assert SAMPLE_PAYLOAD_DTYPE.itemsize == SAMPLE_PAYLOAD_LEN
_PAYLOAD_NAMES = [name for name, _ in _PAYLOAD_FIELDS]
_PAYLOAD_FORMATS = [fmt for _, fmt in _PAYLOAD_FIELDS]
_PAYLOAD_OFFSETS = [sum(np.dtype(fmt).itemsize for fmt in _PAYLOAD_FORMATS[:k]) for k in range(len(_PAYLOAD_FORMATS))]
#: A SAMPLE frame from its payload on: the payload fields, then the stored CRC (22 bytes).
_SAMPLE_TAIL_DTYPE = np.dtype(
    {
        "names": [*_PAYLOAD_NAMES, "crc"],
        "formats": [*_PAYLOAD_FORMATS, "<u4"],
        "offsets": [*_PAYLOAD_OFFSETS, SAMPLE_PAYLOAD_LEN],
        "itemsize": SAMPLE_PAYLOAD_LEN + 4,
    }
)
_TAIL_WORDS = _SAMPLE_TAIL_DTYPE.itemsize // 2


#: CRC-32 of a SAMPLE body (type, len, 9 payload words) by linearity over GF(2) (``crc.PairTables``):
#: for the 20-byte body ``01 12 w0 .. w8`` (w_j little-endian u16), ``crc32(body) = C ^ XOR_j W_j[w_j]``
#: where ``W_j[v]`` is the raw CRC of v placed at payload word j with zeros elsewhere, and ``C =
#: crc32(01 12 00 .. 00)`` carries init, xorout and the fixed header: 9 table look-ups per frame.
_SAMPLE_CRC = iso_hdlc_tables(2 + SAMPLE_PAYLOAD_LEN).with_fixed_prefix(bytes((TYPE_SAMPLE, SAMPLE_PAYLOAD_LEN)))
_SAMPLE_WORDS = SAMPLE_PAYLOAD_LEN // 2  # 9 little-endian u16 words

_VALID, _CRC_ERROR, _LENGTH_ERROR, _TRUNCATED = 0, 1, 2, 3
_PIECE_BYTES = 1 << 20
_INFINITE_END = np.iinfo(np.int64).max


@dataclass
class SampleArrays:
    """SAMPLE frames as columns, wire values unchanged; one row per frame."""

    offset: np.ndarray  #: int64 stream offset of each frame
    seq: np.ndarray  #: uint16
    t_us: np.ndarray  #: uint32
    dtheta_counts: np.ndarray  #: int32
    t_top_raw: np.ndarray  #: int16
    t_bottom_raw: np.ndarray
    t_housing_raw: np.ndarray
    status: np.ndarray  #: uint16

    def __len__(self) -> int:
        return len(self.offset)

    @classmethod
    def from_frames(cls, frames: list[SampleFrame]) -> SampleArrays:
        """Columns from streaming events (the reference the batch path is tested against)."""
        rows = np.array([tuple(f[1:]) for f in frames], dtype=SAMPLE_PAYLOAD_DTYPE)
        offsets = np.array([f.offset for f in frames], dtype=np.int64)
        return cls(offsets, *(np.ascontiguousarray(rows[name]) for name in _PAYLOAD_NAMES))

    def frame(self, i: int) -> SampleFrame:
        return SampleFrame(
            int(self.offset[i]),
            int(self.seq[i]),
            int(self.t_us[i]),
            int(self.dtheta_counts[i]),
            int(self.t_top_raw[i]),
            int(self.t_bottom_raw[i]),
            int(self.t_housing_raw[i]),
            int(self.status[i]),
        )


@dataclass
class DecodedCapture:
    """Everything the decoder found in a byte sequence."""

    samples: SampleArrays
    identities: list[IdentityFrame]
    unknown: list[UnknownFrame]
    counters: DecoderCounters
    pending: int  #: bytes at the end still waiting for more data (0 when final)
    identity_offsets: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        self.identity_offsets = np.array([f.offset for f in self.identities], dtype=np.int64)

    def events(self) -> list[Event]:
        """All frames as streaming events, in stream order (slow; for tests and small data)."""
        merged: list[Event] = [self.samples.frame(i) for i in range(len(self.samples))]
        merged += self.identities
        merged += self.unknown
        merged.sort(key=lambda e: e.offset)
        return merged


def _u16_views(data: bytes) -> tuple[np.ndarray, np.ndarray]:
    """The data as little-endian u16 words starting at even and at odd offsets."""
    n = len(data)
    return (
        np.frombuffer(data, dtype="<u2", count=n // 2),
        np.frombuffer(data, dtype="<u2", offset=1, count=(n - 1) // 2) if n > 1 else np.zeros(0, np.uint16),
    )


def _sync_positions(views: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """Every offset holding ``AA 55`` (the u16 0x55AA), ascending."""
    sync_word = SYNC0 | (SYNC1 << 8)
    even = np.flatnonzero(views[0] == sync_word) * 2
    odd = np.flatnonzero(views[1] == sync_word) * 2 + 1
    # Two ascending runs: the stable sort (timsort) merges them in linear time.
    return np.sort(np.concatenate((even, odd)).astype(np.int64), kind="stable")


def _gather(data: bytes, at: np.ndarray, dtype: np.dtype) -> np.ndarray:
    """The ``dtype`` value stored at each byte offset in ``at`` (any alignment), as a new array.

    Indexes a stride-1, read-only view of the bytes as opaque ``void`` items
    (numpy then copies each with a plain memcpy instead of gathering a structured
    or unaligned numeric view) and reinterprets the copy.
    """
    raw = np.dtype((np.void, dtype.itemsize))
    count = max(0, len(data) - dtype.itemsize + 1)
    view = np.ndarray(shape=(count,), dtype=raw, buffer=data, offset=0, strides=(1,))
    gathered: np.ndarray = view[at].view(dtype)
    return gathered


def _classify(data: bytes, cand: np.ndarray, final: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Verdict and frame length of every sync candidate.

    Also returns the indices (into ``cand``) of the CRC-checked SAMPLE candidates
    and their payloads and stored CRCs (``_SAMPLE_TAIL_DTYPE`` rows), reused for the columns.
    """
    n = len(data)
    m = len(cand)
    verdict = np.full(m, _VALID, dtype=np.int8)
    has_header = cand + HEADER_LEN <= n
    # type | len << 8, read at every candidate in one gather.
    header = np.full(m, 0xFFFF, dtype=np.uint16)  # no header: no known type
    header[has_header] = _gather(data, cand[has_header] + 2, np.dtype("<u2"))
    frame_type = header & 0xFF
    payload_len = (header >> 8).astype(np.int64)
    payload_len[~has_header] = 0
    frame_len = payload_len + OVERHEAD_LEN
    is_sample = frame_type == TYPE_SAMPLE
    is_identity = frame_type == TYPE_IDENTITY
    length_error = (is_sample & (payload_len != SAMPLE_PAYLOAD_LEN)) | (
        is_identity & (payload_len != IDENTITY_PAYLOAD_LEN)
    )
    verdict[length_error] = _LENGTH_ERROR
    truncated = ~length_error & (cand + frame_len > n)
    verdict[truncated] = _TRUNCATED
    checkable = ~length_error & ~truncated

    sample_idx = np.flatnonzero(checkable & is_sample)
    # Every SAMPLE candidate's payload and stored CRC, 22 bytes each, in one gather.
    tails = _gather(data, cand[sample_idx] + HEADER_LEN, _SAMPLE_TAIL_DTYPE)
    tail_words = tails.view(np.uint16).reshape(-1, _TAIL_WORDS)
    crc = _SAMPLE_CRC.of_words(tail_words[:, :_SAMPLE_WORDS])
    verdict[sample_idx[crc != tails["crc"]]] = _CRC_ERROR
    for i in np.flatnonzero(checkable & ~is_sample).tolist():
        p = int(cand[i])
        crc_at = p + HEADER_LEN + int(payload_len[i])
        if zlib.crc32(data[p + 2 : crc_at]) != int.from_bytes(data[crc_at : crc_at + 4], "little"):
            verdict[i] = _CRC_ERROR
    return verdict, frame_len, sample_idx, tails


class BatchDecoder:
    """The batch decoder with explicit state, fed blocks of any size (``lfilter(zi)`` style).

    ``decode(block)`` returns the frames the block completes, as columns; the
    undecided tail (at most one frame's worth) is carried into the next call,
    together with the resync flag and the seq and t_us unwrappers, so decoding a
    capture in blocks gives exactly what ``FrameDecoder`` gives for the same
    bytes in any chunks: the same frames at the same stream offsets and the
    same cumulative ``counters``.  ``decode(block, final=True)`` ends the stream.
    """

    def __init__(self) -> None:
        self.counters = DecoderCounters()
        self._carry = b""
        self._base = 0  # stream offset of _carry[0]
        self._hunting = False
        self._seq = Unwrapper(SEQ_MODULUS)
        self._t_us = Unwrapper(T_US_MODULUS)
        self._closed = False

    @property
    def pending(self) -> int:
        return len(self._carry)

    def decode(self, block: bytes | bytearray | memoryview, final: bool = False) -> DecodedCapture:
        """Decode ``block`` (any size; large ones in 1 MiB pieces) after whatever was carried over."""
        if self._closed:
            raise RuntimeError("decode() after the final block")
        data = bytes(block)
        self.counters.bytes_in += len(data)
        parts = []
        # Pieces of about 1 MiB keep every temporary array small enough to stay in cache and be
        # reused by the allocator (benchmarks/bench_decode.py measures the decode rate).
        for start in range(0, max(len(data), 1), _PIECE_BYTES):
            piece = data[start : start + _PIECE_BYTES]
            is_last = start + _PIECE_BYTES >= len(data)
            parts.append(self._decode(self._carry + piece if self._carry else piece, final and is_last))
        self._closed = final
        return parts[0] if len(parts) == 1 else concatenate(parts)

    def _decode(self, data: bytes, final: bool) -> DecodedCapture:
        a = np.frombuffer(data, dtype=np.uint8)
        n = len(a)
        base = self._base
        cand = _sync_positions(_u16_views(data))
        verdict, frame_len, sample_idx, sample_tails = _classify(data, cand, final)

        blocking = (verdict == _TRUNCATED) & (not final)
        selectable = (verdict == _VALID) | blocking
        sel = np.flatnonzero(selectable)
        starts = cand[sel]
        ends = np.where(blocking[sel], _INFINITE_END, starts + frame_len[sel])
        keep = greedy_accept(starts, ends)
        kept = sel[keep]
        kept_starts = starts[keep]
        kept_ends = ends[keep]

        pending = 0
        if len(kept) and blocking[kept[-1]]:
            pending = n - int(kept_starts[-1])
            kept, kept_starts, kept_ends = kept[:-1], kept_starts[:-1], kept_ends[:-1]
        elif not final and n and a[-1] == SYNC0 and (not len(kept_ends) or kept_ends[-1] < n):
            pending = 1

        # Rejected candidates the scan actually reached: not inside an accepted frame, before the pending tail.
        rejected = np.flatnonzero(~selectable)
        rej_pos = cand[rejected]
        if len(kept_starts):
            j = np.searchsorted(kept_starts, rej_pos, side="right") - 1
            covered = (j >= 0) & (rej_pos < kept_ends[np.maximum(j, 0)])
        else:
            covered = np.zeros(len(rejected), dtype=bool)
        reached = ~covered & (rej_pos < n - pending)
        rej_verdict = verdict[rejected][reached]

        c = self.counters
        in_frames = int((kept_ends - kept_starts).sum())
        c.bytes_in_frames += in_frames
        c.bytes_discarded += n - in_frames - pending
        c.crc_errors += int(np.count_nonzero(rej_verdict == _CRC_ERROR))
        c.length_errors += int(np.count_nonzero(rej_verdict == _LENGTH_ERROR))
        c.truncated_frames += int(np.count_nonzero(rej_verdict == _TRUNCATED))
        if len(kept_starts):
            # A frame is a resync when bytes were discarded since the previous frame (in this block or before).
            previous_ends = np.concatenate(([-1 if self._hunting else 0], kept_ends[:-1]))
            c.resyncs += int(np.count_nonzero(kept_starts > previous_ends))
            self._hunting = n - pending > int(kept_ends[-1])
        else:
            self._hunting = self._hunting or n - pending > 0

        kinds = a[kept_starts + 2] if len(kept_starts) else np.zeros(0, np.uint8)
        kept_samples = kept[kinds == TYPE_SAMPLE]
        if len(kept_samples) == len(sample_idx):  # the usual case: every SAMPLE candidate was accepted
            tails = sample_tails
        else:
            tails = sample_tails[np.searchsorted(sample_idx, kept_samples)]
        samples = SampleArrays(
            cand[kept_samples] + base, *(np.ascontiguousarray(tails[name]) for name in _PAYLOAD_NAMES)
        )
        identities = []
        unknown = []
        for p, kind in zip(kept_starts[kinds != TYPE_SAMPLE].tolist(), kinds[kinds != TYPE_SAMPLE].tolist()):
            payload = data[p + HEADER_LEN : p + HEADER_LEN + data[p + 3]]
            if kind == TYPE_IDENTITY:
                identities.append(parse_identity_payload(base + p, payload))
            else:
                unknown.append(UnknownFrame(base + p, kind, payload))
        c.sample_frames += len(samples)
        c.identity_frames += len(identities)
        c.unknown_frames += len(unknown)
        self._count_sequence(samples)

        self._carry = data[n - pending :] if pending else b""
        self._base = base + n - pending
        return DecodedCapture(samples, identities, unknown, replace(c), pending)

    def _count_sequence(self, samples: SampleArrays) -> None:
        if not len(samples):
            return
        count_seq_steps(self.counters, self._seq.advance(samples.seq).steps_taken)
        wraps = self._t_us.wraps
        self._t_us.advance(samples.t_us)
        self.counters.t_us_wraps += self._t_us.wraps - wraps


#: A whole SAMPLE frame, for the vectorized encoder.
_SAMPLE_FRAME_DTYPE = np.dtype(
    {
        "names": ["sync", "type", "len", *_PAYLOAD_NAMES, "crc"],
        "formats": ["<u2", "u1", "u1", *_PAYLOAD_FORMATS, "<u4"],
        "offsets": [0, 2, 3, *(HEADER_LEN + offset for offset in _PAYLOAD_OFFSETS), HEADER_LEN + SAMPLE_PAYLOAD_LEN],
        "itemsize": HEADER_LEN + SAMPLE_PAYLOAD_LEN + 4,
    }
)


def encode_sample_frames(
    seq: np.ndarray,
    t_us: np.ndarray,
    dtheta_counts: np.ndarray,
    t_top_raw: np.ndarray,
    t_bottom_raw: np.ndarray,
    t_housing_raw: np.ndarray,
    status: np.ndarray,
) -> np.ndarray:
    """Many SAMPLE frames at once: the vector form of ``encode_sample`` (identical bytes, tested).

    Returns a (count, 26) uint8 array, one frame per row; ``seq`` and ``t_us``
    are wrapped to 16 and 32 bits here.  The CRC uses the same linearity tables
    as the batch decoder.
    """
    frames = np.zeros(len(seq), dtype=_SAMPLE_FRAME_DTYPE)
    frames["sync"] = SYNC0 | (SYNC1 << 8)
    frames["type"] = TYPE_SAMPLE
    frames["len"] = SAMPLE_PAYLOAD_LEN
    frames["seq"] = np.asarray(seq) % SEQ_MODULUS
    frames["t_us"] = np.asarray(t_us) % (1 << 32)
    for name, values in (
        ("dtheta_counts", dtheta_counts),
        ("t_top_raw", t_top_raw),
        ("t_bottom_raw", t_bottom_raw),
        ("t_housing_raw", t_housing_raw),
        ("status", status),
    ):
        frames[name] = values
    words = frames.view(np.uint16).reshape(len(frames), _SAMPLE_FRAME_DTYPE.itemsize // 2)
    words = words[:, HEADER_LEN // 2 : HEADER_LEN // 2 + _SAMPLE_WORDS]
    frames["crc"] = _SAMPLE_CRC.of_words(words)
    return frames.view(np.uint8).reshape(len(frames), _SAMPLE_FRAME_DTYPE.itemsize)


def decode_bytes(data: bytes | bytearray | memoryview, final: bool = True) -> DecodedCapture:
    """Decode a whole byte sequence; equals ``FrameDecoder`` fed the same bytes (then ``close()`` if final)."""
    return BatchDecoder().decode(data, final=final)


#: Block size for decoding files: big enough that numpy's per-call costs vanish, small enough for bounded memory.
FILE_BLOCK_BYTES = 16 << 20


def iter_decode_file(
    path: str | Path,
    block_bytes: int = FILE_BLOCK_BYTES,
    on_block: Callable[[bytes], None] | None = None,
) -> Iterator[DecodedCapture]:
    """Decode a capture file block by block (bounded memory); each part carries the cumulative counters.

    ``on_block`` sees every raw block as read (for hashing or progress).  A file that cannot be opened is
    an ``InputFileError`` (one line: the path and the reason).
    """
    decoder = BatchDecoder()
    for block, final in iter_file_blocks(path, block_bytes, on_block):
        yield decoder.decode(block, final=final)


def iter_file_blocks(
    path: str | Path, block_bytes: int = FILE_BLOCK_BYTES, on_block: Callable[[bytes], None] | None = None
) -> Iterator[tuple[bytes, bool]]:
    """A capture file's ``(block, final)`` pairs, ``final`` True for the last (an empty file: one empty
    block); ``on_block`` sees every block as read.  A file that cannot be opened is an ``InputFileError``."""
    with _open_capture(path) as f:
        block = f.read(block_bytes)
        while True:
            following = f.read(block_bytes) if block else b""
            if on_block and block:
                on_block(block)
            yield block, not following
            if not following:
                return
            block = following


def _open_capture(path: str | Path) -> BinaryIO:
    """``path`` opened for reading; one that cannot be opened is an ``InputFileError`` (one line)."""
    try:
        return Path(path).open("rb")
    except OSError as exc:
        raise InputFileError(f"{path}: cannot read the capture: {exc.strerror or exc}") from None


def concatenate(parts: list[DecodedCapture]) -> DecodedCapture:
    """One ``DecodedCapture`` from consecutive parts (counters and pending from the last)."""
    if not parts:
        return decode_bytes(b"")
    columns = [np.concatenate([getattr(p.samples, name) for p in parts]) for name in SampleArrays.__dataclass_fields__]
    return DecodedCapture(
        SampleArrays(*columns),
        [f for p in parts for f in p.identities],
        [f for p in parts for f in p.unknown],
        parts[-1].counters,
        parts[-1].pending,
    )


def decode_file(path: str | Path, block_bytes: int = FILE_BLOCK_BYTES) -> DecodedCapture:
    """Read and decode a whole capture file (end of stream included), block by block."""
    return concatenate(list(iter_decode_file(path, block_bytes)))
