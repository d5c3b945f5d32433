"""Output files: nothing a user made is overwritten without ``--force``, and every output is checked first.

Every command that writes files names all of them to ``check_outputs`` before it writes any (or does
any long work): a missing directory, a directory where a file goes (or a file where a directory goes),
an output that is also an input, or an existing file without ``--force`` is a one-line
``OutputFileError`` (exit 73) that says what the existing file is, read from its content
(``describe``): a capture's provenance sidecar, a fitted model, a truth file...  So a run never stops
half-way with some outputs written and others refused.

A raw capture (``is_capture``) is the one record of a run that cannot be made again: only a new capture
(``record``, ``simulate``) may replace it, with ``--force``.  Any other output on a capture's path (a
model, a CSV, a sidecar, a report) is a one-line ``UsageError`` (exit 64), ``--force`` or not.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path

import yaml

from ..errors import OutputFileError, UsageError
from ..protocol import decode_bytes
from ..protocol.wire import SYNC
from .bounded import read_head
from .kinds import (
    ADAPT_STATE_FORMAT,
    COMPENSATE_PROVENANCE_FORMAT,
    MODEL_FORMAT,
    PROVENANCE_FORMAT,
    ROW_COLUMNS_FIRST,
    TRUTH_HEADER,
)

_SNIFF_BYTES = 1 << 20
#: How much of a file ``is_capture`` decodes: a capture holds frames from its first bytes on.
_CAPTURE_HEAD_BYTES = 64 * 1024


def _kinds() -> tuple[tuple[tuple[str, str], ...], dict[str, str]]:
    """(the first line of each kind of text file the project writes, its name), and the ``format`` tags of
    its YAML files -> their names ({capture}: a sidecar's capture)."""
    text = ((TRUTH_HEADER, "a simulator truth file"), (",".join(ROW_COLUMNS_FIRST), "a compensate CSV"))
    tags = {
        PROVENANCE_FORMAT: "a capture's provenance sidecar (of {capture})",
        MODEL_FORMAT: "a fitted model",
        ADAPT_STATE_FORMAT: "an adaptation state",
        COMPENSATE_PROVENANCE_FORMAT: "a compensate CSV's provenance sidecar (of {csv})",
    }
    return text, tags


def _names_capture(sidecar: Path, capture: Path) -> bool:
    """Whether ``sidecar`` is a capture's provenance sidecar (its ``format`` tag) naming ``capture``."""
    head = None if sidecar == capture else read_head(sidecar, _SNIFF_BYTES + 1)
    if head is None or len(head) > _SNIFF_BYTES:
        return False
    try:
        doc = yaml.safe_load(head.decode("utf-8"))
    except (UnicodeDecodeError, yaml.YAMLError):
        return False
    return isinstance(doc, dict) and doc.get("format") == PROVENANCE_FORMAT and doc.get("capture") == capture.name


def is_capture(path: str | Path) -> bool:
    """Whether ``path`` is a raw capture: a file whose first 64 kB decode to at least one protocol v1 frame
    (checksum verified), or one that a capture's provenance sidecar beside it names (``NAME.yaml``, or
    ``STEM.yaml`` from before: a capture of another frame format always has one, which records the device
    settings it is read with; an interrupted recording too, whatever its bytes)."""
    path = Path(path)
    if not path.is_file():
        return False
    if any(_names_capture(side, path) for side in (path.with_name(path.name + ".yaml"), path.with_suffix(".yaml"))):
        return True
    head = read_head(path, _CAPTURE_HEAD_BYTES)
    if head is None:
        return False
    counters = decode_bytes(head).counters
    return counters.sample_frames + counters.identity_frames > 0


def refuse_captures(paths: Iterable[str | Path]) -> None:
    """A one-line ``UsageError`` (exit 64) for the first of ``paths`` that is a raw capture (``is_capture``):
    outputs of another kind never replace one, ``--force`` or not."""
    for path in map(Path, paths):
        if is_capture(path):
            raise UsageError(
                f"{path}: is a raw capture; no output of another kind replaces one, --force or not (give another name)"
            )


def describe(path: str | Path) -> str:
    """What an existing ``path`` is, by its content: "a directory", "a capture", "a fitted model"..."""
    path = Path(path)
    if path.is_dir():
        return "a directory"
    if path.exists() and not path.is_file():  # never opened: a FIFO would hold the open, a device never end
        return "not a regular file"
    head = read_head(path, _SNIFF_BYTES + 1)
    if head is None:
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
            return yaml_kinds[doc["format"]].format(
                capture=doc.get("capture", "a capture"), csv=doc.get("csv", "a compensate CSV")
            )
    if head.startswith(SYNC) or (path.suffix == ".bin" and head) or is_capture(path):  # garbage may come first
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
    captures: Iterable[str | Path] = (),
) -> None:
    """Check every output of a command before it writes any; a problem is a one-line ``OutputFileError``.

    ``files``: files the command creates or replaces.  ``directories``: folders it writes files into: a
    folder may exist (it is created otherwise; its parent must exist), and without ``force`` it must be
    empty (a report never mixes with other files).  An output that is one of ``inputs`` is refused even
    with ``force``.  ``captures``: those of ``files`` that are new captures (``record``, ``simulate``): they
    alone may replace a raw capture (with ``force``); any other file on a capture's path is a ``UsageError``
    whatever ``force`` says (``refuse_captures``).
    """
    inputs = [Path(p) for p in inputs]
    new_captures = [Path(p) for p in captures]
    for path in map(Path, files):
        for source in inputs:
            if _same_file(path, source):
                raise OutputFileError(f"{path}: is also an input of this command; refusing to overwrite it")
        if path not in new_captures:
            refuse_captures([path])
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
