"""The store of kept models beside the raw captures: ``models/<sha256>.yaml``, and the index that prunes them.

The daemon keeps a copy of each model it compensates with (``KeptModels.keep``), named by its SHA-256
(``captures.kept_model_path``: once per content, atomic), so that ``compensate`` can replay a reload from the
captures alone.  A copy is needed while a capture that names it is left in the directory; the retention limits
(``RotatingCapture.prune``) delete captures, then ``KeptModels.prune`` deletes the copies none of the captures
left names.

Which captures name a model is in the index, ``models/index.json`` (written atomically at each change): for each
kept model its ``sha256``, ``bytes``, ``kept_utc`` (when the copy was written) and ``captures``, per capture
prefix the ranges of capture numbers (``<prefix>-<nnnnnn>-...``) written while it was in use.  The rule it
follows: a model is in use from its ``keep`` (the file being written then names it: the daemon notes the reload
there) until the next model's, so it names the file open at that time (or, when none is open, the next one to
open: the note waits for it) and every file opened while it is in use.  A prune thus lists the directory, never
reads a sidecar.

An index that is missing (a directory from before it, or a copy kept by an older version), that cannot be read
or parsed, or that does not list every copy in ``models/`` is rebuilt from the files: each numbered capture's
sidecar names the models whose SHA-256 its text holds.  That costs one log line (``kept_models_index_rebuilt``)
and is never fatal; an index that cannot be written is logged (``kept_models_index_failed``) and the store goes
on with what it knows.  The model in use is never pruned.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import hashlib
import json
import re
from pathlib import Path
from typing import Any

import structlog

from ..errors import FogDriverError, OutputFileError
from ..files.bounded import read_regular
from ..files.stamps import utc_now_iso
from ..files.yamlio import MAX_YAML_BYTES, write_text
from ..samples.captures import KEPT_MODELS_DIR, find_sidecar, kept_model_path

log = structlog.get_logger("fog_driver.daemon")

#: The index's name in ``models/`` (not ``*.yaml``: never taken for a kept model).
INDEX_NAME = "index.json"
INDEX_FORMAT = "fog-driver-kept-models"
INDEX_VERSION = 1
#: An index larger than this is not read (rebuilt instead).
MAX_INDEX_BYTES = 4 * 2**20
#: The digits of a capture's number, at least (``<prefix>-<nnnnnn>-<UTC>.bin``).
CAPTURE_NUMBER_DIGITS = 6
_CAPTURE_NAME = re.compile(rf"^(.+)-(\d{{{CAPTURE_NUMBER_DIGITS},}})-[0-9TZ]+\.bin$")
_SHA256 = re.compile(r"^[0-9a-f]{64}$")


def numbered_captures(directory: Path) -> dict[str, dict[int, Path]]:
    """The ``<prefix>-<nnnnnn>-<UTC>.bin`` captures (regular files) in ``directory``: prefix -> number -> path."""
    found: dict[str, dict[int, Path]] = {}
    for path in directory.iterdir():
        match = _CAPTURE_NAME.match(path.name)
        if match and path.is_file():
            found.setdefault(match.group(1), {})[int(match.group(2))] = path
    return found


def capture_number(path: Path) -> tuple[str, int]:
    """``(prefix, number)`` of a numbered capture's path."""
    match = _CAPTURE_NAME.match(path.name)
    if match is None:
        raise ValueError(f"{path.name}: not a numbered capture's name")
    return match.group(1), int(match.group(2))


