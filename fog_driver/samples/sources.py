"""Bytes of any registered frame format -> the instrument's ``Sample`` stream, live or from a capture file.

Protocol v1 frames say everything themselves (IDENTITY: rate, scale, serial).  Another format's frames do
not, so its ``WireSettings`` say it: the format, the instrument's angle axis (``axis``, default z), the
output rate (``rate_hz``) and, for KVH, the units the device was set to (``=ROTFMT``, ``=ROTUNITS``,
``=TEMPUNITS``).  The daemon takes them from its config (``format:``, ``axis:``, ``device:``) and records
them in each capture's sidecar (``wire_format``, ``wire_settings``), so offline tools never guess; a
capture without a sidecar is sniffed (``formats.registry.sniff``) and another format's defaults apply.

``ImuSampleStream`` reduces a format's ``ImuSample`` (three axes, named temperature channels, common flags)
to the one-axis ``Sample`` the compensation consumes:

* ``dtheta_arcsec``: the chosen axis' increment (a rate output: ``rate_dph / rate_hz``, the frame's own
  period, as a protocol v1 frame's increment is; frames lost in a gap are counted in ``missing_before``,
  their angle is not invented), held on a grid of ``2^-24`` arcsec (6e-8 arcsec, far below any gyro's
  resolution) so that sums of increments are exact in float64 and do not depend on their order: the
  per-sample and the batch paths and any split of a capture agree bit for bit, as they do for v1's integer
  counts times a float32 scale;
* the format's temperature channels (``FrameFormat.temperature_channels``) in the sample's three
  temperature places in order (``t_top_c``, ``t_bottom_c``, ``t_housing_c`` hold a KVH's one ``sensor``
  reading and two NaN, or STDBIN's ``fog``, ``accelerometer``, ``board``), held on a ``2^-16`` degC grid
  (exact sums again); a channel a frame does not carry (KVH Format C multiplexes its temperature into every
  fourth frame) keeps its last reading, a channel it reports invalid is NaN;
* time: device time where the format has it (STDBIN's validity time, in whole microseconds); KVH normal
  mode has none, so ``t_s = seq / rate_hz`` from the unwrapped sequence counter (a gap of a whole multiple
  of the counter's 128 frames cannot be seen: the format's limit);
* an increment that is not a number or beyond ``MAX_RATE_DPH`` (a float word that passed its checksum as
  NaN or garbage) is taken as 0 and flagged, and counted in ``increments_rejected``: the angle, a sum of
  increments, is never poisoned;
* the common flags as protocol v1 status bits (``sensor_invalid`` -> loop unlocked, ``startup``,
  ``over_range``, ``temperature_invalid`` -> thermometer fault), the raw status kept nowhere else;
* an ``IdentityFrame`` made up before the first sample (``serial`` from the settings, firmware 0, the
  settings' rate, scale 1), so every consumer binds the model as it does for protocol v1.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from ..errors import InputFileError
from ..files.bounded import open_regular
from ..flags import SAMPLE_OVER_RANGE, SAMPLE_SENSOR_INVALID, SAMPLE_STARTUP, SAMPLE_TEMPERATURE_INVALID
from ..formats.common import AXES, FormatCounters, ImuSample
from ..formats.kvh import _ARCSEC_PER_UNIT, _TEMP_SCALE, BIT_FRAME_LEN, GYRO_VALID, SAMPLE_FORMATS, decode_kvh_batch
from ..formats.registry import FORMATS, SNIFF_BYTES, sniff
from ..protocol import (
    STATUS_LOOP_UNLOCKED,
    STATUS_OVER_RANGE,
    STATUS_STARTUP,
    STATUS_THERMOMETER_FAULT,
    IdentityFrame,
    iter_decode_file,
)
from ..protocol.batch import FILE_BLOCK_BYTES, iter_file_blocks
from .captures import find_sidecar, read_provenance, sidecar_path
from .stream import Sample, SampleBlock, SampleStream

PROTOCOL_V1 = "fog-v1"
#: Increments are held on this grid (arcsec) and temperatures on ``TEMP_GRID_C`` (degC): exact sums.
DTHETA_GRID_ARCSEC = 2.0**-24
TEMP_GRID_C = 2.0**-16
_FLAG_STATUS = {
    SAMPLE_SENSOR_INVALID: STATUS_LOOP_UNLOCKED,
    SAMPLE_STARTUP: STATUS_STARTUP,
    SAMPLE_OVER_RANGE: STATUS_OVER_RANGE,
    SAMPLE_TEMPERATURE_INVALID: STATUS_THERMOMETER_FAULT,
}
#: Keys a sidecar's ``wire_settings`` may hold that describe the simulation, not the device: ignored here.
_DESCRIPTIVE_KEYS = ("temperature_channel", "temperature_channels", "version")
_KVH_CHOICES = {"rot_format": ("delta", "rate"), "rot_units": ("deg", "rad"), "temp_units": ("c", "c_100")}
MAX_RATE_HZ = 100_000
#: A chosen-axis rate beyond this (10,000 deg/s, in deg/h) is no gyro's: a float word a device sent as NaN,
#: infinity or garbage that passed its checksum.  Its increment is taken as 0 (the angle is never poisoned)
#: and the sample flagged as protocol v1's loop-unlocked bit.
MAX_RATE_DPH = 3.6e7


@dataclass(frozen=True)
class WireSettings:
    """What the frames of a stream are and how the device that sent them was set.

    ``format``: a ``formats.registry.FORMATS`` name.  ``axis``: the instrument's angle axis among the
    format's three (protocol v1 has one).  ``rate_hz``: the device's output rate (needed by every format but
    protocol v1, whose IDENTITY says it).  ``rot_format``, ``rot_units``, ``temp_units``: KVH's ``=ROTFMT``,
    ``=ROTUNITS``, ``=TEMPUNITS``.  ``serial``: the instrument's serial number where the format sends none
    (a model file records the serial it was fitted on).
    """

    format: str = PROTOCOL_V1
    axis: str = "z"
    rate_hz: int | None = None
    rot_format: str = "delta"
    rot_units: str = "rad"
    temp_units: str = "c"
    serial: str = ""

    def __post_init__(self) -> None:
        if not isinstance(self.format, str) or self.format not in FORMATS:
            raise ValueError(f"format: unknown frame format {self.format!r} (known: {', '.join(FORMATS)})")
        if self.axis not in AXES:
            raise ValueError(f"axis: must be one of {', '.join(AXES)}, not {self.axis!r}")
        if self.rate_hz is not None and (
            isinstance(self.rate_hz, bool) or not isinstance(self.rate_hz, int) or not 1 <= self.rate_hz <= MAX_RATE_HZ
        ):
            raise ValueError(f"rate_hz: must be an integer 1..{MAX_RATE_HZ}, not {self.rate_hz!r}")
        if self.format != PROTOCOL_V1 and self.rate_hz is None:
            raise ValueError(f"rate_hz: {self.format} frames do not say the device's output rate: give it")
        for key, choices in _KVH_CHOICES.items():
            if getattr(self, key) not in choices:
                raise ValueError(f"{key}: must be one of {', '.join(choices)}, not {getattr(self, key)!r}")
        if not isinstance(self.serial, str) or len(self.serial) > 64 or not self.serial.isprintable():
            raise ValueError("serial: at most 64 printable characters")

    @classmethod
    def from_sidecar(cls, wire_format: str | None, settings: Any, where: str = "") -> WireSettings:
        """From a sidecar's ``wire_format`` and ``wire_settings`` (None: protocol v1); ``ValueError`` naming
        the key when they are not usable."""
        if wire_format is None:
            return cls()
        if settings is None:
            settings = {}
        if not isinstance(settings, dict):
            raise ValueError(f"{where}wire_settings: expected a mapping")
        known = {f.name for f in fields(cls)} - {"format"}
        values = {}
        for key, value in settings.items():
            if key in _DESCRIPTIVE_KEYS:
                continue
            if key not in known:
                raise ValueError(f"{where}wire_settings: unknown key {key!r} (known: {', '.join(sorted(known))})")
            values[key] = value
        if isinstance(values.get("rate_hz"), float) and float(values["rate_hz"]).is_integer():
            values["rate_hz"] = int(values["rate_hz"])
        try:
            return cls(format=str(wire_format), **values)
        except ValueError as exc:
            raise ValueError(f"{where}{exc}") from None

    def sidecar_fields(self) -> dict[str, Any]:
        """What a capture's sidecar records (nothing for protocol v1, whose frames say it all)."""
        if self.format == PROTOCOL_V1:
            return {}
        settings: dict[str, Any] = {"rate_hz": self.rate_hz, "axis": self.axis}
        if self.format.startswith("kvh-"):
            settings.update(rot_format=self.rot_format, rot_units=self.rot_units, temp_units=self.temp_units)
        if self.serial:
            settings["serial"] = self.serial
        return {"wire_format": self.format, "wire_settings": settings}

    @property
    def temperature_channels(self) -> tuple[str, ...]:
        return FORMATS[self.format].temperature_channels

    def make_decoder(self) -> Any:
        """The format's streaming decoder, set as the device was."""
        return FORMATS[self.format].decoder(
            {
                "rot_format": self.rot_format,
                "rot_units": self.rot_units,
                "temp_units": self.temp_units,
                "rate_hz": self.rate_hz,
            }
        )


