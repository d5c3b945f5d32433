"""What the web page shows, built from the daemon's own objects (sans-IO: objects in, JSON-ready dicts out).

The web listener (``web.py``) hands every published batch of ANGLE objects and every other object (STATUS,
DEVICE, VERSION, BIAS, ...) to one ``ViewState`` on its own thread; the page gets a ``snapshot()`` when it
connects and an ``update()`` a few times a second.  The decimation happens here, on the server: a page never
receives more than one sample per update, whatever the instrument's rate.

Series kept for the plots (the last ``history_min`` minutes of device time):

* ``points``: one per ``point_every_s`` of device time (1 s, longer for a history beyond an hour, so a
  page never holds more than ``MAX_POINTS``), from the span's last sample: its UTC, drift estimate and its
  ``drift_sigma_dph``, temperatures and angle, and the span's mean compensated rate
  ``rate_dph = (1/n) * sum_i rate_dph_i`` over its n samples; and the half-width of the band the drift plot
  draws, ``drift_band_dph = BAND_SIGMAS * sigma`` with sigma as shown then (``display.drift_sigma``: the
  sample's sigma(t), or once STATUS says a bias was captured, sqrt(sigma(t)^2 + sigma(t_b)^2), and
  ``band_since_bias`` true), None without a sigma; ``drift_dph`` and the band None while the sample has no
  estimate (its ``drift_dph`` absent, flagged ``uncompensated``; a sample so flagged is never drawn as a drift);
* ``minutes``: one per minute of device time that the samples cover (the first within ``MINUTE_COVER_S`` of its
  start, the last within it of its end: not the minute the daemon started in, nor one a link gap cut short),
  the minute's mean compensated and raw rates ``rate_dph = (1/n) * sum_i rate_dph_i`` (every sample, not the
  decimated ones: a mean of the published rates is the angle gained over the minute divided by its duration,
  unaffected by a ``?ZERO`` meanwhile).

``page_state``: what the figures are (live; stale while the link is down or no data comes, which the page greys;
waiting before the first sample), for the page's pill.  STATUS counters in ``STATUS_ROWS``; the uptime as
``display.format_duration`` shows it.

Also ``rate_1s_dph``, the compensated rate's mean over the last second of device time (shown, and exported as a
metric), computed by ``display.RateAverage``, the code ``fog-driver watch`` shows its rate with: fed every
sample, it is the mean of their ``rate_dph``.  A span closes when the first sample of the next one arrives.
Device time that goes back (the instrument restarted, another one plugged in) starts the series afresh.

The numbers shown are formatted here (``text``), with ``watch``'s rules (``format_arcsec``,
``format_dms``), so the page, ``fog-driver watch`` and a script formatting an ANGLE line all agree; so is the
model in use (``model``, ``model_sha256``: STATUS's ``model_file``, new after a reload, else VERSION's).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterable, Mapping
from typing import Any

from ...client.display import (
    BAND_SIGMAS,
    NO_DATA_S,
    TEMPERATURE_ORDER,
    RateAverage,
    banners,
    drift_sigma,
    format_arcsec,
    format_dms,
    format_duration,
    link_down,
    model_in_use,
    model_text,
)
from ...client.display import finite_number as _number
from ...client.display import fixed as _fixed

#: Device seconds per plotted point (at least), and per mean of the rate plot.
POINT_EVERY_S = 1.0
MEAN_EVERY_S = 60.0
#: Plotted points kept at most: a longer history spaces them further apart.
MAX_POINTS = 3600
DEFAULT_HISTORY_MIN = 60.0
#: Events (BIAS results, ...) kept for a page that connects later.
MAX_EVENTS = 20
#: A minute is plotted when its samples begin within this long (device s) of its start and end within this long
#: of its end (the first minute after a start, or one a link gap cut, is not a minute's mean).
MINUTE_COVER_S = 1.0
#: A STATUS whose ``missing_frames`` grew within this long (host s) shows the "samples missing" banner.
MISSING_BANNER_S = 60.0


#: STATUS counters on the page, in this order: (key, label).
STATUS_ROWS = (
    ("port_state", "port"),
    ("frames", "frames"),
    ("missing_frames", "missing frames"),
    ("crc_errors", "CRC errors"),
    ("bytes_discarded", "bytes discarded"),
    ("seq_gaps", "sequence gaps"),
    ("published", "published"),
    ("clients", "NDJSON clients"),
    ("dropped_clients", "dropped NDJSON clients"),
    ("web_clients", "web pages"),
    ("web_dropped_clients", "dropped web pages"),
    ("capture_state", "capture"),
    ("capture_bytes", "capture bytes"),
    ("chamber", "chamber (read-only)"),
    ("bias_dph", "bias removed (deg/h)"),
    ("adapting", "adapting"),
    ("cpu_percent", "daemon CPU (%)"),
    ("rss_mb", "daemon RSS (MB)"),
    ("uptime_s", "uptime"),
)


class _Mean:
    """Running sums of one bucket (a second or a minute of device time)."""

    __slots__ = ("bucket", "n", "rate_sum", "raw_sum", "first_t_s", "last")

    def __init__(self, bucket: int) -> None:
        self.bucket = bucket
        self.n = 0
        self.rate_sum = 0.0
        self.raw_sum = 0.0
        self.first_t_s: float | None = None  # device time of its first sample
        self.last: Mapping[str, Any] | None = None


class ViewState:
    """The page's data: the latest sample and objects, the plotted series, the banners."""

    def __init__(self, history_min: float = DEFAULT_HISTORY_MIN, control_address: str | None = None) -> None:
        if not (math.isfinite(history_min) and history_min > 0):
            raise ValueError(f"history_min must be a positive number of minutes, got {history_min!r}")
        self.history_s = history_min * 60.0
        self.point_every_s = max(POINT_EVERY_S, self.history_s / MAX_POINTS)
        self.control_address = control_address  # the NDJSON listener, for the bias banner's ctl command
        self.points: deque[dict[str, Any]] = deque()
        self.minutes: deque[dict[str, Any]] = deque()
        self.angle: Mapping[str, Any] | None = None
        self.angle_host_s: float | None = None
        self._rate = RateAverage()
        self.objects: dict[str, Mapping[str, Any]] = {}  # the last STATUS, DEVICE, VERSION by class
        self.events: deque[Mapping[str, Any]] = deque(maxlen=MAX_EVENTS)
        self.samples = 0
        self.restarts = 0
        self._point: _Mean | None = None
        self._minute: _Mean | None = None
        self._missing: tuple[float, int] | None = None  # (host s it last grew, the count then)
        self._started_s: float | None = None

    # -------------------------------------------------------------------------------- input

    def add_angles(self, objs: Iterable[Mapping[str, Any]], now_s: float) -> None:
        """A published batch of ANGLE objects (``now_s``: host monotonic seconds it arrived)."""
        for obj in objs:
            t_s = _number(obj.get("t_s"))
            if t_s is None:
                continue
            if self.angle is not None and t_s < self.angle["t_s"]:
                self._restart()
            self._add(obj, t_s)
            self.angle = obj
            self.samples += 1
        if self.angle is not None:
            self.angle_host_s = now_s

    def add_object(self, obj: Mapping[str, Any], now_s: float) -> None:
        """Any other published object: the last of each class is kept; BIAS results are events."""
        cls = obj.get("class")
        if not isinstance(cls, str):
            return
        if cls in ("STATUS", "DEVICE", "VERSION"):
            if cls == "STATUS":
                missing = obj.get("missing_frames")
                if isinstance(missing, int):
                    if self._missing is None or missing < self._missing[1]:
                        self._missing = (-math.inf, missing)  # the first STATUS, or the daemon restarted
                    elif missing > self._missing[1]:
                        self._missing = (now_s, missing)
            self.objects[cls] = obj
        else:
            self.events.append(obj)

    def _restart(self) -> None:
        self.points.clear()
        self.minutes.clear()
        self._point = self._minute = None
        self._rate.reset()
        self.restarts += 1

    @property
    def rate_1s_dph(self) -> float | None:
        """The compensated rate's mean over the last second of device time (``display.RateAverage``), or None."""
        mean = self._rate.mean()
        return None if mean is None else mean[0]

    def _add(self, obj: Mapping[str, Any], t_s: float) -> None:
        self._rate.add(obj)
        point = math.floor(t_s / self.point_every_s)
        if self._point is None or point != self._point.bucket:
            if self._point is not None:
                self._close_point(self._point)
            self._point = _Mean(point)
        minute = math.floor(t_s / MEAN_EVERY_S)
        if self._minute is None or minute != self._minute.bucket:
            if self._minute is not None:
                self._close_minute(self._minute)
            self._minute = _Mean(minute)
        rate, raw = _number(obj.get("rate_dph")), _number(obj.get("rate_raw_dph"))
        for mean in (self._point, self._minute):
            if rate is not None and raw is not None:
                mean.n += 1
                mean.rate_sum += rate
                mean.raw_sum += raw
            if mean.first_t_s is None:
                mean.first_t_s = t_s
            mean.last = obj

    def _close_point(self, point: _Mean) -> None:
        last = point.last
        temps = last.get("temps_c") if isinstance(last.get("temps_c"), Mapping) else {}
        shown, since_bias = drift_sigma(last, self.objects.get("STATUS", {}))
        flags = last.get("flags")
        estimated = not (isinstance(flags, list) and "uncompensated" in flags)  # no estimate: drift_dph absent
        self.points.append(
            {
                "t_s": last["t_s"],
                "utc": last.get("utc"),
                "drift_dph": None if estimated is False else _number(last.get("drift_dph")),
                "drift_sigma_dph": _number(last.get("drift_sigma_dph")),
                "drift_band_dph": None if shown is None or estimated is False else BAND_SIGMAS * shown,
                "band_since_bias": since_bias,
                "angle_arcsec": _number(last.get("angle_arcsec")),
                "rate_dph": point.rate_sum / point.n if point.n else None,
                "temps_c": {str(k): _number(v) for k, v in temps.items()},
            }
        )
        self._trim(self.points)

    def _close_minute(self, minute: _Mean) -> None:
        start_s = minute.bucket * MEAN_EVERY_S
        covered = (
            minute.first_t_s is not None
            and minute.first_t_s < start_s + MINUTE_COVER_S
            and minute.last["t_s"] >= start_s + MEAN_EVERY_S - MINUTE_COVER_S
        )
        if not minute.n or not covered:  # begun part-way (the start, a link gap) or cut short: not a minute's mean
            return
        self.minutes.append(
            {
                "t_s": minute.bucket * MEAN_EVERY_S,
                "utc": minute.last.get("utc"),
                "rate_dph": minute.rate_sum / minute.n,
                "rate_raw_dph": minute.raw_sum / minute.n,
                "samples": minute.n,
            }
        )
        self._trim(self.minutes)

    def _trim(self, series: deque) -> None:
        newest = series[-1]["t_s"]
        while series and series[0]["t_s"] < newest - self.history_s:
            series.popleft()

    # -------------------------------------------------------------------------------- output

    def snapshot(self, now_s: float) -> dict[str, Any]:
        """Everything a page needs when it connects: the full series and the current state."""
        return {
            "type": "snapshot",
            "points": list(self.points),
            "minutes": list(self.minutes),
            "events": list(self.events),
            "rows": [list(row) for row in STATUS_ROWS],
            **self._current(now_s),
        }

    def update(self, now_s: float, points_after_s: float | None, minutes_after_s: float | None) -> dict[str, Any]:
        """The current state and the series' points newer than the device times given (None: all)."""
        return {
            "type": "update",
            "points": _newer(self.points, points_after_s),
            "minutes": _newer(self.minutes, minutes_after_s),
            **self._current(now_s),
        }

    def _current(self, now_s: float) -> dict[str, Any]:
        if self._started_s is None:
            self._started_s = now_s
        angle = self.angle or {}
        status = self.objects.get("STATUS", {})
        state = {
            "device": self.objects.get("DEVICE", {}),
            "status": status,
            "angle": angle,
            "angle_age_s": None if self.angle_host_s is None else now_s - self.angle_host_s,
            "elapsed_s": now_s - self._started_s,
            "address": self.control_address,
        }
        lines = [
            {"text": line.strip("* "), "level": "alarm" if line.startswith("***") else "notice"}
            for line in banners(state)
        ]
        missing = self._missing is not None and now_s - self._missing[0] <= MISSING_BANNER_S
        if missing:
            lines.insert(
                0,
                {
                    "text": f"SAMPLES MISSING: {self._missing[1]:,} frames missing since start, the last "
                    f"{now_s - self._missing[0]:.0f} s ago",
                    "level": "alarm",
                },
            )
        shown, since_bias = drift_sigma(angle, status)
        return {
            "angle": dict(angle),
            "drift_sigma": {  # the sample's sigma(t), the capture's sigma(t_b), and the sigma shown
                "sigma_dph": _number(angle.get("drift_sigma_dph")),
                "bias_sigma_dph": _number(status.get("bias_sigma_dph")) if since_bias else None,
                "shown_dph": shown,
                "since_bias": since_bias,
                "band_sigmas": BAND_SIGMAS,
            },
            "rate_1s_dph": self.rate_1s_dph,
            "status": dict(status),
            "device": dict(self.objects.get("DEVICE", {})),
            "version": dict(self.objects.get("VERSION", {})),
            "banners": lines,
            "temperatures": temperature_names(self.angle),
            "restarts": self.restarts,
            "alarm": any(line["level"] == "alarm" for line in lines),
            "page_state": page_state(state),
            "text": self.text(state["angle_age_s"]),
        }

    def text(self, angle_age_s: float | None) -> dict[str, str]:
        """The page's numbers as shown, formatted here so every view agrees."""
        a = self.angle or {}
        temps = a.get("temps_c") if isinstance(a.get("temps_c"), Mapping) else {}
        flags = a.get("flags") if isinstance(a.get("flags"), list) else []
        status = self.objects.get("STATUS", {})
        device = self.objects.get("DEVICE", {})
        out = {
            "seq": str(a["seq"]) if isinstance(a.get("seq"), int) else "-",
            "t_s": _fixed(a.get("t_s"), 3),
            "utc": str(a.get("utc", "-")),
            "angle_arcsec": _angle(a.get("angle_arcsec"), format_arcsec),
            "angle_dms": _angle(a.get("angle_arcsec"), format_dms),
            "angle_raw_arcsec": _angle(a.get("angle_raw_arcsec"), format_arcsec),
            "angle_raw_dms": _angle(a.get("angle_raw_arcsec"), format_dms),
            "rate_dph": _fixed(a.get("rate_dph"), 1),
            "rate_1s_dph": _fixed(self.rate_1s_dph, 2),
            "rate_raw_dph": _fixed(a.get("rate_raw_dph"), 1),
            "drift_dph": _fixed(a.get("drift_dph"), 3),
            **_sigma_text(a, status),
            "flags": ", ".join(str(f) for f in flags) or "none",
            "age": "-" if angle_age_s is None else f"{angle_age_s:.1f} s ago",
            "link": {"activated": "link up", "deactivated": "link down"}.get(device.get("state"), "-"),
            "instrument": " ".join(str(device[k]) for k in ("serial", "format") if k in device) or "-",
            **_model_texts(model_in_use(status, self.objects.get("VERSION", {}))),
        }
        for name, value in temps.items():
            out[f"temp_{name}"] = _fixed(value, 3)
        for key, _label in STATUS_ROWS:
            value = status.get(key)
            out[f"status_{key}"] = (
                format_duration(value) if key == "uptime_s" and value is not None else _status_text(value)
            )
        out["status_chamber"] = chamber_text(status.get("chamber"))
        return out


