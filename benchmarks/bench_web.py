"""The web view's cost: the daemon at 2 kHz with the page open in two browsers and Prometheus scraping every second.

    python -m benchmarks.bench_web [--quick] [--seconds S] [--browsers N] [--scrape-every-s S] [--tick-ms MS]

Target: with the web view open in two browsers and a scrape of ``/metrics`` every second, the daemon at
2 kHz keeps the p99 latency from frame written to NDJSON line received under 5 ms and its CPU under 25 % of
one core.  (``--browsers 0`` leaves the Chromium run out.)

Method
------
Three live runs as ``benchmarks/bench_daemon.py``'s (its helpers: frames from the simulator paced into a pty
every ``--tick-ms``, two NDJSON clients in processes of their own watching every sample, latency from the
write to the line's arrival, the daemon's CPU from /proc after ``--warmup-s``), in one invocation:

1. the baseline: ``fog-driver run`` without the web view;
2. ``--http 127.0.0.1:0`` with ``--browsers`` (2) pages as WebSocket readers (aiohttp, a process each:
   what the daemon does for a browser on another desk, without a browser's CPU on this machine) and a
   scraper thread here fetching ``/metrics`` every ``--scrape-every-s`` (1 s);
3. the same with real headless Chromium instead (Playwright, one browser process tree each, all in a process
   of their own at nice 19, as an operator's browser on the instrument PC would be best started; each
   page ready once connected to the stream, then each must show a sample).  Their CPU (every process of the
   tree, from /proc) is reported; on a 2-core machine it competes with the daemon and its clients for the
   cores.

Reported: per NDJSON client the samples lost and p50/p99/max latency, the daemon's CPU and its ratio to the
baseline's, the pages' updates received, the scrapes done and their time.  Needs the ``web`` extra,
Playwright and Chromium (``apt-get install chromium``; ``FOG_CHROMIUM`` for another path).  No assertion:
figures are printed next to their targets; exits non-zero only when a sample was lost or a page or scrape
failed.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import shutil
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path

import numpy as np

from benchmarks.bench_daemon import (
    Table,
    add_pacing_options,
    live_run,
    ok,
    start_readers,
    stat_cpu_s,
    stat_fields,
)

ROOT = Path(__file__).resolve().parents[1]

# Pages' WebSockets without a browser (a process of its own): argv url n [local_address|-] [token].  Opens n
# WebSockets one after another (from local_address when given; with the token as "Authorization: Bearer"), prints
# "ready" once each has its snapshot, then records each update's arrival (time.monotonic()) until stdin closes, and
# prints one JSON line: per socket the arrival times and how the daemon ended it (null: it did not).
WS_READER = r"""
import asyncio, json, sys, time
import aiohttp

async def main(url, n, address, token):
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    connector = aiohttp.TCPConnector(limit=0, local_addr=(address, 0) if address else None)
    async with aiohttp.ClientSession(connector=connector) as session:
        sockets = []
        for _ in range(n):  # one at a time: a connection holds an unauthorized slot until its request is read
            ws = await session.ws_connect(url, headers=headers)
            await ws.receive()  # the snapshot
            sockets.append(ws)
        print("ready", flush=True)
        times, ends = [[] for _ in sockets], [None] * n

        async def read(k):
            while True:
                message = await sockets[k].receive()
                if message.type in (aiohttp.WSMsgType.CLOSE, aiohttp.WSMsgType.CLOSED, aiohttp.WSMsgType.ERROR):
                    ends[k] = f"{message.type.name} {sockets[k].close_code}"
                    return
                times[k].append(time.monotonic())

        readers = [asyncio.create_task(read(k)) for k in range(n)]
        await asyncio.get_running_loop().run_in_executor(None, sys.stdin.read)
        for task in readers:
            task.cancel()
        for ws in sockets:
            await ws.close()
    print(json.dumps({"times": times, "ends": ends}), flush=True)

address = sys.argv[3] if len(sys.argv) > 3 and sys.argv[3] != "-" else None
asyncio.run(main(sys.argv[1], int(sys.argv[2]), address, sys.argv[4] if len(sys.argv) > 4 else None))
"""

# The browsers (a process of their own): argv chromium url n.  Prints "ready" once every page is connected
# to the stream, then waits for stdin to close and prints each page's updates received and any page error as JSON.
BROWSERS = r"""
import json, re, sys
from playwright.sync_api import expect, sync_playwright
chromium, url, n = sys.argv[1], sys.argv[2], int(sys.argv[3])
errors = []
with sync_playwright() as p:
    browsers = [p.chromium.launch(executable_path=chromium, args=["--no-sandbox"]) for _ in range(n)]
    pages = []
    for b in browsers:
        page = b.new_page(viewport={"width": 1280, "height": 860})
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(url)
        # connected: "waiting for data" until the frames start (they start once every page is ready)
        expect(page.locator("#page-state")).to_have_text(re.compile("waiting for data|live"), timeout=30000)
        pages.append(page)
    print("ready", flush=True)
    for page in pages:
        expect(page.locator("body")).to_have_attribute("data-seq", re.compile(r"^\d+$"), timeout=30000)
    sys.stdin.read()
    updates = [int(page.locator("body").get_attribute("data-updates") or 0) for page in pages]
    points = [int(page.locator("#plot-drift").get_attribute("data-points") or 0) for page in pages]
    for b in browsers:
        b.close()