def _grid(value: float, step: float) -> float:
    """``value`` on the grid of ``step`` (round half to even); NaN and infinities as they are."""
    return round(value / step) * step if math.isfinite(value) else value


class AxesSample(Sample):
    """A ``Sample`` that also carries its frame's mean rate about each of the three axes (``axes_rate_dph``,
    deg/h, raw: x, y, z), for a daemon that publishes all three (``publish_axes``)."""

    axes_rate_dph: tuple[float, float, float]


class ImuSampleStream:
    """``ImuSample`` events -> ``Sample`` records of the chosen axis (the module docstring), explicit state.

    ``step(event)`` returns a ``Sample`` for an ``ImuSample`` and None for anything else (a built-in-test
    reply, an answer telegram); ``identity`` is the made-up IDENTITY (set by ``step`` at the first sample).
    """

    identities_rejected = 0  #: (protocol v1's counter; another format has no IDENTITY to reject)
    identity_changes = 0

    def __init__(self, wire: WireSettings, keep_axes: bool = False) -> None:
        if wire.format == PROTOCOL_V1:
            raise ValueError("protocol v1 frames go through stream.SampleStream")
        self.wire = wire
        self.keep_axes = keep_axes  #: give ``AxesSample`` (the three axes' rates) instead of ``Sample``
        self.channels = wire.temperature_channels
        self.axis_index = AXES.index(wire.axis)
        self.rate_hz = int(wire.rate_hz)
        self.identity: IdentityFrame | None = None
        self.increments_rejected = 0  #: samples whose increment was not a number or beyond MAX_RATE_DPH
        self._last_seq: int | None = None
        self._temps = [math.nan] * 3

    def make_identity(self, offset: int) -> IdentityFrame:
        return IdentityFrame(offset, self.wire.serial, 0, self.rate_hz, 1.0)

    def step(self, event: Any) -> Sample | None:
        if not isinstance(event, ImuSample):
            return None
        if self.identity is None:
            self.identity = self.make_identity(event.offset)
        a = self.axis_index
        dtheta = event.rate_dph[a] / self.rate_hz if event.from_rate else event.dtheta_arcsec[a]
        sensor_bad = 0
        if not abs(dtheta) * self.rate_hz <= MAX_RATE_DPH:  # NaN, infinite, or no gyro's: never integrated
            dtheta, sensor_bad = 0.0, STATUS_LOOP_UNLOCKED
            self.increments_rejected += 1
        seq = event.seq if event.seq is not None else (0 if self._last_seq is None else self._last_seq + 1)
        missing = 0 if self._last_seq is None else max(0, seq - self._last_seq - 1)
        self._last_seq = seq
        t_us = seq * 1_000_000 // self.rate_hz if event.t_s is None or event.host_time else round(event.t_s * 1e6)
        temps = self._temps
        event_temps = event.temps_c
        for k, name in enumerate(self.channels):
            value = event_temps.get(name)
            if value is not None:
                temps[k] = _grid(float(value), TEMP_GRID_C)
        status = sensor_bad
        if event.flags:
            for flag in event.flags:
                status |= _FLAG_STATUS.get(flag, 0)
        fields = (
            seq,
            t_us / 1e6,
            _grid(float(dtheta), DTHETA_GRID_ARCSEC),
            temps[0],
            temps[1],
            temps[2],
            status,
            missing,
            event.offset,
        )
        if not self.keep_axes:
            return Sample(*fields)
        sample = AxesSample(*fields)
        sample.axes_rate_dph = tuple(float(r) for r in event.rate_dph)
        return sample


