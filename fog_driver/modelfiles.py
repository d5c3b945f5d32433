"""Model files and adaptation state files: reading and writing them (YAML, safe loading only, never pickle;
written atomically), at the edge of the compensation layer, which works on their documents.

Everything needed to reproduce the outputs exactly on another machine is in a model file as plain
numbers (floats written by ``yaml.safe_dump`` round-trip exactly): the feature settings, the input
normalization, and every matrix.  Also the schema version, the instrument serial the model was fitted
for, and provenance (the captures' SHA-256s, the fit configuration and metrics, the date).  A model
fitted for another serial is refused unless forced (``compensation.binding``).

An adaptation state file holds ``adapt.OnlineReadout.state_document`` (with the static detector's and,
from a compensator, the pipeline's state): a run saved and restored continues bit for bit.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import yaml

from .compensation.adapt import ADAPT_STATE_FORMAT, ADAPT_STATE_SCHEMA_VERSION, OnlineReadout, StaticDetector
from .compensation.model import MODEL_FORMAT, MODEL_SCHEMA_VERSION, ModelFile, model_file_from_doc
from .compensation.pipeline import Compensator
from .errors import InputFileError, OutputFileError
from .files.bounded import not_regular_kind, read_head
from .files.outputs import describe
from .files.yamlio import (
    check_tagged,
    parse_yaml,
    read_tagged_yaml,
    read_yaml_text,
    write_text,
    write_yaml,
    yaml_text,
)

# -- model files ---------------------------------------------------------------------------------------

#: A model file's first and last lines (YAML comments: the document is ``to_doc``'s, whatever reads it).  A
#: file that starts with the first and does not end with the last was cut short (a copy interrupted, a disk
#: full): ``load_model`` says so, wherever the cut is.
MODEL_FIRST_LINE = "# fog_driver drift model; a file without its last line (below) is incomplete"
MODEL_LAST_LINE = "# end of the model file"
#: The top-level keys ``ModelFile.to_doc`` writes, in order (``provenance`` last, in every version); those of
#: ``MODEL_OPTIONAL_KEYS`` only when the model has them, and files made before the first and last lines existed
#: may also lack those of ``MODEL_LATER_KEYS`` (they came later).
MODEL_KEYS = (
    "format",
    "schema_version",
    "kind",
    "instrument_serial",
    "created_utc",
    "fog_driver_version",
    "model_rate_hz",
    "features",
    "normalizer",
    "model",
    "domain",
    "substitution",
    "temperature_channels",
    "noise_1min_dph",
    "uncertainty",
    "provenance",
)
MODEL_OPTIONAL_KEYS = frozenset({"domain", "noise_1min_dph", "uncertainty"})
MODEL_LATER_KEYS = frozenset({"substitution", "temperature_channels"})


def model_text(model_file: ModelFile) -> str:
    """The text of a model file: ``MODEL_FIRST_LINE``, ``to_doc()`` as YAML, ``MODEL_LAST_LINE``."""
    return f"{MODEL_FIRST_LINE}\n{yaml_text(model_file.to_doc())}{MODEL_LAST_LINE}\n"


def save_model(path: str | Path, model_file: ModelFile) -> Path:
    """Write ``model_text(model_file)`` to ``path`` (atomically; ``OutputFileError`` on failure).

    The text is first read back with ``model_from_text``, the checks every reader applies (every number finite
    and within ``model_checks.MAX_MODEL_NUMBER``, the counts within what a model may hold): a model that would
    not load is not written (``InputFileError``: what the data made of it), so no file the daemon would refuse
    is ever saved."""
    text = model_text(model_file)
    try:
        model_from_text(text, path)
    except InputFileError as exc:
        reason = str(exc).removeprefix(f"{path}: ")
        raise InputFileError(f"{path} not written: the fitted model would not load ({reason})") from None
    return write_text(path, text, "model")


def load_model(path: str | Path) -> ModelFile:
    """Read and validate a model file; a truncated, corrupt or wrong-version file is a one-line ``InputFileError``.

    A file cut short says "model file truncated or incomplete: 'KEY' missing (it ends in or after 'LAST')"
    (``truncation``) before anything its missing part would make fail."""
    return model_from_text(read_yaml_text(path, "model file") or "", path)


def model_from_text(text: str, path: str | Path) -> ModelFile:
    """The model in ``text`` read from ``path``, with ``load_model``'s checks and one-line errors."""
    where = str(path)
    if not text.strip():
        raise InputFileError(f"{where}: the model file is empty")
    if _begins_as_written(text) and not _has_last_line(text):  # ours, cut short: no need to parse it
        raise InputFileError(f"{where}: {truncation(_top_level_keys(text), written_with_last_line=True)}")
    try:
        doc = parse_yaml(text, path, "model file", loader=ModelLoader)
    except AliasInModel as exc:
        raise InputFileError(f"{where}: corrupt model: {exc}") from None
    if isinstance(doc, dict) and doc.get("format") == MODEL_FORMAT and "provenance" not in doc:
        raise InputFileError(f"{where}: {truncation(list(doc), written_with_last_line=False)}")
    check_tagged(doc, path, "model file", MODEL_FORMAT, MODEL_SCHEMA_VERSION)
    return model_file_from_doc(doc, where)


