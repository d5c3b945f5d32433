"""The token-protected daemon under load: 50 pages, 8 hostile NDJSON clients, a watcher timing every sample.

    python -m benchmarks.bench_web_load [--seconds S] [--warmup-s S] [--settle-s S] [--rate-hz HZ]
                                        [--ws-clients N] [--ws-addresses N] [--hostile N] [--tick-ms MS]

Targets: under the load below, every sample reaches a watching NDJSON client; its p99 lateness is at most twice
the baseline's p99 plus 10 ms; ``/metrics`` answers in 50 ms (p50); the daemon's RSS stays flat (the mean of its
last 10 s within 5 MB of its first 10 s).

Method
------
One daemon, started as ``benchmarks/bench_daemon.py`` starts it (``Daemon``: ``fog-driver run`` on the slave of a
``PtyPair``) with ``--http 127.0.0.1:0`` and a config holding a random ``token``, as a station reached from
elsewhere would have: every client below that is meant to get in carries it (the watcher ``?AUTH``, the pages and
the scraper ``Authorization: Bearer``).  A simulated instrument at ``--rate-hz`` (1 kHz): the frames of
``make_frames`` paced into the pty master in real time by ``pace`` (every ``--tick-ms``, the frames due), in a
thread of this process, for ``--warmup-s`` (10) + ``--seconds`` (30) + ``--settle-s`` (5) + ``--seconds``.

* The watcher (``bench_daemon``'s client script, a process of its own, from 127.0.0.1) watches every sample and
  records for each ANGLE line its ``seq``, its device time ``t_s`` and its arrival (``time.monotonic()`` right
  after the ``recv`` that completed it); its seq, unwrapped across the u16 wrap, says which frame it is.  A
  sample's lateness is its arrival minus its device time, both taken relative to the first sample received, less
  the least of that over the run: the two clocks have no common zero, and the first sample is no good one (the
  first through the daemon's cold paths, it came 5 to 13 ms later than the least-late in trial runs here, which
  made every later one look early and the baseline's p99 negative); the least-late sample, the pty, the daemon
  and the reader at their quickest, is.  The first sample's own lateness is printed.  The writer's ticks are in
  it: a frame waits up to a tick for its write, as it would for a USB serial adapter's lump.
* The scraper (``bench_web.Scraper``, a thread here) GETs ``/metrics`` once a second, timing each.
* The load, from the start: ``--ws-clients`` (50) WebSocket clients reading the page's stream (``bench_web``'s
  reader script: aiohttp, a snapshot then an update every 0.5 s), one process per loopback address 127.0.0.1 ..
  127.0.0.``--ws-addresses`` (4), each socket bound to its process's address (Linux routes all of 127/8 to lo);
  and ``--hostile`` (8) hostile NDJSON clients (``tests/hostile.py``, a process of their own, each from its own
  address 127.0.0.10 ...: floods of empty lines, binary junk, oversized lines, broken JSON, token guesses, absurd
  ``rate_hz``, a client that never reads, an idle one; each reconnects when thrown out).  The one that never
  reads has the token: only an authorized client gets the stream, so only it leaves a backlog behind.
* Phases, by the writer's schedule: the warm-up (left out), the ``--seconds`` under load; then the pages and the
  hostile clients are stopped and ``--settle-s`` (5) left for them to go; then the same ``--seconds`` with the
  watcher and the scraper alone: the baseline, in the same run and the same daemon.
* The daemon's CPU (utime + stime, ``/proc/PID/stat``) over each measured phase, and the machine's (every core,
  ``/proc/stat``: other work on the machine shows there); its VmRSS from ``/proc/PID/status`` once a second.

The web listener's connection limits stay as the daemon has them (``fog_driver/daemon/limits.py``: 64
connections, 24 from one address, of which clients without the token hold at most half; each page carries the
token from its first request, and a process opens its pages one at a time): the 50 pages over 4 addresses need 13
from one address (14 from 127.0.0.1 with the scraper's) and 51 in all, within them.  Other counts are checked
before the run: beyond the limits it stops with a message (the limits are constants, not configuration).

Printed: the setup, then per phase the watcher's samples and lateness p50 / p99 / max (with where the max falls
and how late the writer wrote that frame), the scrapes and their p50 / max time, the daemon's CPU and the
machine's, the daemon's mean VmRSS over the first and last 10 s; under load the pages' updates received (in all,
and the fewest and most per page), their worst gap between two updates and any page the daemon closed; the
daemon's CPU per thread, the first sample's lateness, the hostile clients' connections and refusals, the watcher's
last STATUS (frames, missing, clients dropped), the scrapes that failed, how long the load took to go, the
writer's worst tick; then a PASS or MISS line per target.
No assertion: exits non-zero only when a sample never reached the watcher (or the run could not be set up).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import secrets
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from benchmarks.bench_daemon import (
    CLIENT,
    CLK_TCK,
    GUARD_S,
    CpuMark,
    Daemon,
    Frames,
    Table,
    add_pacing_options,
    frame_index,
    join_readers,
    make_frames,
    pace,
    rss_mb,
    start_hostile,
    start_readers,
)
from benchmarks.bench_web import WS_READER, Scraper, web_url
from fog_driver.daemon.limits import WEB_MAX_CONNECTIONS, WEB_MAX_CONNECTIONS_PER_PEER
from fog_driver.transport import PtyPair

#: ``/metrics`` is scraped this often (s), as Prometheus would.
SCRAPE_EVERY_S = 1.0
#: The RSS target: the mean over the last ``RSS_SPAN_S`` of the phase within ``RSS_FLAT_MB`` of the first's.
RSS_SPAN_S = 10.0
RSS_FLAT_MB = 5.0
#: The lateness target: p99 under load <= ``LATENESS_FACTOR`` x the baseline's p99 + ``LATENESS_MARGIN_MS``.
LATENESS_FACTOR = 2.0
LATENESS_MARGIN_MS = 10.0
#: The ``/metrics`` target: p50 under load at most this (ms).
SCRAPE_P50_MS = 50.0


@dataclass(frozen=True)
class Phase:
    """A measured stretch, in seconds of the writer's schedule (from the first frame's write)."""

    name: str
    start_s: float
    end_s: float


def machine_cpu_s() -> tuple[float, float]:
    """(busy, all) CPU seconds of every core since boot, from ``/proc/stat``'s first line (busy: neither idle
    nor waiting for I/O; guest time is in user time already)."""
    with open("/proc/stat") as f:
        ticks = [int(x) for x in f.readline().split()[1:9]]  # user nice system idle iowait irq softirq steal
    return (sum(ticks) - ticks[3] - ticks[4]) / CLK_TCK, sum(ticks) / CLK_TCK


@dataclass
class Mark:
    daemon: CpuMark
    machine: tuple[float, float]

    @classmethod
    def take(cls, pid: int) -> Mark:
        return cls(CpuMark.take(pid), machine_cpu_s())

    def since(self, earlier: Mark) -> tuple[float, list[tuple[str, float]], float]:
        """The daemon's CPU (% of one core, and per thread) and the machine's (% of all its cores) since."""
        daemon_pct, threads = self.daemon.percent_since(earlier.daemon)
        busy, total = (now - then for now, then in zip(self.machine, earlier.machine))
        return daemon_pct, threads, 100.0 * busy / max(total, 1e-9)


@dataclass
class Watched:
    """What the watcher received: per ANGLE line its frame's index ``k`` (seq unwrapped) and its lateness."""

    k: np.ndarray
    lateness_ms: np.ndarray  #: (arrival - device time) - the least of it over the run: >= 0
    first_ms: float  #: the first sample's own lateness on that scale (the review's zero)
    status: dict | None  #: the last STATUS it had


