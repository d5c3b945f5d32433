"""The CRC-32s of the wire formats, once: byte at a time, and many fixed-length messages at once with numpy.

Two CRC-32s, both of polynomial 0x04C11DB7 and register initialised to 0xFFFFFFFF:

* CRC-32/ISO-HDLC (protocol v1, zlib's ``crc32``): reflected (LSB first, table of the reversed
  polynomial 0xEDB88320), final xor 0xFFFFFFFF; check value of ``b"123456789"``: 0xCBF43926;
* CRC-32/MPEG-2 (KVH): not reflected (MSB first), no final xor; check value 0x0376E6E7.

Vector form.  Without its initial value and final xor a CRC is linear over GF(2), so for messages of a
fixed length ``m``::

    crc(msg) = crc(m zero bytes) XOR T[0, msg[0]] XOR ... XOR T[m-1, msg[m-1]]

where ``T[j, v]`` is the CRC, register starting at 0 and no final xor, of the message holding ``v`` at
byte ``j`` and zeros elsewhere (the initial value and the final xor ride in the first term).  Pairing
the bytes, ``P[k, lo | hi << 8] = T[2k, lo] ^ T[2k + 1, hi]``, gives ``m / 2`` look-ups per message in
65,536-entry tables (``PairTables``), gathered across messages one column at a time; bytes fixed in
every message (a header) fold into the constant.
"""

from __future__ import annotations

import functools
import zlib
from dataclasses import dataclass
from typing import Final

import numpy as np
import numpy.typing as npt

Buffer = bytes | bytearray | memoryview
U32Array = npt.NDArray[np.uint32]

POLY: Final = 0x04C11DB7  #: the polynomial of both CRCs, MSB-first form
POLY_REFLECTED: Final = 0xEDB88320  #: the same, bit-reversed (LSB-first form)
CHECK_ISO_HDLC: Final = 0xCBF43926  #: CRC-32/ISO-HDLC of b"123456789"
CHECK_MPEG2: Final = 0x0376E6E7  #: CRC-32/MPEG-2 of b"123456789"


def _iso_hdlc_table() -> U32Array:
    """``table[v]``: the reflected register (from 0) after the byte ``v``: eight LSB-first shifts."""
    table = np.arange(256, dtype=np.uint32)
    for _ in range(8):
        table = np.where(table & 1, (table >> 1) ^ np.uint32(POLY_REFLECTED), table >> 1).astype(np.uint32)
    return table


def _mpeg2_table() -> list[int]:
    """``table[v]``: the MSB-first register (from 0) after the byte ``v``: eight MSB-first shifts."""
    table = []
    for byte in range(256):
        crc = byte << 24
        for _ in range(8):
            crc = ((crc << 1) ^ POLY) & 0xFFFFFFFF if crc & 0x80000000 else (crc << 1) & 0xFFFFFFFF
        table.append(crc)
    return table


#: CRC-32/ISO-HDLC byte table (reflected), as numpy uint32.
ISO_HDLC_TABLE: Final = _iso_hdlc_table()
#: CRC-32/MPEG-2 byte table (MSB first), as ints and as numpy uint32.
MPEG2_TABLE: Final = _mpeg2_table()
MPEG2_TABLE_NP: Final = np.array(MPEG2_TABLE, dtype=np.uint32)

_REVERSE_BITS8 = bytes(int(f"{b:08b}"[::-1], 2) for b in range(256))


# --- byte at a time --------------------------------------------------------------------------------------


def crc32(data: Buffer) -> int:
    """CRC-32/ISO-HDLC (protocol v1): poly 0x04C11DB7 reflected, init and xorout 0xFFFFFFFF (zlib's)."""
    return zlib.crc32(data) & 0xFFFFFFFF


def crc32_reference(data: Buffer) -> int:
    """The textbook LSB-first table-driven CRC-32/ISO-HDLC (slow; the definition ``crc32`` is tested against)."""
    crc = 0xFFFFFFFF
    table = ISO_HDLC_TABLE.tolist()
    for b in bytes(data):
        crc = table[(crc ^ b) & 0xFF] ^ (crc >> 8)
    return crc ^ 0xFFFFFFFF


def crc32_mpeg2(data: Buffer) -> int:
    """CRC-32/MPEG-2 of ``data``.

    Computed with zlib's reflected CRC-32 on bit-reversed bytes: CRC-32 (ISO-HDLC) is the same register
    with every byte and the result bit-reversed and a final xor of 0xFFFFFFFF, so
    ``mpeg2(d) = reverse32(crc32(reverse8(d)) ^ 0xFFFFFFFF)``.  ``crc32_mpeg2_reference`` is the table
    form it is tested against.
    """
    reg = (
        zlib.crc32(
            data.translate(_REVERSE_BITS8)
            if not isinstance(data, memoryview)
            else bytes(data).translate(_REVERSE_BITS8)
        )
        ^ 0xFFFFFFFF
    )
    # reverse32: the bytes in the opposite order, each bit-reversed
    return int.from_bytes(reg.to_bytes(4, "little").translate(_REVERSE_BITS8), "big")


def crc32_mpeg2_reference(data: Buffer) -> int:
    """The textbook MSB-first table-driven CRC-32/MPEG-2 (slow; the definition)."""
    crc = 0xFFFFFFFF
    for b in bytes(data):
        crc = ((crc << 8) & 0xFFFFFFFF) ^ MPEG2_TABLE[((crc >> 24) ^ b) & 0xFF]
    return crc


# --- many fixed-length messages at once -----------------------------------------------------------------


