"""Fitting the wavelet echo-state drift model (``models.wesn``): its readout, and for the ring form its
structure, chosen from the fit data.

Fitting (``_fit_ring_form``), everything from the fit data alone:

0. the structure cut down to what the data can identify (``identifiable_structure``: lags up to a
   tenth of the longest capture, a coil of several stages only in runs of 250 min, history up to a
   third, the bias powers only over 5 degC), each cut said in ``selection["limits"]``.  When the best
   coil sits at the longest lag tried, lags up to a fifth (``EDGE_LAG_FRACTION``) are tried too, and
   one of them is taken only when it beats that edge as more stages must beat fewer (below); a lag
   at the top of those is said as "at least"; longer lags that tie with the edge join the candidate
   structures (docs/decisions/2026-12-07-wesn-edge-lags.md);
1. the coil: its lag (mean delay) from ``COIL_LAG_GRID_S`` (60 s to 87 min, 25 % apart) and its
   number of stages (1, 2 or 3), by the smallest in-sample residual in 1-minute means of the model
   WITHOUT the history neurons (with them, the fit can shape a multi-stage coil's response out of
   history neurons and then evaluate the bias powers at the wrong lag); more stages only when they
   beat fewer by ``ORDER_TOLERANCE`` (1 %) and by more than two standard errors of the paired margin
   (``choice``, over 20-minute chunks): each adds a regressor;
2. the ridge penalty, from ``ridge_alpha_grid``, by blocked cross-validation (4 contiguous
   folds, 10-minute means of the held-out residual), each penalty with its own lag;
3. the final fit with the history neurons, whose penalty is ``history_penalty`` (100) times the
   others': a prior that a thermal history must show clearly to be believed, because on one
   chamber profile it is confounded with the coil's lag.

What one paper-profile run cannot do: tell some coils' lags apart.  The coils that explain the run
within the noise of the best (``tied_coils``: not beaten by two standard errors of the paired margin)
are listed in the model's provenance, and when their lags span more than ``LAG_INTERVAL_WARN`` (1.5)
the fit warns (``lag_warning``), and, when it knows the runs' programs (``fitting.program``), says what
they leave unidentified that bears on the lag and what would narrow the interval.  Up to
``MAX_CANDIDATES`` of them, refitted as the chosen one is, ride in the model file as its candidate
structures: where they disagree, the data did not decide (``drift_sigma_dph``).  A second run with
faster ramps, fitted together, resolves a lag one paper run leaves open.  The ring form's misses are coils
whose lag one paper run cannot pin down.  ``benchmarks/bench_population.py`` measures the form against the
polynomial; the forms and criteria tried before this one: docs/decisions/2026-12-07-wesn-ring-form.md.
``fit.model_choice`` then compares it with the polynomial on the fit's own validation split, and
``fog-driver fit`` without ``--kind`` saves the polynomial only when it leaves less there by more than
two standard errors of the paired margin (``choice``).
Random reservoirs over all eight inputs fit the training profile's history and extrapolate worse
than the polynomial baseline (docs/explanation/accuracy.md).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import numpy as np

from ..aflp import AflpFilter, AflpParams
from ..features import channels_of, ring_of
from ..models.wesn import WesnConfig, WesnModel, n_regressors
from ..readout import AdaptiveLaw
from ..uncertainty import MAX_CANDIDATES
from .choice import block_squares, paired_margin
from .data import capture_groups, first_valid_block
from .program import RATE_TERMS_SLOW, RunProgram, lag_gaps
from .ridge import cross_validated_alpha, standardized_ridge

#: The fit warns (``lag_warning``) when the lags that explain its data equally well span more than this factor.
LAG_INTERVAL_WARN = 1.5


#: A coil of more stages is chosen only when its in-sample residual beats the fewer stages' by this fraction.
ORDER_TOLERANCE = 0.01


#: What a fit can identify: coil lags up to this fraction of its longest capture, history neurons up to
#: HISTORY_FRACTION of it, and the bias curve's powers only over a ring temperature span of MIN_SPAN_C.
LAG_FRACTION = 0.1


#: When the residual still falls at the longest lag LAG_FRACTION allows, lags up to this fraction are tried too.
EDGE_LAG_FRACTION = 0.2


HISTORY_FRACTION = 1.0 / 3.0


MIN_SPAN_C = 5.0


#: A cut in the coil lags is said when it excludes lags below this: one coil stage can lag 25 min.
NOTED_LAG_S = 1500.0


def capture_regressors(model: WesnModel, capture, normalizer, teacher: np.ndarray | None) -> np.ndarray:
    """Reservoir regressors over one capture, from rest at its first valid input as the compensator
    starts (rows before it are zeros: never fitted); feedback teacher-forced with ``teacher``."""
    z = normalizer.transform(np.where(np.isfinite(capture.inputs), capture.inputs, 0.0))
    first = first_valid_block(capture.inputs)
    model.reset()
    model.start(z[first])
    y_prev = None if teacher is None else np.r_[teacher[first], teacher[first:-1]]
    f = np.zeros((len(z), len(model.weights)))
    f[first:] = model.regressors(model.reservoir.run(z[first:], y_prev), z[first:])
    return f


def _aflp_target(target: np.ndarray) -> np.ndarray:
    return AflpFilter(AflpParams()).run(target)


def fit_wesn(kind: str, defaults: WesnConfig, captures, normalizer, config, progress=None) -> WesnModel:
    """Fit a WESN model of the given form to the captures (see the module docstring); ``progress(text)``
    hears which phase runs and how far it is."""

    say = progress or (lambda text: None)
    if defaults.ring_input and defaults.readout == "ridge":
        return _fit_ring_form(kind, defaults, captures, normalizer, config, say)
    wc = defaults
    reservoir = wc.reservoir(1.0 / config.model_rate_hz, n_inputs=len(normalizer.mean))
    n_features = n_regressors(
        reservoir.params.n_neurons, wc.linear_path, wc.state_powers, wc.max_power, n_inputs=reservoir.params.n_inputs
    )
    model = WesnModel(kind, reservoir, np.zeros(n_features), 0.0, wc.linear_path, wc.state_powers, wc.max_power)
    regressors, targets = [], []
    for k, c in enumerate(captures):
        say(f"{kind}: reservoir states, capture {k + 1}/{len(captures)} ({100 * k / len(captures):.0f} %)")
        target = _aflp_target(c.target_dph) if wc.aflp_target else c.target_dph
        regressors.append(capture_regressors(model, c, normalizer, target if wc.feedback_scale else None))
        targets.append(target)
    x_fit = np.vstack([f[c.static] for f, c in zip(regressors, captures)])
    y_fit = np.concatenate([t[c.static] for t, c in zip(targets, captures)])
    groups = capture_groups(captures)
    say(f"{kind}: readout ({wc.readout})")
    if wc.readout == "ridge":
        alpha = wc.ridge_alpha
        if alpha is None:
            alpha, _ = cross_validated_alpha(x_fit, y_fit, groups=groups)
        weights, intercept = standardized_ridge(x_fit, y_fit, alpha, groups=groups)
    elif len(captures) > 1:  # one intercept per capture: the law learns on each capture's deviations from its means
        x_means = np.array([x_fit[groups == g].mean(axis=0) for g in range(len(captures))])
        y_means = np.array([y_fit[groups == g].mean() for g in range(len(captures))])
        weights, intercept = _adaptive_readout(x_fit - x_means[groups], y_fit - y_means[groups], wc, config)
        intercept += float(y_means[0] - x_means[0] @ weights)  # capture 0's, as standardized_ridge returns
    else:
        weights, intercept = _adaptive_readout(x_fit, y_fit, wc, config)
    return WesnModel(kind, reservoir, weights, intercept, wc.linear_path, wc.state_powers, wc.max_power)


def _fit_ring_form(kind: str, wc: WesnConfig, captures, normalizer, config, say=lambda text: None) -> WesnModel:
    """The ring form's structure and penalty, chosen from the fit data (module docstring, "Fitting"):

    1. for each penalty of ``ridge_alpha_grid``, the coil (its lag from ``fiber_lag_grid_s`` and its
       order from ``coil_orders``) whose fit WITHOUT the history neurons leaves the smallest in-sample
       residual in 1-minute means; a higher order only when it beats the best lower one by more than
       ``ORDER_TOLERANCE``;
    2. of those (coil, penalty) pairs, the one with the smallest blocked cross-validation error
       (4 contiguous folds, 10-minute means of the held-out residual);
    3. the final fit at that coil and penalty with the history neurons, penalized ``history_penalty``
       times more.
    """

    rate = config.model_rate_hz
    grid_s = wc.fiber_lag_grid_s
    wc, limits = identifiable_structure(wc, captures, rate)
    n_history = len(wc.history_s)
    targets = [c.target_dph for c in captures]
    y_fit = np.concatenate([t[c.static] for t, c in zip(targets, captures)])
    groups = capture_groups(captures)
    per_coil: dict[tuple[float, int], Any] = {}
    ring_weights = ring_weights_for(normalizer)

    def add_coils(lags: tuple[float, ...]) -> None:
        coils = len(wc.coil_orders) * len(lags)
        for n, (order, lag) in enumerate((m, v) for m in wc.coil_orders for v in lags):
            say(f"{kind}: reservoir states, coil {n + 1}/{coils} ({100 * n / coils:.0f} %)")
            reservoir = wc.reservoir(1.0 / rate, lag, order, ring_weights, len(normalizer.mean))
            n_features = n_regressors(
                reservoir.params.n_neurons,
                wc.linear_path,
                wc.state_powers,
                wc.max_power,
                wc.coil_rate,
                reservoir.params.n_inputs,
            )
            probe = WesnModel(
                kind, reservoir, np.zeros(n_features), 0.0, wc.linear_path, wc.state_powers, wc.max_power, wc.coil_rate
            )
            regressors = [capture_regressors(probe, c, normalizer, None) for c in captures]
            no_history = np.r_[0, np.arange(1 + n_history, n_features)]  # every column but the history neurons'
            per_coil[lag, order] = (reservoir, regressors, no_history)

    alphas = (wc.ridge_alpha,) if wc.ridge_alpha is not None else wc.ridge_alpha_grid
    minute = max(2, int(round(60 * rate)))
    edge_s = max(wc.fiber_lag_grid_s)

    scored: dict[tuple[float, tuple[float, int]], tuple[float, np.ndarray]] = {}  # kept when the lags extend
    cv_of: dict[tuple[float, tuple[float, int]], float] = {}

    def choose_coils() -> dict[float, Any]:
        choices = {}
        for k, alpha in enumerate(alphas):
            say(f"{kind}: ridge penalty {k + 1}/{len(alphas)}, coil lags and cross-validation")
            for coil, (_, regressors, columns) in per_coil.items():
                if (alpha, coil) not in scored:
                    x = np.vstack([f[c.static][:, columns] for f, c in zip(regressors, captures)])
                    w, b = standardized_ridge(x, y_fit, alpha, groups=groups)
                    residuals = [t - (f[:, columns] @ w + b) for f, t in zip(regressors, targets)]
                    scored[alpha, coil] = (
                        _averaged_residual(residuals, captures, minute),
                        minute_chunk_squares(residuals, captures, minute),
                    )
            criteria = {coil: scored[alpha, coil][0] for coil in per_coil}
            squares = {coil: scored[alpha, coil][1] for coil in per_coil}
            coil = _beyond_edge(edge_s, criteria, squares)
            tied = tied_coils(coil, squares)
            if (alpha, coil) not in cv_of:
                _, regressors, columns = per_coil[coil]
                x = np.vstack([f[c.static][:, columns] for f, c in zip(regressors, captures)])
                _, cv = cross_validated_alpha(
                    x, y_fit, folds=4, average_rows=max(2, int(round(600 * rate))), grid=(alpha,), groups=groups
                )
                cv_of[alpha, coil] = cv[alpha]
            choices[alpha] = (cv_of[alpha, coil], coil, criteria, tied)
        return choices

    add_coils(wc.fiber_lag_grid_s)
    choices = choose_coils()
    beyond = tuple(v for v in grid_s if edge_s < v <= EDGE_LAG_FRACTION * _longest_s(captures, rate))
    if beyond and any(v[1][0] == edge_s for v in choices.values()):  # the residual still falls at the edge
        add_coils(beyond)
        choices = choose_coils()
        limits = [t for t in limits if LAG_LIMIT not in t]
        limits.append(
            f"the residual still fell at the longest coil lag tried first ({edge_s / 60:.1f} min, a tenth of the "
            f"longest capture), so lags up to {max(beyond) / 60:.1f} min (a fifth) were tried too"
        )
    alpha = min(choices, key=lambda a: choices[a][0])
    _, (lag, order), criteria, tied = choices[alpha]
    tried = {v for v, _ in per_coil}
    if len(tried) > 1 and lag == max(tried) and lag < max(grid_s):
        limits.append(
            f"the coil's lag is at least {lag / 60:.1f} min: the residual still falls at the longest lag tried, "
            f"and longer lags are beyond what these captures can identify"
        )

    def final(coil: tuple[float, int]) -> WesnModel:
        reservoir, regressors, _ = per_coil[coil]
        x_fit = np.vstack([f[c.static] for f, c in zip(regressors, captures)])
        penalty = np.ones(x_fit.shape[1])
        penalty[1 : 1 + n_history] = wc.history_penalty
        weights, intercept = standardized_ridge(x_fit, y_fit, alpha, penalty, groups)
        return WesnModel(
            kind, reservoir, weights, intercept, wc.linear_path, wc.state_powers, wc.max_power, wc.coil_rate
        )

    model = final((lag, order))
    programs = [getattr(c, "program", None) for c in captures]  # the runs' programs, when known (``fitting.program``)
    model.selection = _selection(wc, lag, order, alpha, choices, criteria, tied, limits, programs)
    say(f"{kind}: candidate structures ({len(tied)} explain the data equally well)")
    model.candidates = [final(c) for c in spread_candidates(tied, (lag, order))]
    return model


def _selection(
    wc: WesnConfig,
    lag: float,
    order: int,
    alpha: float,
    choices: dict[float, Any],
    criteria: dict[tuple[float, int], float],
    tied: list[tuple[float, int]],
    limits: list[str],
    programs: Sequence[RunProgram | None] = (),
) -> dict[str, Any]:
    """The ring form's ``selection`` (the model file's provenance): the chosen coil (``lag``, ``order``) and
    penalty ``alpha``, every penalty's cross-validation score (``choices``), every coil's in-sample residual
    (``criteria``), the coils that explain the captures equally well (``tied``: within the noise of the best,
    ``tied_coils``; ``lag_warning`` when their lags span more than ``LAG_INTERVAL_WARN``), and
    what the data could not identify (``limits``)."""
    lags = sorted({float(v) for v, _ in tied})
    selection: dict[str, Any] = {
        "coil_lag_s": float(lag),
        "coil_order": int(order),
        "ridge_alpha": float(alpha),
        "history_s": [float(v) for v in wc.history_s],
        "history_penalty": float(wc.history_penalty),
        "cv_rms_dph": {float(a): float(v[0]) for a, v in choices.items()},
        "lag_rms_1min_dph": {float(k): float(v) for (k, m), v in criteria.items() if m == order},
        "order_rms_1min_dph": {m: float(min(v for (_, o), v in criteria.items() if o == m)) for m in wc.coil_orders},
        "lags_explaining_equally_s": lags,
        "coils_explaining_equally": [[float(v), int(m)] for v, m in sorted(tied)],
        "state_powers": wc.state_powers,
    }
    if limits:
        selection["limits"] = limits
    warning = lag_warning(lags, lag, programs)
    if warning:
        selection["warning"] = warning
    return selection


def _programs_text(programs: Sequence[RunProgram]) -> str:
    """The captures' programs, named, with where each was learned and, for a capture that holds only part of its
    program, how much, and the verb: "their program, paper (chamber.bin's sidecar), leaves"."""

    def one(p: RunProgram) -> str:
        cut = f", its first {p.held_min:.0f} of {p.program_min:.0f} min" if p.cut else ""
        return f"{p.name} ({p.source}{cut})"

    if len(programs) == 1:
        return f"their program, {one(programs[0])}, leaves"
    return f"their programs, {', '.join(one(p) for p in programs)}, leave"


def lag_warning(lags_s: Sequence[float], lag_s: float, programs: Sequence[RunProgram | None] = ()) -> str | None:
    """The warning when the coil lags that explain the fit captures equally well (``lags_s``; the fit takes
    ``lag_s``) span more than ``LAG_INTERVAL_WARN``, else None.  It gives the interval and, from the captures'
    programs (``programs``, one per capture, ``fitting.program``), what would narrow it:

    * a program not known (None, or no programs): the interval only, and how to give the program;
    * programs that leave something bearing on the lag unidentified (``program.lag_gaps``, left by every
      capture's program: the runs are fitted together): those gaps, and the calibration program for the
      user's chamber; when every program is ``fog-driver plan``'s own for its limits, what its limits would
      have to be instead (a longer program, a faster chamber); when a capture holds only part of its program,
      the whole program;
    * programs that leave nothing bearing on the lag: the interval is the noise's, and what else narrows
      it, more data (another run fitted together) or slower ramps (``RunProgram.slower_max_rate_c_per_min``).

    Never the program just run."""
    if not lags_s or max(lags_s) <= LAG_INTERVAL_WARN * min(lags_s):
        return None
    interval = (min(lags_s), max(lags_s))
    head = (
        f"the coil's lag is poorly identified by these captures: {interval[0]:g} s to {interval[1]:g} s explain "
        f"them within the noise of the best (the fit takes {lag_s:g} s); on faster ramps they would differ, and "
        f"drift_sigma_dph grows with that interval"
    )
    known = [p for p in programs if p is not None]
    if not known or len(known) < len(programs):
        return (
            f"{head}. The program the captures ran is not known (no sidecar records it): with fit --profile the "
            f"fit judges it and says what would narrow the interval"
        )
    shared = set.intersection(*({g.term for g in lag_gaps(p, interval)} for p in known))
    gaps = [g for g in lag_gaps(known[0], interval) if g.term in shared]
    named = _programs_text(known)
    if gaps:
        left = f"{head}; {named} unidentified: {'; '.join(g.what for g in gaps)}"
        if any(p.cut for p in known):
            return f"{left}. Remedy: record the whole program, and fit it"
        if all(p.planned for p in known):
            remedies = []
            if shared - {RATE_TERMS_SLOW}:  # what a short budget gave up: long soaks, plateaus, rates, rate steps
                longest = max(p.held_min for p in known)
                remedies.append(
                    f"a longer program (`fog-driver plan --minutes` over {longest:.0f}: its soaks last a tenth "
                    f"of the run, and it gives up less of the design)"
                )
            if RATE_TERMS_SLOW in shared:
                remedies.append("a chamber that ramps faster (`fog-driver plan --max-rate-c-per-min`)")
            return (
                f"{left}: {'it is' if len(known) == 1 else 'they are'} `fog-driver plan`'s program for the chamber's "
                f"limits, which leave these. Remedy: "
                f"{' or '.join(remedies)}, or add a run with other ramp rates and fit the runs together"
            )
        return (
            f"{left}. Remedy: run the calibration program `fog-driver plan` writes for your chamber (on the "
            f"simulator, `--profile calibration`), or add a run with other ramp rates, and fit the runs together"
        )
    slower = [p.slower_max_rate_c_per_min for p in known]
    ramps = (
        ""
        if None in slower
        else f", or a program with slower ramps (`fog-driver plan --max-rate-c-per-min "
        f"{max(r for r in slower if r is not None):g}`: its ramps last longer)"
    )
    return (
        f"{head}; {named} nothing that bears on the lag unidentified: the gyro's noise leaves this interval. "
        f"What narrows it: another run, fitted together with these captures{ramps}"
    )


def ring_weights_for(normalizer) -> tuple[float, ...]:
    """(w_top, w_bottom) such that ``w_top z_top + w_bottom z_bottom`` on inputs standardized by
    ``normalizer`` is ``(R - mean R) / s``, R = (T1 + T2) / 2 the ring mean in degC, s = (s_top + s_bottom) / 2:
    ``w = s_k / (s_top + s_bottom)``.  (Equal weights on the standardized thermometers would weight
    each by the inverse of its spread in the fit data: a combination no coil is made of.)  A one-channel
    format: (1,), its one temperature."""
    if channels_of(len(normalizer.scale)) == 1:
        return (1.0,)
    s_top, s_bottom = float(normalizer.scale[0]), float(normalizer.scale[1])
    return s_top / (s_top + s_bottom), s_bottom / (s_top + s_bottom)


def _beyond_edge(edge_s: float, criteria: dict, squares: dict) -> tuple[float, int]:
    """``_chosen_coil`` among the lags up to ``edge_s``; a longer lag (tried only when the residual still
    falls at the edge) only when it beats that choice by more than ``ORDER_TOLERANCE`` and by more than
    ``choice.SE_MULTIPLE`` standard errors of the paired margin, as more stages must."""
    coil = _chosen_coil({k: v for k, v in criteria.items() if k[0] <= edge_s}, squares)
    longer = _chosen_coil(criteria, squares)
    if (
        longer[0] > edge_s
        and criteria[longer] < criteria[coil] * (1.0 - ORDER_TOLERANCE)
        and paired_margin(squares[coil], squares[longer]).b_better
    ):
        return longer
    return coil


def _chosen_coil(criteria: dict, squares: dict) -> tuple[float, int]:
    """The (lag, order) of smallest criterion, a higher order only when it beats every lower order's best
    by more than ``ORDER_TOLERANCE`` and by more than ``choice.SE_MULTIPLE`` standard errors of the paired
    margin (``minute_chunk_squares``): more stages add regressors, they must earn them beyond the noise."""
    best: Any = None
    for order in sorted({m for _, m in criteria}):
        coil = min((k for k in criteria if k[1] == order), key=criteria.__getitem__)
        if best is None or (
            criteria[coil] < criteria[best] * (1.0 - ORDER_TOLERANCE)
            and paired_margin(squares[best], squares[coil]).b_better
        ):
            best = coil
    return best


#: In-sample residuals are compared over chunks of this many whole static minutes (long against the
#: residual's correlation: a misfit of a ramp lasts its ramp).
CHUNK_MINUTES = 20


def minute_chunk_squares(residuals, captures, window: int) -> np.ndarray:
    """The residual's means over whole static windows of ``window`` blocks (each capture's mean of them
    removed, as ``_averaged_residual``), their mean square per chunk of ``CHUNK_MINUTES`` windows:
    ``choice.block_squares`` of them, what ``choice.paired_margin`` pairs."""
    rows, groups, windows = [], [], []
    for g, (r, c) in enumerate(zip(residuals, captures)):
        n = len(r) // window * window
        ok = np.flatnonzero(c.static[:n].reshape(-1, window).all(axis=1))
        if len(ok) < 2:
            continue
        rows.append(r[:n].reshape(-1, window)[ok].mean(axis=1))
        groups.append(np.full(len(ok), g))
        windows.append(ok)
    if not rows:
        return np.zeros(0)
    w = np.concatenate(windows)
    return block_squares(np.concatenate(rows), np.concatenate(groups), w, w // CHUNK_MINUTES)


def tied_coils(chosen: tuple[float, int], squares: dict) -> list[tuple[float, int]]:
    """The coils that explain the captures as well as ``chosen`` within the noise: those the chosen coil
    does not beat by more than ``choice.SE_MULTIPLE`` standard errors of the paired margin (chosen included)."""
    return sorted(k for k in squares if k == chosen or not paired_margin(squares[k], squares[chosen]).b_better)


def spread_candidates(tied: list[tuple[float, int]], chosen: tuple[float, int]) -> list[tuple[float, int]]:
    """At most ``MAX_CANDIDATES`` of the ``tied`` coils other than ``chosen``, spread evenly over them in
    order of (lag, order): the extremes of the interval always among them."""
    others = [k for k in sorted(tied) if k != chosen]
    if len(others) <= MAX_CANDIDATES:
        return others
    picks = np.unique(np.round(np.linspace(0, len(others) - 1, MAX_CANDIDATES)).astype(int))
    return [others[i] for i in picks]


LAG_LIMIT = "coil lags above"


def _longest_s(captures, model_rate_hz: float) -> float:
    return max(len(c.static) for c in captures) / model_rate_hz


def identifiable_structure(wc: WesnConfig, captures, model_rate_hz: float) -> tuple[WesnConfig, list[str]]:
    """The ring form's structure cut down to what the captures can identify, and what was cut, in words.

    A lag shows in a run only if the run is many lags long: coil lags beyond ``LAG_FRACTION`` of the
    longest capture are not tried, a coil of several stages only when lags up to ``NOTED_LAG_S`` are
    (250 min), history neurons beyond ``HISTORY_FRACTION`` of it are left out; the
    bias curve's powers need the ring temperature to span ``MIN_SPAN_C``, else the model is linear in
    the coil temperature (``state_powers`` 0)."""
    longest_s = _longest_s(captures, model_rate_hz)
    ring = np.concatenate([ring_of(c.inputs[c.static])[0] for c in captures])
    ring = ring[np.isfinite(ring)]
    span_c = float(ring.max() - ring.min()) if len(ring) else 0.0
    minutes = longest_s / 60.0
    limits = []
    lags = tuple(v for v in wc.fiber_lag_grid_s if v <= LAG_FRACTION * longest_s) or wc.fiber_lag_grid_s[:1]
    if max(lags) < NOTED_LAG_S and len(lags) < len(wc.fiber_lag_grid_s):  # said when it can matter
        limits.append(
            f"the fit data last {minutes:.0f} min: {LAG_LIMIT} {max(lags) / 60:.1f} min cannot be "
            f"identified and were not tried"
        )
    orders = wc.coil_orders
    if max(lags) < NOTED_LAG_S and len(orders) > 1:  # telling stages apart takes more than telling lags apart
        orders = (1,)
        limits.append(
            f"the fit data last {minutes:.0f} min: a coil of several stages in series cannot be told "
            f"from one stage (it takes {LAG_FRACTION**-1 * NOTED_LAG_S / 60:.0f} min), so one stage "
            f"was fitted"
        )
    history = tuple(v for v in wc.history_s if v <= HISTORY_FRACTION * longest_s)
    if len(history) < len(wc.history_s):
        dropped = ", ".join(f"{v / 60:g}" for v in wc.history_s if v not in history)
        limits.append(
            f"the fit data last {minutes:.0f} min: thermal history over {dropped} min cannot be identified "
            f"(it needs runs three times as long): those neurons are left out"
        )
    powers = wc.state_powers
    if span_c < MIN_SPAN_C and powers:
        powers = 0
        limits.append(
            f"the ring temperature spans {span_c:.1f} degC (under {MIN_SPAN_C:g}): the bias curve's shape "
            f"cannot be identified, so the model is linear in the coil temperature"
        )
    structure = dataclasses.replace(
        wc, fiber_lag_grid_s=lags, coil_orders=orders, history_s=history, state_powers=powers
    )
    return structure, limits


def _averaged_residual(residuals, captures, window: int) -> float:
    """RMS of the residual's means over whole static windows of ``window`` blocks, per capture mean removed."""
    squares, count = 0.0, 0
    for r, c in zip(residuals, captures):
        n = len(r) // window * window
        r = r[:n].reshape(-1, window)
        ok = c.static[:n].reshape(-1, window).all(axis=1)
        if ok.sum() < 2:
            continue
        means = r[ok].mean(axis=1)
        squares += float(np.sum((means - means.mean()) ** 2))
        count += len(means)
    return float(np.sqrt(squares / count)) if count else float("inf")


def _adaptive_readout(x: np.ndarray, y: np.ndarray, wc: WesnConfig, config) -> tuple[np.ndarray, float]:
    """Stage 3 as the paper trains it: the adaptive law over the fit data (several passes), with a
    constant regressor for the intercept."""
    x1 = np.column_stack([x, np.ones(len(x))])
    law = AdaptiveLaw(wc.adaptive, x1.shape[1], 1.0 / config.model_rate_hz)
    for _ in range(wc.adaptive_epochs):
        law.run(x1, y, True)
    w = law.weights
    return w[:-1].copy(), float(w[-1])
