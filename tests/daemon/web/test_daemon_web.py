"""The web view's data (``view.ViewState``), its metrics (``metrics``) and its listener (``web.WebView``).

The listener is tested in-process on a free loopback port, with raw sockets where a client must misbehave
(aiohttp's own client would not).  Readiness: ``WebView.start`` returns once the socket listens; WebSocket
messages are waited for, never slept for.
"""

from __future__ import annotations

import gzip
import importlib.resources
import json
import math
import re
import socket
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
import yaml
from prometheus_client.parser import text_string_to_metric_families
from web_helpers import MODEL_FILE, SCRAPED_STATE, TIMEOUT_S, WsClient, angle, get, host_of, http, login, post, stream

from fog_driver.client.display import format_duration
from fog_driver.daemon.limits import AUTH_FAILURES_BEFORE_BACKOFF
from fog_driver.daemon.limits import WEB_MAX_CONNECTIONS_PER_PEER as MAX_CONNECTIONS_PER_PEER
from fog_driver.daemon.limits import WEB_MAX_WS_MESSAGES_PER_S as MAX_WS_MESSAGES_PER_S
from fog_driver.daemon.web.metrics import (
    DEPRECATED_NAMES,
    LATENCY_BUCKETS_S,
    METRICS,
    DaemonCollector,
    LatencyHistogram,
)
from fog_driver.daemon.web.server import WebView
from fog_driver.daemon.web.view import MEAN_EVERY_S, MISSING_BANNER_S, ViewState
from fog_driver.tools.watch import format_arcsec, format_dms

# ---------------------------------------------------------------------------------------------- ViewState


def test_minute_means_are_every_samples_mean_and_points_one_per_second():
    samples = stream(100 * 200)  # 200 s at 100 Hz from t = 3 s
    view = ViewState()
    view.add_angles(samples, 0.0)
    t = np.array([s["t_s"] for s in samples])
    rate = np.array([s["rate_dph"] for s in samples])
    raw = np.array([s["rate_raw_dph"] for s in samples])
    minute = np.floor(t / MEAN_EVERY_S)
    closed = np.unique(minute)[1:-1]  # the first began 3 s in (not a whole minute), the last is still open
    assert [m["t_s"] for m in view.minutes] == [k * MEAN_EVERY_S for k in closed]
    for m, k in zip(view.minutes, closed):
        assert m["rate_dph"] == pytest.approx(rate[minute == k].mean(), rel=1e-12)
        assert m["rate_raw_dph"] == pytest.approx(raw[minute == k].mean(), rel=1e-12)
        assert m["samples"] == int((minute == k).sum())
    second = np.floor(t)
    closed_s = np.unique(second)[:-1]
    assert len(view.points) == len(closed_s)
    for p, k in zip(view.points, closed_s):
        last = samples[int(np.nonzero(second == k)[0][-1])]
        assert p["t_s"] == last["t_s"] and p["drift_dph"] == last["drift_dph"]
        assert p["temps_c"] == last["temps_c"]
        assert p["rate_dph"] == pytest.approx(rate[second == k].mean(), rel=1e-12)
    assert view.rate_1s_dph == pytest.approx(rate[t > t[-1] - 1.0].mean(), rel=1e-12)  # the last second's


def test_the_rate_1s_mean_is_watchs_every_samples_mean_over_the_last_second_through_a_zero_and_a_gap():
    """The page and ``fog-driver watch`` show the 1-s mean with one piece of code (``display.RateAverage``): over
    every sample it is the mean of their ``rate_dph`` in the last second of device time; a ``?ZERO`` (the angles
    jump to 0) does not disturb it, and after frames lost (a replug) it starts again from the first sample after
    them, averaging on through the samples flagged ``gap`` while the estimate settles."""
    from fog_driver.client.display import RateAverage

    samples = stream(100 * 5)  # 5 s at 100 Hz from t = 3 s
    for s in samples[-50:]:  # a ?ZERO half a second before the end
        s["angle_arcsec"] -= samples[-51]["angle_arcsec"]
    view = ViewState()
    view.add_angles(samples, 0.0)
    t = np.array([s["t_s"] for s in samples])
    rate = np.array([s["rate_dph"] for s in samples])
    assert view.rate_1s_dph == pytest.approx(rate[t > t[-1] - 1.0].mean(), rel=1e-12)
    # 145 s of frames lost, then 0.5 s of samples all flagged gap: the mean of those after the first
    after = [angle(14500 + i, 150.0 + i / 100, flags=["gap"]) for i in range(50)]
    view.add_angles(after, 1.0)
    assert view.rate_1s_dph == pytest.approx(np.mean([s["rate_dph"] for s in after[1:]]), rel=1e-12)
    watch = RateAverage()
    for s in samples + after:
        watch.add(s)
    assert watch.mean() == (view.rate_1s_dph, pytest.approx(0.49, rel=1e-9))


