"""KVH normal-mode decode throughput: numpy batch vs a straightforward struct-per-frame loop (same run).

    python -m benchmarks.bench_kvh_decode [--frames N] [--repeat R] [--format a|b|c]

Generates N frames of one format (a BIT reply every 1000 frames, no corruption), checks that the batch
path and the baseline agree on every frame, and prints frames/s for: the batch path to arrays
(``decode_kvh_batch``), the batch path including materialising ``ImuSample`` events, the streaming decoder
(4096-byte chunks) and the baseline loop (find the header, check the CRC-32/MPEG-2 through zlib,
struct.unpack, one frame at a time).  The best of R repeats is printed; nothing is asserted (the machines
are shared and noisy).
"""

from __future__ import annotations

import argparse
import struct

import numpy as np

from benchmarks.bench_decode import best_time
from fog_driver.formats.kvh import (
    SAMPLE_FORMATS,
    KvhDecoder,
    crc32_mpeg2,
    decode_kvh_batch,
    encode_kvh_bit_frame,
    encode_kvh_frame,
)

BODY = {"a": ">6fBBh", "b": ">6fIBBh", "c": ">6ffBB"}


def make_capture(n_frames: int, fmt: str, seed: int = 0) -> bytes:
    rng = np.random.default_rng(seed)
    gyro = rng.normal(0, 1e-5, (n_frames, 3)).astype(np.float32).tolist()
    accel = rng.normal(0, 1e-2, (n_frames, 3)).astype(np.float32).tolist()
    bit = encode_kvh_bit_frame(0xAA, bytes([0x7F] * 6))
    parts = []
    for k in range(n_frames):
        if k % 1000 == 0:
            parts.append(bit)
        parts.append(encode_kvh_frame(fmt, gyro[k], accel[k], 0x77, k % 128, 30, k))
    return b"".join(parts)


def baseline_decode(data: bytes, fmt: str) -> list[tuple]:
    """The straightforward decoder: find the header, check the CRC, struct.unpack, one frame at a time."""
    second, length = SAMPLE_FORMATS[fmt]
    header = bytes((0xFE, 0x81, 0xFF, second))
    unpack = struct.Struct(BODY[fmt]).unpack_from
    crc_of = struct.Struct(">I").unpack_from
    out = []
    pos = data.find(header)
    n = len(data)
    while 0 <= pos <= n - length:
        if crc32_mpeg2(data[pos : pos + length - 4]) == crc_of(data, pos + length - 4)[0]:
            out.append(unpack(data, pos + 4))
            pos = data.find(header, pos + length)
        else:
            pos = data.find(header, pos + 1)
    return out


def streaming(data: bytes, fmt: str) -> int:
    d = KvhDecoder(format=fmt, rate_hz=1000)
    n = 0
    for at in range(0, len(data), 4096):
        n += len(d.feed(data[at : at + 4096]))
    return n + len(d.close())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=300_000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--format", default="a", choices=sorted(SAMPLE_FORMATS))
    args = ap.parse_args()
    n, fmt = args.frames, args.format
    data = make_capture(n, fmt)
    n_frames = n + (n + 999) // 1000

    t_batch, batch = best_time(lambda: decode_kvh_batch(data, format=fmt, rate_hz=1000), args.repeat)
    t_base, base = best_time(lambda: baseline_decode(data, fmt), args.repeat)
    sample = batch.kind != 0xAA
    assert len(base) == int(sample.sum()) == n, "batch and baseline disagree on the frame count"
    base_gyro = np.array([b[:3] for b in base])
    assert np.array_equal(base_gyro, batch.gyro[sample]), "batch and baseline disagree on the gyro words"
    t_events, _ = best_time(lambda: decode_kvh_batch(data, format=fmt, rate_hz=1000).events(), 1)
    t_stream, n_stream = best_time(lambda: streaming(data, fmt), 1)

    print(f"KVH Format {fmt.upper()}: {n} sample frames + {n_frames - n} BIT replies, {len(data)} bytes")
    rows = [
        ("batch to arrays (numpy)", t_batch),
        ("batch incl. ImuSample events", t_events),
        ("streaming decoder, 4096-byte chunks", t_stream),
        ("baseline struct-per-frame loop", t_base),
    ]
    for name, t in rows:
        print(f"  {name:38s} {n_frames / t:14,.0f} frames/s   {t_base / t:6.1f}x baseline")


if __name__ == "__main__":
    from benchmarks._harness import run_main

    run_main(main)
