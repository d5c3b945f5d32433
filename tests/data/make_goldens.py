"""Regenerate the golden client output in tests/data/golden/ (only on purpose; say why in the commit).

    python tests/data/make_goldens.py

``sim-faults.watch-1hz.ndjson``: the ANGLE lines a client that sent
``?WATCH={"enable":true,"rate_hz":1};`` receives when ``tests/data/sim-faults.bin``
is fed to ``fog-driver run`` with the shipped default model, byte for byte.
The HIL test feeds the capture through a real pty into the daemon and compares.
A change of any published value (compensation, flags, formatting) shows up here.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parents[1]))

from fog_driver.config import DriverConfig  # noqa: E402
from fog_driver.daemon.hub import encode  # noqa: E402
from fog_driver.daemon.service import Service  # noqa: E402

GOLDEN = HERE / "golden" / "sim-faults.watch-1hz.ndjson"


def golden_lines(rate_hz: float = 1.0) -> list[bytes]:
    """The daemon's ANGLE objects for the capture, decimated as ``?WATCH`` does, encoded as sent."""
    service = Service(DriverConfig(), port="unused")
    lines, last_period = [], None
    for obj in service.process((HERE / "sim-faults.bin").read_bytes()):
        period = math.floor(obj["t_s"] * rate_hz)
        if period != last_period:
            lines.append(encode(obj))
            last_period = period
    return lines


def main() -> None:
    GOLDEN.parent.mkdir(exist_ok=True)
    GOLDEN.write_bytes(b"".join(golden_lines()))
    print(f"{GOLDEN.relative_to(HERE.parents[1])}: {len(golden_lines())} lines")


if __name__ == "__main__":
    main()