class KeptModels:
    """The kept models of one capture directory, for the captures of ``prefix`` (see the module docstring).

    Not thread-safe: the capture's owner (the sink's thread) calls it.
    """

    def __init__(self, directory: str | Path, prefix: str) -> None:
        self.directory = Path(directory)
        self.models_dir = self.directory / KEPT_MODELS_DIR
        self.index_path = self.models_dir / INDEX_NAME
        self.prefix = prefix
        self.in_use: str | None = None  #: the SHA-256 of the model kept last (never pruned)
        self._open_number: int | None = None  # the capture of ``prefix`` being written, if any
        self._waiting: set[str] = set()  # kept while no capture was open: the next one names them (its events)

    def keep(self, sha256: str, data: bytes) -> Path:
        """Keep a copy of the model file ``data`` (of SHA-256 ``sha256``) the daemon compensates with from here
        on, at ``kept_model_path`` (once per content; atomic), and index it as naming the capture being written
        (or the next one).  ``OutputFileError`` when the copy cannot be written; ``ValueError`` when ``data`` is
        not of ``sha256``."""
        if hashlib.sha256(data).hexdigest() != sha256:
            raise ValueError("the model's bytes are not those of its SHA-256")
        index = self._load()  # before the copy: a new copy is no sign of a lost index
        path = kept_model_path(self.directory / "capture.bin", sha256)
        if not path.exists():
            try:
                path.parent.mkdir(exist_ok=True)
            except OSError as exc:
                raise OutputFileError(f"{path.parent}: cannot keep the model: {exc.strerror or exc}") from None
            write_text(path, data, "the model's copy")
        self.in_use = sha256
        entry = index.setdefault(sha256, {"bytes": len(data), "kept_utc": utc_now_iso(), "captures": {}})
        if self._open_number is not None:
            _add_number(entry["captures"].setdefault(self.prefix, []), self._open_number)
        else:
            self._waiting.add(sha256)
        self._save(index)
        return path

    def capture_opened(self, path: Path) -> None:
        """A capture of this prefix opened: the model in use names it, and so do those kept since the last one
        closed."""
        self._open_number = capture_number(path)[1]
        naming, self._waiting = self._waiting | ({self.in_use} if self.in_use is not None else set()), set()
        if not naming:
            return
        index = self._load()
        for sha256 in naming:
            if sha256 in index:
                _add_number(index[sha256]["captures"].setdefault(self.prefix, []), self._open_number)
        self._save(index)

    def capture_closed(self) -> None:
        """The capture being written closed: the next model kept names the next one to open."""
        self._open_number = None

    def prune(self) -> list[Path]:
        """Delete the kept models no capture left in the directory names (by the index), but the one in use;
        returns what was deleted.  A copy that cannot be deleted is logged and left."""
        if not self.models_dir.is_dir():
            return []
        index = self._load()
        try:
            captures = numbered_captures(self.directory)
        except OSError as exc:  # what the captures name is not known: nothing goes
            log.error("model_copy_prune_failed", model=str(self.models_dir), reason=exc.strerror or str(exc))
            return []
        deleted = []
        for sha256 in sorted(index):
            if sha256 == self.in_use or _named(index[sha256]["captures"], captures):
                continue
            path = kept_model_path(self.directory / "capture.bin", sha256)
            try:
                path.unlink(missing_ok=True)
            except OSError as exc:
                log.error("model_copy_prune_failed", model=str(path), reason=exc.strerror or str(exc))
                continue
            del index[sha256]
            deleted.append(path)
            log.info("model_copy_pruned", model=str(path))
        if deleted:
            self._save(index)
        return deleted

    # -- the index -------------------------------------------------------------------------------

    def _copies(self) -> set[str]:
        """The SHA-256 of every copy in ``models/`` (a file not named by a SHA-256 is none: it is left alone)."""
        if not self.models_dir.is_dir():
            return set()
        return {path.stem for path in self.models_dir.glob("*.yaml") if _SHA256.match(path.stem)}

    def _load(self) -> dict[str, dict[str, Any]]:
        """The index (sha256 -> entry) of the copies in ``models/``: read, or rebuilt when it cannot serve."""
        copies = self._copies()
        problem = None
        try:
            index = _parse(read_regular(self.index_path, "kept models' index", MAX_INDEX_BYTES, missing_ok=True))
        except FogDriverError as exc:
            index, problem = None, str(exc)
        except ValueError as exc:
            index, problem = None, f"{self.index_path}: {exc}"
        if index is None and problem is None:
            if not copies:
                return {}
            problem = f"{self.index_path}: missing"
        elif index is not None and not copies <= set(index):
            problem = f"{self.index_path}: does not list {len(copies - set(index))} kept model(s)"
        if problem is not None:
            index = self._rebuild(copies)
            log.warning("kept_models_index_rebuilt", reason=problem, models=len(index))
            self._save(index)
        assert index is not None
        return {sha256: entry for sha256, entry in index.items() if sha256 in copies}

    def _rebuild(self, copies: set[str]) -> dict[str, dict[str, Any]]:
        """The index from the files: each numbered capture's sidecar names the copies whose SHA-256 its text holds
        (a sidecar that cannot be read names none)."""
        index: dict[str, dict[str, Any]] = {}
        for sha256 in copies:
            path = kept_model_path(self.directory / "capture.bin", sha256)
            with contextlib.suppress(OSError):
                st = path.stat()
                index[sha256] = {"bytes": st.st_size, "kept_utc": _utc(st.st_mtime), "captures": {}}
        try:
            captures = numbered_captures(self.directory)
        except OSError:  # none to read: a prune cannot list them either, so it deletes nothing
            captures = {}
        for prefix, numbered in captures.items():
            for number in sorted(numbered):
                text = ""
                with contextlib.suppress(FogDriverError, UnicodeDecodeError):
                    sidecar = find_sidecar(numbered[number])  # (a FIFO or a huge file: never waited on, never read)
                    if sidecar is not None:
                        text = (read_regular(sidecar, "sidecar", MAX_YAML_BYTES) or b"").decode("utf-8")
                for sha256, entry in index.items():
                    if sha256 in text:
                        _add_number(entry["captures"].setdefault(prefix, []), number)
        return index

    def _save(self, index: dict[str, dict[str, Any]]) -> None:
        doc = {"format": INDEX_FORMAT, "version": INDEX_VERSION, "models": index}
        try:
            write_text(self.index_path, json.dumps(doc, sort_keys=True) + "\n", "the kept models' index")
        except OutputFileError as exc:  # the copies stay; the next load rebuilds what is missing
            log.error("kept_models_index_failed", reason=str(exc))


