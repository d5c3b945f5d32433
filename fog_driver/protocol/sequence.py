"""Sequence counters and clocks that wrap, unwrapped once: a step form and a vector form that agree exactly.

A counter of modulus ``M`` reads ``r(n) = u(n) mod M``; the unwrapped value follows it by the smallest
step that explains the reading::

    u(0) = r(0)
    u(n) = u(n-1) + d(n),   d(n) = (r(n) - r(n-1)) mod M              in [0, M)       (forward only)
                            d(n) = ((r(n) - r(n-1) + M/2) mod M) - M/2  in [-M/2, M/2)  (``signed``)

Forward-only suits a frame counter or a clock that never runs back (protocol v1's seq and t_us, KVH's
7-bit counter, STDBIN's counter); ``signed`` reads a step of half the range or more as a small step back
(STDBIN's validity time).  ``wraps`` counts the steps forward across the modulus (``r(n) < r(n-1)`` and
``d(n) > 0``).  For a sequence counter, ``d = 1`` is the next frame, ``d = 0`` a repeat and ``d = k > 1``
a gap of ``k - 1`` missing frames: ``count_seq_step`` and ``count_seq_steps`` add those to a decoder's
counters.

``Unwrapper.step(raw)`` takes one reading, ``Unwrapper.run(raw)`` an array of them; both start from and
update the same state, so any split of a stream into pieces gives the same values, steps and counts
(tested at every split point).
"""

from __future__ import annotations

from typing import NamedTuple, Protocol

import numpy as np
import numpy.typing as npt

I64Array = npt.NDArray[np.int64]


class SeqCounters(Protocol):
    """The sequence counters a decoder keeps (``DecoderCounters``, ``FormatCounters``)."""

    seq_gaps: int
    missing_frames: int
    seq_repeats: int


class Steps(NamedTuple):
    """What ``Unwrapper.advance`` found: one row per reading."""

    step: npt.NDArray[np.integer]  #: d(n), the step from the reading before (0 for the stream's first reading)
    first: bool  #: whether row 0 is the stream's first reading (its step is no step)

    @property
    def steps_taken(self) -> npt.NDArray[np.integer]:
        """The steps from a previous reading: ``step`` without the stream's first reading."""
        return self.step[1:] if self.first else self.step


class Unwrapped(NamedTuple):
    """What ``Unwrapper.run`` found: one row per reading."""

    value: I64Array  #: u(n), the unwrapped values
    step: I64Array  #: d(n), the step from the reading before (0 for the stream's first reading)
    first: bool  #: whether row 0 is the stream's first reading (its step is no step)

    @property
    def steps_taken(self) -> I64Array:
        """The steps from a previous reading: ``step`` without the stream's first reading."""
        return self.step[1:] if self.first else self.step


class Unwrapper:
    """The unwrapped value of a counter of modulus ``modulus`` (module docstring), with explicit state.

    ``last_raw`` (None before the first reading), ``value`` (u of the last reading), ``delta`` (the last
    step taken, None after the stream's first reading) and ``wraps`` (steps forward across the modulus).
    """

    __slots__ = ("delta", "half", "last_raw", "mask", "modulus", "signed", "value", "wraps")

    def __init__(self, modulus: int, signed: bool = False) -> None:
        if modulus < 2:
            raise ValueError("the modulus must be at least 2")
        self.modulus = modulus
        self.signed = signed
        self.half = modulus // 2
        #: ``modulus - 1`` for a power of two (then ``x mod M == x & (M - 1)`` in two's complement: numpy's
        #: integer ``%`` is many times slower than ``&``), else None.
        self.mask = modulus - 1 if modulus & (modulus - 1) == 0 else None
        self.last_raw: int | None = None
        self.value = 0
        self.delta: int | None = None
        self.wraps = 0

    def step(self, raw: int) -> int | None:
        """Take the next reading ``raw`` (``0 <= raw < modulus``): its step d (None for the stream's first
        reading, also kept as ``delta``); ``value`` is then its unwrapped value."""
        last = self.last_raw
        self.last_raw = raw
        if last is None:
            self.delta = None
            self.value = raw
            return None
        d = (raw - last) % self.modulus
        if d >= self.half and self.signed:
            d -= self.modulus
        elif raw < last:  # a forward step (d > 0) to a smaller reading: across the modulus
            self.wraps += 1
        self.delta = d
        self.value += d
        return d

    def advance(self, raw: npt.ArrayLike) -> Steps:
        """``step`` over every reading of ``raw`` (one-dimensional) at once, without the unwrapped values:
        the steps and the same state after.

        The steps keep ``raw``'s dtype when it is unsigned and wide enough for a power-of-two modulus (the
        subtraction wraps modulo its width, a multiple of the modulus, and the mask finishes it): no int64
        temporaries, which for a 1 MiB piece of frames would leave the allocator's reused blocks."""
        r = np.asarray(raw)
        n = len(r)
        first = self.last_raw is None
        if n == 0:
            return Steps(np.zeros(0, np.int64), False)
        mask = self.mask
        if mask is None or self.signed or r.dtype.kind != "u" or mask > np.iinfo(r.dtype).max:
            r = r.astype(np.int64)
        previous = np.empty_like(r)
        previous[0] = r[0] if first else self.last_raw
        previous[1:] = r[:-1]
        steps = r - previous
        if mask is not None:
            steps &= mask
        else:
            steps %= self.modulus
        if self.signed:
            steps[steps >= self.half] -= self.modulus
        self.wraps += int(np.count_nonzero((r < previous) & (steps > 0)))
        self.value = (int(r[0]) if first else self.value) + int(steps.sum(dtype=np.int64))
        self.last_raw = int(r[-1])
        self.delta = None if first and n == 1 else int(steps[-1])
        return Steps(steps, first)

    def run(self, raw: npt.ArrayLike) -> Unwrapped:
        """``step`` over every reading of ``raw`` (one-dimensional), at once: the same values, steps and
        state (steps as int64)."""
        r = np.asarray(raw)
        start = int(r[0]) if self.last_raw is None and len(r) else self.value
        steps, first = self.advance(r)
        values = start + np.cumsum(steps, dtype=np.int64)
        return Unwrapped(values, steps.astype(np.int64), first)


def count_seq_step(counters: SeqCounters, delta: int | None) -> None:
    """Count one sequence step (None: the stream's first frame): 0 a repeat, k > 1 a gap of k - 1 frames."""
    if delta is None or delta == 1:
        return
    if delta == 0:
        counters.seq_repeats += 1
    elif delta > 1:
        counters.seq_gaps += 1
        counters.missing_frames += delta - 1


def count_seq_steps(counters: SeqCounters, steps: npt.NDArray[np.integer]) -> None:
    """``count_seq_step`` over the steps taken (``Unwrapped.steps_taken``), at once."""
    gaps = steps > 1
    n_gaps = int(np.count_nonzero(gaps))
    counters.seq_gaps += n_gaps
    counters.missing_frames += int(steps[gaps].sum(dtype=np.int64)) - n_gaps
    counters.seq_repeats += int(np.count_nonzero(steps == 0))


def missing_before(steps: I64Array) -> I64Array:
    """Frames lost just before each reading: ``d - 1`` where ``d > 1``, else 0."""
    return np.where(steps > 1, steps - 1, 0)


__all__ = ["SeqCounters", "Steps", "Unwrapped", "Unwrapper", "count_seq_step", "count_seq_steps", "missing_before"]
