"""Files in, files out: a model applied to a capture file (``fog-driver compensate``, ``evaluate``).

``compensate_capture`` decodes a capture block by block and compensates it with the daemon's binding rules
(``compensation.binding.InstrumentCompensation``), so that a capture compensated offline gives what the
daemon published; ``rows`` aggregates its frames into the CSV rows.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import cast

from ..compensation.adapt import AdaptConfig
from ..compensation.binding import InstrumentCompensation, check_channels, split_at_identities
from ..compensation.model import ModelFile
from ..compensation.pipeline import CompensatedColumns, Compensator
from ..errors import InputFileError
from ..modelfiles import adaptation_restorer, save_adaptation
from ..samples.captures import what_it_is
from ..samples.sources import CaptureReader, wire_settings_for
from ..samples.stream import SampleBlock


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
    scale_override_arcsec_per_count: float | None = None,
    save_adapt_state: bool = True,
    wire_format: str = "auto",
) -> Iterator[tuple[float, CompensatedColumns]]:
    """Decode ``path`` block by block and yield (frame period s, compensated frames), bounded memory.

    The binding rules of ``InstrumentCompensation`` (the module docstring).  With ``adapt`` the weights adapt
    online against ``reference_rate_dph`` (None: frozen, but a restored state's adapted weights give the
    estimate, as in the daemon); ``adapt_state`` is restored first when it exists (as a new run: the bias is
    captured again) and, with ``save_adapt_state``, saved when the capture ends.
    ``scale_override_arcsec_per_count``: the daemon's setting of that name.  ``wire_format``: ``--format``
    (``sources.wire_settings_for``); a model fitted on other temperature channels is refused first.
    """
    wire = wire_settings_for(path, wire_format)
    check_channels(model_file, wire, model_name, str(path))
    reader = CaptureReader(path, wire, scale_override_arcsec_per_count)
    binding = InstrumentCompensation(
        model_file,
        force=force,
        model_name=model_name,
        adapt=adapt,
        reference_rate_dph=reference_rate_dph,
        restore_adaptation=adaptation_restorer(adapt_state),
    )
    pending: list[SampleBlock] = []  # samples before the first IDENTITY
    samples_seen = 0
    for part in reader.parts():
        samples = part.samples
        samples_seen += len(samples)
        if progress:
            progress(part.bytes_in)
        for identity, block in split_at_identities(samples, part.identities, binding):
            if identity is not None:
                binding.bind(identity)
            if not binding.bound:
                if len(block):
                    pending.append(block)
                continue
            frame_period_s = cast(Compensator, binding.compensator).frame_period_s  # bound
            for earlier in pending:
                yield frame_period_s, binding.run(earlier)
            pending = []
            if len(block):
                yield frame_period_s, binding.run(block)
    if not samples_seen:
        raise InputFileError(f"{path}: no SAMPLE frames to compensate{what_it_is(path)}")
    if not binding.bound:
        raise InputFileError(f"{path}: no IDENTITY frame: frame rate unknown")
    if adapt is not None and adapt_state is not None and save_adapt_state:
        save_adaptation(cast(Compensator, binding.compensator), adapt_state)  # bound
