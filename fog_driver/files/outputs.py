"""Output files: nothing a user made is overwritten without ``--force``, and every output is checked first.

Every command that writes files names all of them to ``check_outputs`` before it writes any (or does
any long work): a missing directory, a directory where a file goes (or a file where a directory goes),
an output that is also an input, or an existing file without ``--force`` is a one-line
``OutputFileError`` (exit 73) that says what the existing file is, read from its content
(``describe``): a capture's provenance sidecar, a fitted model, a truth file...  So a run never stops
half-way with some outputs written and others refused.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path

import yaml

from ..errors import OutputFileError
from ..protocol.wire import SYNC
from .kinds import ADAPT_STATE_FORMAT, MODEL_FORMAT, PROVENANCE_FORMAT, ROW_COLUMNS_FIRST, TRUTH_HEADER

_SNIFF_BYTES = 1 << 20


def _kinds() -> tuple[tuple[tuple[str, str], ...], dict[str, str]]:
    """(the first line of each kind of text file the project writes, its name), and the ``format`` tags of
    its YAML files -> their names ({capture}: a sidecar's capture)."""
    text = ((TRUTH_HEADER, "a simulator truth file"), (",".join(ROW_COLUMNS_FIRST), "a compensate CSV"))
    tags = {
        PROVENANCE_FORMAT: "a capture's provenance sidecar (of {capture})",
        MODEL_FORMAT: "a fitted model",
        ADAPT_STATE_FORMAT: "an adaptation state",
    }
    return text, tags


def describe(path: str | Path) -> str:
    """What an existing ``path`` is, by its content: "a directory", "a capture", "a fitted model"..."""
    path = Path(path)
    if path.is_dir():
        return "a directory"
    try:
        with path.open("rb") as f:
            head = f.read(_SNIFF_BYTES + 1)
    except OSError:
        return "a file"
    text_kinds, yaml_kinds = _kinds()
    for start, kind in text_kinds:
        if head.startswith(start.encode()):
            return kind
    if len(head) <= _SNIFF_BYTES:
        try:
            doc = yaml.safe_load(head.decode("utf-8"))
        except (UnicodeDecodeError, yaml.YAMLError):
            doc = None
        if isinstance(doc, dict) and doc.get("format") in yaml_kinds:
            return yaml_kinds[doc["format"]].format(capture=doc.get("capture", "a capture"))
    if head.startswith(SYNC) or (path.suffix == ".bin" and head):  # raw bytes: garbage may come first
        return "a capture"
    return "a file" if head else "an empty file"


def _same_file(a: Path, b: Path) -> bool:
    try:
        return a.exists() and b.exists() and os.path.samefile(a, b)
    except OSError:
        return False


def _check_parent(path: Path) -> None:
    parent = path.parent
    if not parent.exists():
        raise OutputFileError(f"{path}: no such directory {parent}")
    if not parent.is_dir():
        raise OutputFileError(f"{path}: {parent} is {describe(parent)}, not a directory")


def check_outputs(
    files: Iterable[str | Path] = (),
    directories: Iterable[str | Path] = (),
    *,
    force: bool = False,
    inputs: Iterable[str | Path] = (),
) -> None:
    """Check every output of a command before it writes any; a problem is a one-line ``OutputFileError``.

    ``files``: files the command creates or replaces.  ``directories``: folders it writes files into: a
    folder may exist (it is created otherwise; its parent must exist), and without ``force`` it must be
    empty (a report never mixes with other files).  An output that is one of ``inputs`` is refused even
    with ``force``.
    """
    inputs = [Path(p) for p in inputs]
    for path in map(Path, files):
        for source in inputs:
            if _same_file(path, source):
                raise OutputFileError(f"{path}: is also an input of this command; refusing to overwrite it")
        if path.is_dir():
            raise OutputFileError(f"{path}: is a directory; give a file name")
        _check_parent(path)
        if (path.exists() or path.is_symlink()) and not force:
            raise OutputFileError(f"{path}: exists and is {describe(path)}; refusing to overwrite (use --force)")
    for folder in map(Path, directories):
        if not folder.exists():
            _check_parent(folder)
            continue
        if not folder.is_dir():
            raise OutputFileError(f"{folder}: exists and is {describe(folder)}, not a directory")
        if force:
            continue
        try:
            present = sorted(p.name for p in folder.iterdir())
        except OSError as exc:
            raise OutputFileError(f"{folder}: cannot list: {exc.strerror or exc}") from None
        if present:
            shown = ", ".join(present[:3]) + (", ..." if len(present) > 3 else "")
            raise OutputFileError(f"{folder}: exists and is not empty ({shown}); refusing to overwrite (use --force)")


def write_error(path: str | Path, what: str, exc: OSError) -> OutputFileError:
    """The one-line error for a failed write of ``what`` to ``path`` (a full disk, a vanished directory)."""
    return OutputFileError(f"{path}: cannot write {what}: {exc.strerror or exc}")