def page_state(state: Mapping[str, Any]) -> dict[str, Any]:
    """What the page's figures are, for its pill and its greying (``stale``): ``waiting for data`` before the
    first sample; ``link down: figures stale`` (``display.link_down``: DEVICE ``deactivated``, STATUS
    ``port_state`` not ``open``); ``no data for N s: figures stale`` after ``NO_DATA_S`` without a sample; else
    ``live``.  ``level``: ``waiting``, ``bad`` or ``ok`` (grey, red, green)."""
    if not state.get("angle"):
        return {"text": "waiting for data", "level": "waiting", "stale": False}
    if link_down(state):
        return {"text": "link down: figures stale", "level": "bad", "stale": True}
    age = state.get("angle_age_s")
    if age is not None and age >= NO_DATA_S:
        return {"text": f"no data for {age:.0f} s: figures stale", "level": "bad", "stale": True}
    return {"text": "live", "level": "ok", "stale": False}


def temperature_names(angle: Mapping[str, Any] | None) -> list[str]:
    """The sample's thermometers as the page lists and plots them: ``TEMPERATURE_ORDER``'s (as ``watch``), then any
    other, sorted."""
    temps = (angle or {}).get("temps_c")
    names = [str(k) for k in temps] if isinstance(temps, Mapping) else []
    return [n for n in TEMPERATURE_ORDER if n in names] + sorted(n for n in names if n not in TEMPERATURE_ORDER)


