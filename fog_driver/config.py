"""Driver configuration: a YAML file read with ``yaml.safe_load`` only, validated key by key.

Only what the foundation layers need lives here so far (the port and the
scale factor); later stages add their own sections.  Unknown keys are errors,
so a typo never silently falls back to a default.

    port: /dev/ttyUSB0              # device path or pyserial URL (replay://x.bin?rate=100)
    baud: 460800
    scale_arcsec_per_count: 0.01    # used until the first IDENTITY frame arrives
    scale_override_arcsec_per_count: null   # set to force a scale over the instrument's
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

from .errors import InputFileError
from .stream import DEFAULT_SCALE_ARCSEC_PER_COUNT, SampleStream
from .yamlfile import read_yaml


@dataclass(frozen=True)
class DriverConfig:
    port: str | None = None
    baud: int = 460800
    scale_arcsec_per_count: float = DEFAULT_SCALE_ARCSEC_PER_COUNT
    scale_override_arcsec_per_count: float | None = None

    def sample_stream(self) -> SampleStream:
        """A ``SampleStream`` applying this configuration's scale-factor rule."""
        return SampleStream(self.scale_arcsec_per_count, self.scale_override_arcsec_per_count)


def _positive_scale(name: str, value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
        raise InputFileError(f"{where}: {name} must be a positive number of arcsec per count, got {value!r}")
    return float(value)


def parse_config(doc: Any, where: str = "config") -> DriverConfig:
    """Validate a parsed YAML document into a ``DriverConfig``."""
    if doc is None:
        return DriverConfig()
    if not isinstance(doc, dict):
        raise InputFileError(f"{where}: expected a YAML mapping of settings")
    known = {f.name for f in fields(DriverConfig)}
    unknown = sorted(set(doc) - known)
    if unknown:
        raise InputFileError(f"{where}: unknown setting {unknown[0]!r} (known: {', '.join(sorted(known))})")
    values: dict[str, Any] = {}
    if doc.get("port") is not None:
        if not isinstance(doc["port"], str) or not doc["port"]:
            raise InputFileError(f"{where}: port must be a device path or URL string")
        values["port"] = doc["port"]
    if "baud" in doc:
        baud = doc["baud"]
        if isinstance(baud, bool) or not isinstance(baud, int) or not 50 <= baud <= 12_000_000:
            raise InputFileError(f"{where}: baud must be an integer baud rate, got {baud!r}")
        values["baud"] = baud
    if "scale_arcsec_per_count" in doc:
        values["scale_arcsec_per_count"] = _positive_scale("scale_arcsec_per_count", doc["scale_arcsec_per_count"], where)
    if doc.get("scale_override_arcsec_per_count") is not None:
        values["scale_override_arcsec_per_count"] = _positive_scale(
            "scale_override_arcsec_per_count", doc["scale_override_arcsec_per_count"], where
        )
    return DriverConfig(**values)


def load_config(path: str | Path) -> DriverConfig:
    """Read and validate a config file; every problem is a one-line ``InputFileError``."""
    path = Path(path)
    doc = read_yaml(path, "config file")
    return parse_config(doc, str(path))