def test_a_one_minute_mean_is_plotted_only_for_a_minute_the_samples_cover():
    """The review's finding 15: a one-minute mean was plotted before the daemon started (the first minute's,
    begun part-way, drawn at its middle).  A minute is plotted when its samples begin within its first second and
    end within its last: not the first one after the start, nor one a link gap cut short at either end; one with
    a short gap inside is the mean of the samples that came."""
    view = ViewState()
    first = [angle(i, 30.0 + i / 100) for i in range(100 * 90)]  # 30 s .. 120 s: minute 0 from 30 s, minute 1 whole
    inside = [s for s in first if not 70.0 <= s["t_s"] < 75.0]  # 5 s lost inside minute 1: kept
    tail = [angle(20000 + i, 170.0 + i / 100) for i in range(100 * 80)]  # 120 s .. 170 s lost: minute 2 cut short
    view.add_angles(inside + tail, 0.0)
    assert [m["t_s"] for m in view.minutes] == [60.0, 180.0]  # minutes 1 and 3 (minute 4 still open)
    minute_1 = [s["rate_dph"] for s in inside if 60.0 <= s["t_s"] < 120.0]
    assert view.minutes[0]["rate_dph"] == pytest.approx(np.mean(minute_1), rel=1e-12)
    assert view.minutes[0]["samples"] == len(minute_1) == 5500


def test_the_drift_plot_starts_at_the_first_estimate_not_from_0():
    """The review's finding 15: the drift plot began with a spike from 0 (the samples before the first estimate
    carry ``drift_dph`` 0, flagged ``uncompensated``).  Their points have no drift: the line starts at the first
    estimate; their temperatures are plotted."""
    view = ViewState()
    samples = stream(100 * 5)
    for s in samples[:250]:
        s.update(drift_dph=0.0, flags=["uncompensated"])
    view.add_angles(samples, 0.0)
    points = view.snapshot(0.1)["points"]
    assert [p["drift_dph"] for p in points] == [None, None, samples[299]["drift_dph"], samples[399]["drift_dph"]]
    assert all(p["drift_band_dph"] is None for p in points[:2]) and points[0]["temps_c"] == samples[99]["temps_c"]


def test_stale_figures_are_marked_and_the_pill_says_so_while_the_link_is_down_or_no_data_comes():
    """The review's finding 15: a green "live" pill beside "link down", the stale rate and drift not greyed.  The
    page state says what the figures are: live, or stale and why (the page greys them); waiting before any."""
    view = ViewState()
    assert view.snapshot(0.0)["page_state"] == {"text": "waiting for data", "level": "waiting", "stale": False}
    view.add_object({"class": "DEVICE", "state": "activated"}, 0.0)
    view.add_angles(stream(10), 0.0)
    assert view.snapshot(0.5)["page_state"] == {"text": "live", "level": "ok", "stale": False}
    view.add_object({"class": "DEVICE", "state": "deactivated"}, 1.0)
    assert view.snapshot(1.5)["page_state"] == {"text": "link down: figures stale", "level": "bad", "stale": True}
    view.add_object({"class": "DEVICE", "state": "activated"}, 2.0)
    assert view.update(2.0 + 5.2, None, None)["page_state"] == {
        "text": "no data for 7 s: figures stale",
        "level": "bad",
        "stale": True,
    }
    view.add_angles([angle(10, 4.0)], 8.0)
    assert view.update(8.1, None, None)["page_state"]["text"] == "live"


@pytest.mark.parametrize(
    ("seconds", "text"),
    [
        (0, "0 s"),
        (59.99, "59 s"),
        (1264.747, "21 min 4 s"),
        (3600, "1 h 00 min"),
        (11_230.5, "3 h 07 min"),
        (2 * 86400 + 5 * 3600 + 59, "2 d 5 h"),
        (None, "-"),
        (-1.0, "-"),
        (math.nan, "-"),
        ("12", "-"),
    ],
)
def test_a_duration_is_shown_as_a_person_reads_it(seconds, text):
    assert format_duration(seconds) == text


def test_the_status_table_shows_the_uptime_formatted_and_the_web_pages_beside_the_ndjson_clients():
    """The review's finding 15: uptime ``1264.747``; "clients 0" with the page open.  A page counts among the web
    listener's clients (STATUS ``web_clients``), shown beside the NDJSON clients (``clients``)."""
    view = ViewState()
    view.add_object({"class": "STATUS", "uptime_s": 1264.747, "clients": 0, "web_clients": 1}, 0.0)
    snapshot = view.snapshot(0.0)
    rows = dict((key, label) for key, label in snapshot["rows"])
    assert rows["uptime_s"] == "uptime" and rows["clients"] == "NDJSON clients" and rows["web_clients"] == "web pages"
    assert snapshot["text"]["status_uptime_s"] == "21 min 4 s"
    assert (snapshot["text"]["status_clients"], snapshot["text"]["status_web_clients"]) == ("0", "1")


