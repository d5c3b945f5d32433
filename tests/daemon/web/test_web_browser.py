"""The web view in a real browser: headless Chromium (Debian's ``chromium``), driven by Playwright.

A daemon (``fog-driver run --http``) reads a recorded capture through a real pty; an NDJSON client watches
every sample beside the page.  The test checks that the numbers the page shows are the NDJSON stream's for the
same ``seq`` (formatted as ``watch`` formats them), that the plots grow, that the LINK DOWN banner appears when
the pty is unplugged and goes when it comes back, and that the page raised no error (its Content Security
Policy included).  Screenshots go to the test's directory, and to ``$FOG_SCREENSHOT_DIR`` when set (the
README's picture: ``FOG_SCREENSHOT_DIR=docs python -m pytest tests/daemon/web/test_web_browser.py``).

Readiness: the daemon's "listening on" line, the DEVICE object, and Playwright's waits on the page's own
elements (``expect``), never sleeps.  The pty is fed at 10 times the capture's pace by a writer thread, as
an instrument would feed it.
"""

from __future__ import annotations

import os
import re
import shutil
import threading
import time
from pathlib import Path

import pytest
from daemon_hil import Client, Daemon
from playwright.sync_api import expect, sync_playwright
from web_helpers import WAIT_MS, open_page

from fog_driver.tools.watch import format_arcsec, format_dms
from fog_driver.transport import PtyPair

pytestmark = pytest.mark.serial  # a browser: run apart from the suite's parallel part

DATA = Path(__file__).resolve().parents[2] / "data"
CAPTURE = DATA / "sim-short.bin"  # 300 s at 10 Hz (its sidecar says how it was made)
FRAME_BYTES = 29
SPEEDUP = 10


def sample(seq: int, t_s: float, **extra) -> dict:
    """An ANGLE object as the daemon publishes it (a drift of -0.5 deg/h, three thermometers)."""
    return {
        "class": "ANGLE",
        "seq": seq,
        "t_s": t_s,
        "angle_arcsec": seq * 0.1,
        "angle_raw_arcsec": seq * 0.11,
        "rate_dph": 10.0,
        "rate_raw_dph": 10.5,
        "drift_dph": -0.5,
        "temps_c": {"top": 20.0, "bottom": 21.0, "housing": 22.0},
        "flags": [],
        "utc": f"2026-12-03T00:{int(t_s) // 60:02d}:{int(t_s) % 60:02d}.000Z",
        **extra,
    }


class Instrument:
    """Writes the capture into the pty at ``SPEEDUP`` times its pace; ``flowing`` pauses it (unplugged)."""

    def __init__(self, pty: PtyPair, data: bytes, rate_hz: int = 10) -> None:
        self.pty = pty
        self.data = data
        self.chunk = FRAME_BYTES * rate_hz  # one second of the instrument's frames
        self.flowing = threading.Event()
        self.flowing.set()
        self.done = threading.Event()
        self.offset = 0
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while not self.done.is_set() and self.offset < len(self.data):
            self.flowing.wait()
            if self.done.is_set():
                break
            try:
                self.pty.write(self.data[self.offset : self.offset + self.chunk])
            except OSError:  # unplugged between the check and the write: written again after the replug
                continue
            self.offset += self.chunk
            time.sleep(1.0 / SPEEDUP)  # the instrument's pace, not a synchronization

    def stop(self) -> None:
        self.done.set()
        self.flowing.set()
        self.thread.join(10)


class Watcher:
    """An NDJSON client taking every ANGLE into ``by_seq`` (in a thread)."""

    def __init__(self, address) -> None:
        self.client = Client(address)
        self.client.send('?WATCH={"enable":true};')
        self.client.wait_device("activated")
        self.by_seq: dict[int, dict] = {}
        self.status: dict = {}
        self.changed = threading.Condition()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        try:
            while True:
                obj = self.client.next()
                if obj.get("class") == "ANGLE":
                    with self.changed:
                        self.by_seq[obj["seq"]] = obj
                        self.changed.notify_all()
                elif obj.get("class") == "STATUS":
                    self.status = obj
        except Exception:  # noqa: BLE001 - the connection closes at the end of the test
            pass

    def angle(self, seq: int) -> dict:
        with self.changed:
            assert self.changed.wait_for(lambda: seq in self.by_seq, timeout=WAIT_MS / 1000), seq
            return self.by_seq[seq]


SHOWN = """() => {
  const t = (id) => document.getElementById(id).textContent;
  const temps = {};
  document.querySelectorAll("#temps [data-text]").forEach((el) => {
    temps[el.dataset.text.slice(5)] = el.textContent;
  });
  return {seq: document.body.dataset.seq, angle: t("angle-arcsec"), dms: t("angle-dms"), raw: t("angle-raw-arcsec"),
          rate: t("rate"), drift: t("drift"), sigma: t("drift-sigma"), flags: t("flags"), temps};
}"""


