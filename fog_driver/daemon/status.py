"""What the daemon says about itself: the VERSION, DEVICE and STATUS objects, and the numbers ``/metrics`` reads.

Each is built from the service's public state when asked (a client's ``?STATUS``, the periodic STATUS, a
scrape), so nothing is counted twice.  The caller holds the service's ``lock`` where the pipeline's counters
are read (``status_object``); ``metrics_state`` takes it itself.
"""

from __future__ import annotations

import datetime as _dt
import math
import os
import resource
import time
from typing import Any

from .. import __version__
from ..protocol import IdentityFrame

__all__ = [
    "PROTO_MAJOR",
    "PROTO_MINOR",
    "CpuMeter",
    "age_s",
    "current_rss_mb",
    "device_object",
    "identity_fields",
    "metrics_state",
    "model_file_fields",
    "status_object",
    "version_object",
]

#: The NDJSON protocol's version (``connection.py``): the major changes only when a key changes meaning or goes,
#: the minor when keys are added (1.1: ANGLE's ``drift_sigma_dph``, STATUS's and BIAS's ``bias_sigma_dph``,
#: STATUS's ``noise_1min_dph``; 1.2: STATUS's and VERSION's ``model_file``).
PROTO_MAJOR = 1
PROTO_MINOR = 3


class CpuMeter:
    """The process's CPU share between two marks: ``100 * (cpu_s - cpu_mark_s) / (now_s - wall_mark_s)`` %."""

    def __init__(self) -> None:
        self._mark = (time.monotonic(), time.process_time())

    def percent(self, now_s: float, *, mark: bool) -> float:
        """The share since the last mark (rounded to 0.01 %); ``mark``: start the next interval now."""
        cpu_s = time.process_time()
        wall_mark_s, cpu_mark_s = self._mark
        if mark:
            self._mark = (now_s, cpu_s)
        return round(100.0 * (cpu_s - cpu_mark_s) / max(now_s - wall_mark_s, 1e-9), 2)


def current_rss_mb() -> float:
    """The resident set size now (VmRSS; Linux), else the peak (``ru_maxrss``)."""
    try:
        with open("/proc/self/status", encoding="ascii") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return round(int(line.split()[1]) / 1024.0, 1)
    except OSError:
        pass
    return round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, 1)


def age_s(created_utc: str) -> float | None:
    """Seconds since an ISO 8601 UTC time (a model's ``created_utc``), or None when it is not one."""
    try:
        created = _dt.datetime.fromisoformat(created_utc.replace("Z", "+00:00"))
    except (ValueError, AttributeError):
        return None
    if created.tzinfo is None:
        created = created.replace(tzinfo=_dt.UTC)
    return (_dt.datetime.now(_dt.UTC) - created).total_seconds()


def identity_fields(identity: IdentityFrame) -> dict:
    """The instrument's identity as VERSION and DEVICE carry it."""
    return {
        "serial": identity.serial,
        "firmware": identity.firmware_version,
        "rate_hz": identity.rate_hz,
        "scale_arcsec_per_count": identity.scale_arcsec_per_count,
    }


def model_file_fields(model_file: Any, path: str | None, sha256: str) -> dict[str, str]:
    """STATUS's and VERSION's ``model_file``: the model in use, ``path`` (absolute; None for a model given as an
    object), ``sha256`` of the bytes it was read from, ``kind``, ``created_utc`` (its fit date) and ``serial`` (the
    instrument serial it was fitted for); an empty value is omitted.  The service keeps it as ``model_fields``,
    made again by each reload, so every view names the model in use."""
    fields = {
        "path": None if path is None else os.path.abspath(path),
        "sha256": sha256,
        "kind": model_file.kind,
        "created_utc": model_file.created_utc,
        "serial": model_file.instrument_serial,
    }
    return {key: value for key, value in fields.items() if value}


def version_object(service: Any) -> dict:
    """VERSION: the release, the protocol's version, the model's kind and file (``model_file_fields``) and (once
    known) the instrument.  A client that has not authorized on a token-protected daemon gets the first three
    only (``hub.PUBLIC_VERSION_KEYS``)."""
    obj: dict[str, Any] = {
        "class": "VERSION",
        "release": __version__,
        "proto_major": PROTO_MAJOR,
        "proto_minor": PROTO_MINOR,
        "model": service.model_file.kind,
        "model_file": dict(service.model_fields),
    }
    identity = service.acquisition.identity
    if identity is not None:
        obj["instrument"] = identity_fields(identity)
    return obj


def device_object(service: Any) -> dict:
    """DEVICE: the port, its state, the frame format, the instrument and the raw capture's state."""
    obj: dict[str, Any] = {
        "class": "DEVICE",
        "path": service.port_url,
        "state": "activated" if service.port_state == "open" else "deactivated",
    }
    if service.source.wire is not None:
        obj["format"] = service.source.wire.format
    identity = service.acquisition.identity
    if identity is not None:
        obj.update(identity_fields(identity))
    if service.capture is not None:
        obj["capture"] = service.capture.status
    return obj


