"""The ``make_hub`` fixture (a started Hub on loopback with fake callbacks, stopped after the test) and
the fake service behind it, for test_daemon_hub.py and test_daemon_hostile_clients.py, with the line-reading
client (``Conn``) and the ANGLE they send; conftest.py registers it as a plugin, so no test module imports a fixture."""

from __future__ import annotations

import concurrent.futures
import json
import socket
import threading

import pytest

from fog_driver.daemon.hub import Hub

VERSION = {"release": "9.9.9", "proto_major": 1, "proto_minor": 0, "serial": "FOG-TEST-0001"}
DEVICE = {"path": "/dev/ttyFOG0", "serial": "FOG-TEST-0001", "rate_hz": 100, "activated": None}


class Control:
    """The service side: records calls, answers ECHO/FAIL/SLOW/SYNC, knows nothing else."""

    def __init__(self) -> None:
        self.calls: list[tuple[str, dict, int]] = []
        self.pending: concurrent.futures.Future | None = None
        self.slow_called = threading.Event()
        self.sync = threading.Event()

    def __call__(self, name: str, args: dict, client_id: int):
        self.calls.append((name, args, client_id))
        if name == "ECHO":
            return {"class": "ECHO", "args": args, "client": client_id, "nothing": None}
        if name == "BARE":
            return {"ok": True}
        if name == "FAIL":
            raise RuntimeError("the instrument is on fire")
        if name == "SLOW":
            self.pending = concurrent.futures.Future()
            self.slow_called.set()
            return self.pending
        if name == "FUTFAIL":
            fut: concurrent.futures.Future = concurrent.futures.Future()
            fut.set_exception(ValueError("future failed"))
            return fut
        if name == "SYNC":
            self.sync.set()
            return {"class": "SYNC"}
        return None


@pytest.fixture
def make_hub():
    hubs: list[Hub] = []

    def factory(**kwargs) -> tuple[Hub, tuple[str, int], Control]:
        control = kwargs.pop("control", None) or Control()
        device = kwargs.pop("device", lambda: DEVICE)
        hub = Hub(version=lambda: VERSION, device=device, control=control, **kwargs)
        hubs.append(hub)
        return hub, hub.start(), control

    yield factory
    for hub in hubs:
        hub.stop()


TIMEOUT_S = 5.0


class Conn:
    """A test client: line reader with a timeout as failure guard; every line must be JSON with a class."""

    def __init__(self, address: tuple[str, int], rcvbuf: int | None = None) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        if rcvbuf is not None:
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
        self.sock.settimeout(TIMEOUT_S)
        self.sock.connect(address)
        self.buf = b""

    def send(self, data: bytes | str) -> None:
        self.sock.sendall(data.encode() if isinstance(data, str) else data)

    def raw_line(self) -> bytes:
        while b"\n" not in self.buf:
            chunk = self.sock.recv(65536)
            if not chunk:
                raise EOFError("connection closed")
            self.buf += chunk
        line, _, self.buf = self.buf.partition(b"\n")
        return line

    def line(self) -> dict:
        raw = self.raw_line()
        obj = json.loads(raw)
        assert isinstance(obj, dict) and isinstance(obj.get("class"), str), raw
        assert b"null" not in raw and b"NaN" not in raw and b"Infinity" not in raw, raw
        return obj

    def expect(self, cls: str) -> dict:
        obj = self.line()
        assert obj["class"] == cls, obj
        return obj

    def greeting(self) -> None:
        self.expect("VERSION")
        self.expect("DEVICE")

    def sync(self) -> None:
        """Round trip: every line the server queued for this client before now precedes the answer."""
        self.send("?VERSION;\n")
        self.expect("VERSION")

    def wait_closed(self) -> None:
        """Read (and discard) until the server closes the connection."""
        while True:
            try:
                chunk = self.sock.recv(65536)
            except ConnectionResetError:
                return
            if not chunk:
                return

    def close(self) -> None:
        self.sock.close()


def angle(seq: int, t_s: float, **extra) -> dict:
    return {"class": "ANGLE", "seq": seq, "t_s": t_s, "angle_arcsec": seq * 0.5, **extra}
