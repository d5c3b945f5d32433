"""iXblue (Exail) STDBIN navigation telegrams, protocol versions 2 to 5 (Phins, Octans, Rovins, ...).

Sans-IO streaming decoder in the style of ``fog_driver.protocol.FrameDecoder``: ``feed(bytes) -> events``,
``close()``, ``counters``; never raises on data, never hangs, ONE-byte resync on a bad checksum or an
impossible header, the decision at a header position depends only on the bytes from there on (any
chunking gives the same events and counters), and every byte is accounted for::

    bytes_in == bytes_in_frames + bytes_discarded + pending

Layout, all fields big-endian (verified against iXblue's open-source ``ixblue_stdbin_decoder``,
``src/stdbin_decoder.cpp`` ``parseHeader`` / ``HEADER_SIZE_V2..V5`` and ``src/memory_block_parser.cpp``
(``big_to_native``), and against the real captures of its ``test/datasets/log_STDBIN_V{2,3,4,5}.log`` and of
``ixblue_ins_stdbin_driver/ixblue_ins_driver/test/datas/stdbin_V{2,3,5}_2Hz.pcapng``, whose telegram sizes
equal header + the blocks below + checksum exactly)::

    offset  size  field
    0       2     'I' 'X'
    2       1     protocol version (2..5)
    3       4     navigation-data bitmask
    (v>=3)  4     extended-navigation-data bitmask
    .       4     external-data bitmask
    (v>=4)  2     navigation size: in every capture = the navigation + extended-navigation blocks' bytes
                  (their external masks are all 0, so "everything between header and checksum" cannot be
                  told apart; the field is read, not checked)
    .       2     telegram size, header to checksum inclusive
    .       4     navigation-data validity time, uint32, 100 us steps (wraps after 2^32 * 100 us = 4.97 d)
    .       4     counter, uint32
    header: 21 bytes (v2), 25 (v3), 27 (v4, v5)
    then the navigation blocks, the extended-navigation blocks, the external-data blocks, each section in
    ascending bit order, each block of a fixed size (``NAV_BLOCK_LEN`` etc.; the same in v2..v5: the real
    v2..v5 captures above all fit these sizes, and the reference decoder has no per-version size)
    last 4  checksum, uint32: the sum of every preceding byte of the telegram, mod 2^32

Blocks decoded (navigation bitmask bit: content), float32 unless said::

    0  attitude: heading, roll, pitch (deg)                       -> extra heading_deg, roll_deg, pitch_deg
    5  rotation rate, vessel frame XV1, XV2, XV3 (deg/s, compensated from earth rotation)
                                                                  -> rate_dph = deg/s * 3600 (x, y, z)
    6  acceleration, vessel frame XV1..XV3 (m/s^2)                -> extra accel_x_mps2 ...
    14 sensor status: 2 x uint32                                  -> extra sensor_status_1, _2 (raw)
    15 INS algorithm status: 4 x uint32                           -> status (word k in bits 32k..32k+31)
    18 AHRS algorithm status: uint32                              -> extra ahrs_algorithm_status (raw)
    25 temperatures: mean FOG, mean accelerometer, board (degC)  -> temps_c fog, accelerometer, board
    extended-navigation bit 2: raw rotation rate, vessel frame XV1..XV3 (deg/s, NOT compensated from earth
       rotation)                                                  -> extra raw_rate_x_dph ... (deg/h)

Every other block present is skipped by its size and counted (``counters.blocks_skipped``).  Flags:
``startup`` when INS algorithm status word 1 bit 1 (ALIGNMENT) is set (``ixblue_stdbin_decoder``
``INSAlgorithmStatus::Status1``; ``ixblue_ins_stdbin_driver`` diagnostics: "System in alignment, do not
move").  The sensor-status and AHRS-status bits have no public meaning, so they are kept raw and mapped to
no flag (no ``sensor_invalid`` from this format).

Time and increments: ``t_s`` = unwrapped validity time * 1e-4 s (device time; a step of more than half
the 2^32 range backwards is a small step back, not a wrap).  The rotation-rate block is an instantaneous
rate, so ``from_rate`` is True, ``rate_dph`` is the rate as sent and ``dtheta_arcsec = rate_dph * dt_s``
(1 deg/h over 1 s is 1 arcsec) where ``dt_s`` is the validity-time step from the previous valid telegram
(the true sample interval, also across a gap of lost telegrams), or ``1 / rate_hz`` when there is no
previous telegram or the step is not positive, or NaN when ``rate_hz`` was not given.  ``seq`` is the
counter unwrapped by ``SeqUnwrapper(2**32)``.  A telegram without the rotation-rate block gives no sample
(``other_frames``).  An impossible header (unknown version, or a telegram size that differs from header +
announced blocks + checksum, or, when a bit of unknown size is set, one too small for the known blocks or
above ``MAX_UNVERIFIED_LEN``) costs one byte (``length_errors``).  STDBIN telegrams are variable-length: there is no
fixed-stride batch path.

Answer telegrams (replies to commands), ``ixblue_stdbin_decoder`` ``parseHeader`` / ``ANSWER_HEADER_SIZE``::

    'A' 'N', protocol version (3..5), telegram size (uint16, whole telegram), payload, checksum (as above)

give a ``StdbinAnswer`` event (``other_frames``, ``answer_frames``); an answer with another version or a
size below 9 bytes is impossible (one byte).
"""