def _parse(data: bytes | None) -> dict[str, dict[str, Any]] | None:
    """The index's ``models`` (None when there is no index); ``ValueError`` when it is not a valid index."""
    if data is None:
        return None
    try:
        doc = json.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"not a kept models' index: {exc}") from None
    if not isinstance(doc, dict) or doc.get("format") != INDEX_FORMAT or doc.get("version") != INDEX_VERSION:
        raise ValueError("not a kept models' index of this version")
    models = doc.get("models")
    if not isinstance(models, dict):
        raise ValueError("its models are not a mapping")
    for sha256, entry in models.items():
        if not (_SHA256.match(sha256) and isinstance(entry, dict) and _valid_captures(entry.get("captures"))):
            raise ValueError(f"its entry {str(sha256)[:70]!r} is not a kept model's")
    return models


def _valid_captures(captures: Any) -> bool:
    """``{prefix: [[first, last], ...]}`` with integer numbers, ``first <= last``."""
    return isinstance(captures, dict) and all(
        isinstance(prefix, str)
        and isinstance(ranges, list)
        and all(
            isinstance(r, list)
            and len(r) == 2
            and all(isinstance(n, int) and not isinstance(n, bool) for n in r)
            and r[0] <= r[1]
            for r in ranges
        )
        for prefix, ranges in captures.items()
    )


def _add_number(ranges: list[list[int]], number: int) -> None:
    """Add ``number`` to ``ranges`` (``[first, last]`` pairs, newest last): the last one grows, or a new one."""
    if ranges and ranges[-1][0] <= number <= ranges[-1][1]:
        return
    if ranges and number == ranges[-1][1] + 1:
        ranges[-1][1] = number
    else:
        ranges.append([number, number])


def _named(ranges_by_prefix: dict[str, list[list[int]]], captures: dict[str, dict[int, Path]]) -> bool:
    """Whether a capture left in the directory has a number in one of a model's ranges."""
    for prefix, ranges in ranges_by_prefix.items():
        numbers = captures.get(prefix, {})
        if any(first <= number <= last for number in numbers for first, last in ranges):
            return True
    return False


def _utc(timestamp: float) -> str:
    """``timestamp`` (seconds since the epoch) as ``utc_now_iso`` writes a time."""
    stamp = _dt.datetime.fromtimestamp(timestamp, _dt.UTC)
    return stamp.isoformat(timespec="milliseconds").replace("+00:00", "Z")


__all__ = ["INDEX_NAME", "KeptModels", "capture_number", "numbered_captures"]
