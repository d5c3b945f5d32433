"""The window of blocks: the cumulative sums of the chain's blocks, kept at each block's middle on a ring.

Each block j of the model (length ``B = block_s``) adds a row of increments to the chain's running sums
(``Columns``): the shape regressors ``g_j B``, the time ``B``, the ring temperature ``T_j B``, the gyro's angle
``m_j dur_j`` (m_j the block's mean rate, deg/h = arcsec/s, dur_j the time its frames span), a 1 for a block
with degraded inputs and one for a block not clean for the warm-up alone, and the frozen drift ``D_hat_j B``.
The ring keeps, for the last ``MAX_WINDOW_S``, the sums at each block's middle (the sums before it plus half
its row) and the block's rate.

A dwell's summary (``BlockWindow.means``) is the mean of those middle sums over the whole blocks inside its
trimmed window; the difference of two dwells' summaries (``WindowSums.between``) is each sum under a kernel K
that rises linearly over the first window, is 1 between the windows and falls over the second::

    theta = sum_j K_j m_j dur_j        x = sum_j K_j g_j B        T_eff = sum_j K_j B
    T_int = sum_j K_j T_j B / T_eff    F = sum_j K_j D_hat_j B

A break (a gap, a restart, ``?ZERO``, a block that cannot be integrated) empties the ring and starts a new
epoch: no interval spans it.  ``BlockWindow.get_state`` is the ring as plain values (its blocks' rows oldest first,
exact), ``set_state`` its inverse.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np

__all__ = ["MAX_WINDOW_S", "Anchor", "BlockWindow", "Columns", "WindowSums"]

#: The most of a dwell's window the law looks back over (the ring of blocks it keeps).
MAX_WINDOW_S = 3600.0


class WindowSums(NamedTuple):
    """The sums of a row (or of a difference of rows) by name: over an interval, x, T_eff, T_int T_eff, theta,
    F (module docstring) and the count of degraded and warm-up blocks under the kernel."""

    shape: np.ndarray  # x: the shape regressors' sums (B each block)
    time_s: float  # T_eff
    temperature_c_s: float  # T_int T_eff
    angle_arcsec: float  # theta
    degraded_blocks: float
    frozen_arcsec: float  # F
    warmup_blocks: float


class Columns:
    """The layout of a row of the ring: the shape regressors' ``n_shape`` columns, then one column for each of
    the other sums of ``WindowSums``, in its order."""

    def __init__(self, n_shape: int) -> None:
        self.n_shape = n_shape
        self.shape = slice(0, n_shape)
        self.time_s, self.temperature_c_s, self.angle_arcsec, self.degraded_blocks, self.frozen_arcsec = range(
            n_shape, n_shape + 5
        )
        self.warmup_blocks = n_shape + 5
        self.width = n_shape + 6

    def increment(
        self,
        g: np.ndarray,
        y_frozen: float,
        block_s: float,
        t_ring_c: float,
        rate_dph: float,
        frames_s: float,
        clean: bool,
        warming_up: bool,
    ) -> np.ndarray:
        """One block's row: ``g B``, ``B``, ``T B``, ``m dur``, degraded (1 unless clean), ``D_hat B``
        (``y_frozen``), warm-up (1 when not clean for the warm-up alone)."""
        inc = np.empty(self.width)
        inc[self.shape] = g
        inc[self.shape] *= block_s
        inc[self.time_s] = block_s
        inc[self.temperature_c_s] = t_ring_c * block_s
        inc[self.angle_arcsec] = rate_dph * frames_s
        inc[self.degraded_blocks] = 0.0 if clean else 1.0
        inc[self.frozen_arcsec] = y_frozen * block_s
        inc[self.warmup_blocks] = 1.0 if warming_up and not clean else 0.0
        return inc

    def named(self, row: np.ndarray) -> WindowSums:
        """``row``'s sums by name (the shape's a view of it)."""
        return WindowSums(
            row[self.shape],
            float(row[self.time_s]),
            float(row[self.temperature_c_s]),
            float(row[self.angle_arcsec]),
            float(row[self.degraded_blocks]),
            float(row[self.frozen_arcsec]),
            float(row[self.warmup_blocks]),
        )

    def between(self, start: np.ndarray, end: np.ndarray) -> WindowSums:
        """The sums from row ``start`` to row ``end`` (``end - start``)."""
        return self.named(end - start)


class Anchor(NamedTuple):
    """A dwell as the start or end of an interval: its summary (``BlockWindow.means``), the table's angle at it
    (arcsec), its window (``window_blocks`` whole blocks, ``first_block`` to ``end_block``) and the chain's
    epoch it belongs to."""

    summary: np.ndarray
    angle_arcsec: float
    window_blocks: int
    first_block: int
    end_block: int
    epoch: int


class BlockWindow:
    """The ring of the chain's blocks (module docstring): ``add`` a block's row, ``means`` over a dwell's
    blocks, ``rates`` of its blocks; ``break_chain`` starts afresh."""

    def __init__(self, n_shape: int, block_s: float) -> None:
        self.columns = Columns(n_shape)
        self.block_s = float(block_s)
        self.capacity = max(2, int(math.ceil(MAX_WINDOW_S / self.block_s)) + 2)
        self._mid = np.zeros((self.capacity, self.columns.width))
        self._rate = np.zeros(self.capacity)
        self.epoch = 0
        self.break_chain()

    def break_chain(self) -> None:
        """A new epoch: the sums from zero, no block on the ring."""
        self.epoch += 1
        self._cum = np.zeros(self.columns.width)
        #: the block index at the ring's oldest position (None: no block since the break)
        self.first: int | None = None
        self._length = 0
        self._pos0 = 0
        #: blocks were dropped off the ring's old end (not a break)
        self.dropped_old = False
        #: device time the chain of blocks began at (its first block's start), None before a block
        self.chain_start_s: float | None = None

    def follows(self, index: int) -> bool:
        """Block ``index`` is the next of the chain (or the first)."""
        return self.first is None or index == self.first + self._length

    def add(self, index: int, inc: np.ndarray, rate_dph: float) -> None:
        """Block ``index`` (the next of the chain) with its row ``inc`` and mean rate; the oldest block drops
        off a full ring."""
        mid = self._cum + 0.5 * inc
        self._cum += inc
        if self.first is None:
            self.first, self._pos0, self._length = index, 0, 0
            self.chain_start_s = index * self.block_s
        if self._length == self.capacity:  # the oldest block drops off
            self._pos0 = (self._pos0 + 1) % self.capacity
            self.first += 1
            self._length -= 1
            self.dropped_old = True
        pos = (self._pos0 + self._length) % self.capacity
        self._mid[pos] = mid
        self._rate[pos] = rate_dph
        self._length += 1

    @property
    def last_block(self) -> int | None:
        """The index of the newest block since the last break (None: none)."""
        return None if self.first is None else self.first + self._length - 1

    def _positions(self, first: int, end: int) -> np.ndarray:
        assert self.first is not None
        return (self._pos0 + np.arange(first - self.first, end - self.first)) % self.capacity

    def middles(self, first: int, end: int) -> np.ndarray:
        """The sums at the middles of blocks ``first`` to ``end`` (exclusive), one row each."""
        return self._mid[self._positions(first, end)]

    def means(self, first: int, end: int) -> np.ndarray:
        """The mean of the middle sums over blocks ``first`` to ``end``: a dwell's summary."""
        return self.middles(first, end).mean(axis=0)

    def rates(self, first: int, end: int) -> np.ndarray:
        """The mean rates of blocks ``first`` to ``end``."""
        return self._rate[self._positions(first, end)]

    def get_state(self) -> dict[str, Any]:
        """The chain's blocks as plain values (exact): the epoch, the running sums, the first block's index and
        the chain's start, whether old blocks were dropped, and the middle sums and rates of the blocks on the
        ring, oldest first."""
        live = (self._pos0 + np.arange(self._length)) % self.capacity
        return {
            "epoch": self.epoch,
            "sums": self._cum.tolist(),
            "first": self.first,
            "chain_start_s": self.chain_start_s,
            "dropped_old": self.dropped_old,
            "middles": self._mid[live].tolist(),
            "rates": self._rate[live].tolist(),
        }

    def set_state(self, state: dict[str, Any]) -> None:
        """Inverse of ``get_state`` (the oldest block at the ring's start); ``ValueError`` (nothing changed) for
        values that do not fit this ring."""
        mid = np.array(state["middles"], dtype=np.float64).reshape(-1, self.columns.width)
        rate = np.array(state["rates"], dtype=np.float64)
        cum = np.array(state["sums"], dtype=np.float64)
        first = None if state["first"] is None else int(state["first"])
        start = None if state["chain_start_s"] is None else float(state["chain_start_s"])
        n = len(mid)
        if cum.shape != (self.columns.width,) or rate.shape != (n,) or n > self.capacity or (first is None) != (n == 0):
            raise ValueError(f"the ring's state does not fit a ring of {self.capacity} blocks of {self.columns.width}")
        self.epoch, self._cum, self.first, self.chain_start_s = int(state["epoch"]), cum, first, start
        self.dropped_old = bool(state["dropped_old"])
        self._mid[:n], self._rate[:n] = mid, rate
        self._pos0, self._length = 0, n
