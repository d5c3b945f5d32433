"""The daemon's control events, replayed offline where they took effect (``compensate`` of a daemon capture).

The daemon notes in a capture's sidecar every control event that changes the compensator, in order with the
bytes: ``at_byte`` (the bytes of the file before it) and ``seq`` (the sequence number of the last sample it
had compensated).  A command runs between two chunks of bytes, so it took effect after that sample: the last
sample starting before ``at_byte`` whose 16-bit sequence number is ``seq``'s (a frame cut by the chunk's end
starts before ``at_byte`` too, and is not it).  Replayed here:

    table   ``?TABLE``: the dwell into the table law (``Compensator.table_dwell``), as the daemon took it
    adapt   ``?ADAPT``: the reference rate (``reference_dph``), or (null) frozen and the table law's end
    zero    ``?ZERO``: the published angles' zero (``offsets.PublishOffsets``), and the table law's chain breaks
    bias    a ``?BIAS`` capture's result (``bias_dph``): removed from the published rate and angle from the
            sample that completed the capture on (that sample included: the event took effect before it)

    model   a model reload: the model the daemon kept beside its captures (``captures.kept_model_path``, named
            by the SHA-256 the event carries; its bytes checked against it), swapped in as the daemon swaps it
            (``InstrumentCompensation.swap_model``)

A reload whose model's copy is not there (or not of its SHA-256), and a sidecar whose events were summarized
past its limit (``events_summary``), cannot be replayed exactly: ``unreplayed`` names them.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np

from ..compensation.binding import InstrumentCompensation
from ..compensation.model import ModelFile
from ..compensation.offsets import PublishOffsets
from ..compensation.pipeline import Compensator
from ..errors import FogDriverError
from ..files.bounded import read_regular
from ..files.yamlio import MAX_YAML_BYTES
from ..modelfiles import model_from_text
from ..samples.captures import kept_model_path
from ..samples.stream import SampleBlock

__all__ = ["REPLAYED", "ControlEvent", "control_events", "split_at_events", "unreplayed"]

#: The events ``compensate`` replays (``model``: when the daemon's copy of the model is beside the capture).
REPLAYED = ("table", "adapt", "zero", "bias", "model")
SEQ_MODULUS = 1 << 16
#: How far back from ``at_byte`` the sample of ``seq`` is looked for: a command took effect at the end of the
#: bytes read (a frame or two back), a bias capture at any sample of the chunk it completed in (one sequence
#: number is unique within 2^16 samples).
MAX_WALK_BACK = SEQ_MODULUS - 1


@dataclass(frozen=True)
class ControlEvent:
    """One replayable event of a sidecar: its kind, where it took effect and what it carried."""

    kind: str
    at_byte: int
    seq: int
    fields: dict[str, Any]

    def apply(self, binding: InstrumentCompensation, offsets: PublishOffsets) -> None:
        """Do to the binding's compensator what the daemon did (a dwell it took is taken here: a refusal is a
        bug); a reference rate is the binding's too, for a compensator rebuilt later (as ``Service.set_reference``)."""
        compensator = cast(Compensator, binding.compensator)
        if self.kind == "model":
            model_file = cast(ModelFile, self.fields["model_file"])
            if binding.identity is not None:
                binding.check(binding.identity, model_file, model_name=f"the model reloaded ({self.fields['sha256']})")
            binding.swap_model(model_file)
        elif self.kind == "zero":
            offsets.zero(compensator.angle_raw_arcsec, compensator.angle_comp_arcsec)
            compensator.break_table_chain()
        elif self.kind == "bias":
            offsets.bias_dph = float(self.fields["bias_dph"])
        elif self.kind == "table":
            compensator.table_dwell(  # the angles checked there as ?TABLE checks them (``dwells.table_angle_deg``)
                self.fields["angle_deg"], float(self.fields["dwell_s"]), self.fields.get("angle_start_deg")
            )
        elif self.kind == "adapt":
            reference = self.fields.get("reference_dph")
            if reference is None and compensator.table_engaged:
                compensator.stop_table()
            else:
                compensator.reference_rate_dph = None if reference is None else float(reference)
                binding.reference_rate_dph = compensator.reference_rate_dph


def _int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and v >= 0


