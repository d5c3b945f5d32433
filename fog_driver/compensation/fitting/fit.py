"""Fitting a drift model to static chamber captures, and the numbers that judge it.

Per capture: decode, block-average to the model rate, compute the 8 inputs,
and take the target ``r = rate - mean(rate over static blocks)``: each run has
its own turn-on bias, so each capture is centred on its own (the paper's
r(n) = D(n) + N(n), with B0 removed).  Blocks are excluded from the fit when
the table moves (|rate - running median| above a threshold, widened by a
margin), when inputs are stale or missing, during the rate smoother's
warm-up, or when frames were lost.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from ...errors import InputFileError
from ..blocks import FLAG_GAP, FLAG_THERMOMETER_FAULT, BlockAverager, BlockColumns
from ..domain import InputDomain
from ..features import (
    DEGRADED_FLAGS,
    V1_CHANNELS,
    FeatureExtractor,
    FeatureParams,
    fit_substitution,
    input_names,
    ring_of,
)
from ..readout import Standardizer
from .quality import FitQuality, assess, condition_number

if TYPE_CHECKING:
    from ..model import ModelFile


@dataclass(frozen=True)
class FitConfig:
    model_rate_hz: float = 1.0
    features: FeatureParams = field(default_factory=FeatureParams)
    motion_threshold_dph: float = 30.0  #: |rate - running median| above this is table motion
    motion_window_s: float = 61.0  #: running-median window
    motion_margin_s: float = 10.0  #: excluded on each side of detected motion
    motion_envelope_s: float = 900.0  #: the drift envelope: a running median of the rate over this window
    motion_sigmas: float = 8.0  #: |rate - envelope| above this many block-noise sigmas is motion ...
    motion_floor_dph: float = 1.0  #: ... and above this (a drift's own curvature inside the envelope's window)
    max_drift_dph: float = 5.0  #: the envelope farther than this from the capture's static level is motion
    warmup_s: float = 300.0  #: rate smoother and instrument start-up: not fitted
    poly_alpha: float | None = 1e-3  #: ridge penalty per row on standardized regressors; None: blocked CV

    def __post_init__(self) -> None:
        if not self.model_rate_hz > 0:
            raise ValueError("model_rate_hz must be > 0")
        if abs(self.features.sample_time_s * self.model_rate_hz - 1.0) > 1e-9:
            raise ValueError(
                f"features.sample_time_s ({self.features.sample_time_s}) must be 1 / model_rate_hz "
                f"({1.0 / self.model_rate_hz})"
            )


@dataclass
class CaptureData:
    """One capture at the model rate: what fitting and evaluation need."""

    path: Path
    sha256: str
    serial: str | None
    frame_period_s: float
    blocks: BlockColumns
    inputs: np.ndarray  #: (n, 8) raw inputs
    input_flags: np.ndarray
    static: np.ndarray  #: bool: usable for fitting
    target_dph: np.ndarray  #: rate minus this capture's static mean
    moving_blocks: int = 0  #: blocks the motion detector found (``motion_mask``; not fitted)
    #: its frame format's temperature channels (the inputs are ``features.input_names`` of them)
    channels: tuple[str, ...] = V1_CHANNELS
    wire_format: str = "fog-v1"

    @property
    def minutes(self) -> float:
        return len(self.blocks) / 60.0


def running_median(x: np.ndarray, window: int) -> np.ndarray:
    """Centred running median (odd ``window``), edges use the available samples."""
    half = window // 2
    padded = np.pad(x, half, mode="edge")
    view = np.lib.stride_tricks.sliding_window_view(padded, window)
    return np.median(view, axis=1)


def block_noise_dph(rate_dph: np.ndarray) -> float:
    """The white noise of one block's rate, robustly: 1.4826 MAD of first differences / sqrt(2) (a drift
    and the table's rare moves barely move the median of the differences)."""
    d = np.diff(rate_dph[np.isfinite(rate_dph)])
    if not len(d):
        return 0.0
    return float(1.4826 * np.median(np.abs(d - np.median(d))) / math.sqrt(2.0))


