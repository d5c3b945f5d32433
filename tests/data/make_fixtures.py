"""Regenerate the small synthetic captures in tests/data/ (deterministic: same bytes every run).

    python tests/data/make_fixtures.py

Each capture gets a provenance sidecar whose ``truth`` section is written by
construction (what was sent, dropped, corrupted, inserted), never by decoding,
so tests can score the decoder and ``inspect`` against it.  These stand in for
recorded frames until the simulator's captures replace them.
"""

from __future__ import annotations

import random
import sys
from pathlib import Path

import yaml

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parents[1]))

from fog_driver.protocol import (  # noqa: E402
    STATUS_THERMOMETER_FAULT,
    THERMOMETER_INVALID,
    encode_identity,
    encode_sample,
)

SERIAL = "FOG-SYN-0001"
FIRMWARE = 0x0102
RATE_HZ = 100
SCALE = 0.0125  # exactly representable in float32
N_FRAMES = 1200
SEQ0 = 65000  # wraps after 536 frames
T0_US = 2**32 - 5_000_000  # t_us wraps after 5 s


def _frames(rng: random.Random, thermometer_fault_at: set[int]) -> list[tuple[int, bytes]]:
    """(index, SAMPLE frame bytes) for a slow warm-up with a constant rate and noise."""
    out = []
    remainder = 0.0
    for k in range(N_FRAMES):
        t_s = k / RATE_HZ
        temp_c = 20.0 + 0.05 * t_s
        raw = [round(256 * (temp_c + d)) for d in (0.0, -0.12, -0.4)]
        status = 0
        if k in thermometer_fault_at:
            raw[k % 3] = THERMOMETER_INVALID
            status |= STATUS_THERMOMETER_FAULT
        rate_counts = (15.0 / RATE_HZ) / SCALE + rng.gauss(0.0, 3.0)
        remainder += rate_counts
        counts = int(round(remainder))
        remainder -= counts
        t_us = T0_US + round(k * 1_000_000 / RATE_HZ)
        out.append((k, encode_sample(SEQ0 + k, t_us, counts, *raw, status)))
    return out


def _identity() -> bytes:
    return encode_identity(SERIAL, FIRMWARE, RATE_HZ, SCALE)


def make_clean() -> tuple[bytes, dict]:
    rng = random.Random(1)
    parts = []
    for k, frame in _frames(rng, set()):
        if k % RATE_HZ == 0:
            parts.append(_identity())
        parts.append(frame)
    truth = {
        "sample_frames": N_FRAMES,
        "identity_frames": N_FRAMES // RATE_HZ,
        "missing_frames": 0,
        "seq_gaps": 0,
        "crc_errors": 0,
        "bytes_discarded": 0,
        "thermometer_faults": 0,
        "t_us_wraps": 1,
    }
    return b"".join(parts), truth


def make_faults() -> tuple[bytes, dict]:
    rng = random.Random(2)
    faults_at = {100, 101, 555, 900}
    dropped = {200, 201, 202, 700}
    corrupted = {300, 650, 1000}
    garbage_at = {50: bytes(range(0x10, 0x30)), 400: b"\x00\x01\xfe" * 7, 800: b"\x55\x55\x13\x11"}
    parts = [b"\x00\x13\x11\x7f\x00"]  # line noise before the first frame
    garbage_bytes = len(parts[0])
    for k, frame in _frames(rng, faults_at):
        if k % RATE_HZ == 0:
            parts.append(_identity())
        if k in garbage_at:
            parts.append(garbage_at[k])
            garbage_bytes += len(garbage_at[k])
        if k in dropped:
            continue
        if k in corrupted:
            frame = frame[:12] + bytes([frame[12] ^ 0x10]) + frame[13:]
        parts.append(frame)
    tail = encode_sample(SEQ0 + N_FRAMES, 0, 0, 0, 0, 0)[:9]  # the recording stopped mid-frame
    parts.append(tail)
    lost = sorted(dropped | corrupted)
    runs = sum(1 for i, k in enumerate(lost) if i == 0 or lost[i - 1] != k - 1)
    truth = {
        "sample_frames": N_FRAMES - len(lost),
        "identity_frames": N_FRAMES // RATE_HZ,
        "missing_frames": len(lost),
        "seq_gaps": runs,
        "crc_errors": len(corrupted),
        "bytes_discarded": garbage_bytes + 26 * len(corrupted) + len(tail),
        "thermometer_faults": len(faults_at),
        "t_us_wraps": 1,
        "tail_bytes": len(tail),
        "dropped_frames": sorted(dropped),
        "corrupted_frames": sorted(corrupted),
    }
    return b"".join(parts), truth


FIXTURES = {"synthetic-clean": make_clean, "synthetic-faults": make_faults}


def provenance(name: str, truth: dict) -> dict:
    return {
        "format": "fog_driver capture provenance",
        "schema_version": 1,
        "capture": f"{name}.bin",
        "source": "synthetic",
        "generator": "tests/data/make_fixtures.py",
        "instrument": {"serial": SERIAL, "firmware": "1.2", "rate_hz": RATE_HZ, "scale_arcsec_per_count": SCALE},
        "notes": "12 s warm-up at 0.05 degC/s, 15 deg/h input, seq and t_us wrap; truth written by construction",
        "truth": truth,
    }


def main() -> None:
    for name, make in FIXTURES.items():
        data, truth = make()
        (HERE / f"{name}.bin").write_bytes(data)
        (HERE / f"{name}.yaml").write_text(yaml.safe_dump(provenance(name, truth), sort_keys=False))
        print(f"{name}.bin: {len(data)} bytes")


if __name__ == "__main__":
    main()
