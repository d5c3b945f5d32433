"""Capture files (raw ``.bin`` bytes) and their provenance sidecars (``.bin.yaml``).

A capture is the byte stream exactly as read from the port: garbage, partial
frames and all.  The raw bytes are the source of truth; everything else is
derived from them.  The sidecar ``<name>.bin.yaml`` beside ``<name>.bin`` records
where the bytes came from: a name no other command gives its output (a model
``<name>.yaml`` and a capture ``<name>.bin`` can share a stem).  Captures made
before that name was used have their sidecar at ``<name>.yaml``; it is still read,
but only when its ``format`` tag says it is a capture's provenance sidecar.
Sidecars are read with ``yaml.safe_load`` only.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from ..errors import InputFileError, OutputFileError
from ..files.bounded import open_regular
from ..files.kinds import PROVENANCE_FORMAT
from ..files.yamlio import read_yaml, write_yaml
from ..formats.registry import sniff_file
from ..protocol import (
    FILE_BLOCK_BYTES,
    IDENTITY_FRAME_LEN,
    OVERHEAD_LEN,
    SAMPLE_FRAME_LEN,
    STATUS_BIT_NAMES,
    THERMOMETER_INVALID,
    DecodedCapture,
    DecoderCounters,
    iter_decode_file,
)
from .stream import SampleStream

PROVENANCE_SCHEMA_VERSION = 1


def sidecar_path(capture_path: str | Path) -> Path:
    """Where a capture's sidecar is written: ``run.bin`` -> ``run.bin.yaml``."""
    capture_path = Path(capture_path)
    return capture_path.with_name(capture_path.name + ".yaml")


def legacy_sidecar_path(capture_path: str | Path) -> Path:
    """Where captures made before ``sidecar_path`` had their sidecar: ``run.bin`` -> ``run.yaml``."""
    return Path(capture_path).with_suffix(".yaml")


#: The directory beside a daemon's captures where it keeps a copy of every model it compensated with.
KEPT_MODELS_DIR = "models"


def kept_model_path(capture_path: str | Path, sha256: str) -> Path:
    """Where the daemon keeps the model of SHA-256 ``sha256`` it used for the capture ``capture_path``:
    ``<capture's directory>/models/<sha256>.yaml`` (named by its content: each model once)."""
    return Path(capture_path).parent / KEPT_MODELS_DIR / f"{sha256}.yaml"


def is_provenance(doc: Any) -> bool:
    """Whether a loaded YAML document is a capture's provenance sidecar (by its ``format`` tag)."""
    return isinstance(doc, dict) and doc.get("format") == PROVENANCE_FORMAT


def find_sidecar(capture_path: str | Path) -> Path | None:
    """The capture's sidecar: ``run.bin.yaml``, else an old ``run.yaml`` that really is a capture's provenance
    sidecar (its ``format`` tag; a model or any other file of that name is not), else None."""
    path = sidecar_path(capture_path)
    if path.exists():
        return path
    legacy = legacy_sidecar_path(capture_path)
    if legacy == path or not legacy.is_file():
        return None
    try:
        doc = read_yaml(legacy, "provenance sidecar")
    except InputFileError:
        return None  # not readable YAML: not a sidecar this project wrote
    return legacy if is_provenance(doc) else None


def _capture_size(path: Path) -> int:
    """The size of a capture file, with a clear ``InputFileError`` for a missing, unreadable or empty one, or one
    that is not a regular file (``bounded.open_regular``: a directory, a FIFO, a device such as ``/dev/zero``)."""
    with open_regular(path, "capture file") as f:
        size = os.fstat(f.fileno()).st_size
    if size == 0:
        raise InputFileError(f"{path}: empty file, not a capture")
    return size


def read_provenance(capture_path: str | Path) -> dict[str, Any] | None:
    """The sidecar's mapping (``find_sidecar``), or None when there is no sidecar.  A malformed sidecar is an
    ``InputFileError``."""
    path = find_sidecar(capture_path)
    if path is None:
        return None
    data = read_yaml(path, "provenance sidecar", missing_ok=True)
    if data is None:
        return None
    if not isinstance(data, dict):
        raise InputFileError(f"{path}: provenance sidecar is not a YAML mapping")
    return data


