"""A model applied to an instrument's stream: the binding the daemon and ``fog-driver compensate`` share.

The same rules live and offline, so that a capture compensated offline gives what the daemon published:

- The compensator is built at the first plausible IDENTITY frame (``stream.identity_is_plausible``): its
  rate gives the frame period.  Samples before it are compensated with it once it arrives.
- A model fitted for another instrument serial is refused (``ModelMismatchError``) unless ``force``.
- A later IDENTITY with another serial or another rate (a unit swapped on the port, a rate changed) rebuilds
  the compensator: the model starts at rest as at switch-on, the angles carry on, and the first frame after
  it is flagged ``gap``.  The serial is checked again.  A change of scale factor alone needs nothing: the
  sample stream applies it.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import cast

import numpy as np

from ..dwells import Dwell
from ..errors import UsageError
from ..flags import FLAG_GAP
from ..protocol import IdentityFrame
from ..samples.stream import SampleBlock, identity_is_plausible
from .adapt import AdaptConfig
from .model import ModelFile
from .pipeline import CompensatedColumns, CompensatedSample, Compensator


class ModelMismatchError(UsageError):
    """The model was fitted for another instrument than the one on the port."""


def check_channels(model_file: ModelFile, wire, model_name: str = "the model", what: str = "the capture") -> None:
    """``ModelMismatchError`` when the frames of ``wire`` (``sources.WireSettings``) do not carry the temperature
    channels ``model_file`` was fitted on: its inputs do not exist there, so no ``force`` can apply it."""
    channels = tuple(model_file.temperature_channels)
    if tuple(wire.temperature_channels) != channels:
        raise ModelMismatchError(
            f"{model_name} was fitted on the temperature channels {', '.join(channels)}; {what}'s {wire.format} "
            f"frames carry {', '.join(wire.temperature_channels)}: it cannot be applied (fit a model on this "
            f"instrument's captures)"
        )


def same_model(a: ModelFile, b: ModelFile) -> bool:
    """The same drift model (kind, normalization, every matrix, and the candidate structures beside it): its
    memory, its candidates' memory and its adaptation (the table law's shape is the candidates') carry over.
    A model that differs in its candidates alone is another model: it starts at rest, as at switch-on."""
    return (
        a.kind == b.kind
        and a.normalizer.to_dict() == b.normalizer.to_dict()
        and a.model.to_dict() == b.model.to_dict()
        and a.sigma_spec.candidates == b.sigma_spec.candidates
    )


def _new_instrument(current: IdentityFrame | None, identity: IdentityFrame) -> bool:
    """Whether ``identity`` names another instrument than ``current`` for the pipeline: a serial or a rate of
    its own (a scale factor alone is the stream's business), or the first one."""
    return current is None or (identity.serial, identity.rate_hz) != (current.serial, current.rate_hz)


def another_instruments_model(model_name: str, model_file: ModelFile, instrument: str, hint: str) -> ModelMismatchError:
    """The one refusal of a model fitted for another serial, live (``instrument``: "the instrument is 'S'") and
    offline ("C is from instrument 'S'"), ``hint`` saying how to apply it anyway."""
    return ModelMismatchError(
        f"{model_name} was fitted for instrument {model_file.instrument_serial!r}, {instrument} ({hint})"
    )


class InstrumentCompensation:
    """A model file bound to the instrument on a stream (see the module docstring).

    ``bind(identity)`` at every plausible IDENTITY, ``step``/``run`` for samples once ``bound``.
    ``restore_adaptation``, when given, is called with the first compensator (with ``adapt``) to restore its
    adaptation state (``modelfiles.adaptation_restorer``: from a file, when it exists, as a new run).
    """

    def __init__(
        self,
        model_file: ModelFile,
        *,
        force: bool = False,
        model_name: str = "the model",
        hint: str = "use --force to apply it anyway",
        adapt: AdaptConfig | None = None,
        reference_rate_dph: float | None = None,
        restore_adaptation: Callable[[Compensator], None] | None = None,
        table_dwells: list[Dwell] | None = None,
    ) -> None:
        self.model_file = model_file
        self.table_dwells = table_dwells  #: adapting from table angles: the table log (first compensator only)
        self.force = force
        self.model_name = model_name
        self.hint = hint
        self.adapt = adapt
        self.reference_rate_dph = reference_rate_dph
        self.restore_adaptation = restore_adaptation
        self.compensator: Compensator | None = None
        self.identity: IdentityFrame | None = None  #: the identity the compensator was built for
        self.rebuilds = 0  #: compensators rebuilt for a new serial or rate
        self._flag_next = False

    @property
    def bound(self) -> bool:
        return self.compensator is not None

    def changes_binding(self, identity: IdentityFrame) -> bool:
        """Whether ``identity`` (plausible) builds or rebuilds the compensator."""
        return _new_instrument(self.identity, identity)

    def check(
        self,
        identity: IdentityFrame,
        model_file: ModelFile | None = None,
        *,
        force: bool | None = None,
        model_name: str | None = None,
    ) -> None:
        """``ModelMismatchError`` when ``model_file`` (default: this one, named ``model_name``) was fitted for
        another serial, unless ``force`` (default: this binding's)."""
        model_file = model_file or self.model_file
        force = self.force if force is None else force
        if identity.serial != model_file.instrument_serial and not force:
            raise another_instruments_model(
                model_name or self.model_name, model_file, f"the instrument is {identity.serial!r}", self.hint
            )

    def bind(self, identity: IdentityFrame) -> str | None:
        """Take a plausible IDENTITY: ``"bound"`` (the first), ``"rebuilt"`` (a new serial or rate), else None."""
        if not self.changes_binding(identity):
            self.identity = identity
            return None
        self.check(identity)
        old = self.compensator
        reference = old.reference_rate_dph if old is not None else self.reference_rate_dph
        table = self.table_dwells is not None
        new = Compensator(
            self.model_file, 1.0 / identity.rate_hz, adapt=self.adapt, reference_rate_dph=reference, table=table
        )
        self.identity = identity
        if old is None:
            if self.table_dwells:
                new.add_dwells(list(self.table_dwells))
            if self.adapt is not None and self.restore_adaptation is not None:
                self.restore_adaptation(new)
            self.compensator = new
            return "bound"
        new.angle_raw_arcsec, new.angle_comp_arcsec = old.angle_raw_arcsec, old.angle_comp_arcsec
        self.compensator = new
        self.rebuilds += 1
        self._flag_next = True
        return "rebuilt"

    def compensator_for(self, model_file: ModelFile, frame_period_s: float) -> Compensator:
        """A compensator for ``model_file`` built as this binding builds them (its adapt config; recording the
        table's angles when it adapts from them)."""
        return Compensator(model_file, frame_period_s, adapt=self.adapt, table=self.table_dwells is not None)

    def swap_model(self, model_file: ModelFile, new: Compensator | None = None) -> None:
        """Compensate with ``model_file`` from the next sample on (a model reload; the daemon's and its replay's):
        ``new`` (``compensator_for``, built beforehand; rebuilt when None or for another frame period) carries
        on from the current compensator: the angles, the reference rate, the open block and the feature
        smoothers; with the same model (``same_model``) also its memory (reservoir) and its adaptation; a
        different model starts at rest at the current inputs (as at switch-on) and adapts afresh.  Unbound: the
        model the first IDENTITY binds."""
        old = self.compensator
        if old is None:
            self.model_file = model_file
            return
        if new is None or new.frame_period_s != old.frame_period_s:
            new = self.compensator_for(model_file, old.frame_period_s)
        new.reference_rate_dph = old.reference_rate_dph
        new.angle_raw_arcsec, new.angle_comp_arcsec = old.angle_raw_arcsec, old.angle_comp_arcsec
        new.continue_from(old, same_model=same_model(old.model_file, model_file))
        self.model_file = model_file
        self.compensator = new

    def step(self, sample) -> CompensatedSample:
        c = cast(Compensator, self.compensator).step(sample)  # bound
        if self._flag_next:
            self._flag_next = False
            c = c._replace(flags=c.flags | FLAG_GAP)
        return c

    def run(self, samples: SampleBlock) -> CompensatedColumns:
        out = cast(Compensator, self.compensator).run(samples)  # bound
        if self._flag_next and len(out):
            self._flag_next = False
            out.flags[0] |= FLAG_GAP
        return out


def split_at_identities(
    samples: SampleBlock, identities: list[IdentityFrame], binding: InstrumentCompensation
) -> list[tuple[IdentityFrame | None, SampleBlock]]:
    """``samples`` cut where an IDENTITY among ``identities`` would change ``binding`` (plausible ones, in
    stream order): ``(identity to bind first or None, the samples after it)``; the first part has None."""
    parts: list[tuple[IdentityFrame | None, SampleBlock]] = []
    start, pending = 0, None
    current = binding.identity
    for identity in identities:
        if not identity_is_plausible(identity):
            continue
        if _new_instrument(current, identity):
            cut = int(np.searchsorted(samples.offset, identity.offset))
            parts.append((pending, samples.take(slice(start, cut))))
            start, pending, current = cut, identity, identity
    parts.append((pending, samples.take(slice(start, len(samples)))))
    return parts
