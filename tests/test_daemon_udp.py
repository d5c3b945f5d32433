"""The UDP publisher as deployed: a destination name that does not resolve yet, and broadcast.

No sleeps: resolution retries run on an injected clock, and the background resolver is waited for
on the publisher's ``resolved`` event.
"""

from __future__ import annotations

import socket
from pathlib import Path

import pytest

from fog_driver.client import udp as client_udp
from fog_driver.daemon import udp as daemon_udp
from fog_driver.daemon.config import DriverConfig
from fog_driver.daemon.service import Service
from fog_driver.daemon.udp import UdpPublisher, decode_datagram

DATA = Path(__file__).resolve().parent / "data"
TIMEOUT_S = 10.0
LATE_NAME = "station.fog-driver-test"  # resolves only once the test says the network is up


class FakeClock:
    def __init__(self, t: float = 1000.0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


class LateResolver:
    """``socket.getaddrinfo`` for which LATE_NAME fails until ``network_up``, then means 127.0.0.1."""

    def __init__(self) -> None:
        self.real = socket.getaddrinfo
        self.network_up = False
        self.attempts = 0

    def __call__(self, host, *args, **kwargs):
        if host != LATE_NAME:
            return self.real(host, *args, **kwargs)
        self.attempts += 1
        if not self.network_up:
            raise socket.gaierror(socket.EAI_NONAME, "Name or service not known")
        return self.real("127.0.0.1", *args, **kwargs)


@pytest.fixture
def late_resolver(monkeypatch):
    resolver = LateResolver()
    monkeypatch.setattr(socket, "getaddrinfo", resolver)
    return resolver


@pytest.fixture
def receiver():
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("0.0.0.0", 0))  # a broadcast reaches a socket bound to the wildcard address
    rx.settimeout(TIMEOUT_S)
    yield rx
    rx.close()


def test_a_name_that_resolves_late_is_retried_in_the_background_and_counted_until_then(late_resolver, receiver):
    clock = FakeClock()
    pub = UdpPublisher(LATE_NAME, receiver.getsockname()[1], retry_resolve_s=5.0, clock=clock)
    assert pub.address is None and not pub.resolved.is_set()
    assert pub.last_error == f"cannot resolve {LATE_NAME}:{receiver.getsockname()[1]}: Name or service not known"
    assert pub.send(seq=1) is False and pub.send(seq=2) is False
    assert late_resolver.attempts == 1  # no retry before retry_resolve_s
    late_resolver.network_up = True
    clock.t += 5.0
    assert pub.send(seq=3) is False  # starts the resolver thread; this sample is not held back for it
    assert pub.resolved.wait(TIMEOUT_S)
    assert late_resolver.attempts == 2 and pub.address == ("127.0.0.1", receiver.getsockname()[1])
    assert pub.send(seq=4) is True
    assert decode_datagram(receiver.recv(2048))["seq"] == 4
    assert (pub.sent, pub.send_errors) == (1, 3)
    fields = pub.status_fields()
    assert fields["udp_sent"] == 1 and fields["udp_send_errors"] == 3 and LATE_NAME in fields["udp_last_error"]
    pub.close()
    assert pub.send(seq=5) is False and pub.send_errors == 4


def test_a_broadcast_destination_gets_the_datagrams(receiver):
    """Without SO_BROADCAST every sendto to a broadcast address failed with EACCES, silently."""
    with UdpPublisher("127.255.255.255", receiver.getsockname()[1]) as pub:  # the loopback net's broadcast
        assert pub.send(seq=7, angle_arcsec=1.5) is True
        assert decode_datagram(receiver.recv(2048))["seq"] == 7
        assert pub.status_fields() == {"udp_sent": 1, "udp_send_errors": 0}


def test_the_daemon_starts_and_publishes_with_a_udp_name_that_does_not_resolve_yet(late_resolver, tmp_path):
    """The review's L1: the unit starts after network.target, before names resolve; the daemon died with
    an uncaught gaierror (exit 1) in start().  Now it runs, and each sample is a counted send error."""
    config = DriverConfig(udp=f"{LATE_NAME}:9", listen="127.0.0.1:0", capture_dir=str(tmp_path / "captures"))
    service = Service(config, port=str(tmp_path / "no-such-tty"))  # acquisition waits for the port
    try:
        service.start()
        angles = service.process((DATA / "sim-short.bin").read_bytes())
        assert len(angles) > 100
        assert service.udp.send_errors == len(angles) and service.udp.sent == 0
    finally:
        service.stop.set()
        service.shutdown()


def test_the_decoder_lives_in_the_client_library_and_the_daemon_re_exports_it():
    for name in client_udp.__all__:
        assert getattr(daemon_udp, name) is getattr(client_udp, name), name
    assert set(client_udp.__all__) - {"DATAGRAM_STRUCT"} <= set(daemon_udp.__all__)
