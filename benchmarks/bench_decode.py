"""Decode throughput: batch (numpy), streaming (64-byte chunks), and a straightforward baseline.

    python -m benchmarks.bench_decode [--frames N] [--repeat R]

Generates a capture of N SAMPLE frames (with an IDENTITY frame every 1000 and
no corruption) in memory, checks every decoder's output against the
generator's truth, and prints frames/s for each, with ratios against the
baseline (a struct-per-frame loop, timed in the same run) and against what a
saturated 921600-baud link carries.  No figure here is asserted: the machines
are shared and noisy, so the numbers are printed for a person to read.
"""

from __future__ import annotations

import argparse
import struct
import time
import tracemalloc
import zlib

import numpy as np

from fog_driver.protocol import FrameDecoder, decode_bytes, encode_identity
from fog_driver.protocol.batch import SAMPLE_PAYLOAD_DTYPE

LINK_FRAMES_PER_S = 921600 / 10 / 26  # 8N1: 10 bits per byte, 26-byte SAMPLE frames


def make_capture(n_frames: int, seed: int = 0) -> tuple[bytes, np.ndarray]:
    """N SAMPLE frames built column-wise (CRC by zlib per frame), IDENTITY every 1000; returns bytes and payloads."""
    rng = np.random.default_rng(seed)
    payload = np.zeros(n_frames, dtype=SAMPLE_PAYLOAD_DTYPE)
    payload["seq"] = np.arange(n_frames) % 65536
    payload["t_us"] = (np.arange(n_frames, dtype=np.int64) * 1000) % 2**32
    payload["dtheta_counts"] = rng.integers(-20000, 20000, n_frames)
    payload["t_top_raw"] = rng.integers(-10000, 15000, n_frames)
    payload["t_bottom_raw"] = rng.integers(-10000, 15000, n_frames)
    payload["t_housing_raw"] = rng.integers(-10000, 15000, n_frames)
    raw = payload.tobytes()
    identity = encode_identity("FOG-BENCH-0001", 0x0102, 1000, 0.01)
    parts = []
    header = b"\x01\x12"
    for k in range(n_frames):
        if k % 1000 == 0:
            parts.append(identity)
        body = header + raw[18 * k : 18 * k + 18]
        parts.append(b"\xaa\x55" + body + struct.pack("<I", zlib.crc32(body)))
    return b"".join(parts), payload


def baseline_decode(data: bytes) -> list[tuple]:
    """The straightforward decoder: find sync, check header and CRC, struct.unpack, one frame at a time."""
    unpack = struct.Struct("<HIihhhH").unpack_from
    out = []
    pos = 0
    n = len(data)
    while True:
        pos = data.find(b"\xaa\x55", pos)
        if pos < 0 or pos + 4 > n:
            break
        length = data[pos + 3]
        end = pos + 8 + length
        if end > n:
            break
        if zlib.crc32(data[pos + 2 : end - 4]) != struct.unpack_from("<I", data, end - 4)[0]:
            pos += 1
            continue
        if data[pos + 2] == 1 and length == 18:
            out.append(unpack(data, pos + 4))
        pos = end
    return out


def best_time(fn, repeat: int) -> tuple[float, object]:
    best = float("inf")
    result = None
    for _ in range(repeat):
        t0 = time.perf_counter()
        result = fn()
        best = min(best, time.perf_counter() - t0)
    return best, result


def streaming_decode(data: bytes, chunk: int) -> int:
    decoder = FrameDecoder()
    n = 0
    feed = decoder.feed
    for i in range(0, len(data), chunk):
        n += len(feed(data[i : i + chunk]))
    n += len(decoder.close())
    return n


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=1_000_000)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    n = args.frames

    t0 = time.perf_counter()
    data, truth = make_capture(n)
    print(
        f"capture: {n:,} SAMPLE frames + {(n + 999) // 1000:,} IDENTITY, {len(data) / 1e6:.1f} MB "
        f"(generated in {time.perf_counter() - t0:.1f} s)"
    )

    t_batch, batch = best_time(lambda: decode_bytes(data), args.repeat)
    for name in SAMPLE_PAYLOAD_DTYPE.names:
        assert np.array_equal(getattr(batch.samples, name), truth[name]), name
    assert batch.counters.bytes_discarded == 0 and len(batch.identities) == (n + 999) // 1000

    t_base, base = best_time(lambda: baseline_decode(data), args.repeat)
    assert len(base) == n and base[-1] == tuple(truth[-1].tolist())

    t_stream, n_stream = best_time(lambda: streaming_decode(data, 64), args.repeat)
    assert n_stream == n + (n + 999) // 1000

    tracemalloc.start()
    decode_bytes(data)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()

    fps = {name: n / t for name, t in (("batch", t_batch), ("stream", t_stream), ("baseline", t_base))}
    print(f"batch decode (numpy)          {fps['batch']:>12,.0f} frames/s  ({t_batch:.3f} s, best of {args.repeat})")
    print(f"streaming decode, 64-B chunks {fps['stream']:>12,.0f} frames/s  ({t_stream:.3f} s, best of {args.repeat})")
    print(f"baseline struct-per-frame     {fps['baseline']:>12,.0f} frames/s  ({t_base:.3f} s, best of {args.repeat})")
    print(f"batch / baseline              {fps['batch'] / fps['baseline']:>12.1f} x")
    print(f"stream / baseline             {fps['stream'] / fps['baseline']:>12.2f} x")
    print(
        f"batch / saturated 921600-baud link ({LINK_FRAMES_PER_S:,.0f} frames/s) "
        f"{fps['batch'] / LINK_FRAMES_PER_S:.0f} x"
    )
    print(f"batch decode peak memory      {peak / 1e6:>12.0f} MB  ({peak / len(data):.1f} x the capture size)")


if __name__ == "__main__":
    from benchmarks._harness import run_main  # --update-readme: the documentation's block for this command

    run_main(main)
