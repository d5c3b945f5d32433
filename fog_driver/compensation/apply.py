"""Compensating a capture file: the loop ``fog-driver compensate`` and the benchmarks share."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path

from ..errors import InputFileError, UsageError
from ..protocol import iter_decode_file
from ..stream import SampleStream
from .adapt import AdaptConfig
from .compensator import CompensatedColumns, Compensator
from .model import ModelFile


def compensate_capture(
    path: str | Path,
    model_file: ModelFile,
    *,
    force: bool = False,
    progress: Callable[[int], None] | None = None,
    model_name: str = "the model",
    adapt: AdaptConfig | None = None,
    reference_rate_dph: float | None = None,
    adapt_state: str | Path | None = None,
) -> Iterator[tuple[float, CompensatedColumns]]:
    """Decode ``path`` block by block and yield (frame period s, compensated frames), bounded memory.

    The frame period comes from the capture's IDENTITY frame; a model fitted for another
    instrument serial is a ``UsageError`` unless ``force``.  With ``adapt`` the weights adapt online
    against ``reference_rate_dph``; ``adapt_state`` is restored first when it exists (as a new run: the
    bias is captured again) and saved when the capture ends.
    """
    stream = SampleStream()
    compensator: Compensator | None = None
    for part in iter_decode_file(path):
        samples = stream.run(part)
        if progress:
            progress(part.counters.bytes_in)
        if compensator is None:
            if not len(samples):
                continue
            identity = stream.identity
            if identity is None:
                raise InputFileError(f"{path}: no IDENTITY frame before the first sample: frame rate unknown")
            if identity.serial != model_file.instrument_serial and not force:
                raise UsageError(
                    f"{model_name} was fitted for instrument {model_file.instrument_serial!r}, "
                    f"this capture is from {identity.serial!r} (use --force to apply it anyway)"
                )
            compensator = Compensator(model_file, 1.0 / identity.rate_hz, adapt=adapt,
                                      reference_rate_dph=reference_rate_dph)  # fmt: skip
            if adapt is not None and adapt_state is not None and Path(adapt_state).exists():
                compensator.load_adaptation(adapt_state)
        yield compensator.frame_period_s, compensator.run(samples)
    if compensator is None:
        raise InputFileError(f"{path}: no SAMPLE frames to compensate")
    if adapt is not None and adapt_state is not None:
        compensator.save_adaptation(adapt_state)
