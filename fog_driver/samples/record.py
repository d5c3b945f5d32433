"""Record a port's raw bytes to a capture file, with its provenance sidecar.

The bytes go to disk exactly as read; a ``FrameDecoder`` watches the same
bytes only to report progress and to note the instrument's identity in the
sidecar, and to end the recording on a frame boundary: when the duration
passes or a signal stops it, the port is read on, a byte at a time, while the
decoder holds part of a frame (at most ``READ_ON_S``; a port that gives no more
in that time, or is lost, leaves the capture ending as the port did).  No
byte the port delivered is ever left out.  The sidecar is written when recording starts (``status:
recording``) and rewritten when it ends, so even a killed recorder leaves a
described capture behind.
"""

from __future__ import annotations

import contextlib
import itertools
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .. import __version__
from ..errors import DeviceError, OutputFileError
from ..files.outputs import check_outputs
from ..files.stamps import utc_now_iso
from ..protocol import DecoderCounters, IdentityFrame
from ..transport import DEFAULT_SILENCE_S, PortError, PortEvent, PortReader
from ..transport.setup import make_on_open
from .captures import CaptureWriter, sidecar_path, write_provenance
from .sources import WireSettings

_FLUSH_EVERY_S = 1.0
#: After a stop, how long the rest of a frame may take to come (a frame's bytes come back to back: well
#: under a millisecond at the instrument's baud rates; a network port may hold them longer).
READ_ON_S = 1.0


@dataclass
class RecordProgress:
    elapsed_s: float
    bytes_written: int
    counters: DecoderCounters
    port_state: str


@dataclass
class RecordResult:
    path: Path
    sidecar: Path
    bytes_written: int
    sha256: str
    elapsed_s: float
    counters: DecoderCounters
    identity: IdentityFrame | None


def record(
    url: str,
    out_path: str | Path,
    *,
    baudrate: int = 460800,
    duration_s: float | None = None,
    reconnect: bool = True,
    stop: threading.Event | None = None,
    on_progress: Callable[[RecordProgress], None] | None = None,
    on_state: Callable[[PortEvent], None] | None = None,
    notes: str | None = None,
    progress_every_s: float = 0.5,
    overwrite: bool = False,
    wait: bool = False,
    wire: Any = None,
    setup: Any = None,
    silence_s: float | None = DEFAULT_SILENCE_S,
    on_event: Callable[[Any], None] | None = None,
    extra_fields: dict[str, Any] | None = None,
) -> RecordResult:
    """Copy bytes from ``url`` into ``out_path`` until ``duration_s`` (host time) passes, ``stop`` is set,
    or (with ``reconnect=False``) the port is lost; a duration or a stop ends on a frame boundary (the module
    docstring).

    A port that cannot be opened the first time raises ``DeviceError`` at once (reconnecting is for a port
    that worked), unless ``wait``: then it is retried until it appears.  A recording that ends before
    the first byte (stopped, or the duration passed) is a ``DeviceError`` and leaves no capture behind;
    once bytes flow, whatever was read is kept, whatever ends the recording.
    An existing capture or sidecar, or a missing directory, is an ``OutputFileError`` (before the port is
    opened) unless ``overwrite``; so is a failed write (disk full), after the sidecar has recorded how
    far the capture got.  ``wire``: what the port sends (``sources.WireSettings``, default protocol v1): its
    decoder counts the frames, and the sidecar records it (``wire_format``, ``wire_settings``).  ``setup``: a
    ``transport.setup.DeviceSetup`` run on every open (its replies are in the capture, as every byte read).
    ``silence_s``: a network port (``socket://``, ``rfc2217://``) that gives no byte for this long after it has
    given some is taken as lost (``PortReader``), and reopened unless ``reconnect=False``; None: never.
    ``on_event``: called, in the recording's thread, with every event the decoder gives (frames, gaps), as it
    decodes the bytes written (``calibrate`` watches the gyro's clock and temperatures by it).
    ``extra_fields``: more sidecar fields, from the start (``calibrate``: the chamber log, the program).
    """
    wire = wire or WireSettings()
    stop = stop or threading.Event()
    out_path = Path(out_path)
    recording = _Recording(wire, on_state, on_event)
    base_fields = {**_base_fields(url, baudrate, wire, notes), **(extra_fields or {})}
    # say so now, not after waiting for the port
    check_outputs([out_path, sidecar_path(out_path)], force=overwrite, captures=[out_path])
    reader = PortReader(
        url,
        baudrate=baudrate,
        reconnect=reconnect,
        on_state=recording.state_changed,
        first_open="wait" if wait else "fail",
        on_open=None if setup is None else make_on_open(setup, on_result=recording.setup_done),
        silence_s=silence_s,
    )
    chunks = reader.chunks(stop, read_on=recording.bytes_to_frame_boundary, read_on_s=READ_ON_S)
    # (a duration past threading.TIMEOUT_MAX, 292 years, never ends a recording: no timer, whose wait would overflow)
    timed = duration_s is not None and duration_s < threading.TIMEOUT_MAX
    timer = threading.Timer(duration_s, stop.set) if timed else None
    if timer:
        timer.daemon = True
        timer.start()
    started = time.monotonic()
    first = _first_chunk(url, reader, chunks, timer, started)
    status = "complete"
    sidecar = sidecar_path(out_path)
    with CaptureWriter(out_path, overwrite=overwrite) as writer:
        write_provenance(out_path, {**base_fields, "status": "recording"})
        try:
            _copy(itertools.chain((first,), chunks), writer, recording, started, on_progress, progress_every_s)
        except OutputFileError as exc:
            status = f"failed: {exc}"
            raise
        finally:
            if timer:
                timer.cancel()
            chunks.close()
            elapsed = time.monotonic() - started
            try:
                writer.close()
            except OutputFileError as exc:
                status = f"failed: {exc}"
            # the disk is full: the write error on its way out says so
            with contextlib.suppress(OSError, OutputFileError):
                write_provenance(out_path, recording.sidecar_fields(base_fields, status, elapsed, writer))
    if status != "complete":
        raise OutputFileError(status.removeprefix("failed: "))
    counters, identity = recording.decoder.counters, recording.identity
    return RecordResult(out_path, sidecar, writer.bytes_written, writer.sha256, elapsed, counters, identity)