class SampleSource:
    """A live stream's bytes -> ``Sample`` and ``IdentityFrame`` items, for any format (the daemon's front end).

    ``feed(chunk)`` returns, in stream order, the IDENTITY frames (protocol v1's, or another format's made-up
    one before its first sample) and the samples.  ``counters`` are the decoder's (``bytes_in``,
    ``sample_frames``, ``crc_errors``, ``bytes_discarded``, ``seq_gaps``, ``missing_frames`` in every format).
    """

    def __init__(self, wire: WireSettings, v1_stream: SampleStream | None = None, keep_axes: bool = False) -> None:
        self.wire = wire
        #: set once when the first ``SNIFF_BYTES`` held no frame of this format: what the sniffer sees instead
        #: (a port configured for the wrong format; the daemon logs it and shows it in STATUS)
        self.format_problem: str | None = None
        self._head: bytearray | None = bytearray()
        self.decoder = wire.make_decoder()
        self.stream: SampleStream | ImuSampleStream = (
            (v1_stream or SampleStream()) if wire.format == PROTOCOL_V1 else ImuSampleStream(wire, keep_axes)
        )

    @property
    def counters(self) -> Any:
        return self.decoder.counters

    @property
    def identity(self) -> IdentityFrame | None:
        return self.stream.identity

    @property
    def identities_rejected(self) -> int:
        return self.stream.identities_rejected

    @property
    def increments_rejected(self) -> int:
        return getattr(self.stream, "increments_rejected", 0)

    @property
    def temperature_channels(self) -> tuple[str, ...]:
        return self.wire.temperature_channels

    def feed(self, chunk: bytes) -> list[Sample | IdentityFrame]:
        items = self._items(self.decoder.feed(chunk))
        if self._head is not None:
            self._check_head(chunk)
        return items

    def _check_head(self, chunk: bytes) -> None:
        if self.counters.sample_frames:  # frames of the format: nothing to say
            self._head = None
            return
        self._head += chunk[: SNIFF_BYTES - len(self._head)]
        if len(self._head) >= SNIFF_BYTES:
            seen = sniff(self._head)
            self.format_problem = (
                f"no {self.wire.format} sample frame in the first {SNIFF_BYTES:,} bytes; the "
                f"sniffer sees {seen.describe()}"
            )
            self._head = None

    def close(self) -> list[Sample | IdentityFrame]:
        return self._items(self.decoder.close())

    def _items(self, events: list) -> list[Sample | IdentityFrame]:
        out: list[Sample | IdentityFrame] = []
        stream = self.stream
        if isinstance(stream, SampleStream):
            for event in events:
                sample = stream.step(event)
                if sample is not None:
                    out.append(sample)
                elif isinstance(event, IdentityFrame):
                    out.append(event)
            return out
        for event in events:
            first = stream.identity is None
            sample = stream.step(event)
            if sample is None:
                continue
            if first:
                out.append(stream.identity)
            out.append(sample)
        return out