def write_provenance(capture_path: str | Path, fields: dict[str, Any], sidecar: str | Path | None = None) -> Path:
    """Write the sidecar atomically (temp file + rename): a crash never leaves half a sidecar.  At
    ``sidecar_path`` unless ``sidecar`` names another (an old-named sidecar rewritten where it is)."""
    path = sidecar_path(capture_path) if sidecar is None else Path(sidecar)
    doc = {
        "format": PROVENANCE_FORMAT,
        "schema_version": PROVENANCE_SCHEMA_VERSION,
        "capture": Path(capture_path).name,
        **fields,
    }
    return write_yaml(path, doc, "provenance sidecar")


class CaptureWriter:
    """Appends raw bytes to a capture file, exactly as given, and tracks size and SHA-256.

    Unbuffered: each ``write`` hands its bytes to the OS at once (a process killed a moment later loses
    nothing it wrote), and ``bytes_written`` and ``sha256`` count only what the OS took: after a failed write
    (a full disk takes part of a chunk) they describe exactly the file on disk.  ``close`` fsyncs.
    """

    def __init__(self, path: str | Path, overwrite: bool = False) -> None:
        self.path = Path(path)
        try:
            # "x" refuses to replace an existing capture: a lost chamber run cannot be re-recorded.
            self._file: BinaryIO = self.path.open("wb" if overwrite else "xb", buffering=0)
        except FileExistsError:
            raise OutputFileError(f"{self.path}: exists; refusing to overwrite a capture (use --force)") from None
        except OSError as exc:
            raise OutputFileError(f"{self.path}: cannot create capture: {exc.strerror or exc}") from None
        self._sha256 = hashlib.sha256()
        self.bytes_written = 0

    def write(self, chunk: bytes) -> None:
        """Write all of ``chunk`` (``OutputFileError`` when the OS refuses the rest: counted up to there)."""
        view = memoryview(chunk)
        while view:
            try:
                n = self._file.write(view)
            except OSError as exc:
                raise OutputFileError(f"{self.path}: cannot write capture: {exc.strerror or exc}") from None
            if not n:  # a raw file returns None only when non-blocking; 0 would loop forever
                raise OutputFileError(f"{self.path}: cannot write capture: the file takes no more bytes")
            self._sha256.update(view[:n])
            self.bytes_written += n
            view = view[n:]

    def flush(self) -> None:
        """Nothing to do: every ``write`` reached the OS (kept for the writers that call it)."""

    def fsync(self) -> None:
        """Ask the OS to put what was written on the disk (a power cut then loses nothing before it)."""
        try:
            os.fsync(self._file.fileno())
        except OSError as exc:
            raise OutputFileError(f"{self.path}: cannot write capture: {exc.strerror or exc}") from None

    def close(self) -> None:
        """Fsync and close; idempotent.  A failed fsync is an ``OutputFileError``."""
        if self._file.closed:
            return
        try:
            self.fsync()
        finally:
            with contextlib.suppress(OSError):  # the fsync above already reported it
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
    identities_rejected: int = 0  #: IDENTITY frames with a rate of 0 or a scale that is not finite and positive
    duration_s: float | None = None  #: device time from first to last sample
    measured_rate_hz: float | None = None
    tail_bytes_discarded: int = 0  #: bytes after the last valid frame (a cut-off recording)
    status_flags_seen: dict[str, int] = field(default_factory=dict)  #: flag name -> frames with it set
    temperature_range_c: dict[str, list[float]] = field(default_factory=dict)  #: sensor -> [min, max]
    provenance: dict[str, Any] | None = None

    @property
    def problems(self) -> list[str]:
        """Anything that makes the capture less than clean, one phrase each."""
        discarded = ("byte discarded", "bytes discarded")
        if self.tail_bytes_discarded:
            tail = f" ({self.tail_bytes_discarded} in a cut-off last frame)"
            discarded = (discarded[0] + tail, discarded[1] + tail)
        checks = [
            (self.crc_errors, ("CRC error", "CRC errors")),
            (self.length_errors, ("length error", "length errors")),
            (self.bytes_discarded, discarded),
            (self.missing_frames, ("missing frame", "missing frames")),
            (self.seq_repeats, ("repeated frame", "repeated frames")),
            (self.unknown_frames, ("unknown-type frame", "unknown-type frames")),
            (self.thermometer_faults, ("frame with a thermometer fault", "frames with a thermometer fault")),
            (self.identity_changes - 1 if self.identity_changes > 1 else 0, ("identity change", "identity changes")),
            (
                self.identities_rejected,
                ("implausible IDENTITY frame (ignored)", "implausible IDENTITY frames (ignored)"),
            ),
        ]
        found = [f"{n:,} {one if n == 1 else many}" for n, (one, many) in checks if n]
        if self.identity_frames == 0:
            found.append("no IDENTITY frame")
        status = (self.provenance or {}).get("status")
        if status is not None and status != "complete":  # interrupted, failed: ..., or still recording
            found.append(f"sidecar status {status}")
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


