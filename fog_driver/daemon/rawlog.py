"""The daemon's always-on raw capture: every byte read from the port, in rotating capture files.

Two layers:

``RotatingCapture`` appends the port's bytes exactly as read (garbage, partial frames and all) to
``<prefix>-<nnnnnn>-<UTC yyyymmddThhmmssZ>.bin`` files in one directory, each with the usual
provenance sidecar ``<same name>.bin.yaml`` (see ``fog_driver.samples.captures``; files from before have it at
``<same name>.yaml``, and ``repair_interrupted`` reads and rewrites either).  The file itself is a
``CaptureWriter``: unbuffered, so size and SHA-256 count exactly the bytes the OS took.  It is not
thread-safe: one thread owns it.

``CaptureSink`` is that thread: the acquisition thread hands each chunk over (``put``, O(1), never a
wait for the disk) and the sink's own thread writes, rotates, fsyncs and rewrites sidecars.  A disk that
fills up or fails degrades the capture, never the daemon (see ``CaptureSink``).

Rules (the tests hold them):

- **A chunk is never split across files.**  Rotation happens only between writes: before writing a
  chunk that would take the current file past ``max_bytes``, the file is closed and the chunk starts
  the next one.  So every file holds at most ``max_bytes``, except a file that starts with a single
  chunk larger than ``max_bytes``: that chunk is written whole, alone in its file (a port read is a
  few kB; ``max_bytes`` is hundreds of MB, so this only happens with a misconfigured limit).
- Files are cut at read-chunk boundaries, not at frame boundaries: a file may begin or end inside
  a frame.  Concatenating the files in name order gives back the port's byte stream exactly
  (``cat fog-*.bin``), which is how a decoder should read a run that spans files; where bytes could not
  be captured the sidecars say so (``events``: ``bytes_lost``).
- Names sort in the order the files were opened, across restarts and whatever the wall clock does (no
  RTC at boot, then NTP): ``<nnnnnn>`` continues from the highest number in the directory; the UTC time
  after it is for people.  A name that exists is never overwritten.
- A file rotates by age when ``max_age_s`` (of ``clock``, monotonic by default) has passed since it
  was opened; checked on each ``write`` and on ``poll``, so a port that goes quiet still gets its
  file closed and described.
- Files open lazily, on the first byte after construction or after a rotation: a silent port
  leaves no empty files.  ``current_path`` is None while no file is open.
- Every ``write`` reaches the OS at once (a SIGKILL loses nothing written); ``sync`` fsyncs (the sink
  does every ``fsync_every_s``, so a power cut loses at most about that much), and ``close`` does.
- Sidecar: written with ``status: recording`` when a file opens, rewritten on close with
  ``status: complete`` (or ``failed: ...``), ``bytes``, ``sha256`` (of exactly the bytes on disk),
  ``start_utc``, ``end_utc``, ``end_reason`` (``max_bytes``, ``max_age_s`` or ``close``), the segment
  number, the previous file's name, ``events`` (``note``: what happened at which byte of the file),
  plus the ``provenance`` mapping given (port, instrument, model...).
- ``keep_model``: a copy of each model the daemon compensates with, ``models/<sha256>.yaml`` in the directory
  (once per content, atomic), for ``compensate`` to replay a reload; ``prune`` deletes the copies no capture
  left names (``modelstore.KeptModels``: by its index, never by reading the sidecars).
- A sidecar a killed process left at ``status: recording`` is set right by ``repair_interrupted``
  (``status: interrupted``, the file's true size and SHA-256) before the next run writes.
- A failed write (disk full) raises the ``CaptureWriter``'s one-line ``OutputFileError`` after the
  file is closed and its sidecar says ``status: failed: ...`` with the bytes that made it; a later
  ``write`` starts a new file.
"""

from __future__ import annotations

import collections
import contextlib
import datetime as _dt
import hashlib
import os
import re
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import structlog

