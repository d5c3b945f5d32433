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

from collections.abc import Callable
from pathlib import Path
from typing import Any

from .compensation.adapt import ADAPT_STATE_FORMAT, ADAPT_STATE_SCHEMA_VERSION, OnlineReadout, StaticDetector
from .compensation.model import MODEL_FORMAT, MODEL_SCHEMA_VERSION, ModelFile, model_file_from_doc
from .compensation.pipeline import Compensator
from .errors import InputFileError
from .files.yamlio import MAX_YAML_BYTES, read_tagged_yaml, write_yaml, yaml_text

# -- model files ---------------------------------------------------------------------------------------


def save_model(path: str | Path, model_file: ModelFile) -> Path:
    """Write ``model_file.to_doc()`` to ``path`` (atomically; ``OutputFileError`` on failure)."""
    return write_yaml(path, model_file.to_doc(), "model")


def load_model(path: str | Path) -> ModelFile:
    """Read and validate a model file; a corrupt or wrong-version file is a one-line ``InputFileError``."""
    doc = read_tagged_yaml(path, "model file", MODEL_FORMAT, MODEL_SCHEMA_VERSION)
    return model_file_from_doc(doc, str(path))


def _read_bytes(path: str | Path) -> bytes | None:
    try:
        return Path(path).read_bytes() if Path(path).stat().st_size <= MAX_YAML_BYTES else None
    except OSError:
        return None


def read_model(path: str | Path, attempts: int = 3) -> tuple[ModelFile, bytes]:
    """The model file at ``path`` and the bytes it was read from (the daemon keeps a copy of them beside its
    captures): read again when the file changed meanwhile (a fit writing it); one-line ``InputFileError``s."""
    for _ in range(attempts):
        before = _read_bytes(path)
        model_file = load_model(path)  # the one-line error of a file that cannot be used
        if before is not None and _read_bytes(path) == before:
            return model_file, before
    raise InputFileError(f"{path}: the model file kept changing while it was read (being written?): try again")


def model_bytes(model_file: ModelFile) -> bytes:
    """The bytes of a model given as an object (not read from a file): the text ``save_model`` writes."""
    return yaml_text(model_file.to_doc()).encode("utf-8")


# -- adaptation state files ----------------------------------------------------------------------------


def read_state_doc(path: str | Path) -> dict[str, Any]:
    """An adaptation state file's document (format and schema checked; one-line ``InputFileError``)."""
    return read_tagged_yaml(path, "adaptation state", ADAPT_STATE_FORMAT, ADAPT_STATE_SCHEMA_VERSION)


def write_state_doc(path: str | Path, doc: dict[str, Any]) -> Path:
    """Write a ``state_document`` to ``path`` (atomically; ``OutputFileError`` on failure)."""
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
