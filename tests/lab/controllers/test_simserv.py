"""The Weiss / Voetsch SIMSERV codec and driver, against the frame of the SIMSERV interface description
(fields separated by byte 0xB6, lines ending CR, answers starting with the status 1 for OK) and a fake server
written here from that description (not from the codec)."""

from __future__ import annotations

from dataclasses import dataclass, field

import pytest
from ascii_chamber_server import (
    LineServer,
    Reply,
    assert_a_drop_mid_reply_is_unreachable,
    assert_every_split_reads_the_same,
)

from fog_driver.errors import UsageError
from fog_driver.lab.controllers.base import ControllerProtocolError
from fog_driver.lab.controllers.codecs import simserv
from fog_driver.lab.controllers.registry import open_controller

SEP = b"\xb6"


@dataclass
class FakeSimserv:
    """A SIMSERV server: 11001 CHB CH VALUE sets a channel's set point, 11002 reads it, 11004 reads the actual
    value, 11007 / 11009 the lower / upper limits, 14001 CHB 1|0 starts / stops manual mode; OK answers
    start with 1, errors with a negative code."""

    actual: dict[int, float] = field(default_factory=lambda: {1: 23.4, 2: 55.0})
    setpoint: dict[int, float] = field(default_factory=lambda: {1: 20.0, 2: 50.0})
    limits: tuple[float, float] = (-75.0, 180.0)
    manual: bool = False

    def __call__(self, line: bytes) -> Reply:
        fields = [part.decode("ascii") for part in line.split(SEP)]
        command, chamber = int(fields[0]), int(fields[1])
        if chamber != 1:
            return b"-5\r\n"
        if command == 14001:
            self.manual = fields[2] == "1"
            return b"1\r\n"
        channel = int(fields[2])
        values = {11002: self.setpoint, 11004: self.actual}
        if command in values:
            return b"1" + SEP + f"{values[command][channel]:.1f}".encode() + b"\r\n"
        if command in (11007, 11009):
            return b"1" + SEP + f"{self.limits[command == 11009]:.1f}".encode() + b"\r\n"
        if command == 11001:
            self.setpoint[channel] = float(fields[3])
            return b"1\r\n"
        return b"-8\r\n"


@pytest.fixture
def chamber():
    fake = FakeSimserv()
    server = LineServer(fake, b"\r")
    yield fake, server
    server.close()


def _open(server, query="", notices=None):
    sink = notices if notices is not None else []
    url = f"simserv://127.0.0.1:{server.port}" + (f"?{query}" if query else "")
    controller = open_controller(url, on_notice=sink.append)
    controller.connect()
    return controller


def test_requests_are_fields_separated_by_0xb6_ending_cr():
    """The frame of the description: '11001 0xB6 1 0xB6 1 0xB6 20.0 CR' sets chamber 1's channel 1 to 20.0;
    '11004 0xB6 1 0xB6 1 CR' reads its actual value; '14001 0xB6 1 0xB6 1 CR' starts manual mode."""
    assert simserv.encode_write_setpoint(1, 1, 20.0) == b"11001\xb61\xb61\xb620.0\r"
    assert simserv.encode_write_setpoint(1, 2, -20.05) == b"11001\xb61\xb62\xb6-20.1\r"
    assert simserv.encode_read(simserv.GET_ACTUAL, 1, 1) == b"11004\xb61\xb61\r"
    assert simserv.encode_read(simserv.GET_SETPOINT, 1, 1) == b"11002\xb61\xb61\r"
    assert simserv.encode_manual_mode(1, start=True) == b"14001\xb61\xb61\r"
    assert simserv.encode_manual_mode(1, start=False) == b"14001\xb61\xb60\r"


def test_answers_starting_with_1_are_ok_and_others_errors():
    assert simserv.decode_value(b"1\xb623.4\r", what="the air") == 23.4
    assert simserv.decode_value(b"\n1\xb6-40.0\r", what="the air") == -40.0
    simserv.decode_ack(b"1\r")
    with pytest.raises(ControllerProtocolError, match="error '-5'"):
        simserv.decode_ack(b"-5\r")


@pytest.mark.parametrize("reply", [b"\xff\xb6\r", b"1\r", b"1\xb6abc\r", b"2\xb623.4\r", b"1\xb623.4", b"1\xb6\x01\r"])
def test_garbage_to_a_read_is_a_protocol_error(reply):
    with pytest.raises(ControllerProtocolError):
        simserv.decode_value(reply, what="the air")


def test_a_reply_split_at_every_point_reads_the_same(chamber):
    fake, server = chamber
    controller = _open(server)
    assert_every_split_reads_the_same(server, controller.read_air_c, b"1\xb6-12.3\r\n", -12.3)
    controller.close()


def test_the_driver_drives_only_its_loop_starts_and_stops(chamber):
    fake, server = chamber
    notices: list[str] = []
    controller = _open(server, "loop=2", notices=notices)
    assert controller.address == f"simserv://127.0.0.1:{server.port}"
    assert controller.read_air_c() == 55.0
    assert (controller.read_range_c().low_c, controller.read_range_c().high_c) == fake.limits
    controller.write_setpoint_c(60.05)
    assert fake.setpoint == {1: 20.0, 2: 60.1} and fake.manual
    assert controller.read_setpoint_c() == 60.1
    controller.write_setpoint_c(61.0)
    assert server.lines.count(b"14001\xb61\xb61") == 1
    controller.safe_stop()
    assert not fake.manual
    assert controller.read_status().state == "unknown"
    controller.read_status()
    assert len(notices) == 2 and "degC assumed" in notices[0] and "state unknown" in notices[1]
    controller.close()


def test_a_controller_set_to_degf_is_read_and_written_in_degc(chamber):
    fake, server = chamber
    fake.actual[1] = 32.0
    controller = _open(server, "unit=F")
    assert controller.read_air_c() == 0.0
    controller.write_setpoint_c(100.0)
    assert fake.setpoint[1] == 212.0
    controller.close()


def test_an_error_answer_to_a_write_is_a_protocol_error(chamber):
    _fake, server = chamber
    controller = _open(server, "chamber=2")
    with pytest.raises(ControllerProtocolError, match="-5"):
        controller.write_setpoint_c(20.0)
    controller.close()


def test_a_connection_dropped_mid_reply_is_unreachable(chamber):
    fake, server = chamber
    controller = _open(server)
    assert_a_drop_mid_reply_is_unreachable(server, controller, controller.read_air_c, b"1" + SEP + b"23")
    controller.close()


def test_options_come_from_the_url_over_the_overrides():
    controller = open_controller("simserv://h?loop=1", overrides={"loop": 3, "upper_limit_command": 11010})
    assert (controller.loop, controller.upper_limit_command) == (1, 11010)
    with pytest.raises(UsageError, match="unknown option lopo"):
        open_controller("simserv://h?lopo=1")