class AutoSampleSource:
    """``SampleSource`` for ``format: auto``: the bytes are held until ``formats.registry.sniff`` names their
    format (``MIN_FRAMES`` checksum-valid frames of one format), then fed to that format's source, built by
    ``make_wire(name)``; ``wire`` is None until then.  Held bytes beyond ``SNIFF_BYTES`` with no verdict are
    dropped oldest first (``bytes_unsniffed``; the raw capture keeps them all)."""

    def __init__(
        self, make_wire: Callable[[str], WireSettings], v1_stream: SampleStream | None = None, keep_axes: bool = False
    ) -> None:
        self._keep_axes = keep_axes
        self._make_wire = make_wire
        self._v1_stream = v1_stream
        self._held = bytearray()
        self._source: SampleSource | None = None
        self._counters = FormatCounters()
        self.bytes_unsniffed = 0

    @property
    def wire(self) -> WireSettings | None:
        return None if self._source is None else self._source.wire

    @property
    def format_problem(self) -> str | None:
        if self._source is not None:
            return self._source.format_problem
        if self.bytes_unsniffed:
            return f"no known format in {self.bytes_unsniffed + len(self._held):,} bytes (format: auto)"
        return None

    @property
    def counters(self) -> Any:
        return self._counters if self._source is None else self._source.counters

    @property
    def identity(self) -> IdentityFrame | None:
        return None if self._source is None else self._source.identity

    @property
    def identities_rejected(self) -> int:
        return 0 if self._source is None else self._source.identities_rejected

    @property
    def increments_rejected(self) -> int:
        return 0 if self._source is None else self._source.increments_rejected

    @property
    def temperature_channels(self) -> tuple[str, ...]:
        return FORMATS[PROTOCOL_V1].temperature_channels if self._source is None else self._source.temperature_channels

    def feed(self, chunk: bytes) -> list[Sample | IdentityFrame]:
        if self._source is not None:
            return self._source.feed(chunk)
        self._held += chunk
        self._counters.bytes_in += len(chunk)
        seen = sniff(self._held)
        if seen.name is None or seen.frames[seen.name] < 2:
            excess = len(self._held) - SNIFF_BYTES
            if excess > 0:
                del self._held[:excess]
                self.bytes_unsniffed += excess
            return []
        self._source = SampleSource(self._make_wire(seen.name), self._v1_stream, self._keep_axes)
        held, self._held = bytes(self._held), bytearray()
        return self._source.feed(held)


