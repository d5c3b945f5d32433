"""Files in, files out: fitting a drift model to capture files (``fog-driver fit``).

``load_capture`` decodes a capture block by block and reduces it to the model rate
(``compensation.fitting.data.capture_data`` makes it the fit's data); ``fit_model_file`` reads the
captures and fits (``compensation.fitting.fit.fit_model``).  Saving the model file is ``modelfiles``'.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from ..compensation.blocks import BlockAverager, BlockColumns
from ..compensation.fitting.data import CaptureData, FitConfig, capture_data
from ..compensation.fitting.fit import WeakFitError, check_kind, fit_model
from ..compensation.fitting.report import FitReport
from ..compensation.model import ModelFile
from ..errors import InputFileError
from ..samples.captures import what_it_is
from ..samples.sources import CaptureReader, wire_settings_for

__all__ = ["FitConfig", "WeakFitError", "fit_model_file", "load_capture"]  # the fit at its edge


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
    (``fitting.data.no_static_reason``; ``purpose`` and ``warmup_setting`` word it).  ``wire_format``: ``--format``
    (``sources.wire_settings_for``: auto reads the sidecar, else sniffs)."""
    path = Path(path)
    sha = hashlib.sha256()
    wire = wire_settings_for(path, wire_format)
    reader = CaptureReader(path, wire)
    n_channels = len(wire.temperature_channels)
    averager: BlockAverager | None = None
    parts = []
    on_block: Callable[[bytes], None] = sha.update
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
        raise InputFileError(f"{path}: no SAMPLE frames to fit{what_it_is(path)}")
    parts.append(BlockColumns.from_blocks(averager.flush()))
    blocks = BlockColumns(*(np.concatenate([getattr(p, f) for p in parts]) for f in BlockColumns.__dataclass_fields__))
    identity = reader.identity
    return capture_data(
        path,
        sha.hexdigest(),
        identity.serial if identity else None,
        averager.frame_period_s,
        blocks,
        config,
        wire.temperature_channels,
        wire.format,
        purpose=purpose,
        warmup_setting=warmup_setting,
    )


def fit_model_file(
    paths: Sequence[str | Path],
    *,
    kind: str,
    config: FitConfig,
    validate_paths: Sequence[str | Path] = (),
    fall_back: bool = False,
    accept_weak: bool = False,
    progress: Callable[[str], None] | None = None,
    wire_format: str = "auto",
) -> tuple[ModelFile, FitReport]:
    """Fit ``kind`` (and the polynomial baseline beside it) to capture files; return the model file and the
    report (``compensation.fitting.fit.fit_model``: the comparisons, the checks, ``WeakFitError``).

    ``progress(text)`` hears every phase and how far it is ("decoding paper.bin 40 %", then the fit's).
    ``wire_format``: ``--format`` (the captures' frame format; auto: each capture's sidecar, else sniffed);
    every capture must have the same temperature channels, which the model file records."""
    check_kind(kind)
    say = progress or (lambda text: None)

    def decoding(p: str | Path) -> Callable[[int, int], None] | None:
        name = Path(p).name
        return (
            None if progress is None else lambda done, total: say(f"decoding {name} {100 * done / max(total, 1):.0f} %")
        )

    captures = [load_capture(p, config, decoding(p), wire_format=wire_format) for p in paths]
    validate = [load_capture(p, config, decoding(p), wire_format=wire_format) for p in validate_paths]
    return fit_model(
        captures, validate, kind=kind, config=config, fall_back=fall_back, accept_weak=accept_weak, progress=progress
    )