def watched(npz_path: Path, frames: Frames) -> Watched:
    """The watcher's record: lateness_i = (a_i - a_0) - (d_i - d_0) - min_j [(a_j - a_0) - (d_j - d_0)], with a
    the arrival (monotonic s) and d the device time ``t_s`` of sample i (0: the first received); the minimum,
    the least-late sample, is the run's fixed offset of the pty, the daemon and the reader at their quickest."""
    empty = Watched(np.array([], dtype=np.int64), np.array([]), float("nan"), None)
    if not npz_path.exists():  # the watcher died: nothing received
        return empty
    with np.load(npz_path) as z:
        seq, arrival_s, device_s = z["seq"], z["t"], z["device_t"]
        empty.status = json.loads(str(z["status"]))
    if seq.size == 0:
        return empty
    k, _ = frame_index(seq, frames)
    from_first_ms = 1e3 * ((arrival_s - arrival_s[0]) - (device_s - device_s[0]))
    floor_ms = float(from_first_ms.min())
    return Watched(k, from_first_ms - floor_ms, -floor_ms, empty.status)


def page_figures(times: list[list[float]], t0: float, phase: Phase) -> tuple[np.ndarray, float]:
    """Per page, the updates that arrived within ``phase``; and the longest wait for one (ms) over every page,
    the phase's edges included (a page that stopped receiving shows its silence up to the phase's end)."""
    start, end = t0 + phase.start_s, t0 + phase.end_s
    counts, worst = [], 0.0
    for arrivals in times:
        inside = [t for t in arrivals if start <= t < end]
        counts.append(len(inside))
        worst = max(worst, float(np.diff([start, *inside, end]).max()))
    return np.array(counts), 1e3 * worst