from .. import __version__
from ..errors import FogDriverError, OutputFileError
from ..files.stamps import utc_now_iso
from ..samples.captures import (
    CaptureWriter,
    find_sidecar,
    legacy_sidecar_path,
    read_provenance,
    sidecar_path,
    write_provenance,
)
from .modelstore import CAPTURE_NUMBER_DIGITS, KeptModels, numbered_captures

log = structlog.get_logger("fog_driver.daemon")

DEFAULT_MAX_BYTES = 256 * 2**20
#: A file's sidecar lists at most this many events; past it they are summarized per kind (``events_summary``:
#: count, first and last ``at_byte``), so a client repeating a command cannot grow the sidecar, which is
#: rewritten at each listed event, without bound.
MAX_EVENTS_PER_FILE = 1000
DEFAULT_MAX_AGE_S = 3600.0
#: The sink fsyncs the current file this often (a power cut loses at most about this much).
DEFAULT_FSYNC_EVERY_S = 5.0
#: Bytes the sink holds for a disk that is slow before it stops capturing them (counted as lost).
DEFAULT_MAX_QUEUE_BYTES = 64 * 2**20
#: While bytes flow, the sink writes what has arrived this often (a killed daemon loses at most about this
#: much of what it read); the first chunk after a pause is written at once.
DEFAULT_WRITE_EVERY_S = 0.02
#: ... or at once when this many bytes wait (an unpaced replay's chunks).
WRITE_AT_BYTES = 64 * 1024
#: After a failed write the sink tries a new file after this long, doubling up to the maximum.
RETRY_FIRST_S = 1.0
RETRY_MAX_S = 60.0


