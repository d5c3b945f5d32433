"""Servers that speak a chamber controller's protocol on a socket, driving a ``SimChamber``.

Built from the vendors' manuals (as the issue quotes them), independently of the client codecs in
``fog_driver/lab/controllers/codecs`` (not imported: a test of client against server can fail):

- ``espec://HOST:PORT`` (Espec P300 / SCP-220): ASCII lines ending CR LF.  ``TEMP?`` -> ``PV,SP,upper,lower``
  (one decimal); ``TEMP, S20.0`` -> ``OK: TEMP, S20.0``; ``MODE?`` -> ``CONSTANT`` | ``STANDBY``;
  ``MODE, CONSTANT`` | ``MODE, STANDBY`` -> ``OK: MODE, ...``; anything else, a set point outside the range, or
  a write in local mode -> ``NA:...``.
- ``thermotron://HOST:PORT`` (8800/8200): commands end CR (a LF is ignored), replies end CR LF.  ``PVAR1?`` ->
  the air; ``SETP1?`` -> the set point; ``SETP1,20.0`` / ``MRMP1,rate`` / ``RUNM`` / ``HOLD`` / ``STOP`` -> ``0``
  (accepted; ``MRMP1`` is accepted and ignored: the simulated chamber's rate is its own); ``SCOD?`` -> the
  status code (0 stop, 2 run manual, 8 hold); an unknown command, or a write in local mode -> ``?``.
- ``simserv://HOST:PORT`` (Weiss / Voetsch SIMSERV): fields separated by byte 0xB6, a request ends CR, a reply
  ends CR LF.  ``11001¶1¶1¶VALUE`` sets the set point of chamber 1, value 1 -> ``1``; ``11002¶1¶1`` -> ``1¶SP``;
  ``11004¶1¶1`` -> ``1¶PV``; ``14001¶1¶1`` (manual mode on) -> ``1``; an unknown command -> ``-5``; a write
  refused (local mode, out of range) -> ``-6``.  (The reply's first field is the status: 1 = done.)
- ``watlow-f4t://HOST:PORT`` (Watlow F4T, Modbus TCP) on pymodbus's server: holding registers (0-based), loop
  N: set point 2782 + 160(N-1), process value 2820 + 160(N-1), range low 2774 + 160(N-1), high 2776 + 160(N-1),
  each a 32-bit IEEE float in two registers, the low word first (``?word_order=high`` for high first); the set
  point is written with function 16 (two registers); loop 1 only is driven (the other loops read 0).  Reads of
  the process value come from the chamber's air at that moment.

Temperatures on the wire are in the chamber's unit (``ChamberParams.unit``: C or F).  Every server binds to
127.0.0.1 unless the URL names a host; port 0 picks a free port (the bound one is in ``ChamberServer.url``).

``ChamberFaults`` (mutable while the server runs, for the tests): ``exception_code`` (Modbus: every request
answers that exception code; the ASCII ones answer their error reply), ``garbage`` (a reply of bytes that are
none), ``drop_mid_reply`` (half the reply, then the connection closed), ``delay_s`` (each reply that late),
``local`` (remote writes refused, as a controller in local mode).
"""

from __future__ import annotations

import asyncio
import struct
import threading
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from ..errors import DeviceError, UsageError
from ..lab.controllers.base import ControllerRefused, c_to_f, f_to_c
from ..lab.controllers.url import ControllerURL, parse_controller_url
from .chamber import COUPLED_BLOCK_STEPS, ChamberAir, ChamberParams, SimChamber, StartedClock
from .instrument import Simulator

