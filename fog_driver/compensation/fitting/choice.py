"""Choosing between models by a margin that accounts for sampling noise.

Two models' residuals on the same blocks are paired: over blocks ``b = 1..n`` (chunks of device time,
long against the residual's correlation), with ``a_b`` and ``p_b`` the mean squared residual of each
model in block ``b``::

    d_b    = a_b - p_b                          (how much more the first leaves in block b)
    margin = mean(d_b)                          ((deg/h)^2: the difference of the mean squares)
    se     = std(d_b, ddof=1) / sqrt(n)         (its standard error)

The same in deg/h, as the report prints it: ``rms_a - rms_p`` and its standard error by the delta
method, ``se / (rms_a + rms_p)`` (d(r^2) = 2 r dr at r = (rms_a + rms_p) / 2).

A choice is made only when the margin exceeds ``SE_MULTIPLE`` (2) standard errors; otherwise the
models are tied and the preferred one (the physical model, or the simpler structure) is kept.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

#: A difference counts when it exceeds this many standard errors.
SE_MULTIPLE = 2.0


class Margin(NamedTuple):
    """Paired comparison of model A's residual with model B's over ``n`` blocks (``paired_margin``)."""

    rms_a_dph: float
    rms_b_dph: float
    margin_dph: float  #: rms_a - rms_b: positive when A leaves more
    se_dph: float  #: its standard error
    n_blocks: int

    @property
    def b_better(self) -> bool:
        """B leaves less than A by more than ``SE_MULTIPLE`` standard errors."""
        return self.margin_dph > SE_MULTIPLE * self.se_dph and self.n_blocks >= 2

    @property
    def a_better(self) -> bool:
        """A leaves less than B by more than ``SE_MULTIPLE`` standard errors."""
        return -self.margin_dph > SE_MULTIPLE * self.se_dph and self.n_blocks >= 2

    @property
    def tied(self) -> bool:
        return not (self.a_better or self.b_better)

    def to_dict(self) -> dict[str, float | int]:
        return {
            "rms_a_dph": self.rms_a_dph,
            "rms_b_dph": self.rms_b_dph,
            "margin_dph": self.margin_dph,
            "se_dph": self.se_dph,
            "n_blocks": self.n_blocks,
        }


def paired_margin(squares_a: np.ndarray, squares_b: np.ndarray) -> Margin:
    """The paired margin (module docstring) from each block's mean squared residual of A and of B."""
    a = np.asarray(squares_a, dtype=float)
    b = np.asarray(squares_b, dtype=float)
    if a.shape != b.shape or a.ndim != 1:
        raise ValueError("paired_margin needs two equal 1-D arrays of block mean squares")
    n = len(a)
    if n == 0:
        return Margin(math.nan, math.nan, math.nan, math.nan, 0)
    rms_a, rms_b = math.sqrt(float(a.mean())), math.sqrt(float(b.mean()))
    d = a - b
    se_sq = float(d.std(ddof=1)) / math.sqrt(n) if n > 1 else math.inf
    scale = rms_a + rms_b
    se = se_sq / scale if scale > 0 else 0.0
    return Margin(rms_a, rms_b, rms_a - rms_b, se, n)


def block_squares(residual: np.ndarray, groups: np.ndarray, windows: np.ndarray, chunks: np.ndarray) -> np.ndarray:
    """Per chunk, the mean square of the residual's window means about each group's mean of them.

    ``residual``, ``groups`` (capture), ``windows`` (window index within the capture: the residual is
    averaged per window, e.g. 1-min or 10-min means) and ``chunks`` (chunk index within the capture, each
    window wholly in one chunk): equal-length 1-D arrays.  Returns one value per (group, chunk) that holds
    a window, in sorted order: what ``paired_margin`` pairs (the same arrays for both models give the
    same blocks)."""
    residual = np.asarray(residual, dtype=float)
    key_w = np.stack([groups, windows]).T
    uniq_w, inverse = np.unique(key_w, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    sums = np.bincount(inverse, weights=residual)
    counts = np.bincount(inverse)
    means = sums / counts
    group_of_w = uniq_w[:, 0]
    for g in np.unique(group_of_w):
        mine = group_of_w == g
        means[mine] -= means[mine].mean()
    chunk_of_w = np.zeros(len(uniq_w), dtype=np.int64)
    chunk_of_w[inverse] = chunks
    key_c = np.stack([group_of_w, chunk_of_w]).T
    _, inverse_c = np.unique(key_c, axis=0, return_inverse=True)
    inverse_c = inverse_c.ravel()
    return np.bincount(inverse_c, weights=means**2) / np.bincount(inverse_c)
