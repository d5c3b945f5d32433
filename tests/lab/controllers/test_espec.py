"""The Espec P-300 / SCP-220 codec and driver, against the frames of Espec's communication manual for the
P-300 / SCP-220 controllers and a fake controller written here from that manual (not from the codec)."""

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
from fog_driver.lab.controllers.base import (
    ControllerProtocolError,
    ControllerRefused,
    ControllerUnreachable,
    c_to_f,
)
from fog_driver.lab.controllers.codecs import espec
from fog_driver.lab.controllers.registry import open_controller


@dataclass
class FakeP300:
    """The P-300 as its manual describes it: CR LF lines; TEMP? -> 'PV,SP,upper,lower'; 'TEMP, Sx' ->
    'OK:TEMP, Sx'; MODE? / 'MODE, m' -> 'OK:MODE, m'; ALARM? -> '0' or 'n,c1,..'; errors 'NA:...'."""

    air: float = 23.4
    setpoint: float = 20.0
    upper: float = 100.0
    lower: float = -40.0
    mode: str = "STANDBY"
    alarms: list[int] = field(default_factory=list)
    refuse: str | None = None  # an NA: message every setting gets (local mode)
    mode_error: bool = False

    def __call__(self, line: bytes) -> Reply:
        text = line.decode("ascii")
        if text == "TEMP?":
            return f"{self.air:.1f},{self.setpoint:.1f},{self.upper:.1f},{self.lower:.1f}\r\n".encode()
        if text == "MODE?":
            return b"NA:COMMAND ERR\r\n" if self.mode_error else f"{self.mode}\r\n".encode()
        if text == "ALARM?":
            return (",".join(str(n) for n in [len(self.alarms), *self.alarms]) + "\r\n").encode()
        if self.refuse is not None and text.startswith(("TEMP,", "MODE,")):
            return f"NA:{self.refuse}\r\n".encode()
        if text.startswith("TEMP, S"):
            self.setpoint = float(text[len("TEMP, S") :])
            return f"OK:{text}\r\n".encode()
        if text in ("MODE, CONSTANT", "MODE, STANDBY"):
            self.mode = text.split(", ")[1]
            return f"OK:{text}\r\n".encode()
        return b"NA:COMMAND ERR\r\n"


@pytest.fixture
def chamber():
    fake = FakeP300()
    server = LineServer(fake, b"\r\n")
    yield fake, server
    server.close()


def _open(server, query="", notices=None, overrides=None):
    url = f"espec://127.0.0.1:{server.port}" + (f"?{query}" if query else "")
    sink = notices if notices is not None else []
    controller = open_controller(url, overrides=overrides, on_notice=sink.append, timeout_s=2.0)
    controller.connect()
    return controller


def test_requests_are_the_manuals_command_lines():
    """The manual's frames: 'TEMP?' (monitor), 'TEMP, S20.0' (set the temperature set point), 'MODE?',
    'MODE, CONSTANT', 'MODE, STANDBY', 'ALARM?', each a line ending CR LF."""
    assert espec.encode_read_temp() == b"TEMP?\r\n"
    assert espec.encode_write_setpoint(20.0) == b"TEMP, S20.0\r\n"
    assert espec.encode_write_setpoint(-40.0) == b"TEMP, S-40.0\r\n"
    assert espec.encode_read_mode() == b"MODE?\r\n"
    assert espec.encode_mode("CONSTANT") == b"MODE, CONSTANT\r\n"
    assert espec.encode_mode("STANDBY") == b"MODE, STANDBY\r\n"
    assert espec.encode_read_alarm() == b"ALARM?\r\n"


def test_set_points_are_written_with_one_decimal_rounded_half_away_from_zero():
    assert espec.encode_write_setpoint(20.05) == b"TEMP, S20.1\r\n"
    assert espec.encode_write_setpoint(-20.05) == b"TEMP, S-20.1\r\n"
    assert espec.encode_write_setpoint(20.04) == b"TEMP, S20.0\r\n"
    assert espec.encode_write_setpoint(-0.04) == b"TEMP, S0.0\r\n"


def test_answers_decode_as_the_manual_gives_them():
    """The manual's answers: TEMP? -> '23.4,20.0,100.0,-40.0' (the measured, the set, the upper and the
    lower limit), a setting -> 'OK:TEMP, S20.0', MODE? -> 'CONSTANT', ALARM? -> '0' or '2,3,14'."""
    temp = espec.decode_temp(b"23.4,20.0,100.0,-40.0\r\n")
    assert (temp.air, temp.setpoint, temp.upper, temp.lower) == (23.4, 20.0, 100.0, -40.0)
    assert espec.decode_ok(b"OK:TEMP, S20.0\r\n") == "TEMP, S20.0"
    assert [espec.decode_mode(f"{m}\r\n".encode()) for m in ("CONSTANT", "RUN", "STANDBY", "OFF")] == [
        "constant",
        "program",
        "standby",
        "standby",
    ]
    assert espec.decode_alarm(b"0\r\n") == ()
    assert espec.decode_alarm(b"2,3,14\r\n") == ("alarm 3", "alarm 14")