SERVED_SCHEMES = ("espec", "thermotron", "simserv", "watlow-f4t")
MAX_LINE_BYTES = 256
GARBAGE = b"\x00\xff#garbage#\xfe"
F4T_SETPOINT = 2782
F4T_PV = 2820
F4T_RANGE_LOW = 2774
F4T_RANGE_HIGH = 2776
F4T_LOOP_STRIDE = 160
# One-register values (the F4T user's guide's Modbus map, 0600-0093-0000): the display unit (F 30, C 15), loop 1's
# control mode (Off 62, Auto 10, Manual 54), the profile's state (149 running, 146 paused; the chamber runs none)
# and the profile action (148 terminate).
F4T_DISPLAY_UNITS = 1328
F4T_CONTROL_MODE = 2730
F4T_PROFILE_STATE = 16568
F4T_PROFILE_ACTION = 16566
F4T_MODE_OFF, F4T_MODE_AUTO, F4T_MODE_MANUAL = 62, 10, 54
F4T_PROFILE_IDLE = 0
SIMSERV_SEP = "\xb6"


@dataclass
class ChamberFaults:
    """What a served chamber does wrong (all off by default); changeable while it runs."""

    exception_code: int | None = None
    garbage: bool = False
    drop_mid_reply: bool = False
    delay_s: float = 0.0
    local: bool = False


class _Wire:
    """The chamber seen in its unit, with the local-mode fault applied to writes."""

    def __init__(self, chamber: SimChamber, faults: ChamberFaults) -> None:
        self.chamber = chamber
        self.faults = faults
        self.in_f = chamber.params.unit == "F"

    def out(self, value_c: float) -> float:
        return c_to_f(value_c) if self.in_f else value_c

    def air(self) -> float:
        return self.out(self.chamber.air_c())

    def setpoint(self) -> float:
        return self.out(self.chamber.setpoint_c())

    def low(self) -> float:
        return self.out(self.chamber.params.low_c)

    def high(self) -> float:
        return self.out(self.chamber.params.high_c)

    def write(self, value: float) -> None:
        """``ControllerRefused`` (local) or ``ValueError`` (outside the range)."""
        if self.faults.local:
            raise ControllerRefused("local mode")
        self.chamber.write_setpoint_c(f_to_c(value) if self.in_f else value)


def _espec(wire: _Wire, line: str) -> str:
    text = line.strip()
    compact = text.replace(" ", "").upper()
    if compact == "TEMP?":
        return f"{wire.air():.1f},{wire.setpoint():.1f},{wire.high():.1f},{wire.low():.1f}"
    if compact == "MODE?":
        return "STANDBY" if wire.chamber.mode == "standby" else "CONSTANT"
    try:
        if compact.startswith("TEMP,S"):
            wire.write(float(compact[len("TEMP,S") :]))
            return f"OK: {text}"
        if compact in ("MODE,CONSTANT", "MODE,STANDBY"):
            if wire.faults.local:
                raise ControllerRefused("local mode")
            wire.chamber.set_mode("constant" if compact.endswith("CONSTANT") else "standby")
            return f"OK: {text}"
    except ControllerRefused:
        return "NA:CONTROLLER NOT READY"
    except ValueError:
        return "NA:DATA OUT OF RANGE"
    return "NA:COMMAND ERR"


def _thermotron(wire: _Wire, line: str) -> str | None:
    """The 8200's interface: a query answers its value; a setting with data answers the value set (the manual's
    ``SETP1,22.000`` -> ``22.000``); ``RUNM``, ``HOLD`` and ``STOP`` answer nothing (None); ``SCOD?`` 0 stopped,
    1 running manual; an error answers ``?``."""
    cmd = line.strip().upper()
    if cmd == "PVAR1?":
        return f"{wire.air():.3f}"
    if cmd == "SETP1?":
        return f"{wire.setpoint():.3f}"
    if cmd == "SCOD?":
        return "0" if wire.chamber.mode == "standby" else "1"
    try:
        if cmd.startswith("SETP1,"):
            wire.write(float(cmd[len("SETP1,") :]))
            return f"{wire.setpoint():.3f}"
        if cmd.startswith("MRMP1,"):
            return f"{float(cmd[len('MRMP1,') :]):.3f}"
        if cmd in ("RUNM", "HOLD", "STOP"):
            if wire.faults.local:
                raise ControllerRefused("local mode")
            wire.chamber.set_mode("standby" if cmd == "STOP" else "constant")
            return None
    except (ControllerRefused, ValueError):
        return "?"
    return "?"


