"""Regenerate the small captures in tests/data/ (deterministic: same bytes every run).

    python tests/data/make_fixtures.py

Each capture gets a provenance sidecar whose ``truth`` section is written by
construction (what was sent, dropped, corrupted, inserted), never by decoding,
so tests can score the decoder and ``inspect`` against it.  The ``sim-*``
captures come from the instrument simulator (``fog-driver simulate``), with
its truth file beside them.
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

#: Captures made by the simulator (name -> simulate arguments): 300 s of the short-test profile at 10 Hz.
SIM_FIXTURES = {
    "sim-short": {"seed": 21, "faults": "none"},
    "sim-faults": {"seed": 22, "faults": "drop=0.005,flip=1e-4,garbage=0.2,thermo=0.1:1,disconnect=100:2"},
}
SIM_PROFILE = "configs/profiles/short-test.yaml"
SIM_RATE_HZ = 10
SIM_DURATION_S = 300


def make_sim(name: str, out_dir: Path, overwrite: bool = True):
    """Simulate one of ``SIM_FIXTURES`` into ``out_dir`` (capture, sidecar, truth)."""
    from fog_driver.lab.profiles import load_profile
    from fog_driver.sim.capture import simulate_to_file
    from fog_driver.sim.faults import parse_fault_spec
    from fog_driver.sim.instrument import Simulator

    args = SIM_FIXTURES[name]
    faults = parse_fault_spec(args["faults"])
    sim = Simulator(load_profile(HERE.parents[1] / SIM_PROFILE), rate_hz=SIM_RATE_HZ, seed=args["seed"], faults=faults)
    return simulate_to_file(
        sim, out_dir / f"{name}.bin", duration_s=SIM_DURATION_S, overwrite=overwrite, faults_text=faults.describe()
    )


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
        (HERE / f"{name}.bin.yaml").write_text(yaml.safe_dump(provenance(name, truth), sort_keys=False))
        print(f"{name}.bin: {len(data)} bytes")
    for name in SIM_FIXTURES:
        result = make_sim(name, HERE)
        print(f"{name}.bin: {result.bytes} bytes (simulated)")


if __name__ == "__main__":
    main()
