"""A serial port over the network: how soon the daemon's samples flow again when the server that carries the
port (``socat``, ``ser2net``) is killed and started again.  ``docs/how-to/network-serial.md`` quotes its output.

    python -m benchmarks.bench_network_reconnect [--servers socat,ser2net-raw,ser2net-rfc2217] [--down-s 0.5,1,2,5,10]
        [--repeat 2] [--rate-hz 100] [--half-open]

Method
------
The simulated instrument (``fog-driver simulate --serve pty``, the ``paper`` profile at ``--rate-hz``, seed 1) serves
a pty behind a symlink.  A server exposes that pty on a loopback TCP port, as a device server exposes a serial port:

* ``socat``: ``socat TCP-LISTEN:PORT,bind=127.0.0.1,reuseaddr FILE:LINK,raw,echo=0`` (raw TCP; the daemon reads
  ``socket://127.0.0.1:PORT``);
* ``ser2net-raw``: ser2net 4 with ``accepter: tcp,127.0.0.1,PORT`` and ``connector: serialdev,LINK,460800n81,local``
  (raw TCP, ``socket://``);
* ``ser2net-rfc2217``: the same with ``accepter: telnet(rfc2217),tcp,127.0.0.1,PORT``; the daemon reads
  ``rfc2217://127.0.0.1:PORT?ign_set_control`` (a pty has no modem lines, so ser2net never acknowledges their
  setting; a real serial port needs no option).

The daemon, ``python -m fog_driver run --port URL --listen 127.0.0.1:0 --capture-dir TMP`` without a terminal,
is ready when its "listening on" line arrives.  A client connects, sends ``?WATCH={"enable":true,"rate_hz":1000};``
(every sample) and records ``time.monotonic()`` at each line it reads: ANGLE (``seq``), DEVICE (``state``) and
STATUS (``seq_gaps``, ``missing_frames``).  Then, ``--repeat`` times over the ``--down-s`` values (the outages,
in order): the server gets SIGTERM and is waited for; it stays away for that long plus a draw of 0 to 1 s (from the
kill; seeded, ``--seed``: without it the outage would end at the same point of the daemon's 1-s retry interval
every time, and the worst case would never be met); it is started
again and is back once its port is listening (``/proc/net/tcp``, polled every 2 ms: a listening socket, or the
daemon's connection when it came first; the server is not connected to, which would take the daemon's place).

Measured: when the daemon saw the loss (DEVICE ``deactivated``, from the kill: pyserial's ``socket://`` and
``rfc2217://`` ports sleep 0.3 s in ``close()`` before the loss is reported), when the first ANGLE arrived after
the server was back (**back after**, the figure: the daemon's retry backoff, 0.1 s doubling up to 1 s, plus the
reconnection), how long no sample came (the last ANGLE before the kill to the first after), and the frames the
daemon counted missing over the outage (STATUS ``missing_frames``, the sequence numbers' gaps, read once samples
have flowed for ``SETTLE_S`` after the reconnection: the first bytes after it may be what the pty held while the
server was away, up to its buffer's size, and the gap comes after them).  At the end the daemon is
stopped and ``fog-driver inspect --json`` reads its raw capture (the files concatenated in name order): it finds
the gaps the daemon counted, from the bytes alone.

``--half-open``: the server is cut off without closing its connection, as by a cable pulled between the host and
the device server: it gets SIGSTOP (it holds its connection open and sends nothing more; the kernel still answers
TCP keepalive, so the daemon's silence rule, ``port_silence_s``, is what ends the connection).  Once the daemon has
seen the loss, the stopped server gets SIGKILL and the outage goes on as above; "loss seen after" runs from the
SIGSTOP, and "down" is from the SIGSTOP to the server listening again (at least the loss and the kill).

Needs ``socat`` and ``ser2net`` on the PATH (``apt-get install socat ser2net``); a server that is missing is skipped
and said so.  No assertion: the figures are printed.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import random
import select
import shutil
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
GUARD_S = 60.0  # the longest any one step may take before the benchmark gives up
SETTLE_S = 1.0  # samples flowing this long after a reconnection before the outage's missing frames are read
JITTER_S = 1.0  # each outage lasts its --down-s plus a draw of up to this (the daemon's longest retry interval)
SERVERS = ("socat", "ser2net-raw", "ser2net-rfc2217")
#: What each server's URL looks like to the daemon.
URLS = {
    "socat": "socket://127.0.0.1:{port}",
    "ser2net-raw": "socket://127.0.0.1:{port}",
    "ser2net-rfc2217": "rfc2217://127.0.0.1:{port}?ign_set_control",
}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def serving(port: int) -> bool:
    """Whether a server is up on ``port``, without connecting to it: a socket listens there, or one there is
    connected (states 0A and 01 in /proc/net/tcp).  ``socat`` without ``fork`` stops listening once it has
    accepted a connection: the daemon, retrying every 0.1 s, may connect before a poll sees the listener."""
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        with contextlib.suppress(OSError), open(table) as f:
            for line in f.readlines()[1:]:
                local, state = line.split()[1], line.split()[3]
                if state in ("0A", "01") and int(local.rsplit(":", 1)[1], 16) == port:
                    return True
    return False


def wait_until(predicate, what: str, timeout_s: float = GUARD_S, poll_s: float = 0.002) -> float:
    """Poll ``predicate`` until it holds; the monotonic time it first did."""
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise RuntimeError(f"timed out waiting for {what}")
        time.sleep(poll_s)
    return time.monotonic()


def read_line_within(stream, timeout_s: float, what: str) -> str:
    ready, _, _ = select.select([stream], [], [], timeout_s)
    line = stream.readline() if ready else ""
    if not line:
        raise RuntimeError(f"no {what} within {timeout_s} s")
    return line


class Server:
    """One network server in front of the simulator's pty, started and killed on demand."""

    def __init__(self, kind: str, link: Path, port: int, workdir: Path) -> None:
        self.kind, self.link, self.port = kind, link, port
        self.proc: subprocess.Popen | None = None
        self.frozen = False  # stopped by freeze(): only SIGKILL ends it
        self.log = (workdir / f"{kind}.log").open("a")
        if kind == "socat":
            self.argv = ["socat", f"TCP-LISTEN:{port},bind=127.0.0.1,reuseaddr", f"FILE:{link},raw,echo=0"]
        else:
            accepter = "telnet(rfc2217),tcp" if kind == "ser2net-rfc2217" else "tcp"
            config = workdir / f"{kind}.yaml"
            config.write_text(
                "connection: &fog\n"
                f"  accepter: {accepter},127.0.0.1,{port}\n"
                f"  connector: serialdev,{link},460800n81,local\n"
                "  options:\n"
                "    kickolduser: true\n"
            )
            self.argv = ["ser2net", "-n", "-u", "-c", str(config)]

    def start(self) -> float:
        """Start it; the monotonic time its port listens."""
        self.proc = subprocess.Popen(self.argv, stdin=subprocess.DEVNULL, stdout=self.log, stderr=self.log)

        def up() -> bool:
            if self.proc.poll() is not None:  # it gave up: say why rather than wait for the guard
                self.log.flush()
                said = Path(self.log.name).read_text()[-2000:]
                raise RuntimeError(f"{self.kind} exited with {self.proc.returncode}: {said}")
            return serving(self.port)

        return wait_until(up, f"{self.kind} to listen on {self.port}")

    def freeze(self) -> float:
        """SIGSTOP: the server holds its connections open and sends nothing more (a half-open peer); the monotonic
        time of the signal."""
        assert self.proc is not None
        t_freeze = time.monotonic()
        self.proc.send_signal(signal.SIGSTOP)
        self.frozen = True
        return t_freeze

    def kill(self) -> float:
        """SIGTERM (SIGKILL when frozen) and wait for it; the monotonic time of the signal."""
        assert self.proc is not None
        t_kill = time.monotonic()
        if self.frozen:
            self.proc.kill()
            self.frozen = False
        else:
            self.proc.terminate()
        self.proc.wait(GUARD_S)
        wait_until(lambda: not serving(self.port), f"{self.kind} to stop serving")
        return t_kill

    def close(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.kill()
        self.log.close()


@dataclass
class Watcher:
    """A client of the daemon recording when each line arrived."""

    address: str
    lines: list[tuple[float, dict]] = field(default_factory=list)
    changed: threading.Condition = field(default_factory=threading.Condition)

    def __post_init__(self) -> None:
        host, port = self.address.rsplit(":", 1)
        self.sock = socket.create_connection((host, int(port)), timeout=GUARD_S)
        self.sock.sendall(b'?WATCH={"enable":true,"rate_hz":1000};\n')
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()

    def _read(self) -> None:
        buffer = b""
        with contextlib.suppress(OSError):
            while chunk := self.sock.recv(65536):
                now = time.monotonic()
                buffer += chunk
                *complete, buffer = buffer.split(b"\n")
                objects = [json.loads(line) for line in complete if line.strip()]
                with self.changed:
                    self.lines.extend((now, obj) for obj in objects)
                    self.changed.notify_all()

    def first(self, kind: str, after: float, test=lambda obj: True) -> tuple[float, dict]:
        """The first line of class ``kind`` that arrived after ``after`` (waits for it)."""
        deadline = time.monotonic() + GUARD_S
        with self.changed:
            while True:
                for t, obj in self.lines:
                    if t > after and obj.get("class") == kind and test(obj):
                        return t, obj
                if not self.changed.wait(deadline - time.monotonic()):
                    raise RuntimeError(f"no {kind} after {after:.3f}")

    def last(self, kind: str, before: float) -> tuple[float, dict]:
        with self.changed:
            return [(t, obj) for t, obj in self.lines if t < before and obj.get("class") == kind][-1]

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.sock.shutdown(socket.SHUT_RDWR)
        self.sock.close()
        self.thread.join(GUARD_S)


@dataclass
class Outage:
    down_s: float
    lost_after_s: float  # the kill to the daemon's DEVICE deactivated
    back_after_s: float  # the server listening again to the first ANGLE
    no_samples_s: float  # the last ANGLE before the kill to the first after
    frames_missing: int  # STATUS missing_frames, its growth over the outage


def start_daemon(url: str, capture_dir: Path, log_path: Path) -> tuple[subprocess.Popen, str]:
    proc = subprocess.Popen(
        [sys.executable, "-m", "fog_driver", "run", "--port", url, "--listen", "127.0.0.1:0"]
        + ["--capture-dir", str(capture_dir), "--log-format", "json"],
        cwd=ROOT,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=log_path.open("w"),  # a file: an unread pipe would block the daemon
        text=True,
    )
    line = read_line_within(proc.stdout, GUARD_S, "listening line from the daemon")
    if "listening on" not in line:
        raise RuntimeError(f"daemon: {line!r}; its log: {log_path.read_text()[-2000:]}")
    return proc, line.split("listening on ")[1].split(";")[0]


def status_after(watcher: Watcher, after: float) -> dict:
    """A STATUS from after ``after`` (asked for, so as not to wait for the next second's)."""
    asked = max(after, time.monotonic())
    watcher.sock.sendall(b"?STATUS;\n")
    return watcher.first("STATUS", asked)[1]


def run_server(
    kind: str, link: Path, downs: list[float], workdir: Path, rng: random.Random, *, half_open: bool = False
) -> tuple[list[Outage], dict, dict]:
    port = free_port()
    server = Server(kind, link, port, workdir)
    capture_dir = workdir / f"captures-{kind}"
    daemon = watcher = None
    outages = []
    try:
        server.start()
        daemon, address = start_daemon(URLS[kind].format(port=port), capture_dir, workdir / f"daemon-{kind}.log")
        watcher = Watcher(address)
        watcher.first("ANGLE", 0.0)
        for planned_s in downs:
            down_s = planned_s + rng.uniform(0.0, JITTER_S)
            flowing, _ = watcher.first("ANGLE", time.monotonic())  # samples flow before each outage
            before = status_after(watcher, flowing)
            t_kill = server.freeze() if half_open else server.kill()
            t_lost, _ = watcher.first("DEVICE", t_kill, lambda obj: obj.get("state") == "deactivated")
            if half_open:
                server.kill()
            time.sleep(max(0.0, t_kill + down_s - time.monotonic()))  # the outage itself: the server stays away
            t_up = server.start()
            if half_open:
                down_s = t_up - t_kill
            t_back, _ = watcher.first("ANGLE", t_up)
            t_last, _ = watcher.last("ANGLE", t_kill)
            settled, _ = watcher.first("ANGLE", t_back + SETTLE_S)  # the pty's backlog read, the gap seen
            after = status_after(watcher, settled)
            outages.append(
                Outage(
                    down_s=down_s,
                    lost_after_s=t_lost - t_kill,
                    back_after_s=t_back - t_up,
                    no_samples_s=t_back - t_last,
                    frames_missing=after["missing_frames"] - before["missing_frames"],
                )
            )
        final = status_after(watcher, time.monotonic())
    finally:
        if watcher is not None:
            watcher.close()
        if daemon is not None:
            daemon.send_signal(signal.SIGTERM)
            daemon.wait(GUARD_S)
        server.close()
    return outages, final, inspect_capture(capture_dir, workdir / f"capture-{kind}.bin")


def inspect_capture(capture_dir: Path, joined: Path) -> dict:
    """``fog-driver inspect --json`` of the daemon's capture files concatenated in name order."""
    with joined.open("wb") as out:
        for path in sorted(capture_dir.glob("fog-*.bin")):
            out.write(path.read_bytes())
    done = subprocess.run(
        [sys.executable, "-m", "fog_driver", "inspect", "--json", str(joined)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=GUARD_S,
    )
    return json.loads(done.stdout)


def describe(kind: str, outages: list[Outage], final: dict, inspected: dict, rate_hz: float) -> str:
    url = URLS[kind].format(port="PORT")
    lines = [
        f"{kind} ({url}), {rate_hz:g} Hz, {len(outages)} outages:",
        "  down s  loss seen after s  back after s  no samples for s  frames missing",
    ]
    for o in outages:
        lines.append(
            f"  {o.down_s:6.1f}  {o.lost_after_s:17.3f}  {o.back_after_s:12.3f}  {o.no_samples_s:16.2f}"
            f"  {o.frames_missing:14,}"
        )
    backs = [o.back_after_s for o in outages]
    lines.append(
        f"  back after the server listened again: median {statistics.median(backs):.2f} s, worst {max(backs):.2f} s"
    )
    lines.append(
        f"  the daemon counted {final['seq_gaps']} gaps, {final['missing_frames']:,} frames missing;"
        f" inspect of its capture: {inspected.get('seq_gaps', 0)} gaps, {inspected.get('missing_frames', 0):,}"
        f" frames missing, {inspected.get('bytes_discarded', 0)} bytes discarded"
    )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--servers", default=",".join(SERVERS), help=f"comma-separated, of {', '.join(SERVERS)}")
    parser.add_argument("--down-s", default="0.5,1,2,5,10", help="the outages, seconds each (comma-separated)")
    parser.add_argument("--repeat", type=int, default=2, help="how many times the outages are run (each server)")
    parser.add_argument("--rate-hz", type=float, default=100.0, help="the simulated instrument's frame rate")
    parser.add_argument("--seed", type=int, default=1, help="the seed of the outages' draws of 0 to 1 s")
    parser.add_argument(
        "--half-open", action="store_true", help="cut each server off without closing (SIGSTOP) instead of killing it"
    )
    args = parser.parse_args(argv)
    if args.repeat < 1:
        parser.error("--repeat must be at least 1")
    kinds = [k for k in args.servers.split(",") if k]
    unknown = set(kinds) - set(SERVERS)
    if unknown:
        parser.error(f"unknown server(s): {', '.join(sorted(unknown))}")
    try:
        downs = [float(d) for d in args.down_s.split(",") if d] * args.repeat
    except ValueError:
        parser.error(f"--down-s: not a list of seconds: {args.down_s!r}")
    if not downs or not all(0 <= d <= 600 for d in downs):
        parser.error("--down-s: outages of 0 to 600 s, at least one")
    print(
        f"python {platform.python_version()}, {os.cpu_count()} CPUs; outages of {args.down_s} s"
        f" (each plus 0 to {JITTER_S:g} s, seed {args.seed}), {args.repeat} time(s)"
        + (
            "; half-open: each server stopped (SIGSTOP), not killed, until the daemon sees the loss"
            if args.half_open
            else ""
        )
    )
    for program in ("socat", "ser2net"):
        if shutil.which(program):
            version = subprocess.run([program, "-V" if program == "socat" else "-v"], capture_output=True, text=True)
            first = next((ln for ln in version.stdout.splitlines() if "version" in ln.lower()), "").strip()
            print(f"{program}: {first}")
    with tempfile.TemporaryDirectory(prefix="bench-net-") as tmp:
        workdir = Path(tmp)
        link = workdir / "sim.tty"
        sim = subprocess.Popen(
            [sys.executable, "-m", "fog_driver", "simulate", "--serve", "pty", "--link", str(link)]
            + ["--rate-hz", f"{args.rate_hz:g}", "--seed", "1"],
            cwd=ROOT,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=(workdir / "simulate.log").open("w"),
            text=True,
        )
        try:
            read_line_within(sim.stdout, GUARD_S, "readiness line from the simulator")
            for kind in kinds:
                program = kind.split("-")[0]
                if not shutil.which(program):
                    print(f"{kind}: skipped, {program} is not installed (apt-get install {program})")
                    continue
                outages, final, inspected = run_server(
                    kind, link, downs, workdir, random.Random(args.seed), half_open=args.half_open
                )
                print(describe(kind, outages, final, inspected, args.rate_hz))
        finally:
            sim.send_signal(signal.SIGTERM)
            sim.wait(GUARD_S)
    return 0


if __name__ == "__main__":
    from benchmarks._harness import run_main  # --update-readme: the documentation's block for this command

    run_main(main)
