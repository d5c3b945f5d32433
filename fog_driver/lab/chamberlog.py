"""The chamber log: one CSV row per step of a chamber program (``chamber run``, ``calibrate``) or per poll of the
daemon's read-only chamber, with a commented header naming the run.

The file, in UTF-8 text with ``\\n`` line ends::

    # fog-driver chamber log 1
    # program_name: "fast-ramps"
    # program_sha256: "3f5c..."
    # controller_url: "watlow-f4t://10.0.0.5"
    # run_id: "20261207T174950Z-1a2b"
    # resumed_from: null
    t_utc,t_s,device_t_s,setpoint_c,air_c,state,program_c,segment
    2026-12-07T17:49:50.123Z,0.0,,20.0,20.4,running,20.0,0

- the first line names the format and its version; then one ``# KEY: VALUE`` line per ``LogHeader`` field, in
  that order, each value a JSON string (or ``null`` for ``resumed_from``), so any name round-trips on one line;
- the column line is ``LOG_COLUMNS`` joined by commas; then the rows, one per line;
- an empty field is None (``t_s`` while settling, ``device_t_s`` in a chamber run, ``setpoint_c``/``air_c``
  while the link is lost, ``program_c``/``segment`` where no program runs, as in the daemon's log);
- numbers are written with ``repr`` (the shortest text that reads back to the same float: round trip exact,
  ``20.0`` for a set point the ASCII protocols gave to one decimal); never NaN or infinite;
- ``t_utc`` is ISO 8601 to the millisecond with a ``Z`` (``format_utc``, the NDJSON ``utc``'s format);
- ``state`` is one of ``LOG_STATES``; ``segment`` is the 0-based index of the program's segment.
- a log saved with CR LF line ends (an editor on Windows) reads the same.

Nothing is lost: ``ChamberLogWriter`` writes each row whole with one ``write`` and flushes it at once, so a
process that dies loses at most the row being written, and ``close`` syncs the file to disk.  The reader's
rule for the row a crash cut: the last line of a log, when it has no line end, is that row; it is dropped and
``ChamberLog.cut_last_row`` says so (callers print one warning), and every complete row before it is read.

``read_chamber_log`` reads the file whole through ``fog_driver.files.bounded`` (a regular file, at most
``MAX_CHAMBER_LOG_BYTES``); anything that is not a chamber log of this version is one ``InputFileError``
line naming the file and the line.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from dataclasses import dataclass, field, fields
from datetime import UTC, datetime
from pathlib import Path
from typing import TextIO

import numpy as np

from ..dwells import _finite as finite_number
from ..errors import InputFileError, OutputFileError
from ..files.bounded import read_regular
from ..files.outputs import check_outputs, write_error
from .program import KIND_OF, ChamberProfile

__all__ = [
    "LOG_COLUMNS",
    "LOG_FORMAT_LINE",
    "LOG_STATES",
    "MAX_CHAMBER_LOG_BYTES",
    "ChamberLog",
    "ChamberLogWriter",
    "LogHeader",
    "LogRow",
    "format_utc",
    "program_sha256",
    "read_chamber_log",
]

LOG_COLUMNS = ("t_utc", "t_s", "device_t_s", "setpoint_c", "air_c", "state", "program_c", "segment")
LOG_STATES = ("settling", "running", "holding", "link_lost", "stopped", "interrupted", "done")
#: The first line of every chamber log (format and version).
LOG_FORMAT_LINE = "# fog-driver chamber log 1"
#: The most bytes ``read_chamber_log`` reads: about 1.2 million rows (two weeks of 1-s steps).
MAX_CHAMBER_LOG_BYTES = 128 * 1024 * 1024

_HEADER_KEYS = ("program_name", "program_sha256", "controller_url", "run_id", "resumed_from")
_FLOAT_COLUMNS = ("t_s", "device_t_s", "setpoint_c", "air_c", "program_c")
_UTC_FORMAT = "%Y-%m-%dT%H:%M:%S.%fZ"


@dataclass(frozen=True)
class LogRow:
    """One row of a chamber log (the module docstring: None is an empty field)."""

    t_utc: str  # ISO 8601, ms, Z (format_utc)
    t_s: float | None  # program time (None while settling or where no program runs)
    device_t_s: float | None  # the gyro's device time of the last frame (None: a chamber run)
    setpoint_c: float | None  # read back (None: link lost)
    air_c: float | None
    state: str  # one of LOG_STATES
    program_c: float | None  # the program's set point at t_s (what was written)
    segment: int | None  # the program's segment index


@dataclass(frozen=True)
class LogHeader:
    """What a chamber log was written by: the program (its name and ``program_sha256``), the controller's URL,
    the run's id, and the run id of the log this one resumes (None: a first run)."""

    program_name: str
    program_sha256: str
    controller_url: str
    run_id: str
    resumed_from: str | None


