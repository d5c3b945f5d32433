"""The batch decoders' greedy accept, once: which candidate frames a sequential scan takes.

A streaming decoder that takes a valid frame jumps over it, so a candidate that starts inside a taken frame
is never looked at.  Given the valid candidates as intervals ``[start, end)`` in ascending ``start``, the
frames taken are the greedy, start-ordered, non-overlapping choice::

    take(k)  <=>  start[k] >= end[j]   for j the last taken candidate before k (always for the first)

Without overlaps (the usual case: a clean stream) that is every candidate, found with one running maximum;
the few conflicts are then resolved by a short loop over them alone.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

I64Array = npt.NDArray[np.int64]


def greedy_accept(starts: I64Array, ends: I64Array) -> npt.NDArray[np.bool_]:
    """Mask of the intervals a left-to-right scan accepts (skipping any that start inside one accepted).

    ``starts`` ascending; ``ends[k] > starts[k]`` (an open-ended interval may end at the int64 maximum).
    A candidate with no conflict (it starts at or after the end of every earlier one) is always accepted;
    for a conflicting one, the last accepted interval before it is the later of the last clean one and the
    last accepted conflicting one.
    """
    m = len(starts)
    keep = np.ones(m, dtype=bool)
    if m < 2:
        return keep
    running_end = np.maximum.accumulate(ends)
    conflict = np.zeros(m, dtype=bool)
    conflict[1:] = starts[1:] < running_end[:-1]
    if not conflict.any():
        return keep
    last_clean = np.maximum.accumulate(np.where(conflict, -1, np.arange(m)))
    last_kept_conflict = -1
    for k in np.flatnonzero(conflict).tolist():
        last = max(int(last_clean[k]), last_kept_conflict)
        if starts[k] < ends[last]:
            keep[k] = False
        else:
            last_kept_conflict = k
    return keep


__all__ = ["greedy_accept"]
