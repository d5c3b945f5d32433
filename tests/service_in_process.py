"""The daemon's service in this process, without sockets, and ``compensate``'s angles to compare with it."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fog_driver.daemon.config import DEFAULT_MODEL
from fog_driver.daemon.service import Service
from fog_driver.modelfiles import load_model
from fog_driver.offline.compensate import compensate_capture


def publish(service: Service, data: bytes, chunk: int = 997) -> list[dict]:
    out: list[dict] = []
    for i in range(0, len(data), chunk):
        out += service.process(data[i : i + chunk])
    return out


def offline(capture: Path, model_path: Path = DEFAULT_MODEL, **settings) -> tuple[list[float], np.ndarray]:
    """The compensated angles and the flags of ``fog-driver compensate`` (with ``settings``: the keyword
    arguments of ``compensate_capture``), sample by sample."""
    parts = [cols for _, cols in compensate_capture(capture, load_model(model_path), **settings)]
    return [float(a) for cols in parts for a in cols.angle_comp_arcsec], np.concatenate([c.flags for c in parts])
