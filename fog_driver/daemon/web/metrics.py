"""Prometheus metrics of the daemon (``/metrics`` on the web listener, through ``prometheus-client``).

Everything is read when Prometheus scrapes, from the same counters STATUS reports: nothing is counted twice
and nothing costs the acquisition anything between scrapes.  One exception is counted as it happens: the
latency histogram, one observation per published chunk (``LatencyHistogram``, standard library only, so the
hub can fill it without the optional ``web`` extra installed).

Names follow Prometheus' conventions (``_total`` counters, base units: ``_seconds``, ``_bytes``, the
instrument's own units spelled out where there is no base unit: ``_degrees_per_hour``, ``_celsius``).  The list,
with what each means, is ``METRICS``; the documentation's monitoring guide (docs/how-to/monitoring.md) prints it.

The names in deg/h used to end in ``_dph``: ``DEPRECATED_NAMES`` maps each old name to its new one, and the old
one is still exported beside it, the same value, for one release (its help text says so and names the new one).
"""

from __future__ import annotations

import bisect
import threading
from collections.abc import Callable, Iterator, Mapping
from typing import Any

#: Upper bounds (s) of the frame-to-publish latency buckets: 0.1 ms to 1 s, roughly x2 apart.
LATENCY_BUCKETS_S = (0.0001, 0.00025, 0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.25, 1.0)

#: ``name: (type, help)`` of every metric this module exports (labels in the help text).
METRICS: dict[str, tuple[str, str]] = {
    "fog_driver_info": (
        "gauge",
        "1, labelled with the release, the frame format, the instrument's serial and firmware",
    ),
    "fog_driver_uptime_seconds": ("gauge", "seconds since the daemon started"),
    "fog_driver_port_up": ("gauge", "1 while the instrument port is open, 0 while it is closed or lost"),
    "fog_driver_port_reconnects_total": ("counter", "times the port was opened again after it was lost"),
    "fog_driver_bytes_total": ("counter", "bytes read from the instrument port"),
    "fog_driver_frames_total": ("counter", "sample frames decoded"),
    "fog_driver_crc_errors_total": ("counter", "frames with a bad checksum (their bytes resynchronized over)"),
    "fog_driver_bytes_discarded_total": ("counter", "bytes that belonged to no valid frame"),
    "fog_driver_missing_frames_total": ("counter", "frames the sequence numbers say were never received"),
    "fog_driver_samples_published_total": ("counter", "compensated samples published"),
    "fog_driver_flagged_samples_total": ("counter", "published samples carrying a flag, by flag"),
    "fog_driver_last_sample_age_seconds": ("gauge", "host seconds since the last sample was published"),
    "fog_driver_clients": ("gauge", "connected clients, by listener (ndjson, web)"),
    "fog_driver_clients_dropped_total": ("counter", "clients dropped for not reading, by listener (ndjson, web)"),
    "fog_driver_capture_up": ("gauge", "1 while the raw capture records (or waits for its first byte), 0 when failed"),
    "fog_driver_capture_failures_total": ("counter", "raw capture write failures (each retried)"),
    "fog_driver_capture_bytes_lost_total": ("counter", "bytes the raw capture could not write"),
    "fog_driver_drift_degrees_per_hour": ("gauge", "the model's drift estimate in deg/h at the last sample"),
    "fog_driver_drift_sigma_degrees_per_hour": (
        "gauge",
        "the 1-sigma of the drift estimate's error as a 1-min mean, in deg/h, at the last sample (absent while "
        "there is no estimate)",
    ),
    "fog_driver_rate_degrees_per_hour": ("gauge", "the compensated rate in deg/h, mean over the last full second"),
    "fog_driver_temperature_celsius": ("gauge", "the instrument's thermometers at the last sample, by channel"),
    "fog_driver_bias_degrees_per_hour": ("gauge", "the bias removed (?BIAS) in deg/h"),
    "fog_driver_bias_sigma_degrees_per_hour": (
        "gauge",
        "the drift estimate's sigma in deg/h while the bias was captured (absent before a ?BIAS capture)",
    ),
    "fog_driver_adapting": ("gauge", "1 while the weights adapt online, 0 while frozen"),
    "fog_driver_model_info": (
        "gauge",
        "1, labelled with the model in use: its file's path and SHA-256, its kind, when it was fitted "
        "(created_utc) and the instrument serial it was fitted for",
    ),
    "fog_driver_model_age_seconds": ("gauge", "seconds since the model in use was fitted"),
    "fog_driver_extrapolating": ("gauge", "1 while the last sample lies outside what the model was fitted on"),
    "fog_driver_chamber_up": (
        "gauge",
        "1 while the chamber (the config's chamber:) answers its reads, 0 while its link is lost (absent: no chamber)",
    ),
    "fog_driver_chamber_air_celsius": ("gauge", "the chamber's air temperature at its last good read, degC"),
    "fog_driver_chamber_setpoint_celsius": ("gauge", "the chamber's set point at its last good read, degC"),
    "fog_driver_chamber_reading_age_seconds": ("gauge", "host seconds since the chamber's last good read"),
    "fog_driver_publish_latency_seconds": (
        "histogram",
        "from the read that completed a chunk of samples to their lines queued for every watching client",
    ),
}