from __future__ import annotations

import functools
import math
import re
import struct
from dataclasses import dataclass
from types import MappingProxyType

from ..flags import SAMPLE_STARTUP
from ..protocol.hunting import HuntingDecoder
from ..protocol.sequence import Unwrapper
from .common import FormatCounters, ImuSample, SeqUnwrapper

SYNC = b"IX"
ANSWER_SYNC = b"AN"
_SYNC_RE = re.compile(b"IX|AN")
_SYNC_FIRST = frozenset(b"IA")
VERSIONS = (2, 3, 4, 5)
ANSWER_VERSIONS = (3, 4, 5)
ANSWER_HEADER_LEN = 5
HEADER_LEN = {2: 21, 3: 25, 4: 27, 5: 27}  #: bytes before the first block, per protocol version
CHECKSUM_LEN = 4
MAX_TELEGRAM_LEN = 0xFFFF  #: the telegram-size field is 16 bits
#: A telegram with a block of unknown size cannot have its size checked against its blocks: such a header is
#: believed up to this size only (the real telegrams are a few hundred bytes).  Without the cap, a false
#: header that claims 65,535 bytes holds a live stream's output back until that many bytes have arrived.
MAX_UNVERIFIED_LEN = 4096
TIME_LSB_S = 1e-4  #: validity time step (100 us)
TIME_MODULUS = 1 << 32
COUNTER_MODULUS = 1 << 32

#: Navigation-data block sizes in bytes by bit (``ixblue_stdbin_decoder`` memory_blocs_parsers/navigation_data).
NAV_BLOCK_LEN = (
    12,
    12,
    16,
    8,
    12,
    12,
    12,
    21,
    16,
    12,
    12,
    8,
    8,
    4,
    8,
    16,  # 0..15
    12,
    4,
    4,
    12,
    4,
    12,
    12,
    12,
    8,
    12,
    16,
    12,
    12,
    12,
    12,  # 16..30
)
#: Extended-navigation block sizes by bit (v3+).
EXTNAV_BLOCK_LEN = (12, 12, 12, 12, 12, 21, 16)
#: External-data block sizes by bit; None: a bit the reference decoder does not know (size unknown).
EXTERNAL_BLOCK_LEN = (
    5,
    46,
    46,
    46,
    13,
    13,
    49,
    49,
    49,
    12,
    37,
    33,
    8,
    8,
    41,
    41,  # 0..15
    41,
    41,
    9,
    9,
    9,
    37,
    33,
    None,
    16,
    17,
    17,
    12,  # 16..27
)

BIT_ATTITUDE = 0
BIT_ROTATION_RATE = 5
BIT_ACCELERATION = 6
BIT_SENSOR_STATUS = 14
BIT_INS_ALGORITHM_STATUS = 15
BIT_AHRS_ALGORITHM_STATUS = 18
BIT_TEMPERATURES = 25
EXTNAV_BIT_RAW_ROTATION_RATE = 2
INS_ALGO1_ALIGNMENT = 1 << 1  #: INS algorithm status word 1: alignment in progress

