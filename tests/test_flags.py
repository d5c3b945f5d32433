"""The flag vocabulary's leaf: one IntFlag, its names, and every old name an alias of the same value."""

from __future__ import annotations

import itertools
import subprocess
import sys

import pytest

from fog_driver import flags
from fog_driver.compensation import blocks, domain, features, pipeline
from fog_driver.daemon import udp
from fog_driver.flags import FLAG_BITS, FLAG_NAMES, Flag, flag_names, flags_from_names
from fog_driver.formats import common

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


@pytest.mark.parametrize(
    ("module", "names"),
    [
        (blocks, ["FLAG_GAP", "FLAG_THERMOMETER_FAULT"]),
        (features, ["FLAG_INPUT_STALE", "FLAG_SUBSTITUTED", "FLAG_RECOVERING"]),
        (domain, ["FLAG_EXTRAPOLATING"]),
        (pipeline, ["FLAG_UNCOMPENSATED", "FLAG_ADAPTING", "FLAG_GUARD"]),
        (udp, [f"FLAG_{f.name}" for f in Flag]),
        (flags, [f"FLAG_{f.name}" for f in Flag]),
    ],
)
def test_old_names_are_plain_int_aliases(module: object, names: list[str]) -> None:
    for name in names:
        value = getattr(module, name)
        assert type(value) is int, name
        assert value == int(Flag[name.removeprefix("FLAG_")]), name


def test_name_maps_are_the_leaf_s() -> None:
    assert pipeline.FLAG_NAMES is FLAG_NAMES
    assert pipeline.flag_names is flag_names
    assert udp.FLAG_BITS == FLAG_BITS


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
    assert (
        common.COMMON_FLAGS == flags.SAMPLE_FLAGS == ("sensor_invalid", "startup", "temperature_invalid", "over_range")
    )
    assert common.FLAG_SENSOR_INVALID == "sensor_invalid" and common.FLAG_STARTUP == "startup"
    assert common.FLAG_TEMPERATURE_INVALID == "temperature_invalid" and common.FLAG_OVER_RANGE == "over_range"
    assert all(type(name) is str for name in flags.SAMPLE_FLAGS)


def test_the_leaf_imports_the_standard_library_only() -> None:
    code = (
        "import sys, fog_driver.flags\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] not in sys.stdlib_module_names"
        " and not m.startswith('_')))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "['fog_driver', 'fog_driver.flags']"
