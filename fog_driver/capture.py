"""Capture files (raw ``.bin`` bytes) and their provenance sidecars (``.yaml``).

A capture is the byte stream exactly as read from the port: garbage, partial
frames and all.  The raw bytes are the source of truth; everything else is
derived from them.  The sidecar ``<name>.yaml`` beside ``<name>.bin`` records
where the bytes came from.  Sidecars are read with ``yaml.safe_load`` only.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
import yaml

from . import __version__
from .errors import InputFileError
from .protocol import (
    IDENTITY_FRAME_LEN,
    OVERHEAD_LEN,
    SAMPLE_FRAME_LEN,
    STATUS_BIT_NAMES,
    THERMOMETER_INVALID,
    DecodedCapture,
    decode_bytes,
)

from .stream import SampleStream

PROVENANCE_FORMAT = "fog_driver capture provenance"
PROVENANCE_SCHEMA_VERSION = 1
_READ_CHUNK = 8 << 20
#: Sidecars are small; a larger file is not a sidecar.
_MAX_SIDECAR_BYTES = 1 << 20


def sidecar_path(capture_path: str | Path) -> Path:
    """``run.bin`` -> ``run.yaml``."""
    return Path(capture_path).with_suffix(".yaml")


def utc_now_iso() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="milliseconds").replace("+00:00", "Z")


def read_capture_bytes(path: str | Path, progress: Callable[[int, int], None] | None = None) -> bytes:
    """The whole capture file, with a clear ``InputFileError`` for a missing, unreadable or empty one."""
    path = Path(path)
    try:
        size = path.stat().st_size
        if path.is_dir():
            raise InputFileError(f"{path}: is a directory, not a capture file")
        parts = []
        done = 0
        with path.open("rb") as f:
            while chunk := f.read(_READ_CHUNK):
                parts.append(chunk)
                done += len(chunk)
                if progress:
                    progress(done, size)
    except FileNotFoundError:
        raise InputFileError(f"{path}: no such capture file") from None
    except PermissionError:
        raise InputFileError(f"{path}: permission denied") from None
    except OSError as exc:
        raise InputFileError(f"{path}: cannot read: {exc.strerror or exc}") from None
    data = b"".join(parts)
    if not data:
        raise InputFileError(f"{path}: empty file, not a capture")
    return data


def read_provenance(capture_path: str | Path) -> dict[str, Any] | None:
    """The sidecar's mapping, or None when there is no sidecar.  A malformed sidecar is an ``InputFileError``."""
    path = sidecar_path(capture_path)
    try:
        if path.stat().st_size > _MAX_SIDECAR_BYTES:
            raise InputFileError(f"{path}: provenance sidecar larger than {_MAX_SIDECAR_BYTES} bytes")
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        return None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputFileError(f"{path}: cannot read provenance sidecar: {exc}") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        where = getattr(exc, "problem_mark", None)
        at = f" at line {where.line + 1}" if where is not None else ""
        raise InputFileError(f"{path}: provenance sidecar is not valid YAML{at}") from None
    if not isinstance(data, dict):
        raise InputFileError(f"{path}: provenance sidecar is not a YAML mapping")
    return data


def write_provenance(capture_path: str | Path, fields: dict[str, Any]) -> Path:
    """Write the sidecar atomically (temp file + rename): a crash never leaves half a sidecar."""
    path = sidecar_path(capture_path)
    doc = {
        "format": PROVENANCE_FORMAT,
        "schema_version": PROVENANCE_SCHEMA_VERSION,
        "capture": Path(capture_path).name,
        **fields,
    }
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(yaml.safe_dump(doc, sort_keys=False, allow_unicode=False), encoding="utf-8")
    os.replace(tmp, path)
    return path


