"""Checking the keys of a model file's parts before they are built (a leaf: dicts in, ``ValueError`` out)."""

from __future__ import annotations

from dataclasses import fields
from typing import Any


def require_known_keys(cls: type, d: Any, what: str) -> None:
    """``ValueError`` unless ``d`` is a dict whose keys are all fields of the dataclass ``cls``
    (missing keys are allowed: they take the defaults).  For ``from_dict`` of model-file parts."""
    known = {f.name for f in fields(cls)}
    if not isinstance(d, dict) or not set(d) <= known:
        extra = sorted(set(d) - known) if isinstance(d, dict) else type(d).__name__
        raise ValueError(f"{what}: unknown keys {extra}")