def _simserv(wire: _Wire, line: str) -> str:
    fields = line.strip("\r\n").split(SIMSERV_SEP)
    cmd = fields[0]
    try:
        if cmd == "11004":
            return f"1{SIMSERV_SEP}{wire.air():.1f}"
        if cmd == "11002":
            return f"1{SIMSERV_SEP}{wire.setpoint():.1f}"
        if cmd == "11007":
            return f"1{SIMSERV_SEP}{wire.low():.1f}"
        if cmd == "11009":
            return f"1{SIMSERV_SEP}{wire.high():.1f}"
        if cmd == "11001" and len(fields) >= 4:
            wire.write(float(fields[3]))
            return "1"
        if cmd == "14001" and len(fields) >= 3 and fields[2] in ("0", "1"):
            if wire.faults.local:
                raise ControllerRefused("local mode")
            wire.chamber.set_mode("constant" if fields[2] == "1" else "standby")
            return "1"
    except (ControllerRefused, ValueError):
        return "-6"
    return "-5"


_LINE_PROTOCOLS: dict[str, tuple[Callable[[_Wire, str], str | None], str]] = {
    "espec": (_espec, "\r\n"),
    "thermotron": (_thermotron, "\r"),
    "simserv": (_simserv, "\r\n"),
}


class ChamberServer:
    """A served chamber, running on its own thread's event loop; ``url``: the bound address; ``stop()``."""

    def __init__(self, scheme: str, host: str, port: int, wire: _Wire, word_order: str) -> None:
        self.scheme = scheme
        self.wire = wire
        self.word_order = word_order
        self._requested = (host, port)
        self.host = host
        self.port = 0
        self._loop = asyncio.new_event_loop()
        self._ready = threading.Event()
        self._stopped: asyncio.Event | None = None
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name=f"chamber-{scheme}", daemon=True)

    @property
    def url(self) -> str:
        return f"{self.scheme}://{self.host}:{self.port}"

    def start(self) -> ChamberServer:
        self._thread.start()
        self._ready.wait()
        if self._error is not None:
            raise DeviceError(f"cannot serve {self.scheme} on {self._requested[0]}:{self._requested[1]}: {self._error}")
        return self

    def stop(self) -> None:
        if self._thread.is_alive() and self._stopped is not None:
            self._loop.call_soon_threadsafe(self._stopped.set)
            self._thread.join(5.0)

    def __enter__(self) -> ChamberServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _run(self) -> None:
        asyncio.set_event_loop(self._loop)
        try:
            self._loop.run_until_complete(self._main())
        finally:
            self._loop.close()

    async def _main(self) -> None:
        self._stopped = asyncio.Event()
        try:
            if self.scheme == "watlow-f4t":
                stop = await self._start_modbus()
            else:
                stop = await self._start_lines()
        except BaseException as exc:  # noqa: BLE001 - reported by start() on the caller's thread
            self._error = exc
            self._ready.set()
            return
        self._ready.set()
        await self._stopped.wait()
        await stop()
        pending = [task for task in asyncio.all_tasks() if task is not asyncio.current_task()]
        for task in pending:  # the connections still open
            task.cancel()
        await asyncio.gather(*pending, return_exceptions=True)

    # -- the ASCII protocols -----------------------------------------------------------------------------------
    async def _start_lines(self) -> Callable[[], Awaitable[None]]:
        answer, ending = _LINE_PROTOCOLS[self.scheme]
        wire = self.wire

        async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
            try:
                while True:
                    line = await _read_line(reader)
                    if line is None:
                        break
                    if not line.strip():
                        continue
                    faults = wire.faults
                    if faults.delay_s > 0:
                        await asyncio.sleep(faults.delay_s)
                    reply: str | None
                    if faults.exception_code is not None:
                        reply = {"espec": "NA:CONTROLLER ERR", "thermotron": "?", "simserv": "-1"}[self.scheme]
                    else:
                        reply = answer(wire, line)
                    if reply is None:  # a command the protocol answers with nothing
                        continue
                    if not await _send_reply(writer, (reply + ending).encode("latin-1"), faults):
                        break
            except (ConnectionError, asyncio.IncompleteReadError, asyncio.CancelledError):
                pass  # (CancelledError: the server stops; ended quietly, as the relay's)
            finally:
                writer.close()

        server = await asyncio.start_server(handle, self._requested[0], self._requested[1])
        self.port = server.sockets[0].getsockname()[1]

        async def stop() -> None:
            server.close()
            await server.wait_closed()

        return stop

    # -- Watlow F4T on pymodbus --------------------------------------------------------------------------------
    async def _start_modbus(self) -> Callable[[], Awaitable[None]]:
        """pymodbus's server on a private loopback port, behind a relay on the served address that passes the
        requests through and applies the reply faults (``garbage``: the reply's bytes replaced by as many that
        are none; ``drop_mid_reply``: half the reply, then the close); exception codes, the delay and local
        mode are the context's (``_f4t_context``)."""
        import logging

        from pymodbus.server import ModbusTcpServer

        logging.getLogger("pymodbus").setLevel(logging.ERROR)  # its datastore's deprecation notice
        server = ModbusTcpServer(_f4t_context(self.wire, self.word_order), address=("127.0.0.1", 0))
        await server.listen()
        listener = server.transport  # pymodbus keeps asyncio's listening Server here
        inner_port = listener.sockets[0].getsockname()[1]  # type: ignore[attr-defined]
        faults = self.wire.faults

        async def relay(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
            inner_reader, inner_writer = await asyncio.open_connection("127.0.0.1", inner_port)

            async def requests() -> None:
                while data := await reader.read(4096):
                    inner_writer.write(data)
                    await inner_writer.drain()
                inner_writer.close()

            pump = asyncio.ensure_future(requests())
            try:
                while True:
                    header = await inner_reader.readexactly(6)  # MBAP: transaction, protocol, length
                    body = await inner_reader.readexactly(struct.unpack(">H", header[4:6])[0])
                    if not await _send_reply(writer, header + body, faults):
                        break
            except (ConnectionError, asyncio.IncompleteReadError):
                pass
            except asyncio.CancelledError:  # the server stops: end the task quietly (3.11's stream callback would
                pass  # log a cancelled handler's CancelledError as an error with its traceback)
            finally:
                pump.cancel()
                inner_writer.close()
                writer.close()

        outer = await asyncio.start_server(relay, self._requested[0], self._requested[1])
        self.port = outer.sockets[0].getsockname()[1]

        async def stop() -> None:
            outer.close()
            await outer.wait_closed()
            await server.shutdown()

        return stop


async def _send_reply(writer: asyncio.StreamWriter, reply: bytes, faults: ChamberFaults) -> bool:
    """Send ``reply`` through the reply faults: ``garbage``, as many bytes that are no reply (a line protocol's
    line ending kept, so the client reads a whole line of garbage); ``drop_mid_reply``, its first half and then
    False (the caller closes the connection).  True: the connection goes on."""
    if faults.garbage:
        ending = reply[-2:] if reply.endswith(b"\r\n") else b""
        size = len(reply) - len(ending)
        reply = (GARBAGE * (size // len(GARBAGE) + 1))[:size] + ending
    if faults.drop_mid_reply:
        writer.write(reply[: max(1, len(reply) // 2)])
        await writer.drain()
        return False
    writer.write(reply)
    await writer.drain()
    return True


async def _read_line(reader: asyncio.StreamReader) -> str | None:
    """One request: bytes up to CR or LF (a lone LF after a CR is an empty request), at most MAX_LINE_BYTES."""
    buf = bytearray()
    while True:
        byte = await reader.read(1)
        if not byte:
            return None
        if byte in (b"\r", b"\n"):
            return buf.decode("latin-1")
        buf += byte
        if len(buf) > MAX_LINE_BYTES:
            return None


def _float_words(value: float, word_order: str) -> list[int]:
    high, low = struct.unpack(">HH", struct.pack(">f", value))
    return [low, high] if word_order == "low" else [high, low]


def _words_float(words: list[int], word_order: str) -> float:
    low, high = (words[0], words[1]) if word_order == "low" else (words[1], words[0])
    return float(struct.unpack(">f", struct.pack(">HH", high, low))[0])


def _f4t_context(wire: _Wire, word_order: str) -> Any:
    """A pymodbus server context whose holding registers are the F4T's loop-1 map over ``wire``: the floats (set
    point, air, range), the display unit, the control mode (written Off 62: standby; Auto 10: constant), the
    profile's state (none runs) and its action (accepted); any other address answers exception 2 (illegal data
    address), as a controller does.  Faults: ``exception_code`` answers
    every request with it, ``delay_s`` delays each answer, ``local`` answers a write exception 4 (device
    failure, as a controller refusing it)."""
    from pymodbus.constants import ExcCodes
    from pymodbus.datastore import ModbusDeviceContext, ModbusServerContext

    values = {
        F4T_SETPOINT: wire.setpoint,
        F4T_PV: wire.air,
        F4T_RANGE_LOW: wire.low,
        F4T_RANGE_HIGH: wire.high,
    }

    def control_mode() -> int:
        if wire.faults.local:
            return F4T_MODE_MANUAL
        return F4T_MODE_OFF if wire.chamber.mode == "standby" else F4T_MODE_AUTO

    words_at: dict[int, Callable[[], int]] = {
        F4T_DISPLAY_UNITS: lambda: 30 if wire.in_f else 15,
        F4T_CONTROL_MODE: control_mode,
        F4T_PROFILE_STATE: lambda: F4T_PROFILE_IDLE,
        F4T_PROFILE_ACTION: lambda: 0,
    }

    class F4TContext(ModbusServerContext):
        async def async_getValues(
            self, device_id: int, func_code: int, address: int, count: int = 1
        ) -> list[int] | list[bool] | ExcCodes:
            faults = wire.faults
            if faults.delay_s > 0:
                await asyncio.sleep(faults.delay_s)
            if faults.exception_code is not None:
                return ExcCodes(faults.exception_code)
            words: list[int] = []
            cache: dict[int, list[int]] = {}
            for reg in range(address, address + count):
                if reg in words_at:
                    words.append(words_at[reg]())
                    continue
                base = reg if reg in values else reg - 1 if reg - 1 in values else None
                if base is None:
                    return ExcCodes.ILLEGAL_ADDRESS
                if base not in cache:
                    cache[base] = _float_words(values[base](), word_order)
                words.append(cache[base][reg - base])
            return words

        async def async_setValues(
            self, device_id: int, func_code: int, address: int, vals: Sequence[int] | Sequence[bool]
        ) -> ExcCodes | None:
            faults = wire.faults
            if faults.delay_s > 0:
                await asyncio.sleep(faults.delay_s)
            if faults.exception_code is not None:
                return ExcCodes(faults.exception_code)
            if address == F4T_CONTROL_MODE and len(vals) == 1:
                if faults.local:
                    return ExcCodes.DEVICE_FAILURE
                mode = {F4T_MODE_OFF: "standby", F4T_MODE_AUTO: "constant"}.get(int(vals[0]))
                if mode is None:
                    return ExcCodes.ILLEGAL_VALUE
                wire.chamber.set_mode(mode)
                return None
            if address == F4T_PROFILE_ACTION and len(vals) == 1:
                return None  # no profile runs: a terminate has nothing to end
            if address == F4T_SETPOINT:
                if func_code != 16 or len(vals) != 2:
                    return ExcCodes.ILLEGAL_VALUE
                try:
                    wire.write(_words_float([int(v) for v in vals], word_order))
                except ControllerRefused:
                    return ExcCodes.DEVICE_FAILURE
                except ValueError:
                    return ExcCodes.ILLEGAL_VALUE
                return None
            return ExcCodes.ILLEGAL_ADDRESS

    context = F4TContext(devices=ModbusDeviceContext())
    context.simdevices = []  # so pymodbus's server asks this context itself (its "old simulator" path)
    context.old_simulator = True
    return context


def serve_chamber(url: str | ControllerURL, chamber: SimChamber, faults: ChamberFaults | None = None) -> ChamberServer:
    """Serve ``chamber`` on ``url``'s protocol (``espec``, ``thermotron``, ``simserv``, ``watlow-f4t``); returns
    once listening (``.url`` names the bound port).  Host 127.0.0.1 unless the URL names one; ``watlow-f4t``
    takes ``?word_order=low|high``.  ``UsageError`` on an unknown scheme or option, or an address it cannot
    bind."""
    parsed = parse_controller_url(url) if isinstance(url, str) else url
    if parsed.scheme not in SERVED_SCHEMES:
        raise UsageError(f"--chamber-serve {parsed.text}: scheme must be one of {', '.join(SERVED_SCHEMES)}")
    if parsed.device is not None:
        raise UsageError(f"--chamber-serve {parsed.text}: serves on TCP only (HOST:PORT)")
    word_order = "low"
    if parsed.scheme == "watlow-f4t":
        word_order = parsed.take("word_order", _word_order, "low")
        parsed.refuse_unknown("word_order")
    else:
        parsed.refuse_unknown("none")
    wire = _Wire(chamber, faults if faults is not None else ChamberFaults())
    host = parsed.host or "127.0.0.1"
    return ChamberServer(parsed.scheme, host, parsed.port or 0, wire, word_order).start()


def _word_order(text: str) -> str:
    if text not in ("low", "high"):
        raise ValueError("low or high")
    return text


CHAMBER_SERVE_OPTIONS = "start_c, rate_c_per_min, tau_s, low_c, high_c, unit, mode"


def coupled_chamber(
    url_text: str, sim: Simulator, speed: float
) -> tuple[Simulator, SimChamber, StartedClock, ControllerURL]:
    """For ``simulate --serve ... --chamber-serve URL``: a chamber (options from the URL: ``start_c``, default
    the profile's start air; ``rate_c_per_min``, ``tau_s``, ``low_c``, ``high_c``, ``unit`` C|F, ``mode``), its
    clock (started with the stream: chamber time = device time) and a simulator like ``sim`` whose air is the
    chamber's (``ChamberAir``, slow grid in ``COUPLED_BLOCK_STEPS`` blocks).  The URL comes back without those
    options, for ``serve_chamber``."""
    url = parse_controller_url(url_text)
    d = ChamberParams()
    start_c = float(sim.profile.chamber.air_temp_c(np.array([0.0]))[0])
    raw = {
        "start_c": url.take("start_c", float, start_c),
        "rate_c_per_min": url.take("rate_c_per_min", float, d.rate_c_per_min),
        "tau_s": url.take("tau_s", float, d.tau_s),
        "low_c": url.take("low_c", float, d.low_c),
        "high_c": url.take("high_c", float, d.high_c),
    }
    unit = url.take("unit", str, d.unit)
    mode = url.take("mode", str, d.mode)
    try:
        params = ChamberParams(unit=unit, mode=mode, **raw)
    except ValueError as exc:
        raise UsageError(f"--chamber-serve {url.text}: {exc}") from None
    clock = StartedClock(speed)
    chamber = SimChamber(clock, params)
    air = ChamberAir(chamber, sim.profile.chamber.duration_s)
    profile = replace(sim.profile, chamber=air)  # type: ignore[arg-type]  # duck-typed: air_temp_c, duration_s
    coupled = Simulator(
        profile,
        sim.config,
        rate_hz=sim.rate_hz,
        seed=sim.seed,
        faults=sim.faults,
        wire_format=sim.wire_format,
        grid_block_steps=COUPLED_BLOCK_STEPS,
    )
    return coupled, chamber, clock, url
