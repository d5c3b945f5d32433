"""The Thermotron 8800 / 8200 codec and driver, against the mnemonics of Thermotron's 8800 interface
communications manual and a fake programmer written here from that manual (not from the codec)."""

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
from fog_driver.lab.controllers.base import ControllerProtocolError, f_to_c
from fog_driver.lab.controllers.codecs import thermotron
from fog_driver.lab.controllers.registry import open_controller


@dataclass
class Fake8800:
    """The 8800 / 8200 as its manual describes it: a request line ends CR, an answer CR LF; PVARn? and SETPn?
    answer a number, SETPn,x and MRMPn,x echo their value (unless ``echo`` is off), RUNM / HOLD / STOP answer
    nothing, SCOD? the status code."""

    air: dict[int, float] = field(default_factory=lambda: {1: 23.4, 2: 50.0})
    setpoint: dict[int, float] = field(default_factory=lambda: {1: 20.0, 2: 45.0})
    ramp: dict[int, float] = field(default_factory=dict)
    status: str = "0"
    echo: bool = True

    def __call__(self, line: bytes) -> Reply:
        text = line.decode("ascii")
        if text.startswith("PVAR") and text.endswith("?"):
            return f"{self.air[int(text[4:-1])]:.2f}\r\n".encode()
        if text.startswith("SETP") and text.endswith("?"):
            return f"{self.setpoint[int(text[4:-1])]:.2f}\r\n".encode()
        if text.startswith(("SETP", "MRMP")):
            loop, value = text[4:].split(",")
            (self.setpoint if text.startswith("SETP") else self.ramp)[int(loop)] = float(value)
            return f"{float(value):.3f}\r\n".encode() if self.echo else None
        if text == "RUNM":
            self.status = "1"
        if text in ("STOP", "HOLD"):
            self.status = "0" if text == "STOP" else "3"
        if text == "SCOD?":
            return f"{self.status}\r\n".encode()
        return None


@pytest.fixture
def chamber():
    fake = Fake8800()
    server = LineServer(fake, b"\r")
    yield fake, server
    server.close()


def _open(server, query="range=-70:180", notices=None):
    sink = notices if notices is not None else []
    controller = open_controller(f"thermotron://127.0.0.1:{server.port}?{query}", on_notice=sink.append)
    controller.connect()
    return controller


def test_requests_are_the_manuals_mnemonics():
    """The manual's mnemonics: 'PVAR1?' (process variable 1), 'SETP1?' / 'SETP1,20.0' (set point 1),
    'MRMP1,2.0' (manual ramp rate), 'RUNM', 'HOLD', 'STOP', 'SCOD?' (status code), each ending CR."""
    assert thermotron.encode_read_air(1) == b"PVAR1?\r"
    assert thermotron.encode_read_setpoint(2) == b"SETP2?\r"
    assert thermotron.encode_write_setpoint(1, 20.0) == b"SETP1,20.0\r"
    assert thermotron.encode_write_setpoint(1, -20.05) == b"SETP1,-20.1\r"
    assert thermotron.encode_ramp_rate(1, 2.0) == b"MRMP1,2.0\r"
    assert (thermotron.encode_run_manual(), thermotron.encode_hold(), thermotron.encode_stop()) == (
        b"RUNM\r",
        b"HOLD\r",
        b"STOP\r",
    )
    assert thermotron.encode_read_status() == b"SCOD?\r"


def test_answers_decode_with_a_cr_or_a_cr_lf():
    assert thermotron.decode_number(b"23.45\r", what="the air") == 23.45
    assert thermotron.decode_number(b"\n-40.00\r", what="the air") == -40.0  # the LF of the last CR LF
    assert [thermotron.decode_status(f"{c}\r".encode()) for c in (0, 1, 2, 9)] == [
        "standby",
        "constant",
        "program",
        "unknown",
    ]


@pytest.mark.parametrize("reply", [b"\xff\r", b"ERR\r", b"1e999\r", b"23.4", b""])
def test_garbage_to_a_read_is_a_protocol_error(reply):
    with pytest.raises(ControllerProtocolError):
        thermotron.decode_number(reply, what="the air")


def test_a_reply_split_at_every_point_reads_the_same(chamber):
    fake, server = chamber
    controller = _open(server)
    assert_every_split_reads_the_same(server, controller.read_air_c, b"-12.30\r\n", -12.3)
    controller.close()