def make_source(config: Any) -> SampleSource | AutoSampleSource:
    """The daemon's front end for a ``config.DriverConfig``: its format's source, or a sniffing one (auto)."""
    v1_stream = config.sample_stream()
    if config.format == "auto":
        return AutoSampleSource(config.wire_settings, v1_stream, config.publish_axes)
    return SampleSource(config.wire_settings(), v1_stream, config.publish_axes)


class SamplePart(NamedTuple):
    """One block of a capture file, decoded: its samples, the IDENTITY frames among them, bytes read so far."""

    samples: SampleBlock
    identities: list[IdentityFrame]
    bytes_in: int


class CaptureReader:
    """A capture file's samples block by block (bounded memory), in whatever format it is.

    ``wire``: how to read it (``wire_settings_for`` works it out from ``--format``, the sidecar and the
    bytes).  ``parts()`` yields ``SamplePart``; ``identity`` is the IDENTITY in force (None before one).
    """

    def __init__(
        self, path: str | Path, wire: WireSettings | None = None, scale_override_arcsec_per_count: float | None = None
    ) -> None:
        self.path = Path(path)
        self.wire = wire or WireSettings()
        if self.wire.format == PROTOCOL_V1:
            self.stream: SampleStream | ImuSampleStream = SampleStream(
                scale_override_arcsec_per_count=scale_override_arcsec_per_count
            )
        else:
            self.stream = ImuSampleStream(self.wire)
        self.counters: Any = None
        #: byte ranges read during a device setup, not decoded (``setup_byte_ranges``)
        self.skip = setup_byte_ranges(self.path) if self.wire.format != PROTOCOL_V1 else []

    @property
    def identity(self) -> IdentityFrame | None:
        return self.stream.identity

    def parts(
        self, on_block: Callable[[bytes], None] | None = None, block_bytes: int = FILE_BLOCK_BYTES
    ) -> Iterator[SamplePart]:
        if self.wire.format == PROTOCOL_V1:
            for part in iter_decode_file(self.path, block_bytes, on_block=on_block):
                self.counters = part.counters
                yield SamplePart(self.stream.run(part), part.identities, part.counters.bytes_in)
            return
        if self.wire.format.startswith("kvh-"):  # fixed-length frames: the numpy batch decoder
            yield from _kvh_file_parts(self, on_block, block_bytes)
            return
        source = SampleSource(self.wire)
        source.stream = self.stream
        self.counters = source.counters
        for block, final in _without(iter_file_blocks(self.path, block_bytes, on_block), self.skip):
            items = source.feed(block) + (source.close() if final else [])
            samples = [s for s in items if isinstance(s, Sample)]
            identities = [s for s in items if isinstance(s, IdentityFrame)]
            yield SamplePart(SampleBlock.from_samples(samples), identities, source.counters.bytes_in)


