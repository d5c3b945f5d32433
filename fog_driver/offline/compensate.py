"""Files in, files out: a model applied to a capture file (``fog-driver compensate``, ``evaluate``).

``compensate_capture`` decodes a capture block by block and compensates it with the daemon's binding rules
(``compensation.binding.InstrumentCompensation``), so that a capture compensated offline gives what the
daemon published; ``rows`` aggregates its frames into the CSV rows.

A model fitted for another instrument serial than the capture's is refused (``ModelMismatchError``, exit 64)
unless ``force_model`` (``--force-model``, the daemon's ``force_model``): ``check_model`` says so before any
work, from the capture's first IDENTITY frame, and the binding checks every later one.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, NamedTuple, cast

from ..compensation.adapt import AdaptConfig
from ..compensation.binding import (
    InstrumentCompensation,
    ModelMismatchError,
    another_instruments_model,
    check_channels,
    split_at_identities,
)
from ..compensation.model import ModelFile
from ..compensation.offsets import PublishOffsets
from ..compensation.pipeline import CompensatedColumns, Compensator
from ..dwells import Dwell
from ..errors import InputFileError
from ..files.kinds import COMPENSATE_PROVENANCE_FORMAT
from ..files.yamlio import write_yaml
from ..modelfiles import adaptation_restorer, save_adaptation
from ..samples.captures import what_it_is
from ..samples.sources import CaptureReader, WireSettings, wire_settings_for
from ..samples.stream import SampleBlock, identity_is_plausible
from .replay import ControlEvent, split_at_events

#: What a refusal of another instrument's model says to do (``--force-model``: the daemon's ``force_model``).
FORCE_MODEL_HINT = "--force-model applies it anyway"
#: ``first_serial`` reads this much at a time: a capture's first IDENTITY comes within its first frames.
_FIRST_SERIAL_BLOCK_BYTES = 1 << 16


def first_serial(path: str | Path, wire: WireSettings) -> str | None:
    """The instrument serial of the capture's first plausible IDENTITY frame, read block by block until it comes
    (``wire``: how to read it, ``sources.wire_settings_for``); None when the capture has none."""
    reader = CaptureReader(path, wire)
    for part in reader.parts(block_bytes=_FIRST_SERIAL_BLOCK_BYTES):
        for identity in part.identities:
            if identity_is_plausible(identity):
                return identity.serial
    return None


class ModelCheck(NamedTuple):
    """A model checked against a capture before any work (``check_model``)."""

    capture_serial: str | None  #: the serial of the capture's first IDENTITY (None: it has none)
    warning: str | None  #: with ``force_model``, the line that says another instrument's model is applied


class CaptureFacts(NamedTuple):
    """What ``check_model`` reads of a capture, once for every model checked against it (``capture_facts``)."""

    wire: WireSettings
    serial: str | None  #: the serial of its first plausible IDENTITY (None: it has none)


def capture_facts(capture: str | Path, wire_format: str = "auto") -> CaptureFacts:
    wire = wire_settings_for(capture, wire_format)
    return CaptureFacts(wire, first_serial(capture, wire))


def check_model(
    model_file: ModelFile,
    capture: str | Path,
    *,
    model_name: str,
    force_model: bool,
    wire_format: str = "auto",
    facts: CaptureFacts | None = None,
) -> ModelCheck:
    """Whether ``model_file`` applies to ``capture``, before any work: fitted on the temperature channels its
    frames carry (else ``ModelMismatchError``, whatever ``force_model`` says), and for the instrument its first
    IDENTITY frame names (else ``ModelMismatchError`` naming both serials and ``--force-model``; with
    ``force_model``, the warning line naming both).  ``facts``: the capture's, when read already."""
    facts = facts or capture_facts(capture, wire_format)
    check_channels(model_file, facts.wire, model_name, str(capture))
    capture_serial = facts.serial
    if capture_serial is None or capture_serial == model_file.instrument_serial:
        return ModelCheck(capture_serial, None)
    if not force_model:
        raise another_instruments_model(
            model_name, model_file, f"{capture} is from instrument {capture_serial!r}", FORCE_MODEL_HINT
        )
    return ModelCheck(
        capture_serial,
        f"--force-model: applying {model_name}, fitted for instrument {model_file.instrument_serial!r}, to "
        f"{capture}, from instrument {capture_serial!r}",
    )


