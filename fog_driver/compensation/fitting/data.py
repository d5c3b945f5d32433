"""The fit's data, assembled: one capture at the model rate (``CaptureData``) and which of its blocks
are fitted (a leaf of ``fitting``: blocks and inputs in, masks and targets out).

Per capture: block-average to the model rate, compute the 8 inputs, and take the target
``r = rate - mean(rate over static blocks)``: each run has its own turn-on bias, so each capture is
centred on its own (the paper's r(n) = D(n) + N(n), with B0 removed).  Blocks are excluded from the
fit when the table moves (|rate - running median| above a threshold, widened by a margin), when
inputs are stale or missing, during the rate smoother's warm-up, or when frames were lost.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ...errors import InputFileError
from ...flags import FLAG_GAP, FLAG_THERMOMETER_FAULT
from ..blocks import BlockColumns
from ..features import DEGRADED_FLAGS, V1_CHANNELS, FeatureExtractor, FeatureParams
from ..readout import Standardizer

if TYPE_CHECKING:
    from .program import RunProgram


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
    #: the chamber program its run followed, judged (``program.RunProgram``), when the fit was told it
    program: RunProgram | None = None

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


def fit_normalizer(captures: list[CaptureData]) -> Standardizer:
    return Standardizer.fit(np.vstack([c.inputs[c.static] for c in captures]))


def whole_static_minutes(mask: np.ndarray, model_rate_hz: float) -> np.ndarray:
    """For each whole minute of blocks: True where all its blocks are in ``mask``."""
    per_minute = int(round(60 * model_rate_hz))
    n = len(mask) // per_minute * per_minute
    return np.asarray(mask[:n].reshape(-1, per_minute).all(axis=1), dtype=bool)


def static_minute_means(values: np.ndarray, mask: np.ndarray, model_rate_hz: float) -> np.ndarray:
    """Means of ``values`` over the whole minutes whose blocks are all in ``mask``."""
    full = whole_static_minutes(mask, model_rate_hz)
    per_minute = int(round(60 * model_rate_hz))
    return values[: len(full) * per_minute].reshape(-1, per_minute)[full].mean(axis=1)


def static_minute_count(captures: list[CaptureData], model_rate_hz: float) -> int:
    """How many whole static minutes the captures hold (as many as ``static_rows``' means)."""
    return sum(int(whole_static_minutes(c.static, model_rate_hz).sum()) for c in captures)


def static_rows(captures: list[CaptureData], model_rate_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """The fit's static inputs (rows, 8) and its target's whole static 1-minute means, all captures."""
    inputs = np.vstack([c.inputs[c.static] for c in captures])
    means = np.concatenate([static_minute_means(c.target_dph, c.static, model_rate_hz) for c in captures])
    return inputs, means


def capture_groups(captures: list[CaptureData]) -> np.ndarray:
    """For rows stacked from each capture's static blocks: the index of the capture each comes from
    (each capture has its own offset: its turn-on bias and its own mean drift, see ``standardized_ridge``)."""
    return np.concatenate([np.full(int(c.static.sum()), i) for i, c in enumerate(captures)])


def first_valid_block(inputs: np.ndarray) -> int:
    """The first block whose inputs are all finite (where a model starts at rest); ``ValueError`` when none is."""
    valid = np.flatnonzero(np.all(np.isfinite(inputs), axis=1))
    if not len(valid):
        raise ValueError("no block with valid inputs")
    return int(valid[0])


def capture_data(
    path: Path,
    sha256: str,
    serial: str | None,
    frame_period_s: float,
    blocks: BlockColumns,
    config: FitConfig,
    channels: tuple[str, ...],
    wire_format: str,
    *,
    purpose: str,
    warmup_setting: str,
) -> CaptureData:
    """A capture's blocks (decoded at ``path``, of the frame format ``wire_format`` with temperature
    ``channels``) made the fit's data: inputs, static blocks and the target centred on their mean.  No
    static, valid block is an ``InputFileError`` saying why (``no_static_reason``; ``purpose`` and
    ``warmup_setting`` word it)."""
    n_channels = len(channels)
    inputs, input_flags = FeatureExtractor(config.features, n_channels=n_channels).run(blocks.temps_c)
    moving = motion_mask(blocks.rate_dph, config)
    static = static_mask(blocks, input_flags, config, moving, n_channels)
    if not static.any():
        reason = no_static_reason(blocks, input_flags, config, moving, warmup_setting, n_channels)
        raise InputFileError(f"{path}: no static, valid block {purpose}: {reason}")
    target = blocks.rate_dph - blocks.rate_dph[static].mean()
    return CaptureData(
        path,
        sha256,
        serial,
        frame_period_s,
        blocks,
        inputs,
        input_flags,
        static,
        target,
        int(moving.sum()),
        channels,
        wire_format,
    )
