"""Fitting the paper's comparator, ``pso-svr`` (``models.svr``: the model and what its rows and
hyperparameters are): a particle swarm (``pso_minimize``) over log10 (C, gamma, epsilon) minimizing
the blocked cross-validation RMS of an RBF SVR on 1-minute rows, then the final SVR on all rows and
one offset per capture by backfitting (y_k = f(z) + a_k, a_0 = 0).

scikit-learn's ``SVR`` is an optional extra (``svr``): it is imported inside the fit (``_import_svr``).
"""

from __future__ import annotations

import itertools
import math
import threading
import warnings
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from ...errors import UsageError
from ...extras import missing_message
from ..models.svr import SvrModel

MISSING_SKLEARN = missing_message("svr", "fitting a pso-svr model", ["scikit-learn"])


def pso_minimize(
    f: Callable[[np.ndarray], float],
    bounds: Sequence[tuple[float, float]],
    n_particles: int = 16,
    iterations: int = 20,
    seed: int = 0,
    inertia: float = 0.72,
    c1: float = 1.49,
    c2: float = 1.49,
    *,
    map_fn: Callable = map,
) -> tuple[np.ndarray, float]:
    """Minimize ``f`` over the box ``bounds`` by a global-best particle swarm; returns ``(best_x, best_f)``.

    Particles start uniformly in the box with velocities uniform in +-half its width; each iteration
    ``v = inertia v + c1 r1 (personal best - x) + c2 r2 (swarm best - x)`` (r1, r2 uniform per
    coordinate), velocities clamped to the box width, positions clipped to the box (and the velocity
    component that hit a wall zeroed).  ``f`` is evaluated ``n_particles * (iterations + 1)`` times,
    a swarm at a time through ``map_fn(f, points)`` (``map``, or e.g. a thread pool's ``map``: the
    result does not depend on it for a deterministic ``f``); a non-finite value counts as +inf; ties
    keep the earlier point.  Seeded (``numpy.random.default_rng(seed)``): the same arguments give the
    same result.
    """
    lo = np.array([float(b[0]) for b in bounds])
    hi = np.array([float(b[1]) for b in bounds])
    if lo.ndim != 1 or not len(lo) or not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(hi > lo)):
        raise ValueError(f"bounds must be finite (lo, hi) pairs with hi > lo, got {list(bounds)!r}")
    if n_particles < 1 or iterations < 0:
        raise ValueError("n_particles must be >= 1 and iterations >= 0")
    rng = np.random.default_rng(seed)
    span = hi - lo
    n, d = int(n_particles), len(lo)
    x = lo + rng.random((n, d)) * span
    v = (rng.random((n, d)) - 0.5) * span

    def evaluate(points: np.ndarray) -> np.ndarray:
        values = np.array([float(v) for v in map_fn(f, [p.copy() for p in points])])
        return np.where(np.isfinite(values), values, np.inf)

    best_x = x.copy()
    best_f = evaluate(x)
    g = int(np.argmin(best_f))
    for _ in range(int(iterations)):
        r1 = rng.random((n, d))
        r2 = rng.random((n, d))
        v = inertia * v + c1 * r1 * (best_x - x) + c2 * r2 * (best_x[g] - x)
        v = np.clip(v, -span, span)
        x = x + v
        wall = (x < lo) | (x > hi)
        x = np.clip(x, lo, hi)
        v[wall] = 0.0
        fx = evaluate(x)
        better = fx < best_f
        best_x[better] = x[better]
        best_f[better] = fx[better]
        g = int(np.argmin(best_f))
    return best_x[g].copy(), float(best_f[g])


@dataclass(frozen=True)
class PsoSvrConfig:
    c_bounds: tuple[float, float] = (1e-2, 1e3)
    gamma_bounds: tuple[float, float] = (1e-3, 1e1)
    epsilon_bounds_dph: tuple[float, float] = (1e-4, 1e-1)
    n_particles: int = 16
    iterations: int = 20
    seed: int = 0
    folds: int = 3
    average_s: float = 60.0  #: rows: averages over whole static windows this long ...
    min_rows: int = 30  #: ... or shorter ones (down to one block) when that gives fewer rows (a short capture)
    #: libsvm iterations per SVR fit during the search (large C with large gamma can take millions; such a
    #: fit is scored as it stands: deterministic, and those corners overfit anyway)
    max_iter: int = 30_000
    final_max_iter: int = 1_000_000  #: the chosen point's fit on all rows
    workers: int = 2  #: threads evaluating the swarm (libsvm releases the GIL); the result does not depend on it


PSO_SVR_DEFAULTS = PsoSvrConfig()


def _import_svr():
    try:
        from sklearn.exceptions import ConvergenceWarning  # type: ignore[import-untyped]  # optional extra: svr
        from sklearn.svm import SVR  # type: ignore[import-untyped]
    except ImportError:
        raise UsageError(MISSING_SKLEARN) from None
    return SVR, ConvergenceWarning