def setup_byte_ranges(path: str | Path) -> list[tuple[int, int]]:
    """The ``(start, end)`` byte ranges of a capture that a daemon or ``record`` read during a device setup
    (the sidecar's ``device_setup`` events: ``at_byte``, ``bytes_not_decoded``): not decoded live, so not
    offline either (frames the device sent under its old settings, and its replies)."""
    events = (read_provenance(path) or {}).get("events") or []
    ranges = []
    for event in events if isinstance(events, list) else []:
        if isinstance(event, dict) and event.get("event") == "device_setup":
            start, n = event.get("at_byte"), event.get("bytes_not_decoded")
            if isinstance(start, int) and isinstance(n, int) and start >= 0 and n > 0:
                ranges.append((start, start + n))
    return sorted(ranges)


def _without(blocks: Iterator[tuple[bytes, bool]], ranges: list[tuple[int, int]]) -> Iterator[tuple[bytes, bool]]:
    """``blocks`` (``iter_file_blocks``) with the bytes of ``ranges`` (file offsets) left out."""
    at = 0
    for block, final in blocks:
        if ranges:
            kept = []
            start = 0
            for a, b in ranges:
                lo, hi = max(a - at, 0), min(b - at, len(block))
                if lo < hi:
                    kept.append(block[start:lo])
                    start = max(start, hi)
            kept.append(block[start:])
            at += len(block)
            block = b"".join(kept)
        yield block, final


def _grid_array(values: np.ndarray, step: float) -> np.ndarray:
    """``_grid`` elementwise (the same round-half-even, the same products: the same bits)."""
    return np.round(values / step) * step


class _KvhBatchState:
    """What the batch path carries from one block of a file to the next (as ``ImuSampleStream`` does)."""

    def __init__(self) -> None:
        self.last_raw: int | None = None
        self.last_seq = 0
        self.temp = math.nan


