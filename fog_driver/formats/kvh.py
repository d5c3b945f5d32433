"""KVH (EMCORE) DSP-1750 / DSP-1760 / 1775 normal-mode binary output: a sans-IO decoder, a batch decoder, an encoder.

Frame layouts (big-endian throughout; ``f32`` = IEEE-754 single, ``u8``/``u32`` unsigned, ``i16`` signed)::

    Format A, 36 bytes            Format B, 40 bytes            Format C, 38 bytes
    0  header FE 81 FF 55         0  header FE 81 FF 56         0  header FE 81 FF 57
    4  gyro x, y, z  3 x f32      4  gyro x, y, z  3 x f32      4  gyro x, y, z  3 x f32
    16 accel x, y, z 3 x f32      16 accel x, y, z 3 x f32      16 accel x, y, z 3 x f32
    28 status u8                  28 time tag u32 (us)          28 mux word f32 (see below)
    29 sequence u8 (0..127)       32 status u8                  32 status u8
    30 temperature i16            33 sequence u8 (0..127)       33 sequence u8 (0..127)
    32 CRC u32                    34 temperature i16            34 CRC u32
                                  36 CRC u32

    BIT reply "=BIT"/"?BIT" (FE 81 00 AA), 11 bytes: header(4), 6 result bytes, 8-bit checksum
    extended BIT reply        (FE 81 00 AB), 13 bytes: header(4), 8 result bytes, 8-bit checksum

CRC (A, B, C): CRC-32/MPEG-2 -- polynomial 0x04C11DB7, init 0xFFFFFFFF, no reflection, no final xor -- over
every byte before the CRC, header included (check value of ``b"123456789"``: 0x0376E6E7).  BIT checksum: the
sum of every byte before it, header included, modulo 256.

Status byte: bit 0/1/2 = gyro x/y/z valid, bit 4/5/6 = accelerometer x/y/z valid (0x77: all valid).  A gyro
axis whose bit is clear gets ``SAMPLE_SENSOR_INVALID``; the raw byte is kept in ``ImuSample.status``.

Format C's mux word carries, by ``sequence mod 4``: 0 -> temperature (degC, f32), 1/2/3 -> magnetometer
x/y/z (gauss).  The sequence counter is 7 bits (0..127); a CRC-valid frame whose sequence byte is above 127
is kept and its counter taken modulo 128.

Sources (the vendor ICD itself was not available here):

* A's layout, the CRC-32/MPEG-2 over the header and data, status 0x77 = all valid, the BIT reply and its
  8-bit sum: real DSP-1750 bytes with their checks (the ROS ``kvh_driver`` package's
  ``kvh_driver/test/kvhtest.cpp``, vendored in github.com/jtukpah/wildfire_hyperdrive_ssrr_2024), and a
  DSP-1750 log showing status ``0b1110111`` (github.com/yoos/kvh_1750_troubleshooting).
* frame sizes 36/40/38 (A/B/C) and 11/13 (BIT AA/AB) and the five headers: KVH's own test script
  ``TestDspImu.pl`` (KVH Industries, 2014) and INSTINCT's ``KvhUartSensor.cpp`` (Univ. of Stuttgart).
* B's time tag (u32 between the accelerations and the status): an OpenDLV-derived ``datagram_parser.cpp``
  Format B parser and a Python Format B decoder of the keelson KVH connector -- not checked on real bytes.
* C's multiplexed word: the keelson KVH connector's notes, which cite OpenDLV's
  ``opendlv-device-imu-kvhp1775`` -- not checked on real bytes.

Units (the decoder's configuration says what the device was set to; the frame does not):

* ``rot_format="delta"``: the gyro word is the angle increment over the sample, in ``rot_units``::

      dtheta_arcsec = g * K          rate_dph = dtheta_arcsec * rate_hz   (1 arcsec/s == 1 deg/h)

* ``rot_format="rate"``: the gyro word is the rate in ``rot_units``/s::

      rate_dph = g * K               dtheta_arcsec = rate_dph / rate_hz   (``from_rate`` True)

  with ``K = 3600`` for ``deg`` (arcsec per degree, and deg/h per deg/s) and ``K = 648000 / pi =
  206264.806...`` for ``rad``.  Without ``rate_hz`` the quantity that needs it is NaN.
* accelerations in g (the DSP-1750/1775 default), reported in ``extra`` as ``accel_x_g`` etc.
* temperature (A, B): ``i16`` in whole degC (``temp_units="c"``) or in 0.01 degC (``"c_100"``, the
  ``=TEMPUNITS`` setting); C: the mux word in degC.  Channel name ``"sensor"``.

Time: normal mode has no device time in Formats A and C; every sample is ``t_s = None``, ``host_time =
True`` and the sample stream times samples (a time derived from ``seq / rate_hz`` would hide dropped frames).
Format B's time tag is passed through raw as ``extra["time_tag_us"]`` (its epoch is not verified), not as
``t_s``.

Framing follows ``fog_driver.protocol.FrameDecoder``: at a header position whose complete frame fails its
check, ONE byte is discarded and the hunt resumes; the decision at a header position depends only on the bytes
from there on, so any chunking gives the same events; ``bytes_in == bytes_in_frames + bytes_discarded +
pending`` at every moment.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..flags import SAMPLE_SENSOR_INVALID
from ..protocol.crc import MPEG2_TABLE, crc32_mpeg2, crc32_mpeg2_reference, crc32_mpeg2_rows
from ..protocol.greedy import greedy_accept
from ..protocol.hunting import HuntingDecoder
from ..protocol.sequence import Unwrapper, count_seq_steps
from .common import FormatCounters, ImuSample, SeqUnwrapper

SYNC = b"\xfe\x81"
SYNC0 = 0xFE
HEADER_LEN = 4
SEQ_MODULUS = 128
#: Status bits 0..2: gyro x, y, z valid (a frame without all three is ``sensor_invalid``).
GYRO_VALID = 0x07

#: sample formats: name -> (fourth header byte, frame length in bytes)
SAMPLE_FORMATS = {"a": (0x55, 36), "b": (0x56, 40), "c": (0x57, 38)}
#: BIT replies: fourth header byte -> frame length in bytes (third header byte 0x00)
BIT_FRAME_LEN = {0xAA: 11, 0xAB: 13}

ARCSEC_PER_DEG = 3600.0
ARCSEC_PER_RAD = 648000.0 / math.pi  # 206264.806...
_ARCSEC_PER_UNIT = {"deg": ARCSEC_PER_DEG, "rad": ARCSEC_PER_RAD}
_TEMP_SCALE = {"c": 1.0, "c_100": 0.01}
_MUX_NAMES = ("temperature", "mag_x_gauss", "mag_y_gauss", "mag_z_gauss")

_BODY = {  # struct of the bytes after the header, up to the CRC
    "a": struct.Struct(">6fBBh"),
    "b": struct.Struct(">6fIBBh"),
    "c": struct.Struct(">6ffBB"),
}
_U32 = struct.Struct(">I")
#: The CRC-32/MPEG-2 byte table (``fog_driver.protocol.crc`` holds the CRCs of every format).
CRC_TABLE = MPEG2_TABLE

# --- events ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class KvhBitFrame:
    """A built-in-test reply: ``kind`` 0xAA (BIT, 6 result bytes) or 0xAB (extended BIT, 8 result bytes).

    Each result byte holds pass bits (0x7F: all tests of that byte passed); they are kept raw."""

    offset: int
    kind: int
    results: bytes


# --- the encoder --------------------------------------------------------------------------------------------


def encode_kvh_frame(
    fmt: str,
    gyro: tuple[float, float, float],
    accel: tuple[float, float, float],
    status: int = 0x77,
    seq: int = 0,
    temp: float = 25,
    time_tag_us: int = 0,
) -> bytes:
    """A normal-mode frame of format ``fmt`` ('a', 'b', 'c') with a correct CRC.

    ``gyro`` and ``accel`` are the words as sent (device units); ``temp`` is the raw ``i16`` for A and B
    and the f32 mux word for C; ``time_tag_us`` is B's time tag.
    """
    fmt = fmt.lower()
    second, _ = SAMPLE_FORMATS[fmt]
    if fmt == "a":
        body = _BODY["a"].pack(*gyro, *accel, status, seq, int(temp))
    elif fmt == "b":
        body = _BODY["b"].pack(*gyro, *accel, time_tag_us, status, seq, int(temp))
    else:
        body = _BODY["c"].pack(*gyro, *accel, float(temp), status, seq)
    frame = bytes((0xFE, 0x81, 0xFF, second)) + body
    return frame + _U32.pack(crc32_mpeg2(frame))


#: numpy dtypes of the frames up to the CRC (big-endian), by format
_FRAME_DTYPE = {
    "a": np.dtype(
        [("header", "u1", 4), ("gyro", ">f4", 3), ("accel", ">f4", 3), ("status", "u1"), ("seq", "u1"), ("temp", ">i2")]
    ),
    "b": np.dtype(
        [
            ("header", "u1", 4),
            ("gyro", ">f4", 3),
            ("accel", ">f4", 3),
            ("time_tag_us", ">u4"),
            ("status", "u1"),
            ("seq", "u1"),
            ("temp", ">i2"),
        ]
    ),
    "c": np.dtype(
        [("header", "u1", 4), ("gyro", ">f4", 3), ("accel", ">f4", 3), ("temp", ">f4"), ("status", "u1"), ("seq", "u1")]
    ),
}


def encode_kvh_frames(
    fmt: str,
    gyro: np.ndarray,
    accel: np.ndarray,
    status: np.ndarray,
    seq: np.ndarray,
    temp: np.ndarray,
    time_tag_us: np.ndarray | None = None,
) -> np.ndarray:
    """Many frames at once: the vector form of ``encode_kvh_frame`` (identical bytes, tested).

    ``gyro`` and ``accel`` are ``(n, 3)`` words as sent; ``status``, ``seq`` (taken mod 128), ``temp`` (the raw
    i16 for A and B, the f32 mux word for C) and B's ``time_tag_us`` one per frame.  Returns an ``(n, length)``
    uint8 array, one frame per row, CRCs by ``crc32_mpeg2_rows``.
    """
    fmt = fmt.lower()
    second, length = SAMPLE_FORMATS[fmt]
    n = len(seq)
    frames = np.zeros(n, dtype=_FRAME_DTYPE[fmt])
    frames["header"] = (0xFE, 0x81, 0xFF, second)
    frames["gyro"] = gyro
    frames["accel"] = accel
    frames["status"] = status
    frames["seq"] = np.asarray(seq) % SEQ_MODULUS
    frames["temp"] = temp
    if fmt == "b":
        frames["time_tag_us"] = np.zeros(n, dtype=np.uint32) if time_tag_us is None else time_tag_us
    body = frames.view(np.uint8).reshape(n, length - 4)
    out = np.empty((n, length), dtype=np.uint8)
    out[:, :-4] = body
    out[:, -4:] = crc32_mpeg2_rows(body).astype(">u4").view(np.uint8).reshape(n, 4)
    return out


def encode_kvh_bit_frame(kind: int, results: bytes) -> bytes:
    """A BIT reply (``kind`` 0xAA with 6 result bytes or 0xAB with 8) with its 8-bit sum checksum."""
    if len(results) != BIT_FRAME_LEN[kind] - 5:
        raise ValueError(f"BIT 0x{kind:02X} carries {BIT_FRAME_LEN[kind] - 5} result bytes")
    frame = bytes((0xFE, 0x81, 0x00, kind)) + bytes(results)
    return frame + bytes((sum(frame) & 0xFF,))


# --- configuration shared by the streaming and the batch decoders ------------------------------------------


@dataclass(frozen=True)
class KvhConfig:
    """How the device was configured (the frames do not say).

    ``format``: 'a', 'b', 'c' or None (accept any of the three headers); ``rot_format``: 'delta' or
    'rate'; ``rot_units``: 'deg' or 'rad'; ``temp_units``: 'c' or 'c_100'; ``rate_hz``: output data
    rate (``=DR``), needed to turn a rate into an increment and back.
    """

    format: str | None = None
    rot_format: str = "delta"
    rot_units: str = "rad"
    temp_units: str = "c"
    rate_hz: float | None = None

    def __post_init__(self) -> None:
        if self.format is not None and self.format not in SAMPLE_FORMATS:
            raise ValueError(f"format must be one of {sorted(SAMPLE_FORMATS)} or None, not {self.format!r}")
        if self.rot_format not in ("delta", "rate"):
            raise ValueError(f"rot_format must be 'delta' or 'rate', not {self.rot_format!r}")
        if self.rot_units not in _ARCSEC_PER_UNIT:
            raise ValueError(f"rot_units must be 'deg' or 'rad', not {self.rot_units!r}")
        if self.temp_units not in _TEMP_SCALE:
            raise ValueError(f"temp_units must be 'c' or 'c_100', not {self.temp_units!r}")
        if self.rate_hz is not None and not self.rate_hz > 0:
            raise ValueError("rate_hz must be > 0")

    def accepted_seconds(self) -> dict[int, tuple[str, int]]:
        """Fourth header byte -> (format, frame length) for the sample formats accepted."""
        return {b: (name, n) for name, (b, n) in SAMPLE_FORMATS.items() if self.format in (None, name)}


_VALID: frozenset[str] = frozenset()
_INVALID = frozenset((SAMPLE_SENSOR_INVALID,))


def _make_sample(cfg: KvhConfig, fmt: str, values: tuple[Any, ...], seq_unwrapped: int, offset: int) -> ImuSample:
    k = _ARCSEC_PER_UNIT[cfg.rot_units]
    gx, gy, gz = values[0:3]
    extra = {"accel_x_g": values[3], "accel_y_g": values[4], "accel_z_g": values[5]}
    temps: dict[str, float] = {}
    if fmt == "a":
        status, seq, temp_raw = values[6:9]
        temps["sensor"] = temp_raw * _TEMP_SCALE[cfg.temp_units]
    elif fmt == "b":
        time_tag, status, seq, temp_raw = values[6:10]
        temps["sensor"] = temp_raw * _TEMP_SCALE[cfg.temp_units]
        extra["time_tag_us"] = float(time_tag)
    else:
        mux, status, seq = values[6:9]
        slot = seq % 4
        if slot == 0:
            temps["sensor"] = mux
        else:
            extra[_MUX_NAMES[slot]] = mux
    rate_hz = cfg.rate_hz
    if cfg.rot_format == "delta":
        dx, dy, dz = dtheta = (gx * k, gy * k, gz * k)
        rate = (dx * rate_hz, dy * rate_hz, dz * rate_hz) if rate_hz else (math.nan,) * 3
        from_rate = False
    else:
        rx, ry, rz = rate = (gx * k, gy * k, gz * k)
        dtheta = (rx / rate_hz, ry / rate_hz, rz / rate_hz) if rate_hz else (math.nan,) * 3
        from_rate = True
    flags = _VALID if status & GYRO_VALID == GYRO_VALID else _INVALID
    return ImuSample(
        seq=seq_unwrapped,
        t_s=None,
        dtheta_arcsec=dtheta,
        rate_dph=rate,
        temps_c=temps,
        flags=flags,
        status=status,
        from_rate=from_rate,
        host_time=True,
        extra=extra,
        offset=offset,
    )


Event = ImuSample | KvhBitFrame


class KvhDecoder(HuntingDecoder[Event, FormatCounters]):
    """Streaming KVH normal-mode decoder: ``feed(bytes) -> list[ImuSample | KvhBitFrame]``, ``close()``.

    >>> frame = encode_kvh_frame("a", (0.0, 0.0, 1e-6), (0.0, 0.0, 1.0), seq=5, temp=30)
    >>> d = KvhDecoder(format="a", rot_format="delta", rot_units="rad", rate_hz=1000)
    >>> d.feed(frame[:7]), d.feed(frame[7:])[0].seq
    ([], 5)
    """

    def __init__(
        self,
        format: str | None = None,
        rot_format: str = "delta",
        rot_units: str = "rad",
        temp_units: str = "c",
        rate_hz: float | None = None,
    ) -> None:
        self.config = KvhConfig(format, rot_format, rot_units, temp_units, rate_hz)
        self._seconds = self.config.accepted_seconds()
        super().__init__(FormatCounters())
        self._unwrap = SeqUnwrapper(SEQ_MODULUS, self.counters)

    def _find(self, buf: bytearray, pos: int) -> int:
        return buf.find(SYNC, pos)

    def _may_begin(self, byte: int) -> bool:
        return byte == SYNC0

    def _judge(self, buf: bytearray, pos: int, end: int, final: bool) -> int | None:
        c = self.counters
        if end - pos < HEADER_LEN:
            return None if not final else 0  # too short to be a header: no frame was cut off
        b2 = buf[pos + 2]
        b3 = buf[pos + 3]
        if b2 == 0xFF and b3 in self._seconds:
            frame_len = self._seconds[b3][1]
            check_len = 4
        elif b2 == 0x00 and b3 in BIT_FRAME_LEN:
            frame_len = BIT_FRAME_LEN[b3]
            check_len = 1
        else:
            return 0  # FE 81 not followed by a known header
        if end - pos < frame_len:
            return self._short(final)
        check_at = pos + frame_len - check_len
        if check_len == 4:
            ok = crc32_mpeg2(buf[pos:check_at]) == _U32.unpack_from(buf, check_at)[0]
        else:
            ok = sum(buf[pos:check_at]) & 0xFF == buf[check_at]
        if not ok:
            c.crc_errors += 1
            return 0
        return frame_len

    def _emit(self, buf: bytearray, pos: int, n: int, events: list[Event]) -> None:
        c = self.counters
        b3 = buf[pos + 3]
        if buf[pos + 2] == 0xFF:
            fmt = self._seconds[b3][0]
            values = _BODY[fmt].unpack_from(buf, pos + HEADER_LEN)
            seq_raw = values[-2] if fmt != "c" else values[-1]
            events.append(
                _make_sample(self.config, fmt, values, self._unwrap.step(seq_raw % SEQ_MODULUS), self._base + pos)
            )
            c.sample_frames += 1
        else:
            events.append(KvhBitFrame(self._base + pos, b3, bytes(buf[pos + HEADER_LEN : pos + n - 1])))
            c.other_frames += 1


# --- the batch decoder ---------------------------------------------------------------------------------------

_DTYPES = {
    "a": np.dtype([("g", ">f4", 3), ("a", ">f4", 3), ("status", "u1"), ("seq", "u1"), ("temp", ">i2")]),
    "b": np.dtype([("g", ">f4", 3), ("a", ">f4", 3), ("tag", ">u4"), ("status", "u1"), ("seq", "u1"), ("temp", ">i2")]),
    "c": np.dtype([("g", ">f4", 3), ("a", ">f4", 3), ("mux", ">f4"), ("status", "u1"), ("seq", "u1")]),
}


@dataclass
class KvhBatch:
    """The frames of a whole buffer decoded at once, as arrays in stream order (one row per frame).

    ``kind`` is the fourth header byte (0x55/0x56/0x57 samples, 0xAA/0xAB BIT replies).  Sample rows carry
    ``gyro`` (device words, n x 3), ``accel_g``, ``status``, ``seq_raw``, ``seq`` (unwrapped), ``temp_raw``
    (i16 for A/B, NaN for C), ``mux`` (C's f32 word, NaN otherwise), ``time_tag_us`` (B, else 0); BIT rows
    have zeros there and their result bytes in ``bit_results``.
    """

    config: KvhConfig
    counters: FormatCounters
    offset: np.ndarray
    kind: np.ndarray
    gyro: np.ndarray
    accel_g: np.ndarray
    status: np.ndarray
    seq_raw: np.ndarray
    seq: np.ndarray
    temp_raw: np.ndarray
    mux: np.ndarray
    time_tag_us: np.ndarray
    bit_results: dict[int, bytes]

    def events(self) -> list[Event]:
        """The events the streaming decoder gives for the same bytes (materialised one by one)."""
        cfg = self.config
        names = {b: name for name, (b, _) in SAMPLE_FORMATS.items()}
        out: list[Event] = []
        gyro = self.gyro.tolist()
        accel = self.accel_g.tolist()
        for i, kind in enumerate(self.kind.tolist()):
            if kind in BIT_FRAME_LEN:
                out.append(KvhBitFrame(int(self.offset[i]), kind, self.bit_results[i]))
                continue
            fmt = names[kind]
            status, seq_raw = int(self.status[i]), int(self.seq_raw[i])
            if fmt == "a":
                values = (*gyro[i], *accel[i], status, seq_raw, int(self.temp_raw[i]))
            elif fmt == "b":
                values = (*gyro[i], *accel[i], int(self.time_tag_us[i]), status, seq_raw, int(self.temp_raw[i]))
            else:
                values = (*gyro[i], *accel[i], float(self.mux[i]), status, seq_raw)
            out.append(_make_sample(cfg, fmt, values, int(self.seq[i]), int(self.offset[i])))
        return out


def decode_kvh_batch(data: bytes | bytearray | memoryview, **config: Any) -> KvhBatch:
    """Decode a complete buffer (as ``feed(data)`` then ``close()``) with numpy; same frames and counters.

    Every position holding a known header is a candidate; the checks of all candidates are computed at
    once (CRC-32/MPEG-2 table-driven across candidates, one column at a time); then the frames the
    sequential 1-byte-resync decoder would take are the valid candidates not inside an earlier taken frame.
    Check failures and truncations are counted only at candidates outside taken frames, as the sequential
    decoder reaches exactly those.
    """
    cfg = KvhConfig(**config)
    buf = np.frombuffer(bytes(data), dtype=np.uint8)
    n = buf.size
    counters = FormatCounters(bytes_in=n)
    kinds = {b: length for b, (_, length) in cfg.accepted_seconds().items()}
    if n >= 4:
        fe = np.flatnonzero(buf[: n - 3] == 0xFE)
        fe = fe[buf[fe + 1] == 0x81]
        third, fourth = buf[fe + 2], buf[fe + 3]
        sample_head = (third == 0xFF) & np.isin(fourth, np.array(list(kinds), dtype=np.uint8))
        bit_head = (third == 0x00) & ((fourth == 0xAA) | (fourth == 0xAB))
        cand = fe[sample_head | bit_head]
    else:
        cand = np.zeros(0, dtype=np.int64)
    cand_kind = buf[cand + 3] if cand.size else np.zeros(0, dtype=np.uint8)
    lengths = {**kinds, **BIT_FRAME_LEN}
    cand_len = np.zeros(cand.size, dtype=np.int64)
    for b, length in lengths.items():
        cand_len[cand_kind == b] = length
    complete = cand + cand_len <= n
    valid = np.zeros(cand.size, dtype=bool)
    windows = {k: np.lib.stride_tricks.sliding_window_view(buf, k) for k in set(lengths.values()) if k <= n}
    for b, length in lengths.items():
        sel = np.flatnonzero((cand_kind == b) & complete)
        if sel.size == 0:
            continue
        rows = windows[length][cand[sel]]
        if b in BIT_FRAME_LEN:
            valid[sel] = (rows[:, :-1].sum(axis=1, dtype=np.uint64) & 0xFF) == rows[:, -1]
        else:
            sent = rows[:, -4:].astype(np.uint32)
            sent = (sent[:, 0] << 24) | (sent[:, 1] << 16) | (sent[:, 2] << 8) | sent[:, 3]
            valid[sel] = crc32_mpeg2_rows(rows[:, :-4]) == sent
    vidx = np.flatnonzero(valid)
    taken = vidx[greedy_accept(cand[vidx], cand[vidx] + cand_len[vidx])]
    starts = cand[taken]
    ends = starts + cand_len[taken]
    # Candidates that failed, outside every taken frame, are the ones the sequential decoder reached.
    failed = np.flatnonzero(~valid)
    if failed.size:
        j = np.searchsorted(starts, cand[failed], side="right") - 1
        end_before = np.concatenate(([0], ends))[j + 1]  # end of the last taken frame starting at or before
        inside = cand[failed] < end_before
        reached = failed[~inside]
        counters.truncated_frames = int(np.count_nonzero(~complete[reached]))
        counters.crc_errors = int(reached.size - counters.truncated_frames)
    counters.bytes_in_frames = int((ends - starts).sum())
    counters.bytes_discarded = n - counters.bytes_in_frames
    if starts.size:
        prev_end = np.concatenate(([0], ends[:-1]))
        counters.resyncs = int(np.count_nonzero(starts != prev_end))
    kind = buf[starts + 3] if starts.size else np.zeros(0, dtype=np.uint8)
    m = starts.size
    gyro = np.zeros((m, 3))
    accel = np.zeros((m, 3))
    status = np.zeros(m, dtype=np.uint8)
    seq_raw = np.zeros(m, dtype=np.int64)
    temp_raw = np.full(m, np.nan)
    mux = np.full(m, np.nan)
    tag = np.zeros(m, dtype=np.int64)
    for name, (b, length) in SAMPLE_FORMATS.items():
        sel = np.flatnonzero(kind == b)
        if sel.size == 0:
            continue
        rows = windows[length][starts[sel], HEADER_LEN : length - 4]
        rec = np.ascontiguousarray(rows).view(_DTYPES[name]).reshape(-1)
        gyro[sel] = rec["g"]
        accel[sel] = rec["a"]
        status[sel] = rec["status"]
        seq_raw[sel] = rec["seq"]
        if name == "c":
            mux[sel] = rec["mux"]
        else:
            temp_raw[sel] = rec["temp"]
        if name == "b":
            tag[sel] = rec["tag"]
    is_sample = ~np.isin(kind, np.array(list(BIT_FRAME_LEN), dtype=np.uint8))
    seq = np.zeros(m, dtype=np.int64)
    s_idx = np.flatnonzero(is_sample)
    if s_idx.size:
        unwrapped = Unwrapper(SEQ_MODULUS).run(seq_raw[s_idx] % SEQ_MODULUS)
        seq[s_idx] = unwrapped.value
        count_seq_steps(counters, unwrapped.steps_taken)
    counters.sample_frames = int(s_idx.size)
    counters.other_frames = int(m - s_idx.size)
    bit_results = {
        int(i): bytes(buf[starts[i] + HEADER_LEN : ends[i] - 1]) for i in np.flatnonzero(~is_sample).tolist()
    }
    return KvhBatch(cfg, counters, starts, kind, gyro, accel, status, seq_raw, seq, temp_raw, mux, tag, bit_results)


__all__ = [
    "BIT_FRAME_LEN",
    "SAMPLE_FORMATS",
    "KvhBatch",
    "KvhBitFrame",
    "KvhConfig",
    "KvhDecoder",
    "crc32_mpeg2",
    "crc32_mpeg2_reference",
    "crc32_mpeg2_rows",
    "decode_kvh_batch",
    "encode_kvh_bit_frame",
    "encode_kvh_frame",
]