class RotatingCapture:
    """Append a port's raw bytes to rotating capture files with provenance sidecars (see the module doc)."""

    def __init__(
        self,
        directory: str | Path,
        *,
        prefix: str = "fog",
        max_bytes: int = DEFAULT_MAX_BYTES,
        max_age_s: float = DEFAULT_MAX_AGE_S,
        provenance: dict[str, Any] | None = None,
        clock: Callable[[], float] = time.monotonic,
        keep_days: float | None = None,
        max_total_bytes: int | None = None,
        wall_clock: Callable[[], float] = time.time,
    ) -> None:
        if not prefix or "/" in prefix or os.sep in prefix or prefix.startswith("."):
            raise ValueError(f"capture prefix {prefix!r} must be a plain, non-hidden file name part")
        if max_bytes <= 0:
            raise ValueError(f"max_bytes must be positive, not {max_bytes}")
        if not max_age_s > 0:
            raise ValueError(f"max_age_s must be positive, not {max_age_s}")
        if keep_days is not None and not keep_days > 0:
            raise ValueError(f"keep_days must be positive (or None: keep every capture), not {keep_days}")
        if max_total_bytes is not None and not max_total_bytes > 0:
            raise ValueError(f"max_total_bytes must be positive (or None: no limit), not {max_total_bytes}")
        self.keep_days = keep_days
        self.max_total_bytes = max_total_bytes
        self._wall_clock = wall_clock
        self.directory = Path(directory)
        self.prefix = prefix
        self.max_bytes = int(max_bytes)
        self.max_age_s = float(max_age_s)
        self._provenance: dict[str, Any] = dict(provenance or {})  # for the files to come
        self._file_provenance: dict[str, Any] = dict(self._provenance)  # the current file's
        self._clock = clock
        _make_directory(self.directory)

        self._files: list[Path] = []
        self._index = _next_index(self.directory, prefix)  # the next <nnnnnn> to try
        self._segment = 0  # files this object opened
        self._writer: CaptureWriter | None = None
        self._fields: dict[str, Any] = {}  # the current file's own sidecar fields (segment, start_utc...)
        self._events: list[dict[str, Any]] = []  # the current file's events
        self._summary: dict[str, dict[str, int]] = {}  # events past MAX_EVENTS_PER_FILE, per kind
        self._pending_summary: dict[str, dict[str, int]] = {}
        self._pending_events: list[dict[str, Any]] = []  # events for the next file (none open now)
        self._opened_at = 0.0
        self._bytes_closed = 0  # bytes in files already closed
        self._closed = False
        self.pruned: list[Path] = []  # captures deleted by the retention limits, oldest first
        self.models = KeptModels(self.directory, prefix)  #: the kept models (``modelstore``)
        self.prune()

    # -- what the daemon reads -------------------------------------------------------------------

    @property
    def files(self) -> list[Path]:
        """Every capture file opened so far, oldest first (the current one last)."""
        return list(self._files)

    @property
    def current_path(self) -> Path | None:
        """The file being written, or None between files (before the first byte, after a rotation)."""
        return self._writer.path if self._writer is not None else None

    @property
    def bytes_written(self) -> int:
        """Bytes written across all files (each taken by the OS)."""
        return self._bytes_closed + (self._writer.bytes_written if self._writer is not None else 0)

    @property
    def closed(self) -> bool:
        return self._closed

    # -- what the owner calls --------------------------------------------------------------------

    def write(self, chunk: bytes) -> None:
        """Append ``chunk`` exactly, rotating first if it would overflow ``max_bytes`` or the file is too old."""
        if self._closed:
            raise ValueError("write to a closed RotatingCapture")
        if not chunk:
            return
        now = self._clock()
        if self._writer is not None:
            reason = self._rotation_reason(len(chunk), now)
            if reason:
                self._finish(reason)
        if self._writer is None:
            self._open(now)
        writer = self._writer
        assert writer is not None
        try:
            writer.write(chunk)
        except OutputFileError as exc:
            self._fail(exc)
            raise

    def poll(self) -> None:
        """Housekeeping for a quiet port: close the current file if it is older than ``max_age_s``."""
        if self._closed or self._writer is None:
            return
        if self._clock() - self._opened_at >= self.max_age_s:
            self._finish("max_age_s")

    def flush(self) -> None:
        """Nothing to do: every ``write`` reached the OS (kept for callers of the buffered version)."""

    def sync(self) -> None:
        """Fsync the current file (``OutputFileError``: the file is closed as failed)."""
        if self._writer is None:
            return
        try:
            self._writer.fsync()
        except OutputFileError as exc:
            self._fail(exc)
            raise

    def update_provenance(self, fields: dict[str, Any], *, current_file: bool = True) -> None:
        """Merge ``fields`` (e.g. the instrument's identity, once its IDENTITY frame arrives) into the
        provenance of the current file (its sidecar is rewritten now; not with ``current_file`` False: the model
        a reload put in use, which the current file's events note) and of every later one."""
        self._provenance.update(fields)
        if current_file or self._writer is None:
            self._file_provenance.update(fields)
            self._rewrite_recording()

    def note(self, event: dict[str, Any]) -> None:
        """Record ``event`` in the sidecar of the file the next byte goes to, with ``at_byte``: the bytes
        of that file before it (a model reload, ADAPT, an identity change, bytes that were not captured)."""
        pending = self._writer is None
        at = 0 if self._writer is None else self._writer.bytes_written
        events, summary = (self._pending_events, self._pending_summary) if pending else (self._events, self._summary)
        if len(events) >= MAX_EVENTS_PER_FILE:  # summarized; written with the sidecar's next rewrite
            kind = str(event.get("event", "?"))
            entry = summary.setdefault(kind, {"count": 0, "first_at_byte": at, "last_at_byte": at})
            entry["count"] += 1
            entry["last_at_byte"] = at
            if isinstance(event.get("bytes"), int):  # bytes_lost: the total, so the files still say what they miss
                entry["bytes"] = entry.get("bytes", 0) + event["bytes"]
            return
        events.append({**event, "at_byte": at})
        if not pending:
            self._rewrite_recording()

    def keep_model(self, sha256: str, data: bytes) -> Path:
        """Keep a copy of the model file ``data`` (of SHA-256 ``sha256``) the daemon compensates with from
        here on, naming the file being written (or the next one): ``KeptModels.keep`` (``OutputFileError``,
        ``ValueError`` as it says)."""
        return self.models.keep(sha256, data)

    def close(self) -> None:
        """Fsync and close the current file and write its final sidecar; idempotent."""
        if self._closed:
            return
        self._closed = True
        if self._writer is not None:
            self._finish("close")

    def __enter__(self) -> RotatingCapture:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- inside ----------------------------------------------------------------------------------

    def _rewrite_recording(self) -> None:
        if self._writer is not None:
            write_provenance(self._writer.path, self._sidecar("recording"))

    def _rotation_reason(self, incoming: int, now: float) -> str | None:
        writer = self._writer
        assert writer is not None
        if writer.bytes_written and writer.bytes_written + incoming > self.max_bytes:
            return "max_bytes"
        if now - self._opened_at >= self.max_age_s:
            return "max_age_s"
        return None

    def _next_path(self, start: _dt.datetime) -> Path:
        stamp = start.strftime("%Y%m%dT%H%M%SZ")
        while True:
            path = self.directory / f"{self.prefix}-{self._index:0{CAPTURE_NUMBER_DIGITS}d}-{stamp}.bin"
            self._index += 1
            if not any(p.exists() for p in (path, sidecar_path(path), legacy_sidecar_path(path))):
                return path

    def _open(self, now: float) -> None:
        start_utc = utc_now_iso()
        path = self._next_path(_dt.datetime.fromisoformat(start_utc))
        writer = CaptureWriter(path)  # "x" mode: never replaces a file that appeared meanwhile
        previous = self._files[-1].name if self._files else None
        self._fields = {"segment": self._segment, "start_utc": start_utc}
        if previous is not None:
            self._fields["previous_capture"] = previous
        self._writer = writer
        self._file_provenance = dict(self._provenance)
        self._events, self._pending_events = self._pending_events, []
        self._summary, self._pending_summary = self._pending_summary, {}
        try:
            write_provenance(path, self._sidecar("recording"))
        except OutputFileError:
            self._writer = None
            self._pending_events, self._events = self._events, []
            self._pending_summary, self._summary = self._summary, {}
            with contextlib.suppress(OutputFileError):
                writer.close()
            path.unlink(missing_ok=True)  # an empty file nothing describes: leave nothing behind
            raise
        self._segment += 1
        self._files.append(path)
        self._opened_at = now
        self.models.capture_opened(path)

    def _detach(self) -> CaptureWriter:
        """Take the current file out of use, counting its bytes as closed."""
        writer = self._writer
        assert writer is not None
        self._writer = None
        self._bytes_closed += writer.bytes_written
        self.models.capture_closed()
        return writer

    def _finish(self, reason: str) -> None:
        """Close the current file (fsync), write its final sidecar, then apply the retention limits."""
        writer = self._detach()
        try:
            writer.close()
        except OutputFileError as exc:
            self._write_final(writer, f"failed: {exc}", reason, quiet=True)
            raise
        self._write_final(writer, "complete", reason, quiet=False)
        self.prune()

    def prune(self) -> list[Path]:
        """Delete the oldest closed captures (with their sidecars) beyond the retention limits.

        A capture goes when its last byte was written more than ``keep_days`` ago (its mtime), or while
        the captures of this prefix in the directory total more than ``max_total_bytes`` (oldest first, by
        number).  Never the file being written, never a file whose sidecar still says ``recording`` (another
        daemon's), never a file of another name.  Called at start and after each file is closed; a capture
        that cannot be deleted is logged and left.  Returns what was deleted now.
        """
        if self.keep_days is None and self.max_total_bytes is None:
            return []
        current = self.current_path
        captures = []  # (path, size, mtime), oldest first
        for _, path in sorted(numbered_captures(self.directory).get(self.prefix, {}).items()):
            try:
                st = path.stat()
            except OSError:
                continue
            captures.append((path, st.st_size, st.st_mtime))
        total = sum(size for _, size, _ in captures)
        cutoff = None if self.keep_days is None else self._wall_clock() - self.keep_days * 86400.0
        deleted = []
        for path, size, mtime in captures:
            too_old = cutoff is not None and mtime < cutoff
            too_much = self.max_total_bytes is not None and total > self.max_total_bytes
            if not (too_old or too_much):
                continue
            if path == current or _recording_elsewhere(path):
                continue
            try:
                sidecar = find_sidecar(path)  # this version's name, or a capture sidecar of the old one
                path.unlink()
                if sidecar is not None:
                    sidecar.unlink(missing_ok=True)
            except OSError as exc:
                log.error("capture_prune_failed", capture=str(path), reason=exc.strerror or str(exc))
                continue
            total -= size
            deleted.append(path)
            log.info(
                "capture_pruned",
                capture=str(path),
                bytes=size,
                reason="older than capture_keep_days" if too_old else "over capture_max_gb",
            )
        self.pruned += deleted
        if deleted:
            self.models.prune()
        return deleted

    def _fail(self, exc: OutputFileError) -> None:
        """A write or fsync failed: close what can be closed and describe the file as failed."""
        writer = self._detach()
        with contextlib.suppress(OutputFileError):  # the error being raised already says why
            writer.close()
        self._write_final(writer, f"failed: {exc}", "write failed", quiet=True)

    def _write_final(self, writer: CaptureWriter, status: str, reason: str, *, quiet: bool) -> None:
        fields = self._sidecar(status)
        fields.update(end_utc=utc_now_iso(), end_reason=reason, bytes=writer.bytes_written, sha256=writer.sha256)
        self._events = []
        try:
            write_provenance(writer.path, fields)
        except OutputFileError:
            if not quiet:
                raise  # the capture itself is closed and intact; only its description failed

    def _sidecar(self, status: str) -> dict[str, Any]:
        doc = {
            "source": "daemon",
            "fog_driver_version": __version__,
            **self._file_provenance,
            "status": status,
            **self._fields,
            "rotation": {"max_bytes": self.max_bytes, "max_age_s": self.max_age_s},
        }
        if self._events:
            doc["events"] = list(self._events)
        if self._summary:
            doc["events_summary"] = {kind: dict(v) for kind, v in self._summary.items()}
        return doc


