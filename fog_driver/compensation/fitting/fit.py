"""Fitting a drift model to captures' data (``data.CaptureData``), and the numbers that judge it.

``fit_model``: the kind's fitter (``FITTERS``) and the polynomial baseline beside it, their report
(``report``), the ring ``wesn``'s comparison with the polynomial on the fit's own validation split
(``own_validation``), the data's checks (``quality``), the bias step test (``bias_step_scan``), and the
model file with its provenance.  Reading the captures is ``offline.fit``'s.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import fields, is_dataclass
from typing import Any, NamedTuple, cast

import numpy as np

from ...errors import InputFileError
from ..domain import InputDomain
from ..features import fit_substitution, input_names, ring_of
from ..model import ModelFile
from ..models.polynomial import PolynomialModel, polynomial_features
from ..models.wesn import PAPER_DEFAULTS, WESN_DEFAULTS
from ..readout import Standardizer
from ..uncertainty import SigmaCalibration, UncertaintySpec
from .choice import block_squares, choose, paired, paired_margin, polynomial_lead
from .data import (
    CaptureData,
    FitConfig,
    capture_groups,
    fit_normalizer,
    measured_rows,
    static_minute_count,
    static_rows,
)
from .quality import FitQuality, assess, condition_number
from .report import FitReport, report_for
from .ridge import standardized_ridge
from .sigma_calibration import calibrate, held_out_minutes
from .sigma_calibration import describe as describe_sigma
from .svr import PSO_SVR_DEFAULTS, fit_pso_svr
from .uncertainty import report_error_dph, uncertainty_for, with_calibration
from .wesn import capture_regressors, fit_wesn


class BiasStep(NamedTuple):
    """The largest bias step ``bias_step_scan`` found: where, how big, and how much it explains."""

    capture: int  #: index of the capture it is in
    minute: int  #: minutes from that capture's start
    step_dph: float
    share: float  #: the fraction of what the temperature terms leave that the step explains


def bias_step_scan(captures: list[CaptureData], normalizer: Standardizer, model_rate_hz: float) -> BiasStep | None:
    """A step test on the fit target: is there a bias step the temperatures cannot explain?

    Over the static 1-minute means of every capture, the target is regressed on the polynomial's
    temperature terms (``polynomial_features``, no memory: a step is not in their span) with one
    intercept per capture; then, at every 10-minute boundary of each capture (not within
    ``STEP_EDGE_MIN`` of its ends), with one step column more (0 before, 1 after).  Returns the boundary
    whose step reduces the residual sum of squares most: its size (the step column's weight) and the
    share of the residual it explains.  None when the data are too short to scan."""
    per_minute = int(round(60 * model_rate_hz))
    xs, ys, minutes, groups = [], [], [], []
    for i, c in enumerate(captures):
        n = len(c.target_dph) // per_minute * per_minute
        full = c.static[:n].reshape(-1, per_minute).all(axis=1)
        x = polynomial_features(normalizer.transform(np.where(np.isfinite(c.inputs[:n]), c.inputs[:n], 0.0)))
        xs.append(x.reshape(-1, per_minute, x.shape[1]).mean(axis=1)[full])
        ys.append(c.target_dph[:n].reshape(-1, per_minute).mean(axis=1)[full])
        minutes.append(np.flatnonzero(full))
        groups.append(np.full(int(full.sum()), i))
    x, y, minute, group = np.vstack(xs), np.concatenate(ys), np.concatenate(minutes), np.concatenate(groups)
    base = np.column_stack([x, (group[:, None] == np.arange(len(captures))[None, :]).astype(float)])
    if len(y) < base.shape[1] + 10:
        return None

    def rss(a: np.ndarray) -> tuple[float, np.ndarray]:
        coef = np.linalg.lstsq(a, y, rcond=None)[0]
        r = y - a @ coef
        return float(r @ r), coef

    rss0, _ = rss(base)
    best: BiasStep | None = None
    best_rss = rss0
    for i in range(len(captures)):
        span = minute[group == i]
        if not len(span):
            continue
        for k in range(STEP_EDGE_MIN, int(span.max()) - STEP_EDGE_MIN + 1, STEP_GRID_MIN):
            step = ((group == i) & (minute >= k)).astype(float)
            if step.sum() < STEP_EDGE_MIN or (group == i).sum() - step.sum() < STEP_EDGE_MIN:
                continue
            r, coef = rss(np.column_stack([base, step]))
            if r < best_rss:
                best_rss, best = r, BiasStep(i, k, float(coef[-1]), 1.0 - r / rss0 if rss0 > 0 else 0.0)
    return best


#: the step test's grid (minutes) and how far from a capture's ends it starts (minutes)
STEP_GRID_MIN = 10
STEP_EDGE_MIN = 30
#: a step this large that explains this share of the temperature terms' residual is reported as a warning
STEP_WARN_DPH = 0.05
STEP_WARN_SHARE = 0.25


def bias_step_warning(step: dict, n_channels: int = 3) -> str | None:
    """The warning for ``provenance.fit_quality.bias_step``, or None when the step is within what the
    temperature terms' misfit alone produces (the polynomial's misfit of a coil lag looks like a small step;
    ``STEP_WARN_DPH`` and ``STEP_WARN_SHARE`` lie above it: docs/decisions/2026-12-07-bias-step-warning.md).
    Not a failing check.  ``n_channels``: the thermometers the
    model has; with one (a KVH unit), drift it cannot follow (a gradient across the coil) looks like a step."""
    if abs(step["step_dph"]) < STEP_WARN_DPH or step["share"] < STEP_WARN_SHARE:
        return None
    causes = "a bias jump, a turn-on transient longer than warmup_s, or a slow move"
    if n_channels == 1:
        causes = (
            f"drift that one thermometer cannot follow (a gradient or a lag across the coil that this "
            f"format's single sensor does not see), {causes}"
        )
    return (
        f"the fit data hold a bias step of {step['step_dph']:+.3f} deg/h at minute {step['minute']} of "
        f"{step['capture']} (it explains {100 * step['share']:.0f} % of what the temperatures leave): {causes}; "
        f"the model absorbs it as drift. Fit the parts either side separately, or raise warmup_s"
    )


def regressor_rows(model, captures: list[CaptureData], normalizer: Standardizer) -> list[np.ndarray] | None:
    """Each capture's regressor matrix (every block) for the models whose readout is a linear regression
    (the polynomial and the ring ``wesn``); None for the others."""
    if isinstance(model, PolynomialModel):
        return [
            polynomial_features(normalizer.transform(np.where(np.isfinite(c.inputs), c.inputs, 0.0))) for c in captures
        ]
    if getattr(model, "selection", None):  # the ring wesn (its structure chosen by the fit)
        return [capture_regressors(model, c, normalizer, None) for c in captures]
    return None


def readout_penalty(model, config: FitConfig) -> tuple[float, np.ndarray | None]:
    """The ridge penalty and the per-column penalty a refit of the readout uses, at the structure the fit chose
    (the polynomial's ``poly_alpha``; the ring ``wesn``'s chosen penalty, its history neurons penalized more)."""
    if isinstance(model, PolynomialModel):
        return (config.poly_alpha if config.poly_alpha is not None else 1e-3), None
    sel = model.selection
    penalty = np.ones(len(model.weights))
    penalty[1 : 1 + len(sel["history_s"])] = sel["history_penalty"]
    return sel["ridge_alpha"], penalty


#: The fit's own validation split: chunks of device time dealt in turn to the folds.
VALIDATION_CHUNK_S = 1200.0
VALIDATION_FOLDS = 4


def own_validation_squares(
    model, captures: list[CaptureData], normalizer: Standardizer, config: FitConfig
) -> np.ndarray:
    """What a model's structure leaves on data it was not fitted on, from the fit data alone: per chunk of
    the fit's own validation split, the mean square of the held-out residual's 10-minute means, (deg/h)^2.

    Chunks of ``VALIDATION_CHUNK_S`` device time (shorter for captures under 4 chunks) are dealt in turn to
    ``VALIDATION_FOLDS`` folds; for each fold the model's readout is refitted, at its chosen structure and
    penalty and with one intercept per capture, on the other folds' static blocks, and its residual on the
    fold is averaged over whole static windows of half a chunk (10 minutes) inside it.  Each capture's and
    fold's mean of those window means is removed, and each chunk gives the mean square of its windows'
    (``choice.block_squares``; one value per chunk, in the order of (capture, fold, chunk)).  The same
    blocks for every model of the same captures and config, so two models' values pair
    (``choice.paired_margin``).  For the polynomial and the ring ``wesn`` (the structures the fit
    compares); interleaved folds keep every temperature in each training set."""
    rate = config.model_rate_hz
    longest = max(len(c.static) for c in captures)
    window = max(1, min(int(round(VALIDATION_CHUNK_S * rate)), longest // (2 * VALIDATION_FOLDS)) // 2)
    chunk = 2 * window  # whole windows in every chunk
    rows = cast(list[np.ndarray], regressor_rows(model, captures, normalizer))  # these two kinds have them
    alpha, penalty = readout_penalty(model, config)
    index = [np.flatnonzero(c.static) for c in captures]
    x = np.vstack([f[i] for f, i in zip(rows, index)])
    y = np.concatenate([c.target_dph[i] for c, i in zip(captures, index)])
    group = np.concatenate([np.full(len(i), g) for g, i in enumerate(index)])
    block = np.concatenate(index)
    fold = (block // chunk) % VALIDATION_FOLDS
    residual = np.full(len(y), np.nan)
    for k in range(VALIDATION_FOLDS):
        train, test = fold != k, fold == k
        if not train.any() or not test.any():
            continue
        w, b = standardized_ridge(x[train], y[train], alpha, penalty, group[train])
        residual[test] = y[test] - (x[test] @ w + b)
    # whole windows only: every block of the window static (so held out, and in the same fold)
    _, in_window, filled = np.unique(
        np.stack([group, block // window]).T, axis=0, return_inverse=True, return_counts=True
    )
    whole = (filled[in_window.ravel()] == window) & np.isfinite(residual)
    return block_squares(
        residual[whole],
        (group * VALIDATION_FOLDS + fold)[whole],  # each capture and fold has its own intercept
        (block // window)[whole],
        (block // chunk)[whole],
    )


def own_validation(model, captures: list[CaptureData], normalizer: Standardizer, config: FitConfig) -> float:
    """The drift a model's structure leaves on the fit's own validation split, deg/h: the RMS over its
    chunks, ``sqrt(mean(s_b))`` of ``own_validation_squares`` (NaN when the split has no chunk)."""
    squares = own_validation_squares(model, captures, normalizer, config)
    return float(np.sqrt(squares.mean())) if len(squares) else float("nan")


def _fit_polynomial(captures: list[CaptureData], normalizer: Standardizer, config: FitConfig, progress=None):
    if progress is not None:
        progress("polynomial: ridge regression")
    z = np.vstack([normalizer.transform(c.inputs[c.static]) for c in captures])
    y = np.concatenate([c.target_dph[c.static] for c in captures])
    return PolynomialModel.fit(z, y, config.poly_alpha, capture_groups(captures))


def _fit_wesn(kind: str):
    defaults = {"wesn": WESN_DEFAULTS, "paper": PAPER_DEFAULTS}[kind]
    return lambda captures, normalizer, config, progress=None: fit_wesn(
        kind, defaults, captures, normalizer, config, progress
    )


def _fit_pso_svr(captures: list[CaptureData], normalizer: Standardizer, config: FitConfig, progress=None):
    return fit_pso_svr(captures, normalizer, config, PSO_SVR_DEFAULTS, progress)


#: Model kinds that can be fitted: name -> fit(captures, normalizer, config, progress=None) -> model
#: (``progress(text)`` hears the phase and how far it is).
FITTERS = {
    "polynomial": _fit_polynomial,
    "wesn": _fit_wesn("wesn"),
    "paper": _fit_wesn("paper"),
    "pso-svr": _fit_pso_svr,
}

#: One line per kind for ``fog-driver fit --help`` (every key of ``FITTERS``).
KIND_HELP = {
    "wesn": "the project's best, the default: wavelet echo-state network, structure chosen from the data",
    "polynomial": "the baseline (fitted beside every kind): cubic in the ring temperature, ridge regression",
    "paper": "the paper's WESN as written, for comparison",
    "pso-svr": "the paper's comparator: RBF SVR tuned by a particle swarm (svr extra; the slowest)",
}


def check_kind(kind: str) -> None:
    """``InputFileError`` unless ``kind`` is a model kind that can be fitted (a key of ``FITTERS``)."""
    if kind not in FITTERS:
        raise InputFileError(f"unknown model kind {kind!r} (known: {', '.join(sorted(FITTERS))})")


def fit_model(
    captures: list[CaptureData],
    validate: list[CaptureData],
    *,
    kind: str,
    config: FitConfig,
    fall_back: bool = False,
    accept_weak: bool = False,
    progress: Callable[[str], None] | None = None,
) -> tuple[ModelFile, FitReport]:
    """Fit ``kind`` (and the polynomial baseline beside it) to captures' data; return the model file and the
    report (``offline.fit.fit_model_file`` reads the captures).

    A ring ``wesn`` is compared with the polynomial on the fit's own validation split (``model_choice``):
    with ``fall_back`` (``fog-driver fit`` without ``--kind``) the polynomial's model file is returned
    instead when it leaves less there by more than ``choice.SE_MULTIPLE`` standard errors; without, the
    ``wesn`` is kept and its provenance warns when the polynomial does that.  The decision and its margin
    are in ``provenance.selection.choice`` and the report's ``choice``.  The fit's data are checked
    (``quality.assess``): a fit that fails a check raises ``WeakFitError`` unless ``accept_weak``, and
    then the model file's ``provenance.fit_quality`` records the failures and that they were accepted.
    ``progress(text)`` hears every phase and how far it is ("pso-svr: iteration 4/20, particle 12/16
    (21 %)", "validating wesn on fast.bin (75 %)").  Every capture must have the same temperature
    channels, which the model file records, and come from one instrument."""
    check_kind(kind)
    say = progress or (lambda text: None)
    for c in [*captures[1:], *validate]:
        if c.channels != captures[0].channels:
            raise InputFileError(
                f"{c.path}: {c.wire_format} frames with temperature channels {', '.join(c.channels)}; "
                f"{captures[0].path.name} has {', '.join(captures[0].channels)}: one model is "
                f"fitted on one instrument's channels"
            )
    serials = {c.serial for c in captures}
    check_one_instrument(captures, validate)
    normalizer = fit_normalizer(captures)
    models = {"polynomial": _fit_polynomial(captures, normalizer, config, progress)}
    if kind != "polynomial":
        models[kind] = FITTERS[kind](captures, normalizer, config, progress)
    inputs, means = static_rows(captures, config.model_rate_hz)
    channels = captures[0].channels
    domain = InputDomain.from_fit(inputs, means, input_names(channels))  # the fit's box, and the estimate's bound
    substitution = fit_substitution(
        [c.inputs for c in captures], [measured_rows(c, config) for c in captures], 1.0 / config.model_rate_hz
    )
    report = report_for(models, normalizer, captures, validate, config.model_rate_hz, domain, progress)
    provenance = _provenance(captures, validate, config, report)
    selection = getattr(models[kind], "selection", None)
    if selection:
        provenance["selection"] = selection
        choice = model_choice(models, kind, captures, normalizer, config, fall_back=fall_back, say=say)
        selection["choice"] = report.choice = choice
        if choice["decision"] == "polynomial saved":
            kind = "polynomial"
            provenance["fell_back"] = f"{polynomial_lead(choice)}: the polynomial was saved instead"
        elif paired(choice).b_better:  # asked for by name: kept, with the warning
            selection["warning_validation"] = f"{polynomial_lead(choice)}: without --kind it would be saved"
    quality = _assess(inputs, means, validate, normalizer, report, kind, config)
    validate_minutes = static_minute_count(validate, config.model_rate_hz) if validate else 0
    r_dph = report_error_dph(report, kind, len(means), validate_minutes)
    uncertainty = uncertainty_for(models[kind], r_dph, domain)
    say("drift_sigma_dph: calibrating on held-out stretches")
    calibration, evidence = calibrate_sigma(models[kind], captures, normalizer, config, report, inputs, uncertainty)
    uncertainty = with_calibration(uncertainty, calibration)
    provenance["sigma_kind"] = uncertainty.sigma_kind
    provenance["sigma_calibration"] = evidence
    report.sigma_line = describe_sigma(evidence)
    provenance["fit_quality"] = quality.to_dict(accept_weak)
    _add_findings(provenance["fit_quality"], models[kind], captures, normalizer, config, say)
    model_file = ModelFile(
        kind=kind,
        instrument_serial=next(iter(serials)) or "",
        model_rate_hz=config.model_rate_hz,
        features=config.features,
        normalizer=normalizer,
        model=models[kind],
        provenance=provenance,
        domain=domain,
        substitution=substitution,
        temperature_channels=channels,
        noise_1min_dph=report.noise_1min_dph,
        uncertainty=uncertainty,
    )
    if quality.failed and not accept_weak:
        raise WeakFitError(quality, report, model_file)
    return model_file, report


def calibrate_sigma(
    model: Any,
    captures: list[CaptureData],
    normalizer: Standardizer,
    config: FitConfig,
    report: FitReport,
    inputs: np.ndarray,
    uncertainty: UncertaintySpec,
) -> tuple[SigmaCalibration, dict[str, Any]]:
    """The sigma's calibration on the fit's held-out stretches (``sigma_calibration``) and its evidence, about
    ``uncertainty``'s validation residual and box term; for a kind without a linear readout, ``method: none``."""
    rows = regressor_rows(model, captures, normalizer)
    if rows is None:
        reason = "this kind's readout is not a linear regression the fit can refit without a stretch"
        return SigmaCalibration("none", reason=reason), {"method": "none", "reason": reason}
    ring_c, _ = ring_of(inputs)
    ring_c = ring_c[np.isfinite(ring_c)]
    bounds = SigmaCalibration("none", ring_low_c=float(ring_c.min()), ring_high_c=float(ring_c.max()))
    alpha, penalty = readout_penalty(model, config)
    noise = report.noise_1min_dph
    held = held_out_minutes(
        model, rows, alpha, penalty, captures, normalizer, config, bounds, noise if noise is not None else 0.0
    )
    box_dph = uncertainty.box_scale * uncertainty.target_range_dph
    return calibrate(held, bounds.ring_low_c, bounds.ring_high_c, uncertainty.residual_dph, box_dph)


def check_one_instrument(captures: list[CaptureData], validate: list[CaptureData]) -> None:
    """An ``InputFileError`` naming each instrument's captures when the fit captures and the validation
    captures (``--validate``) do not all come from one instrument (their IDENTITY serial): a model is fitted
    and judged on its own instrument's data."""
    serials = {c.serial for c in [*captures, *validate]}
    if len(serials) == 1:
        return
    fitted = {c.serial for c in captures}
    by_serial = {
        serial: ", ".join(
            [c.path.name for c in captures if c.serial == serial]
            + [f"{c.path.name} (--validate)" for c in validate if c.serial == serial]
        )
        for serial in sorted(serials, key=str)
    }
    which = "fit captures" if len(fitted) > 1 else "fit and validation captures"
    raise InputFileError(
        f"the {which} come from different instruments: "
        + "; ".join(f"{serial or 'no serial'}: {names}" for serial, names in by_serial.items())
    )


def model_choice(
    models: dict[str, Any],
    kind: str,
    captures: list[CaptureData],
    normalizer: Standardizer,
    config: FitConfig,
    *,
    fall_back: bool,
    say: Callable[[str], None] = lambda text: None,
) -> dict[str, Any]:
    """``kind`` against the polynomial on the fit's own validation split: both models' held-out residuals
    over the same chunks (``own_validation_squares``), paired (``choice.paired_margin``), and the decision
    (``choice.choose``: with ``fall_back``, the polynomial only when it leaves less by more than
    ``SE_MULTIPLE`` standard errors)."""
    squares = {}
    for name in (kind, "polynomial"):
        say(f"own validation split: {name}, {VALIDATION_FOLDS} folds")
        squares[name] = own_validation_squares(models[name], captures, normalizer, config)
    return choose(paired_margin(squares[kind], squares["polynomial"]), kind, fall_back=fall_back)


def _add_findings(
    fit_quality: dict[str, Any],
    model: Any,
    captures: list[CaptureData],
    normalizer: Standardizer,
    config: FitConfig,
    say: Callable[[str], None],
) -> None:
    """What the fit reports beside its checks, into ``fit_quality``: the largest bias step
    (``bias_step_scan``; a warning, not a check: ``bias_step_warning``) and, for information, the condition
    number of the model's own regressors (the review's M6)."""
    say("bias step test")
    step = bias_step_scan(captures, normalizer, config.model_rate_hz)
    if step is not None:  # reported, not a check: see bias_step_warning
        fit_quality["bias_step"] = {
            "capture": captures[step.capture].path.name,
            "minute": step.minute,
            "step_dph": step.step_dph,
            "share": step.share,
        }
    rows = regressor_rows(model, captures, normalizer)
    if rows is not None:  # for information: the model's own regressors (the review's M6)
        fit_quality["model_condition"] = condition_number(np.vstack([r[c.static] for r, c in zip(rows, captures)]))


def _provenance(
    captures: list[CaptureData], validate: list[CaptureData], config: FitConfig, report: FitReport
) -> dict[str, Any]:
    """The model file's provenance before the model's own parts: the captures (name, SHA-256, blocks, and the
    chamber program of its run when the fit was told it: its name and where it was learned), the validation
    captures, the fit config, the report's rows and the noise floor."""
    floor = cast(tuple[float, float | None], report.noise_floor)  # report_for sets it
    return {
        "captures": [
            {
                "file": c.path.name,
                "sha256": c.sha256,
                "blocks": len(c.blocks),
                "static_blocks": int(c.static.sum()),
                "moving_blocks": c.moving_blocks,
                **({"program": {"name": c.program.name, "from": c.program.source}} if c.program else {}),
            }
            for c in captures
        ],
        "validate": [{"file": c.path.name, "sha256": c.sha256} for c in validate],
        "config": _plain(config),
        "metrics": {
            what: {
                "fit": fit_v,
                **({"validate": val_v} if val_v is not None else {}),
                **({"worse_than_uncompensated": report.worse()[what]} if what in report.worse() else {}),
            }
            for what, fit_v, val_v in report.rows
        },
        "noise_floor_1min_dph": {
            "fit": floor[0],
            **({"validate": floor[1]} if validate else {}),
        },
    }


class WeakFitError(InputFileError):
    """The fit data cannot support the model (``quality``); the fit's ``report`` and the unsaved
    ``model_file`` ride along for the caller to show."""

    def __init__(self, quality: FitQuality, report: FitReport, model_file: ModelFile) -> None:
        failed = quality.failed
        more = f" (and {len(failed) - 1} more)" if len(failed) > 1 else ""
        super().__init__(f"the fit data cannot support this model: {failed[0].message}{more}")
        self.quality, self.report, self.model_file = quality, report, model_file


def _assess(
    inputs: np.ndarray,
    means: np.ndarray,
    validate: list[CaptureData],
    normalizer: Standardizer,
    report: FitReport,
    kind: str,
    config: FitConfig,
) -> FitQuality:
    """``quality.assess`` of this fit (``static_rows``: its static inputs and target minute means): their
    span and duration, the data's conditioning, and its report's before/after rows for the saved model."""
    rate = config.model_rate_hz

    # the data's conditioning, in the physical basis every kind is built on (a model's own basis may be
    # collinear by design, e.g. the coil's rate beside the coil and the ring: the penalty handles that)
    condition = condition_number(polynomial_features(normalizer.transform(inputs)))
    by_name = {what: (fit_v, val_v) for what, fit_v, val_v in report.rows}
    before, after = by_name["before compensation"], by_name[f"after, {kind}"]
    validated = cast(tuple[float, float], (before[1], after[1])) if validate else None  # measured: validate given
    ring_c, ring_rate_c_per_min = ring_of(inputs)
    return assess(
        len(inputs) / rate / 60.0, ring_c, ring_rate_c_per_min, means, condition, (before[0], after[0]), validated
    )


def _plain(obj):
    if is_dataclass(obj):
        return {f.name: _plain(getattr(obj, f.name)) for f in fields(obj)}
    if isinstance(obj, tuple):
        return [_plain(v) for v in obj]
    return obj