_SENSORS = ("top", "bottom", "housing")


class CaptureSummarizer:
    """Builds a ``CaptureSummary`` from decoded parts of a capture, one part at a time (bounded memory)."""

    def __init__(self) -> None:
        self._stream = SampleStream()
        self._thermometer_faults = 0
        self._flag_counts = np.zeros(16, dtype=np.int64)
        self._t_min = np.full(3, np.inf)
        self._t_max = np.full(3, -np.inf)
        self._first: tuple[int, float] | None = None  # (seq, t_s) of the first sample
        self._last: tuple[int, float] | None = None
        self._last_frame_end = 0

    def add(self, part: DecodedCapture) -> None:
        frames = part.samples
        samples = self._stream.run(part)
        faulty = np.zeros(len(frames), dtype=bool)
        for raw in (frames.t_top_raw, frames.t_bottom_raw, frames.t_housing_raw):
            faulty |= raw == THERMOMETER_INVALID
        self._thermometer_faults += int(np.count_nonzero(faulty))
        for bit in range(16):
            self._flag_counts[bit] += np.count_nonzero(frames.status & (1 << bit))
        for k, column in enumerate((samples.t_top_c, samples.t_bottom_c, samples.t_housing_c)):
            valid = column[~np.isnan(column)]
            if len(valid):
                self._t_min[k] = min(self._t_min[k], valid.min())
                self._t_max[k] = max(self._t_max[k], valid.max())
        if len(samples):
            if self._first is None:
                self._first = (int(samples.seq[0]), float(samples.t_s[0]))
            self._last = (int(samples.seq[-1]), float(samples.t_s[-1]))
        self._last_frame_end = max(self._last_frame_end, _last_frame_end(part))

    def finish(
        self, counters: DecoderCounters, *, path: str = "", sha256: str = "", provenance: dict[str, Any] | None = None
    ) -> CaptureSummary:
        c = counters
        # Every decoder counter the summary reports under the same name.
        shared = {k: v for k, v in c.as_dict().items() if k in CaptureSummary.__dataclass_fields__}
        summary = CaptureSummary(
            path=path,
            bytes=c.bytes_in,
            sha256=sha256,
            **shared,
            thermometer_faults=self._thermometer_faults,
            identity_changes=self._stream.identity_changes,
            identities_rejected=self._stream.identities_rejected,
            provenance=provenance,
        )
        identity = self._stream.identity
        if identity is not None:
            summary.serial = identity.serial
            summary.firmware = identity.firmware_version
            summary.rate_hz = identity.rate_hz
            summary.scale_arcsec_per_count = identity.scale_arcsec_per_count
        if self._first is not None and self._last is not None:
            summary.duration_s = self._last[1] - self._first[1]
            if summary.duration_s > 0:
                # Frames the instrument sent (unwrapped seq span) per second of its own clock: gaps do not bias it.
                summary.measured_rate_hz = (self._last[0] - self._first[0]) / summary.duration_s
        summary.tail_bytes_discarded = c.bytes_in - self._last_frame_end if self._last_frame_end else 0
        for bit in range(16):
            if self._flag_counts[bit]:
                name = STATUS_BIT_NAMES.get(1 << bit, f"reserved_bit{bit}")
                summary.status_flags_seen[name] = int(self._flag_counts[bit])
        for k, name in enumerate(_SENSORS):
            if np.isfinite(self._t_min[k]):
                summary.temperature_range_c[name] = [float(self._t_min[k]), float(self._t_max[k])]
        return summary