_F3 = struct.Struct(">3f")
_U32 = struct.Struct(">I")
_HEADER_TAIL = struct.Struct(">HII")  # telegram size, validity time, counter


def _table(table: tuple[int | None, ...], n: int) -> list[int | None]:
    return [table[b] if b < len(table) else None for b in range(n)]


_NAV = _table(NAV_BLOCK_LEN, 32)
_EXTNAV = _table(EXTNAV_BLOCK_LEN, 32)
_EXTERNAL = _table(EXTERNAL_BLOCK_LEN, 32)


def _blocks_len(mask: int, table: list[int | None]) -> tuple[int, int]:
    """(bytes of the known blocks, number of set bits of unknown size) for ``mask``."""
    total = unknown = 0
    bit = 0
    while mask:
        if mask & 1:
            size = table[bit]
            if size is None:
                unknown += 1
            else:
                total += size
        mask >>= 1
        bit += 1
    return total, unknown


@dataclass
class StdbinCounters(FormatCounters):
    """``FormatCounters`` plus what STDBIN adds."""

    version_errors: int = 0  #: 'IX' positions with an unknown protocol version (also in length_errors)
    blocks_skipped: int = 0  #: blocks of valid telegrams skipped by size, not decoded
    unknown_blocks: int = 0  #: set bitmask bits of unknown size in valid telegrams
    time_wraps: int = 0  #: validity-time wraps (2^32 x 100 us)
    answer_frames: int = 0  #: valid 'AN' answer telegrams (also in other_frames)


@dataclass(frozen=True)
class StdbinAnswer:
    """An 'AN' answer telegram: its protocol version and payload (between header and checksum)."""

    version: int
    payload: bytes


