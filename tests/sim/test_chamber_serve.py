"""The served chambers answer their protocols' frames (raw bytes written here from the manuals; pymodbus's client
for the Watlow F4T), the faults do what they say, and ``simulate --serve pty --chamber-serve`` couples the
instrument's temperatures to the served chamber's air."""

from __future__ import annotations

import logging
import socket
import struct
from collections.abc import Iterator

import numpy as np
import pytest
from readerthread import Reader
from sim_serving import GUARD_S, _next_line, _start_cli

from fog_driver.errors import UsageError
from fog_driver.protocol import THERMOMETER_COUNTS_PER_C, decode_bytes
from fog_driver.sim.chamber import ChamberParams, SimChamber
from fog_driver.sim.chamber_serve import ChamberFaults, ChamberServer, serve_chamber


class FakeClock:
    def __init__(self) -> None:
        self.t_s = 0.0

    def __call__(self) -> float:
        return self.t_s


@pytest.fixture
def clock() -> FakeClock:
    return FakeClock()


@pytest.fixture
def chamber(clock: FakeClock) -> SimChamber:
    return SimChamber(clock, ChamberParams(start_c=20.0, rate_c_per_min=0.0, tau_s=0.0, low_c=-40.0, high_c=150.0))


def served(scheme: str, chamber: SimChamber, faults: ChamberFaults | None = None, query: str = "") -> ChamberServer:
    return serve_chamber(f"{scheme}://127.0.0.1:0{query}", chamber, faults)


def ask(server: ChamberServer, request: bytes, ending: bytes = b"\r\n") -> bytes:
    """One request, the reply up to ``ending`` (or up to the server's close)."""
    with socket.create_connection((server.host, server.port), timeout=GUARD_S) as sock:
        sock.sendall(request)
        reply = b""
        while not reply.endswith(ending):
            chunk = sock.recv(256)
            if not chunk:
                break
            reply += chunk
    return reply


@pytest.fixture
def servers() -> Iterator[list[ChamberServer]]:
    running: list[ChamberServer] = []
    yield running
    for server in running:
        server.stop()


def test_espec_answers_temp_mode_and_refuses_unknown_commands(chamber: SimChamber, clock: FakeClock, servers) -> None:
    server = served("espec", chamber)
    servers.append(server)
    assert server.url.startswith("espec://127.0.0.1:") and server.port > 0
    assert ask(server, b"TEMP?\r\n") == b"20.0,20.0,150.0,-40.0\r\n"
    assert ask(server, b"TEMP, S35.5\r\n") == b"OK: TEMP, S35.5\r\n"
    clock.t_s = 1.0
    assert ask(server, b"TEMP?\r\n") == b"35.5,35.5,150.0,-40.0\r\n"
    assert chamber.setpoint_c() == 35.5
    assert ask(server, b"MODE?\r\n") == b"CONSTANT\r\n"
    assert ask(server, b"MODE, STANDBY\r\n") == b"OK: MODE, STANDBY\r\n"
    assert ask(server, b"MODE?\r\n") == b"STANDBY\r\n"
    assert ask(server, b"TEMP, S200.0\r\n").startswith(b"NA:")
    assert ask(server, b"HELLO\r\n").startswith(b"NA:")


def test_espec_in_fahrenheit_speaks_degf(clock: FakeClock, servers) -> None:
    chamber = SimChamber(clock, ChamberParams(start_c=20.0, rate_c_per_min=0.0, tau_s=0.0, unit="F"))
    server = served("espec", chamber)
    servers.append(server)
    assert ask(server, b"TEMP?\r\n") == b"68.0,68.0,356.0,-94.0\r\n"  # 20, 20, 180, -70 degC
    ask(server, b"TEMP, S212.0\r\n")
    assert chamber.setpoint_c() == pytest.approx(100.0)


def test_thermotron_answers_pvar_setp_and_status(chamber: SimChamber, clock: FakeClock, servers) -> None:
    """The 8200 manual's forms: lines end CR; a query answers its value (``PVAR1?`` -> ``22.000``), a setting
    with data its value set (``SETP1,22.000`` -> ``22.000``); ``RUNM`` and ``STOP`` answer nothing (the next
    query's answer is the next line); ``SCOD?`` 0 stopped, 1 running manual."""
    server = served("thermotron", chamber)
    servers.append(server)
    assert ask(server, b"PVAR1?\r", b"\r") == b"20.000\r"
    assert ask(server, b"SETP1,-12.5\r", b"\r") == b"-12.500\r"
    assert ask(server, b"MRMP1,2.0\r", b"\r") == b"2.000\r"
    assert ask(server, b"SETP1?\r", b"\r") == b"-12.500\r"
    clock.t_s = 5.0
    assert ask(server, b"PVAR1?\r", b"\r") == b"-12.500\r"
    assert ask(server, b"RUNM\rSCOD?\r", b"\r") == b"1\r"
    assert ask(server, b"STOP\rSCOD?\r", b"\r") == b"0\r"
    assert ask(server, b"XYZZY\r", b"\r") == b"?\r"