class CaptureSink:
    """A ``RotatingCapture`` written by a thread of its own, so that the port's reader never waits for the disk.

    - ``put(chunk)`` (any thread, O(1)): the bytes join a queue the writer thread empties in order.
      The thread writes the first chunk after a pause at once, and then, while bytes keep coming, what
      has arrived every ``write_every_s`` (20 ms) or as soon as ``WRITE_AT_BYTES`` wait: one wake-up per
      batch rather than per chunk, so while bytes flow the thread's wake-ups follow ``write_every_s`` (and
      ``WRITE_AT_BYTES``), not how finely the port hands its bytes over (``benchmarks/bench_daemon.py``
      measures the daemon's CPU per thread, the capture thread's included).  A killed daemon
      (SIGKILL) loses at most the batch being gathered; a stopped one writes everything.
      When ``max_queue_bytes`` are already waiting (a disk that stalls) or the capture has failed, the
      chunk is not captured: it is counted in ``bytes_lost`` and the gap is noted in the sidecar of the
      file the next captured byte goes to (``events``: ``bytes_lost``, at that byte), so the files still
      say exactly what they hold.
    - ``note(event)`` (any thread): an event for the sidecar, in order with the bytes put before it.
    - A write, fsync or file-open error (a full disk, EIO, no descriptor left) is logged once, the file
      is closed as ``failed`` (its sidecar counts the bytes on disk), ``status`` becomes ``failed`` and
      the sink tries a new file after ``retry_first_s`` (1 s), doubling up to ``retry_max_s`` (60 s); the first file
      that opens again sets ``status`` back to ``recording`` (``on_status`` is called at each change).
    - Every ``fsync_every_s`` the current file is fsynced; ``poll_s`` is the thread's housekeeping tick
      (age rotation of a quiet port).
    - ``status_fields()``: a snapshot for STATUS: ``status`` (``idle`` before the first byte, ``recording``, ``failed``,
      ``retrying``: the next chunk tries a new file, ``closed``), the file, bytes captured and lost, failures,
      the last error.
    - ``close(timeout_s)``: writes what is queued, closes the file, joins the thread (bounded).
    """

    def __init__(
        self,
        capture: RotatingCapture,
        *,
        max_queue_bytes: int = DEFAULT_MAX_QUEUE_BYTES,
        fsync_every_s: float = DEFAULT_FSYNC_EVERY_S,
        poll_s: float = 1.0,
        write_every_s: float = DEFAULT_WRITE_EVERY_S,
        retry_first_s: float = RETRY_FIRST_S,
        retry_max_s: float = RETRY_MAX_S,
        on_status: Callable[[str], None] | None = None,
    ) -> None:
        if (
            max_queue_bytes <= 0
            or not fsync_every_s > 0
            or not poll_s > 0
            or not write_every_s > 0
            or not 0 < retry_first_s <= retry_max_s
        ):
            raise ValueError(
                "max_queue_bytes, fsync_every_s, poll_s, write_every_s and retry_first_s <= retry_max_s "
                "must be positive"
            )
        self.write_every_s = float(write_every_s)
        self.retry_first_s = float(retry_first_s)
        self.retry_max_s = float(retry_max_s)
        self.capture = capture
        self.max_queue_bytes = int(max_queue_bytes)
        self.fsync_every_s = float(fsync_every_s)
        self.poll_s = float(poll_s)
        self._on_status = on_status
        self._cond = threading.Condition()
        self._queue: collections.deque[tuple[str, Any]] = collections.deque()
        self._queued_bytes = 0
        self._idle = False  # the writer waits for bytes (not gathering a batch): the next put wakes it
        self._closing = False
        self._status = "idle"  # idle (no byte yet), recording, failed, closed
        self._error: str | None = None
        self._retry_at = 0.0
        self._retry_s = self.retry_first_s
        self._lost_pending = 0  # bytes lost since the last note of it
        self.bytes_put = 0
        self.bytes_lost = 0
        self.failures = 0
        self._current: str | None = None
        self._bytes_captured = 0
        self._thread = threading.Thread(target=self._run, name="capture", daemon=True)
        self._thread.start()

    @property
    def status(self) -> str:
        """The capture's status now: ``idle`` (no byte yet), ``recording``, ``failed``, ``retrying``, ``closed``."""
        return self._status

    def put(self, chunk: bytes) -> None:
        if not chunk:
            return
        with self._cond:
            self.bytes_put += len(chunk)
            if self._closing or self._status == "failed" or self._queued_bytes + len(chunk) > self.max_queue_bytes:
                self.bytes_lost += len(chunk)
                self._lost_pending += len(chunk)
                return
            if self._lost_pending:
                self._queue.append(("note", {"event": "bytes_lost", "bytes": self._lost_pending, "utc": utc_now_iso()}))
                self._lost_pending = 0
            self._queue.append(("bytes", chunk))
            self._queued_bytes += len(chunk)
            if self._idle or self._queued_bytes >= WRITE_AT_BYTES:
                self._cond.notify()

    def note(self, event: dict[str, Any]) -> None:
        with self._cond:
            if self._closing:
                return
            self._queue.append(("note", {**event, "utc": utc_now_iso()}))
            self._cond.notify()

    def update_provenance(self, fields: dict[str, Any], *, current_file: bool = True) -> None:
        with self._cond:
            if self._closing:
                return
            self._queue.append(("provenance", (dict(fields), current_file)))
            self._cond.notify()

    def keep_model(self, sha256: str, data: bytes) -> None:
        """``RotatingCapture.keep_model``, on the sink's thread (a failure is logged: the capture goes on)."""
        with self._cond:
            if self._closing:
                return
            self._queue.append(("model", (sha256, data)))
            self._cond.notify()

    def status_fields(self) -> dict[str, Any]:
        with self._cond:
            out: dict[str, Any] = {
                "status": self._status,
                "bytes": self._bytes_captured,
                "bytes_lost": self.bytes_lost,
                "failures": self.failures,
            }
            if self._current is not None:
                out["path"] = self._current
            if self._error is not None:
                out["last_error"] = self._error
            return out

    def close(self, timeout_s: float = 5.0) -> bool:
        """Write what is queued and close; True when the thread finished within ``timeout_s``."""
        with self._cond:
            self._closing = True
            self._cond.notify()
        self._thread.join(timeout_s)
        return not self._thread.is_alive()

    # -- the writer thread ---------------------------------------------------------------------------

    def _set_status(self, status: str, error: str | None = None) -> None:
        with self._cond:
            changed = status != self._status
            self._status = status
            if error is not None:
                self._error = error
            self._current = str(self.capture.current_path) if self.capture.current_path is not None else None
            self._bytes_captured = self.capture.bytes_written
        if changed and self._on_status is not None:
            try:
                self._on_status(status)
            except Exception:  # noqa: BLE001 - a listener's bug must not stop the capture
                log.exception("capture_state_listener_failed")

    def _run(self) -> None:
        last_sync = time.monotonic()
        try:
            for capture in repair_interrupted(self.capture.directory, self.capture.prefix):
                log.warning("capture_repaired", capture=str(capture), status="interrupted")
            gather = False  # bytes were just written: wait write_every_s for more before writing again
            while True:
                with self._cond:
                    if gather and not self._closing and self._queued_bytes < WRITE_AT_BYTES:
                        self._cond.wait(self.write_every_s)  # put() does not wake it: one write per batch
                    elif not self._queue and not self._closing:
                        wait_s = self.poll_s
                        if self._status == "failed":
                            wait_s = max(0.0, min(wait_s, self._retry_at - time.monotonic()))
                        self._idle = True
                        self._cond.wait(wait_s)
                        self._idle = False
                    items = list(self._queue)
                    self._queue.clear()
                    self._queued_bytes = 0
                    closing = self._closing
                for kind, item in items:
                    self._apply(kind, item)
                gather = any(kind == "bytes" for kind, _ in items)
                now = time.monotonic()
                if self._status == "failed" and now >= self._retry_at:
                    self._set_status("retrying")  # put() queues again; the next chunk tries a new file
                elif self._status == "recording":
                    self._guard(self.capture.poll)
                    if now - last_sync >= self.fsync_every_s:
                        self._guard(self.capture.sync)
                        last_sync = now
                self._set_status(self._status)
                if closing:
                    break
        except Exception as exc:  # noqa: BLE001 - a bug: the capture stops, the daemon goes on
            log.exception("capture_crashed", reason=str(exc))
            self._set_status("failed", f"internal error: {exc}")
        finally:
            try:
                self.capture.close()
            except FogDriverError as exc:
                log.error("capture_close_failed", reason=str(exc))
            with self._cond:
                self._closing = True
            self._set_status("closed")

    def _apply(self, kind: str, item: Any) -> None:
        if kind == "bytes":
            if self._status == "failed":  # queued before the failure: not captured
                with self._cond:
                    self.bytes_lost += len(item)
                    self._lost_pending += len(item)
                return
            before = self.capture.bytes_written
            if not self._guard(self.capture.write, item):
                with self._cond:  # the part of the chunk the file did not take
                    missed = len(item) - (self.capture.bytes_written - before)
                    self.bytes_lost += missed
                    self._lost_pending += missed
            else:
                if self._status != "recording":
                    log.info("capture_recording", path=str(self.capture.current_path))
                    self._retry_s = self.retry_first_s
                self._set_status("recording")
        elif kind == "note":
            self._guard(self.capture.note, item)
        elif kind == "provenance":
            fields, current_file = item
            self._guard(lambda: self.capture.update_provenance(fields, current_file=current_file))
        elif kind == "model":
            try:
                self.capture.keep_model(*item)
            except (OutputFileError, ValueError) as exc:  # the capture goes on; a replay will say it is missing
                log.error("model_copy_failed", reason=str(exc))

    def _guard(self, action: Callable[..., None], *args: Any) -> bool:
        """Run one capture action; an ``OutputFileError`` fails the capture (logged, retried later)."""
        try:
            action(*args)
        except OutputFileError as exc:
            self.failures += 1
            log.error("capture_failed", reason=str(exc), retry_in_s=self._retry_s, failures=self.failures)
            self._retry_at = time.monotonic() + self._retry_s
            self._retry_s = min(2 * self._retry_s, self.retry_max_s)
            self._set_status("failed", str(exc))
            return False
        return True