def _sigma_text(angle: Mapping[str, Any], status: Mapping[str, Any]) -> dict[str, str]:
    """The drift's 1-sigma as the page shows it (``display.drift_sigma``, as ``watch``), its label, and the label
    of the band around the drift plot."""
    shown, since_bias = drift_sigma(angle, status)
    if _number(angle.get("drift_sigma_dph")) is None:
        label = "none (no estimate yet, or a model without one)"
    elif since_bias and shown is None:
        label = "since the bias: unknown (the bias was captured without one)"
    elif since_bias:
        label = "1\u03c3 since the bias: \u221a(\u03c3(t)\u00b2 + \u03c3(t_b)\u00b2)"
    else:
        label = "1\u03c3 of the 1-min mean, about the run's mean (the bias)"
    band = f"\u00b1{BAND_SIGMAS:g}\u03c3 (95 %)" + (", since the bias" if since_bias else "")
    return {"drift_sigma_dph": _fixed(shown, 4), "drift_sigma_label": label, "drift_band_label": band}


def _model_texts(model_file: Mapping[str, Any]) -> dict[str, str]:
    """The model in use as the page names it: ``display.model_text`` (as ``watch`` and ``ctl status``) and the
    whole SHA-256 of its file."""
    sha256 = model_file.get("sha256")
    return {"model": model_text(model_file), "model_sha256": sha256 if isinstance(sha256, str) else "-"}


