"""The whole daemon as a process (``fog-driver run`` on a free loopback port) and a raw NDJSON client of it,
for the tests that start one: readiness from its "listening on" line and from DEVICE, never from sleeps."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from fog_driver.daemon.config import DEFAULT_MODEL
from fog_driver.modelfiles import load_model
from fog_driver.offline.compensate import compensate_capture
from fog_driver.protocol import decode_bytes
from fog_driver.transport import PtyPair

DATA = Path(__file__).resolve().parent / "data"


GUARD_S = 30.0


class Daemon:
    """``fog-driver run`` in a subprocess, listening on a free loopback port."""

    def __init__(self, tmp_path: Path, port: str, *extra: str, preexec=None) -> None:
        self.capture_dir = tmp_path / "captures"
        self.log_path = tmp_path / "daemon.log"
        self.log = self.log_path.open("w")  # a file: a full, unread pipe would block the daemon
        # PYTHONFAULTHANDLER: a hung daemon told SIGABRT writes every thread's stack to its log.
        self.proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "fog_driver",
                "run",
                "--port",
                port,
                "--listen",
                "127.0.0.1:0",
                "--capture-dir",
                str(self.capture_dir),
                *extra,
            ],
            stdout=subprocess.PIPE,
            stderr=self.log,
            text=True,
            stdin=subprocess.DEVNULL,
            env={**os.environ, "PYTHONFAULTHANDLER": "1"},
            preexec_fn=preexec,
        )
        line = self.proc.stdout.readline()  # the readiness line
        self.readiness = line
        assert "listening on" in line, (line, (tmp_path / "daemon.log").read_text())
        address = line.split("listening on ")[1].split(";")[0]
        host, _, number = address.rpartition(":")
        self.address = (host, int(number))

    def terminate(self) -> int:
        self.proc.send_signal(signal.SIGTERM)
        return self.wait()

    def wait(self) -> int:
        """The exit status; a daemon still running after GUARD_S fails with its thread stacks and log."""
        try:
            return self.proc.wait(GUARD_S)
        except subprocess.TimeoutExpired:
            self.proc.send_signal(signal.SIGABRT)  # faulthandler dumps every thread, then the process dies
            self.proc.wait(GUARD_S)
            pytest.fail(f"the daemon did not exit within {GUARD_S} s; its log:\n{self.log_path.read_text()[-20000:]}")

    def raw_capture(self) -> bytes:
        return b"".join(p.read_bytes() for p in sorted(self.capture_dir.glob("*.bin")))

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(GUARD_S)


class Client:
    def __init__(self, address: tuple[str, int]) -> None:
        self.sock = socket.create_connection(address, timeout=GUARD_S)
        self.file = self.sock.makefile("rb")
        self.device_state: str | None = None

    def send(self, line: str) -> None:
        self.sock.sendall(line.encode() + b"\n")

    def next(self, cls: str | None = None) -> dict:
        """The next line (of class ``cls``, skipping others); a hang guard fails the test after GUARD_S."""
        deadline = time.monotonic() + GUARD_S
        while True:
            assert time.monotonic() < deadline, f"no {cls or 'line'} within {GUARD_S} s"
            raw = self.file.readline()
            assert raw, "the daemon closed the connection"
            obj = json.loads(raw)
            assert "class" in obj and None not in obj.values()
            if obj["class"] == "DEVICE":
                self.device_state = obj.get("state")
            if cls is None or obj["class"] == cls:
                return obj

    def wait_device(self, state: str) -> None:
        """Until the port is in ``state`` (from a DEVICE line already passed, or the next ones)."""
        while self.device_state != state:
            self.next("DEVICE")

    def close(self) -> None:
        """Hang up (the file made by makefile holds the socket open until it is closed too)."""
        self.file.close()
        self.sock.close()


def offline_angles(capture_bytes: bytes, tmp_path: Path) -> dict[int, float]:
    path = tmp_path / "offline.bin"
    path.write_bytes(capture_bytes)
    angles = {}
    for _, cols in compensate_capture(path, load_model(DEFAULT_MODEL)):
        angles.update(zip(cols.seq.tolist(), cols.angle_comp_arcsec.tolist()))
    return angles


SHORT = (DATA / "sim-short.bin").read_bytes()


N_SHORT = decode_bytes(SHORT).counters.sample_frames


def next_status(client: Client, until, what: str, limit: int = 120) -> dict:
    """The first STATUS for which ``until(status)`` holds, within ``limit`` of them (one a second)."""
    for _ in range(limit):
        status = client.next("STATUS")
        if until(status):
            return status
    pytest.fail(f"no STATUS with {what} within {limit} of them")


def watch_all(client: Client, n: int) -> list[dict]:
    """``n`` consecutive ANGLE lines; the seqs must have no hole (nothing was lost on the way)."""
    angles = [client.next("ANGLE") for _ in range(n)]
    seqs = [a["seq"] for a in angles]
    assert seqs == list(range(seqs[0], seqs[0] + n)), "a sample was not published"
    return angles


def start_watching(daemon: Daemon) -> Client:
    client = Client(daemon.address)
    client.send('?WATCH={"enable":true};')
    client.next("WATCH")
    client.wait_device("activated")
    return client


@contextlib.contextmanager
def watched_daemon(tmp_path: Path, *extra: str, preexec=None) -> Iterator[tuple[PtyPair, Daemon, Client]]:
    """A daemon on a pty with a client watching every sample, the port open; killed if still running at the end."""
    with PtyPair() as pty:
        daemon = Daemon(tmp_path, pty.slave_path, *extra, preexec=preexec)
        try:
            yield pty, daemon, start_watching(daemon)
        finally:
            daemon.kill()
