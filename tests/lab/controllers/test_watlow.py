"""The Watlow F4T driver against pymodbus's Modbus server (an independent implementation of the protocol) on
127.0.0.1, its holding registers laid out as the F4T's manual says: degC and degF controllers, loop 2 leaving
loop 1 alone, both word orders, RTU framing, the state, the safe stop, and the URL's options.

The server runs on its own event loop in a thread; each test waits for it to listen (an event set once its
socket is bound), never sleeps.  The expected register contents are computed with ``struct``, not the codec.
"""

from __future__ import annotations

import asyncio
import socket
import struct
import threading
from collections.abc import Iterator

import pytest
from pymodbus.framer import FramerType
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from fog_driver.errors import UsageError
from fog_driver.lab.controllers import registry, watlow
from fog_driver.lab.controllers.base import ChamberController, ControllerProtocolError, ControllerUnreachable
from fog_driver.lab.controllers.codecs import modbus
from fog_driver.lab.controllers.links import StreamLink
from fog_driver.lab.controllers.url import parse_controller_url

UNITS = 1328
PROFILE_STATE = 16568
PROFILE_ACTION = 16566
GUARD_S = 10.0


def loop_registers(loop: int) -> dict[str, int]:
    step = 160 * (loop - 1)
    return {
        "setpoint": 2782 + step,
        "air": 2820 + step,
        "low": 2774 + step,
        "high": 2776 + step,
        "mode": 2730 + step,
    }


def float_words(value: float, word_order: str = "low") -> list[int]:
    high, low = struct.unpack(">HH", struct.pack(">f", value))
    return [low, high] if word_order == "low" else [high, low]


def words_float(words: list[int], word_order: str = "low") -> float:
    low, high = words if word_order == "low" else words[::-1]
    return struct.unpack(">f", struct.pack(">HH", high, low))[0]


def chamber_registers(
    *,
    loops: dict[int, dict[str, float]],
    units: int | None = 15,
    word_order: str = "low",
    profile_state: int | None = 61,
    control_mode: int | None = 10,
) -> dict[int, int]:
    """A register image: per loop its set point, air and range (in the controller's unit)."""
    image: dict[int, int] = {}
    for loop, values in loops.items():
        at = loop_registers(loop)
        for name, value in values.items():
            words = float_words(value, word_order)
            image[at[name]], image[at[name] + 1] = words
        if control_mode is not None:
            image[at["mode"]] = control_mode
    if units is not None:
        image[UNITS] = units
    if profile_state is not None:
        image[PROFILE_STATE] = profile_state
        image[PROFILE_ACTION] = 0
    return image