def repair_interrupted(directory: str | Path, prefix: str = "fog") -> list[Path]:
    """Set right the sidecars a killed process left at ``status: recording``: ``status: interrupted`` with
    the capture's true ``bytes`` and ``sha256``.  A sidecar whose ``pid`` is a process still running (another
    daemon on the same directory, or this one) is left alone.  Returns the captures repaired."""
    repaired = []
    for capture in sorted(Path(directory).glob(f"{prefix}-*.bin")):
        try:
            side = find_sidecar(capture)  # <name>.bin.yaml, or <name>.yaml from before
            doc = read_provenance(capture)
        except FogDriverError:
            continue
        if not doc or doc.get("status") != "recording" or not capture.is_file() or _alive(doc.get("pid")):
            continue
        sha = hashlib.sha256()
        with capture.open("rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                sha.update(block)
        end = _dt.datetime.fromtimestamp(capture.stat().st_mtime, _dt.UTC)
        fields = {k: v for k, v in doc.items() if k not in ("format", "schema_version", "capture")}
        fields.update(
            status="interrupted",
            end_reason="the recording process ended without closing it",
            end_utc=end.isoformat(timespec="milliseconds").replace("+00:00", "Z"),
            bytes=capture.stat().st_size,
            sha256=sha.hexdigest(),
        )
        try:
            write_provenance(capture, fields, sidecar=side)  # where it is: never a second sidecar
        except OutputFileError as exc:
            log.error("capture_repair_failed", capture=str(capture), reason=str(exc))
            continue
        repaired.append(capture)
    return repaired


def _alive(pid: Any) -> bool:
    """Whether ``pid`` (from a sidecar) names a running process (this one included)."""
    if isinstance(pid, bool) or not isinstance(pid, int) or pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # exists, owned by someone else
        return True
    return True


def _recording_elsewhere(capture: Path) -> bool:
    """Whether ``capture``'s sidecar says another live process is still writing it."""
    try:
        doc = read_provenance(capture)
    except FogDriverError:
        return False
    return bool(doc) and doc.get("status") == "recording" and _alive(doc.get("pid")) and doc.get("pid") != os.getpid()


def _next_index(directory: Path, prefix: str) -> int:
    """One more than the highest ``<prefix>-<nnnnnn>-`` number in ``directory`` (0 when there is none)."""
    pattern = re.compile(rf"^{re.escape(prefix)}-(\d{{{CAPTURE_NUMBER_DIGITS},}})-")
    numbers = [int(m.group(1)) for p in directory.iterdir() if (m := pattern.match(p.name))]
    return max(numbers, default=-1) + 1


def _make_directory(directory: Path) -> None:
    """Create the capture directory (and its parents); any failure is a one-line ``OutputFileError``."""
    if directory.exists() and not directory.is_dir():
        raise OutputFileError(f"{directory}: exists and is not a directory; cannot hold captures")
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputFileError(f"{directory}: cannot create capture directory: {exc.strerror or exc}") from None
    if not os.access(directory, os.W_OK | os.X_OK):
        raise OutputFileError(f"{directory}: capture directory is not writable")