#: What the plots hold: the drift estimate's values (how many, how many exactly 0), and the times of the first
#: plotted point and of the first one-minute mean (ms since the epoch).
PLOTTED = """() => {
  const drift = document.getElementById("plot-drift").data;
  const estimate = drift[drift.length - 1].y.filter((v) => v !== null && v !== undefined);
  const first = (id) => +new Date(document.getElementById(id).data[0].x[0]);
  return {drift_values: estimate.length, drift_zeros: estimate.filter((v) => v === 0).length,
          first_point_ms: first("plot-drift"), first_minute_ms: first("plot-rate")};
}"""
OPACITY = "(selector) => getComputedStyle(document.querySelector(selector)).opacity"


def test_the_page_shows_the_streams_numbers_live_plots_and_the_link_banner(tmp_path):
    data = CAPTURE.read_bytes()
    link = tmp_path / "ttyFOG0"
    pty = PtyPair()
    pty.symlink(link)
    daemon = Daemon(tmp_path, str(link), "--http", "127.0.0.1:0")
    instrument = None
    shots = [Path(os.environ["FOG_SCREENSHOT_DIR"])] if os.environ.get("FOG_SCREENSHOT_DIR") else []
    try:
        url = re.search(r"web view on (http://\S+/)", daemon.readiness).group(1)
        watcher = Watcher(daemon.address)
        instrument = Instrument(pty, data)
        problems: list[str] = []
        with sync_playwright() as p:
            browser, page = open_page(p, problems)
            page.goto(url)
            expect(page.locator("#page-state")).to_have_text("live", timeout=WAIT_MS)
            expect(page.locator("body")).to_have_attribute("data-seq", re.compile(r"^\d+$"), timeout=WAIT_MS)

            # The numbers: whatever sample the page shows, they are the NDJSON stream's for its seq.
            seen = set()
            while len(seen) < 3:
                shown = page.evaluate(SHOWN)
                seq = int(shown["seq"])
                if seq in seen:
                    expect(page.locator("body")).not_to_have_attribute("data-seq", str(seq), timeout=WAIT_MS)
                    continue
                seen.add(seq)
                obj = watcher.angle(seq)
                assert shown["angle"] == format_arcsec(obj["angle_arcsec"])
                assert shown["dms"] == format_dms(obj["angle_arcsec"])
                assert shown["raw"] == format_arcsec(obj["angle_raw_arcsec"])
                assert shown["rate"] == f"{obj['rate_dph']:.1f}"
                assert shown["drift"] == f"{obj['drift_dph']:.3f}"
                # no bias captured here: the sample's own sigma, "-" when the model gives none
                assert shown["sigma"] == (f"{obj['drift_sigma_dph']:.4f}" if "drift_sigma_dph" in obj else "-")
                assert shown["flags"] == (", ".join(obj["flags"]) or "none")
                assert shown["temps"] == {k: f"{v:.3f}" for k, v in obj["temps_c"].items()}
                assert set(shown["temps"]) == {"top", "bottom", "housing"}

            # The plots grow as device seconds and minutes close.
            drift = page.locator("#plot-drift")
            points = drift.get_attribute("data-points")
            expect(drift).not_to_have_attribute("data-points", points, timeout=WAIT_MS)
            expect(page.locator("#plot-rate")).not_to_have_attribute("data-points", "0", timeout=WAIT_MS)
            band = any("drift_sigma_dph" in a for a in list(watcher.by_seq.values()))  # the band: 2 more traces
            assert page.locator("#plot-drift .scatterlayer .trace").count() == (3 if band else 1)
            assert page.locator("#plot-temps .scatterlayer .trace").count() == 3
            expect(page.locator("#banners .alarm")).to_have_count(0)
            # The review's finding 15: the page counted among the clients (STATUS web_clients: this one), the
            # uptime as a person reads it, no drift plotted from 0 before the first estimate, and no one-minute
            # mean drawn before the first sample.
            expect(page.locator("#status-web_clients")).to_have_text("1", timeout=WAIT_MS)
            expect(page.locator("#status-uptime_s")).to_have_text(re.compile(r"^(\d+ min )?\d+ s$"))
            plotted = page.evaluate(PLOTTED)
            assert plotted["drift_zeros"] == 0 and plotted["drift_values"] > 0, plotted
            assert plotted["first_minute_ms"] >= plotted["first_point_ms"], plotted
            assert page.locator("body").get_attribute("data-stale") == "0"
            page.screenshot(path=str(tmp_path / "web-view.png"), full_page=True)

            # Unplugged: the banner says so; back: it goes.
            instrument.flowing.clear()
            pty.unplug()
            expect(page.locator("#banners .alarm").first).to_contain_text("LINK DOWN", timeout=WAIT_MS)
            expect(page.locator("#link")).to_have_text("link down")
            # the pill says the figures are stale (not a green "live" beside "link down"), and they are greyed
            expect(page.locator("#page-state")).to_have_text("link down: figures stale", timeout=WAIT_MS)
            expect(page.locator("#page-state")).to_have_class(re.compile(r"\bbad\b"))
            expect(page.locator("body")).to_have_attribute("data-stale", "1")
            assert float(page.evaluate(OPACITY, "section.numbers")) < 1.0
            page.screenshot(path=str(tmp_path / "web-view-link-down.png"), full_page=True)
            pty.close()
            pty = PtyPair()  # the adapter comes back: a new /dev/pts behind the same link
            pty.symlink(link)
            instrument.pty = pty
            instrument.flowing.set()
            expect(page.locator("#link")).to_have_text("link up", timeout=WAIT_MS)
            expect(page.locator("#page-state")).to_have_text("live", timeout=WAIT_MS)
            expect(page.locator("body")).to_have_attribute("data-stale", "0")
            assert float(page.evaluate(OPACITY, "section.numbers")) == 1.0
            expect(page.locator("#banners")).not_to_contain_text("LINK DOWN", timeout=WAIT_MS)
            banners = page.locator("#banners").inner_text()
            missing = re.search(r"SAMPLES MISSING: ([\d,]+) frames", banners)
            if missing:  # bytes the unplug cut off: the page says as many as the daemon's STATUS does
                assert int(missing.group(1).replace(",", "")) == watcher.status["missing_frames"] > 0, banners
            before = int(page.evaluate(SHOWN)["seq"])
            expect(page.locator("body")).not_to_have_attribute("data-seq", str(before), timeout=WAIT_MS)
            received = len(watcher.by_seq)
            metrics = page.request.get(url + "metrics").text()  # the same listener's Prometheus text
            frames = float(re.search(r"^fog_driver_frames_total (\S+)$", metrics, re.M).group(1))
            latencies = float(re.search(r"^fog_driver_publish_latency_seconds_count (\S+)$", metrics, re.M).group(1))
            assert frames >= received > 0 and latencies > 0  # measured with a watcher
            assert re.search(r"^fog_driver_port_up 1\.0$", metrics, re.M)
            for directory in shots:
                directory.mkdir(parents=True, exist_ok=True)
                shutil.copy(tmp_path / "web-view.png", directory / "web-view.png")
            browser.close()
        assert problems == [], problems
        assert daemon.terminate() == 0
    finally:
        if instrument is not None:
            instrument.stop()
        pty.close()
        daemon.kill()


