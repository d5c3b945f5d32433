"""Typed mappings: a YAML document checked against a frozen dataclass by msgspec, every problem a one-line error.

The dataclass stays the type the code uses, with its defaults and its ``__post_init__`` range checks.  A
schema derived from its annotations (a ``msgspec.Struct`` with ``forbid_unknown_fields``, every field
optional so that a missing key takes the dataclass's default) checks the document's shape with
``msgspec.convert(doc, schema, strict=True)``; then the dataclass is built from the keys the document gave.

What each annotation accepts::

    bool                a YAML true or false, nothing else
    int                 an integer, never a bool or a float
    float               an integer or a float, finite (nan and inf refused); held as a float
    str                 a string
    tuple[str, ...]     a list of strings, held as a tuple
    tuple[float, ...]   a list of numbers (no bools), held as a tuple of floats
    dict[str, ...]      a mapping of names to strings, integers, finite numbers or true/false (a driver's
                        settings, such as a chamber controller's register overrides), held as a dict
    X | None            also null
    a dataclass         a nested mapping, checked the same way

Every problem is an ``InputFileError`` naming the file, then the key's path within it, then what was
wrong: ``badval.yaml: baud: expected an integer, got 'fast'``, ``sim.yaml: thermal: unknown key 'x'
(known: ...)`` (``fog.yaml: unknown key 'lisen' (did you mean 'listen'?)`` when a known key is close),
``fit.yaml: features: need 0 < rate_tau_fast_s < rate_tau_slow_s`` (a dataclass's own ``ValueError``).
msgspec's ``ValidationError`` gives the path (``... - at `$.thermal.tau_top_s```); the message is the
project's, chosen by the field's kind, with the document's value.
"""

from __future__ import annotations

import dataclasses
import difflib
import functools
import re
import sys
import types
import typing
from collections.abc import Iterable
from typing import Annotated, Any

import msgspec

from ..errors import InputFileError

#: A finite float: msgspec compares against the largest doubles, and nan fails every comparison.
FiniteFloat = Annotated[float, msgspec.Meta(ge=-sys.float_info.max, le=sys.float_info.max)]

#: What a value of each kind should have been, in the one-line message.
EXPECTED = {
    "bool": "expected true or false",
    "int": "expected an integer",
    "float": "expected a finite number",
    "str": "expected a string",
    "strings": "expected a list of strings",
    "numbers": "expected a list of numbers",
    "mapping": "expected a mapping",
    "settings": "expected a mapping of names to numbers, strings or true/false",
}

#: The schema type of each kind (``mapping``: a nested schema, built apart).
_SCHEMA_TYPES: dict[str, Any] = {
    "bool": bool,
    "int": int,
    "float": FiniteFloat,
    "str": str,
    "strings": tuple[str, ...],
    "numbers": tuple[float, ...],
    "settings": dict[str, str | bool | int | FiniteFloat],
}

#: The kind of each scalar annotation.
_SCALARS: dict[Any, str] = {bool: "bool", int: "int", float: "float", str: "str"}

#: The key path at the end of a msgspec validation message: `` - at `$.a.b[2]``` or `` - at `key` in `$.a```.
_AT = re.compile(r" - at `(?:key` in `)?\$(?P<path>[^`]*)`$")


class FieldType(typing.NamedTuple):
    """A dataclass field's type as a YAML value: its kind, whether null is allowed, the nested dataclass."""

    kind: str  #: a key of ``EXPECTED``
    optional: bool
    dataclass: type | None = None  #: for kind ``mapping``


def field_type(annotation: Any) -> FieldType:
    """What a field annotated ``annotation`` (resolved, not a string) holds; ``TypeError`` for a type no YAML
    setting has."""
    args = typing.get_args(annotation)
    optional = typing.get_origin(annotation) in (typing.Union, types.UnionType) and type(None) in args
    if optional:
        rest = [a for a in args if a is not type(None)]
        if len(rest) != 1:
            raise TypeError(f"cannot read a {annotation!r} setting from YAML")
        annotation, args = rest[0], typing.get_args(rest[0])
    if dataclasses.is_dataclass(annotation):
        return FieldType("mapping", optional, typing.cast(type, annotation))
    if typing.get_origin(annotation) is tuple and len(args) == 2 and args[1] is Ellipsis:
        if args[0] is str:
            return FieldType("strings", optional)
        if args[0] in (float, int):
            return FieldType("numbers", optional)
    if typing.get_origin(annotation) is dict and args[:1] == (str,):
        return FieldType("settings", optional)
    kind = _SCALARS.get(annotation)
    if kind is not None:
        return FieldType(kind, optional)
    raise TypeError(f"cannot read a {annotation!r} setting from YAML")