def motion_mask(rate_dph: np.ndarray, config: FitConfig) -> np.ndarray:
    """Blocks where the table moves, by three tests (each catches what the others miss):

    1. fast moves: ``|rate - running median (motion_window_s)| > motion_threshold_dph``;
    2. steady motion (a turn longer than half that window, which becomes its median) and slow creeps:
       ``|rate - E| > max(motion_sigmas * sigma_b, motion_floor_dph)``, E the running median over
       ``motion_envelope_s`` (a thermal drift changes little in 15 minutes), sigma_b the block noise
       (``block_noise_dph``);
    3. motion as long as the envelope itself: ``|E - L| > max_drift_dph``, L the median rate of the
       blocks 1 and 2 left (the capture's static level: Earth rate and bias), where no thermal drift goes.
    """
    rate = rate_dph
    rate_hz = config.model_rate_hz
    window = max(3, int(round(config.motion_window_s * rate_hz)) | 1)
    moving = np.abs(rate - running_median(rate, window)) > config.motion_threshold_dph
    envelope_window = max(3, int(round(config.motion_envelope_s * rate_hz)) | 1)
    if len(rate) >= 3:
        envelope = running_median(rate, envelope_window)
        sigma = block_noise_dph(rate)
        moving |= np.abs(rate - envelope) > max(config.motion_sigmas * sigma, config.motion_floor_dph)
        if (~moving).any():
            level = float(np.median(rate[~moving]))
            moving |= np.abs(envelope - level) > config.max_drift_dph
    return moving


def static_mask(
    blocks: BlockColumns,
    input_flags: np.ndarray,
    config: FitConfig,
    moving: np.ndarray | None = None,
    n_channels: int = 3,
) -> np.ndarray:
    """Blocks to fit: no motion (``moving``, by default ``motion_mask``; widened by ``motion_margin_s``),
    fresh, measured (not substituted) and settled thermometers, no lost frames, past the warm-up."""
    return ~np.any(list(_exclusions(blocks, input_flags, config, moving, n_channels).values()), axis=0)


def _exclusions(
    blocks: BlockColumns,
    input_flags: np.ndarray,
    config: FitConfig,
    moving: np.ndarray | None = None,
    n_channels: int = 3,
) -> dict[str, np.ndarray]:
    """Why each block is not fitted (``static_mask``): one mask per reason, named as ``no_static_reason``
    tells the user.  ``n_channels``: the temperature places the capture's format fills."""
    moving = motion_mask(blocks.rate_dph, config) if moving is None else moving
    margin = int(round(config.motion_margin_s * config.model_rate_hz))
    if margin and moving.any():
        kernel = np.ones(2 * margin + 1)
        moving = np.convolve(moving.astype(float), kernel, mode="same") > 0
    return {
        "warm-up": blocks.t_end_s <= config.warmup_s,
        "table motion (with motion_margin_s either side)": moving,
        "no valid, settled thermometers": ((input_flags & DEGRADED_FLAGS) != 0)
        | ~np.all(np.isfinite(blocks.temps_c[:, :n_channels]), axis=1),
        "lost frames": (blocks.flags & FLAG_GAP) != 0,
    }


def no_static_reason(
    blocks: BlockColumns,
    input_flags: np.ndarray,
    config: FitConfig,
    moving: np.ndarray,
    warmup_setting: str,
    n_channels: int = 3,
) -> str:
    """Why no block is static and valid, in the user's terms: the capture's length against the warm-up
    (named as ``warmup_setting``), or how many of the blocks after it each reason excluded."""
    length_s = float(blocks.t_end_s[-1]) if len(blocks) else 0.0
    reasons = _exclusions(blocks, input_flags, config, moving, n_channels)
    warmup = reasons.pop("warm-up")
    if warmup.all():
        return (
            f"the capture is {length_s:.0f} s and its first {config.warmup_s:g} s are excluded as warm-up "
            f"({warmup_setting})"
        )
    after = ~warmup
    counts = ", ".join(
        f"{int(np.count_nonzero(mask & after)):,} {why}" for why, mask in reasons.items() if (mask & after).any()
    )
    return f"of its {int(after.sum()):,} blocks after the {config.warmup_s:g}-s warm-up: {counts}"


def measured_rows(capture: CaptureData, config: FitConfig) -> np.ndarray:
    """Blocks where all three thermometers were measured and their smoothers settled (past the warm-up),
    moving or not: the data the sensors' thermal coupling (``features.fit_substitution``) is fitted on."""
    ok = capture.input_flags == 0
    ok &= (capture.blocks.flags & FLAG_THERMOMETER_FAULT) == 0
    ok &= capture.blocks.t_end_s > config.warmup_s
    return ok & np.all(np.isfinite(capture.inputs), axis=1)