@pytest.mark.determinism
def test_the_series_do_not_depend_on_how_the_samples_are_batched():
    samples = stream(100 * 130)
    whole = ViewState()
    whole.add_angles(samples, 0.0)
    rng = np.random.default_rng(7)
    pieces = ViewState()
    i = 0
    while i < len(samples):
        n = int(rng.integers(1, 300))
        pieces.add_angles(samples[i : i + n], 0.0)
        i += n
    one = ViewState()
    for s in samples:
        one.add_angles([s], 0.0)
    for other in (pieces, one):
        assert list(other.points) == list(whole.points)
        assert list(other.minutes) == list(whole.minutes)


def test_device_time_going_back_starts_the_series_afresh_and_history_is_bounded():
    view = ViewState(history_min=2.0)
    view.add_angles(stream(100 * 400), 0.0)  # 400 s: only the last 2 minutes of points are kept
    assert view.points[-1]["t_s"] - view.points[0]["t_s"] <= 120.0
    assert len(view.points) in (120, 121)
    view.add_angles(stream(250, t0=1.0), 1.0)  # the instrument restarted
    assert view.restarts == 1
    assert [p["t_s"] for p in view.points] == [1.99, 2.99]
    assert list(view.minutes) == []


def test_a_long_history_spaces_its_points_so_a_page_never_holds_more_than_an_hours_worth():
    view = ViewState(history_min=24 * 60)
    assert view.point_every_s == 24.0
    view.add_angles([angle(i, float(i)) for i in range(3 * 3600)], 0.0)  # 3 h at 1 Hz
    assert len(view.points) == 3 * 3600 // 24 - 1
    assert all(b["t_s"] - a["t_s"] == 24.0 for a, b in zip(view.points, list(view.points)[1:]))


def test_the_numbers_are_formatted_as_watch_formats_them():
    view = ViewState()
    sample = angle(12345, 100.0, rate=-3.25)
    sample["angle_arcsec"] = 3723.495
    view.add_angles([sample], 0.0)
    text = view.snapshot(0.5)["text"]
    assert text["seq"] == "12345"
    assert text["angle_arcsec"] == format_arcsec(3723.495) == "3723.50"
    assert text["angle_dms"] == format_dms(3723.495) == "1\u00b002'03.50\""
    assert text["rate_dph"] == "-3.2" or text["rate_dph"] == f"{-3.25:.1f}"
    assert text["temp_top"] == f"{sample['temps_c']['top']:.3f}"
    assert text["age"] == "0.5 s ago"


def test_the_thermometers_come_in_watchs_order():
    """The page sorted them by name (bottom, housing, top); ``fog-driver watch`` shows top, bottom, housing."""
    view = ViewState()
    assert view.snapshot(0.0)["temperatures"] == []  # no sample yet
    view.add_angles([angle(1, 3.0, temps_c={"housing": 22.0, "aux": 1.0, "bottom": 21.0, "top": 20.0})], 0.0)
    assert view.snapshot(0.1)["temperatures"] == ["top", "bottom", "housing", "aux"]
    view.add_angles([angle(2, 3.1, temps_c={"bottom": 21.0})], 0.1)
    assert view.update(0.2, None, None)["temperatures"] == ["bottom"]


def test_banners_for_a_link_down_and_for_missing_frames():
    view = ViewState(control_address="127.0.0.1:2948")
    view.add_angles(stream(10), 0.0)
    view.add_object({"class": "DEVICE", "state": "activated"}, 0.0)
    view.add_object({"class": "STATUS", "port_state": "open", "missing_frames": 0, "bias_captured": True}, 0.0)
    assert view.snapshot(0.1)["banners"] == [] and not view.snapshot(0.1)["alarm"]
    view.add_object({"class": "DEVICE", "state": "deactivated"}, 1.0)
    current = view.snapshot(1.1)
    assert current["alarm"] and current["banners"][0]["text"].startswith("LINK DOWN")
    assert current["text"]["link"] == "link down"
    view.add_object({"class": "DEVICE", "state": "activated"}, 2.0)
    view.add_object({"class": "STATUS", "port_state": "open", "missing_frames": 7, "bias_captured": True}, 2.0)
    view.add_angles([angle(20, 4.0)], 2.0)
    current = view.snapshot(3.0)
    assert [b["text"].split(":")[0] for b in current["banners"]] == ["SAMPLES MISSING"] and current["alarm"]
    view.add_angles([angle(21, 4.01)], 2.0 + MISSING_BANNER_S)
    assert view.snapshot(2.0 + MISSING_BANNER_S + 1)["banners"] == []  # a minute without new losses
    assert view.snapshot(2.0 + MISSING_BANNER_S + 5)["banners"][0]["text"].startswith("NO DATA for 5 s")
    view.add_object({"class": "STATUS", "port_state": "open", "missing_frames": 7, "bias_captured": False}, 70.0)
    view.add_angles([angle(22, 4.02)], 70.0)
    notice = view.snapshot(70.0)["banners"]
    assert [b["level"] for b in notice] == ["notice"] and "fog-driver ctl bias 60" in notice[0]["text"]


