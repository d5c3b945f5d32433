"""The F4T's register map: the manual's addresses per loop, floats in both word orders against ``struct`` as the
reference, the unit and state values."""

from __future__ import annotations

import math
import struct

import pytest

from fog_driver.lab.controllers.base import CHAMBER_STATES, ControllerProtocolError
from fog_driver.lab.controllers.codecs import f4t

VALUES = [0.0, 1.0, -1.0, 23.5, -40.0, 180.0, 356.0, 1e-3, 123456.789, -55555.0]


@pytest.mark.parametrize("loop", [1, 2, 3, 4])
def test_each_loops_registers_are_the_manuals_plus_160_per_loop(loop):
    registers = f4t.loop_map(loop)
    step = 160 * (loop - 1)
    assert (registers.setpoint, registers.process_value) == (2782 + step, 2820 + step)
    assert (registers.range_low, registers.range_high) == (2774 + step, 2776 + step)
    assert registers.control_mode == 2730 + step
    assert registers.units == 1328 and registers.word_order == "low"


def test_a_loop_the_f4t_does_not_have_or_an_unknown_word_order_is_refused():
    for loop in (0, 5):
        with pytest.raises(ValueError):
            f4t.loop_map(loop)
    with pytest.raises(ValueError):
        f4t.loop_map(1, word_order="big")


@pytest.mark.parametrize("value", VALUES)
def test_a_float_in_low_word_order_is_its_little_endian_words(value):
    # low word first: the registers are the float's two 16-bit halves, least significant first
    expected = struct.unpack("<HH", struct.pack("<f", value))
    assert f4t.encode_float(value, "low") == expected
    assert f4t.decode_float(expected, "low") == struct.unpack("<f", struct.pack("<f", value))[0]


@pytest.mark.parametrize("value", VALUES)
def test_a_float_in_high_word_order_is_its_big_endian_words(value):
    expected = struct.unpack(">HH", struct.pack(">f", value))
    assert f4t.encode_float(value, "high") == expected
    assert f4t.decode_float(expected, "high") == struct.unpack(">f", struct.pack(">f", value))[0]


def test_the_two_word_orders_are_each_others_swap():
    for value in VALUES:
        low = f4t.encode_float(value, "low")
        assert f4t.encode_float(value, "high") == (low[1], low[0])


def test_a_known_float_sits_in_the_registers_as_the_ieee_bits_say():
    # 25.0 = 0x41C80000: high word 0x41C8, low word 0x0000
    assert f4t.encode_float(25.0, "low") == (0x0000, 0x41C8)
    assert f4t.encode_float(25.0, "high") == (0x41C8, 0x0000)


def test_registers_holding_no_finite_float_are_garbage():
    nan_high, nan_low = struct.unpack(">HH", struct.pack(">f", math.nan))
    with pytest.raises(ControllerProtocolError, match="not a finite float"):
        f4t.decode_float((nan_low, nan_high), "low")
    inf_high, inf_low = struct.unpack(">HH", struct.pack(">f", math.inf))
    with pytest.raises(ControllerProtocolError):
        f4t.decode_float((inf_high, inf_low), "high")
    with pytest.raises(ControllerProtocolError):
        f4t.decode_float((1,), "low")
    with pytest.raises(ValueError):
        f4t.encode_float(math.nan, "low")


def test_the_unit_register_values_are_the_manuals():
    assert f4t.decode_units(30) == "F" and f4t.decode_units(15) == "C"
    with pytest.raises(ControllerProtocolError, match="neither F"):
        f4t.decode_units(0)


def test_the_state_follows_the_profile_then_the_control_mode():
    assert f4t.chamber_state(f4t.PROFILE_RUNNING, None) == "program"
    assert f4t.chamber_state(f4t.PROFILE_PAUSED, 10) == "program"
    assert f4t.chamber_state(61, 62) == "standby"
    assert f4t.chamber_state(None, 10) == "constant"
    assert f4t.chamber_state(None, 54) == "local"
    assert f4t.chamber_state(None, None) == "unknown"
    assert f4t.chamber_state(None, 999) is None
    assert {f4t.chamber_state(None, mode) for mode in f4t.CONTROL_MODES} <= set(CHAMBER_STATES)