@dataclass(frozen=True)
class PairTables:
    """The CRC of fixed-length messages by linearity (module docstring)::

        crc(msg) = constant ^ XOR_k pairs[k][w_k]        w_k = msg[2k] | msg[2k + 1] << 8

    ``bytes_`` holds the per-byte tables ``T[j, v]`` (for odd lengths).
    """

    constant: int
    pairs: U32Array  #: (m // 2, 65536)
    bytes_: U32Array  #: (m, 256)

    def of_words(self, words: npt.NDArray[np.uint16]) -> U32Array:
        """The CRCs of ``(n, m // 2)`` messages given as byte-pair words ``lo | hi << 8``."""
        crc = np.full(words.shape[0], self.constant, dtype=np.uint32)
        for k in range(words.shape[1]):
            crc ^= self.pairs[k][words[:, k]]
        return crc

    def with_fixed_prefix(self, prefix: bytes) -> PairTables:
        """The tables of the messages' tail after ``prefix`` (an even number of bytes every message starts
        with): ``prefix``'s terms fold into the constant and its pair tables drop."""
        if len(prefix) % 2:
            raise ValueError("the fixed prefix must be an even number of bytes")
        k = len(prefix) // 2
        constant = self.constant
        for j in range(k):
            constant ^= int(self.pairs[j][prefix[2 * j] | prefix[2 * j + 1] << 8])
        return PairTables(constant, self.pairs[k:], self.bytes_[2 * k :])


def _pairs_of(byte_tables: U32Array) -> U32Array:
    """``P[k, lo | hi << 8] = T[2k, lo] ^ T[2k + 1, hi]`` for the byte tables ``T`` (an even count)."""
    m = byte_tables.shape[0]
    return (byte_tables[0 : m - 1 : 2, None, :] ^ byte_tables[1::2, :, None]).reshape(m // 2, 65536)


@functools.lru_cache(maxsize=16)
def iso_hdlc_tables(m: int) -> PairTables:
    """``PairTables`` of CRC-32/ISO-HDLC for messages of ``m`` bytes.

    ``T[j, v]`` is the byte table (register from 0 after ``v``) advanced through the ``m - 1 - j`` zero
    bytes after it; the constant is the CRC of ``m`` zero bytes."""
    tables = np.empty((m, 256), dtype=np.uint32)
    reg = ISO_HDLC_TABLE.copy()
    for j in range(m - 1, -1, -1):
        tables[j] = reg
        reg = ISO_HDLC_TABLE[reg & 0xFF] ^ (reg >> np.uint32(8))  # one more zero byte after
    return PairTables(crc32(bytes(m)), _pairs_of(tables), tables)


@functools.lru_cache(maxsize=16)
def mpeg2_tables(m: int) -> PairTables:
    """``PairTables`` of CRC-32/MPEG-2 for messages of ``m`` bytes (as ``iso_hdlc_tables``, MSB first)."""
    tables = np.empty((m, 256), dtype=np.uint32)
    reg = MPEG2_TABLE_NP.copy()
    for j in range(m - 1, -1, -1):
        tables[j] = reg
        reg = (reg << np.uint32(8)) ^ MPEG2_TABLE_NP[reg >> np.uint32(24)]  # one more zero byte after
    return PairTables(crc32_mpeg2_reference(bytes(m)), _pairs_of(tables), tables)


def _rows_crc(tables: PairTables, rows: npt.NDArray[np.uint8]) -> U32Array:
    n, m = rows.shape
    if n == 0:
        return np.zeros(0, dtype=np.uint32)
    if m % 2 == 0:  # columns of byte pairs lo | hi << 8 (whatever the host order), one gather per column
        table, columns = tables.pairs, np.ascontiguousarray(np.ascontiguousarray(rows).view("<u2").T)
    else:
        table, columns = tables.bytes_, np.ascontiguousarray(rows.T)
    crc = np.full(n, tables.constant, dtype=np.uint32)
    for k in range(columns.shape[0]):
        crc ^= table[k].take(columns[k])
    return crc


def crc32_rows(rows: npt.NDArray[np.uint8]) -> U32Array:
    """CRC-32/ISO-HDLC of every row of a ``(n, m)`` uint8 array at once (``crc32`` of each, bit for bit)."""
    return _rows_crc(iso_hdlc_tables(rows.shape[1]), rows)


def crc32_mpeg2_rows(rows: npt.NDArray[np.uint8]) -> U32Array:
    """CRC-32/MPEG-2 of every row of a ``(n, m)`` uint8 array at once (``crc32_mpeg2`` of each, bit for bit).

    For a fixed length m, ``crc(msg) = crc(m zero bytes) XOR T[0, msg[0]] XOR ... XOR T[m-1, msg[m-1]]``
    (module docstring): m table gathers (one per column, vectorized across frames) xor-ed together; for
    even m the gathers are over byte pairs (m / 2 lookups per frame in 65536-entry tables).
    """
    return _rows_crc(mpeg2_tables(rows.shape[1]), rows)


__all__ = [
    "CHECK_ISO_HDLC",
    "CHECK_MPEG2",
    "ISO_HDLC_TABLE",
    "MPEG2_TABLE",
    "MPEG2_TABLE_NP",
    "POLY",
    "POLY_REFLECTED",
    "PairTables",
    "crc32",
    "crc32_mpeg2",
    "crc32_mpeg2_reference",
    "crc32_mpeg2_rows",
    "crc32_reference",
    "crc32_rows",
    "iso_hdlc_tables",
    "mpeg2_tables",
]