def _angle(value: Any, fmt: Any) -> str:
    """An angle as ``watch`` shows it (``fmt``: ``format_arcsec`` or ``format_dms``), ``-`` when not a number."""
    return fmt(value) if _number(value) is not None else "-"


def chamber_text(chamber: Any) -> str:
    """STATUS's ``chamber`` on the page: "air 41.25 degC, set point 42.00 degC (link up, 1.2 s ago)"; the last
    good reading with "link lost" while it is; "-" without a chamber."""
    if not isinstance(chamber, Mapping):
        return "-"
    link = "link up" if chamber.get("link_up") else "link lost" if chamber.get("state") == "link_lost" else "starting"
    age = chamber.get("age_s")
    when = f", {age:.1f} s ago" if isinstance(age, (int, float)) and not isinstance(age, bool) else ""
    air, setpoint = _fixed(chamber.get("air_c"), 2), _fixed(chamber.get("setpoint_c"), 2)
    if air == "-" and setpoint == "-":
        return f"no reading yet ({link})"
    return f"air {air} degC, set point {setpoint} degC ({link}{when})"


def _status_text(value: Any) -> str:
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int):
        return f"{value:,}"
    return str(value)


def _newer(series: deque, after_s: float | None) -> list[dict[str, Any]]:
    if after_s is None:
        return list(series)
    out = []
    for item in reversed(series):
        if item["t_s"] <= after_s:
            break
        out.append(item)
    out.reverse()
    return out


__all__ = [
    "DEFAULT_HISTORY_MIN",
    "MEAN_EVERY_S",
    "NO_DATA_S",
    "POINT_EVERY_S",
    "STATUS_ROWS",
    "TEMPERATURE_ORDER",
    "ViewState",
    "page_state",
    "temperature_names",
]
