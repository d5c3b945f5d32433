"""Per-frame samples -> model-rate blocks (block averages by device time).

Block j holds the samples whose device time since the first sample lies in
``[j P, (j + 1) P)``, P = 1 / model_rate_hz, computed in integer microseconds.
For each block::

    rate_dph  = sum(dtheta_arcsec) / (n * frame_period_s)     mean rate over the frames received
    T_c       = mean of the valid readings of each thermometer (NaN if none): not NaN, inside PLAUSIBLE_TEMP_C
    t_end_s   = t_last - t_first + frame_period_s              device time at the end of the block

Exactness: temperatures are multiples of 1/256 degC and angle increments are
integer counts times a float32 scale, so the block sums are exact in float64
whatever the summation order; the vectorized ``run`` and the per-sample
``step`` therefore give bit-identical blocks (tested), and so does any split.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple, cast

import numpy as np

from ..flags import FLAG_GAP, FLAG_THERMOMETER_FAULT
from ..protocol import STATUS_THERMOMETER_FAULT
from ..samples.stream import Sample, SampleBlock

#: Readings outside this range (degC) are implausible for the instrument's thermometers (a saturated 127.99 degC
#: is a fault, not a temperature): they count as invalid.
PLAUSIBLE_TEMP_C = (-55.0, 125.0)


def plausible_temp(value: float) -> bool:
    """One reading: not NaN and inside ``PLAUSIBLE_TEMP_C`` (the per-sample form of ``plausible_temps``)."""
    return PLAUSIBLE_TEMP_C[0] <= value <= PLAUSIBLE_TEMP_C[1]


def plausible_temps(temps_c: np.ndarray) -> np.ndarray:
    """True where a reading is valid: not NaN and inside ``PLAUSIBLE_TEMP_C``."""
    low, high = PLAUSIBLE_TEMP_C
    temps_c = np.asarray(temps_c)
    return (temps_c >= low) & (temps_c <= high)


class ModelBlock(NamedTuple):
    index: int  # type: ignore[assignment]  # (shadows tuple.index)  #: block number since the first sample
    t_end_s: float  #: device time at the end of the block, s from the first sample
    n_samples: int
    rate_dph: float  #: mean rate over the block's frames, deg/h
    temps_c: tuple[float, ...]  #: top, bottom, housing means (NaN: no valid reading)
    flags: int


@dataclass
class BlockColumns:
    """Many ``ModelBlock`` as columns."""

    index: np.ndarray
    t_end_s: np.ndarray
    n_samples: np.ndarray
    rate_dph: np.ndarray
    temps_c: np.ndarray  #: (n, 3)
    flags: np.ndarray

    def __len__(self) -> int:
        return len(self.index)

    def block(self, i: int) -> ModelBlock:
        return ModelBlock(
            int(self.index[i]),
            float(self.t_end_s[i]),
            int(self.n_samples[i]),
            float(self.rate_dph[i]),
            tuple(float(v) for v in self.temps_c[i]),
            int(self.flags[i]),
        )

    @classmethod
    def from_blocks(cls, blocks: list[ModelBlock]) -> BlockColumns:
        if not blocks:
            return cls(
                np.zeros(0, dtype=np.int64),
                np.zeros(0, dtype=np.float64),
                np.zeros(0, dtype=np.int64),
                np.zeros(0, dtype=np.float64),
                np.zeros((0, 3)),
                np.zeros(0, np.int64),
            )
        return cls(
            np.array([b.index for b in blocks], dtype=np.int64),
            np.array([b.t_end_s for b in blocks]),
            np.array([b.n_samples for b in blocks], dtype=np.int64),
            np.array([b.rate_dph for b in blocks]),
            np.array([b.temps_c for b in blocks], dtype=np.float64),
            np.array([b.flags for b in blocks], dtype=np.int64),
        )


def _us(t_s: np.ndarray | float) -> np.ndarray:
    """Device time back to integer microseconds (t_s came from integer microseconds / 1e6)."""
    return np.rint(np.asarray(t_s) * 1e6).astype(np.int64)


class BlockAverager:
    """Block-averages samples to the model rate, with explicit state (a partly filled block).

    ``step(sample)`` returns the blocks the sample completes (at most one: the block it
    closes by starting a new one); ``run(samples)`` takes a ``SampleBlock``; ``flush()``
    closes the last, partial block at the end of a stream.
    """

    def __init__(self, frame_period_s: float, model_rate_hz: float = 1.0, n_channels: int = 3) -> None:
        if not frame_period_s > 0 or not model_rate_hz > 0:
            raise ValueError("frame_period_s and model_rate_hz must be > 0")
        #: the temperature places a format fills (a KVH: 1); the others' NaN is no thermometer fault
        self.n_channels = n_channels
        self.frame_period_s = float(frame_period_s)
        self.model_rate_hz = float(model_rate_hz)
        self.block_us = int(round(1e6 / model_rate_hz))
        self._first_us: int | None = None
        self._current = -1  # index of the open block
        self._n = 0
        self._sum_dtheta = 0.0
        self._sum_t = [0.0, 0.0, 0.0]
        self._n_t = [0, 0, 0]
        self._flags = 0
        self._last_t_us = 0

    _STATE_KEYS = (
        "frame_period_s",
        "block_us",
        "first_us",
        "current",
        "n",
        "sum_dtheta",
        "sum_t",
        "n_t",
        "flags",
        "last_t_us",
    )

    def get_state(self) -> dict:
        """The open block and the block grid, as plain YAML-safe values (exact)."""
        return {
            "frame_period_s": self.frame_period_s,
            "block_us": self.block_us,
            "first_us": self._first_us,
            "current": self._current,
            "n": self._n,
            "sum_dtheta": self._sum_dtheta,
            "sum_t": list(self._sum_t),
            "n_t": list(self._n_t),
            "flags": self._flags,
            "last_t_us": self._last_t_us,
        }

    def set_state(self, state: dict) -> None:
        """Inverse of ``get_state``; ``ValueError`` for a state of another frame period or block length."""
        if not isinstance(state, dict) or set(state) != set(self._STATE_KEYS):
            raise ValueError(f"block averager state needs exactly the keys {sorted(self._STATE_KEYS)}")
        if state["frame_period_s"] != self.frame_period_s or state["block_us"] != self.block_us:
            raise ValueError("block averager state is for another frame period or model rate")
        try:
            first = None if state["first_us"] is None else int(state["first_us"])
            sum_t = [float(v) for v in state["sum_t"]]
            n_t = [int(v) for v in state["n_t"]]
            values = (
                int(state["current"]),
                int(state["n"]),
                float(state["sum_dtheta"]),
                int(state["flags"]),
                int(state["last_t_us"]),
            )
        except (TypeError, ValueError) as exc:
            raise ValueError(f"block averager state: not numbers: {exc}") from None
        if len(sum_t) != 3 or len(n_t) != 3:
            raise ValueError("block averager state: sum_t and n_t need 3 values each")
        self._first_us, self._sum_t, self._n_t = first, sum_t, n_t
        self._current, self._n, self._sum_dtheta, self._flags, self._last_t_us = values

    @property
    def first_us(self) -> int | None:
        """The first sample's device time, us: the block grid's origin (None before any sample)."""
        return self._first_us

    @property
    def open_block(self) -> int:
        """The index of the open block, the latest sample's (-1 before any sample)."""
        return self._current

    @property
    def device_time_s(self) -> float | None:
        """The device time at the end of the latest frame, s from the first (None: no frame yet)."""
        if self._first_us is None:
            return None
        return (self._last_t_us - self._first_us) / 1e6 + self.frame_period_s

    def blocks_of(self, t_s: np.ndarray) -> np.ndarray:
        """The block index of each frame time ``t_s`` (s, int64), on the grid the samples set: ``(t_us - first_us)
        // block_us``, as ``step`` and ``run`` place frames (the grid's origin is set: call after ``run``)."""
        first_us = cast(int, self._first_us)
        return (np.rint(t_s * 1e6).astype(np.int64) - first_us) // self.block_us

    def _close(self) -> ModelBlock:
        assert self._first_us is not None  # set by the first sample, before any block closes
        temps = tuple(s / n if n else float("nan") for s, n in zip(self._sum_t, self._n_t))
        block = ModelBlock(
            self._current,
            cast(float, self.device_time_s),
            self._n,
            self._sum_dtheta / (self._n * self.frame_period_s),
            temps,
            self._flags,
        )
        self._n = 0
        self._sum_dtheta = 0.0
        self._sum_t = [0.0, 0.0, 0.0]
        self._n_t = [0, 0, 0]
        self._flags = 0
        return block

    def step(self, sample: Sample) -> list[ModelBlock]:
        t_us = round(sample.t_s * 1e6)  # ``_us`` of one value: the same float64 product, rounded half to even
        if self._first_us is None:
            self._first_us = t_us
        index = (t_us - self._first_us) // self.block_us
        done = []
        if index != self._current:
            if self._n:
                done.append(self._close())
            self._current = index
        self._n += 1
        self._sum_dtheta += sample.dtheta_arcsec
        low, high = PLAUSIBLE_TEMP_C
        for k, value in enumerate((sample.t_top_c, sample.t_bottom_c, sample.t_housing_c)):
            if low <= value <= high:  # plausible_temp: not NaN, not implausible
                self._sum_t[k] += value
                self._n_t[k] += 1
            elif k < self.n_channels:
                self._flags |= FLAG_THERMOMETER_FAULT
        if sample.status & STATUS_THERMOMETER_FAULT:
            self._flags |= FLAG_THERMOMETER_FAULT
        if sample.missing_before:
            self._flags |= FLAG_GAP
        self._last_t_us = t_us
        return done

    def flush(self) -> list[ModelBlock]:
        """Close the open (partial) block, if any: the end of the stream."""
        return [self._close()] if self._n else []

    def run(self, samples: SampleBlock, final: bool = False) -> BlockColumns:
        """Vector form of ``step`` over ``samples`` (and ``flush`` if ``final``): bit-identical blocks."""
        n = len(samples)
        if n == 0:
            return BlockColumns.from_blocks(self.flush() if final else [])
        t_us = _us(samples.t_s)
        if self._first_us is None:
            self._first_us = int(t_us[0])
        index = (t_us - self._first_us) // self.block_us
        starts = np.flatnonzero(np.r_[True, index[1:] != index[:-1]])
        # The open block continues if the first samples belong to it.
        continues = self._n > 0 and index[0] == self._current
        temps = np.column_stack([samples.t_top_c, samples.t_bottom_c, samples.t_housing_c])
        valid = plausible_temps(temps)
        sum_dtheta = np.add.reduceat(samples.dtheta_arcsec, starts)
        sum_t = np.add.reduceat(np.where(valid, temps, 0.0), starts, axis=0)
        n_t = np.add.reduceat(valid.astype(np.int64), starts, axis=0)
        count = np.diff(np.r_[starts, n])
        flags = np.where(
            np.logical_or.reduceat(~valid[:, : self.n_channels].all(axis=1), starts), FLAG_THERMOMETER_FAULT, 0
        )
        flags |= np.where(
            np.logical_or.reduceat((samples.status & STATUS_THERMOMETER_FAULT) != 0, starts), FLAG_THERMOMETER_FAULT, 0
        )
        flags |= np.where(np.logical_or.reduceat(samples.missing_before > 0, starts), FLAG_GAP, 0)
        last_t_us = t_us[np.r_[starts[1:] - 1, n - 1]]

        blocks: list[ModelBlock] = []
        first = 0
        if continues:
            # Merge the first run into the open block, then close it if more follow.
            self._n += int(count[0])
            self._sum_dtheta += float(sum_dtheta[0])
            for k in range(3):
                self._sum_t[k] += float(sum_t[0, k])
                self._n_t[k] += int(n_t[0, k])
            self._flags |= int(flags[0])
            self._last_t_us = int(last_t_us[0])
            first = 1
            if len(starts) > 1:
                blocks.append(self._close())
        elif self._n:
            blocks.append(self._close())
        # Complete blocks: all but the last run; the last run stays open.
        m = len(starts)
        inner = slice(first, m - 1)
        cols = BlockColumns(
            index=index[starts[inner]],
            t_end_s=(last_t_us[inner] - self._first_us) / 1e6 + self.frame_period_s,
            n_samples=count[inner],
            rate_dph=sum_dtheta[inner] / (count[inner] * self.frame_period_s),
            temps_c=np.where(n_t[inner] > 0, sum_t[inner] / np.maximum(n_t[inner], 1), np.nan),
            flags=flags[inner].astype(np.int64),
        )
        if first < m:
            last = m - 1
            if last >= first and not (continues and last == 0):
                self._current = int(index[starts[last]])
                self._n = int(count[last])
                self._sum_dtheta = float(sum_dtheta[last])
                self._sum_t = [float(v) for v in sum_t[last]]
                self._n_t = [int(v) for v in n_t[last]]
                self._flags = int(flags[last])
                self._last_t_us = int(last_t_us[last])
        out = BlockColumns.from_blocks(blocks)
        out = _concat(out, cols)
        if final:
            out = _concat(out, BlockColumns.from_blocks(self.flush()))
        return out


def _concat(a: BlockColumns, b: BlockColumns) -> BlockColumns:
    if not len(a):
        return b
    if not len(b):
        return a
    return BlockColumns(*(np.concatenate((getattr(a, f), getattr(b, f))) for f in BlockColumns.__dataclass_fields__))