def kvh_batch_samples(
    batch: Any, wire: WireSettings, state: _KvhBatchState, base: int, stream: ImuSampleStream
) -> SampleBlock:
    """``ImuSampleStream.step`` over a ``formats.kvh.decode_kvh_batch`` result, vectorized: the same samples,
    bit for bit (tested).  ``base``: the file offset of the buffer decoded; ``stream``'s identity and
    ``increments_rejected`` are kept up to date."""
    sample_kinds = np.array([b for b, _ in SAMPLE_FORMATS.values()], dtype=np.uint8)
    rows = np.flatnonzero(np.isin(batch.kind, sample_kinds))
    if not rows.size:
        return SampleBlock.from_samples([])
    raw = batch.seq_raw[rows] % 128
    previous = raw[0] if state.last_raw is None else state.last_raw
    steps = np.diff(np.r_[previous, raw]) % 128
    seq = (raw[0] if state.last_raw is None else state.last_seq) + np.cumsum(steps)
    missing = np.maximum(0, np.diff(np.r_[seq[0] if state.last_raw is None else state.last_seq, seq]) - 1)
    state.last_raw, state.last_seq = int(raw[-1]), int(seq[-1])
    rate_hz = stream.rate_hz
    k = _ARCSEC_PER_UNIT[wire.rot_units]
    g = batch.gyro[rows, AXES.index(wire.axis)] * k
    dtheta = g / rate_hz if wire.rot_format == "rate" else g
    with np.errstate(invalid="ignore", over="ignore"):
        bad = ~(np.abs(dtheta) * rate_hz <= MAX_RATE_DPH)
    dtheta = np.where(bad, 0.0, dtheta)
    stream.increments_rejected += int(np.count_nonzero(bad))
    status = np.where((batch.status[rows] & GYRO_VALID) != GYRO_VALID, STATUS_LOOP_UNLOCKED, 0) | np.where(
        bad, STATUS_LOOP_UNLOCKED, 0
    )
    kind = batch.kind[rows]
    c_byte = SAMPLE_FORMATS["c"][0]
    temp = np.where(kind == c_byte, np.nan, batch.temp_raw[rows] * _TEMP_SCALE[wire.temp_units])
    sent_c = (kind == c_byte) & (batch.seq_raw[rows] % 4 == 0)
    temp = np.where(sent_c, batch.mux[rows], temp)
    has = (kind != c_byte) | sent_c
    temp = np.where(has, _grid_array(temp, TEMP_GRID_C), np.nan)
    # a frame without the reading (Format C between its temperature slots) keeps the last one
    last = np.maximum.accumulate(np.where(has, np.arange(len(temp)), -1))
    held = np.where(last >= 0, temp[np.maximum(last, 0)], state.temp)
    state.temp = float(held[-1])
    offset = batch.offset[rows].astype(np.int64) + base
    if stream.identity is None:
        stream.identity = stream.make_identity(int(offset[0]))
    nan = np.full(len(rows), np.nan)
    return SampleBlock(
        seq=seq.astype(np.int64),
        t_s=(seq * 1_000_000 // rate_hz) / 1e6,
        dtheta_arcsec=_grid_array(dtheta, DTHETA_GRID_ARCSEC),
        t_top_c=held,
        t_bottom_c=nan,
        t_housing_c=nan.copy(),
        status=status.astype(np.uint16),
        missing_before=missing.astype(np.int64),
        offset=offset,
    )


#: The longest KVH frame: a file block's last bytes shorter than this wait for the next block.
_KVH_MAX_FRAME = 40


def _kvh_file_parts(
    reader: CaptureReader, on_block: Callable[[bytes], None] | None, block_bytes: int
) -> Iterator[SamplePart]:
    """``CaptureReader.parts`` of a KVH capture through the numpy batch decoder: each block is decoded with the
    bytes carried from the one before; frames starting within the last ``_KVH_MAX_FRAME`` bytes of a block
    that is not the last wait for the next (they may be cut off), so every frame is decided on whole bytes,
    as the streaming decoder decides it."""
    frame_len = {**dict(SAMPLE_FORMATS.values()), **BIT_FRAME_LEN}  # fourth header byte -> frame length
    wire = reader.wire
    config = dict(
        format=wire.format[-1],
        rot_format=wire.rot_format,
        rot_units=wire.rot_units,
        temp_units=wire.temp_units,
        rate_hz=wire.rate_hz,
    )
    state = _KvhBatchState()
    carry = b""
    base = 0  # file offset of carry[0]
    bytes_in = 0
    for block, final in _without(iter_file_blocks(reader.path, block_bytes, on_block), reader.skip):
        bytes_in += len(block)
        data = carry + block
        batch = decode_kvh_batch(data, **config)
        if not final:
            cutoff = max(0, len(data) - _KVH_MAX_FRAME)
            decided = batch.offset < cutoff
            for name in ("offset", "kind", "gyro", "status", "seq_raw", "temp_raw", "mux"):
                setattr(batch, name, getattr(batch, name)[decided])
            last_end = int(batch.offset[-1]) + frame_len[int(batch.kind[-1])] if decided.any() else 0
            keep_from = max(cutoff, last_end)
        else:
            keep_from = len(data)
        samples = kvh_batch_samples(batch, wire, state, base, reader.stream)
        carry, base = data[keep_from:], base + keep_from
        yield SamplePart(
            samples,
            [reader.stream.identity] if len(samples) and samples.offset[0] == (reader.stream.identity.offset) else [],
            bytes_in,
        )


def capture_format(path: str | Path, requested: str = "auto") -> tuple[str, dict]:
    """The frame format to read the capture ``path`` as, and its sidecar (``{}``: none).  ``requested`` is
    ``--format`` (``auto``: the sidecar's ``wire_format``, else what the sniffer finds in the first bytes, else
    protocol v1).  A requested format that the bytes contradict, or bytes without one frame of the format,
    are an ``InputFileError`` naming what the sniffer saw."""
    doc = read_provenance(path) or {}
    try:
        with open_regular(path, "capture file") as f:  # (a FIFO, a device, a directory: one line)
            head = f.read(SNIFF_BYTES)
    except OSError as exc:
        raise InputFileError(f"{path}: cannot read the capture: {exc.strerror or exc}") from None
    seen = sniff(head)
    recorded = doc.get("wire_format")
    if recorded is not None and recorded not in FORMATS:
        raise InputFileError(
            f"{find_sidecar(path)}: wire_format: unknown frame format {recorded!r} (known: {', '.join(FORMATS)})"
        )
    if requested == "auto":
        name = recorded or seen.name or PROTOCOL_V1
    else:
        name = requested
        if seen.name is not None and seen.name != name:
            raise InputFileError(f"{path}: --format {name}, but the sniffer saw {seen.describe()}")
    if seen.name is None and head and name != PROTOCOL_V1 and not seen.frames[name]:
        raise InputFileError(f"{path}: no {name} frame: the sniffer saw {seen.describe()}")
    return name, doc


def wire_settings_for(path: str | Path, requested: str = "auto") -> WireSettings:
    """How to read the capture ``path`` (``capture_format``), with the device settings its sidecar recorded; a
    sidecar whose wire settings cannot be used, or a capture of another format without one, is an
    ``InputFileError``."""
    name, doc = capture_format(path, requested)
    if doc.get("wire_format") == name:
        try:
            return WireSettings.from_sidecar(name, doc.get("wire_settings"), f"{find_sidecar(path)}: ")
        except ValueError as exc:
            raise InputFileError(str(exc)) from None
    if name == PROTOCOL_V1:
        return WireSettings()
    raise InputFileError(
        f"{path}: a {name} capture needs the device's settings (rate_hz ...) and has no sidecar "
        f"recording them: write {sidecar_path(path).name} with wire_format and "
        f"wire_settings (see the documentation: how-to/instruments)"
    )