@functools.cache
def field_types(cls: type) -> dict[str, FieldType]:
    """Every field of the dataclass ``cls`` by name, in declaration order."""
    hints = typing.get_type_hints(cls)
    return {f.name: field_type(hints[f.name]) for f in dataclasses.fields(cls)}


@functools.cache
def schema(cls: type) -> type[msgspec.Struct]:
    """The msgspec ``Struct`` that checks a mapping for the dataclass ``cls``: its fields, each optional
    (``UNSET`` when absent), unknown keys refused."""
    fields = []
    for name, ft in field_types(cls).items():
        t = schema(ft.dataclass) if ft.dataclass is not None else _SCHEMA_TYPES[ft.kind]
        if ft.optional:
            t = t | None
        fields.append((name, t | msgspec.UnsetType, msgspec.UNSET))
    return msgspec.defstruct(f"{cls.__name__}Schema", fields, forbid_unknown_fields=True, frozen=True)


def dataclass_from_mapping(cls: type, doc: Any, where: str, path: str = "") -> Any:
    """Build the (nested) frozen dataclass ``cls`` from a YAML mapping ``doc``: unknown keys, wrong types and the
    dataclass's own ``ValueError``s are one-line ``InputFileError``s naming ``where`` (the file) and the key's
    ``path`` within it (``fit.yaml: features.hold_s: expected a finite number, got 'x'``).

    ``path`` is where ``doc`` sits in its file ("" for the whole file)."""
    try:
        checked = msgspec.convert(doc, schema(cls), strict=True)
    except msgspec.ValidationError as exc:
        raise InputFileError(_one_line(cls, doc, where, path, str(exc))) from None
    return _build(cls, checked, where, path)


def _build(cls: type, checked: msgspec.Struct, where: str, path: str) -> Any:
    """The dataclass from a checked schema instance: the keys given, nested dataclasses built first."""
    values = {}
    for name, ft in field_types(cls).items():
        value = getattr(checked, name)
        if value is msgspec.UNSET:
            continue  # not in the file: the dataclass's default
        if ft.dataclass is not None and value is not None:
            value = _build(ft.dataclass, value, where, _join(path, name))
        values[name] = value
    try:
        return cls(**values)
    except ValueError as exc:
        raise InputFileError(f"{_at(where, path)}{exc}") from None


def _join(path: str, name: str) -> str:
    return f"{path}.{name}" if path else name


def _at(where: str, path: str) -> str:
    return f"{where}: {path}: " if path else f"{where}: "


def _one_line(cls: type, doc: Any, where: str, path: str, message: str) -> str:
    """The project's message for msgspec's ``message`` about ``doc``: follow its key path through the
    dataclasses and the document to the field (or the mapping) it names."""
    found = _AT.search(message)
    names = re.findall(r"\.([A-Za-z_]\w*)", found["path"]) if found else []  # list indices are dropped
    node = doc
    for name in names:
        ft = field_types(cls).get(name)
        if ft is None or not isinstance(node, dict) or name not in node:
            break  # not a path through this schema: msgspec's own words below
        value, here = node[name], _join(path, name)
        if ft.dataclass is None:
            return f"{where}: {here}: {EXPECTED[ft.kind]}, got {value!r}"
        cls, node, path = ft.dataclass, value, here
    else:
        if not isinstance(node, dict):
            return f"{_at(where, path)}{EXPECTED['mapping']}"
        known = field_types(cls)
        for key in node:
            if key not in known:
                return f"{_at(where, path)}{unknown_key(key, known)}"
    return f"{_at(where, path)}{message}"


def unknown_key(key: Any, known: Iterable[str]) -> str:
    """What to say of a key no schema has: "unknown key 'lisen' (did you mean 'listen'?)" when one known key is
    close to it (``difflib.get_close_matches``, its default cutoff 0.6, case ignored), else the known keys:
    "unknown key 'x' (known: a, b)".  Every YAML file a user writes says it so (configs, fit configs,
    instrument configs, profiles)."""
    names = sorted(known)
    by_folded = {name.lower(): name for name in names}
    close = difflib.get_close_matches(str(key).lower(), list(by_folded), n=1)
    if close:
        return f"unknown key {key!r} (did you mean {by_folded[close[0]]!r}?)"
    return f"unknown key {key!r} (known: {', '.join(names) or 'none'})"
