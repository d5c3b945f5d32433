"""The daemon's always-on raw capture: every byte read from the port, in rotating capture files.

``RotatingCapture`` appends the port's bytes exactly as read (garbage, partial frames and all) to
``<prefix>-<UTC yyyymmddThhmmssZ>-<nnnn>.bin`` files in one directory, each with the usual
provenance sidecar ``<same name>.yaml`` (see ``fog_driver.capture``).  The file itself is a
``CaptureWriter``: size, SHA-256, the one-line ``OutputFileError`` on a full disk all come from it.

Rules (the tests hold them):

- **A chunk is never split across files.**  Rotation happens only between writes: before writing a
  chunk that would take the current file past ``max_bytes``, the file is closed and the chunk starts
  the next one.  So every file holds at most ``max_bytes``, except a file that starts with a single
  chunk larger than ``max_bytes``: that chunk is written whole, alone in its file (a port read is a
  few kB; ``max_bytes`` is hundreds of MB, so this only happens with a misconfigured limit).
- Files are cut at read-chunk boundaries, not at frame boundaries: a file may begin or end inside
  a frame.  Concatenating the files in name order gives back the port's byte stream exactly
  (``cat fog-*.bin``), which is how a decoder should read a run that spans files.
- A file rotates by age when ``max_age_s`` (of ``clock``, monotonic by default) has passed since it
  was opened; checked on each ``write`` and on ``poll``, so a port that goes quiet still gets its
  file closed and described (call ``poll`` from the daemon's main loop).
- Files open lazily, on the first byte after construction or after a rotation: a silent port
  leaves no empty files.  ``current_path`` is None while no file is open.
- Data is flushed to the OS when ``flush_every_s`` has passed since the last flush (on ``write``
  and on ``poll``): a SIGKILL loses at most about that much.  ``close`` flushes and fsyncs.
  (A power cut can lose whatever the OS has not written back since the last fsync.)
- Sidecar: written with ``status: recording`` when a file opens, rewritten on close with
  ``status: complete`` (or ``failed: ...``), ``bytes``, ``sha256``, ``start_utc``, ``end_utc``,
  ``end_reason`` (``max_bytes``, ``max_age_s`` or ``close``), the segment number, the previous
  file's name, plus the ``provenance`` mapping given (port, instrument...).
- A failed write (disk full) raises the ``CaptureWriter``'s one-line ``OutputFileError`` after the
  file is closed and its sidecar says ``status: failed: ...`` with the bytes that made it; the
  service decides what to do.  A later ``write`` starts a new file.
- ``<nnnn>`` counts the files this object opened (0000, 0001, ...; a fifth digit after 9999); a name
  that already exists (a restart within the same second) is skipped, never overwritten.

Not thread-safe: one acquisition loop owns it.
"""

from __future__ import annotations

import datetime as _dt
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from .. import __version__
from ..capture import CaptureWriter, sidecar_path, utc_now_iso, write_provenance
from ..errors import OutputFileError

DEFAULT_MAX_BYTES = 256 * 2**20
DEFAULT_MAX_AGE_S = 3600.0
DEFAULT_FLUSH_EVERY_S = 1.0