def test_simserv_answers_its_0xb6_separated_commands(chamber: SimChamber, clock: FakeClock, servers) -> None:
    server = served("simserv", chamber)
    servers.append(server)
    sep = b"\xb6"
    assert ask(server, b"11004" + sep + b"1" + sep + b"1\r") == b"1" + sep + b"20.0\r\n"
    assert ask(server, sep.join([b"11001", b"1", b"1", b"45.0"]) + b"\r") == b"1\r\n"
    assert ask(server, b"11002" + sep + b"1" + sep + b"1\r") == b"1" + sep + b"45.0\r\n"
    assert (
        ask(server, b"11007" + sep + b"1" + sep + b"1\r") == b"1" + sep + f"{chamber.range_c().low_c:.1f}\r\n".encode()
    )  # the lower limit
    assert (
        ask(server, b"11009" + sep + b"1" + sep + b"1\r") == b"1" + sep + f"{chamber.range_c().high_c:.1f}\r\n".encode()
    )  # the upper limit
    assert ask(server, b"14001" + sep + b"1" + sep + b"0\r") == b"1\r\n"
    assert chamber.mode == "standby"
    assert ask(server, b"14001" + sep + b"1" + sep + b"1\r") == b"1\r\n"
    assert chamber.mode == "constant"
    assert ask(server, b"99999\r") == b"-5\r\n"


def _f32_low_first(value: float) -> list[int]:
    high, low = struct.unpack(">HH", struct.pack(">f", value))
    return [low, high]


def _from_low_first(words: list[int]) -> float:
    return struct.unpack(">f", struct.pack(">HH", words[1], words[0]))[0]


def test_watlow_f4t_reads_and_writes_its_registers_over_modbus_tcp(chamber, clock: FakeClock, servers) -> None:
    from pymodbus.client import ModbusTcpClient

    faults = ChamberFaults()
    server = served("watlow-f4t", chamber, faults)
    servers.append(server)
    client = ModbusTcpClient(server.host, port=server.port, timeout=GUARD_S)
    assert client.connect()
    try:
        low_high = client.read_holding_registers(2774, count=4).registers
        assert _from_low_first(low_high[0:2]) == -40.0 and _from_low_first(low_high[2:4]) == 150.0
        assert not client.write_registers(2782, _f32_low_first(55.0)).isError()
        assert chamber.setpoint_c() == 55.0
        clock.t_s = 3.0
        assert _from_low_first(client.read_holding_registers(2820, count=2).registers) == 55.0
        assert _from_low_first(client.read_holding_registers(2782, count=2).registers) == 55.0
        faults.exception_code = 4
        reply = client.read_holding_registers(2820, count=2)
        assert reply.isError() and reply.exception_code == 4
        faults.exception_code = None
        faults.local = True
        reply = client.write_registers(2782, _f32_low_first(10.0))
        assert reply.isError() and chamber.setpoint_c() == 55.0
    finally:
        client.close()


def test_watlow_f4t_with_the_high_word_first(chamber: SimChamber, servers) -> None:
    from pymodbus.client import ModbusTcpClient

    server = served("watlow-f4t", chamber, query="?word_order=high")
    servers.append(server)
    client = ModbusTcpClient(server.host, port=server.port, timeout=GUARD_S)
    assert client.connect()
    try:
        words = client.read_holding_registers(2782, count=2).registers
        assert struct.unpack(">f", struct.pack(">HH", *words))[0] == 20.0
    finally:
        client.close()


def test_faults_garbage_a_dropped_reply_a_delay_and_local_mode(chamber: SimChamber, servers) -> None:
    faults = ChamberFaults()
    server = served("espec", chamber, faults)
    servers.append(server)
    faults.garbage = True
    reply = ask(server, b"TEMP?\r\n")
    assert (
        reply != b"20.0,20.0,150.0,-40.0\r\n"
        and not reply.rstrip(b"\r\n").replace(b",", b"").replace(b".", b"").isdigit()
    )
    faults.garbage = False
    faults.drop_mid_reply = True
    whole = b"20.0,20.0,150.0,-40.0\r\n"
    cut = ask(server, b"TEMP?\r\n")
    assert 0 < len(cut) < len(whole) and whole.startswith(cut)  # half the reply, then the close
    faults.drop_mid_reply = False
    faults.delay_s = 0.05
    assert ask(server, b"TEMP?\r\n") == whole  # late, but whole
    faults.delay_s = 0.0
    faults.local = True
    assert ask(server, b"TEMP, S30.0\r\n").startswith(b"NA:") and chamber.setpoint_c() == 20.0
    faults.local = False
    faults.exception_code = 1
    assert ask(server, b"TEMP?\r\n").startswith(b"NA:")


@pytest.mark.parametrize("url", ["modbus://127.0.0.1:0", "espec://127.0.0.1:0?bogus=1", "espec:///dev/ttyUSB0"])
def test_serving_an_unknown_scheme_or_option_is_a_usage_error(chamber: SimChamber, url: str) -> None:
    with pytest.raises(UsageError):
        serve_chamber(url, chamber)