def load_capture(
    path: str | Path,
    config: FitConfig,
    progress: Callable[[int, int], None] | None = None,
    *,
    purpose: str = "to fit",
    warmup_setting: str = "warmup_s in the fit config, fit --config FILE",
    wire_format: str = "auto",
) -> CaptureData:
    """Decode a capture block by block and reduce it to the model rate; ``progress(bytes read, file size)``
    after every block read.  No static, valid block is an ``InputFileError`` saying why
    (``no_static_reason``; ``purpose`` and ``warmup_setting`` word it).  ``wire_format``: ``--format``
    (``sources.wire_settings_for``: auto reads the sidecar, else sniffs)."""
    from ...samples.sources import CaptureReader, wire_settings_for

    path = Path(path)
    sha = hashlib.sha256()
    wire = wire_settings_for(path, wire_format)
    reader = CaptureReader(path, wire)
    n_channels = len(wire.temperature_channels)
    averager: BlockAverager | None = None
    parts = []
    on_block = sha.update
    if progress is not None:
        size = path.stat().st_size if path.is_file() else 0
        done = [0]

        def on_block(block: bytes) -> None:
            sha.update(block)
            done[0] += len(block)
            progress(done[0], size)

    for part in reader.parts(on_block=on_block):
        samples = part.samples
        if averager is None:
            if reader.identity is None:
                if not len(samples):
                    continue
                raise InputFileError(f"{path}: no IDENTITY frame before the first sample: frame rate unknown")
            averager = BlockAverager(1.0 / reader.identity.rate_hz, config.model_rate_hz, n_channels)
        parts.append(averager.run(samples))
    if averager is None:
        from ...samples.captures import what_it_is

        raise InputFileError(f"{path}: no SAMPLE frames to fit{what_it_is(path)}")
    parts.append(BlockColumns.from_blocks(averager.flush()))
    blocks = BlockColumns(*(np.concatenate([getattr(p, f) for p in parts]) for f in BlockColumns.__dataclass_fields__))
    inputs, input_flags = FeatureExtractor(config.features, n_channels=n_channels).run(blocks.temps_c)
    moving = motion_mask(blocks.rate_dph, config)
    static = static_mask(blocks, input_flags, config, moving, n_channels)
    if not static.any():
        reason = no_static_reason(blocks, input_flags, config, moving, warmup_setting, n_channels)
        raise InputFileError(f"{path}: no static, valid block {purpose}: {reason}")
    target = blocks.rate_dph - blocks.rate_dph[static].mean()
    identity = reader.identity
    return CaptureData(
        path,
        sha.hexdigest(),
        identity.serial if identity else None,
        averager.frame_period_s,
        blocks,
        inputs,
        input_flags,
        static,
        target,
        int(moving.sum()),
        wire.temperature_channels,
        wire.format,
    )


def minute_rms(residual_dph: np.ndarray, mask: np.ndarray, model_rate_hz: float = 1.0) -> float:
    """RMS of 1-minute averages of a residual over the usable blocks, its mean removed (a bias is not drift)."""
    means = static_minute_means(residual_dph, mask, model_rate_hz)
    if not len(means):
        return float("nan")
    return float(np.sqrt(np.mean((means - means.mean()) ** 2)))


def fit_normalizer(captures: list[CaptureData]) -> Standardizer:
    return Standardizer.fit(np.vstack([c.inputs[c.static] for c in captures]))


def applied_prediction(
    model, capture: CaptureData, normalizer: Standardizer, domain: InputDomain | None = None
) -> np.ndarray:
    """The drift the compensator would apply in each block: the model's output from the block before,
    the model started at rest at the first valid input (as ``Compensator`` does), its inputs clamped to
    ``domain`` and its output bounded by it (as ``Compensator`` does)."""
    from ..models.wesn import first_valid_block

    u = np.where(np.isfinite(capture.inputs), capture.inputs, 0.0)
    if domain is not None:
        u, _ = domain.clamp(u)
    z = normalizer.transform(u)
    first = first_valid_block(capture.inputs)
    model.reset()
    model.start(z[first])
    out = np.zeros(len(z))
    out[first:] = model.run(z[first:])
    if domain is not None:
        out, _ = domain.bound_many(out)
    return np.r_[0.0, out[:-1]]


