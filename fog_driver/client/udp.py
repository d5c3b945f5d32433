"""Optional UDP datagrams, one per sample, for stations that prefer a fixed binary record (LabVIEW): the layout
and its decoder (standard library only; the daemon's sender is ``fog_driver.daemon.udp``).

Each datagram is big-endian (network order): version 1 (the default) is exactly
68 bytes, ``struct`` format ``>4sHHQdddddfff``; version 2 (config ``udp_version: 2``)
is version 1 with one field appended, 72 bytes, ``>4sHHQdddddffff``:

======  =====  ================  ====================================================
offset  type   field             meaning
======  =====  ================  ====================================================
0       4s     magic             ``b"FOGA"``
4       u16    version           layout version, 1 or 2
6       u16    flags             the compensator's flag word, bit for bit (the ANGLE
                                 object's ``flags`` names): bit 0 gap (frames missing),
                                 1 thermometer_fault, 2 input_stale, 3 uncompensated
                                 (no drift estimate applied), 4 adapting, 5 guard (an
                                 estimate or the adapting reference was rejected),
                                 6 extrapolating (inputs
                                 outside the model's fit range, or its estimate
                                 clipped), 7 substituted (a faulted thermometer
                                 replaced from a healthy one), 8 recovering (the
                                 model settling after a thermometer fault), 9
                                 scale_factor (the scale factor learned from table
                                 angles corrects the angle); other bits reserved, zero
8       u64    seq               sample sequence number (unwrapped, monotonic)
16      f64    t_s               device time, s
24      f64    angle_arcsec      compensated angle, arcsec
32      f64    angle_raw_arcsec  uncompensated angle, arcsec
40      f64    rate_dph          measured rate, deg/h
48      f64    drift_dph         estimated temperature drift, deg/h; NaN while there
                                 is no estimate (flag uncompensated)
56      f32    t_top_c           fiber ring top thermometer, degC
60      f32    t_bottom_c        fiber ring bottom thermometer, degC
64      f32    t_housing_c       housing thermometer, degC
68      f32    drift_sigma_dph   (version 2 only) the 1-sigma of the drift estimate's
                                 error as a 1-min mean, deg/h; NaN while there is
                                 no estimate
======  =====  ================  ====================================================

In this binary layout NaN (IEEE quiet NaN) is the documented absent value: an
invalid thermometer, or a quantity not computed yet, is sent as NaN (the JSON
protocol omits the key instead).  A receiver checks ``magic`` and ``version``
and ignores datagrams it does not recognise; a new layout gets a new version
number and only appends fields, so its first bytes are the older layout's (a
receiver of version 1 may read the first 68 bytes of a version-2 datagram).
UDP may lose or reorder datagrams: ``seq`` tells.
"""

from __future__ import annotations

import math
import struct
from typing import Any

__all__ = [
    "DATAGRAM_FORMAT",
    "DATAGRAM_SIZE",
    "DATAGRAM_STRUCT",
    "DATAGRAM_V2_FORMAT",
    "DATAGRAM_V2_SIZE",
    "DATAGRAM_V2_STRUCT",
    "DATAGRAM_VERSION",
    "DATAGRAM_VERSIONS",
    "FIELDS",
    "FIELDS_V2",
    "MAGIC",
    "decode_datagram",
]

MAGIC = b"FOGA"
#: The version sent unless configured otherwise (``udp_version``), and its layout.
DATAGRAM_VERSION = 1
DATAGRAM_FORMAT = ">4sHHQdddddfff"
#: The version-1 layout as a ``struct.Struct`` (the sender packs with it, the decoder unpacks).
DATAGRAM_STRUCT = struct.Struct(DATAGRAM_FORMAT)
DATAGRAM_SIZE = DATAGRAM_STRUCT.size  # 68
#: Version 2: version 1 and ``drift_sigma_dph`` (f32) at byte 68.
DATAGRAM_V2_FORMAT = DATAGRAM_FORMAT + "f"
DATAGRAM_V2_STRUCT = struct.Struct(DATAGRAM_V2_FORMAT)
DATAGRAM_V2_SIZE = DATAGRAM_V2_STRUCT.size  # 72
#: Every layout this module sends and reads, by version.
DATAGRAM_VERSIONS = {1: DATAGRAM_STRUCT, 2: DATAGRAM_V2_STRUCT}

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
#: The fields of version 2, in datagram order.
FIELDS_V2 = (*FIELDS, "drift_sigma_dph")


def decode_datagram(data: bytes) -> dict[str, Any]:
    """The fields of a version-1 or version-2 datagram, ``version`` and every field of ``FIELDS_V2`` (NaN where
    absent: ``drift_sigma_dph`` is NaN in version 1, which has no room for it); ValueError if it is neither.

    Bytes beyond its version's size are ignored (room for appended fields).
    """
    if len(data) < DATAGRAM_SIZE:
        raise ValueError(f"datagram too short: {len(data)} bytes, a version-1 datagram has {DATAGRAM_SIZE}")
    magic, version = struct.unpack_from(">4sH", data)
    if magic != MAGIC:
        raise ValueError(f"bad magic {magic!r}, expected {MAGIC!r}")
    layout = DATAGRAM_VERSIONS.get(version)
    if layout is None:
        raise ValueError(
            f"datagram version {version}, this decoder reads versions {', '.join(map(str, DATAGRAM_VERSIONS))}"
        )
    if len(data) < layout.size:
        raise ValueError(f"datagram too short: {len(data)} bytes, a version-{version} datagram has {layout.size}")
    values = layout.unpack_from(data)[2:]
    return {"version": version, **dict.fromkeys(FIELDS_V2, math.nan), **dict(zip(FIELDS_V2, values))}
