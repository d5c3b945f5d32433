"""The dwell of the turntable and the table log that lists them: one type and one reader for every layer.

A dwell (``Dwell``): the table stood from ``t_start_s`` to ``t_end_s`` (device time, seconds from the capture's
first sample) at ``angle_deg``, cumulative (360 is not 0); with ``angle_end_deg`` it moved within the dwell (a
creep), linearly to that angle.  The lab's motion plan makes them (``lab.motion.MotionPlan.dwells``), a
station's table log lists them (``read_table_log``), the daemon's ``?TABLE`` gives one live, and the table-angle
law (``compensation.table``) and ``evaluate``'s positioning table measure the gyro over them
(``compensation.dwell``).

A table angle, wherever it comes from (a table log, ``?TABLE``, a sidecar's table events or positioning stops), is
a number within +-``MAX_TABLE_ANGLE_DEG`` (``table_angle_deg``).

The table log (``TABLE_LOG_FORMAT`` holds the same text for help and error texts)::

    # turntable reference for chamber-run-07.bin   <- '#' starts a comment (whole line or the rest of one)
    t_start_s,t_end_s,angle_deg                    <- the header, these three names (any order; other columns ignored)
    1500.0,1560.0,0                                <- one dwell per row: start, end (device time, s from
    1563.8,1623.8,36                                  the capture's first sample) and the table's angle,
    ...                                               cumulative, in degrees (360 is not 0)

    Rows are in time order: t_end_s > t_start_s and each t_start_s >= the previous row's t_end_s
    (``check_dwell_order``).  An optional column ``angle_end_deg`` gives the angle at the dwell's end.
    Angles within +-1e6 degrees (``MAX_TABLE_ANGLE_DEG``, the bound ``?TABLE`` applies).  UTF-8 (a BOM is
    allowed), lines ended by LF, CRLF or CR, at most 1 MB, at least one row.  Every problem is a one-line
    ``InputFileError`` naming the file and the line.
"""

from __future__ import annotations

import csv
import math
import re
from dataclasses import dataclass
from pathlib import Path

from .errors import InputFileError
from .files.bounded import read_regular

__all__ = [
    "ANGLE_END_COLUMN",
    "MAX_TABLE_ANGLE_DEG",
    "MAX_TABLE_LOG_BYTES",
    "TABLE_LOG_COLUMNS",
    "TABLE_LOG_FORMAT",
    "Dwell",
    "check_dwell_order",
    "number_within",
    "read_table_log",
    "table_angle_deg",
]

#: The largest table angle a dwell may give, degrees either sign: live (``?TABLE``), in a table log and in a
#: sidecar's table events alike (``table_angle_deg``).  Cumulative angles of a table that turned for years stay
#: far below; 1e308 would overflow the law's arcseconds.
MAX_TABLE_ANGLE_DEG = 1e6
MAX_TABLE_LOG_BYTES = 1_000_000
#: The columns every table log has (its header names them, in any order).
TABLE_LOG_COLUMNS = ("t_start_s", "t_end_s", "angle_deg")
#: Optional: where the table's angle ended when it moved within the dwell (a creep the log saw).
ANGLE_END_COLUMN = "angle_end_deg"
#: What ends a line of a table log: LF, CRLF, or CR alone (an old Mac's).
LINE_END = re.compile(r"\r\n|\r|\n")

TABLE_LOG_FORMAT = """\
Turntable reference CSV: one dwell (the table still) per row, in time order.
  header    t_start_s,t_end_s,angle_deg   (any order; other columns are ignored)
  t_start_s when the dwell starts, t_end_s when it ends: device time, seconds from the
            capture's first sample; t_end_s > t_start_s >= the previous row's t_end_s
  angle_deg the table's cumulative angle during the dwell, degrees (360 is not 0), within +-1e6
  angle_end_deg  (optional column) the angle at the dwell's end, when the table moved within it:
            the dwell's angle is then taken as changing linearly from angle_deg to angle_end_deg
  '#' starts a comment (a whole line or the rest of one); blank lines are ignored;
  UTF-8, at most 1 MB, at least one row.
Example:
  # chamber run 07, -40 degC
  t_start_s,t_end_s,angle_deg
  1500.0,1560.0,0
  1563.8,1623.8,36
"""


@dataclass(frozen=True)
class Dwell:
    """The table stood from ``t_start_s`` to ``t_end_s`` at ``angle_deg`` (cumulative); with ``angle_end_deg``
    it moved within the dwell, linearly to that angle (None: it did not)."""

    t_start_s: float
    t_end_s: float
    angle_deg: float
    angle_end_deg: float | None = None