def test_the_page_draws_the_drift_band_and_switches_to_the_since_bias_form(tmp_path):
    """A web listener in this process fed samples with a drift sigma: the page shows sigma(t) and a band of
    1.96 sigma around the drift plot; once STATUS says a bias was captured, the since-bias form, labelled."""
    from fog_driver.daemon.web.server import WebView

    def samples(first: int, n: int) -> list[dict]:
        return [
            sample(i, 3.0 + i / 10, drift_dph=-0.5 + i * 1e-4, drift_sigma_dph=0.03, temps_c={"top": 20.0})
            for i in range(first, first + n)
        ]

    view = WebView("127.0.0.1", 0, update_hz=10.0)
    view.start()
    problems: list[str] = []
    try:
        view.publish({"class": "DEVICE", "state": "activated", "serial": "S1", "format": "fog-v1"})
        view.publish({"class": "STATUS", "port_state": "open", "bias_captured": False, "bias_dph": 0.0})
        view.publish_angles(samples(0, 100))
        host, port = view.address
        with sync_playwright() as p:
            browser, page = open_page(p, problems)
            page.goto(f"http://{host}:{port}/")
            expect(page.locator("#drift-sigma")).to_have_text("0.0300", timeout=WAIT_MS)
            expect(page.locator("#drift-sigma-label")).to_contain_text("1\u03c3 of the 1-min mean")
            # the band (two traces: its edges, filled between) and the estimate
            expect(page.locator("#plot-drift .scatterlayer .trace")).to_have_count(3, timeout=WAIT_MS)
            expect(page.locator("#plot-drift .legend")).to_contain_text("band: \u00b11.96\u03c3 (95 %)")
            view.publish({"class": "STATUS", "port_state": "open", "bias_captured": True, "bias_sigma_dph": 0.04})
            view.publish_angles(samples(100, 100))
            expect(page.locator("#drift-sigma")).to_have_text("0.0500", timeout=WAIT_MS)  # sqrt(0.03^2 + 0.04^2)
            expect(page.locator("#drift-sigma-label")).to_contain_text("1\u03c3 since the bias")
            expect(page.locator("#plot-drift .legend")).to_contain_text("since the bias", timeout=WAIT_MS)
            page.screenshot(path=str(tmp_path / "web-view-sigma.png"), full_page=True)
            browser.close()
    finally:
        view.stop()
    assert problems == [], problems


