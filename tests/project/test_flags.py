"""The flag vocabulary's leaf: one IntFlag, its names, and no other home for a flag."""

from __future__ import annotations

import ast
import itertools
import subprocess
import sys
from pathlib import Path

from fog_driver import flags
from fog_driver.flags import FLAG_BITS, FLAG_NAMES, Flag, flag_names, flags_from_names

#: The flag word as documented before the leaf existed (the UDP datagram's table, the NDJSON names).
DOCUMENTED = {
    1 << 0: "gap",
    1 << 1: "thermometer_fault",
    1 << 2: "input_stale",
    1 << 3: "uncompensated",
    1 << 4: "adapting",
    1 << 5: "guard",
    1 << 6: "extrapolating",
    1 << 7: "substituted",
    1 << 8: "recovering",
    1 << 9: "scale_factor",
}


def test_bits_and_names_are_the_documented_ones_in_bit_order() -> None:
    assert FLAG_NAMES == DOCUMENTED
    assert list(FLAG_NAMES) == sorted(DOCUMENTED)
    assert {int(f): f.name.lower() for f in Flag} == DOCUMENTED
    assert {name: bit for bit, name in DOCUMENTED.items()} == FLAG_BITS
    assert all(type(bit) is int for bit in FLAG_NAMES)


def test_the_int_forms_are_plain_ints_of_the_same_bits() -> None:
    for flag in Flag:
        value = getattr(flags, f"FLAG_{flag.name}")
        assert type(value) is int and value == int(flag), flag.name


def _binds_a_leaf_name(value: ast.expr | None, leaf_names: set[str]) -> bool:
    """A module-level value that is one of the leaf's flags under another name: ``FLAG_GAP``, ``Flag.GAP``,
    ``int(Flag.GAP)``, ``SAMPLE_STARTUP`` (a set, a mapping or a combination of flags is a thing of its own)."""
    if isinstance(value, ast.Call) and isinstance(value.func, ast.Name) and value.func.id == "int" and value.args:
        value = value.args[0]
    if isinstance(value, ast.Name):
        return value.id in leaf_names
    return isinstance(value, ast.Attribute) and isinstance(value.value, ast.Name) and value.value.id in leaf_names


def test_no_module_but_the_leaf_binds_a_flag_to_a_name_of_its_own() -> None:
    """Flag bits and the sample flags come from ``fog_driver.flags`` alone: no module assigns one to a
    module-level name (``FLAG_GAP = int(Flag.GAP)``, ``GAP = Flag.GAP``, ``FLAG_STARTUP = SAMPLE_STARTUP``), and
    none imports one from anywhere but the leaf (a re-export through another module is an alias too)."""
    root = Path(flags.__file__).resolve().parent
    leaf_names = {n for n in vars(flags) if n.startswith(("FLAG_", "SAMPLE_")) or n in ("Flag", "flag_names")}
    found = []
    for path in sorted(root.rglob("*.py")):
        if path == root / "flags.py":
            continue
        where = path.relative_to(root.parent)
        for node in ast.parse(path.read_text(encoding="utf-8")).body:
            if isinstance(node, (ast.Assign, ast.AnnAssign)) and _binds_a_leaf_name(node.value, leaf_names):
                found.append(f"{where}:{node.lineno}")
            imported = {a.name for a in node.names} & leaf_names if isinstance(node, ast.ImportFrom) else set()
            if imported and (node.module or "").split(".")[-1] != "flags":
                found.append(f"{where}:{node.lineno} imports {sorted(imported)} from {node.module}")
    assert found == []


def test_flag_names_every_word_against_a_loop() -> None:
    for bits in range(1 << 11):
        expected = [DOCUMENTED[1 << k] for k in range(10) if bits >> k & 1]
        assert flag_names(bits) == expected
        assert int(flags_from_names(expected)) == bits & 0x3FF
    assert flag_names(Flag.GAP | Flag.GUARD) == ["gap", "guard"]
    first = flag_names(3)
    first.append("x")
    assert flag_names(3) == ["gap", "thermometer_fault"]  # a new list each call


def test_flags_from_names_ignores_unknown_and_repeated_names() -> None:
    assert flags_from_names([]) == Flag(0)
    assert flags_from_names(["gap", "gap", "from_the_future"]) == Flag.GAP
    for a, b in itertools.combinations(DOCUMENTED.values(), 2):
        assert flags_from_names([a, b]) == FLAG_BITS[a] | FLAG_BITS[b]


def test_sample_flags_are_the_formats_names() -> None:
    assert flags.SAMPLE_FLAGS == ("sensor_invalid", "startup", "temperature_invalid", "over_range")
    assert flags.SAMPLE_SENSOR_INVALID == "sensor_invalid" and flags.SAMPLE_STARTUP == "startup"
    assert flags.SAMPLE_TEMPERATURE_INVALID == "temperature_invalid" and flags.SAMPLE_OVER_RANGE == "over_range"
    assert all(type(name) is str for name in flags.SAMPLE_FLAGS)


def test_the_leaf_imports_the_standard_library_only() -> None:
    code = (
        "import sys, fog_driver.flags\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] not in sys.stdlib_module_names"
        " and not m.startswith('_')))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "['fog_driver', 'fog_driver.flags']"