def program_sha256(chamber: ChamberProfile) -> str:
    """The SHA-256 (hex) of a program's start temperature and segments (kind and numbers, in order), not its
    name: ``--resume`` knows a log of the same program whatever the file was called.  The numbers are hashed by
    ``repr``, so two programs hash alike exactly when their floats are equal."""
    doc = {
        "start_c": repr(float(chamber.start_c)),
        "segments": [
            [KIND_OF[type(seg)]] + [f"{f.name}={float(getattr(seg, f.name))!r}" for f in fields(seg)]
            for seg in chamber.segments
        ],
    }
    return hashlib.sha256(json.dumps(doc, separators=(",", ":")).encode()).hexdigest()


def format_utc(dt: datetime) -> str:
    """An aware datetime as the log's ``t_utc``: UTC, ISO 8601 to the millisecond (truncated), ``Z``:
    ``2026-12-07T17:49:50.123Z``.  A naive datetime is a ValueError (its zone is unknown)."""
    if dt.tzinfo is None or dt.utcoffset() is None:
        raise ValueError(f"format_utc: a naive datetime has no time zone: {dt!r}")
    return dt.astimezone(UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")


def _field_text(name: str, value: object) -> str:
    if value is None:
        return ""
    if name == "segment":
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise ValueError(f"chamber log row: segment must be an int >= 0 or None, not {value!r}")
        return str(value)
    if name in _FLOAT_COLUMNS:
        number = float(value)  # type: ignore[arg-type]
        if not math.isfinite(number):
            raise ValueError(f"chamber log row: {name} must be finite or None, not {value!r}")
        return repr(number)
    text = str(value)
    if name == "state" and text not in LOG_STATES:
        raise ValueError(f"chamber log row: state must be one of {', '.join(LOG_STATES)}, not {text!r}")
    if "," in text or "\n" in text or "\r" in text:
        raise ValueError(f"chamber log row: {name} holds a comma or a line end: {text!r}")
    return text


def _row_line(row: LogRow) -> str:
    return ",".join(_field_text(name, getattr(row, name)) for name in LOG_COLUMNS) + "\n"


def _header_lines(header: LogHeader) -> str:
    lines = [LOG_FORMAT_LINE]
    for key in _HEADER_KEYS:
        value = getattr(header, key)
        if value is not None and not isinstance(value, str):
            raise ValueError(f"chamber log header: {key} must be a string, not {value!r}")
        lines.append(f"# {key}: {json.dumps(value)}")
    lines.append(",".join(LOG_COLUMNS))
    return "\n".join(lines) + "\n"


class ChamberLogWriter:
    """A chamber log being written: the header at once, then ``write`` one row at a time, each flushed.

    ``path`` is checked as every output is (``check_outputs``): an existing file without ``force`` is a one-line
    ``OutputFileError`` (exit 73) that says what it is; the file is then created exclusively (``O_EXCL``), so a
    log another process created in between is refused too.  A failed write (a full disk) is an
    ``OutputFileError``."""

    def __init__(self, path: str | Path, header: LogHeader, *, force: bool = False) -> None:
        self.path = Path(path)
        self.header = header
        self.rows_written = 0
        text = _header_lines(header)
        check_outputs([self.path], force=force)
        flags = os.O_WRONLY | os.O_CREAT | os.O_CLOEXEC | (os.O_TRUNC if force else os.O_EXCL)
        try:
            fd = os.open(self.path, flags, 0o644)
        except FileExistsError:
            raise OutputFileError(f"{self.path}: exists; refusing to overwrite (use --force)") from None
        except OSError as exc:
            raise write_error(self.path, "the chamber log", exc) from None
        self._file: TextIO | None = os.fdopen(fd, "w", encoding="utf-8", newline="\n")
        self._put(text)

    def _put(self, text: str) -> None:
        if self._file is None:
            raise ValueError(f"{self.path}: the chamber log is closed")
        try:
            self._file.write(text)
            self._file.flush()
        except OSError as exc:
            raise write_error(self.path, "the chamber log", exc) from None

    def write(self, row: LogRow) -> None:
        """Append ``row`` (one line, written and flushed at once).  A row with a value the log cannot hold (NaN,
        an unknown state, a comma) is a ValueError: a bug of the caller, nothing written."""
        self._put(_row_line(row))
        self.rows_written += 1

    def close(self) -> None:
        """Flush, sync to disk and close (twice is harmless)."""
        if self._file is None:
            return
        f, self._file = self._file, None
        try:
            f.flush()
            os.fsync(f.fileno())
        except OSError as exc:
            raise write_error(self.path, "the chamber log", exc) from None
        finally:
            f.close()

    def __enter__(self) -> ChamberLogWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass
class ChamberLog:
    """A chamber log read back: its header, its complete rows, and whether a cut last row was dropped.

    The column accessors give numpy float arrays, NaN for an empty field."""

    header: LogHeader
    rows: list[LogRow]
    cut_last_row: bool = False
    path: Path | None = field(default=None, compare=False)

    def _column(self, name: str) -> np.ndarray:
        return np.array([np.nan if (v := getattr(r, name)) is None else v for r in self.rows], dtype=np.float64)

    @property
    def t_s(self) -> np.ndarray:
        return self._column("t_s")

    @property
    def device_t_s(self) -> np.ndarray:
        return self._column("device_t_s")

    @property
    def setpoint_c(self) -> np.ndarray:
        return self._column("setpoint_c")

    @property
    def air_c(self) -> np.ndarray:
        return self._column("air_c")

    @property
    def program_c(self) -> np.ndarray:
        return self._column("program_c")

    @property
    def segment(self) -> np.ndarray:
        """The segment index as floats (NaN: empty)."""
        return self._column("segment")

    @property
    def utc_s(self) -> np.ndarray:
        """``t_utc`` as POSIX seconds (the host's time axis)."""
        return np.array([_parse_utc(r.t_utc).timestamp() for r in self.rows], dtype=np.float64)

    @property
    def states(self) -> list[str]:
        return [r.state for r in self.rows]

    def cut_warning(self) -> str | None:
        """The one warning line for a dropped cut row (None when the log ended on a whole row)."""
        if not self.cut_last_row:
            return None
        return f"{self.path or 'chamber log'}: its last row was cut (a crash while it was written): dropped"


def _parse_utc(text: str) -> datetime:
    return datetime.strptime(text, _UTC_FORMAT).replace(tzinfo=UTC)


def _parse_row(fields_: list[str], where: str) -> LogRow:
    if len(fields_) != len(LOG_COLUMNS):
        raise InputFileError(f"{where}: {len(fields_)} fields, a chamber log row has {len(LOG_COLUMNS)}")
    values: dict[str, object] = {}
    for name, text in zip(LOG_COLUMNS, fields_, strict=True):
        if name == "t_utc":
            try:
                _parse_utc(text)
            except ValueError:
                raise InputFileError(
                    f"{where}: t_utc {text!r} is not ISO 8601 UTC (2026-12-07T17:49:50.123Z)"
                ) from None
            values[name] = text
        elif name == "state":
            if text not in LOG_STATES:
                raise InputFileError(f"{where}: state {text!r} is not one of {', '.join(LOG_STATES)}")
            values[name] = text
        elif text == "":
            values[name] = None
        elif name == "segment":
            if not text.isdigit():
                raise InputFileError(f"{where}: segment {text!r} is not a whole number >= 0")
            values[name] = int(text)
        else:
            values[name] = finite_number(text, name, where)  # the table log's rule and words
    return LogRow(**values)  # type: ignore[arg-type]


def _parse_header(lines: list[str], path: Path) -> LogHeader:
    values: dict[str, str | None] = {}
    for number, (key, line) in enumerate(zip(_HEADER_KEYS, lines[1 : 1 + len(_HEADER_KEYS)], strict=False), 2):
        where = f"{path}: line {number}"
        prefix = f"# {key}: "
        if not line.startswith(prefix):
            raise InputFileError(f"{where}: expected the header line '{prefix}...', found {line[:60]!r}")
        try:
            value = json.loads(line[len(prefix) :])
        except ValueError:
            raise InputFileError(f"{where}: {key} is not a JSON string") from None
        if not (isinstance(value, str) or (value is None and key == "resumed_from")):
            raise InputFileError(f"{where}: {key} must be a JSON string, not {value!r}")
        values[key] = value
    missing = [k for k in _HEADER_KEYS if k not in values]
    if missing:
        raise InputFileError(f"{path}: the chamber log's header ends before {missing[0]}")
    return LogHeader(**values)  # type: ignore[arg-type]


def read_chamber_log(path: str | Path) -> ChamberLog:
    """The chamber log at ``path`` (the module docstring's format and rule for a cut last row); anything else is
    one ``InputFileError`` line (exit 65): missing, not a regular file, too large, not UTF-8, another format or
    version, a header or column line out of place, a row with a bad field (its line number)."""
    path = Path(path)
    data = read_regular(path, "chamber log", MAX_CHAMBER_LOG_BYTES) or b""
    if not data:
        raise InputFileError(f"{path}: empty, not a chamber log")
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise InputFileError(f"{path}: not a chamber log (not UTF-8 text at byte {exc.start})") from None
    lines = text.split("\n")
    cut = lines[-1] != ""  # a last line without its line end: the row a crash cut
    lines = lines[:-1]
    lines = [line.removesuffix("\r") for line in lines]  # a log saved with CR LF line ends reads the same
    first = lines[0] if lines else text
    if first != LOG_FORMAT_LINE:
        if first.startswith("# fog-driver chamber log "):
            raise InputFileError(
                f"{path}: a chamber log of version {first.rsplit(' ', 1)[-1]!r}; this fog_driver reads version 1"
            )
        raise InputFileError(f"{path}: not a chamber log (its first line is not '{LOG_FORMAT_LINE}')")
    header = _parse_header(lines, path)
    column_index = 1 + len(_HEADER_KEYS)
    if len(lines) <= column_index:
        raise InputFileError(f"{path}: the chamber log ends before its column line")
    if lines[column_index] != ",".join(LOG_COLUMNS):
        raise InputFileError(f"{path}: line {column_index + 1}: expected the column line {','.join(LOG_COLUMNS)!r}")
    rows = [
        _parse_row(line.split(","), f"{path}: line {number}")
        for number, line in enumerate(lines[column_index + 1 :], column_index + 2)
    ]
    return ChamberLog(header=header, rows=rows, cut_last_row=cut, path=path)
