"""Output rows of ``compensate``: per-frame results aggregated over periods of device time.

Row r holds the frames whose device time since the first frame lies in
``[r E, (r + 1) E)`` (E = ``every_s``, integer microseconds); a final partial
period is a last row.  Columns::

    t_s               device time at the end of the period (last frame + one frame period), s from the first frame
    n_samples         frames received in the period
    rate_raw_dph      sum(dtheta) / (n * frame_period)          mean over the period
    drift_dph         mean of the drift applied to each frame; NaN (written ``nan``) when a frame of the period
                      has no estimate (flagged ``uncompensated``: nothing was subtracted from it)
    rate_comp_dph     sum(dtheta_comp) / (n * frame_period)     = rate_raw - drift (= rate_raw where no frame has
                      an estimate)
    angle_raw_arcsec, angle_comp_arcsec                          cumulative from the capture start to t_s
    t_top_c, t_bottom_c, t_housing_c                             means of the valid readings
    flags             the flags of any frame in the period, by name, joined by '|'
    drift_sigma_dph   mean of the drift_sigma_dph of the frames that have one (the 1-sigma of the drift
                      estimate's error as a 1-min mean); NaN (written ``nan``) when no frame has one, or
                      drift_dph is NaN (the row has no estimate, so no sigma of one)
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from typing import cast

import numpy as np

from ..compensation.pipeline import CompensatedColumns
from ..flags import flag_names


class RowAggregator:
    """Aggregates compensated frames into rows, carrying the open row across calls."""

    def __init__(self, every_s: float, frame_period_s: float) -> None:
        if not every_s > 0:
            raise ValueError("every_s must be > 0")
        self.every_us = int(round(every_s * 1e6))
        self.frame_period_s = frame_period_s
        self._first_us: int | None = None
        self._pending: CompensatedColumns | None = None  # frames of the open row

    def add(self, cols: CompensatedColumns) -> list[tuple]:
        """Rows completed by these frames."""
        if not len(cols):
            return []
        if self._pending is not None:
            cols = _concat(self._pending, cols)
        t_us = np.rint(cols.t_s * 1e6).astype(np.int64)
        if self._first_us is None:
            self._first_us = int(t_us[0])
        row = (t_us - self._first_us) // self.every_us
        last_start = int(np.flatnonzero(row == row[-1])[0])
        self._pending = _slice(cols, last_start, len(cols))
        return self._rows(_slice(cols, 0, last_start), row[:last_start], t_us[:last_start])

    def finish(self) -> list[tuple]:
        """The last, possibly partial, row."""
        if self._pending is None:
            return []
        cols, self._pending = self._pending, None
        t_us = np.rint(cols.t_s * 1e6).astype(np.int64)
        first_us = cast(int, self._first_us)  # set with the pending frames
        return self._rows(cols, (t_us - first_us) // self.every_us, t_us)

    def _rows(self, cols: CompensatedColumns, row: np.ndarray, t_us: np.ndarray) -> list[tuple]:
        n = len(row)
        if not n:
            return []
        starts = np.flatnonzero(np.r_[True, row[1:] != row[:-1]])
        ends = np.r_[starts[1:], n] - 1
        count = np.diff(np.r_[starts, n])
        period = count * self.frame_period_s
        rate_raw = np.add.reduceat(cols.dtheta_arcsec, starts) / period
        rate_comp = np.add.reduceat(cols.dtheta_comp_arcsec, starts) / period
        drift = np.add.reduceat(cols.drift_dph, starts) / count  # NaN in, NaN out: a frame without an estimate
        temps = _valid_means(cols.temps_c, starts)
        flags = np.bitwise_or.reduceat(cols.flags, starts)
        sigma = np.where(np.isnan(drift), np.nan, _valid_means(cast(np.ndarray, cols.drift_sigma_dph), starts))
        t_end = (t_us[ends] - self._first_us) / 1e6 + self.frame_period_s
        return [
            (
                t_end[i],
                int(count[i]),
                rate_raw[i],
                drift[i],
                rate_comp[i],
                cols.angle_raw_arcsec[ends[i]],
                cols.angle_comp_arcsec[ends[i]],
                *temps[i],
                "|".join(flag_names(int(flags[i]))),
                sigma[i],
            )
            for i in range(len(starts))
        ]


def _valid_means(values: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """Per row (rows begin at ``starts``; per column of a 2-D ``values``): the mean of the values that are not
    NaN, ``sum(v_i) / n_valid``; NaN when the row has none (the temperatures, the drift's sigma)."""
    valid = ~np.isnan(values)
    total = np.add.reduceat(np.where(valid, values, 0.0), starts, axis=0)
    n_valid = np.add.reduceat(valid.astype(np.int64), starts, axis=0)
    return np.where(n_valid > 0, total / np.maximum(n_valid, 1), np.nan)


def compensated_rows(chunks: Iterable[tuple[float, CompensatedColumns]], every_s: float) -> Iterator[tuple]:
    """The rows of ``compensate --every EVERY_S`` from ``apply.compensate_capture``'s (frame period,
    frames) chunks, the last partial row included (``RowAggregator``)."""
    aggregator = None
    for frame_period_s, cols in chunks:
        aggregator = aggregator or RowAggregator(every_s, frame_period_s)
        yield from aggregator.add(cols)
    if aggregator is not None:
        yield from aggregator.finish()


def _slice(c: CompensatedColumns, lo: int, hi: int) -> CompensatedColumns:
    return CompensatedColumns(*(getattr(c, f)[lo:hi] for f in CompensatedColumns.__dataclass_fields__))


def _concat(a: CompensatedColumns, b: CompensatedColumns) -> CompensatedColumns:
    return CompensatedColumns(
        *(np.concatenate((getattr(a, f), getattr(b, f))) for f in CompensatedColumns.__dataclass_fields__)
    )


def format_row(row: tuple) -> str:
    t_s, n, raw, drift, comp, a_raw, a_comp, t1, t2, t3, flags, sigma = row
    return (
        f"{t_s:.6f},{n},{raw:.6f},{drift:.6f},{comp:.6f},{a_raw:.6f},{a_comp:.6f},{t1:.4f},{t2:.4f},{t3:.4f},{flags},"
        f"{sigma:.6f}"
    )