class RotatingCapture:
    """Append a port's raw bytes to rotating capture files with provenance sidecars (see the module doc)."""

    def __init__(
        self,
        directory: str | Path,
        *,
        prefix: str = "fog",
        max_bytes: int = DEFAULT_MAX_BYTES,
        max_age_s: float = DEFAULT_MAX_AGE_S,
        flush_every_s: float = DEFAULT_FLUSH_EVERY_S,
        provenance: dict[str, Any] | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if not prefix or "/" in prefix or os.sep in prefix or prefix.startswith("."):
            raise ValueError(f"capture prefix {prefix!r} must be a plain, non-hidden file name part")
        if max_bytes <= 0:
            raise ValueError(f"max_bytes must be positive, not {max_bytes}")
        if not max_age_s > 0:
            raise ValueError(f"max_age_s must be positive, not {max_age_s}")
        if not flush_every_s >= 0:
            raise ValueError(f"flush_every_s must be zero or positive, not {flush_every_s}")
        self.directory = Path(directory)
        self.prefix = prefix
        self.max_bytes = int(max_bytes)
        self.max_age_s = float(max_age_s)
        self.flush_every_s = float(flush_every_s)
        self._provenance: dict[str, Any] = dict(provenance or {})
        self._clock = clock
        _make_directory(self.directory)

        self._files: list[Path] = []
        self._segment = 0  # the next <nnnn> to try
        self._writer: CaptureWriter | None = None
        self._fields: dict[str, Any] = {}  # the current file's own sidecar fields (segment, start_utc...)
        self._opened_at = 0.0
        self._last_flush = 0.0
        self._unflushed = False
        self._bytes_closed = 0  # bytes in files already closed
        self._closed = False

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
        """Bytes written across all files (those handed to the OS or still in the buffer)."""
        return self._bytes_closed + (self._writer.bytes_written if self._writer is not None else 0)

    @property
    def closed(self) -> bool:
        return self._closed

    # -- what the daemon calls -------------------------------------------------------------------

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
        self._unflushed = True
        if now - self._last_flush >= self.flush_every_s:
            self._flush(now)

    def poll(self) -> None:
        """Housekeeping for a quiet port (call it from the main loop, e.g. once a second):
        flush if due, and close the current file if it is older than ``max_age_s``."""
        if self._closed or self._writer is None:
            return
        now = self._clock()
        if now - self._opened_at >= self.max_age_s:
            self._finish("max_age_s")
        elif self._unflushed and now - self._last_flush >= self.flush_every_s:
            self._flush(now)

    def flush(self) -> None:
        """Hand everything written so far to the OS (no fsync)."""
        if self._writer is not None:
            self._flush(self._clock())

    def update_provenance(self, fields: dict[str, Any]) -> None:
        """Merge ``fields`` (e.g. the instrument's identity, once its IDENTITY frame arrives) into the
        provenance of the current file (its sidecar is rewritten now) and of every later one."""
        self._provenance.update(fields)
        if self._writer is not None:
            write_provenance(self._writer.path, self._sidecar("recording"))

    def close(self) -> None:
        """Flush, fsync and close the current file and write its final sidecar; idempotent."""
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
            path = self.directory / f"{self.prefix}-{stamp}-{self._segment:04d}.bin"
            self._segment += 1
            if not path.exists() and not sidecar_path(path).exists():
                return path

    def _open(self, now: float) -> None:
        start_utc = utc_now_iso()
        path = self._next_path(_dt.datetime.fromisoformat(start_utc))
        writer = CaptureWriter(path)  # "x" mode: never replaces a file that appeared meanwhile
        previous = self._files[-1].name if self._files else None
        self._fields = {"segment": self._segment - 1, "start_utc": start_utc}
        if previous is not None:
            self._fields["previous_capture"] = previous
        self._writer = writer
        try:
            write_provenance(path, self._sidecar("recording"))
        except OutputFileError:
            self._writer = None
            try:
                writer.close()
            except OutputFileError:
                pass
            path.unlink(missing_ok=True)  # an empty file nothing describes: leave nothing behind
            raise
        self._files.append(path)
        self._opened_at = now
        self._last_flush = now
        self._unflushed = False

    def _flush(self, now: float) -> None:
        writer = self._writer
        assert writer is not None
        try:
            writer.flush()
        except OutputFileError as exc:
            self._fail(exc)
            raise
        self._last_flush = now
        self._unflushed = False

    def _detach(self) -> CaptureWriter:
        """Take the current file out of use, counting its bytes as closed."""
        writer = self._writer
        assert writer is not None
        self._writer = None
        self._bytes_closed += writer.bytes_written
        return writer

    def _finish(self, reason: str) -> None:
        """Close the current file (flush + fsync) and write its final sidecar."""
        writer = self._detach()
        try:
            writer.close()
        except OutputFileError as exc:
            self._write_final(writer, f"failed: {exc}", reason, quiet=True)
            raise
        self._write_final(writer, "complete", reason, quiet=False)

    def _fail(self, exc: OutputFileError) -> None:
        """A write or flush failed: close what can be closed and describe the file as failed."""
        writer = self._detach()
        try:
            writer.close()
        except OutputFileError:
            pass  # the error being raised already says why
        self._write_final(writer, f"failed: {exc}", "write failed", quiet=True)

    def _write_final(self, writer: CaptureWriter, status: str, reason: str, *, quiet: bool) -> None:
        fields = self._sidecar(status)
        fields.update(
            end_utc=utc_now_iso(),
            end_reason=reason,
            bytes=writer.bytes_written,
            sha256=writer.sha256,
        )
        try:
            write_provenance(writer.path, fields)
        except OutputFileError:
            if not quiet:
                raise  # the capture itself is closed and intact; only its description failed

    def _sidecar(self, status: str) -> dict[str, Any]:
        return {
            "source": "daemon",
            "fog_driver_version": __version__,
            **self._provenance,
            "status": status,
            **self._fields,
            "rotation": {"max_bytes": self.max_bytes, "max_age_s": self.max_age_s},
        }


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