#: The names in deg/h as they were (``_dph``) -> their names now; each old one is still exported for one release,
#: the same value, its help text saying it is deprecated (``deprecated_help``).
DEPRECATED_NAMES: dict[str, str] = {
    "fog_driver_drift_dph": "fog_driver_drift_degrees_per_hour",
    "fog_driver_drift_sigma_dph": "fog_driver_drift_sigma_degrees_per_hour",
    "fog_driver_rate_dph": "fog_driver_rate_degrees_per_hour",
    "fog_driver_bias_dph": "fog_driver_bias_degrees_per_hour",
    "fog_driver_bias_sigma_dph": "fog_driver_bias_sigma_degrees_per_hour",
}


#: A name now -> its deprecated name (``DEPRECATED_NAMES`` turned round).
OLD_NAMES: dict[str, str] = {new: old for old, new in DEPRECATED_NAMES.items()}


def deprecated_help(old: str) -> str:
    """The help text of a deprecated name: what it is, and which name to use instead."""
    new = DEPRECATED_NAMES[old]
    return f"deprecated, removed in the next release: use {new} ({METRICS[new][1]})"


class LatencyHistogram:
    """Counts of latencies (s) in ``LATENCY_BUCKETS_S`` buckets, their sum and count; thread-safe.

    ``observe`` is called by the hub's thread once per chunk published; ``snapshot`` by the scrape.
    """

    def __init__(self, buckets_s: tuple[float, ...] = LATENCY_BUCKETS_S) -> None:
        self.buckets_s = tuple(buckets_s)
        self._counts = [0] * (len(self.buckets_s) + 1)  # the last: above every bound (+Inf)
        self._sum_s = 0.0
        self._lock = threading.Lock()

    def observe(self, latency_s: float) -> None:
        i = bisect.bisect_left(self.buckets_s, latency_s)
        with self._lock:
            self._counts[i] += 1
            self._sum_s += latency_s

    def snapshot(self) -> tuple[list[tuple[str, int]], float]:
        """``([(upper bound, cumulative count), ..., ("+Inf", count)], sum_s)``, as Prometheus wants them."""
        with self._lock:
            counts, total_s = list(self._counts), self._sum_s
        cumulative, running = [], 0
        for bound, n in zip([*map(repr, self.buckets_s), "+Inf"], counts):
            running += n
            cumulative.append((bound, running))
        return cumulative, total_s