def window_blocks(captures, model_rate_hz: float, average_s: float = 60.0, min_rows: int = 30) -> int:
    """Blocks per averaging window: ``average_s``, shortened (to the static blocks / ``min_rows``, at
    least 1) when the captures have too few static blocks for ``min_rows`` full windows."""
    per = max(1, int(round(average_s * model_rate_hz)))
    static_blocks = sum(int(c.static.sum()) for c in captures)
    return max(1, min(per, static_blocks // max(1, min_rows)))


def minute_rows(
    captures, normalizer, model_rate_hz: float, average_s: float = 60.0, per: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Averages of the standardized inputs and of the target over whole static windows of ``average_s``
    (or ``per`` blocks), aligned with each capture's first block, in time order, captures one after
    another: (z (m, 8), y (m,))."""
    if per is None:
        per = max(1, int(round(average_s * model_rate_hz)))
    zs, ys = [], []
    for c in captures:
        n = len(c.target_dph) // per * per
        finite = np.all(np.isfinite(c.inputs), axis=1)
        z = normalizer.transform(np.where(np.isfinite(c.inputs), c.inputs, 0.0))
        ok = (c.static & finite)[:n].reshape(-1, per).all(axis=1)
        zs.append(z[:n].reshape(-1, per, z.shape[1])[ok].mean(axis=1))
        ys.append(c.target_dph[:n].reshape(-1, per)[ok].mean(axis=1))
    return np.vstack(zs), np.concatenate(ys)


def blocked_cv_rms(svr_factory, z: np.ndarray, y: np.ndarray, folds: int = 3) -> float:
    """RMS of the held-out residual over ``folds`` contiguous folds, each fold's mean removed."""
    edges = np.linspace(0, len(y), folds + 1).astype(int)
    total, count = 0.0, 0
    for lo, hi in zip(edges[:-1], edges[1:]):
        if hi - lo < 1:
            continue
        train = np.r_[0:lo, hi : len(y)]
        model = svr_factory().fit(z[train], y[train])
        r = y[lo:hi] - model.predict(z[lo:hi])
        total += float(np.sum((r - r.mean()) ** 2))
        count += hi - lo
    return math.sqrt(total / count) if count else math.inf


#: Backfitting passes for the per-capture offsets of a multi-capture fit: y_k = f(z) + a_k, f refitted
#: on y - a, a_k the mean of capture k's residual (a_0 = 0); the offsets settle in two or three.
OFFSET_PASSES = 3


def fit_pso_svr(captures, normalizer, config, settings: PsoSvrConfig = PSO_SVR_DEFAULTS, progress=None) -> SvrModel:
    """Fit a ``pso-svr`` model (module docstring); ``UsageError`` without scikit-learn.  ``progress(text)``
    hears the swarm's iteration and particle ("pso-svr: iteration 4/20, particle 12/16 (21 %)")."""
    SVR, ConvergenceWarning = _import_svr()
    per = window_blocks(captures, config.model_rate_hz, settings.average_s, settings.min_rows)
    parts = [minute_rows([c], normalizer, config.model_rate_hz, per=per) for c in captures]
    z, y = np.vstack([p[0] for p in parts]), np.concatenate([p[1] for p in parts])
    group = np.concatenate([np.full(len(p[1]), k) for k, p in enumerate(parts)])
    if len(y) < 2 * settings.folds:
        raise ValueError(f"pso-svr: {len(y)} whole static minutes to fit, need at least {2 * settings.folds}")

    def make(log_params: np.ndarray, max_iter: int = settings.max_iter):
        c, gamma, eps = (float(v) for v in 10.0 ** np.asarray(log_params))
        return lambda: SVR(kernel="rbf", C=c, gamma=gamma, epsilon=eps, max_iter=max_iter)

    bounds = [
        (math.log10(lo), math.log10(hi))
        for lo, hi in (settings.c_bounds, settings.gamma_bounds, settings.epsilon_bounds_dph)
    ]
    n, total = settings.n_particles, settings.n_particles * (settings.iterations + 1)
    done = itertools.count()
    lock = threading.Lock()

    def score_of(p: np.ndarray) -> float:
        value = blocked_cv_rms(make(p), z, y, settings.folds)
        if progress is not None:
            with lock:  # the pool's threads report one at a time
                k = next(done)
                progress(
                    f"pso-svr: iteration {k // n}/{settings.iterations}, particle {k % n + 1}/{n} "
                    f"({100 * (k + 1) / total:.0f} %)"
                )
        return value

    with warnings.catch_warnings(), ThreadPoolExecutor(max(1, settings.workers)) as pool:
        warnings.simplefilter("ignore", ConvergenceWarning)  # the iteration cap, by design
        best, score = pso_minimize(
            score_of,
            bounds,
            n_particles=settings.n_particles,
            iterations=settings.iterations,
            seed=settings.seed,
            map_fn=pool.map,
        )
        if progress is not None:
            progress("pso-svr: the final fit at the swarm's best")
        svr = make(best, settings.final_max_iter)().fit(z, y)
        if len(captures) > 1:  # one offset per capture (each target is centred on its own mean): backfitting
            offsets = np.zeros(len(captures))
            for _ in range(OFFSET_PASSES):
                residual = y - svr.predict(z)
                offsets = np.array(
                    [residual[group == k].mean() if (group == k).any() else 0.0 for k in range(len(captures))]
                )
                offsets -= offsets[0]  # capture 0's level is the model's, as for the other kinds
                svr = make(best, settings.final_max_iter)().fit(z, y - offsets[group])
    c, _, eps = (float(v) for v in 10.0**best)
    return SvrModel.from_sklearn(svr, C=c, epsilon=eps, cv_rms_dph=score, average_s=per / config.model_rate_hz)
