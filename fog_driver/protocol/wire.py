"""Wire protocol v1: constants, frame events and encoders.

The specification is ``firmware_protocol/PROTOCOL.md`` (with its golden vectors and C
reference encoder).  A frame is::

    sync(0xAA 0x55) | type u8 | len u8 | payload[len] | crc32 u32 LE

with the CRC-32/ISO-HDLC (zlib's ``crc32``) computed over ``type``, ``len`` and
``payload``.  Everything here is pure: no I/O, no clock.
"""

from __future__ import annotations

import struct
from typing import NamedTuple

from .crc import crc32

SYNC = b"\xaa\x55"
SYNC0 = 0xAA
SYNC1 = 0x55
HEADER_LEN = 4  # sync (2) + type (1) + len (1)
CRC_LEN = 4
OVERHEAD_LEN = HEADER_LEN + CRC_LEN
MAX_FRAME_LEN = OVERHEAD_LEN + 255

TYPE_SAMPLE = 0x01
TYPE_IDENTITY = 0x02

SAMPLE_PAYLOAD_LEN = 18
IDENTITY_PAYLOAD_LEN = 24
SAMPLE_FRAME_LEN = OVERHEAD_LEN + SAMPLE_PAYLOAD_LEN  # 26
IDENTITY_FRAME_LEN = OVERHEAD_LEN + IDENTITY_PAYLOAD_LEN  # 32

#: Payload length of every type this decoder knows.  A known type with any
#: other length is corrupt (one byte is discarded and the hunt goes on).
KNOWN_PAYLOAD_LEN = {TYPE_SAMPLE: SAMPLE_PAYLOAD_LEN, TYPE_IDENTITY: IDENTITY_PAYLOAD_LEN}

SEQ_MODULUS = 1 << 16
T_US_MODULUS = 1 << 32

#: Thermometer value meaning "no valid reading" (0x8000 as i16).
THERMOMETER_INVALID = -32768
#: Thermometer resolution: counts per degC.
THERMOMETER_COUNTS_PER_C = 256.0

# SAMPLE status bits (bits 5-15 are reserved: kept, not interpreted).
STATUS_LIGHT_SOURCE_FAULT = 1 << 0
STATUS_LOOP_UNLOCKED = 1 << 1
STATUS_THERMOMETER_FAULT = 1 << 2
STATUS_OVER_RANGE = 1 << 3
STATUS_STARTUP = 1 << 4
STATUS_BIT_NAMES = {
    STATUS_LIGHT_SOURCE_FAULT: "light_source_fault",
    STATUS_LOOP_UNLOCKED: "loop_unlocked",
    STATUS_THERMOMETER_FAULT: "thermometer_fault",
    STATUS_OVER_RANGE: "over_range",
    STATUS_STARTUP: "startup",
}

_SAMPLE_STRUCT = struct.Struct("<HIihhhH")
_IDENTITY_STRUCT = struct.Struct("<16sHHf")
_HEADER_STRUCT = struct.Struct("<2sBB")
_CRC_STRUCT = struct.Struct("<I")


class SampleFrame(NamedTuple):
    """A decoded SAMPLE frame, wire values unchanged (no scaling, no unwrapping)."""

    offset: int  #: stream position of the frame's first sync byte
    seq: int  #: u16, +1 per SAMPLE frame
    t_us: int  #: u32 instrument clock, microseconds
    dtheta_counts: int  #: i32 angle increment since the previous SAMPLE
    t_top_raw: int  #: i16, 1/256 degC, -32768 = no reading
    t_bottom_raw: int
    t_housing_raw: int
    status: int  #: u16 status bits


class IdentityFrame(NamedTuple):
    """A decoded IDENTITY frame."""

    offset: int
    serial: str  #: ASCII, NUL padding removed
    firmware: int  #: (major << 8) + minor
    rate_hz: int  #: nominal SAMPLE rate
    scale_arcsec_per_count: float  #: the f32 on the wire, widened exactly to float

    @property
    def firmware_version(self) -> str:
        return f"{self.firmware >> 8}.{self.firmware & 0xFF}"


class UnknownFrame(NamedTuple):
    """A CRC-valid frame of a type this decoder does not know (skipped, counted)."""

    offset: int
    frame_type: int
    payload: bytes


Event = SampleFrame | IdentityFrame | UnknownFrame


def encode_frame(frame_type: int, payload: bytes) -> bytes:
    """Frame any payload: ``AA 55 type len payload crc32(type len payload)``."""
    if not 0 <= frame_type <= 0xFF:
        raise ValueError(f"frame type {frame_type} is not a byte")
    if len(payload) > 255:
        raise ValueError(f"payload of {len(payload)} bytes exceeds 255")
    body = bytes((frame_type, len(payload))) + bytes(payload)
    return SYNC + body + _CRC_STRUCT.pack(crc32(body))


def encode_sample(
    seq: int,
    t_us: int,
    dtheta_counts: int,
    t_top_raw: int,
    t_bottom_raw: int,
    t_housing_raw: int,
    status: int = 0,
) -> bytes:
    """Encode one SAMPLE frame (26 bytes).  ``seq`` and ``t_us`` are wrapped here."""
    payload = _SAMPLE_STRUCT.pack(
        seq % SEQ_MODULUS,
        t_us % T_US_MODULUS,
        dtheta_counts,
        t_top_raw,
        t_bottom_raw,
        t_housing_raw,
        status,
    )
    return encode_frame(TYPE_SAMPLE, payload)


def encode_identity(serial: str, firmware: int, rate_hz: int, scale_arcsec_per_count: float) -> bytes:
    """Encode one IDENTITY frame (32 bytes).  ``serial`` is ASCII, at most 16 bytes."""
    serial_bytes = serial.encode("ascii")
    if len(serial_bytes) > 16:
        raise ValueError(f"serial {serial!r} is longer than 16 bytes")
    payload = _IDENTITY_STRUCT.pack(serial_bytes, firmware, rate_hz, scale_arcsec_per_count)
    return encode_frame(TYPE_IDENTITY, payload)


def encode_event(event: Event) -> bytes:
    """Re-encode a decoded event.

    Gives back the exact bytes it came from for any frame a conforming encoder
    wrote; an IDENTITY serial that broke the "ASCII, NUL-padded" rule (bytes
    after the first NUL, non-ASCII bytes) does not survive decoding unchanged.
    """
    if isinstance(event, SampleFrame):
        return encode_sample(*event[1:])
    if isinstance(event, IdentityFrame):
        return encode_identity(event.serial, event.firmware, event.rate_hz, event.scale_arcsec_per_count)
    return encode_frame(event.frame_type, event.payload)


def parse_sample_payload(offset: int, payload: bytes | memoryview) -> SampleFrame:
    return SampleFrame(offset, *_SAMPLE_STRUCT.unpack(payload))


def parse_identity_payload(offset: int, payload: bytes | memoryview) -> IdentityFrame:
    serial, firmware, rate_hz, scale = _IDENTITY_STRUCT.unpack(payload)
    return IdentityFrame(offset, _decode_serial(serial), firmware, rate_hz, scale)


def _decode_serial(raw: bytes) -> str:
    # NUL-padded ASCII; anything non-ASCII is shown escaped rather than raising.
    return raw.split(b"\0", 1)[0].decode("ascii", errors="backslashreplace")


def status_names(status: int) -> list[str]:
    """Names of the set status bits; reserved bits appear as ``reserved_bitN``."""
    names = []
    for bit in range(16):
        mask = 1 << bit
        if status & mask:
            names.append(STATUS_BIT_NAMES.get(mask, f"reserved_bit{bit}"))
    return names