class ModbusServer:
    """pymodbus's TCP server on 127.0.0.1 (an ephemeral port) holding ``image`` for unit ``unit``."""

    def __init__(self, image: dict[int, int], *, unit: int = 1, framer: FramerType = FramerType.SOCKET) -> None:
        # one register per SimData: an address the image does not hold answers exception 2 (illegal address)
        registers = [SimData(address=a, values=v, datatype=DataType.REGISTERS) for a, v in sorted(image.items())]
        self.device = SimDevice(id=unit, simdata=registers)
        self.unit = unit
        self.framer = framer
        self.requests: list[bytes] = []  # every frame the server received, as pymodbus traces it
        self.port = 0
        self._ready = threading.Event()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._server: ModbusTcpServer | None = None
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _trace(self, sending: bool, data: bytes) -> bytes:
        if not sending:
            self.requests.append(bytes(data))
        return data

    def _run(self) -> None:
        asyncio.run(self._serve())

    async def _serve(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        self._server = ModbusTcpServer(
            self.device, framer=self.framer, address=("127.0.0.1", 0), trace_packet=self._trace
        )
        await self._server.listen()
        self.port = self._server.transport.sockets[0].getsockname()[1]
        self._ready.set()
        await self._stop.wait()
        await self._server.shutdown()

    def __enter__(self) -> ModbusServer:
        self._thread.start()
        assert self._ready.wait(GUARD_S), "the Modbus server did not start"
        return self

    def __exit__(self, *exc: object) -> None:
        assert self._loop is not None and self._stop is not None
        self._loop.call_soon_threadsafe(self._stop.set)
        self._thread.join(GUARD_S)

    def words(self, address: int, count: int = 2) -> list[int]:
        """The registers as the server holds them (asked on its own loop)."""
        assert self._loop is not None and self._server is not None
        future = asyncio.run_coroutine_threadsafe(
            self._server.async_getValues(self.unit, 3, address, count), self._loop
        )
        return list(future.result(GUARD_S))

    def set_word(self, address: int, value: int) -> None:
        assert self._loop is not None and self._server is not None
        future = asyncio.run_coroutine_threadsafe(
            self._server.async_setValues(self.unit, 16, address, [value]), self._loop
        )
        future.result(GUARD_S)

    def float_at(self, address: int, word_order: str = "low") -> float:
        return words_float(self.words(address), word_order)


@pytest.fixture
def notices() -> list[str]:
    return []


def _open(server: ModbusServer, notices: list[str], query: str = "", overrides: dict | None = None):
    url = f"watlow-f4t://127.0.0.1:{server.port}" + (f"?{query}" if query else "")
    controller = registry.open_controller(url, overrides=overrides, on_notice=notices.append, timeout_s=GUARD_S)
    controller.connect()
    return controller


@pytest.fixture
def celsius_chamber() -> Iterator[ModbusServer]:
    image = chamber_registers(loops={1: {"setpoint": 23.0, "air": 21.25, "low": -40.0, "high": 180.0}})
    with ModbusServer(image) as server:
        yield server


def test_a_celsius_f4t_reads_its_air_set_point_and_range_and_takes_a_set_point(celsius_chamber, notices):
    controller = _open(celsius_chamber, notices)
    try:
        assert isinstance(controller, ChamberController)
        assert controller.read_air_c() == 21.25
        assert controller.read_setpoint_c() == 23.0
        chamber_range = controller.read_range_c()
        assert (chamber_range.low_c, chamber_range.high_c) == (-40.0, 180.0)
        controller.write_setpoint_c(37.5)
        assert celsius_chamber.float_at(2782) == 37.5
        assert controller.read_setpoint_c() == 37.5
        assert controller.read_status().state == "constant"
        controller.safe_stop()
    finally:
        controller.close()
    assert notices == []
    functions = {frame[7] for frame in celsius_chamber.requests}  # the MBAP header is 7 bytes
    assert functions == {3, 16}  # never function 6


def test_a_fahrenheit_f4t_is_read_and_written_in_degf_and_seen_in_degc(notices):
    image = chamber_registers(loops={1: {"setpoint": 77.0, "air": 68.0, "low": -40.0, "high": 356.0}}, units=30)
    with ModbusServer(image) as server:
        controller = _open(server, notices)
        assert controller.read_air_c() == pytest.approx((68.0 - 32.0) * 5.0 / 9.0, abs=1e-9)
        assert controller.read_setpoint_c() == pytest.approx(25.0, abs=1e-9)
        chamber_range = controller.read_range_c()
        assert chamber_range.low_c == pytest.approx(-40.0, abs=1e-9)
        assert chamber_range.high_c == pytest.approx(180.0, abs=1e-9)
        controller.write_setpoint_c(30.0)
        assert server.float_at(2782) == pytest.approx(86.0, abs=1e-4)
        assert abs(controller.read_setpoint_c() - 30.0) < controller.resolution_c / 2
        controller.close()
    assert notices == []


def test_driving_loop_2_leaves_loop_1_alone(notices):
    loop1 = {"setpoint": 23.0, "air": 22.0, "low": -40.0, "high": 180.0}
    loop2 = {"setpoint": 50.0, "air": 45.0, "low": 10.0, "high": 95.0}
    with ModbusServer(chamber_registers(loops={1: loop1, 2: loop2})) as server:
        loop1_addresses = list(chamber_registers(loops={1: loop1}, units=None, profile_state=None))
        before = {address: server.words(address, 1)[0] for address in loop1_addresses}
        controller = _open(server, notices, "loop=2")
        assert controller.read_air_c() == 45.0
        assert (controller.read_range_c().low_c, controller.read_range_c().high_c) == (10.0, 95.0)
        controller.write_setpoint_c(60.0)
        controller.safe_stop()
        assert server.float_at(2782 + 160) == 60.0
        assert server.words(2730 + 160, 1) == [62]
        assert {address: server.words(address, 1)[0] for address in loop1_addresses} == before
        assert controller.address == f"watlow-f4t://127.0.0.1:{server.port}/1/2"
        controller.close()


def test_a_controller_set_to_high_word_first_is_read_with_word_order_high(notices):
    image = chamber_registers(
        loops={1: {"setpoint": -12.5, "air": -10.125, "low": -70.0, "high": 150.0}}, word_order="high"
    )
    with ModbusServer(image) as server:
        controller = _open(server, notices, "word_order=high")
        assert controller.read_air_c() == -10.125
        assert controller.read_setpoint_c() == -12.5
        controller.write_setpoint_c(-20.0)
        assert server.words(2782) == float_words(-20.0, "high")
        controller.close()
        wrong = _open(server, notices)  # the default low word order misreads it: proof the option matters
        assert wrong.read_setpoint_c() != -20.0
        wrong.close()


def test_the_rtu_framing_is_understood_by_pymodbus_s_rtu_framer(notices):
    image = chamber_registers(loops={1: {"setpoint": 23.0, "air": 21.5, "low": -40.0, "high": 180.0}})
    with ModbusServer(image, unit=7, framer=FramerType.RTU) as server:
        registers = watlow.open_controller(
            parse_controller_url("watlow-f4t+rtu:///dev/ttyUSB1?unit=7"),
            overrides={},
            on_notice=notices.append,
            timeout_s=GUARD_S,
        ).registers
        link = StreamLink(where="rtu over tcp", host="127.0.0.1", port=server.port, timeout_s=GUARD_S)
        controller = watlow.WatlowF4T(
            url="test",
            address="test",
            link=link,
            framer=modbus.RtuFramer(7),
            registers=registers,
            resolution_c=0.01,
            on_notice=notices.append,
        )
        controller.connect()
        assert controller.read_air_c() == 21.5
        controller.write_setpoint_c(40.0)
        assert server.float_at(2782) == 40.0
        controller.close()


def test_a_running_profile_is_state_program_and_the_safe_stop_terminates_it_then_goes_standby(notices):
    image = chamber_registers(
        loops={1: {"setpoint": 23.0, "air": 21.5, "low": -40.0, "high": 180.0}}, profile_state=149
    )
    with ModbusServer(image) as server:
        controller = _open(server, notices)
        assert controller.read_status().state == "program"
        controller.safe_stop()
        assert server.words(PROFILE_ACTION, 1) == [148]
        assert server.words(2730, 1) == [62]
        server.set_word(PROFILE_STATE, 253)  # terminated
        assert controller.read_status().state == "standby"
        controller.close()


def test_a_controller_refusing_the_state_reads_is_state_unknown_said_once(notices):
    image = chamber_registers(
        loops={1: {"setpoint": 23.0, "air": 21.5, "low": -40.0, "high": 180.0}}, profile_state=None, control_mode=None
    )
    with ModbusServer(image) as server:
        controller = _open(server, notices)
        assert [controller.read_status().state for _ in range(3)] == ["unknown"] * 3
        assert len(notices) == 2, notices  # the profile state's exception, the control mode's: each once
        assert all("illegal data address" in line and "unknown" in line for line in notices)
        assert controller.read_air_c() == 21.5  # the link stays up after an exception reply
        controller.close()


def test_a_controller_without_the_unit_register_is_taken_as_degc_said_once(notices):
    image = chamber_registers(loops={1: {"setpoint": 23.0, "air": 21.5, "low": -40.0, "high": 180.0}}, units=None)
    with ModbusServer(image) as server:
        controller = _open(server, notices)
        controller.close()
        controller.connect()  # a reconnection does not say it again
        assert controller.read_air_c() == 21.5
        controller.close()
    assert len(notices) == 1 and "degC" in notices[0] and "illegal data address" in notices[0]


def test_units_register_none_assumes_degc_and_says_so(celsius_chamber, notices):
    controller = _open(celsius_chamber, notices, "units_register=none")
    assert controller.read_air_c() == 21.25
    controller.close()
    assert len(notices) == 1 and "degC" in notices[0]


def test_an_exception_to_a_required_read_is_one_line_naming_it(notices):
    image = chamber_registers(loops={1: {"setpoint": 23.0, "low": -40.0, "high": 180.0}})
    with ModbusServer(image) as server:
        controller = _open(server, notices)
        with pytest.raises(ControllerProtocolError) as caught:
            controller.read_air_c()
        message = str(caught.value)
        assert "illegal data address" in message and "2820" in message and "\n" not in message
        controller.close()


def test_a_register_moved_on_the_controller_is_found_with_an_override(celsius_chamber, notices):
    controller = _open(celsius_chamber, notices, overrides={"air_register": 2782})
    assert controller.read_air_c() == 23.0  # the set point's registers, as told
    controller.close()
    url_wins = _open(celsius_chamber, notices, "air_register=2820", overrides={"air_register": 2782})
    assert url_wins.read_air_c() == 21.25
    url_wins.close()


def test_a_controller_nobody_listens_for_is_unreachable(notices):
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    controller = registry.open_controller(f"watlow-f4t://127.0.0.1:{port}", on_notice=notices.append, timeout_s=2.0)
    with pytest.raises(ControllerUnreachable, match="cannot connect"):
        controller.connect()
    with pytest.raises(ControllerUnreachable, match="not connected"):
        controller.read_air_c()


@pytest.mark.parametrize(
    ("url", "message"),
    [
        ("watlow-f4t://chamber?colour=red", "unknown option colour"),
        ("watlow-f4t://chamber?baud=9600", "unknown option baud"),
        ("watlow-f4t://chamber?word_order=big", "bad word_order"),
        ("watlow-f4t://chamber?loop=5", "bad loop"),
        ("watlow-f4t://chamber?unit=x", "bad unit"),
        ("watlow-f4t+rtu:///dev/ttyUSB1?unit=0", "bad unit"),
        ("watlow-f4t+rtu:///dev/ttyUSB1?baud=fast", "bad baud"),
        ("watlow-f4t://chamber?setpoint_register=70000", "bad setpoint_register"),
        ("watlow-f4t://chamber?resolution_c=0", "bad resolution_c"),
        ("watlow-f4t+rtu://chamber", "takes a serial device"),
        ("watlow-f4t:///dev/ttyUSB1", "takes a host"),
    ],
)
def test_a_bad_url_option_is_one_usage_line(url, message):
    with pytest.raises(UsageError, match=message) as caught:
        registry.open_controller(url)
    assert "\n" not in str(caught.value)


def test_an_unknown_setting_in_the_config_is_one_usage_line():
    with pytest.raises(UsageError, match="unknown setting colour"):
        registry.open_controller("watlow-f4t://chamber", overrides={"colour": "red"})


def test_the_urls_options_name_the_controller_and_its_lock_address():
    tcp = registry.open_controller("watlow-f4t://chamber.lab?unit=3&loop=2&word_order=high&resolution_c=0.1")
    assert isinstance(tcp, watlow.WatlowF4T)
    assert tcp.address == "watlow-f4t://chamber.lab:502/3/2"
    assert tcp.registers.setpoint == 2782 + 160 and tcp.registers.word_order == "high" and tcp.resolution_c == 0.1
    rtu = registry.open_controller("watlow-f4t+rtu:///dev/ttyUSB1?baud=38400&unit=2", overrides={"loop": 3})
    assert isinstance(rtu, watlow.WatlowF4T)
    assert rtu.address == "watlow-f4t+rtu:///dev/ttyUSB1/2"
    assert rtu.registers.process_value == 2820 + 320
    explicit_port = registry.open_controller("watlow-f4t://10.0.0.5:1502")
    assert explicit_port.address == "watlow-f4t://10.0.0.5:1502/1/1"


class RawPeer:
    """A TCP peer on 127.0.0.1 that reads one request and answers it with ``answer(request)`` bytes, then
    closes (garbage, a reply cut off)."""

    def __init__(self, answer) -> None:
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.port = self.listener.getsockname()[1]
        self.answer = answer
        self._thread = threading.Thread(target=self._serve, daemon=True)

    def _serve(self) -> None:
        connection, _ = self.listener.accept()
        with connection:
            request = connection.recv(260)
            connection.sendall(self.answer(request))

    def __enter__(self) -> RawPeer:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._thread.join(GUARD_S)
        self.listener.close()


def test_a_garbage_reply_is_one_protocol_line_and_drops_the_link(notices):
    def garbage(request: bytes) -> bytes:
        return request[:2] + b"\x00\x00\x00\x05\x01\x2b\x0e\x01\x01"  # a function 43 reply to a read

    with RawPeer(garbage) as peer:
        controller = registry.open_controller(
            f"watlow-f4t://127.0.0.1:{peer.port}?units_register=none", on_notice=notices.append, timeout_s=GUARD_S
        )
        controller.connect()
        with pytest.raises(ControllerProtocolError) as caught:
            controller.read_air_c()
        assert "function 43" in str(caught.value) and "\n" not in str(caught.value)
        with pytest.raises(ControllerUnreachable, match="not connected"):
            controller.read_air_c()


def test_a_reply_cut_off_by_the_controller_closing_is_a_lost_link(notices):
    def half(request: bytes) -> bytes:
        return request[:2] + b"\x00\x00\x00\x07\x01\x03\x04\x00"  # 4 of the 7 bytes announced

    with RawPeer(half) as peer:
        controller = registry.open_controller(
            f"watlow-f4t://127.0.0.1:{peer.port}?units_register=none", on_notice=notices.append, timeout_s=GUARD_S
        )
        controller.connect()
        with pytest.raises(ControllerUnreachable, match="link lost"):
            controller.read_setpoint_c()


def test_a_serial_device_that_is_not_there_is_unreachable(tmp_path, notices):
    missing = tmp_path / "ttyUSB9"
    controller = registry.open_controller(f"watlow-f4t+rtu://{missing}?unit=1", on_notice=notices.append)
    with pytest.raises(ControllerUnreachable, match="cannot connect") as caught:
        controller.connect()
    assert str(missing) in str(caught.value) and "\n" not in str(caught.value)
