"""Frames -> samples: unwrapped sequence and device time, physical units, gap markers.

A ``Sample`` is one SAMPLE frame in the units the rest of the project uses:

* ``seq``: the 16-bit wire counter unwrapped to a non-decreasing integer,
  ``seq(n) = seq(n-1) + ((seq_wire(n) - seq_wire(n-1)) mod 2^16)``;
* ``t_s``: the 32-bit microsecond clock unwrapped the same way, in seconds;
* ``dtheta_arcsec = dtheta_counts * scale`` with the scale factor in force:
  the configured override if one is given, else the latest IDENTITY's, else
  (before the first IDENTITY) the configured default;
* temperatures in degC (``raw / 256``), NaN for the -32768 "no reading" value;
* ``missing_before``: SAMPLE frames the instrument sent that never arrived
  (``seq`` step - 1), the explicit gap marker; 0 on an unbroken stream.

``SampleStream.step(event)`` takes one decoder event; ``SampleStream.run(
decoded)`` takes a batch decode.  Both start from and update the same state,
so any split of a capture into pieces gives bit-identical samples.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ..errors import InputFileError
from ..protocol import (
    SEQ_MODULUS,
    T_US_MODULUS,
    THERMOMETER_COUNTS_PER_C,
    THERMOMETER_INVALID,
    DecodedCapture,
    Event,
    IdentityFrame,
    SampleArrays,
    SampleFrame,
    iter_decode_file,
)
from ..protocol.sequence import Unwrapper, missing_before

#: Scale factor used before any IDENTITY frame when the configuration gives none.
DEFAULT_SCALE_ARCSEC_PER_COUNT = 0.01
#: The largest scale factor an IDENTITY may carry: one count of a degree (real gyros: hundredths of an arcsec).
MAX_SCALE_ARCSEC_PER_COUNT = 3600.0


def identity_is_plausible(identity: IdentityFrame) -> bool:
    """An IDENTITY a driver can use: a rate of at least 1 Hz and a scale factor in (0, 1 degree] per count.

    A CRC-valid frame from a firmware bug or an unconfigured unit (rate 0, a NaN scale) would otherwise
    divide by zero or make every later angle NaN."""
    scale = identity.scale_arcsec_per_count
    return identity.rate_hz >= 1 and math.isfinite(scale) and 0.0 < scale <= MAX_SCALE_ARCSEC_PER_COUNT


_US_PER_S = 1e6


class Sample(NamedTuple):
    """One SAMPLE frame in physical units."""

    seq: int  #: unwrapped sequence number
    t_s: float  #: unwrapped device time, seconds on the instrument clock
    dtheta_arcsec: float  #: angle increment since the previous sample
    t_top_c: float  #: fiber ring top thermometer, NaN when invalid
    t_bottom_c: float  #: fiber ring bottom thermometer
    t_housing_c: float  #: housing thermometer
    status: int  #: wire status bits
    missing_before: int  #: frames lost just before this one (0: no gap)
    offset: int  #: byte offset of the frame in the raw stream

    @property
    def gap(self) -> bool:
        return self.missing_before > 0


@dataclass
class SampleBlock:
    """Many samples as columns (the batch form of ``Sample``)."""

    seq: np.ndarray  #: int64
    t_s: np.ndarray  #: float64
    dtheta_arcsec: np.ndarray  #: float64
    t_top_c: np.ndarray  #: float64, NaN when invalid
    t_bottom_c: np.ndarray
    t_housing_c: np.ndarray
    status: np.ndarray  #: uint16
    missing_before: np.ndarray  #: int64
    offset: np.ndarray  #: int64

    def __len__(self) -> int:
        return len(self.seq)

    def take(self, index: slice | np.ndarray) -> SampleBlock:
        """The samples at ``index`` (a slice, a mask or indices), as a block of their own."""
        return SampleBlock(*(getattr(self, name)[index] for name in self.__dataclass_fields__))

    def sample(self, i: int) -> Sample:
        return Sample(
            int(self.seq[i]),
            float(self.t_s[i]),
            float(self.dtheta_arcsec[i]),
            float(self.t_top_c[i]),
            float(self.t_bottom_c[i]),
            float(self.t_housing_c[i]),
            int(self.status[i]),
            int(self.missing_before[i]),
            int(self.offset[i]),
        )

    @classmethod
    def from_samples(cls, samples: list[Sample]) -> SampleBlock:
        columns = list(zip(*samples)) if samples else [()] * len(Sample._fields)
        dtypes = (np.int64, np.float64, np.float64, np.float64, np.float64, np.float64, np.uint16, np.int64, np.int64)
        return cls(*(np.array(col, dtype=dt) for col, dt in zip(columns, dtypes)))

    @classmethod
    def concatenate(cls, parts: list[SampleBlock]) -> SampleBlock:
        """One block of ``parts`` in order (an empty block for none)."""
        if not parts:
            return cls.from_samples([])
        return cls(*(np.concatenate([getattr(p, name) for p in parts]) for name in cls.__dataclass_fields__))


def _f32(value: float) -> float:
    return float(np.float32(value))


def temperature_c(raw: int) -> float:
    """degC from a 1/256 degC thermometer reading; NaN for the -32768 sentinel."""
    return float("nan") if raw == THERMOMETER_INVALID else raw / THERMOMETER_COUNTS_PER_C


def temperature_c_array(raw: np.ndarray) -> np.ndarray:
    """Vector form of ``temperature_c`` (bit-identical)."""
    out = raw.astype(np.float64) / THERMOMETER_COUNTS_PER_C
    out[raw == THERMOMETER_INVALID] = np.nan
    return out


class SampleStream:
    """Turns decoder events into ``Sample`` records, keeping the unwrap state.

    ``scale_override_arcsec_per_count``, when given, is used for every sample
    whatever the instrument says; otherwise ``default_scale_arcsec_per_count``
    applies until the first IDENTITY frame, whose scale then applies.  An IDENTITY
    that is not plausible (``identity_is_plausible``: rate 0, a scale that is not a
    finite positive number) is counted in ``identities_rejected`` and ignored: the
    identity in force stays.
    """

    def __init__(
        self,
        default_scale_arcsec_per_count: float = DEFAULT_SCALE_ARCSEC_PER_COUNT,
        scale_override_arcsec_per_count: float | None = None,
    ) -> None:
        # Scale factors are held at float32 precision, as the instrument stores and sends them: then
        # every increment (counts x scale) and every sum of increments is exact in float64, so block
        # sums do not depend on summation order (streaming and vectorized paths agree bit for bit).
        self.default_scale_arcsec_per_count = _f32(default_scale_arcsec_per_count)
        self.scale_override_arcsec_per_count = (
            None if scale_override_arcsec_per_count is None else _f32(scale_override_arcsec_per_count)
        )
        self.identity: IdentityFrame | None = None  #: the latest IDENTITY frame
        self.identity_changes = 0  #: IDENTITY frames that differed from the one before
        self.identities_rejected = 0  #: implausible IDENTITY frames, ignored
        self._seq = Unwrapper(SEQ_MODULUS)
        self._t_us = Unwrapper(T_US_MODULUS)

    @property
    def scale_arcsec_per_count(self) -> float:
        """The scale factor the next sample will be converted with."""
        if self.scale_override_arcsec_per_count is not None:
            return self.scale_override_arcsec_per_count
        if self.identity is not None:
            return self.identity.scale_arcsec_per_count
        return self.default_scale_arcsec_per_count

    def _observe_identity(self, identity: IdentityFrame) -> None:
        if not identity_is_plausible(identity):
            self.identities_rejected += 1
            return
        if self.identity is None or identity[1:] != self.identity[1:]:
            self.identity_changes += 1
        self.identity = identity

    def step(self, event: Event) -> Sample | None:
        """Consume one decoder event; return a ``Sample`` for a SAMPLE frame, else None."""
        if isinstance(event, SampleFrame):
            return self._step_sample(event)
        if isinstance(event, IdentityFrame):
            self._observe_identity(event)
        return None

    def _step_sample(self, frame: SampleFrame) -> Sample:
        seq, t_us = self._seq, self._t_us
        step = seq.step(frame.seq)
        t_us.step(frame.t_us)
        return Sample(
            seq.value,
            t_us.value / _US_PER_S,
            frame.dtheta_counts * self.scale_arcsec_per_count,
            temperature_c(frame.t_top_raw),
            temperature_c(frame.t_bottom_raw),
            temperature_c(frame.t_housing_raw),
            frame.status,
            step - 1 if step is not None and step > 1 else 0,
            frame.offset,
        )

    def step_all(self, events: list[Event]) -> list[Sample]:
        """``step`` over a list of events, keeping only the samples."""
        return [s for s in map(self.step, events) if s is not None]

    def run(self, decoded: DecodedCapture) -> SampleBlock:
        """Batch form of ``step`` over every frame of ``decoded``, in stream order."""
        return self.run_arrays(decoded.samples, decoded.identities)

    def run_arrays(self, frames: SampleArrays, identities: list[IdentityFrame]) -> SampleBlock:
        """``run`` from the columns of SAMPLE frames and the IDENTITY frames among them."""
        n = len(frames)
        sample_offsets = frames.offset
        # Scale in force at each sample: the latest IDENTITY before it, else the current one.
        scale = np.full(n, self.scale_arcsec_per_count, dtype=np.float64)
        # The state follows IDENTITY frames after the last sample too, as step() would.
        for identity in identities:
            self._observe_identity(identity)
        identities = [f for f in identities if identity_is_plausible(f)]
        if identities and self.scale_override_arcsec_per_count is None:
            identity_offsets = np.array([f.offset for f in identities], dtype=np.int64)
            identity_scales = np.array([f.scale_arcsec_per_count for f in identities], dtype=np.float64)
            latest = np.searchsorted(identity_offsets, sample_offsets) - 1
            has_identity = latest >= 0
            scale[has_identity] = identity_scales[latest[has_identity]]

        seq = self._seq.run(frames.seq)
        t_us = self._t_us.run(frames.t_us)
        return SampleBlock(
            seq=seq.value,
            t_s=t_us.value / _US_PER_S,
            dtheta_arcsec=frames.dtheta_counts.astype(np.float64) * scale,
            t_top_c=temperature_c_array(frames.t_top_raw),
            t_bottom_c=temperature_c_array(frames.t_bottom_raw),
            t_housing_c=temperature_c_array(frames.t_housing_raw),
            status=frames.status.astype(np.uint16, copy=True),
            missing_before=missing_before(seq.step),
            offset=sample_offsets.astype(np.int64, copy=True),
        )


def read_capture_samples(path) -> tuple[SampleBlock, float]:
    """A whole capture file's samples in memory and its frame period, s (from its IDENTITY frame): for
    tests and benchmarks that alter samples before compensating them.  ``InputFileError`` without one."""
    stream = SampleStream()
    parts = [stream.run(part) for part in iter_decode_file(path)]
    if stream.identity is None:
        raise InputFileError(f"{path}: no IDENTITY frame: frame rate unknown")
    return SampleBlock.concatenate([p for p in parts if len(p)]), 1.0 / stream.identity.rate_hz