def summarize(
    decoded: DecodedCapture,
    *,
    path: str = "",
    sha256: str = "",
    provenance: dict[str, Any] | None = None,
) -> CaptureSummary:
    """Summarize a capture decoded in one piece."""
    summarizer = CaptureSummarizer()
    summarizer.add(decoded)
    return summarizer.finish(decoded.counters, path=path, sha256=sha256, provenance=provenance)


def _f32_text(value: float | None) -> str | None:
    """The shortest text that reads back as the same float32 (how the instrument stores the scale)."""
    return None if value is None else np.format_float_positional(np.float32(value), trim="-")


def _last_frame_end(decoded: DecodedCapture) -> int:
    ends = []
    if len(decoded.samples):
        ends.append(int(decoded.samples.offset[-1]) + SAMPLE_FRAME_LEN)
    for frame in decoded.identities[-1:]:
        ends.append(frame.offset + IDENTITY_FRAME_LEN)
    for frame in decoded.unknown[-1:]:
        ends.append(frame.offset + OVERHEAD_LEN + len(frame.payload))
    return max(ends, default=0)


def what_it_is(path: str | Path) -> str:
    """For a file that holds no protocol v1 frame: what the format sniffer sees in it, as the end of a one-line
    error ("; it looks like kvh-a (...): read it with --format kvh-a or auto"; "" when it cannot be read)."""
    try:
        seen = sniff_file(str(path))
    except OSError:
        return ""
    if seen.name is None:
        return f"; the format sniffer sees {seen.describe()}"
    return f"; it looks like {seen.describe()}: read it with --format {seen.name} or auto"


def inspect_capture(
    path: str | Path,
    progress: Callable[[int, int], None] | None = None,
    block_bytes: int = FILE_BLOCK_BYTES,
) -> CaptureSummary:
    """Read, decode and summarize a capture file block by block (memory bounded by the block size).

    A missing, unreadable or empty file, or one with no valid frame, is an ``InputFileError``.
    """
    path = Path(path)
    size = _capture_size(path)
    sha256 = hashlib.sha256()
    done = 0

    def on_block(block: bytes) -> None:
        nonlocal done
        sha256.update(block)
        done += len(block)
        if progress:
            progress(done, size)

    summarizer = CaptureSummarizer()
    counters = DecoderCounters()
    try:
        for part in iter_decode_file(path, block_bytes, on_block=on_block):
            summarizer.add(part)
            counters = part.counters
    except OSError as exc:
        raise InputFileError(f"{path}: cannot read: {exc.strerror or exc}") from None
    if counters.sample_frames + counters.identity_frames + counters.unknown_frames == 0:
        raise InputFileError(
            f"{path}: not a protocol v1 capture: no valid frame in {counters.bytes_in} bytes"
            + (" (too short to hold one)" if counters.bytes_in < SAMPLE_FRAME_LEN else what_it_is(path))
        )
    return summarizer.finish(counters, path=str(path), sha256=sha256.hexdigest(), provenance=read_provenance(path))


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
        described = [
            f"{k} {p[k]}" for k in ("source", "status", "port", "baud", "start_utc", "profile", "seed") if k in p
        ]
        lines.append("provenance    " + (", ".join(described) or "sidecar present"))
    else:
        lines.append("provenance    no sidecar")
    problems = s.problems
    lines.append("verdict       " + ("clean" if not problems else "; ".join(problems)))
    return "\n".join(lines)