def test_the_drift_band_is_plain_sigma_before_a_bias_and_the_since_bias_form_after():
    """Each point keeps its sample's sigma and the band half-width 1.96 sigma as shown then: sigma(t) before a
    ?BIAS capture, sqrt(sigma(t)^2 + sigma(t_b)^2) once STATUS says one completed; none without a sigma."""
    view = ViewState()
    view.add_object({"class": "STATUS", "bias_captured": False, "bias_dph": 0.0}, 0.0)
    sigma = [None if i < 150 else 0.03 for i in range(400)]  # no estimate for the first 1.5 s
    view.add_angles(
        [angle(i, 3.0 + i / 100, **({} if v is None else {"drift_sigma_dph": v})) for i, v in enumerate(sigma)], 0.0
    )
    plain = view.snapshot(0.1)
    bands = [(p["t_s"], p["drift_sigma_dph"], p["drift_band_dph"], p["band_since_bias"]) for p in plain["points"]]
    assert bands == [(3.99, None, None, False), (4.99, 0.03, 1.96 * 0.03, False), (5.99, 0.03, 1.96 * 0.03, False)]
    assert plain["drift_sigma"] == {
        "sigma_dph": 0.03,
        "bias_sigma_dph": None,
        "shown_dph": 0.03,
        "since_bias": False,
        "band_sigmas": 1.96,
    }
    assert (
        plain["text"]["drift_sigma_dph"] == "0.0300" and plain["text"]["drift_band_label"] == "\u00b11.96\u03c3 (95 %)"
    )
    assert plain["text"]["drift_sigma_label"].startswith("1\u03c3 of the 1-min mean")
    # A bias captured with sigma(t_b) = 0.04: from then on sqrt(0.03^2 + 0.04^2) = 0.05, band 0.098.
    view.add_object({"class": "STATUS", "bias_captured": True, "bias_dph": 9.8, "bias_sigma_dph": 0.04}, 1.0)
    view.add_angles([angle(i, 3.0 + i / 100, drift_sigma_dph=0.03) for i in range(400, 600)], 1.0)
    after = view.snapshot(1.1)
    assert [p["band_since_bias"] for p in after["points"]] == [False, False, False, True, True]
    assert after["points"][-1]["drift_band_dph"] == pytest.approx(1.96 * 0.05, rel=1e-14)
    assert after["points"][2]["drift_band_dph"] == 1.96 * 0.03  # a point keeps the band it closed with
    assert after["drift_sigma"]["shown_dph"] == pytest.approx(0.05, rel=1e-14) and after["drift_sigma"]["since_bias"]
    assert after["drift_sigma"]["bias_sigma_dph"] == 0.04
    assert after["text"]["drift_sigma_dph"] == "0.0500" and "since the bias" in after["text"]["drift_band_label"]
    assert after["text"]["drift_sigma_label"].startswith("1\u03c3 since the bias")
    # No sigma in the samples (no estimate, a model without one): nothing shown, no band.
    none = ViewState()
    none.add_angles(stream(300), 0.0)
    snapshot = none.snapshot(0.1)
    assert all(p["drift_band_dph"] is None and p["drift_sigma_dph"] is None for p in snapshot["points"])
    assert snapshot["drift_sigma"]["shown_dph"] is None and snapshot["text"]["drift_sigma_dph"] == "-"
    assert snapshot["text"]["drift_sigma_label"].startswith("none")


def test_an_update_carries_only_points_newer_than_asked_for():
    view = ViewState()
    view.add_angles(stream(100 * 10), 0.0)
    first = view.update(0.0, None, None)
    assert len(first["points"]) == 9
    view.add_angles([angle(1000 + i, 13.0 + i / 100) for i in range(300)], 1.0)
    second = view.update(1.0, first["points"][-1]["t_s"], None)
    assert [p["t_s"] for p in second["points"]] == [12.99, 13.99, 14.99]