class CaptureWriter:
    """Appends raw bytes to a capture file, exactly as given, and tracks size and SHA-256."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        try:
            self._file: BinaryIO = self.path.open("wb")
        except OSError as exc:
            raise InputFileError(f"{self.path}: cannot create capture: {exc.strerror or exc}") from None
        self._sha256 = hashlib.sha256()
        self.bytes_written = 0

    def write(self, chunk: bytes) -> None:
        self._file.write(chunk)
        self._sha256.update(chunk)
        self.bytes_written += len(chunk)

    def flush(self) -> None:
        self._file.flush()

    def close(self) -> None:
        if not self._file.closed:
            self._file.flush()
            os.fsync(self._file.fileno())
            self._file.close()

    @property
    def sha256(self) -> str:
        return self._sha256.hexdigest()

    def __enter__(self) -> CaptureWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass
class CaptureSummary:
    """What a user needs to trust a capture (the ``inspect`` report)."""

    path: str
    bytes: int
    sha256: str
    sample_frames: int
    identity_frames: int
    unknown_frames: int
    crc_errors: int
    length_errors: int
    truncated_frames: int
    bytes_discarded: int
    resyncs: int
    seq_gaps: int
    missing_frames: int
    seq_repeats: int
    t_us_wraps: int
    thermometer_faults: int  #: SAMPLE frames with at least one -32768 reading
    serial: str | None = None
    firmware: str | None = None
    rate_hz: int | None = None
    scale_arcsec_per_count: float | None = None
    identity_changes: int = 0
    duration_s: float | None = None  #: device time from first to last sample
    measured_rate_hz: float | None = None
    tail_bytes_discarded: int = 0  #: bytes after the last valid frame (a cut-off recording)
    status_flags_seen: dict[str, int] = field(default_factory=dict)  #: flag name -> frames with it set
    temperature_range_c: dict[str, list[float]] = field(default_factory=dict)  #: sensor -> [min, max]
    provenance: dict[str, Any] | None = None

    @property
    def problems(self) -> list[str]:
        """Anything that makes the capture less than clean, one phrase each."""
        checks = [
            (self.crc_errors, "CRC errors"),
            (self.length_errors, "length errors"),
            (self.bytes_discarded, "bytes discarded"),
            (self.missing_frames, "missing frames"),
            (self.seq_repeats, "repeated frames"),
            (self.unknown_frames, "unknown-type frames"),
            (self.thermometer_faults, "frames with a thermometer fault"),
        ]
        found = [f"{n} {what}" for n, what in checks if n]
        if self.identity_frames == 0:
            found.append("no IDENTITY frame")
        return found

    def as_json_dict(self) -> dict[str, Any]:
        """JSON-ready: absent values are omitted, never null."""
        out: dict[str, Any] = {}
        for name in self.__dataclass_fields__:
            value = getattr(self, name)
            if value is None:
                continue
            out[name] = value
        out["problems"] = self.problems
        return out


def summarize(
    decoded: DecodedCapture,
    *,
    path: str = "",
    sha256: str = "",
    provenance: dict[str, Any] | None = None,
) -> CaptureSummary:
    """Summarize a decoded capture."""
    c = decoded.counters
    frames = decoded.samples
    stream = SampleStream()
    samples = stream.run(decoded)
    raw_temps = (frames.t_top_raw, frames.t_bottom_raw, frames.t_housing_raw)
    faulty = np.zeros(len(frames), dtype=bool)
    for raw in raw_temps:
        faulty |= raw == THERMOMETER_INVALID
    summary = CaptureSummary(
        path=path,
        bytes=c.bytes_in,
        sha256=sha256,
        sample_frames=c.sample_frames,
        identity_frames=c.identity_frames,
        unknown_frames=c.unknown_frames,
        crc_errors=c.crc_errors,
        length_errors=c.length_errors,
        truncated_frames=c.truncated_frames,
        bytes_discarded=c.bytes_discarded,
        resyncs=c.resyncs,
        seq_gaps=c.seq_gaps,
        missing_frames=c.missing_frames,
        seq_repeats=c.seq_repeats,
        t_us_wraps=c.t_us_wraps,
        thermometer_faults=int(np.count_nonzero(faulty)),
        identity_changes=stream.identity_changes,
        provenance=provenance,
    )
    identity = stream.identity
    if identity is not None:
        summary.serial = identity.serial
        summary.firmware = identity.firmware_version
        summary.rate_hz = identity.rate_hz
        summary.scale_arcsec_per_count = identity.scale_arcsec_per_count
    if len(samples) >= 2:
        summary.duration_s = float(samples.t_s[-1] - samples.t_s[0])
        if summary.duration_s > 0:
            # Frames the instrument sent (unwrapped seq span) per second of its own clock: gaps do not bias it.
            summary.measured_rate_hz = float(samples.seq[-1] - samples.seq[0]) / summary.duration_s
    elif len(samples) == 1:
        summary.duration_s = 0.0
    last_frame_end = _last_frame_end(decoded)
    summary.tail_bytes_discarded = c.bytes_in - last_frame_end if last_frame_end else 0
    for mask, name in STATUS_BIT_NAMES.items():
        _count_flag(summary.status_flags_seen, name, frames.status & mask)
    for bit in range(5, 16):
        _count_flag(summary.status_flags_seen, f"reserved_bit{bit}", frames.status & (1 << bit))
    for name, column in (("top", samples.t_top_c), ("bottom", samples.t_bottom_c), ("housing", samples.t_housing_c)):
        valid = column[~np.isnan(column)]
        if len(valid):
            summary.temperature_range_c[name] = [float(valid.min()), float(valid.max())]
    return summary


def _f32_text(value: float | None) -> str | None:
    """The shortest text that reads back as the same float32 (how the instrument stores the scale)."""
    return None if value is None else np.format_float_positional(np.float32(value), trim="-")


def _count_flag(seen: dict[str, int], name: str, bits: np.ndarray) -> None:
    n = int(np.count_nonzero(bits))
    if n:
        seen[name] = n


def _last_frame_end(decoded: DecodedCapture) -> int:
    ends = []
    if len(decoded.samples):
        ends.append(int(decoded.samples.offset[-1]) + SAMPLE_FRAME_LEN)
    for frame in decoded.identities[-1:]:
        ends.append(frame.offset + IDENTITY_FRAME_LEN)
    for frame in decoded.unknown[-1:]:
        ends.append(frame.offset + OVERHEAD_LEN + len(frame.payload))
    return max(ends, default=0)


def inspect_capture(path: str | Path, progress: Callable[[int, int], None] | None = None) -> CaptureSummary:
    """Read, decode and summarize a capture file; a file with no valid frame is an ``InputFileError``."""
    data = read_capture_bytes(path, progress)
    decoded = decode_bytes(data, final=True)
    c = decoded.counters
    if c.sample_frames + c.identity_frames + c.unknown_frames == 0:
        raise InputFileError(
            f"{path}: not a protocol v1 capture: no valid frame in {len(data)} bytes"
            + (" (too short to hold one)" if len(data) < SAMPLE_FRAME_LEN else "")
        )
    return summarize(
        decoded,
        path=str(path),
        sha256=hashlib.sha256(data).hexdigest(),
        provenance=read_provenance(path),
    )


def format_summary(s: CaptureSummary) -> str:
    """The human-readable ``inspect`` report."""

    def num(n: int) -> str:
        return f"{n:,}"

    def opt(value: object, fmt: str = "{}") -> str:
        return "unknown" if value is None else fmt.format(value)

    lines = [
        f"capture       {s.path} ({num(s.bytes)} bytes, sha256 {s.sha256[:16]}...)",
        f"instrument    serial {opt(s.serial)}, firmware {opt(s.firmware)}, "
        f"{opt(s.rate_hz, '{} Hz')} nominal, scale {opt(_f32_text(s.scale_arcsec_per_count), '{} arcsec/count')}"
        + (f" ({s.identity_changes - 1} identity changes)" if s.identity_changes > 1 else ""),
        f"duration      {opt(s.duration_s, '{:.3f} s')} of device time"
        + (f", measured {s.measured_rate_hz:.4f} Hz" if s.measured_rate_hz else ""),
        f"frames        {num(s.sample_frames)} sample, {num(s.identity_frames)} identity, "
        f"{num(s.unknown_frames)} unknown type",
        f"integrity     {num(s.crc_errors)} CRC errors, {num(s.length_errors)} length errors, "
        f"{num(s.bytes_discarded)} bytes discarded, {num(s.resyncs)} resyncs",
        f"sequence      {num(s.seq_gaps)} gaps, {num(s.missing_frames)} frames missing, "
        f"{num(s.seq_repeats)} repeats, {num(s.t_us_wraps)} t_us wraps",
        f"thermometers  {num(s.thermometer_faults)} frames with a fault; "
        + (
            ", ".join(f"{k} {lo:.2f}..{hi:.2f} degC" for k, (lo, hi) in s.temperature_range_c.items())
            or "no valid reading"
        ),
        "status flags  "
        + (", ".join(f"{name} in {num(n)} frames" for name, n in s.status_flags_seen.items()) or "none set"),
    ]
    if s.tail_bytes_discarded:
        lines.append(
            f"tail          capture ends inside a frame: last {num(s.tail_bytes_discarded)} bytes are not a whole frame"
        )
    if s.provenance:
        p = s.provenance
        described = [f"{k} {p[k]}" for k in ("source", "port", "baud", "start_utc", "profile", "seed") if k in p]
        lines.append("provenance    " + (", ".join(described) or "sidecar present"))
    else:
        lines.append("provenance    no sidecar")
    problems = s.problems
    lines.append("verdict       " + ("clean" if not problems else "; ".join(problems)))
    return "\n".join(lines)

