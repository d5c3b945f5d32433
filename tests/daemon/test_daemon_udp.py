"""The UDP publisher as deployed: a destination name that does not resolve yet, and broadcast.

No sleeps: resolution retries run on an injected clock, and the background resolver is waited for
on the publisher's ``resolved`` event.
"""

from __future__ import annotations

import math
import socket
import struct
from pathlib import Path

import numpy as np
import pytest

from fog_driver.client import udp as client_udp
from fog_driver.daemon import udp as daemon_udp
from fog_driver.daemon.config import DriverConfig, parse_config
from fog_driver.daemon.service import Service
from fog_driver.daemon.udp import UdpPublisher, decode_datagram
from fog_driver.errors import InputFileError

DATA = Path(__file__).resolve().parents[1] / "data"
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


# -- version 2: the drift's sigma at byte 68 -------------------------------------------------------------

#: An ANGLE object as the daemon publishes it (since protocol 1.1, with drift_sigma_dph).
ANGLE = {
    "class": "ANGLE",
    "seq": 4242,
    "t_s": 424.2,
    "angle_arcsec": -12.345678,
    "angle_raw_arcsec": 4567.891,
    "rate_dph": 10.25,
    "rate_raw_dph": 10.3,
    "drift_dph": -0.078125,
    "drift_sigma_dph": 0.0123,
    "temps_c": {"top": 25.5, "housing": 24.25},
    "flags": ["extrapolating", "substituted"],
    "utc": "2026-12-02T14:56:26.123Z",
}
#: Its version-1 datagram as the sender made it before version 2 existed (taken from that code, not from
#: this one): version 1 must stay byte for byte what it was.
ANGLE_V1_BEFORE_V2 = bytes.fromhex(
    "464f4741000100c00000000000001092407a833333333333c028b0fcb4f1e4b440b1d7e4189374bc4024800000000000"
    "bfb400000000000041cc00007fc0000041c20000"
)


def test_version_1_is_the_default_and_byte_for_byte_what_it_was():
    assert daemon_udp.encode_datagram(**daemon_udp.fields_from_angle(ANGLE)) == ANGLE_V1_BEFORE_V2
    assert DriverConfig().udp_version == 1
    decoded = decode_datagram(ANGLE_V1_BEFORE_V2)
    assert decoded["version"] == 1 and decoded["seq"] == 4242 and decoded["drift_dph"] == -0.078125
    assert math.isnan(decoded["drift_sigma_dph"])  # version 1 has no room for it: NaN, the absent value
    assert list(decoded) == ["version", *client_udp.FIELDS_V2]


def test_version_2_appends_the_sigma_as_a_big_endian_f32_at_byte_68():
    v2 = daemon_udp.encode_datagram(**daemon_udp.fields_from_angle(ANGLE), version=2)
    # independently: version 1 with 2 in the version field, and the f32 appended in the record's byte order
    assert v2 == ANGLE_V1_BEFORE_V2[:4] + b"\x00\x02" + ANGLE_V1_BEFORE_V2[6:] + struct.pack(">f", 0.0123)
    assert len(v2) == client_udp.DATAGRAM_V2_SIZE == 72 and v2[68:] == bytes.fromhex("3c4985f0")
    decoded = decode_datagram(v2)
    assert decoded["version"] == 2 and decoded["drift_sigma_dph"] == float(np.float32(0.0123))
    v1 = decode_datagram(ANGLE_V1_BEFORE_V2)
    assert [repr(decoded[k]) for k in client_udp.FIELDS] == [repr(v1[k]) for k in client_udp.FIELDS]  # NaN too
    assert decode_datagram(v2 + b"future fields")["drift_sigma_dph"] == decoded["drift_sigma_dph"]
    # no estimate (the key omitted): NaN, the quiet NaN the thermometers use
    without = {k: v for k, v in ANGLE.items() if k != "drift_sigma_dph"}
    nan_v2 = daemon_udp.encode_datagram(**daemon_udp.fields_from_angle(without), version=2)
    assert nan_v2[68:] == bytes.fromhex("7fc00000") and math.isnan(decode_datagram(nan_v2)["drift_sigma_dph"])
    # a version-1 receiver reading the first 68 bytes sees version 1's fields unchanged
    assert v2[6:68] == ANGLE_V1_BEFORE_V2[6:68]