@pytest.mark.parametrize(
    "reply",
    [b"\xff\xfe\r\n", b"23.4,20.0,100.0\r\n", b"a,b,c,d\r\n", b"23.4,nan,1,2\r\n", b"23.4,20.0,1,2", b"\x0723\r\n"],
)
def test_garbage_to_a_temperature_read_is_a_protocol_error(reply):
    with pytest.raises(ControllerProtocolError):
        espec.decode_temp(reply)


def test_an_na_answer_is_a_protocol_error_naming_its_message():
    with pytest.raises(ControllerProtocolError, match="NA:PARAMETER ERR"):
        espec.decode_ok(b"NA:PARAMETER ERR\r\n")
    with pytest.raises(ControllerProtocolError, match="DATA NOT READY"):
        espec.decode_temp(b"NA:DATA NOT READY\r\n")
    with pytest.raises(ControllerRefused):
        espec.decode_ok(b"NA:CONTROLLER NOT READY-2\r\n")


def test_a_reply_split_at_every_point_reads_the_same(chamber):
    fake, server = chamber
    controller = _open(server)
    assert_every_split_reads_the_same(server, controller.read_setpoint_c, b"23.4,21.5,100.0,-40.0\r\n", 21.5)
    controller.close()


def test_the_driver_reads_writes_starts_and_stops_a_p300(chamber):
    fake, server = chamber
    notices: list[str] = []
    controller = _open(server, notices=notices)
    assert controller.address == f"espec://127.0.0.1:{server.port}"
    assert controller.resolution_c == 0.1
    assert controller.read_air_c() == fake.air
    assert controller.read_setpoint_c() == fake.setpoint
    assert (controller.read_range_c().low_c, controller.read_range_c().high_c) == (fake.lower, fake.upper)
    controller.write_setpoint_c(25.04)
    assert fake.setpoint == 25.0 and fake.mode == "CONSTANT"
    controller.write_setpoint_c(26.0)
    assert server.lines.count(b"MODE, CONSTANT") == 1  # started once per connection
    fake.alarms = [7]
    status = controller.read_status()
    assert (status.state, status.alarms) == ("constant", ("alarm 7",))
    controller.safe_stop()
    assert fake.mode == "STANDBY"
    assert notices == ["espec: the protocol does not say its unit: degC assumed (unit=F if not)"]
    controller.close()


def test_a_controller_in_local_mode_refuses_the_write(chamber):
    fake, server = chamber
    fake.refuse = "CONTROLLER NOT READY-2"
    controller = _open(server)
    with pytest.raises(ControllerRefused, match="NOT READY"):
        controller.write_setpoint_c(25.0)
    assert fake.setpoint == 20.0
    controller.close()


def test_a_controller_set_to_degf_is_read_and_written_in_degc(chamber):
    fake, server = chamber
    fake.air, fake.setpoint, fake.upper, fake.lower = 68.0, 77.0, 212.0, -40.0
    notices: list[str] = []
    controller = _open(server, "unit=F", notices=notices)
    assert controller.read_air_c() == pytest.approx((68.0 - 32.0) * 5.0 / 9.0)
    assert controller.read_setpoint_c() == pytest.approx(25.0)
    assert controller.read_range_c().high_c == pytest.approx(100.0)
    controller.write_setpoint_c(30.0)
    assert fake.setpoint == pytest.approx(c_to_f(30.0))
    assert notices == []
    controller.close()


def test_a_mode_read_answering_an_error_is_state_unknown_said_once(chamber):
    fake, server = chamber
    fake.mode_error = True
    notices: list[str] = []
    controller = _open(server, "unit=C", notices=notices)
    assert controller.read_status().state == "unknown"
    assert controller.read_status().state == "unknown"
    assert len(notices) == 1 and "NA:COMMAND ERR" in notices[0]
    controller.close()


def test_a_connection_dropped_mid_reply_is_unreachable(chamber):
    fake, server = chamber
    controller = _open(server)
    assert_a_drop_mid_reply_is_unreachable(server, controller, controller.read_air_c, b"23.4,20")
    controller.close()


def test_an_endless_reply_is_cut_at_its_bound(chamber):
    fake, server = chamber
    controller = _open(server)
    server.inject(b"1" * 5000)
    with pytest.raises(ControllerUnreachable, match="more than"):
        controller.read_air_c()
    controller.close()


def test_a_misspelt_option_is_refused_and_overrides_yield_to_the_url():
    with pytest.raises(UsageError, match="unknown option unti"):
        open_controller("espec://h?unti=F")
    controller = open_controller("espec://h?unit=C", overrides={"unit": "F"})
    assert controller.resolution_c == 0.1
    with pytest.raises(UsageError, match="baud is for a serial line"):
        open_controller("espec://h?baud=9600")
    controller = open_controller("espec:///dev/ttyUSB1?baud=9600", overrides={"unit": "F"})
    assert controller.address == "/dev/ttyUSB1" and controller.resolution_c < 0.1