def _base_fields(url: str, baudrate: int, wire: Any, notes: str | None) -> dict[str, Any]:
    """The sidecar's fields known when the recording starts: the port, the wire format, the notes."""
    base_fields: dict[str, Any] = {
        "source": "record",
        "port": url,
        "baud": baudrate,
        "start_utc": utc_now_iso(),
        "fog_driver_version": __version__,
        **wire.sidecar_fields(),
    }
    if notes:
        base_fields["notes"] = notes
    return base_fields


class _Recording:
    """What a recording learns as it goes, for its sidecar: the port's states, the device setups run on each
    open (the offline readers skip their bytes, as the daemon does), the frames decoded and the identity."""

    def __init__(
        self, wire: Any, on_state: Callable[[PortEvent], None] | None, on_event: Callable[[Any], None] | None = None
    ) -> None:
        self.decoder = wire.make_decoder()
        self.identity: IdentityFrame | None = None
        self.port_state = "opening"
        self.port_events: list[dict[str, Any]] = []
        self.events: list[dict[str, Any]] = []
        self.bytes_written = 0  # to the capture so far
        self._on_state = on_state
        self._on_event = on_event

    def state_changed(self, event: PortEvent) -> None:
        self.port_state = event.state
        entry = {"utc": utc_now_iso(), "state": event.state}
        if event.detail:
            entry["detail"] = event.detail
        self.port_events.append(entry)
        if self._on_state:
            self._on_state(event)

    def setup_done(self, result: Any) -> None:
        """A device setup ran (before its bytes are yielded: they start at the bytes written so far)."""
        self.events.append(
            {
                "event": "device_setup",
                "utc": utc_now_iso(),
                "at_byte": self.bytes_written,
                "bytes_not_decoded": len(result.raw),
                "replies": list(result.replies),
            }
        )

    def bytes_to_frame_boundary(self) -> int:
        """How many bytes to read at most before the next look: 1 while the decoder holds part of a possible
        frame (it cannot say how long the rest is before it has it), 0 at a frame boundary."""
        return 1 if self.decoder.pending else 0

    def feed(self, chunk: bytes, bytes_written: int) -> None:
        """A chunk written to the capture, which now holds ``bytes_written`` bytes: decode it."""
        self.bytes_written = bytes_written
        for event in self.decoder.feed(chunk):
            if isinstance(event, IdentityFrame):
                self.identity = event
            if self._on_event is not None:
                self._on_event(event)

    def sidecar_fields(self, base_fields: dict[str, Any], status: str, elapsed_s: float, writer: CaptureWriter) -> dict:
        """The sidecar at the end: ``base_fields``, how the recording ended, and what it learnt."""
        fields = {
            **base_fields,
            "status": status,
            "end_utc": utc_now_iso(),
            "host_duration_s": round(elapsed_s, 3),
            "bytes": writer.bytes_written,
            "sha256": writer.sha256,
            "port_events": self.port_events,
            "decoded_while_recording": self.decoder.counters.as_dict(),
            **({"events": self.events} if self.events else {}),
        }
        if self.identity is not None:
            fields["instrument"] = {
                "serial": self.identity.serial,
                "firmware": self.identity.firmware_version,
                "rate_hz": self.identity.rate_hz,
                "scale_arcsec_per_count": self.identity.scale_arcsec_per_count,
            }
        return fields


def _first_chunk(url: str, reader: PortReader, chunks: Iterator[bytes], timer: Any, started: float) -> bytes:
    """The recording's first bytes; a port that fails to open, or a recording stopped before its first byte,
    is a ``DeviceError`` (an empty capture would only block a rerun)."""
    try:
        first = next(chunks, b"")
    except PortError as exc:
        if timer:
            timer.cancel()
        raise DeviceError(str(exc)) from None
    if not first:  # stopped before the first byte: an empty capture would only block a rerun
        if timer:
            timer.cancel()
        why = "never opened" if not reader.opens else "sent no bytes"
        raise DeviceError(f"nothing recorded: {url} {why} in {time.monotonic() - started:.1f} s; no capture written")
    return first


def _copy(
    chunks: Iterator[bytes],
    writer: CaptureWriter,
    recording: _Recording,
    started: float,
    on_progress: Callable[[RecordProgress], None] | None,
    progress_every_s: float,
) -> None:
    """Write every chunk to the capture and decode it; flush every ``_FLUSH_EVERY_S`` and report progress
    every ``progress_every_s`` (host time)."""
    last_flush = last_progress = started
    for chunk in chunks:
        writer.write(chunk)
        recording.feed(chunk, writer.bytes_written)
        now = time.monotonic()
        if now - last_flush >= _FLUSH_EVERY_S:
            writer.flush()
            last_flush = now
        if on_progress and now - last_progress >= progress_every_s:
            counters = recording.decoder.counters
            on_progress(RecordProgress(now - started, writer.bytes_written, counters, recording.port_state))
            last_progress = now