class AliasInModel(Exception):
    """A YAML anchor or alias in a model file (``ModelLoader``)."""


class ModelLoader(yaml.SafeLoader):
    """The safe loader of model files, which also refuses every YAML anchor (``&a``) and alias (``*a``) as the
    composer meets it, before anything is built: the fit never writes one, and an alias lets a small file
    stand for a large document (10,000 candidates in 48 KB)."""

    def compose_node(self, parent: Any, index: Any) -> Any:
        event = self.peek_event()
        if isinstance(event, yaml.AliasEvent) or getattr(event, "anchor", None) is not None:
            what = "alias" if isinstance(event, yaml.AliasEvent) else "anchor"
            raise AliasInModel(
                f"a YAML {what} ({'*' if what == 'alias' else '&'}{event.anchor}) at line "
                f"{event.start_mark.line + 1}: a model file has none (the fit never writes one)"
            )
        return super().compose_node(parent, index)


#: A top-level key of a model file as ``yaml_text`` writes it: at the start of a line, then a colon.
_TOP_LEVEL_KEY = re.compile(r"^([A-Za-z_]\w*):", re.MULTILINE)


def _top_level_keys(text: str) -> list[str]:
    """The top-level keys of a model file's text as written (``key:`` at a line's start), in file order."""
    return _TOP_LEVEL_KEY.findall(text)


def _begins_as_written(text: str) -> bool:
    """The text starts with ``MODEL_FIRST_LINE`` (or is a start of it: cut inside it)."""
    first = MODEL_FIRST_LINE + "\n"
    return text.startswith(first) or first.startswith(text)


def _has_last_line(text: str) -> bool:
    """``MODEL_LAST_LINE`` is a whole line, and only blank or comment lines follow it (a note added by hand)."""
    at = text.rfind("\n" + MODEL_LAST_LINE + "\n")
    if at < 0:
        return False
    rest = text[at + len(MODEL_LAST_LINE) + 2 :]
    return all(not line.strip() or line.lstrip().startswith("#") for line in rest.splitlines())


def truncation(present: list[str], *, written_with_last_line: bool) -> str:
    """What a model file cut short lacks, given the top-level keys ``present`` (in file order): "model file
    truncated or incomplete: 'KEY' missing (it ends in or after 'LAST')", KEY the first key ``to_doc`` always
    writes after the last one present, LAST (files without the first and last lines, older ones, may lack
    those of ``MODEL_LATER_KEYS``: they are not named).  With every key there the cut is inside the last
    one's value (provenance) or in the last line.

    Which files are cut short: one that starts with ``MODEL_FIRST_LINE`` and lacks ``MODEL_LAST_LINE``, or one
    that names itself a model file (``format``) and lacks ``provenance``, the last key in every version.  A file
    written before the first and last lines existed and cut inside its ``provenance`` cannot be told from a
    whole one: it is read, with every number the model needs intact."""
    known = [k for k in present if k in MODEL_KEYS]
    if not known:
        return "model file truncated or incomplete: 'format' missing (it ends before its first key)"
    last = known[-1]
    maybe_absent = MODEL_OPTIONAL_KEYS if written_with_last_line else MODEL_OPTIONAL_KEYS | MODEL_LATER_KEYS
    after = MODEL_KEYS[MODEL_KEYS.index(last) + 1 :]
    missing = next((k for k in after if k not in present and k not in maybe_absent), None)
    what = f"the end of {last!r} and the line {MODEL_LAST_LINE!r}" if missing is None else repr(missing)
    return f"model file truncated or incomplete: {what} missing (it ends in or after {last!r})"


def read_model(path: str | Path) -> tuple[ModelFile, bytes]:
    """The model file at ``path`` and the bytes it was read from (the daemon keeps a copy of them beside its
    captures), from one bounded read (``read_yaml_text``): the model is the one those bytes hold, however the
    file changes meanwhile (valid UTF-8 encodes back to the bytes it was decoded from); one-line
    ``InputFileError``s."""
    text = read_yaml_text(path, "model file") or ""
    return model_from_text(text, path), text.encode("utf-8")