# ---------------------------------------------------------------------------------------------- metrics


def scrape(collector: DaemonCollector) -> dict:
    from prometheus_client import CollectorRegistry, generate_latest

    registry = CollectorRegistry(auto_describe=False)
    registry.register(collector)
    out: dict = {}
    for family in text_string_to_metric_families(generate_latest(registry).decode()):
        for sample in family.samples:
            out[(sample.name, tuple(sorted(sample.labels.items())))] = sample.value
    return out


def test_metrics_carry_the_status_counters_and_the_latency_histogram():
    latencies = np.random.default_rng(1).lognormal(np.log(0.002), 1.0, 5000)
    histogram = LatencyHistogram()
    for value in latencies:
        histogram.observe(float(value))
    state = SCRAPED_STATE
    m = scrape(DaemonCollector(lambda: state, histogram))
    assert m[("fog_driver_info", (("firmware", "2"), ("format", "kvh-a"), ("release", "9.9"), ("serial", "S1")))] == 1
    expected = {
        "fog_driver_bytes_total": 123456,
        "fog_driver_frames_total": 4000,
        "fog_driver_crc_errors_total": 3,
        "fog_driver_bytes_discarded_total": 77,
        "fog_driver_missing_frames_total": 12,
        "fog_driver_samples_published_total": 3990,
        "fog_driver_port_up": 0,
        "fog_driver_capture_up": 0,
        "fog_driver_port_reconnects_total": 4,
        "fog_driver_capture_failures_total": 6,
        "fog_driver_capture_bytes_lost_total": 999,
        "fog_driver_bias_degrees_per_hour": 0.25,
        "fog_driver_adapting": 1,
        "fog_driver_model_age_seconds": 86400,
        "fog_driver_drift_degrees_per_hour": -1.5,
        "fog_driver_drift_sigma_degrees_per_hour": 0.0375,
        "fog_driver_bias_sigma_degrees_per_hour": 0.0125,
        "fog_driver_rate_degrees_per_hour": 14.9,
        "fog_driver_last_sample_age_seconds": 0.25,
        "fog_driver_extrapolating": 1,
        "fog_driver_uptime_seconds": 12.5,
    }
    for name, value in expected.items():
        assert m[(name, ())] == value, name
    for old, new in DEPRECATED_NAMES.items():  # kept for a release: the same value under the old name
        assert m[(old, ())] == m[(new, ())], old
    assert m[("fog_driver_model_info", tuple(sorted(MODEL_FILE.items())))] == 1
    assert m[("fog_driver_clients", (("listener", "ndjson"),))] == 2
    assert m[("fog_driver_clients", (("listener", "web"),))] == 3
    assert m[("fog_driver_clients_dropped_total", (("listener", "web"),))] == 2
    assert m[("fog_driver_temperature_celsius", (("channel", "bottom"),))] == 31.0
    assert m[("fog_driver_flagged_samples_total", (("flag", "extrapolating"),))] == 5
    for bound in LATENCY_BUCKETS_S:  # cumulative counts against numpy's own count
        key = ("fog_driver_publish_latency_seconds_bucket", (("le", repr(bound)),))
        assert m[key] == int((latencies <= bound).sum()), bound
    assert m[("fog_driver_publish_latency_seconds_count", ())] == len(latencies)
    assert m[("fog_driver_publish_latency_seconds_sum", ())] == pytest.approx(latencies.sum(), rel=1e-9)
    exported = {name for name, _ in m} | {name[: -len("_bucket")] for name, _ in m if name.endswith("_bucket")}
    for name, (_kind, _) in METRICS.items():  # every documented metric is there
        assert name in exported, name


def test_metrics_of_a_daemon_that_has_said_nothing_yet_are_still_valid():
    m = scrape(DaemonCollector(lambda: {}, LatencyHistogram()))
    assert m[("fog_driver_publish_latency_seconds_count", ())] == 0


def test_no_sigma_gauges_without_an_estimate_or_a_bias_capture():
    """A sample without drift_sigma_dph (no estimate, or a daemon whose model gives none) and a STATUS before
    any ?BIAS: the gauges are absent, never NaN; the drift gauge is still there."""
    state = {"status": {"bias_dph": 0.0, "bias_captured": False}, "angle": {"drift_dph": 0.0, "flags": []}}
    m = scrape(DaemonCollector(lambda: state, LatencyHistogram()))
    assert m[("fog_driver_drift_degrees_per_hour", ())] == 0.0 and m[("fog_driver_bias_degrees_per_hour", ())] == 0.0
    names = {name for name, _ in m}
    for name in ("fog_driver_drift_sigma_degrees_per_hour", "fog_driver_bias_sigma_degrees_per_hour"):
        assert name not in names and {v: k for k, v in DEPRECATED_NAMES.items()}[name] not in names