class StdbinDecoder(HuntingDecoder[ImuSample | StdbinAnswer, StdbinCounters]):
    """Streaming STDBIN decoder: bytes in, ``ImuSample`` events out.

    ``rate_hz``: the configured output rate, used for the increment of a telegram with no usable previous
    validity time (the first one); None leaves that increment NaN.
    """

    def __init__(self, rate_hz: float | None = None) -> None:
        self.rate_hz = rate_hz
        super().__init__(StdbinCounters())
        self._seq = SeqUnwrapper(COUNTER_MODULUS, self.counters)
        self._time = Unwrapper(TIME_MODULUS, signed=True)

    def _find(self, buf: bytearray, pos: int) -> int:
        found = _SYNC_RE.search(buf, pos)
        return -1 if found is None else found.start()

    def _may_begin(self, byte: int) -> bool:
        return byte in _SYNC_FIRST

    def _emit(self, buf: bytearray, pos: int, n: int, events: list[ImuSample | StdbinAnswer]) -> None:
        c = self.counters
        telegram = bytes(buf[pos : pos + n])
        if telegram[0] == ANSWER_SYNC[0]:
            c.answer_frames += 1
            c.other_frames += 1
            events.append(StdbinAnswer(telegram[2], telegram[ANSWER_HEADER_LEN:-CHECKSUM_LEN]))
        else:
            sample = self._telegram(telegram, self._base + pos)
            if sample is not None:
                events.append(sample)

    def _judge(self, buf: bytearray, pos: int, end: int, final: bool) -> int | None:
        """At an 'IX' or 'AN': the telegram length if a valid telegram starts here, 0 if not (counted),
        None to wait for more bytes."""
        c = self.counters
        have = end - pos
        if have < 3:
            return self._short(final)
        version = buf[pos + 2]
        if buf[pos] == ANSWER_SYNC[0]:
            if version not in ANSWER_VERSIONS:
                c.version_errors += 1
                c.length_errors += 1
                return 0
            if have < ANSWER_HEADER_LEN:
                return self._short(final)
            size = struct.unpack_from(">H", buf, pos + 3)[0]
            if size < ANSWER_HEADER_LEN + CHECKSUM_LEN:
                c.length_errors += 1
                return 0
            return self._check(buf, pos, end, size, final)
        if version not in HEADER_LEN:
            c.version_errors += 1
            c.length_errors += 1
            return 0
        header_len = HEADER_LEN[version]
        if have < header_len:
            return self._short(final)
        nav_mask, extnav_mask, external_mask, size = _header_masks(buf, pos, version)
        known, unknown = _masks_len(nav_mask, extnav_mask, external_mask)
        known += header_len + CHECKSUM_LEN
        if (size != known) if unknown == 0 else not (known + unknown <= size <= MAX_UNVERIFIED_LEN):
            c.length_errors += 1
            return 0
        return self._check(buf, pos, end, size, final)

    def _check(self, buf: bytearray, pos: int, end: int, size: int, final: bool) -> int | None:
        """``size`` if the checksum of the telegram of ``size`` bytes at ``pos`` holds, else 0 (None: wait)."""
        c = self.counters
        if end - pos < size:
            return self._short(final)
        body_end = pos + size - CHECKSUM_LEN
        if sum(buf[pos:body_end]) & 0xFFFFFFFF != _U32.unpack_from(buf, body_end)[0]:
            c.crc_errors += 1
            return 0
        return size

    def _telegram(self, t: bytes, offset: int) -> ImuSample | None:
        """Decode one checksum-valid telegram (its bytes, header to checksum)."""
        c = self.counters
        version = t[2]
        nav_mask, extnav_mask, external_mask, _ = _header_masks(t, 0, version)
        time_raw, counter = struct.unpack_from(">II", t, HEADER_LEN[version] - 8)
        seq = self._seq.step(counter)
        dt_s = self._step_time(time_raw)
        t_s = self._time.value * TIME_LSB_S

        blocks, raw_rate_at, skipped, unknown = _layout(HEADER_LEN[version], nav_mask, extnav_mask, external_mask)
        c.blocks_skipped += skipped
        c.unknown_blocks += unknown

        if BIT_ROTATION_RATE not in blocks:
            c.other_frames += 1
            return None
        rate_dph = tuple(r * 3600.0 for r in _F3.unpack_from(t, blocks[BIT_ROTATION_RATE]))
        if dt_s is None or dt_s <= 0:
            dt_s = 1.0 / self.rate_hz if self.rate_hz else math.nan
        dtheta = tuple(r * dt_s for r in rate_dph)

        extra: dict[str, float] = {}
        if raw_rate_at is not None:
            raw = _F3.unpack_from(t, raw_rate_at)
            extra.update(zip(("raw_rate_x_dph", "raw_rate_y_dph", "raw_rate_z_dph"), (r * 3600.0 for r in raw)))
        if BIT_ATTITUDE in blocks:
            extra["heading_deg"], extra["roll_deg"], extra["pitch_deg"] = _F3.unpack_from(t, blocks[BIT_ATTITUDE])
        if BIT_ACCELERATION in blocks:
            acc = _F3.unpack_from(t, blocks[BIT_ACCELERATION])
            extra.update(zip(("accel_x_mps2", "accel_y_mps2", "accel_z_mps2"), acc))
        if BIT_SENSOR_STATUS in blocks:
            s1, s2 = struct.unpack_from(">II", t, blocks[BIT_SENSOR_STATUS])
            extra["sensor_status_1"], extra["sensor_status_2"] = float(s1), float(s2)
        if BIT_AHRS_ALGORITHM_STATUS in blocks:
            extra["ahrs_algorithm_status"] = float(_U32.unpack_from(t, blocks[BIT_AHRS_ALGORITHM_STATUS])[0])
        status = 0
        flags: set[str] = set()
        if BIT_INS_ALGORITHM_STATUS in blocks:
            words = struct.unpack_from(">4I", t, blocks[BIT_INS_ALGORITHM_STATUS])
            status = sum(w << (32 * k) for k, w in enumerate(words))
            if words[0] & INS_ALGO1_ALIGNMENT:
                flags.add(SAMPLE_STARTUP)
        temps: dict[str, float] = {}
        if BIT_TEMPERATURES in blocks:
            temps = dict(zip(("fog", "accelerometer", "board"), _F3.unpack_from(t, blocks[BIT_TEMPERATURES])))
        c.sample_frames += 1
        return ImuSample(
            seq=seq,
            t_s=t_s,
            dtheta_arcsec=dtheta,
            rate_dph=rate_dph,
            temps_c=temps,
            flags=frozenset(flags),
            status=status,
            from_rate=True,
            extra=extra,
            offset=offset,
        )

    def _step_time(self, raw: int) -> float | None:
        """Unwrap the validity time (a step of half the range or more is a step back); return the step from
        the previous telegram in s (None: first)."""
        time = self._time
        wraps = time.wraps
        step = time.step(raw)
        self.counters.time_wraps += time.wraps - wraps
        return None if step is None else step * TIME_LSB_S