def model_bytes(model_file: ModelFile) -> bytes:
    """The bytes of a model given as an object (not read from a file): the text ``save_model`` writes."""
    return model_text(model_file).encode("utf-8")


# -- adaptation state files ----------------------------------------------------------------------------


def read_state_doc(path: str | Path) -> dict[str, Any]:
    """An adaptation state file's document (format and schema checked; one-line ``InputFileError``)."""
    return read_tagged_yaml(path, "adaptation state", ADAPT_STATE_FORMAT, ADAPT_STATE_SCHEMA_VERSION)


#: The first line of every adaptation state file ``write_state_doc`` writes (its document's first key).
STATE_FIRST_LINE = f"format: {ADAPT_STATE_FORMAT}\n"


def not_a_state_file(path: str | Path) -> str | None:
    """What the file at ``path`` is when it is not an adaptation state, judged by its content: None when nothing
    is there (nor a symlink's target) or it is an adaptation state, else what it is ("a fitted model", "a
    capture", "a capture's provenance sidecar (of run1.bin)", "a directory", "an empty file", "a file without
    'format: ...'": ``outputs.describe``'s names; "not a regular file (it is a FIFO)" for a FIFO, a socket, a device).

    An adaptation state is a file that begins with ``STATE_FIRST_LINE``, as ``write_state_doc`` writes every
    one (whatever follows: a state cut short, or corrupt in its fields, is still one), or a YAML mapping tagged
    ``format: fog_driver adaptation state`` (one written by hand).  Only such a file may be read, set aside
    or replaced as a state: the daemon's start check and ``compensate --adapt-state`` both ask here.  A
    directory, a FIFO, a socket or a device is never opened."""
    path = Path(path)
    if not path.exists():
        return None
    if (other := not_regular_kind(path)) is not None:
        return other if other == "a directory" else f"not a regular file (it is {other})"
    head = read_head(path, len(STATE_FIRST_LINE))  # (opened without waiting: swapped for a FIFO, never blocks)
    if head is None:
        return "a file that cannot be read"
    if head == STATE_FIRST_LINE.encode():
        return None
    kind = describe(path)
    if kind == "an adaptation state":
        return None
    return f"a file without {STATE_FIRST_LINE.strip()!r}" if kind == "a file" else kind


def write_state_doc(path: str | Path, doc: dict[str, Any]) -> Path:
    """Write a ``state_document`` to ``path`` (atomically; ``OutputFileError`` on failure), never over a file
    that is not an adaptation state (``not_a_state_file``): that is an ``OutputFileError`` too, "PATH: is
    WHAT, not an adaptation state: not replaced", and the file is left as it was."""
    kind = not_a_state_file(path)
    if kind is not None:
        raise OutputFileError(f"{path}: is {kind}, not an adaptation state: not replaced")
    return write_yaml(Path(path), doc, "adaptation state")


def save_readout_state(
    readout: OnlineReadout,
    path: str | Path,
    detector: StaticDetector | None = None,
    pipeline: dict[str, Any] | None = None,
) -> Path:
    """Write the readout's state (and a static detector's, and a compensator's ``pipeline`` state, if given)
    as YAML; ``OutputFileError`` on failure."""
    return write_state_doc(path, readout.state_document(detector, pipeline))


def load_readout_state(
    readout: OnlineReadout, path: str | Path, detector: StaticDetector | None = None
) -> StaticDetector | None:
    """Restore the readout's state from ``save_readout_state``'s file; a corrupt, wrong-format or
    wrong-version file, or one for another model, is a one-line ``InputFileError`` (and nothing is
    changed).  Returns the file's static detector (``OnlineReadout.load_state_doc``)."""
    return readout.load_state_doc(read_state_doc(path), str(path), detector)


def save_adaptation(compensator: Compensator, path: str | Path) -> Path:
    """The compensator's adaptation state as YAML (``Compensator.adaptation_document``); only when adapting."""
    return write_state_doc(path, compensator.adaptation_document())


def load_adaptation(compensator: Compensator, path: str | Path, *, new_run: bool = True) -> None:
    """Restore ``save_adaptation``'s file into the compensator (``Compensator.restore_adaptation``:
    ``InputFileError`` when it does not fit this model; ``new_run`` as there)."""
    compensator.check_adapting()
    compensator.restore_adaptation(read_state_doc(path), str(path), new_run=new_run)


def adaptation_restorer(path: str | Path | None) -> Callable[[Compensator], None] | None:
    """For ``InstrumentCompensation(restore_adaptation=...)``: restore the state file at ``path`` into the first
    compensator, when the file exists then (as a new run); None without a path."""
    if path is None:
        return None

    def restore(compensator: Compensator) -> None:
        if Path(path).exists():
            load_adaptation(compensator, path)

    return restore