# ---------------------------------------------------------------------------------------------- the listener


def test_the_page_its_assets_and_plotly_from_the_installed_package(web):
    view = web()
    status, headers, body = get(view.address, "/")
    assert status == 200 and b"/static/plotly.min.js" in body and b'<script src="http' not in body
    assert "default-src 'self'" in headers["content-security-policy"]
    plotly = importlib.resources.files("plotly").joinpath("package_data/plotly.min.js").read_bytes()
    status, headers, body = get(view.address, "/static/plotly.min.js")
    assert status == 200 and body == plotly and headers["content-type"].startswith("text/javascript")
    status, headers, body = get(view.address, "/static/plotly.min.js", "Accept-Encoding: gzip")
    assert headers["content-encoding"] == "gzip" and gzip.decompress(body) == plotly
    assert get(view.address, "/static/plotly.min.js", f"If-None-Match: {headers['etag']}")[0] == 304
    assert get(view.address, "/static/../../etc/passwd")[0] == 404
    assert get(view.address, "/static/nothing.js")[0] == 404
    delete = f"DELETE / HTTP/1.1\r\nHost: {host_of(view.address)}\r\nConnection: close\r\n\r\n"
    assert http(view.address, delete.encode())[0] == 405
    assert get(view.address, "/ws")[0] == 400  # not an upgrade


def test_the_websocket_sends_a_snapshot_then_decimated_updates(web):
    view = web(update_hz=20.0)
    view.publish({"class": "DEVICE", "state": "activated", "serial": "S9", "format": "fog-v1"})
    view.publish_angles(stream(500))
    ws = WsClient(view.address)
    assert ws.status == 101
    snapshot = ws.message()
    assert snapshot["type"] == "snapshot" and snapshot["angle"]["seq"] == 499
    assert [p["t_s"] for p in snapshot["points"]] == [3.99, 4.99, 5.99, 6.99]
    assert snapshot["text"]["instrument"] == "S9 fog-v1" and snapshot["text"]["link"] == "link up"
    sent = 500
    seen = []
    while len(seen) < 10:
        batch = stream(sent + 200)[sent:]  # 2 s of samples per update: only the last one is shown
        view.publish_angles(batch)
        sent += 200
        message = ws.message()
        assert message["type"] == "update"
        seen.append(message["angle"]["seq"])
        for point in message["points"]:
            assert point["t_s"] > snapshot["points"][-1]["t_s"]
    assert len(set(seen)) >= 5 and max(seen) < sent
    ws.close()


def test_api_view_carries_the_sigma_and_the_band(web):
    view = web()
    view.publish({"class": "STATUS", "bias_captured": True, "bias_sigma_dph": 0.04})
    view.publish_angles([angle(i, 3.0 + i / 100, drift_sigma_dph=0.03) for i in range(300)])
    status, headers, body = get(view.address, "/api/view")
    doc = json.loads(body)
    assert status == 200 and doc["angle"]["drift_sigma_dph"] == 0.03
    assert doc["drift_sigma"]["since_bias"] is True and doc["drift_sigma"]["shown_dph"] == pytest.approx(0.05)
    assert [p["drift_sigma_dph"] for p in doc["points"]] == [0.03, 0.03]
    assert [p["drift_band_dph"] for p in doc["points"]] == [pytest.approx(1.96 * 0.05)] * 2


def test_pages_start_their_series_afresh_when_the_instrument_restarts(web):
    view = web(update_hz=20.0)
    view.publish_angles(stream(1000))
    ws = WsClient(view.address)
    snapshot = ws.message()
    assert snapshot["restarts"] == 0 and snapshot["points"][-1]["t_s"] == 11.99
    view.publish_angles(stream(350, t0=1.0))  # device time went back
    message = ws.message()
    while message["restarts"] == 0:
        message = ws.message()
    assert [p["t_s"] for p in message["points"]] == [1.99, 2.99, 3.99]
    ws.close()


