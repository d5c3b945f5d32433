"""The ridge solver of every fit: ridge regression on standardized columns, one intercept per capture,
and the penalty chosen by blocked cross-validation (a leaf: numbers in, weights out).

With X's columns standardized (mean m_j, scale s_j, times ``sqrt(penalty_j)``)::

    w_std = argmin |y - b - X_std w|^2 + alpha * rows * |w|^2        (``readout.ridge_fit``)
    w_j = w_std_j / s_j,   b = b_std - sum_j m_j w_j

The polynomial, the wesn's readout, the own-validation split and the thermometers' coupling
(``features.fit_substitution``) all solve with ``standardized_ridge``.
"""

from __future__ import annotations

import numpy as np

from ..readout import ridge_fit

#: Ridge penalties tried by cross-validation, relative to the number of rows (standardized columns).
ALPHA_GRID = (1e-6, 3e-6, 1e-5, 3e-5, 1e-4, 3e-4, 1e-3, 3e-3, 1e-2)


def standardized_ridge(
    x: np.ndarray, y: np.ndarray, alpha: float, penalty: np.ndarray | None = None, groups: np.ndarray | None = None
) -> tuple[np.ndarray, float]:
    """Ridge on standardized columns (penalty ``alpha * rows``), weights folded back to raw columns.

    ``penalty``: a multiplier per column (default 1): column j's standardized weight is penalized by
    ``alpha * rows * penalty[j]`` (solved by scaling the column by ``1 / sqrt(penalty[j])``).
    ``groups``: the capture each row comes from (0..K-1).  Each capture gets its own intercept (its
    target was centred on its own mean, which holds its own turn-on bias and its own mean drift), fitted
    as nearly unpenalized indicator columns and then dropped; the intercept returned is capture 0's.
    """
    if groups is not None and np.ptp(groups) > 0:
        labels = np.unique(groups)
        indicators = (np.asarray(groups)[:, None] == labels[None, 1:]).astype(np.float64)
        penalty = np.r_[np.ones(x.shape[1]) if penalty is None else penalty, np.full(len(labels) - 1, 1e-8)]
        w, b = standardized_ridge(np.column_stack([x, indicators]), y, alpha, penalty)
        return w[: x.shape[1]], b
    mean = x.mean(axis=0)
    scale = x.std(axis=0)
    scale = np.where(scale > 1e-12, scale, 1.0)
    if penalty is not None:
        scale = scale * np.sqrt(np.asarray(penalty, dtype=np.float64))
    w_std, b_std = ridge_fit((x - mean) / scale, y, alpha * len(y))
    return w_std / scale, float(b_std - (mean / scale) @ w_std)


def cross_validated_alpha(
    x: np.ndarray,
    y: np.ndarray,
    folds: int = 5,
    average_rows: int = 60,
    grid: tuple[float, ...] = ALPHA_GRID,
    penalty: np.ndarray | None = None,
    groups: np.ndarray | None = None,
) -> tuple[float, dict[float, float]]:
    """The penalty with the smallest blocked cross-validation error.

    Rows are in time order; each fold is a contiguous stretch (another part of the thermal run,
    so the score rewards extrapolation, not interpolation).  The error is the RMS of the held-out
    residual averaged over ``average_rows`` rows (1 minute at 1 Hz), its mean removed per fold:
    averaging lets the slow model error show through the white sensor noise.
    """
    edges = np.linspace(0, len(y), folds + 1).astype(int)
    scores: dict[float, float] = {}
    for alpha in grid:
        total = 0.0
        count = 0
        for lo, hi in zip(edges[:-1], edges[1:]):
            train = np.r_[0:lo, hi : len(y)]
            w, b = standardized_ridge(x[train], y[train], alpha, penalty, None if groups is None else groups[train])
            residual = y[lo:hi] - (x[lo:hi] @ w + b)  # a capture's own offset: removed with the fold's mean below
            m = len(residual) // average_rows * average_rows
            if m == 0:
                continue
            means = residual[:m].reshape(-1, average_rows).mean(axis=1)
            total += float(np.sum((means - means.mean()) ** 2))
            count += len(means)
        scores[alpha] = float(np.sqrt(total / count)) if count else float("inf")
    return min(scores, key=scores.__getitem__), scores