def test_the_driver_drives_only_its_loop_and_stops(chamber):
    fake, server = chamber
    controller = _open(server, "range=-70:180&loop=1&ramp_rate=5")
    assert controller.address == f"thermotron://127.0.0.1:{server.port}"
    assert controller.read_air_c() == 23.4
    assert (controller.read_range_c().low_c, controller.read_range_c().high_c) == (-70.0, 180.0)
    controller.write_setpoint_c(30.05)
    assert controller.read_setpoint_c() == 30.1
    assert fake.setpoint[2] == 45.0 and fake.ramp == {1: 5.0}
    assert controller.read_status().state == "constant"
    controller.write_setpoint_c(31.0)
    assert server.lines.count(b"RUNM") == 1
    controller.safe_stop()
    assert controller.read_status().state == "standby"
    controller.close()


def test_the_8200_manuals_set_point_example_round_trips():
    """The 8200 manual's example: 'SETP1,22.000' (53 45 54 50 31 2C 32 32 2E 30 30 30 0D) -> '22.000'
    (32 32 2E 30 30 30 0D); 'PVAR1?' (50 56 41 52 31 3F 0D) -> '22.000'."""
    assert thermotron.encode_read_air(1) == bytes.fromhex("50 56 41 52 31 3F 0D")
    assert thermotron.decode_number(bytes.fromhex("32 32 2E 30 30 30 0D"), what="the air") == 22.0
    assert thermotron.encode_write_setpoint(1, 22.0) == b"SETP1,22.0\r"  # one decimal, not the example's three


def test_an_interface_that_echoes_nothing_is_driven_with_write_echo_0(chamber):
    fake, server = chamber
    fake.echo = False
    controller = _open(server, "range=-70:180&write_echo=0&ramp_rate=2")
    controller.write_setpoint_c(12.3)
    assert controller.read_air_c() == 23.4  # no echo taken for the air
    assert fake.setpoint[1] == 12.3 and fake.ramp[1] == 2.0
    controller.close()


def test_a_controller_set_to_degf_is_read_and_written_in_degc(chamber):
    fake, server = chamber
    fake.air[1] = 212.0
    controller = _open(server, "range=-70:180&unit=F&ramp_rate=1")
    assert controller.read_air_c() == pytest.approx(100.0)
    controller.write_setpoint_c(-40.0)
    assert controller.read_setpoint_c() == pytest.approx(-40.0)
    assert fake.setpoint[1] == -40.0 and fake.ramp[1] == 1.8
    controller.close()


def test_a_status_code_that_is_not_one_is_state_unknown_said_once(chamber):
    fake, server = chamber
    fake.status = "BAD"
    notices: list[str] = []
    controller = _open(server, "range=-70:180&unit=C", notices=notices)
    assert controller.read_status().state == "unknown"
    assert controller.read_status().state == "unknown"
    assert len(notices) == 1 and "status code" in notices[0]
    controller.close()


def test_a_connection_dropped_mid_reply_is_unreachable(chamber):
    fake, server = chamber
    controller = _open(server)
    assert_a_drop_mid_reply_is_unreachable(server, controller, controller.read_air_c, b"23.")
    controller.close()


def test_without_a_range_the_driver_refuses_to_open():
    with pytest.raises(UsageError, match="range=LOW:HIGH"):
        open_controller("thermotron://h")
    with pytest.raises(UsageError, match="bad range"):
        open_controller("thermotron://h?range=50:10")
    controller = open_controller("thermotron://h", overrides={"range": [-40, 120], "unit": "F", "write_echo": False})
    assert controller.read_range_c().low_c == -40.0 and not controller.write_echo
    assert controller.resolution_c == pytest.approx(f_to_c(0.1) - f_to_c(0.0))
    with pytest.raises(UsageError, match="unknown option"):
        open_controller("thermotron://h?range=-40:120&loops=2")


def test_an_extra_answer_arriving_unasked_is_not_taken_for_the_next(chamber):
    fake, server = chamber
    controller = _open(server)
    server.inject(b"23.40\r\n99.90\r\n")  # one write: the answer and a stray line after it (a late echo)
    assert controller.read_air_c() == 23.4
    assert controller.read_setpoint_c() == fake.setpoint[1]
    controller.close()
