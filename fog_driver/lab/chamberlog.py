"""The chamber log: one CSV row per set-point step of a chamber run (the runner writes it, ``fit`` and ``evaluate``
read it).  A minimal version for the runner: the full one (H5) replaces it.

The file: comment lines (``# fog-driver chamber log 1``, then ``# key: value`` for the header's fields), a line
of ``LOG_COLUMNS``, then one row per step, flushed as written.  An empty cell is None.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
from dataclasses import asdict, dataclass, fields
from datetime import UTC, datetime
from pathlib import Path
from typing import IO

import numpy as np

from ..errors import InputFileError, OutputFileError, read_error
from .program import ChamberProfile

MAGIC = "# fog-driver chamber log 1"
LOG_COLUMNS = ("t_utc", "t_s", "device_t_s", "setpoint_c", "air_c", "state", "program_c", "segment")
LOG_STATES = ("settling", "running", "holding", "link_lost", "stopped", "interrupted", "done")
_HEADER_KEYS = ("program_name", "program_sha256", "controller_url", "run_id", "resumed_from")


@dataclass(frozen=True)
class LogRow:
    t_utc: str  # ISO 8601, ms, Z
    t_s: float | None  # program time (None while settling)
    device_t_s: float | None  # the gyro's device time of the last frame (None: chamber run)
    setpoint_c: float | None  # read back (None: link lost)
    air_c: float | None
    state: str  # one of LOG_STATES
    program_c: float | None  # the program's set point at t_s (what was written)
    segment: int | None  # the program's segment index


@dataclass(frozen=True)
class LogHeader:
    program_name: str
    program_sha256: str
    controller_url: str
    run_id: str
    resumed_from: str | None


def program_sha256(chamber: ChamberProfile) -> str:
    """The SHA-256 of the program's start and segments (its name left out): ``--resume`` knows its run by it."""
    doc = {"start_c": chamber.start_c, "segments": [[type(s).__name__, asdict(s)] for s in chamber.segments]}
    return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()


def format_utc(dt: datetime) -> str:
    """``dt`` in UTC, ISO 8601 to the millisecond with a ``Z``."""
    return dt.astimezone(UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")


def _cell(value: object) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return repr(value)
    return str(value)


class ChamberLogWriter:
    """Write a chamber log at ``path``; ``OutputFileError`` (73) if it exists and ``force`` is not set."""

    def __init__(self, path: str | Path, header: LogHeader, *, force: bool = False) -> None:
        self.path = Path(path)
        try:
            self._file: IO[str] = open(self.path, "w" if force else "x", encoding="utf-8", newline="")  # noqa: SIM115
        except FileExistsError:
            raise OutputFileError(f"{self.path}: exists (give --force to overwrite it)") from None
        except OSError as exc:
            raise OutputFileError(f"{self.path}: cannot write the chamber log: {exc.strerror or exc}") from None
        lines = [MAGIC] + [
            f"# {key}: {'' if getattr(header, key) is None else getattr(header, key)}" for key in _HEADER_KEYS
        ]
        self._file.write("\n".join(lines) + "\n" + ",".join(LOG_COLUMNS) + "\n")
        self._file.flush()
        self._csv = csv.writer(self._file, lineterminator="\n")

    def write(self, row: LogRow) -> None:
        self._csv.writerow([_cell(getattr(row, name)) for name in LOG_COLUMNS])
        self._file.flush()

    def close(self) -> None:
        self._file.close()


@dataclass
class ChamberLog:
    header: LogHeader
    rows: list[LogRow]

    def column(self, name: str) -> np.ndarray:
        """A numeric column as floats (NaN where empty)."""
        return np.array([np.nan if getattr(r, name) is None else getattr(r, name) for r in self.rows], dtype=float)


def _float(text: str) -> float | None:
    return None if text == "" else float(text)


def read_chamber_log(path: str | Path) -> ChamberLog:
    """Read a chamber log; ``InputFileError`` (one line) on anything that is not one."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as exc:
        raise read_error(path, "chamber log", exc) from None
    except UnicodeDecodeError:
        raise InputFileError(f"{path}: not a chamber log (not text)") from None
    lines = text.splitlines()
    if not lines or lines[0] != MAGIC:
        raise InputFileError(f"{path}: not a chamber log (no '{MAGIC}' line)")
    values: dict[str, str] = {}
    k = 1
    while k < len(lines) and lines[k].startswith("# "):
        key, _, value = lines[k][2:].partition(": ")
        values[key] = value
        k += 1
    if any(key not in values for key in _HEADER_KEYS):
        raise InputFileError(f"{path}: not a chamber log (header incomplete)")
    header = LogHeader(**{key: values[key] for key in _HEADER_KEYS[:4]}, resumed_from=values["resumed_from"] or None)
    reader = csv.reader(io.StringIO("\n".join(lines[k:])))
    if next(reader, None) != list(LOG_COLUMNS):
        raise InputFileError(f"{path}: not a chamber log (columns are not {','.join(LOG_COLUMNS)})")
    rows = []
    for n, cells in enumerate(reader, start=k + 2):
        try:
            if len(cells) != len(LOG_COLUMNS) or cells[5] not in LOG_STATES:
                raise ValueError
            row = LogRow(
                cells[0],
                _float(cells[1]),
                _float(cells[2]),
                _float(cells[3]),
                _float(cells[4]),
                cells[5],
                _float(cells[6]),
                None if cells[7] == "" else int(cells[7]),
            )
        except ValueError:
            raise InputFileError(f"{path}: line {n}: not a chamber log row") from None
        rows.append(row)
    assert [f.name for f in fields(LogRow)] == list(LOG_COLUMNS)
    return ChamberLog(header, rows)