def in_phase(times_s: np.ndarray, t0: float, phase: Phase) -> np.ndarray:
    return (times_s >= t0 + phase.start_s) & (times_s < t0 + phase.end_s)


def pct(values: np.ndarray, q: float) -> float:
    return float(np.percentile(values, q)) if values.size else float("nan")


def mean_rss(samples: np.ndarray, start_s: float, end_s: float) -> float:
    """The mean VmRSS (MB) of the once-a-second samples (t from the first write, MB) within [start_s, end_s)."""
    inside = samples[(samples[:, 0] >= start_s) & (samples[:, 0] < end_s), 1]
    return float(inside.mean()) if inside.size else float("nan")


class Collector(threading.Thread):
    """Closes a load process's stdin (which stops it) and keeps what it prints."""

    def __init__(self, proc: subprocess.Popen) -> None:
        super().__init__(daemon=True)
        self.proc = proc
        self.out = ""
        self.start()

    def run(self) -> None:
        try:
            self.out, _ = self.proc.communicate("", timeout=60)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.out, _ = self.proc.communicate()

    def last_json(self) -> dict:
        lines = self.out.strip().splitlines()
        return json.loads(lines[-1]) if lines else {}


def check_web_limits(ws_clients: int, ws_addresses: int) -> tuple[list[int], str]:
    """The pages per address, and a line saying they (and the scraper, from 127.0.0.1) fit the web listener's
    default limits; exits when they would not (the limits are constants, not configuration)."""
    per_address = [ws_clients // ws_addresses + (i < ws_clients % ws_addresses) for i in range(ws_addresses)]
    busiest = per_address[0] + 1  # 127.0.0.1 has the scraper's connection too
    if busiest > WEB_MAX_CONNECTIONS_PER_PEER or ws_clients + 1 > WEB_MAX_CONNECTIONS:
        sys.exit(
            f"{ws_clients} pages over {ws_addresses} addresses need {busiest} connections from 127.0.0.1 and "
            f"{ws_clients + 1} in all: beyond the web listener's limits ({WEB_MAX_CONNECTIONS} connections, "
            f"{WEB_MAX_CONNECTIONS_PER_PEER} per address): use more --ws-addresses"
        )
    return per_address, (
        f"web listener limits as by default ({WEB_MAX_CONNECTIONS} connections, {WEB_MAX_CONNECTIONS_PER_PEER} per "
        f"address): the pages and the scraper need {busiest} from 127.0.0.1 at most and {ws_clients + 1} in all"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rate-hz", type=int, default=1000, help="instrument rate (default 1000)")
    parser.add_argument("--seconds", type=float, default=30.0, help="each measured phase (default 30)")
    parser.add_argument(
        "--settle-s", type=float, default=5.0, help="between the phases, for the load to go (default 5)"
    )
    parser.add_argument("--ws-clients", type=int, default=50, help="WebSocket clients reading the page (default 50)")
    parser.add_argument("--ws-addresses", type=int, default=4, help="loopback addresses they come from (default 4)")
    parser.add_argument("--hostile", type=int, default=8, help="hostile NDJSON clients (default 8)")
    add_pacing_options(parser, warmup_s=10.0)
    args = parser.parse_args()
    if not (1 <= args.ws_addresses <= 9 and args.ws_clients >= 1 and args.seconds > 0):
        sys.exit("--ws-addresses must be 1..9 (127.0.0.1 .. 127.0.0.9), --ws-clients and --seconds positive")
    per_address, limits_line = check_web_limits(args.ws_clients, args.ws_addresses)
    rate, tick_s = args.rate_hz, args.tick_ms / 1e3
    load = Phase("under load", args.warmup_s, args.warmup_s + args.seconds)
    base = Phase("baseline", load.end_s + args.settle_s, load.end_s + args.settle_s + args.seconds)
    print(
        f"web load: {os.cpu_count()} cores, Python {platform.python_version()}, {rate} Hz, writer tick "
        f"{args.tick_ms:g} ms; {args.warmup_s:g} s warm-up, {args.seconds:g} s under load, {args.settle_s:g} s "
        f"settling, {args.seconds:g} s baseline",
        flush=True,
    )
    print(f"daemon: --http 127.0.0.1:0, a token; {limits_line}", flush=True)
    frames = make_frames(rate, base.end_s)
    token = secrets.token_hex(16)
    wall0 = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="bench-web-load-") as tmp, PtyPair() as pty:
        tmp_path = Path(tmp)
        config = tmp_path / "fog.yaml"
        config.write_text(f"token: {token}\n")
        daemon = Daemon(tmp_path, pty.slave_path, "--config", str(config), "--http", "127.0.0.1:0")
        watcher, pages, attackers, collectors = [], [], None, []
        try:
            host, port = daemon.address
            out = tmp_path / "watcher.npz"
            watcher = start_readers(CLIENT, [[host, str(port), str(frames.n), str(out), "-", token]])
            url = web_url(daemon)
            scraper = Scraper(url + "metrics", SCRAPE_EVERY_S, token)
            scraper.start()
            ws_url = "ws://" + url.split("//", 1)[1] + "ws"
            pages = start_readers(
                WS_READER,
                [[ws_url, str(n), f"127.0.0.{i + 1}", token] for i, n in enumerate(per_address)],
                stdin=subprocess.PIPE,
            )
            attackers = start_hostile(daemon.address, args.hostile, token) if args.hostile else None
            print(
                f"... the watcher, the scraper, {args.ws_clients} pages from 127.0.0.1..{args.ws_addresses} "
                f"({' / '.join(map(str, per_address))}) and {args.hostile} hostile clients are in; "
                f"{frames.n:,} frames to write",
                flush=True,
            )

            pacing = []
            writer = threading.Thread(
                target=lambda: pacing.append(pace(pty, frames, tick_s, 0.0, None)), name="writer", daemon=True
            )
            t0 = time.monotonic()
            writer.start()
            marks: dict[str, Mark] = {}
            boundaries = [
                (load.start_s, "load0"),
                (load.end_s, "load1"),
                (base.start_s, "base0"),
                (base.end_s, "base1"),
            ]
            rss: list[tuple[float, float]] = []
            next_rss_s, load_gone_s = 0.0, float("nan")
            while boundaries or writer.is_alive():
                now_s = time.monotonic() - t0
                while boundaries and now_s >= boundaries[0][0]:
                    name = boundaries.pop(0)[1]
                    marks[name] = Mark.take(daemon.pid)
                    if name == "load1":  # the load goes: the baseline is the watcher and the scraper alone
                        collectors = [Collector(p) for p in [*pages, *([attackers] if attackers else [])]]
                if collectors and math.isnan(load_gone_s) and not any(c.is_alive() for c in collectors):
                    load_gone_s = now_s - load.end_s
                if now_s >= next_rss_s:
                    rss.append((now_s, rss_mb(daemon.pid)[0]))
                    next_rss_s += 1.0
                wake_s = min(next_rss_s, boundaries[0][0] if boundaries else next_rss_s)
                time.sleep(min(0.1, max(0.0, wake_s - (time.monotonic() - t0))))
            writer.join()
            join_readers(watcher, timeout_s=10.0)
            scraper.stopping.set()
            scraper.join(15)
            for c in collectors:
                c.join(GUARD_S)
        finally:
            for proc in [*watcher, *pages, *([attackers] if attackers else [])]:
                if proc.poll() is None:
                    proc.kill()
            exit_code = daemon.stop()
        seen = watched(out, frames)

    # -- figures ---------------------------------------------------------------------------------------------
    table = Table()
    k = seen.k
    received = np.unique(k[(k >= 0) & (k < frames.n)]).size
    lost = frames.n - received
    repeats = int(k.size - received)
    scrape_t, scrape_ms = np.array(scraper.started_s), np.array(scraper.times_ms)
    rss_arr = np.array(rss)
    span_s = min(RSS_SPAN_S, args.seconds / 2)
    page_results = [c.last_json() for c in collectors[: len(pages)]]
    page_times = [times for r in page_results for times in r.get("times", [])]
    page_ends = [end for r in page_results for end in r.get("ends", []) if end is not None]
    results = {}
    for phase, (m0, m1) in ((load, ("load0", "load1")), (base, ("base0", "base1"))):
        measured = (k >= phase.start_s * rate) & (k < phase.end_s * rate)
        expected = int(math.ceil(phase.end_s * rate) - math.ceil(phase.start_s * rate))
        lat = seen.lateness_ms[measured]
        scrapes = scrape_ms[in_phase(scrape_t, t0, phase)]
        cpu_pct, threads, machine_pct = marks[m1].since(marks[m0])
        rss_first = mean_rss(rss_arr, phase.start_s, phase.start_s + span_s)
        rss_last = mean_rss(rss_arr, phase.end_s - span_s, phase.end_s)
        results[phase.name] = (lat, scrapes, rss_first, rss_last, threads)
        table.add(
            phase.name, "watcher: samples received of written", f"{np.unique(k[measured]).size:,} of {expected:,}"
        )
        table.add(
            "",
            "watcher lateness p50 / p99 / max, ms",
            f"{pct(lat, 50):.2f} / {pct(lat, 99):.2f} / {lat.max():.2f}" if lat.size else "none",
        )
        if lat.size and pacing:
            worst = int(k[measured][lat.argmax()])
            written_late_ms = 1e3 * (pacing[0].written_t[worst] - pacing[0].written_t[0] - worst / rate)
            table.add("", "  the max: at s, written late by ms", f"{worst / rate:.1f}, {written_late_ms:.1f}")
        table.add(
            "",
            "/metrics scrapes; p50 / max time, ms",
            f"{scrapes.size}; {pct(scrapes, 50):.1f} / {scrapes.max() if scrapes.size else float('nan'):.1f}",
        )
        table.add("", "daemon CPU, % of one core", f"{cpu_pct:.1f}")
        table.add("", f"machine CPU, % of its {os.cpu_count()} cores (everything)", f"{machine_pct:.0f}")
        table.add("", f"daemon VmRSS, mean of first -> last {span_s:g} s, MB", f"{rss_first:.1f} -> {rss_last:.1f}")
        if phase is load:
            counts, worst_gap_ms = page_figures(page_times, t0, load)
            table.add(
                "",
                "pages: updates received (fewest / most per page)",
                f"{counts.sum():,} ({counts.min()} / {counts.max()})" if counts.size else "none",
                f"~{2 * args.seconds * len(page_times):g} ({2 * args.seconds:g} each)",
            )
            table.add("", "pages: worst gap between two updates, ms", f"{worst_gap_ms:.0f}", "(~500: 2 a second)")
            table.add("", "pages closed by the daemon", f"{len(page_ends)} of {len(page_times)}")
    table.print()
    print()
    for name, (_, _, _, _, threads) in results.items():
        print(f"{name}: daemon CPU % by thread: " + ", ".join(f"{n} {p:.1f}" for n, p in threads if p >= 0.05))
    print(
        f"lateness counted from the least-late sample; the first sample's was {seen.first_ms:.2f} ms (counted from "
        f"the first, every lateness would be that much less)"
    )
    if attackers is not None:
        kinds = collectors[-1].last_json()
        print(
            "hostile clients, connections / refused: "
            + ", ".join(f"{kind} {v['connections']}/{v['refused']}" for kind, v in kinds.items())
        )
    s = seen.status or {}
    print(
        f"last STATUS: frames {s.get('frames')}, missing {s.get('missing_frames')}, crc {s.get('crc_errors')}, "
        f"NDJSON clients dropped {s.get('dropped_clients')}, pages dropped {s.get('web_dropped_clients')}; "
        f"scrape failures {scraper.failures}{' (' + scraper.last_error[:80] + ')' if scraper.last_error else ''}; "
        f"the load gone {load_gone_s:.1f} s after its phase; writer worst tick "
        f"{pacing[0].max_late_ms if pacing else float('nan'):.1f} ms late; page ends: "
        f"{', '.join(sorted(set(page_ends))) or 'none'}; daemon exit {exit_code}"
    )
    print()

    # -- targets ---------------------------------------------------------------------------------------------
    load_lat, load_scrapes, rss_first, rss_last, _ = results[load.name]
    base_p99 = pct(results[base.name][0], 99)
    limit_ms = LATENESS_FACTOR * base_p99 + LATENESS_MARGIN_MS
    verdict = {True: "PASS", False: "MISS"}
    print(
        f"{verdict[lost == 0]}  every sample reached the watcher: {received:,} of {frames.n:,} "
        f"({lost} lost, {repeats} repeated; seq unwrapped)"
    )
    print(
        f"{verdict[pct(load_lat, 99) <= limit_ms]}  p99 lateness under load {pct(load_lat, 99):.2f} ms <= "
        f"{LATENESS_FACTOR:g} x the baseline's {base_p99:.2f} + {LATENESS_MARGIN_MS:g} = {limit_ms:.2f} ms"
    )
    print(
        f"{verdict[pct(load_scrapes, 50) <= SCRAPE_P50_MS]}  /metrics p50 under load {pct(load_scrapes, 50):.1f} ms "
        f"<= {SCRAPE_P50_MS:g} ms"
    )
    print(
        f"{verdict[abs(rss_last - rss_first) <= RSS_FLAT_MB]}  RSS flat under load: mean VmRSS {rss_first:.1f} MB "
        f"(first {span_s:g} s) -> {rss_last:.1f} MB (last {span_s:g} s), within {RSS_FLAT_MB:g} MB"
    )
    print(f"total wall time {time.monotonic() - wall0:.0f} s")
    if lost:
        sys.exit(f"{lost} samples never reached the watcher")


if __name__ == "__main__":
    from benchmarks._harness import run_main  # --update-readme: the block in docs/explanation/performance.md

    run_main(main)