def status_object(service: Any, *, mark_cpu: bool = True) -> dict:
    """STATUS now; ``mark_cpu``: the CPU share is over the time since the last marked call (the periodic
    STATUS marks it; a client's ``?STATUS`` does not, so it cannot skew the periodic figure)."""
    now = time.monotonic()
    cpu_percent = service.cpu.percent(now, mark=mark_cpu)
    acquisition = service.acquisition
    c = service.source.counters
    compensator = service.compensator
    obj: dict[str, Any] = {
        "class": "STATUS",
        "uptime_s": round(now - service.started_monotonic, 3),
        "port_state": service.port_state,
        "bytes_in": c.bytes_in,
        "frames": c.sample_frames,
        "crc_errors": c.crc_errors,
        "bytes_discarded": c.bytes_discarded,
        "seq_gaps": c.seq_gaps,
        "missing_frames": c.missing_frames,
        "identities_rejected": service.source.identities_rejected,
        "instrument_changes": service.binding.rebuilds,
        "published": acquisition.samples_published,
        "flagged": dict(acquisition.flagged),
        "cpu_percent": cpu_percent,
        "rss_mb": current_rss_mb(),
        "bias_dph": acquisition.offsets.bias_dph,
        "bias_captured": acquisition.bias_captured,
        "adapting": bool(compensator and compensator.reference_rate_dph is not None),
        "reloads": service.reloads,
        "model_file": dict(service.model_fields),
    }
    obj.update(_pipeline_fields(service))
    obj.update(_listener_fields(service))
    chamber = getattr(service, "chamber", None)
    if chamber is not None:  # the config's read-only chamber: its last reading (daemon/chamber.py)
        obj["chamber"] = chamber.snapshot()
    return obj


def _pipeline_fields(service: Any) -> dict[str, Any]:
    """STATUS keys present only when they say something: a bias capture running, the drift's sigma during the
    last one, samples dropped before the first IDENTITY, a format problem, rejected increments, whether the
    adapted weights are in use, the loaded model's ``noise_1min_dph``."""
    acquisition = service.acquisition
    obj: dict[str, Any] = {}
    capture = acquisition.bias_capture
    if capture is not None:  # a ?BIAS capture running: how far it is, in seconds of device time
        obj["bias_capture_s"] = capture.seconds
        obj["bias_capture_target_s"] = capture.target_s
    if acquisition.bias_captured and math.isfinite(acquisition.bias_sigma_dph):
        obj["bias_sigma_dph"] = acquisition.bias_sigma_dph  # sigma(t_b): the since-bias form's second term
    if acquisition.samples_dropped_before_identity:
        obj["samples_dropped_before_identity"] = acquisition.samples_dropped_before_identity
    if service.source.format_problem is not None:
        obj["format_problem"] = service.source.format_problem
    if service.source.increments_rejected:  # another format's float words that were NaN or no gyro's
        obj["increments_rejected"] = service.source.increments_rejected
    online = service.compensator.online if service.compensator is not None else None
    if online is not None:  # is the published drift the adapted weights' (the comparison guard's verdict)?
        obj["adapted_in_use"] = online.adapted_in_use
    compensator = service.compensator
    if (
        compensator is not None
        and compensator.table is not None
        and (compensator.table_engaged or compensator.table.outcomes)
    ):
        obj["table"] = table_fields(compensator)
    if service.model_file.noise_1min_dph is not None:  # the loaded model's (files before it have none)
        obj["noise_1min_dph"] = service.model_file.noise_1min_dph
    return obj


def table_fields(compensator: Any) -> dict[str, Any]:
    """STATUS ``table``: adapting from table angles (``compensation.table``): whether it gives the estimate,
    the dwells by outcome, the last one's outcome, the scale factor."""
    law = compensator.table
    summary = law.summary()
    out: dict[str, Any] = {"engaged": bool(compensator.table_engaged), "pending": len(compensator.pending_dwells)}
    out.update(summary)
    out["scale_factor_applied"] = bool(summary["scale_factor_applied"] and compensator.table_engaged)
    if law.outcomes:
        last = law.outcomes[-1]
        out["last"] = {"t_end_s": last.t_end_s, "status": last.status, "reason": last.reason}
    return out


def _listener_fields(service: Any) -> dict[str, Any]:
    """STATUS keys of the listeners and outputs that run: clients, web pages, the raw capture, UDP."""
    obj: dict[str, Any] = {}
    if service.hub is not None:
        obj["clients"] = service.hub.clients
        obj["dropped_clients"] = service.hub.dropped_clients
    if service.web is not None:
        obj["web_clients"] = len(service.web.fanout.browsers)
        obj["web_dropped_clients"] = service.web.fanout.dropped_browsers
    if service.capture is not None:
        capture = service.capture.status_fields()
        obj["capture_state"] = capture["status"]
        obj["capture_bytes"] = capture["bytes"]
        obj["capture_bytes_lost"] = capture["bytes_lost"]
        if "path" in capture:
            obj["capture"] = capture["path"]
        if "last_error" in capture:
            obj["capture_error"] = capture["last_error"]
    if service.udp is not None:
        obj.update(service.udp.status_fields())
    return obj


def metrics_state(service: Any) -> dict[str, Any]:
    """What ``/metrics`` reads at each scrape (``metrics.DaemonCollector``): STATUS, DEVICE, VERSION and
    the counters STATUS does not carry (any thread)."""
    with service.lock:
        out: dict[str, Any] = {
            "status": status_object(service, mark_cpu=False),
            "device": device_object(service),
            "version": version_object(service),
        }
    reader = service.reader
    if reader is not None:
        out["reconnects"] = max(0, reader.opens - 1)
    if service.capture is not None:
        out["capture_failures"] = service.capture.status_fields()["failures"]
    out["model_age_s"] = age_s(service.model_file.created_utc)
    return out