def test_beyond_loopback_every_request_needs_the_token(web):
    with pytest.raises(ValueError, match="without a token"):
        WebView("0.0.0.0", 0)
    view = web("0.0.0.0", token="s3cret-token")
    address = ("127.0.0.1", view.address[1])
    assert get(address, "/metrics")[0] == 401
    assert get(address, "/api/view")[0] == 401
    assert get(address, "/metrics", "Authorization: Bearer wrong-token")[0] == 401  # counts as a wrong token
    assert get(address, "/metrics", "Authorization: Bearer s3cret-token")[0] == 200  # and a right one resets
    status, headers, _ = get(address, "/", "Accept: text/html")
    assert status == 302 and headers["location"] == "/login"
    assert WsClient(address).status == 401
    cookie = login(address, "s3cret-token")
    assert "s3cret" not in cookie
    assert get(address, "/api/view", f"Cookie: {cookie}")[0] == 200
    ws = WsClient(address, headers=[f"Cookie: {cookie}"])
    assert ws.status == 101 and ws.message()["type"] == "snapshot"
    view.set_token("another-token")  # rotated: the old cookie no longer opens anything, the page is closed
    with pytest.raises(ConnectionError):
        while True:
            ws.message()
    ws.close()
    assert get(address, "/api/view", f"Cookie: {cookie}")[0] == 401
    status, headers, _ = get(address, "/", f"Cookie: {cookie}", "Accept: text/html")
    assert status == 302 and headers["location"] == "/login"  # a browser is sent to log in again
    assert get(address, "/metrics", "Authorization: Bearer another-token")[0] == 200
    codes = [post(address, "/login", b"token=nope")[0] for _ in range(AUTH_FAILURES_BEFORE_BACKOFF + 2)]
    assert codes == [401] * (AUTH_FAILURES_BEFORE_BACKOFF + 1) + [429]  # then this address waits
    assert get(address, "/metrics", "Authorization: Bearer another-token")[0] == 429  # the right one too: unread


def test_a_websocket_from_another_origin_is_refused(web):
    view = web()
    assert WsClient(view.address, origin="http://evil.example").status == 403
    ws = WsClient(view.address, origin=f"http://{view.address[0]}:{view.address[1]}")
    assert ws.status == 101
    ws.close()


def test_oversized_requests_get_a_clear_status(web):
    view = web()
    long_header = "X-Junk: " + "a" * 10000
    assert get(view.address, "/", long_header)[0] == 431
    assert get(view.address, "/" + "a" * 10000)[0] == 414
    many = [f"X-H{i}: 1" for i in range(200)]
    assert get(view.address, "/", *many)[0] == 431
    view_beyond = web("0.0.0.0", token="s3cret-token")
    assert post(("127.0.0.1", view_beyond.address[1]), "/login", b"token=" + b"a" * 5000)[0] == 413


def test_connections_beyond_the_per_peer_limit_are_closed_at_once(web):
    view = web()
    held = [socket.create_connection(view.address, timeout=TIMEOUT_S) for _ in range(MAX_CONNECTIONS_PER_PEER)]
    try:
        for s in held:  # each one answered: they are counted as open connections
            s.sendall(f"GET /favicon.ico HTTP/1.1\r\nHost: {host_of(view.address)}\r\n\r\n".encode())
            assert s.recv(4096).startswith(b"HTTP/1.1 204")
        extra = socket.create_connection(view.address, timeout=TIMEOUT_S)
        assert extra.recv(4096) == b""  # closed before a byte was read
        extra.close()
        assert view.refused_connections == 1
    finally:
        for s in held:
            s.close()


def test_a_connection_that_sends_no_request_is_closed(web, monkeypatch):
    monkeypatch.setattr("fog_driver.daemon.web.server.WEB_REQUEST_HEAD_TIMEOUT_S", 0.5)
    view = web()
    idle = socket.create_connection(view.address, timeout=TIMEOUT_S)
    idle.sendall(b"GET / HTTP/1.1\r\nHost: x\r\n")  # ...and never the blank line
    started = time.monotonic()
    assert idle.recv(4096) == b""
    assert time.monotonic() - started < 5.0
    idle.close()


def test_a_kept_alive_connection_that_starts_a_request_and_never_ends_it_is_closed(web, monkeypatch):
    monkeypatch.setattr("fog_driver.daemon.web.server.WEB_REQUEST_HEAD_TIMEOUT_S", 0.5)
    view = web()
    slow = socket.create_connection(view.address, timeout=TIMEOUT_S)
    slow.sendall(f"GET /favicon.ico HTTP/1.1\r\nHost: {host_of(view.address)}\r\n\r\n".encode())
    assert slow.recv(4096).startswith(b"HTTP/1.1 204")
    slow.sendall(b"GET / HTTP/1.1\r\nHost: x\r\nX-Slow: 1")  # the second request's head, never finished
    started = time.monotonic()
    assert slow.recv(4096) == b""
    assert time.monotonic() - started < 5.0
    slow.close()


def test_a_websocket_outlives_the_request_head_timeout(web, monkeypatch):
    monkeypatch.setattr("fog_driver.daemon.web.server.WEB_REQUEST_HEAD_TIMEOUT_S", 0.2)
    view = web(update_hz=20.0)
    ws = WsClient(view.address)
    ws.message()
    deadline = time.monotonic() + 1.5  # several sweeps past the timeout, the page still gets its updates
    n = 0
    while time.monotonic() < deadline:
        if n % 5 == 0:
            ws.send_text("{}")  # frames from the page too (4 a second, under the limit): they are no request head
        assert ws.message()["type"] == "update"
        n += 1
    ws.close()