@pytest.mark.parametrize(
    "bad, message",
    [
        (ANGLE_V1_BEFORE_V2[:4] + b"\x00\x02" + ANGLE_V1_BEFORE_V2[6:], "a version-2 datagram has 72"),
        (ANGLE_V1_BEFORE_V2[:4] + b"\x00\x03" + ANGLE_V1_BEFORE_V2[6:] + bytes(8), "reads versions 1, 2"),
        (ANGLE_V1_BEFORE_V2[:67], "a version-1 datagram has 68"),
        (b"FOGB" + ANGLE_V1_BEFORE_V2[4:], "bad magic"),
    ],
)
def test_the_decoder_refuses_what_is_neither_version(bad, message):
    with pytest.raises(ValueError, match=message):
        decode_datagram(bad)


@pytest.mark.parametrize("version", [0, 3])
def test_an_unknown_version_is_refused_by_the_sender_and_the_config(version):
    with pytest.raises(ValueError, match=f"version must be one of \\[1, 2\\], got {version}"):
        UdpPublisher("127.0.0.1", 9, version=version)
    with pytest.raises(ValueError, match="version must be one of"):
        daemon_udp.encode_datagram(seq=1, version=version)
    with pytest.raises(InputFileError, match=f"^bench.yaml: udp_version must be 1 or 2, got {version}$"):
        parse_config({"udp_version": version}, "bench.yaml")
    with pytest.raises(InputFileError, match="^bench.yaml: udp_version: expected an integer, got "):
        parse_config({"udp_version": "2"}, "bench.yaml")


@pytest.mark.parametrize("version", [1, 2])
def test_the_daemon_sends_its_configured_version_with_the_angles_sigma(version, receiver, tmp_path):
    """Every datagram of the configured layout; in version 2 the sigma is the ANGLE's (the shipped model's),
    as f32, and NaN where the ANGLE omits it (no estimate yet)."""
    udp = f"127.0.0.1:{receiver.getsockname()[1]}"
    config = DriverConfig(udp=udp, udp_version=version, listen="127.0.0.1:0", capture_dir=str(tmp_path / "c"))
    service = Service(config, port=str(tmp_path / "no-such-tty"))  # acquisition waits for the port
    data = (DATA / "sim-short.bin").read_bytes()[:20000]
    pairs = []
    try:
        service.start()
        for i in range(0, len(data), 1300):  # about 50 samples a chunk, read before the next: none dropped
            for angle in service.process(data[i : i + 1300]):
                pairs.append((angle, receiver.recv(2048)))
    finally:
        service.stop.set()
        service.shutdown()
    assert len(pairs) > 600 and service.udp.send_errors == 0
    size = {1: 68, 2: 72}[version]
    assert all(len(raw) == size for _, raw in pairs)
    for angle, raw in pairs:
        got = decode_datagram(raw)
        assert (got["version"], got["seq"], got["angle_arcsec"]) == (version, angle["seq"], angle["angle_arcsec"])
        if version == 2 and "drift_sigma_dph" in angle:
            assert got["drift_sigma_dph"] == float(np.float32(angle["drift_sigma_dph"]))
        else:
            assert math.isnan(got["drift_sigma_dph"])
    assert sum("drift_sigma_dph" in a for a, _ in pairs) > 500 and "drift_sigma_dph" not in pairs[0][0]


def test_udp_version_needs_a_restart_as_udp_does():
    service = Service(DriverConfig(), port="unused")
    result = service.reload_config(DriverConfig(udp_version=2))
    assert result["restart_needed"] == ["udp_version"] and service.config.udp_version == 1