_DECODED_BITS = frozenset(
    (
        BIT_ATTITUDE,
        BIT_ROTATION_RATE,
        BIT_ACCELERATION,
        BIT_SENSOR_STATUS,
        BIT_INS_ALGORITHM_STATUS,
        BIT_AHRS_ALGORITHM_STATUS,
        BIT_TEMPERATURES,
    )
)


@functools.lru_cache(maxsize=256)
def _masks_len(nav_mask: int, extnav_mask: int, external_mask: int) -> tuple[int, int]:
    """(bytes of the known blocks, number of set bits of unknown size) of the three masks (``_blocks_len`` of
    each, summed; cached: a unit sends the same masks in every telegram, and the cache is bounded, so a flood
    of false headers with random masks costs what it did without it)."""
    known = unknown = 0
    for mask, table in ((nav_mask, _NAV), (extnav_mask, _EXTNAV), (external_mask, _EXTERNAL)):
        k, u = _blocks_len(mask, table)
        known += k
        unknown += u
    return known, unknown


@functools.lru_cache(maxsize=256)
def _layout(
    header_len: int, nav_mask: int, extnav_mask: int, external_mask: int
) -> tuple[MappingProxyType[int, int], int | None, int, int]:
    """Where a telegram with these masks has its blocks: (decoded navigation bit -> offset in the telegram,
    the raw rotation rate block's offset or None, blocks skipped by size, set bits of unknown size).
    Cached (bounded) as ``_masks_len``."""
    blocks: dict[int, int] = {}
    skipped = unknown = 0
    offset = header_len
    for bit in range(31):
        if nav_mask >> bit & 1:
            if bit in _DECODED_BITS:
                blocks[bit] = offset
            else:
                skipped += 1
            offset += NAV_BLOCK_LEN[bit]
    raw_rate_at = None
    if nav_mask >> 31 & 1:
        unknown += 1
        offset = -1  # the extended blocks' offsets are unknown
    for mask, table in ((extnav_mask, _EXTNAV), (external_mask, _EXTERNAL)):
        for bit in range(32):
            if mask >> bit & 1:
                if table[bit] is None:
                    unknown += 1
                elif table is _EXTNAV and bit == EXTNAV_BIT_RAW_ROTATION_RATE and offset >= 0:
                    raw_rate_at = offset
                else:
                    skipped += 1
                if table is _EXTNAV and offset >= 0:
                    size = table[bit]
                    offset = -1 if size is None else offset + size
    return MappingProxyType(blocks), raw_rate_at, skipped, unknown


def _header_masks(buf: bytes | bytearray, pos: int, version: int) -> tuple[int, int, int, int]:
    """(navigation, extended-navigation (0 in v2), external masks, telegram size) of the header at pos."""
    nav = _U32.unpack_from(buf, pos + 3)[0]
    p = pos + 7
    extnav = 0
    if version >= 3:
        extnav = _U32.unpack_from(buf, p)[0]
        p += 4
    external = _U32.unpack_from(buf, p)[0]
    p += 4
    if version >= 4:
        p += 2  # navigation size
    return nav, extnav, external, struct.unpack_from(">H", buf, p)[0]


