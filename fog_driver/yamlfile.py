"""Reading the project's YAML files (configs, profiles, sidecars): safe loading only, bounded, one-line errors."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from .errors import InputFileError

#: Every YAML file the project reads is small; a larger one is not what it claims to be.
MAX_YAML_BYTES = 1 << 20


def read_yaml(path: str | Path, what: str, *, missing_ok: bool = False, hint: str = "") -> Any:
    """``yaml.safe_load`` of a file (never a Python object tag, never code).

    Every problem is an ``InputFileError`` naming the file and ``what`` it should
    have been (``"config file"``, ``"profile file"``...); a missing file gives
    None with ``missing_ok``.  ``hint`` is appended to the missing-file message.
    """
    path = Path(path)
    try:
        if path.is_dir():
            raise InputFileError(f"{path}: is a directory, not a {what}")
        if path.stat().st_size > MAX_YAML_BYTES:
            raise InputFileError(f"{path}: {what} larger than {MAX_YAML_BYTES} bytes")
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        if missing_ok:
            return None
        raise InputFileError(f"{path}: no such {what}{hint}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputFileError(f"{path}: cannot read {what}: {exc}") from None
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        at = f" at line {mark.line + 1}" if mark is not None else ""
        raise InputFileError(f"{path}: {what} is not valid YAML{at}") from None