def test_the_page_waits_for_data_then_plots_one_point_with_axes_around_it(tmp_path):
    """A newcomer saw '-' everywhere beside a green "live" pill before the first sample, a first point plotted on
    an axis of milliseconds, and the temperatures sorted by name in degrees symbol: the page now says it waits,
    puts a minute of time and a small band of values around a lone point, and lists the thermometers as
    ``fog-driver watch`` does (top, bottom, housing; degC)."""
    from fog_driver.daemon.web.server import WebView

    view = WebView("127.0.0.1", 0, update_hz=10.0)
    view.start()
    problems: list[str] = []
    try:
        host, port = view.address
        with sync_playwright() as p:
            browser, page = open_page(p, problems)
            page.goto(f"http://{host}:{port}/")
            expect(page.locator("#page-state")).to_have_text("waiting for data", timeout=WAIT_MS)
            assert "ok" not in page.locator("#page-state").get_attribute("class")
            expect(page.locator("#waiting")).to_be_visible()
            expect(page.locator("#logout")).to_be_hidden()  # no token: nothing to log out of
            housing_first = {"housing": 22.0, "bottom": 21.0, "top": 20.0}
            view.publish_angles([sample(0, 3.0, temps_c=housing_first), sample(1, 4.0, temps_c=housing_first)])
            expect(page.locator("#page-state")).to_have_text("live", timeout=WAIT_MS)
            expect(page.locator("#plot-drift")).to_have_attribute("data-points", "1", timeout=WAIT_MS)
            axes = page.evaluate(
                """() => {
                  const l = document.getElementById("plot-temps")._fullLayout;
                  const d = document.getElementById("plot-drift")._fullLayout;
                  const ms = (r) => new Date(r[1]).getTime() - new Date(r[0]).getTime();
                  return {temps_x_ms: ms(l.xaxis.range), drift_x_ms: ms(d.xaxis.range), drift_y: d.yaxis.range};
                }"""
            )
            assert axes["temps_x_ms"] == 60_000 and axes["drift_x_ms"] == 60_000, axes
            low, high = axes["drift_y"]
            assert low < -0.5 < high and high - low < 1.0, axes
            rows = page.locator("#temps th").all_inner_texts()
            assert rows == ["top temperature", "bottom temperature", "housing temperature"]
            assert page.locator("#temps td").first.inner_text() == "20.000 degC"
            legend = page.locator("#plot-temps .legend .legendtext").all_text_contents()
            assert legend == ["top", "bottom", "housing"]
            expect(page.locator("#plot-temps .gtitle")).to_have_text("temperatures (degC)")
            browser.close()
    finally:
        view.stop()
    assert problems == [], problems


def test_a_browser_logs_in_reads_the_page_and_logs_out(tmp_path):
    """With a token the page needs it on loopback too: the browser is sent to the login form (styled: its CSS
    needs no token), the form's post passes the Origin check, the session cookie opens the page and its
    WebSocket, and "log out" ends the session (the page is the login form again)."""
    from fog_driver.daemon.web.server import WebView

    view = WebView("127.0.0.1", 0, token="s3cret-token", update_hz=10.0)
    view.start()
    problems: list[str] = []
    try:
        view.publish_angles([sample(0, 3.0), sample(1, 4.0)])
        host, port = view.address
        with sync_playwright() as p:
            browser, page = open_page(p, problems)
            page.goto(f"http://{host}:{port}/")
            expect(page).to_have_url(f"http://{host}:{port}/login")
            assert page.evaluate("getComputedStyle(document.body).maxWidth") != "none"  # view.css loaded
            page.fill("input[name=token]", "s3cret-token")
            page.click("button[type=submit]")
            expect(page.locator("#page-state")).to_have_text("live", timeout=WAIT_MS)
            expect(page.locator("#logout")).to_be_visible()
            page.click("#logout button")
            expect(page).to_have_url(f"http://{host}:{port}/login", timeout=WAIT_MS)
            assert page.request.get(f"http://{host}:{port}/api/view").status == 401  # the session is over
            browser.close()
    finally:
        view.stop()
    assert [p for p in problems if "401" not in p] == [], problems