def test_simulate_with_a_served_chamber_moves_the_instruments_temperatures_towards_its_set_point(tmp_path) -> None:
    link = tmp_path / "ttyFOG0"
    proc, lines = _start_cli(  # the short-test profile holds 20 degC for its first 5 minutes
        "--chamber-serve",
        "espec://127.0.0.1:0?rate_c_per_min=60&tau_s=5",
        "--speed",
        "50",
        "--duration",
        "600",
        link=link,
    )
    reader = None
    try:
        chamber_line = _next_line(proc, lines)
        assert chamber_line.startswith("serving the chamber on espec://127.0.0.1:")
        host, port = chamber_line.rsplit("//", 1)[1].strip().split(":")
        assert _next_line(proc, lines).startswith("serving short-test")
        reader = Reader(str(link), reconnect=False)
        assert reader.opened.wait(GUARD_S)
        with socket.create_connection((host, int(port)), timeout=GUARD_S) as sock:
            sock.sendall(b"TEMP, S60.0\r\n")
            assert sock.recv(64) == b"OK: TEMP, S60.0\r\n"
        received = b""
        first_housing_c = None
        while True:  # until the housing thermometer has warmed by 2 degC (the profile alone holds 20 degC)
            kind, item = reader.items.get(timeout=GUARD_S)
            assert kind != "state" or item.state in ("opening", "open"), f"stream ended early: {item}"
            if kind != "data":
                continue
            received += item
            samples = decode_bytes(received).samples
            if len(samples) < 10:
                continue
            housing_c = samples.t_housing_raw.astype(float) / THERMOMETER_COUNTS_PER_C
            if first_housing_c is None:
                first_housing_c = float(np.median(housing_c[:10]))
                assert abs(first_housing_c - 20.0) < 1.0
            if housing_c[-1] > first_housing_c + 2.0:
                break
            received = received[-4096:] if len(received) > 1 << 20 else received
        with socket.create_connection((host, int(port)), timeout=GUARD_S) as sock:
            sock.sendall(b"TEMP?\r\n")
            air_c = float(sock.recv(64).split(b",")[0])
        assert air_c > first_housing_c + 2.0  # the air leads the instrument towards the set point
    finally:
        if reader is not None:
            reader.stop.set()
        proc.terminate()
        proc.wait(GUARD_S)
        while lines.get(timeout=GUARD_S) is not None:  # the pump has read to the end of stdout
            pass
        proc.stdout.close()
        proc.stderr.close()


def _mbap_read(transaction: int, address: int, count: int) -> bytes:
    """A Modbus TCP request, function 3, unit 1 (MBAP: transaction, protocol 0, length, unit; PDU)."""
    pdu = struct.pack(">BHH", 3, address, count)
    return struct.pack(">HHHB", transaction, 0, len(pdu) + 1, 1) + pdu


def test_watlow_f4t_faults_garbage_and_a_dropped_reply(chamber: SimChamber, servers) -> None:
    faults = ChamberFaults()
    server = served("watlow-f4t", chamber, faults)
    servers.append(server)
    with socket.create_connection((server.host, server.port), timeout=GUARD_S) as sock:
        sock.sendall(_mbap_read(7, 2820, 2))
        whole = b""
        while len(whole) < 13:  # MBAP 7 + fc, byte count, 4 bytes
            whole += sock.recv(64)
        assert whole[:2] == b"\x00\x07" and whole[7:9] == b"\x03\x04"
        assert struct.unpack(">f", whole[11:13] + whole[9:11])[0] == 20.0  # low word first
        faults.garbage = True
        sock.sendall(_mbap_read(8, 2820, 2))
        junk = b""
        while len(junk) < 13:
            junk += sock.recv(64)
        assert len(junk) == 13 and junk != whole and junk[:2] != b"\x00\x08"
    faults.garbage = False
    faults.drop_mid_reply = True
    with socket.create_connection((server.host, server.port), timeout=GUARD_S) as sock:
        sock.sendall(_mbap_read(9, 2820, 2))
        cut = b""
        while chunk := sock.recv(64):
            cut += chunk
        assert cut == b"\x00\x09\x00\x00\x00\x07"[: len(cut)] and 0 < len(cut) < 13


@pytest.mark.parametrize("scheme", ["watlow-f4t", "espec"])
def test_a_server_stopped_with_a_client_connected_logs_no_traceback(
    scheme: str, chamber: SimChamber, caplog: pytest.LogCaptureFixture
) -> None:
    """Stopping the simulated lab (Ctrl-C) while a driver is connected ends its connections quietly: Python
    3.11's stream callback would log a cancelled handler's CancelledError with a traceback."""
    from fog_driver.offline.chamber import open_lab_controller

    caplog.set_level(logging.ERROR, logger="asyncio")
    server = served(scheme, chamber)
    controller = open_lab_controller(server.url, on_notice=lambda line: None)
    controller.connect()
    assert controller.read_air_c() == pytest.approx(chamber.air_c(), abs=0.05)
    server.stop()
    controller.close()
    assert [record.getMessage() for record in caplog.records if record.name == "asyncio"] == []
