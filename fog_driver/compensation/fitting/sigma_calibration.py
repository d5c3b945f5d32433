"""Each fit calibrates its own ``drift_sigma_dph`` on contiguous stretches of its own run that the model was
refitted without (``compensation.uncertainty``, "Calibrated by the fit on its own data").

**The held-out stretches.**  The fit's blocks are cut into stretches of ``MIN_STRETCH_S`` of device time
(``STRETCHES`` equal ones, longer, when the run holds more; per capture, a tail shorter than half of one
joins the stretch before it).  For each stretch the model's readout is refitted, at its chosen structure
and penalty and with one intercept per capture (``fit.readout_penalty``, as the own validation split
refits it), on the static blocks of every other stretch less ``GUARD_S`` either side of it, and its
residual on the stretch is kept; so is every candidate structure's, refitted on the same blocks, and their
spread about the model on the stretch is the spread feature there: out of sample, as at run time (on the
data they were fitted on, the candidates agree by construction).  Unlike the interleaved folds of the
model choice, which put every temperature in each training set, a stretch shows what the model does over a
part of the run it never saw.

**The errors.**  The residual is averaged over windows of ``WINDOW_MIN`` whole static minutes inside a
stretch (one window starting at each minute): the model's error is slow, while the gyro's white noise at
1 min is as large as it.  Each capture's mean over its windows is removed (the bias a zero window takes
away): ``e_m``.  Its features ``f_m`` are the windows' means of the squared features
(``SigmaCalibration.features``: a constant, the candidates' spread, the ring's rate, the cold and the warm
end of the fit's range, and the distance from the box of the blocks the refit saw).

**The error's size.**  ``E[e_m^2] = o_m + v_m`` with the offset ``o_m = n^2 + (k_b R)^2 d_m^2``: ``n`` the
white noise of a window's mean (the report's 1-min floor over sqrt(``WINDOW_MIN``)) and the box term the
run-time rule puts beside the calibrated part (``d`` from the refit's box), so that a window outside what
its refit saw is judged with the same floor it gets at run time.  The calibrated part is

    v_m = c_b (rho^2 + s_m^2) + sum_j c_j f_mj          c >= 0

``rho`` the model's validation residual ``r`` (``uncertainty``; at least the floor ``mean(e^2) sqrt(2 / N)``
over the ``N`` windows: an error the data cannot tell from 0 is not 0) and ``s`` the candidates' spread: the
model's own two parts of its uncertainty, in the proportion the model gives them; the ``f_j`` the squared
features the held-out stretches may add (the ring's rate, the cold end and the warm end of the fit range).
The weights come by the largest Gaussian likelihood (a gamma GLM with identity link: iteratively reweighted
non-negative least squares of ``e_m^2 - o_m``, weights ``1 / (o_m + v_m)^2``; the non-negative solution exact
over the subsets of the few features).  The run-time weights (``SigmaCalibration.weights``) are
``c_0 = c_b rho^2``, ``c_spread = c_b`` and the ``c_j``; the box's weight is 0 (it is the floor beside).

**Which features carry it.** The spread and the residual always (a model without candidates: the residual): they are
the model's own statement of where it is unsure, and a few stretches of one run cannot show what the spread shows on
other profiles (the development runs: selected like the others on eight stretches, the spread was dropped on about
half the fits; kept on all, it gave a median top-to-bottom error ratio of 3.06 on other runs). Their evidence is
reported all the same (the held-out gain of ``rho^2 + s^2`` over ``rho^2`` alone). Each other feature joins by
forward selection only when adding it improves the held-out likelihood stretch by stretch (the variance model
refitted without each stretch and scored on it) by more than ``SELECT_SE`` standard errors of the paired per-stretch
gains, the most significant first, until none does. A feature that does not predict the held-out error on this fit
gets weight 0; the fit report and ``provenance.sigma_calibration`` give each feature's gain and its standard error.

**The scale.**  Then the split-conformal step: the smallest ``k`` for which ``|e_m| <= 1.96 sqrt(o_m + k^2
v_m)`` holds on a share ``ceil(0.95 (N + 1)) / N`` of the windows, within ``SCALE_LIMITS``; the run-time sigma
is ``sqrt(k^2 v + (k_b d R)^2)`` (the noise is not the estimate's error).

**Too few to calibrate.**  Fewer than ``MIN_STRETCHES`` stretches with ``MIN_STRETCH_MINUTES`` whole static
minutes each (a run under four hours), or a kind whose readout is not a linear regression (the paper's
WESN, the PSO-SVR): no calibration (``method: none`` with the reason), and the fall-back rule, today's
factors without their shrink (``uncertainty.FALLBACK_SCALE``), with a warning.

The choices and the development runs that made them: docs/decisions/2026-12-07-sigma-held-out-stretches.md
and docs/decisions/2026-12-08-sigma-shape-and-stretches.md.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..features import channels_of, ring_of
from ..readout import Standardizer
from ..uncertainty import SIGMA_FEATURES, SigmaCalibration
from .data import CaptureData, FitConfig
from .ridge import standardized_ridge
from .wesn import capture_regressors

#: The held-out stretches: the fit's blocks cut into stretches of ``MIN_STRETCH_S`` of device time, or into
#: ``STRETCHES`` equal ones when the run is longer than ``STRETCHES`` of those; the guard either side of a
#: stretch left out of its refit, s.  The shorter a stretch, the nearer its refit is to the model fitted on the
#: whole run, whose error the sigma describes; half an hour is six times the guard.  On the development fits
#: of the paper program, eighths of the run (55 min) sized the sigma off by a factor of 1.8 on average (either
#: way), half hours by 1.4 (the decision page).
MIN_STRETCH_S = 1800.0
STRETCHES = 16
GUARD_S = 300.0
#: The fewest held-out stretches a sigma is calibrated on, and the fewest whole static minutes a stretch
#: needs to count: eight stretches give the conformal quantile and the paired selection at least eight
#: independent pieces of evidence (the minutes within a stretch are not independent).
MIN_STRETCHES = 8
MIN_STRETCH_MINUTES = 10
#: The held-out error is judged in means over windows of this many whole minutes (one window starting at each
#: minute of a stretch): the model's error is slow, the gyro's white noise at 1 min is as large as it, and
#: over 10 minutes the noise falls by sqrt(10) while the model's error hardly changes.
WINDOW_MIN = 10
#: The band's two-sided 95 % point and the share of held-out minutes it must cover.
Z95 = 1.96
COVERAGE = 0.95
#: The conformal scale k is kept within these: the likelihood fit sets the size, k corrects the tails.
SCALE_LIMITS = (0.5, 3.0)
#: A feature beyond the spread and the residual joins when its paired held-out gain exceeds this many standard
#: errors: at 2 the rate joined on development fits where it inverted the sigma on other runs (worst
#: top-to-bottom ratio 0.79); at 3 none did (the decision page).
SELECT_SE = 3.0
#: IRLS iterations of the variance fit.
IRLS_ITERATIONS = 25


@dataclass
class HeldOut:
    """The held-out windows of a fit: their errors ``e_m`` (deg/h, each capture's mean removed), their squared
    features ``f_m`` (rows, ``SIGMA_FEATURES``), the stretch each is in, and the white noise ``n`` of a window's
    mean (the 1-min noise over sqrt(``WINDOW_MIN``))."""

    error_dph: np.ndarray
    features: np.ndarray
    stretch: np.ndarray
    noise_1min_dph: float
    stretch_min: float

    @property
    def stretches(self) -> int:
        return len(np.unique(self.stretch))


def held_out_minutes(
    model: Any,
    rows: list[np.ndarray],
    alpha: float,
    penalty: np.ndarray | None,
    captures: list[CaptureData],
    normalizer: Standardizer,
    config: FitConfig,
    calibration: SigmaCalibration,
    noise_1min_dph: float,
) -> HeldOut:
    """The held-out minutes (module docstring) of ``model`` whose readout regressors are ``rows`` (one matrix
    per capture, every block), refitted with ``alpha`` and ``penalty``; ``calibration`` gives the ring range
    the features are made with."""
    rate = config.model_rate_hz
    total = sum(len(c.static) for c in captures)
    stretch_blocks = max(1, int(round(MIN_STRETCH_S * rate)), total // STRETCHES)
    guard = int(round(GUARD_S * rate))
    per_minute = max(1, int(round(60.0 * rate)))
    labels = []
    for c in captures:
        n = len(c.static)
        last = max(n // stretch_blocks - (1 if n % stretch_blocks < stretch_blocks // 2 else 0), 0)
        labels.append(np.minimum(np.arange(n) // stretch_blocks, last))
    index = [np.flatnonzero(c.static) for c in captures]
    candidates = getattr(model, "candidates", None) or []
    candidate_x = [  # each candidate's regressors on the static blocks, refitted beside the model
        np.vstack([capture_regressors(cand, c, normalizer, None)[i] for c, i in zip(captures, index)])
        for cand in candidates
    ]
    x = np.vstack([f[i] for f, i in zip(rows, index)])
    channels = channels_of(captures[0].inputs.shape[1])
    temps = np.vstack([c.inputs[i][:, :channels] for c, i in zip(captures, index)])
    y = np.concatenate([c.target_dph[i] for c, i in zip(captures, index)])
    group = np.concatenate([np.full(len(i), g) for g, i in enumerate(index)])
    block = np.concatenate(index)
    label = np.concatenate([lab[i] for lab, i in zip(labels, index)])
    errors, features, stretch_of = [], [], []
    stretch_id = 0
    for g, c in enumerate(captures):
        ring_c, ring_rate = ring_of(c.inputs)  # the capture's, for every stretch of it
        for s in np.unique(labels[g]):
            blocks = np.flatnonzero(labels[g] == s)
            lo, hi = int(blocks[0]), int(blocks[-1]) + 1
            test = (group == g) & (label == s)
            near = (group == g) & (block >= lo - guard) & (block < hi + guard)
            train = ~near
            if not test.any() or not train.any():
                continue
            w, b = standardized_ridge(x[train], y[train], alpha, penalty, group[train])
            estimate = x[test] @ w + b
            residual = np.full(len(c.static), np.nan)
            residual[block[test]] = y[test] - estimate
            spread = np.zeros(len(c.static))
            for cx in candidate_x:  # each candidate refitted without the stretch too: its spread out of sample
                wc, bc = standardized_ridge(
                    cx[train], y[train], alpha, _penalty_for(penalty, cx.shape[1]), group[train]
                )
                spread[block[test]] += (cx[test] @ wc + bc - estimate) ** 2
            if candidate_x:
                spread /= len(candidate_x)
            first, last = -(-lo // per_minute), hi // per_minute  # whole minutes inside the stretch
            minutes = []
            for m in range(first, last):
                part = slice(m * per_minute, (m + 1) * per_minute)
                if c.static[part].all():
                    minutes.append(m)
            if len(minutes) < MIN_STRETCH_MINUTES:
                continue
            f = calibration.features(spread, ring_c, ring_rate, _fold_box_distance(temps[train], c.inputs))
            minute_e = {m: float(residual[m * per_minute : (m + 1) * per_minute].mean()) for m in minutes}
            minute_f = {m: f[m * per_minute : (m + 1) * per_minute].mean(axis=0) for m in minutes}
            for m in minutes:  # windows of WINDOW_MIN consecutive whole minutes, one starting at each minute
                window = range(m, m + WINDOW_MIN)
                if all(k in minute_e for k in window):
                    errors.append(float(np.mean([minute_e[k] for k in window])))
                    features.append(np.mean([minute_f[k] for k in window], axis=0))
                    stretch_of.append((g, stretch_id))
            stretch_id += 1
    if not errors:
        return HeldOut(np.zeros(0), np.zeros((0, len(SIGMA_FEATURES))), np.zeros(0, int), noise_1min_dph, 0.0)
    e = np.array(errors)
    groups = np.array([g for g, _ in stretch_of])
    for g in np.unique(groups):  # each capture's mean over its held-out minutes: the bias, removed
        e[groups == g] -= e[groups == g].mean()
    return HeldOut(
        e,
        np.array(features),
        np.array([s for _, s in stretch_of]),
        noise_1min_dph / math.sqrt(WINDOW_MIN),
        stretch_blocks / rate / 60.0,
    )


def _fold_box_distance(train_temps: np.ndarray, inputs: np.ndarray) -> np.ndarray:
    """d per block of ``inputs``: how far its temperatures lie outside the box of ``train_temps`` (the blocks a
    stretch's refit saw), in spans of it, as ``uncertainty.box_distance`` measures it from the fit box."""
    lo, hi = np.nanmin(train_temps, axis=0), np.nanmax(train_temps, axis=0)
    span = hi - lo
    t = inputs[:, : train_temps.shape[1]]
    with np.errstate(invalid="ignore", divide="ignore"):
        d = np.maximum((lo - t) / span, (t - hi) / span)
    d = np.where((span > 0) & np.isfinite(d), d, 0.0)
    return np.maximum(d.max(axis=1), 0.0)


def _penalty_for(penalty: np.ndarray | None, columns: int) -> np.ndarray | None:
    """The model's per-column penalty for a candidate of ``columns`` regressors (the history neurons, which
    come first after the linear path, penalized alike; the rest 1)."""
    if penalty is None:
        return None
    out = np.ones(columns)
    n = min(columns, len(penalty))
    out[:n] = penalty[:n]
    return out


def _nnls(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """min |a c - b|^2 over c >= 0, exactly, by the subsets of the (few) columns: the optimum is the
    unconstrained solution on its own support."""
    p = a.shape[1]
    best, best_cost = np.zeros(p), float(b @ b)
    for size in range(1, p + 1):
        for support in itertools.combinations(range(p), size):
            cols = list(support)
            sol, *_ = np.linalg.lstsq(a[:, cols], b, rcond=None)
            if (sol < 0).any():
                continue
            c = np.zeros(p)
            c[cols] = sol
            r = a @ c - b
            cost = float(r @ r)
            if cost < best_cost:
                best, best_cost = c, cost
    return best


def fit_variance(features: np.ndarray, e2: np.ndarray, offset: Any, floor: float = 0.0) -> np.ndarray:
    """The ``c_j >= 0`` of ``E[e^2] = offset + f c`` by the largest Gaussian likelihood (module docstring);
    ``offset`` (a number or one per row) the variance the weights do not carry: the noise, and the box term;
    column 0's weight at least ``floor``."""
    target = e2 - offset
    start = max(float(np.mean(target)) / max(float(np.mean(features[:, 0])), 1e-300), floor, 1e-12)
    c = np.zeros(features.shape[1])
    c[0] = start
    for _ in range(IRLS_ITERATIONS):
        mu = np.maximum(offset + features @ c, 1e-12)
        w = 1.0 / mu
        new = _nnls(features * w[:, None], target * w)
        new[0] = max(new[0], floor, 1e-12)
        if np.allclose(new, c, rtol=1e-6, atol=1e-15):
            c = new
            break
        c = new
    return c


def _nll(features: np.ndarray, e2: np.ndarray, offset: Any, c: np.ndarray) -> np.ndarray:
    mu = np.maximum(offset + features @ c, 1e-12)
    return 0.5 * (np.log(2.0 * math.pi * mu) + e2 / mu)


def _per_stretch_nll(
    features: np.ndarray,
    e2: np.ndarray,
    offset: np.ndarray,
    stretch: np.ndarray,
    columns: Sequence[int],
    floor: float = 0.0,
) -> np.ndarray:
    """Each stretch's held-out negative log-likelihood under the variance model of ``columns`` refitted
    without it (the first column's weight at least ``floor``)."""
    cols = list(columns)
    out = []
    for s in np.unique(stretch):
        test = stretch == s
        c = fit_variance(features[~test][:, cols], e2[~test], offset[~test], floor)
        out.append(float(_nll(features[test][:, cols], e2[test], offset[test], c).sum()))
    return np.array(out)


def _paired(base: np.ndarray, trial: np.ndarray) -> tuple[float, float]:
    """The mean per-stretch gain of ``trial`` over ``base`` (their held-out NLLs) and its standard error."""
    d = base - trial
    se = float(d.std(ddof=1) / math.sqrt(len(d))) if len(d) > 1 else math.inf
    return float(d.mean()), se


def conformal_scale(held: HeldOut, v: np.ndarray, offset: Any = None) -> float:
    """The smallest k of the module docstring, by bisection, within ``SCALE_LIMITS``; ``offset`` the variance
    beside ``k^2 v`` (default: the noise, ``n^2``)."""
    n = len(held.error_dph)
    share = min(1.0, math.ceil(COVERAGE * (n + 1)) / n)
    a = np.abs(held.error_dph)
    off = held.noise_1min_dph**2 if offset is None else offset

    def covered(k: float) -> float:
        return float(np.mean(a <= Z95 * np.sqrt(off + k * k * v)))

    lo, hi = SCALE_LIMITS
    if covered(lo) >= share:
        return lo
    if covered(hi) < share:
        return hi
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if covered(mid) >= share:
            hi = mid
        else:
            lo = mid
    return hi


def calibrate(
    held: HeldOut, ring_low_c: float, ring_high_c: float, residual_dph: float = 0.0, box_dph: float = 0.0
) -> tuple[SigmaCalibration, dict[str, Any]]:
    """The calibration of a fit's sigma from its held-out minutes, and the evidence for the fit report and the
    provenance (module docstring); ``residual_dph`` the model's validation residual r, ``box_dph`` the box
    term's k_b R; ``method: none`` when the minutes are too few."""
    stretches = held.stretches
    if stretches < MIN_STRETCHES:
        reason = (
            f"{stretches} held-out stretches of at least {MIN_STRETCH_S / 60:g} min with {MIN_STRETCH_MINUTES} "
            f"whole static minutes each (at least {MIN_STRETCHES} are needed: a run of "
            f"{MIN_STRETCHES * MIN_STRETCH_S / 3600:g} h): too few to calibrate the sigma on"
        )
        return SigmaCalibration("none", reason=reason), {"method": "none", "reason": reason}
    e2 = held.error_dph**2
    f = held.features
    spread, box = SIGMA_FEATURES.index("spread"), SIGMA_FEATURES.index("box")
    offset = held.noise_1min_dph**2 + box_dph**2 * f[:, box]
    floor = float(np.mean(e2)) * math.sqrt(2.0 / len(e2))
    rho2 = max(residual_dph**2, floor, 1e-300)  # > 0 even for errors and a residual of exactly 0
    low = floor / rho2  # c_b at least this: the constant c_b rho^2 at least the floor
    extras = [j for j in range(len(SIGMA_FEATURES)) if j not in (0, spread, box)]
    g = np.column_stack([rho2 + f[:, spread], np.full(len(e2), rho2), *(f[:, j] for j in extras)])
    stretch = held.stretch
    evidence: dict[str, Any] = {}
    base = _per_stretch_nll(g, e2, offset, stretch, [0], low)
    own = ["constant", "spread"] if np.any(f[:, spread] > 0) else ["constant"]  # no candidates: no spread
    if len(own) == 2:
        gain, se = _paired(_per_stretch_nll(g, e2, offset, stretch, [1], low), base)
        evidence["spread"] = {"gain_per_stretch": gain, "se": se, "with": ["constant"], "kept": True}
    chosen = [0]
    while True:
        trials = {}
        for col, j in enumerate(extras, start=2):
            if col in chosen or not np.ptp(g[:, col]) > 0:
                continue
            nll = _per_stretch_nll(g, e2, offset, stretch, [*chosen, col], low)
            trials[col] = (*_paired(base, nll), nll)
            evidence[SIGMA_FEATURES[j]] = {
                "gain_per_stretch": trials[col][0],
                "se": trials[col][1],
                "with": [*own, *(SIGMA_FEATURES[extras[c - 2]] for c in chosen[1:])],
            }
        passing = {c: t for c, t in trials.items() if t[0] > SELECT_SE * t[1] and t[0] > 0}
        if not passing:
            break
        col = max(passing, key=lambda c: passing[c][0] / max(passing[c][1], 1e-300))
        chosen.append(col)
        base = passing[col][2]
    c_sub = fit_variance(g[:, chosen], e2, offset, low)
    c = np.zeros(len(SIGMA_FEATURES))
    c[0], c[spread] = c_sub[0] * rho2, c_sub[0]
    for col, weight in zip(chosen[1:], c_sub[1:]):
        c[extras[col - 2]] = weight
    v = f @ c
    k = conformal_scale(held, v, offset)
    calibration = SigmaCalibration(
        "held-out-stretches", tuple(c), k, ring_low_c, ring_high_c, stretches, held.stretch_min
    )
    sigma_sq = k * k * v + box_dph**2 * f[:, box]
    covered = float(np.mean(np.abs(held.error_dph) <= Z95 * np.sqrt(held.noise_1min_dph**2 + sigma_sq)))
    for j in extras:
        name = SIGMA_FEATURES[j]
        if name in evidence:
            evidence[name]["kept"] = any(extras[col - 2] == j for col in chosen[1:])
    return calibration, {
        "method": "held-out-stretches",
        "stretches": stretches,
        "stretch_min": held.stretch_min,
        "minutes": len(e2),
        "noise_1min_dph": held.noise_1min_dph,
        "held_out_rms_dph": float(np.sqrt(np.mean(e2))),
        "residual_dph": math.sqrt(rho2),
        "features": [*own, *(SIGMA_FEATURES[extras[col - 2]] for col in chosen[1:])],
        "evidence": evidence,
        "scale": k,
        "held_out_coverage": covered,
        "median_sigma_dph": float(np.median(np.sqrt(sigma_sq))),
    }


def describe(evidence: dict[str, Any]) -> str:
    """The fit report's line on the sigma's calibration."""
    if evidence.get("method") != "held-out-stretches":
        return f"drift_sigma_dph: not calibrated ({evidence.get('reason', '')}); the conservative fall-back rule"
    parts = []
    for name, ev in evidence["evidence"].items():
        verdict = "kept, the model's own" if name == "spread" else "kept" if ev.get("kept") else "no weight"
        parts.append(f"{name} {verdict} (held-out log-likelihood {ev['gain_per_stretch']:+.2f} +- {ev['se']:.2f})")
    return (
        f"drift_sigma_dph calibrated on {evidence['stretches']} held-out stretches of {evidence['stretch_min']:.0f} "
        f"min ({evidence['minutes']} minutes, RMS error {evidence['held_out_rms_dph']:.4f} deg/h): carried by "
        f"{', '.join(evidence['features'])}; scale {evidence['scale']:.2f}; " + "; ".join(parts)
    )
