"""The ``make_hub`` fixture (a started Hub on loopback with fake callbacks, stopped after the test) and
the fake service behind it, for test_daemon_hub.py and test_daemon_hostile_clients.py; conftest.py
registers it as a plugin, so no test module imports a fixture."""

from __future__ import annotations

import concurrent.futures
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
