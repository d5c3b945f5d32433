"""Comparing outputs with golden files: floats to a stated tolerance, everything else exactly.

The project promises two things (docs/explanation/determinism.md, "Same numbers on every machine"):

* on one machine, bit-identical: live == offline replay, ``step`` == ``run``.  Those tests use ``==``;
* on any machine, floats within ``REL_TOL`` of each other (or ``ABS_TOL`` in the field's own unit, for
  values near zero), and everything else exactly: integers, strings, flags, keys and their order,
  classes, the number of lines and their order.  Golden files are compared that way, here.

A mismatch fails the test with one line naming the file, the line, the field and both values; a
golden file that is missing or malformed fails it with one line too, never deep inside a parser.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable
from pathlib import Path

import pytest

#: The promise across machines (and numpy versions): relative, and absolute near zero.
REL_TOL = 1e-12
ABS_TOL = 1e-12
REGENERATE = ".venv/bin/python tests/data/make_goldens.py"


class Mismatch(Exception):
    """The first difference: ``where`` (a field path) and a sentence saying how they differ."""


def floats_agree(a: float, b: float, rel_tol: float = REL_TOL, abs_tol: float = ABS_TOL) -> bool:
    if math.isnan(a) or math.isnan(b):
        return math.isnan(a) and math.isnan(b)
    return a == b or math.isclose(a, b, rel_tol=rel_tol, abs_tol=abs_tol)


def compare_values(got, want, where: str = "", rel_tol: float = REL_TOL, abs_tol: float = ABS_TOL) -> None:
    """Raise ``Mismatch`` at the first difference between two parsed JSON values."""
    if type(got) is not type(want):  # 1 and 1.0, true and 1 differ: JSON writes them differently
        raise Mismatch(f"{where or 'value'}: got {got!r}, golden {want!r} (not the same type)")
    if isinstance(want, dict):
        if list(got) != list(want):
            raise Mismatch(f"{where or 'object'}: keys {list(got)} != golden keys {list(want)}")
        for key in want:
            compare_values(got[key], want[key], f"{where}.{key}" if where else key, rel_tol, abs_tol)
    elif isinstance(want, list):
        if len(got) != len(want):
            raise Mismatch(f"{where or 'list'}: {len(got)} items, golden {len(want)}: {got!r} != {want!r}")
        for i, (g, w) in enumerate(zip(got, want)):
            compare_values(g, w, f"{where}[{i}]", rel_tol, abs_tol)
    elif isinstance(want, float):
        if not floats_agree(got, want, rel_tol, abs_tol):
            rel = abs(got - want) / max(abs(got), abs(want))
            raise Mismatch(f"{where}: got {got!r}, golden {want!r} (relative difference {rel:.1e} > {rel_tol:g})")
    elif got != want:
        raise Mismatch(f"{where or 'value'}: got {got!r}, golden {want!r}")


def _fail(message: str):
    pytest.fail(message, pytrace=False)


def read_golden_lines(path: Path) -> list[str]:
    """The golden file's lines; a missing, unreadable or empty file fails the test in one line."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        _fail(f"golden file {path} is missing: regenerate it on purpose with `{REGENERATE}`")
    except (OSError, UnicodeDecodeError) as exc:
        _fail(f"golden file {path} cannot be read: {exc}")
    lines = text.splitlines()
    if not lines:
        _fail(f"golden file {path} is empty: regenerate it on purpose with `{REGENERATE}`")
    return lines


def parse_ndjson(lines: Iterable[str | bytes], what: str) -> list[dict]:
    """One JSON object per line; anything else fails the test in one line naming ``what`` and the line."""
    out = []
    for n, line in enumerate(lines, 1):
        try:
            obj = json.loads(line)
        except (ValueError, UnicodeDecodeError) as exc:
            _fail(f"{what} line {n}: not JSON ({exc}): {line[:80]!r}")
        if not isinstance(obj, dict):
            _fail(f"{what} line {n}: not a JSON object: {line[:80]!r}")
        out.append(obj)
    return out


def first_difference(got: list, want: list, rel_tol: float = REL_TOL, abs_tol: float = ABS_TOL) -> str | None:
    """None when the records agree (floats within the tolerance, the rest exactly), else one line."""
    for n, (g, w) in enumerate(zip(got, want), 1):
        try:
            compare_values(g, w, "", rel_tol, abs_tol)
        except Mismatch as exc:
            return f"line {n}, {exc}"
    if len(got) != len(want):
        return f"{len(got)} lines, golden {len(want)} (the first {min(len(got), len(want))} agree)"
    return None


def assert_matches_ndjson(got_lines: Iterable[str | bytes], golden: Path, rel_tol: float = REL_TOL) -> None:
    """``got_lines`` (NDJSON) agree with the golden file within the tolerance, else one-line failure."""
    want = parse_ndjson(read_golden_lines(golden), f"golden file {golden}")
    got = parse_ndjson(got_lines, "output")
    difference = first_difference(got, want, rel_tol)
    if difference is not None:
        _fail(f"{Path(golden).name} differs: {difference} (regenerate only on purpose: `{REGENERATE}`)")


def parse_csv(lines: Iterable[str], what: str) -> list[dict]:
    """Comment lines (``#``) skipped, a header, then rows of cells: a number (as a float: ``%g`` writes
    20.00000004 as ``20``, and 20.00000005 as ``20.0000001``) or else text."""
    rows = [line for line in lines if line and not line.startswith("#")]
    if not rows:
        _fail(f"{what}: no header")
    header = rows[0].split(",")
    out = []
    for n, line in enumerate(rows[1:], 2):
        cells = line.split(",")
        if len(cells) != len(header):
            _fail(f"{what} row {n}: {len(cells)} cells, the header has {len(header)}")
        out.append({key: _number(cell) for key, cell in zip(header, cells)})
    return out


def _number(cell: str) -> float | str:
    try:
        return float(cell)
    except ValueError:
        return cell


def assert_matches_csv(got_text: str, golden: Path, rel_tol: float) -> None:
    """A CSV (e.g. a truth file written with 9 significant digits, ``rel_tol`` 1e-8) against its golden."""
    want = parse_csv(read_golden_lines(golden), f"golden file {golden}")
    got = parse_csv(got_text.splitlines(), "output")
    difference = first_difference(got, want, rel_tol)
    if difference is not None:
        _fail(f"{Path(golden).name} differs: {difference}")
