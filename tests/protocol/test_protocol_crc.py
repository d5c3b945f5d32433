"""The CRC leaf against independent references: bitwise definitions (no tables), zlib, check values."""

from __future__ import annotations

import zlib

import numpy as np
import pytest

from fog_driver.formats import kvh
from fog_driver.protocol import batch, wire
from fog_driver.protocol.crc import (
    CHECK_ISO_HDLC,
    CHECK_MPEG2,
    ISO_HDLC_TABLE,
    MPEG2_TABLE,
    crc32,
    crc32_mpeg2,
    crc32_mpeg2_reference,
    crc32_mpeg2_rows,
    crc32_reference,
    crc32_rows,
    iso_hdlc_tables,
    mpeg2_tables,
)


def bitwise_iso_hdlc(data: bytes) -> int:
    """CRC-32/ISO-HDLC one bit at a time, LSB first (the catalogue's definition)."""
    crc = 0xFFFFFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xEDB88320 if crc & 1 else crc >> 1
    return crc ^ 0xFFFFFFFF


def bitwise_mpeg2(data: bytes) -> int:
    """CRC-32/MPEG-2 one bit at a time, MSB first, no reflection, no final xor."""
    crc = 0xFFFFFFFF
    for byte in data:
        crc ^= byte << 24
        for _ in range(8):
            crc = ((crc << 1) ^ 0x04C11DB7) & 0xFFFFFFFF if crc & 0x80000000 else (crc << 1) & 0xFFFFFFFF
    return crc


def test_check_values() -> None:
    check = b"123456789"
    assert crc32(check) == crc32_reference(check) == bitwise_iso_hdlc(check) == CHECK_ISO_HDLC == 0xCBF43926
    assert crc32_mpeg2(check) == crc32_mpeg2_reference(check) == bitwise_mpeg2(check) == CHECK_MPEG2 == 0x0376E6E7


def test_tables_are_one_byte_of_the_bitwise_register() -> None:
    for v in range(256):
        reg = v
        for _ in range(8):
            reg = (reg >> 1) ^ 0xEDB88320 if reg & 1 else reg >> 1
        assert int(ISO_HDLC_TABLE[v]) == reg
        reg = v << 24
        for _ in range(8):
            reg = ((reg << 1) ^ 0x04C11DB7) & 0xFFFFFFFF if reg & 0x80000000 else (reg << 1) & 0xFFFFFFFF
        assert MPEG2_TABLE[v] == reg


@pytest.mark.parametrize("m", [1, 2, 3, 7, 8, 20, 32, 33, 36])
def test_row_forms_equal_the_bitwise_definitions(m: int) -> None:
    rng = np.random.default_rng(m)
    rows = rng.integers(0, 256, (25, m), dtype=np.uint8)
    rows[0] = 0
    rows[1] = 0xFF
    assert crc32_rows(rows).tolist() == [bitwise_iso_hdlc(r.tobytes()) for r in rows]
    assert crc32_mpeg2_rows(rows).tolist() == [bitwise_mpeg2(r.tobytes()) for r in rows]
    # a non-contiguous view gives the same
    wide = np.zeros((25, m + 3), dtype=np.uint8)
    wide[:, 1 : m + 1] = rows
    assert crc32_mpeg2_rows(wide[:, 1 : m + 1]).tolist() == crc32_mpeg2_rows(rows).tolist()
    assert crc32_rows(wide[:, 1 : m + 1]).tolist() == crc32_rows(rows).tolist()


def test_empty_row_sets() -> None:
    assert crc32_rows(np.zeros((0, 8), np.uint8)).tolist() == []
    assert crc32_mpeg2_rows(np.zeros((0, 9), np.uint8)).tolist() == []


def test_byte_at_a_time_forms_on_random_data() -> None:
    rng = np.random.default_rng(7)
    for size in (0, 1, 2, 5, 64, 1000):
        data = rng.integers(0, 256, size, dtype=np.uint8).tobytes()
        assert crc32(data) == crc32_reference(data) == bitwise_iso_hdlc(data) == zlib.crc32(data)
        assert crc32(bytearray(data)) == crc32(memoryview(data)) == crc32(data)
        assert crc32_mpeg2(data) == crc32_mpeg2_reference(data) == bitwise_mpeg2(data)
        assert crc32_mpeg2(memoryview(data)) == crc32_mpeg2(bytearray(data)) == crc32_mpeg2(data)


def test_pair_tables_with_a_fixed_prefix_are_the_crc_of_the_whole_message() -> None:
    rng = np.random.default_rng(11)
    prefix = bytes((0x01, 0x12))
    tail = rng.integers(0, 256, (40, 18), dtype=np.uint8)
    tables = iso_hdlc_tables(20).with_fixed_prefix(prefix)
    words = tail.view("<u2").astype(np.uint16)
    assert tables.of_words(words).tolist() == [zlib.crc32(prefix + t.tobytes()) for t in tail]
    mp = mpeg2_tables(36).with_fixed_prefix(bytes((0xFE, 0x81, 0xFF, 0x55)))
    body = rng.integers(0, 256, (10, 32), dtype=np.uint8)
    assert mp.of_words(body.view("<u2").astype(np.uint16)).tolist() == [
        bitwise_mpeg2(b"\xfe\x81\xff\x55" + b.tobytes()) for b in body
    ]
    with pytest.raises(ValueError, match="even"):
        iso_hdlc_tables(20).with_fixed_prefix(b"\x01")


def test_every_user_computes_with_the_leaf() -> None:
    """One implementation: the protocol, its batch decoder and KVH use the leaf's functions and tables."""
    assert wire.crc32 is crc32
    assert kvh.crc32_mpeg2 is crc32_mpeg2 and kvh.crc32_mpeg2_rows is crc32_mpeg2_rows
    assert kvh.CRC_TABLE is MPEG2_TABLE
    assert batch._SAMPLE_CRC.constant == zlib.crc32(bytes((1, 18)) + bytes(18))
