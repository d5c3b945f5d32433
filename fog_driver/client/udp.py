"""Optional UDP datagrams, one per sample, for stations that prefer a fixed binary record (LabVIEW): the layout
and its decoder (standard library only; the daemon's sender is ``fog_driver.daemon.udp``).

Each datagram is exactly 68 bytes, big-endian (network order), ``struct``
format ``>4sHHQdddddfff``:

======  =====  ================  ====================================================
offset  type   field             meaning
======  =====  ================  ====================================================
0       4s     magic             ``b"FOGA"``
4       u16    version           layout version, 1
6       u16    flags             the compensator's flag word, bit for bit (the ANGLE
                                 object's ``flags`` names): bit 0 gap (frames missing),
                                 1 thermometer_fault, 2 input_stale, 3 uncompensated
                                 (no drift estimate applied), 4 adapting, 5 guard (an
                                 estimate or the adapting reference was rejected),
                                 6 extrapolating (inputs
                                 outside the model's fit range, or its estimate
                                 clipped), 7 substituted (a faulted thermometer
                                 replaced from a healthy one), 8 recovering (the
                                 model settling after a thermometer fault); other
                                 bits reserved, zero
8       u64    seq               sample sequence number (unwrapped, monotonic)
16      f64    t_s               device time, s
24      f64    angle_arcsec      compensated angle, arcsec
32      f64    angle_raw_arcsec  uncompensated angle, arcsec
40      f64    rate_dph          measured rate, deg/h
48      f64    drift_dph         estimated temperature drift, deg/h
56      f32    t_top_c           fiber ring top thermometer, degC
60      f32    t_bottom_c        fiber ring bottom thermometer, degC
64      f32    t_housing_c       housing thermometer, degC
======  =====  ================  ====================================================

In this binary layout NaN (IEEE quiet NaN) is the documented absent value: an
invalid thermometer, or a quantity not computed yet, is sent as NaN (the JSON
protocol omits the key instead).  A receiver checks ``magic`` and ``version``
and ignores datagrams it does not recognise; a future layout gets a new
version number (fields are only ever appended, so a version-1 reader may read
the first 68 bytes of a longer datagram).  UDP may lose or reorder datagrams:
``seq`` tells.
"""

from __future__ import annotations

import struct
from typing import Any

# The compensator's flags, from the leaf that defines them (standard library only).
from ..flags import (
    FLAG_ADAPTING,
    FLAG_BITS,
    FLAG_EXTRAPOLATING,
    FLAG_GAP,
    FLAG_GUARD,
    FLAG_INPUT_STALE,
    FLAG_RECOVERING,
    FLAG_SUBSTITUTED,
    FLAG_THERMOMETER_FAULT,
    FLAG_UNCOMPENSATED,
)

__all__ = [
    "DATAGRAM_FORMAT",
    "DATAGRAM_SIZE",
    "DATAGRAM_STRUCT",
    "DATAGRAM_VERSION",
    "FIELDS",
    "FLAG_ADAPTING",
    "FLAG_BITS",
    "FLAG_EXTRAPOLATING",
    "FLAG_GAP",
    "FLAG_GUARD",
    "FLAG_INPUT_STALE",
    "FLAG_RECOVERING",
    "FLAG_SUBSTITUTED",
    "FLAG_THERMOMETER_FAULT",
    "FLAG_UNCOMPENSATED",
    "MAGIC",
    "decode_datagram",
]

MAGIC = b"FOGA"
DATAGRAM_VERSION = 1
DATAGRAM_FORMAT = ">4sHHQdddddfff"
#: The version-1 layout as a ``struct.Struct`` (the sender packs with it, the decoder unpacks).
DATAGRAM_STRUCT = struct.Struct(DATAGRAM_FORMAT)
DATAGRAM_SIZE = DATAGRAM_STRUCT.size  # 68

#: The sample fields after magic and version, in datagram order.
FIELDS = (
    "flags",
    "seq",
    "t_s",
    "angle_arcsec",
    "angle_raw_arcsec",
    "rate_dph",
    "drift_dph",
    "t_top_c",
    "t_bottom_c",
    "t_housing_c",
)


def decode_datagram(data: bytes) -> dict[str, Any]:
    """The fields of a version-1 datagram (NaN where absent); ValueError if it is not one.

    Bytes beyond the 68 of version 1 are ignored (room for appended fields).
    """
    if len(data) < DATAGRAM_SIZE:
        raise ValueError(f"datagram too short: {len(data)} bytes, a version-1 datagram has {DATAGRAM_SIZE}")
    values = DATAGRAM_STRUCT.unpack_from(data)
    if values[0] != MAGIC:
        raise ValueError(f"bad magic {values[0]!r}, expected {MAGIC!r}")
    if values[1] != DATAGRAM_VERSION:
        raise ValueError(f"datagram version {values[1]}, this decoder reads version {DATAGRAM_VERSION}")
    return {"version": values[1], **dict(zip(FIELDS, values[2:]))}