def number_within(value: object, bound: float) -> bool:
    """Whether ``value`` is a number (an int or a float, not a bool), finite and within +-``bound``: the check of
    a number read from JSON or YAML, whose integers may have any number of digits (one too large for a float is
    out of bounds, and raises nothing)."""
    if not isinstance(value, (int, float)) or isinstance(value, bool):
        return False
    try:
        return math.isfinite(value) and abs(value) <= bound
    except OverflowError:  # an int too large for a float
        return False


def table_angle_deg(value: object, name: str = "angle_deg") -> float:
    """``value`` as a dwell's table angle: a number (not a bool), finite and within +-``MAX_TABLE_ANGLE_DEG``
    (``number_within``); else a one-line ``ValueError`` naming ``name``.  The one check of a table angle,
    wherever it comes from."""
    if not number_within(value, MAX_TABLE_ANGLE_DEG):
        try:
            shown = repr(value)
        except ValueError:  # an int of more digits than Python converts
            shown = "an integer of thousands of digits"
        shown = shown if len(shown) <= 40 else shown[:40] + "..."
        raise ValueError(f"{name} must be a number within +-{MAX_TABLE_ANGLE_DEG:g} degrees, got {shown}")
    return float(value)  # type: ignore[arg-type]  # a number


def check_dwell_order(dwells: list[Dwell], start: float, end: float, where: str) -> None:
    """A one-line ``InputFileError`` at ``where`` unless a dwell from ``start`` to ``end`` may follow ``dwells``:
    ``start`` not negative (device time from the first sample), ``end`` after it, ``start`` not before the last
    dwell's end."""
    if start < 0:
        raise InputFileError(
            f"{where}: t_start_s must not be negative (device time from the first sample), got {start:g}"
        )
    if not end > start:
        raise InputFileError(f"{where}: t_end_s ({end:g}) must be after t_start_s ({start:g})")
    if dwells and start < dwells[-1].t_end_s:
        raise InputFileError(
            f"{where}: times must increase: t_start_s {start:g} is before the previous "
            f"dwell's t_end_s {dwells[-1].t_end_s:g}"
        )


def _finite(text: str, name: str, where: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise InputFileError(f"{where}: {name} is not a number: {text.strip()!r}") from None
    if not math.isfinite(value):
        raise InputFileError(f"{where}: {name} must be finite, got {text.strip()!r}")
    return value


def _angle(text: str, name: str, where: str) -> float:
    """A table angle of a row: finite, within the bound ``?TABLE`` applies (``table_angle_deg``)."""
    try:
        return table_angle_deg(_finite(text, name, where), name)
    except ValueError as exc:
        raise InputFileError(f"{where}: {exc} (the bound ?TABLE applies)") from None


def read_table_log(path: str | Path) -> list[Dwell]:
    """A station's table log, its dwells in time order (format: the module docstring, ``TABLE_LOG_FORMAT``)."""
    path = Path(path)
    over = f"reference CSV over the limit of {MAX_TABLE_LOG_BYTES:,} bytes"
    data = read_regular(path, "reference CSV", MAX_TABLE_LOG_BYTES, too_large=over) or b""
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError:
        raise InputFileError(f"{path}: reference CSV is not UTF-8 text") from None
    header: list[str] | None = None
    index: dict[str, int] = {}
    dwells: list[Dwell] = []
    for lineno, line in enumerate(LINE_END.split(text), start=1):  # \n, \r\n or \r alone end a line
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        where = f"{path}:{lineno}"
        try:
            cells = [c.strip() for c in next(csv.reader([line]))]
        except csv.Error as exc:  # a field over csv's limit, a stray quote
            raise InputFileError(f"{where}: not a CSV row: {exc}") from None
        if header is None:
            header = cells
            missing = [c for c in TABLE_LOG_COLUMNS if c not in header]
            if missing:
                raise InputFileError(
                    f"{where}: missing column{'s' if len(missing) > 1 else ''} "
                    f"{', '.join(missing)} (the header must name {','.join(TABLE_LOG_COLUMNS)})"
                )
            index = {c: header.index(c) for c in (*TABLE_LOG_COLUMNS, ANGLE_END_COLUMN) if c in header}
            continue
        if len(cells) != len(header):
            raise InputFileError(f"{where}: {len(cells)} fields, the header has {len(header)}")
        start, end = (_finite(cells[index[c]], c, where) for c in TABLE_LOG_COLUMNS[:2])
        angle = _angle(cells[index["angle_deg"]], "angle_deg", where)
        check_dwell_order(dwells, start, end, where)
        angle_end = (
            _angle(cells[index[ANGLE_END_COLUMN]], ANGLE_END_COLUMN, where) if ANGLE_END_COLUMN in index else None
        )
        dwells.append(Dwell(start, end, angle, angle_end))
    if header is None:
        raise InputFileError(f"{path}: reference CSV is empty (expected the header {','.join(TABLE_LOG_COLUMNS)})")
    if not dwells:
        raise InputFileError(f"{path}: reference CSV has a header but no stops")
    return dwells