def static_minute_means(values: np.ndarray, mask: np.ndarray, model_rate_hz: float) -> np.ndarray:
    """Means of ``values`` over the whole minutes whose blocks are all in ``mask``."""
    per_minute = int(round(60 * model_rate_hz))
    n = len(values) // per_minute * per_minute
    full = mask[:n].reshape(-1, per_minute).all(axis=1)
    return values[:n].reshape(-1, per_minute)[full].mean(axis=1)


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
    from ..models.polynomial import polynomial_features

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
    temperature terms' misfit alone produces.  Not a failing check: without a step, the 12 development
    instruments' paper runs (the polynomial's misfit of a coil lag) show steps up to 0.07 deg/h explaining
    up to 20 % of the residual; a 0.1 deg/h step mid-run explains 32 %.  ``n_channels``: the thermometers the
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


def static_rows(captures: list[CaptureData], model_rate_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """The fit's static inputs (rows, 8) and its target's whole static 1-minute means, all captures."""
    inputs = np.vstack([c.inputs[c.static] for c in captures])
    means = np.concatenate([static_minute_means(c.target_dph, c.static, model_rate_hz) for c in captures])
    return inputs, means


#: The marker on a report row whose model leaves more drift than no compensation.
WORSE_MARKER = "WORSE than uncompensated"


@dataclass
class FitReport:
    """Drift RMS of 1-minute averages (usable blocks, mean removed), deg/h.

    A model row that leaves more than the "before compensation" row in a column is marked
    ``WORSE_MARKER`` (``worse``).  ``noise_floor`` (fit data, validate data or None): the white noise of
    the 1-s blocks over sqrt(60) (``noise_floor_dph``), what the 1-minute RMS of a perfect model still
    holds on measured data, in expectation (a few minutes, or a model fitted to them, can show less)."""

    rows: list[tuple[str, float, float | None]]  #: (what, on fit data, on validate data)
    noise_floor: tuple[float, float | None] | None = None

    def worse(self) -> dict[str, list[str]]:
        """For each model row worse than no compensation: the columns ("fit", "validate") where it is."""
        before = self.rows[0]
        out: dict[str, list[str]] = {}
        for what, fit_value, validate_value in self.rows[1:]:
            cols = [
                col
                for col, v, b in (("fit", fit_value, before[1]), ("validate", validate_value, before[2]))
                if v is not None and b is not None and v > b
            ]
            if cols:
                out[what] = cols
        return out

    def format(self) -> str:
        has_validate = any(v is not None for _, _, v in self.rows)
        header = f"{'1-min drift RMS, deg/h':34s} {'fit data':>10s}" + (f" {'validate':>10s}" if has_validate else "")
        lines = [header]
        worse = self.worse()
        rows = list(self.rows)
        if self.noise_floor is not None:
            rows.append(("noise floor (white, 1-min means)", *self.noise_floor))
        for what, fit_value, validate_value in rows:
            line = f"{what:34s} {fit_value:10.4f}"
            if has_validate:
                line += f" {validate_value:10.4f}" if validate_value is not None else f" {'':>10s}"
            if what in worse:
                where = " and ".join("validation" if c == "validate" else "fit data" for c in worse[what])
                line += f"  {WORSE_MARKER} ({where})"
            lines.append(line)
        return "\n".join(lines)

    def floor_note(self) -> str | None:
        """The line that says what the noise floor means for the table."""
        if self.noise_floor is None:
            return None
        fit_floor, validate_floor = self.noise_floor
        also = f", {validate_floor:.4f} on the validation data" if validate_floor is not None else ""
        return (
            f"noise floor of 1-min means: {fit_floor:.4f} deg/h on the fit data{also}: the gyro's white noise, "
            f"which no model removes; differences between models well below it are not meaningful on measured "
            f"data (evaluate --truth scores against the true drift)"
        )


def noise_floor_dph(captures: list[CaptureData], rate_hz: float) -> float:
    """The white-noise floor of 1-minute means, deg/h: ``block_noise_dph`` of each capture's static blocks
    (1.4826 MAD of first differences / sqrt(2)) over sqrt(blocks a minute), pooled as an RMS."""
    per_minute = 60.0 * rate_hz
    values = [block_noise_dph(c.blocks.rate_dph[c.static]) / math.sqrt(per_minute) for c in captures if c.static.any()]
    return float(np.sqrt(np.mean(np.square(values)))) if values else float("nan")


def _pooled_minute_rms(captures: list[CaptureData], residuals: list[np.ndarray], rate_hz: float) -> float:
    values = [minute_rms(r, c.static, rate_hz) for c, r in zip(captures, residuals)]
    values = [v for v in values if v == v]
    return float(np.sqrt(np.mean(np.square(values)))) if values else float("nan")


def report_for(
    models: dict[str, object],
    normalizer: Standardizer,
    fit_data: list[CaptureData],
    validate: list[CaptureData],
    rate_hz: float,
    domain: InputDomain | None = None,
    progress: Callable[[str], None] | None = None,
) -> FitReport:
    """Drift RMS before and after each model, on the fit data and the validation data (each model applied
    as the compensator applies it: inputs clamped to ``domain``, estimates bounded), and the noise floor."""
    runs = len(models) * (len(fit_data) + len(validate))
    done = [0]

    def rms_after(name, model, captures, where):
        if not captures:
            return None
        residuals = []
        for c in captures:
            if progress is not None:
                progress(f"{where} {name} on {c.path.name} ({100 * done[0] / runs:.0f} %)")
            done[0] += 1
            residuals.append(c.target_dph - applied_prediction(model, c, normalizer, domain))
        return _pooled_minute_rms(captures, residuals, rate_hz)

    before_fit = _pooled_minute_rms(fit_data, [c.target_dph for c in fit_data], rate_hz)
    before_val = _pooled_minute_rms(validate, [c.target_dph for c in validate], rate_hz) if validate else None
    rows: list[tuple[str, float, float | None]] = [("before compensation", before_fit, before_val)]
    for name, model in models.items():
        rows.append(
            (
                f"after, {name}",
                rms_after(name, model, fit_data, "applying"),
                rms_after(name, model, validate, "validating"),
            )
        )
    floor = (noise_floor_dph(fit_data, rate_hz), noise_floor_dph(validate, rate_hz) if validate else None)
    return FitReport(rows, floor)


def regressor_rows(model, captures: list[CaptureData], normalizer: Standardizer) -> list[np.ndarray] | None:
    """Each capture's regressor matrix (every block) for the models whose readout is a linear regression
    (the polynomial and the ring ``wesn``); None for the others."""
    from ..models.polynomial import PolynomialModel, polynomial_features

    if isinstance(model, PolynomialModel):
        return [
            polynomial_features(normalizer.transform(np.where(np.isfinite(c.inputs), c.inputs, 0.0))) for c in captures
        ]
    if getattr(model, "selection", None):  # the ring wesn (its structure chosen by the fit)
        from ..models.wesn import _capture_regressors

        return [_capture_regressors(model, c, normalizer, None) for c in captures]
    return None


#: The fit's own validation split: chunks of device time dealt in turn to the folds.
VALIDATION_CHUNK_S = 1200.0
VALIDATION_FOLDS = 4


def own_validation(model, captures: list[CaptureData], normalizer: Standardizer, config: FitConfig) -> float:
    """The drift a model's structure leaves on data it was not fitted on, from the fit data alone, deg/h.

    Chunks of ``VALIDATION_CHUNK_S`` device time (shorter for captures under 4 chunks) are dealt in turn to
    ``VALIDATION_FOLDS`` folds; for each fold the model's readout is refitted, at its chosen structure and
    penalty and with one intercept per capture, on the other folds' static blocks, and its residual on the
    fold is averaged over windows of half a chunk (10 minutes) inside it.  Returns the RMS of those means,
    each capture's and fold's mean removed.  For the polynomial and the ring ``wesn`` (the structures the
    fit compares); interleaved folds keep every temperature in each training set."""
    from ..models.polynomial import PolynomialModel, standardized_ridge

    rate = config.model_rate_hz
    longest = max(len(c.static) for c in captures)
    window = max(1, min(int(round(VALIDATION_CHUNK_S * rate)), longest // (2 * VALIDATION_FOLDS)) // 2)
    chunk = 2 * window  # whole windows in every chunk
    rows = regressor_rows(model, captures, normalizer)
    if isinstance(model, PolynomialModel):
        alpha, penalty = (config.poly_alpha if config.poly_alpha is not None else 1e-3), None
    else:
        sel = model.selection
        alpha = sel["ridge_alpha"]
        penalty = np.ones(len(model.weights))
        penalty[1 : 1 + len(sel["history_s"])] = sel["history_penalty"]
    index = [np.flatnonzero(c.static) for c in captures]
    x = np.vstack([f[i] for f, i in zip(rows, index)])
    y = np.concatenate([c.target_dph[i] for c, i in zip(captures, index)])
    group = np.concatenate([np.full(len(i), g) for g, i in enumerate(index)])
    block = np.concatenate(index)
    fold = (block // chunk) % VALIDATION_FOLDS
    squares, count = 0.0, 0
    for k in range(VALIDATION_FOLDS):
        train, test = fold != k, fold == k
        if not train.any() or not test.any():
            continue
        w, b = standardized_ridge(x[train], y[train], alpha, penalty, group[train])
        residual = y[test] - (x[test] @ w + b)
        for g in np.unique(group[test]):
            mine = group[test] == g
            windows, inverse, sizes = np.unique(block[test][mine] // window, return_inverse=True, return_counts=True)
            means = np.bincount(inverse, weights=residual[mine])[sizes == window] / window
            if len(means) > 1:
                squares += float(np.sum((means - means.mean()) ** 2))
                count += len(means)
    return float(np.sqrt(squares / count)) if count else float("nan")


def _fit_polynomial(captures: list[CaptureData], normalizer: Standardizer, config: FitConfig, progress=None):
    from ..models.polynomial import PolynomialModel

    if progress is not None:
        progress("polynomial: ridge regression")
    z = np.vstack([normalizer.transform(c.inputs[c.static]) for c in captures])
    y = np.concatenate([c.target_dph[c.static] for c in captures])
    return PolynomialModel.fit(z, y, config.poly_alpha, capture_groups(captures))


def capture_groups(captures: list[CaptureData]) -> np.ndarray:
    """For rows stacked from each capture's static blocks: the index of the capture each comes from
    (each capture has its own offset: its turn-on bias and its own mean drift, see ``standardized_ridge``)."""
    return np.concatenate([np.full(int(c.static.sum()), i) for i, c in enumerate(captures)])


def _fit_wesn(kind: str):
    from ..models.wesn import PAPER_DEFAULTS, WESN_DEFAULTS, fit_wesn

    defaults = {"wesn": WESN_DEFAULTS, "paper": PAPER_DEFAULTS}[kind]
    return lambda captures, normalizer, config, progress=None: fit_wesn(
        kind, defaults, captures, normalizer, config, progress
    )


def _fit_pso_svr(captures: list[CaptureData], normalizer: Standardizer, config: FitConfig, progress=None):
    from ..models.svr import PSO_SVR_DEFAULTS, fit_pso_svr

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


def fit_model_file(
    paths: list[str | Path],
    *,
    kind: str,
    config: FitConfig,
    validate_paths: list[str | Path] = (),
    fall_back: bool = False,
    accept_weak: bool = False,
    progress: Callable[[str], None] | None = None,
    wire_format: str = "auto",
) -> tuple[ModelFile, FitReport]:
    """Fit ``kind`` (and the polynomial baseline beside it) to captures; return the model file and the report.

    A ring ``wesn`` is compared with the polynomial on the fit's own validation split (``own_validation``);
    when it does worse, its provenance says so, and with ``fall_back`` (``fog-driver fit`` without
    ``--kind``) the polynomial's model file is returned instead.  The fit's data are checked
    (``quality.assess``): a fit that fails a check raises ``WeakFitError`` unless ``accept_weak``, and
    then the model file's ``provenance.fit_quality`` records the failures and that they were accepted.
    ``progress(text)`` hears every phase and how far it is ("decoding paper.bin 40 %", "pso-svr: iteration
    4/20, particle 12/16 (21 %)", "validating wesn on fast.bin (75 %)").  ``wire_format``: ``--format`` (the
    captures' frame format; auto: each capture's sidecar, else sniffed); every capture must have the same
    temperature channels, which the model file records."""
    from ..model import ModelFile

    if kind not in FITTERS:
        raise InputFileError(f"unknown model kind {kind!r} (known: {', '.join(sorted(FITTERS))})")
    say = progress or (lambda text: None)

    def decoding(p):
        name = Path(p).name
        return (
            None if progress is None else lambda done, total: say(f"decoding {name} {100 * done / max(total, 1):.0f} %")
        )

    captures = [load_capture(p, config, decoding(p), wire_format=wire_format) for p in paths]
    validate = [load_capture(p, config, decoding(p), wire_format=wire_format) for p in validate_paths]
    for c in [*captures[1:], *validate]:
        if c.channels != captures[0].channels:
            raise InputFileError(
                f"{c.path}: {c.wire_format} frames with temperature channels {', '.join(c.channels)}; "
                f"{captures[0].path.name} has {', '.join(captures[0].channels)}: one model is "
                f"fitted on one instrument's channels"
            )
    serials = {c.serial for c in captures}
    if len(serials) != 1:
        raise InputFileError(
            f"the fit captures come from different instruments: {', '.join(sorted(map(str, serials)))}"
        )
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
    provenance = {
        "captures": [
            {
                "file": c.path.name,
                "sha256": c.sha256,
                "blocks": len(c.blocks),
                "static_blocks": int(c.static.sum()),
                "moving_blocks": c.moving_blocks,
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
            "fit": report.noise_floor[0],
            **({"validate": report.noise_floor[1]} if validate else {}),
        },
    }
    selection = getattr(models[kind], "selection", None)
    if selection:
        provenance["selection"] = selection
        scores = {}
        for name in ("polynomial", kind):
            say(f"own validation split: {name}, {VALIDATION_FOLDS} folds")
            scores[name] = own_validation(models[name], captures, normalizer, config)
        selection["own_validation_rms_dph"] = scores
        if scores[kind] > scores["polynomial"]:
            selection["warning_validation"] = (
                f"on its own validation split (interleaved {VALIDATION_CHUNK_S / 60:g}-min chunks of the fit data) the "
                f"{kind} leaves {scores[kind]:.4f} deg/h, the polynomial {scores['polynomial']:.4f}"
            )
            if fall_back:
                kind = "polynomial"
                provenance["fell_back"] = f"{selection['warning_validation']}: the polynomial was saved instead"
    quality = _assess(inputs, means, validate, normalizer, report, kind, config)
    provenance["fit_quality"] = quality.to_dict(accept_weak)
    say("bias step test")
    step = bias_step_scan(captures, normalizer, config.model_rate_hz)
    if step is not None:  # reported, not a check: see bias_step_warning
        provenance["fit_quality"]["bias_step"] = {
            "capture": captures[step.capture].path.name,
            "minute": step.minute,
            "step_dph": step.step_dph,
            "share": step.share,
        }
    rows = regressor_rows(models[kind], captures, normalizer)
    if rows is not None:  # for information: the model's own regressors (the review's M6)
        provenance["fit_quality"]["model_condition"] = condition_number(
            np.vstack([r[c.static] for r, c in zip(rows, captures)])
        )
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
    )
    if quality.failed and not accept_weak:
        raise WeakFitError(quality, report, model_file)
    return model_file, report


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
    from ..models.polynomial import polynomial_features

    rate = config.model_rate_hz

    # the data's conditioning, in the physical basis every kind is built on (a model's own basis may be
    # collinear by design, e.g. the coil's rate beside the coil and the ring: the penalty handles that)
    condition = condition_number(polynomial_features(normalizer.transform(inputs)))
    by_name = {what: (fit_v, val_v) for what, fit_v, val_v in report.rows}
    before, after = by_name["before compensation"], by_name[f"after, {kind}"]
    validated = (before[1], after[1]) if validate else None
    ring_c, ring_rate_c_per_min = ring_of(inputs)
    return assess(
        len(inputs) / rate / 60.0, ring_c, ring_rate_c_per_min, means, condition, (before[0], after[0]), validated
    )


def _plain(obj):
    from dataclasses import fields as dc_fields
    from dataclasses import is_dataclass

    if is_dataclass(obj):
        return {f.name: _plain(getattr(obj, f.name)) for f in dc_fields(obj)}
    if isinstance(obj, tuple):
        return [_plain(v) for v in obj]
    return obj