class DaemonCollector:
    """A ``prometheus_client`` collector: the metric families of one daemon, built at each scrape.

    ``read()`` returns a mapping with the STATUS object (``status``), the DEVICE object (``device``), the
    VERSION object (``version``), the port's ``reconnects``, the capture's ``capture_failures``, the model's
    ``model_age_s``, the web listener's ``web_clients`` / ``web_dropped``, the last sample (``angle``) and its
    age (``angle_age_s``), the last second's mean rate (``rate_1s_dph``); any may be absent.
    """

    def __init__(self, read: Callable[[], Mapping[str, Any]], latency: LatencyHistogram) -> None:
        self._read = read
        self._latency = latency

    def describe(self) -> list:
        return []  # built at scrape time only: the registry must not call collect() when it is registered

    def collect(self) -> Iterator[Any]:
        from prometheus_client.core import (  # optional extra: web
            CounterMetricFamily,
            GaugeMetricFamily,
            HistogramMetricFamily,
        )

        state = self._read()
        status: Mapping[str, Any] = state.get("status") or {}
        device: Mapping[str, Any] = state.get("device") or {}
        version: Mapping[str, Any] = state.get("version") or {}

        def family(name: str, labels: tuple[str, ...] = ()):
            kind, text = METRICS[name]
            cls = CounterMetricFamily if kind == "counter" else GaugeMetricFamily
            plain = name[: -len("_total")] if kind == "counter" else name
            return cls(plain, text, labels=labels)

        def single(name: str, value: Any) -> Iterator[Any]:
            if _is_number(value):
                f = family(name)
                f.add_metric([], float(value))
                yield f
                if name in OLD_NAMES:  # the same value under its deprecated name
                    deprecated = GaugeMetricFamily(OLD_NAMES[name], deprecated_help(OLD_NAMES[name]))
                    deprecated.add_metric([], float(value))
                    yield deprecated

        info = family("fog_driver_info", ("release", "format", "serial", "firmware"))
        info.add_metric(
            [
                str(version.get("release", "")),
                str(device.get("format", "")),
                str(device.get("serial", "")),
                str(device.get("firmware", "")),
            ],
            1.0,
        )
        yield info
        model_file = status.get("model_file")
        if isinstance(model_file, Mapping):
            labels = ("path", "sha256", "kind", "created_utc", "serial")
            model = family("fog_driver_model_info", labels)
            model.add_metric([str(model_file.get(label, "")) for label in labels], 1.0)
            yield model
        yield from single("fog_driver_uptime_seconds", status.get("uptime_s"))
        if "port_state" in status:
            yield from single("fog_driver_port_up", 1 if status["port_state"] == "open" else 0)
        yield from single("fog_driver_port_reconnects_total", state.get("reconnects"))
        for name, key in (
            ("fog_driver_bytes_total", "bytes_in"),
            ("fog_driver_frames_total", "frames"),
            ("fog_driver_crc_errors_total", "crc_errors"),
            ("fog_driver_bytes_discarded_total", "bytes_discarded"),
            ("fog_driver_missing_frames_total", "missing_frames"),
            ("fog_driver_samples_published_total", "published"),
            ("fog_driver_capture_bytes_lost_total", "capture_bytes_lost"),
            ("fog_driver_bias_degrees_per_hour", "bias_dph"),
            ("fog_driver_bias_sigma_degrees_per_hour", "bias_sigma_dph"),
        ):
            yield from single(name, status.get(key))
        flagged = status.get("flagged")
        if isinstance(flagged, Mapping):
            f = family("fog_driver_flagged_samples_total", ("flag",))
            for flag, n in sorted(flagged.items()):
                if _is_number(n):
                    f.add_metric([str(flag)], float(n))
            yield f
        yield from single("fog_driver_last_sample_age_seconds", state.get("angle_age_s"))
        yield from self._listeners_and_readings(state, family, single)
        chamber = status.get("chamber")
        if isinstance(chamber, Mapping):
            yield from single("fog_driver_chamber_up", 1 if chamber.get("link_up") else 0)
            yield from single("fog_driver_chamber_air_celsius", chamber.get("air_c"))
            yield from single("fog_driver_chamber_setpoint_celsius", chamber.get("setpoint_c"))
            yield from single("fog_driver_chamber_reading_age_seconds", chamber.get("age_s"))
        buckets, total_s = self._latency.snapshot()
        h = HistogramMetricFamily(
            "fog_driver_publish_latency_seconds", METRICS["fog_driver_publish_latency_seconds"][1]
        )
        h.add_metric([], buckets, total_s)
        yield h

    @staticmethod
    def _listeners_and_readings(state: Mapping[str, Any], family: Callable, single: Callable) -> Iterator[Any]:
        """The clients of each listener, the capture, and the last sample's readings."""
        status: Mapping[str, Any] = state.get("status") or {}
        angle: Mapping[str, Any] = state.get("angle") or {}
        clients = family("fog_driver_clients", ("listener",))
        dropped = family("fog_driver_clients_dropped_total", ("listener",))
        for listener, now, gone in (
            ("ndjson", status.get("clients"), status.get("dropped_clients")),
            ("web", state.get("web_clients"), state.get("web_dropped")),
        ):
            if _is_number(now):
                clients.add_metric([listener], float(now))
            if _is_number(gone):
                dropped.add_metric([listener], float(gone))
        yield clients
        yield dropped
        if "capture_state" in status:
            yield from single("fog_driver_capture_up", 1 if status["capture_state"] in ("idle", "recording") else 0)
        yield from single("fog_driver_capture_failures_total", state.get("capture_failures"))
        yield from single("fog_driver_drift_degrees_per_hour", angle.get("drift_dph"))
        yield from single("fog_driver_drift_sigma_degrees_per_hour", angle.get("drift_sigma_dph"))
        yield from single("fog_driver_rate_degrees_per_hour", state.get("rate_1s_dph"))
        temps = angle.get("temps_c")
        if isinstance(temps, Mapping):
            f = family("fog_driver_temperature_celsius", ("channel",))
            for channel, value in temps.items():
                if _is_number(value):
                    f.add_metric([str(channel)], float(value))
            yield f
        if "adapting" in status:
            yield from single("fog_driver_adapting", 1 if status["adapting"] else 0)
        yield from single("fog_driver_model_age_seconds", state.get("model_age_s"))
        flags = angle.get("flags")
        if isinstance(flags, list):
            yield from single("fog_driver_extrapolating", 1 if "extrapolating" in flags else 0)


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


__all__ = ["DEPRECATED_NAMES", "LATENCY_BUCKETS_S", "METRICS", "DaemonCollector", "LatencyHistogram", "deprecated_help"]