def compensate_capture(
    path: str | Path,
    model_file: ModelFile,
    *,
    force_model: bool = False,
    progress: Callable[[int], None] | None = None,
    model_name: str = "the model",
    adapt: AdaptConfig | None = None,
    reference_rate_dph: float | None = None,
    adapt_state: str | Path | None = None,
    scale_override_arcsec_per_count: float | None = None,
    save_adapt_state: bool = True,
    wire_format: str = "auto",
    on_block: Callable[[bytes], None] | None = None,
    table_dwells: list[Dwell] | None = None,
    on_done: Callable[[Compensator], None] | None = None,
    events: list[ControlEvent] | None = None,
) -> Iterator[tuple[float, CompensatedColumns]]:
    """Decode ``path`` block by block and yield (frame period s, compensated frames), bounded memory.

    The binding rules of ``InstrumentCompensation`` (the module docstring).  With ``adapt`` the weights adapt
    online against ``reference_rate_dph`` (None: frozen, but a restored state's adapted weights give the
    estimate, as in the daemon); ``adapt_state`` is restored first when it exists (as a new run: the bias is
    captured again) and, with ``save_adapt_state``, saved when the capture ends.
    ``scale_override_arcsec_per_count``: the daemon's setting of that name.  ``wire_format``: ``--format``
    (``sources.wire_settings_for``); a model fitted on other temperature channels is refused first, one fitted
    for another instrument serial unless ``force_model``.  ``on_block(bytes)``: every block of the file as read
    (a SHA-256 of the capture).  ``table_dwells``: adapt from the table's angles (``compensation.table``),
    these dwells in device time from the capture's first sample.  ``on_done(compensator)`` once the capture
    is through (its table law's outcomes, say).  ``events``: a daemon capture's control events to replay where
    they took effect (``replay.control_events``); with any, the compensator is built as the daemon builds it
    (adapting ready, the table law recording).
    """
    events = list(events or [])
    replaying = bool(events)  # the daemon's ?ZERO and ?BIAS offsets on the angles (none: the angles as they are)
    offsets = PublishOffsets()
    if events and table_dwells is None:  # as the daemon builds it: the table law records from the start
        table_dwells = []
    if events and adapt is None:
        adapt = AdaptConfig()
    wire = wire_settings_for(path, wire_format)
    check_channels(model_file, wire, model_name, str(path))
    reader = CaptureReader(path, wire, scale_override_arcsec_per_count)
    binding = InstrumentCompensation(
        model_file,
        force=force_model,
        model_name=model_name,
        hint=FORCE_MODEL_HINT,
        adapt=adapt,
        reference_rate_dph=reference_rate_dph,
        restore_adaptation=adaptation_restorer(adapt_state),
        table_dwells=table_dwells,
    )
    pending: list[SampleBlock] = []  # samples before the first IDENTITY
    samples_seen = 0
    for part in reader.parts(on_block=on_block):
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
            for earlier in [*pending, block]:
                for piece, event in split_at_events(earlier, events):
                    if len(piece):
                        cols = binding.run(piece)
                        yield frame_period_s, offsets.published(cols, frame_period_s) if replaying else cols
                    if event is not None:
                        try:
                            if event.kind == "model":  # the daemon checked it against the port's frames
                                check_channels(event.fields["model_file"], wire, "the model reloaded", str(path))
                            event.apply(binding, offsets)
                        except (TypeError, ValueError, KeyError, ModelMismatchError) as exc:  # a sidecar edited by hand
                            raise InputFileError(
                                f"{path}: its sidecar's {event.kind} event at byte {event.at_byte:,} cannot be "
                                f"replayed: {exc}"
                            ) from None
            pending = []
    if not samples_seen:
        raise InputFileError(f"{path}: no SAMPLE frames to compensate{what_it_is(path)}")
    if not binding.bound:
        raise InputFileError(f"{path}: no IDENTITY frame: frame rate unknown")
    if adapt is not None and adapt_state is not None and save_adapt_state:
        save_adaptation(cast(Compensator, binding.compensator), adapt_state)  # bound
    if on_done is not None:
        on_done(cast(Compensator, binding.compensator))  # bound


#: The schema version of the provenance sidecar ``compensate`` writes beside its CSV.
CSV_PROVENANCE_SCHEMA_VERSION = 1


def csv_sidecar_path(csv_path: str | Path) -> Path:
    """Where ``compensate`` describes its CSV: ``check.csv`` -> ``check.csv.yaml`` (the CSV itself stays plain)."""
    csv_path = Path(csv_path)
    return csv_path.with_name(csv_path.name + ".yaml")


def write_csv_provenance(csv_path: str | Path, fields: dict[str, Any]) -> Path:
    """Write the CSV's provenance sidecar (``csv_sidecar_path``) with ``yaml.safe_dump``, atomically: its
    ``format`` tag, schema version and the CSV's name, then ``fields`` (docs: reference/file-formats)."""
    doc = {
        "format": COMPENSATE_PROVENANCE_FORMAT,
        "schema_version": CSV_PROVENANCE_SCHEMA_VERSION,
        "csv": Path(csv_path).name,
        **fields,
    }
    return write_yaml(csv_sidecar_path(csv_path), doc, "the CSV's provenance sidecar")