def kept_model(capture_path: str | Path | None, sha256: Any) -> ModelFile | None:
    """The model of SHA-256 ``sha256`` the daemon kept beside ``capture_path`` (``captures.kept_model_path``),
    when it is there, of that SHA-256, and a model file; else None."""
    if capture_path is None or not isinstance(sha256, str) or len(sha256) != 64 or not sha256.isalnum():
        return None
    path = kept_model_path(capture_path, sha256)
    try:
        data = read_regular(path, "model file", MAX_YAML_BYTES, missing_ok=True)
        if data is None or hashlib.sha256(data).hexdigest() != sha256:
            return None
        return model_from_text(data.decode("utf-8"), path)
    except (UnicodeDecodeError, FogDriverError):
        return None


def control_events(provenance: dict[str, Any] | None, capture_path: str | Path | None = None) -> list[ControlEvent]:
    """The sidecar's replayable events, in order; a ``model`` event's ``fields["model_file"]`` is the model
    kept beside ``capture_path`` (those that cannot be replayed are left out: ``unreplayed`` says which)."""
    out = []
    for e in (provenance or {}).get("events") or []:
        if isinstance(e, dict) and e.get("event") in REPLAYED and _int(e.get("at_byte")) and _int(e.get("seq")):
            fields = {k: v for k, v in e.items() if k not in ("event", "at_byte", "seq", "utc")}
            if e["event"] == "model":
                fields["model_file"] = kept_model(capture_path, e.get("sha256"))  # read and checked once
                if fields["model_file"] is None:
                    continue
            out.append(ControlEvent(str(e["event"]), int(e["at_byte"]), int(e["seq"]), fields))
    return out


def unreplayed(provenance: dict[str, Any] | None, capture_path: str | Path | None = None) -> list[str]:
    """What a replay of this sidecar's events misses, one phrase each ([]: it gives what the daemon published)."""
    provenance = provenance or {}
    events = [e for e in provenance.get("events") or [] if isinstance(e, dict)]
    out = []
    models = [e for e in events if e.get("event") == "model" and _int(e.get("seq"))]
    n = sum(not _int(e.get("at_byte")) or kept_model(capture_path, e.get("sha256")) is None for e in models)
    if n:
        out.append(
            f"{n} model reload{'s' if n > 1 else ''} whose model is not kept beside the capture (in "
            f"{kept_model_path(capture_path or '.', 'SHA256').parent}/, named by its SHA-256)"
        )
    n = sum(e.get("event") in REPLAYED and not _int(e.get("seq")) for e in events)
    if n:
        out.append(f"{n} control events without a sample position (a daemon before they were noted)")
    summary = provenance.get("events_summary") or {}
    if isinstance(summary, dict):
        for kind in REPLAYED:
            entry = summary.get(kind)
            if isinstance(entry, dict) and entry.get("count"):
                out.append(f"{entry['count']} {kind} events past the sidecar's limit (summarized, not replayable)")
    return out


def _cut_after(samples: SampleBlock, event: ControlEvent) -> int | None:
    """The index of the sample ``event`` took effect after, when it lies in ``samples`` and a later sample
    shows the cut is here (-1: before the first); None: not yet known (every sample starts before it)."""
    k = int(np.searchsorted(samples.offset, event.at_byte))  # samples before it: [0, k)
    target = event.seq % SEQ_MODULUS
    before = 1 if event.kind == "bias" else 0  # a bias took effect at its sample, the others after theirs
    lo = max(k - MAX_WALK_BACK, 0)
    found = np.flatnonzero(samples.seq[lo:k] % SEQ_MODULUS == target)
    if len(found):  # its sample (a sequence number is unique within 2^16 samples)
        return lo + int(found[-1]) - before
    return None if k >= len(samples) else k - 1 - before  # its sample may be in the next part; else the bytes


def split_at_events(
    samples: SampleBlock, events: list[ControlEvent]
) -> Iterator[tuple[SampleBlock, ControlEvent | None]]:
    """``samples`` cut where the pending ``events`` (consumed from the front) took effect: each part with the
    event to apply after it (None for the last part, whose events, if any, lie in later samples)."""
    start = 0
    while events:
        j = _cut_after(samples, events[0])
        if j is None:
            break
        yield samples.take(slice(start, max(j + 1, start))), events.pop(0)
        start = max(j + 1, start)
    yield samples.take(slice(start, len(samples))), None