def encode_stdbin(
    version: int,
    *,
    counter: int,
    validity_time_100us: int,
    attitude_deg: tuple[float, float, float] | None = None,
    rotation_rate_dps: tuple[float, float, float] | None = None,
    acceleration_mps2: tuple[float, float, float] | None = None,
    sensor_status: tuple[int, int] | None = None,
    ins_algorithm_status: tuple[int, int, int, int] | None = None,
    ahrs_algorithm_status: int | None = None,
    temperatures_c: tuple[float, float, float] | None = None,
    nav_blocks: dict[int, bytes] | None = None,
    extnav_blocks: dict[int, bytes] | None = None,
    external_blocks: dict[int, bytes] | None = None,
) -> bytes:
    """One STDBIN navigation telegram (layout in the module docstring).

    The named blocks are encoded from values; ``nav_blocks`` / ``extnav_blocks`` / ``external_blocks`` add
    raw blocks by bit (their length must be the block's size; extended blocks need version >= 3).  Raises
    ValueError on an unknown version, a wrong block length or a duplicated bit.
    """
    if version not in HEADER_LEN:
        raise ValueError(f"unknown STDBIN version {version}")
    nav = dict(nav_blocks or {})
    named = (
        (BIT_ATTITUDE, attitude_deg, ">3f"),
        (BIT_ROTATION_RATE, rotation_rate_dps, ">3f"),
        (BIT_ACCELERATION, acceleration_mps2, ">3f"),
        (BIT_SENSOR_STATUS, sensor_status, ">2I"),
        (BIT_INS_ALGORITHM_STATUS, ins_algorithm_status, ">4I"),
        (BIT_AHRS_ALGORITHM_STATUS, None if ahrs_algorithm_status is None else (ahrs_algorithm_status,), ">I"),
        (BIT_TEMPERATURES, temperatures_c, ">3f"),
    )
    for bit, values, fmt in named:
        if values is not None:
            if bit in nav:
                raise ValueError(f"navigation bit {bit} given twice")
            nav[bit] = struct.pack(fmt, *values)
    extnav = dict(extnav_blocks or {})
    external = dict(external_blocks or {})
    if version < 3 and extnav:
        raise ValueError("extended navigation blocks need version >= 3")

    def section(blocks: dict[int, bytes], table: list[int | None], name: str) -> tuple[int, bytes]:
        mask = 0
        out = b""
        for bit in sorted(blocks):
            if not 0 <= bit < 32 or table[bit] is None or len(blocks[bit]) != table[bit]:
                raise ValueError(f"{name} block {bit}: unknown bit or wrong length")
            mask |= 1 << bit
            out += blocks[bit]
        return mask, out

    nav_mask, nav_bytes = section(nav, _NAV, "navigation")
    extnav_mask, extnav_bytes = section(extnav, _EXTNAV, "extended navigation")
    external_mask, external_bytes = section(external, _EXTERNAL, "external")
    size = HEADER_LEN[version] + len(nav_bytes) + len(extnav_bytes) + len(external_bytes) + CHECKSUM_LEN
    if size > MAX_TELEGRAM_LEN:
        raise ValueError(f"telegram of {size} bytes exceeds the 16-bit size field")
    header = b"IX" + bytes([version]) + _U32.pack(nav_mask)
    if version >= 3:
        header += _U32.pack(extnav_mask)
    header += _U32.pack(external_mask)
    if version >= 4:
        header += struct.pack(">H", len(nav_bytes) + len(extnav_bytes))
    header += _HEADER_TAIL.pack(size, validity_time_100us % TIME_MODULUS, counter % COUNTER_MODULUS)
    body = header + nav_bytes + extnav_bytes + external_bytes
    return body + _U32.pack(sum(body) & 0xFFFFFFFF)


def encode_stdbin_answer(version: int, payload: bytes) -> bytes:
    """One 'AN' answer telegram (version 3..5) carrying ``payload``; ValueError if it cannot be sent."""
    if version not in ANSWER_VERSIONS:
        raise ValueError(f"answer telegrams exist in versions {ANSWER_VERSIONS}, not {version}")
    size = ANSWER_HEADER_LEN + len(payload) + CHECKSUM_LEN
    if size > MAX_TELEGRAM_LEN:
        raise ValueError(f"telegram of {size} bytes exceeds the 16-bit size field")
    body = ANSWER_SYNC + bytes([version]) + struct.pack(">H", size) + payload
    return body + _U32.pack(sum(body) & 0xFFFFFFFF)