print(json.dumps({"updates": updates, "points": points, "errors": errors}), flush=True)
"""


#: The browsers' niceness: an operator's browser runs on another desk, not on the instrument PC's two cores.
NICE = 19


def tree_cpu_s(root: int) -> float:
    """utime + stime (s) of ``root`` and every process descended from it, from /proc."""
    parents: dict[int, int] = {}
    times: dict[int, float] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            fields = stat_fields(f"/proc/{entry}/stat")
        except OSError:  # the process ended meanwhile
            continue
        parents[int(entry)] = int(fields[1])
        times[int(entry)] = stat_cpu_s(fields)
    total, todo = 0.0, [root]
    while todo:
        pid = todo.pop()
        total += times.get(pid, 0.0)
        todo.extend(child for child, parent in parents.items() if parent == pid)
    return total


def chromium() -> str:
    path = os.environ.get("FOG_CHROMIUM") or shutil.which("chromium") or shutil.which("chromium-browser")
    if not path:
        sys.exit("bench_web needs Chromium: apt-get install chromium (or FOG_CHROMIUM=/path/to/chrome)")
    return path


def web_url(daemon) -> str:
    """The web view's address (``http://HOST:PORT/``) from the daemon's readiness line."""
    return re.search(r"web view on (http://\S+/)", daemon.readiness).group(1)


class Scraper(threading.Thread):
    """GET /metrics every ``every_s`` (host time), timing each (with ``token``: as ``Authorization: Bearer``)."""

    def __init__(self, url: str, every_s: float, token: str | None = None) -> None:
        super().__init__(daemon=True)
        self.url, self.every_s = url, every_s
        self.headers = {"Authorization": f"Bearer {token}"} if token else {}
        self.started_s: list[float] = []  #: each successful scrape's start (monotonic s)
        self.times_ms: list[float] = []
        self.failures = 0
        self.last_error = ""
        self.bytes = 0
        self.stopping = threading.Event()

    def run(self) -> None:
        next_s = time.monotonic()
        while not self.stopping.wait(max(0.0, next_s - time.monotonic())):
            next_s += self.every_s
            started = time.monotonic()
            try:
                request = urllib.request.Request(self.url, headers=self.headers)
                with urllib.request.urlopen(request, timeout=10) as response:
                    body = response.read()
                if b"fog_driver_frames_total" not in body:
                    raise ValueError("no fog_driver_frames_total")
                self.bytes = len(body)
                self.times_ms.append((time.monotonic() - started) * 1e3)
                self.started_s.append(started)
            except (OSError, ValueError) as exc:
                self.failures += 1
                self.last_error = repr(exc)


def web_companions(n_browsers: int, scrape_every_s: float, mode: str):
    def start(daemon) -> callable:
        url = web_url(daemon)
        browsers = None
        readers = []
        if mode == "ws":  # the pages as WebSocket readers: what the daemon does for a browser on another desk
            host_port = url.split("//", 1)[1].rstrip("/")
            readers = start_readers(WS_READER, [[f"ws://{host_port}/ws", "1"]] * n_browsers, stdin=subprocess.PIPE)
        elif n_browsers:
            browsers = subprocess.Popen(
                [sys.executable, "-c", BROWSERS, chromium(), url, str(n_browsers)],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                text=True,
                cwd=ROOT,
                preexec_fn=lambda: os.nice(NICE),
            )
            if browsers.stdout.readline().strip() != "ready":
                browsers.kill()
                sys.exit("the browsers did not open the page")
        scraper = Scraper(url + "metrics", scrape_every_s)
        if scrape_every_s > 0:
            scraper.start()
        started = (time.monotonic(), tree_cpu_s(browsers.pid) if browsers is not None else 0.0)

        def stop() -> dict:
            if scraper.is_alive():
                scraper.stopping.set()
                scraper.join(15)
            pages = {"updates": [], "points": [], "errors": []}
            for reader in readers:
                out, _ = reader.communicate("", timeout=30)
                pages["updates"].append(len(json.loads(out.splitlines()[-1])["times"][0]) if out.strip() else 0)
            browsers_cpu = float("nan")
            if browsers is not None:
                browsers_cpu = 100 * (tree_cpu_s(browsers.pid) - started[1]) / (time.monotonic() - started[0])
                out, _ = browsers.communicate("", timeout=60)
                pages = json.loads(out.strip().splitlines()[-1]) if out.strip() else {**pages, "errors": ["no output"]}
            return {
                "pages": pages,
                "scrapes_ms": scraper.times_ms,
                "scrape_failures": scraper.failures,
                "scrape_error": scraper.last_error,
                "browsers_cpu_pct": browsers_cpu,
                "scrape_bytes": scraper.bytes,
            }

        return stop

    return start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="a short run: 5 s each")
    parser.add_argument("--rate-hz", type=int, default=2000, help="instrument rate (default 2000)")
    parser.add_argument("--seconds", type=float, default=20.0, help="length of each run (default 20)")
    parser.add_argument("--browsers", type=int, default=2, help="browsers with the page open (default 2; 0: none)")
    parser.add_argument("--scrape-every-s", type=float, default=1.0, help="/metrics scrape period (default 1; 0: none)")
    add_pacing_options(parser, warmup_s=2.0)
    args = parser.parse_args()
    if args.quick:
        args.seconds = 5.0
    if args.browsers:
        chromium()
    print(
        f"web view: {os.cpu_count()} cores, Python {platform.python_version()}, {args.rate_hz} Hz for "
        f"{args.seconds:g} s per run, two NDJSON clients, writer tick {args.tick_ms:g} ms, CPU after a "
        f"{args.warmup_s:g} s warm-up{' (--quick)' if args.quick else ''}",
        flush=True,
    )
    wall0 = time.monotonic()
    tick_s = args.tick_ms / 1e3
    runs = [("no web view", live_run("baseline", args.rate_hz, args.seconds, tick_s, args.warmup_s, 2))]
    for mode, title in (
        ("ws", f"{args.browsers} pages elsewhere (WebSocket readers)"),
        ("chromium", f"{args.browsers} Chromium here, nice {NICE}"),
    ):
        if mode == "chromium" and not args.browsers:
            continue
        r = live_run(
            "web",
            args.rate_hz,
            args.seconds,
            tick_s,
            args.warmup_s,
            2,
            daemon_args=("--http", "127.0.0.1:0"),
            companions=web_companions(args.browsers, args.scrape_every_s, mode),
        )
        runs.append((f"{title}, /metrics every {args.scrape_every_s:g} s", r))
    table = Table()
    failed = False
    base_cpu = runs[0][1].cpu_pct
    for title, r in runs:
        for i, c in enumerate(r.clients, 1):
            failed |= c.lost > 0
            table.add(
                title if i == 1 else "",
                f"NDJSON client {i}: lost / p50 / p99 / max latency, ms",
                f"{c.lost} / {c.pct(50):.2f} / {c.pct(99):.2f} / "
                f"{c.lat_ms.max() if c.lat_ms.size else float('nan'):.2f}",
                "0 lost, p99 <= 5",
                ok(c.lost == 0 and c.pct(99) <= 5.0),
            )
        table.add(
            "",
            "daemon CPU, % of one core (x the run without)",
            f"{r.cpu_pct:.1f} ({r.cpu_pct / base_cpu:.2f}x)",
            "<= 25",
            ok(r.cpu_pct <= 25.0),
        )
        seen = r.companions
        if not seen:
            continue
        pages = seen["pages"]
        scrapes = np.array(seen["scrapes_ms"])
        failed |= bool(pages["errors"]) or seen["scrape_failures"] > 0
        table.add(
            "",
            "page updates received, per page",
            " / ".join(map(str, pages["updates"])),
            f"~{2 * args.seconds:g} each (2 a second)",
        )
        if pages.get("points"):
            table.add("", "drift plot points, per page", " / ".join(map(str, pages["points"])))
        if seen["browsers_cpu_pct"] == seen["browsers_cpu_pct"]:
            table.add("", "the browsers' CPU (all their processes), % of one core", f"{seen['browsers_cpu_pct']:.1f}")
        table.add(
            "",
            "scrapes ok / failed; p50 / max time, ms",
            f"{scrapes.size} / {seen['scrape_failures']}; "
            f"{np.percentile(scrapes, 50) if scrapes.size else float('nan'):.1f} / "
            f"{scrapes.max() if scrapes.size else float('nan'):.1f}",
            "0 failed",
            ok(seen["scrape_failures"] == 0),
        )
        if seen["scrape_error"]:
            table.add("", "last scrape error", seen["scrape_error"][:60])
        if pages["errors"]:
            table.add("", "page errors", "; ".join(pages["errors"])[:60])
    table.print()
    print(
        f"one scrape: {runs[-1][1].companions.get('scrape_bytes', 0):,} bytes; total wall time "
        f"{time.monotonic() - wall0:.0f} s"
    )
    if failed:
        sys.exit("a sample was lost, a page failed or a scrape failed")


if __name__ == "__main__":
    from benchmarks._harness import run_main  # --update-readme: the documentation's block for this command

    run_main(main)
