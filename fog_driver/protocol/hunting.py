"""What every streaming frame decoder shares: the buffer, ``feed``/``close``, and the byte accounting.

A decoder hunts for frame headers in the bytes fed so far and decides at each header position from the
bytes from there on (h11 style: bytes in, events out; no I/O, never raises on data).  The hunt is one loop
(``_decode``); a format implements ``_find`` (where a header may start), ``_may_begin``, ``_judge`` (is a
valid frame there, and how long) and ``_emit`` (what it holds): adding a format is those four methods.
The loop keeps ``bytes_in == bytes_in_frames + bytes_discarded + pending`` in the counters.
"""

from __future__ import annotations

from typing import Generic, Protocol, TypeVar

#: Decided bytes are dropped from the buffer once this many have accumulated (or all are decided).
COMPACT_AT = 1 << 16


class HuntingCounters(Protocol):
    """The counters the hunt keeps (a format's counters have these and more)."""

    bytes_in: int
    bytes_in_frames: int
    bytes_discarded: int
    resyncs: int
    truncated_frames: int


EventT = TypeVar("EventT")
CountersT = TypeVar("CountersT", bound=HuntingCounters)


class HuntingDecoder(Generic[EventT, CountersT]):
    """Base of the streaming decoders: protocol v1's ``FrameDecoder`` and the other formats'.

    ``EventT``: what ``feed`` returns a list of; ``CountersT``: the counters' class."""

    def __init__(self, counters: CountersT) -> None:
        self.counters = counters
        self._buf = bytearray()
        self._pos = 0  # index in _buf of the first undecided byte
        self._base = 0  # stream offset of _buf[0]
        self._hunting = False  # bytes discarded since the last valid frame
        self._closed = False

    @property
    def pending(self) -> int:
        """Bytes held while waiting for the rest of a possible frame."""
        return len(self._buf) - self._pos

    @property
    def offset(self) -> int:
        """Stream offset of the first undecided byte."""
        return self._base + self._pos

    def feed(self, data: bytes | bytearray | memoryview) -> list[EventT]:
        """Add bytes; return the events they complete, in stream order."""
        if self._closed:
            raise RuntimeError("feed() after close()")
        if data:
            self.counters.bytes_in += len(data)
            self._buf += data
        return self._decode(final=False)

    def close(self) -> list[EventT]:
        """End of stream: decide every pending byte; return the last events."""
        if self._closed:
            return []
        events = self._decode(final=True)
        self._closed = True
        return events

    def _discard(self, n: int) -> None:
        self.counters.bytes_discarded += n
        self._hunting = True

    def _resynced(self) -> None:
        """A valid frame after discarded bytes: the header was found again (``resyncs``), the hunt is over."""
        self.counters.resyncs += 1
        self._hunting = False

    def _skip_to_header(self, pos: int, at: int, end: int, partial_tail: bool) -> int:
        """Discard the bytes before the header found at ``at``; with none found (``at < 0``), every byte but a
        last one that may begin a header (``partial_tail``: the caller checks that the stream is not final and
        the last byte is a header's first).  Returns the new position."""
        if at < 0:
            keep = 1 if partial_tail and end > pos else 0
            if end - keep > pos:
                self._discard(end - keep - pos)
                pos = end - keep
        elif at > pos:
            self._discard(at - pos)
            pos = at
        return pos

    def _settle(self, pos: int) -> None:
        """Keep ``pos`` as the first undecided byte; drop the decided bytes once ``COMPACT_AT`` of them have
        accumulated or all are decided."""
        if pos >= COMPACT_AT or pos == len(self._buf):
            del self._buf[:pos]
            self._base += pos
            pos = 0
        self._pos = pos

    # -- the hunt: one loop for every format; a format says where a header may start, whether a frame is
    # -- there, and what it holds

    def _find(self, buf: bytearray, pos: int) -> int:
        """Index of the next possible header at or after ``pos`` in ``buf``, -1 when there is none."""
        raise NotImplementedError

    def _may_begin(self, byte: int) -> bool:
        """Whether a last byte may be the first of a header (kept while waiting for more)."""
        raise NotImplementedError

    def _judge(self, buf: bytearray, pos: int, end: int, final: bool) -> int | None:
        """At a possible header at ``pos`` (``end``: the end of the bytes held): the length of the valid frame
        that starts there; 0 when none does (the subclass counts why: a checksum error, a bad length, a cut-off
        frame); None to wait for more bytes.  It may look only at ``buf[pos:end]``."""
        raise NotImplementedError

    def _emit(self, buf: bytearray, pos: int, n: int, events: list[EventT]) -> None:
        """Decode the valid frame of ``n`` bytes at ``pos`` into ``events`` and count it."""
        raise NotImplementedError

    def _short(self, final: bool) -> int | None:
        """A ``_judge`` verdict for a frame not all held: wait, or at the end of the stream, cut off (counted)."""
        if not final:
            return None
        self.counters.truncated_frames += 1
        return 0

    def _decode(self, final: bool) -> list[EventT]:
        """Every decision the bytes held allow: at each possible header the subclass's ``_judge`` says
        wait, no frame (ONE byte discarded, the hunt goes on from the next), or a frame (emitted, skipped)."""
        buf = self._buf
        pos = self._pos
        end = len(buf)
        events: list[EventT] = []
        while True:
            at = self._find(buf, pos)
            pos = self._skip_to_header(pos, at, end, not final and end > pos and self._may_begin(buf[end - 1]))
            if at < 0:
                break
            n = self._judge(buf, pos, end, final)
            if n is None:
                break
            if not n:
                self._discard(1)
                pos += 1
                continue
            if self._hunting:  # (checked here: the call only on the rare resync, off the per-frame path)
                self._resynced()
            self._emit(buf, pos, n, events)
            self.counters.bytes_in_frames += n
            pos += n
        self._settle(pos)
        return events