def test_a_browser_that_stops_reading_is_dropped_and_others_carry_on(web):
    view = web(update_hz=50.0, max_backlog_s=0.5)
    stalled = WsClient(view.address, rcvbuf=4096)
    assert stalled.status == 101
    live = WsClient(view.address)
    live.message()
    seq = 0
    pad = "x" * 60000
    while view.fanout.dropped_browsers == 0:
        view.publish_angles([angle(seq, 3.0 + seq / 100, pad=pad)])
        seq += 1
        message = live.message()  # the live page keeps getting its updates meanwhile
        assert message["type"] == "update"
    assert len(view.fanout.browsers) == 1
    live.close()
    stalled.close()


def test_a_page_that_floods_the_socket_is_closed(web):
    view = web()
    ws = WsClient(view.address)
    ws.message()
    for _ in range(MAX_WS_MESSAGES_PER_S + 5):
        ws.send_text("hello")
    with pytest.raises(ConnectionError, match="closed"):
        while True:
            ws.message()
    ws.close()


def test_api_view_is_the_snapshot(web):
    view = web()
    view.publish_angles(stream(350))
    status, _, body = get(view.address, "/api/view")
    doc = json.loads(body)
    assert status == 200 and doc["type"] == "snapshot" and doc["angle"]["seq"] == 349
    counts = defaultdict(int)
    for p in doc["points"]:
        counts[math.floor(p["t_s"])] += 1
    assert set(counts.values()) == {1}


def test_the_shipped_prometheus_and_grafana_configs_name_only_metrics_that_exist():
    root = Path(__file__).resolve().parents[3] / "configs" / "monitoring"
    dashboard = json.loads(root.joinpath("grafana-dashboard.json").read_text())
    exprs = [t["expr"] for panel in dashboard["panels"] for t in panel["targets"]]
    rules = yaml.safe_load(root.joinpath("fog-driver-rules.yml").read_text())
    exprs += [rule["expr"] for group in rules["groups"] for rule in group["rules"]]
    assert "fog-driver-rules.yml" in yaml.safe_load(root.joinpath("prometheus.yml").read_text())["rule_files"]
    used = {re.sub(r"_(bucket|count|sum)$", "", name) for e in exprs for name in re.findall(r"fog_driver_\w+", e)}
    assert used and used <= set(METRICS), used - set(METRICS)
    assert {"fog_driver_port_up", "fog_driver_missing_frames_total", "fog_driver_publish_latency_seconds"} <= used
    counters = {name for name, (kind, _) in METRICS.items() if kind == "counter"}
    for e in exprs:  # a counter is only ever read through rate() or increase()
        for name in set(re.findall(r"fog_driver_\w+", e)) & counters:
            assert re.search(rf"(rate|increase)\({name}\b", e), e


def test_the_readme_lists_every_metric():
    readme = (Path(__file__).resolve().parents[3] / "docs" / "how-to" / "monitoring.md").read_text()
    for name, (kind, _) in METRICS.items():
        assert f"| `{name}` | {kind} |" in readme, name


def test_the_daemon_refuses_a_web_view_beyond_loopback_without_a_token_and_one_on_a_busy_port(tmp_path):
    from cli_run import assert_one_line_error, run_cli

    port = f"replay://{Path(__file__).resolve().parents[2] / 'data' / 'sim-short.bin'}?rate=10"
    proc = run_cli(
        "run",
        "--port",
        port,
        "--listen",
        "127.0.0.1:0",
        "--http",
        "0.0.0.0:0",
        "--capture-dir",
        str(tmp_path / "c"),
        cwd=tmp_path,
    )
    assert_one_line_error(proc, 78, "http 0.0.0.0:0", "without a token")
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        proc = run_cli(
            "run",
            "--port",
            port,
            "--listen",
            "127.0.0.1:0",
            "--http",
            f"127.0.0.1:{busy.getsockname()[1]}",
            "--capture-dir",
            str(tmp_path / "c"),
            cwd=tmp_path,
        )
    assert_one_line_error(proc, 75, "cannot listen on", "(http)")


def test_without_the_web_extra_the_error_says_what_to_install(monkeypatch):
    import importlib.util

    from fog_driver.daemon.web import server as web_module

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "plotly" else real(name, *a))
    with pytest.raises(
        web_module.WebUnavailable, match=r"needs plotly \(the 'web' extra\); .*pip install -e '\.\[web\]'"
    ):
        web_module.check_web_extra()
