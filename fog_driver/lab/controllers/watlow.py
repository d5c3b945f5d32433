"""The Watlow F4T over Modbus TCP (``watlow-f4t://HOST[:502]``) or RTU (``watlow-f4t+rtu:///dev/ttyUSB1``).

Our own codec (``codecs.modbus``, ``codecs.f4t``) over our own link (``links.StreamLink``): each call sends one
request and reads its one reply, the late reply of a request that timed out dropped first.  Set points are
written with function 16 as the float's two registers, never function 6.

The URL's options, each also a key of the ``overrides`` mapping (a config file's ``chamber:`` section; the URL
wins): ``unit`` (the Modbus unit id, 1), ``loop`` (1..4, 1), ``word_order`` (``low``: the float's low word in
the first register, the F4T's default; ``high``), ``baud`` (RTU only, 38400), ``resolution_c`` (0.01), and the
registers ``setpoint_register``, ``air_register``, ``range_low_register``, ``range_high_register`` (defaults:
the loop's, from the manual), ``units_register`` (1328), ``control_mode_register`` (the loop's, 2730 +
160 (N - 1)), ``profile_state_register`` (16568), ``profile_action_register`` (16566); ``none`` for the last
four: not read (the unit assumed degC; the state ``unknown``).

The unit: read at each ``connect`` from the units register (F = 30, C = 15).  A controller in degF is read in
degF and converted (the air, the set point read and written, the range).  Where the unit cannot be read (no
register, or an exception to it), degC is assumed and said once (``on_notice``).

The state (``read_status``): ``program`` while the controller runs or holds a profile of its own, else the
loop's control mode: Off -> ``standby``, Auto -> ``constant``, Manual -> ``local``.  An exception to those reads,
or a value the map does not know: ``unknown``, said once.  No alarms are read (the manual's alarm registers
give an alarm's settings, and what its state values mean is not in the pages we could read).

The safe stop (``safe_stop``): terminate the controller's own profile if one runs, then the loop's control
mode Off (standby).  Other loops are never written.

``resolution_c`` 0.01 degC: a 32-bit float holds a chamber's set point to about 1e-5 degC, so a set point
reads back as written within far less than half of 0.01, degF conversion included.  A controller that rounds
its set points coarser is told so with ``resolution_c=`` (or the runner would take the rounding for someone
else driving the chamber).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import replace
from typing import Any

from ...errors import UsageError
from .base import (
    ChamberRange,
    ChamberStatus,
    ControllerProtocolError,
    ControllerUnreachable,
    Notice,
    c_to_f,
    f_to_c,
)
from .codecs import f4t, modbus
from .links import StreamLink
from .url import ControllerURL

DEFAULT_PORT = 502
DEFAULT_BAUD = 38400
DEFAULT_RESOLUTION_C = 0.01
SCHEME_TCP = "watlow-f4t"
SCHEME_RTU = "watlow-f4t+rtu"

REGISTER_OPTIONS = ("setpoint_register", "air_register", "range_low_register", "range_high_register")
OPTIONAL_REGISTER_OPTIONS = (
    "units_register",
    "control_mode_register",
    "profile_state_register",
    "profile_action_register",
)
COMMON_OPTIONS = ("unit", "loop", "word_order", "resolution_c", *REGISTER_OPTIONS, *OPTIONAL_REGISTER_OPTIONS)


def _register(text: str) -> int:
    value = int(text, 0)
    if not 0 <= value <= 0xFFFE:
        raise ValueError("a register address is 0..65534")
    return value


def _optional_register(text: str) -> int | None:
    return None if text.strip().lower() == "none" else _register(text)


def _bounded(low: int, high: int) -> Callable[[str], int]:
    def convert(text: str) -> int:
        value = int(text)
        if not low <= value <= high:
            raise ValueError(f"not {low}..{high}")
        return value

    return convert


def _word_order(text: str) -> str:
    if text not in f4t.WORD_ORDERS:
        raise ValueError("low or high")
    return text


def _resolution(text: str) -> float:
    value = float(text)
    if not 0 < value <= 10:
        raise ValueError("a resolution in degC, more than 0")
    return value


def _override_text(value: Any) -> str:
    return "none" if value is None else str(value)


class WatlowF4T:
    """One loop of an F4T, degC at this interface (``ChamberController``)."""

    def __init__(
        self,
        *,
        url: str,
        address: str,
        link: StreamLink,
        framer: modbus.TcpFramer | modbus.RtuFramer,
        registers: f4t.F4TMap,
        resolution_c: float,
        on_notice: Notice,
    ) -> None:
        self.url = url
        self.address = address
        self.resolution_c = resolution_c
        self.registers = registers
        self.unit_of_values: str = "C"
        self._link = link
        self._framer = framer
        self._on_notice = on_notice
        self._said: set[str] = set()

    # the link and one transaction

    def connect(self) -> None:
        self._link.connect()
        self.unit_of_values = self._read_unit()

    def close(self) -> None:
        self._link.close()

    def _transact(self, pdu: bytes) -> bytes:
        if not self._link.connected:
            raise ControllerUnreachable(f"{self._link.where}: not connected")
        self._link.discard_input()
        self._link.send(self._framer.request(pdu))
        frame = b""
        with self._named():
            while (needed := self._framer.bytes_needed(frame)) > len(frame):
                frame += self._link.read_exact(needed - len(frame))
            return self._framer.reply(frame)

    @contextmanager
    def _named(self, detail: str = "") -> Iterator[None]:
        """Protocol errors raised inside, on one line naming the controller (and ``detail``).  Garbage also
        closes the link (what follows it cannot be trusted; the next ``connect`` starts afresh); an exception
        reply is a well-formed answer and leaves it open."""
        try:
            yield
        except modbus.ModbusExceptionReply as exc:
            raise modbus.ModbusExceptionReply(
                f"{self._link.where}: {exc}{detail}", function=exc.function, code=exc.code
            ) from None
        except ControllerProtocolError as exc:
            self._link.close()
            raise ControllerProtocolError(f"{self._link.where}: {exc}{detail}") from None

    def _read(self, address: int, count: int) -> tuple[int, ...]:
        pdu = self._transact(modbus.read_holding_request(address, count))
        with self._named():
            return modbus.decode_read_holding_reply(pdu, address, count)

    def _write(self, address: int, values: tuple[int, ...]) -> None:
        pdu = self._transact(modbus.write_multiple_request(address, values))
        with self._named():
            modbus.decode_write_multiple_reply(pdu, address, len(values))

    def _say_once(self, key: str, line: str) -> None:
        if key not in self._said:
            self._said.add(key)
            self._on_notice(line)

    # the unit

    def _read_unit(self) -> str:
        register = self.registers.units
        if register is None:
            self._say_once("unit", f"{self._link.where}: no unit register given: the F4T's values taken as degC")
            return "C"
        try:
            (value,) = self._read(register, 1)
        except modbus.ModbusExceptionReply as exc:
            self._say_once("unit", f"{exc}; the F4T's values taken as degC")
            return "C"
        with self._named(f" (units_register={register})"):
            return f4t.decode_units(value)

    def _to_c(self, value: float) -> float:
        return f_to_c(value) if self.unit_of_values == "F" else value

    def _from_c(self, value_c: float) -> float:
        return c_to_f(value_c) if self.unit_of_values == "F" else value_c

    def _read_float(self, address: int) -> float:
        registers = self._read(address, 2)
        with self._named(f" (register {address})"):
            return f4t.decode_float(registers, self.registers.word_order)

    # the interface

    def read_air_c(self) -> float:
        return self._to_c(self._read_float(self.registers.process_value))

    def read_setpoint_c(self) -> float:
        return self._to_c(self._read_float(self.registers.setpoint))

    def write_setpoint_c(self, setpoint_c: float) -> None:
        self._write(self.registers.setpoint, f4t.encode_float(self._from_c(setpoint_c), self.registers.word_order))

    def read_range_c(self) -> ChamberRange:
        low = self._to_c(self._read_float(self.registers.range_low))
        high = self._to_c(self._read_float(self.registers.range_high))
        return ChamberRange(low_c=low, high_c=high)

    def _read_optional(self, register: int | None, what: str) -> int | None:
        if register is None:
            return None
        try:
            (value,) = self._read(register, 1)
        except modbus.ModbusExceptionReply as exc:
            self._say_once(what, f"{exc}: the chamber's state is unknown")
            return None
        return value

    def read_status(self) -> ChamberStatus:
        profile_state = self._read_optional(self.registers.profile_state, "profile state")
        if profile_state in (f4t.PROFILE_RUNNING, f4t.PROFILE_PAUSED):
            return ChamberStatus(state="program")
        control_mode = self._read_optional(self.registers.control_mode, "control mode")
        if control_mode is None and self.registers.control_mode is None:
            self._say_once("control mode", f"{self._link.where}: no control mode register given: the state is unknown")
        state = f4t.chamber_state(profile_state, control_mode)
        if state is None:
            self._say_once(
                "control mode value",
                f"{self._link.where}: the loop's control mode register {self.registers.control_mode} holds "
                f"{control_mode}, which the F4T map does not know: the state is unknown",
            )
            state = "unknown"
        return ChamberStatus(state=state)

    def safe_stop(self) -> None:
        """Terminate the controller's own profile if one runs, then put the loop in standby (control mode Off)."""
        profile_state = self._read_optional(self.registers.profile_state, "profile state")
        if profile_state in (f4t.PROFILE_RUNNING, f4t.PROFILE_PAUSED) and self.registers.profile_action is not None:
            self._write(self.registers.profile_action, (f4t.PROFILE_TERMINATE,))
        if self.registers.control_mode is None:
            raise ControllerProtocolError(
                f"{self._link.where}: no control mode register: cannot put the loop in standby"
            )
        self._write(self.registers.control_mode, (f4t.CONTROL_MODE_OFF,))


def open_controller(
    url: ControllerURL, *, overrides: Mapping[str, Any], on_notice: Notice, timeout_s: float
) -> WatlowF4T:
    """The F4T ``url`` names (not connected); ``UsageError`` (one line) on a bad or unknown option."""
    rtu = url.scheme == SCHEME_RTU
    known = (*COMMON_OPTIONS, "baud") if rtu else COMMON_OPTIONS
    unknown = sorted(str(k) for k in overrides if k not in known)
    if unknown:
        raise UsageError(
            f"chamber settings for {url.text}: unknown setting {', '.join(unknown)} "
            f"(this scheme takes: {', '.join(known)})"
        )
    options = {str(k): _override_text(v) for k, v in overrides.items()}
    options.update(url.options)
    url.options = options
    if rtu and url.device is None:
        raise UsageError(f"controller URL {url.text}: {SCHEME_RTU} takes a serial device: {SCHEME_RTU}:///dev/ttyUSB1")
    if not rtu and url.host is None:
        raise UsageError(f"controller URL {url.text}: {SCHEME_TCP} takes a host: {SCHEME_TCP}://HOST[:PORT]")
    unit = url.take("unit", _bounded(1, 247) if rtu else _bounded(0, 255), 1)
    loop = url.take("loop", _bounded(1, f4t.LOOPS), 1)
    word_order = url.take("word_order", _word_order, "low")
    resolution_c = url.take("resolution_c", _resolution, DEFAULT_RESOLUTION_C)
    baud = url.take("baud", _bounded(300, 1_000_000), DEFAULT_BAUD) if rtu else DEFAULT_BAUD
    registers = f4t.loop_map(loop, word_order=word_order)
    registers = replace(
        registers,
        setpoint=url.take("setpoint_register", _register, registers.setpoint),
        process_value=url.take("air_register", _register, registers.process_value),
        range_low=url.take("range_low_register", _register, registers.range_low),
        range_high=url.take("range_high_register", _register, registers.range_high),
        units=url.take("units_register", _optional_register, registers.units),
        control_mode=url.take("control_mode_register", _optional_register, registers.control_mode),
        profile_state=url.take("profile_state_register", _optional_register, registers.profile_state),
        profile_action=url.take("profile_action_register", _optional_register, registers.profile_action),
    )
    url.refuse_unknown(", ".join(known))
    framer: modbus.TcpFramer | modbus.RtuFramer
    if rtu:
        assert url.device is not None
        where = f"{url.device} (unit {unit})"
        link = StreamLink(where=where, device=url.device, baud=baud, timeout_s=timeout_s)
        framer = modbus.RtuFramer(unit)
        address = f"{SCHEME_RTU}://{url.device}/{unit}"
    else:
        port = url.port if url.port is not None else DEFAULT_PORT
        where = f"{url.host}:{port} (unit {unit})"
        link = StreamLink(where=where, host=url.host, port=port, timeout_s=timeout_s)
        framer = modbus.TcpFramer(unit)
        address = f"{SCHEME_TCP}://{url.host}:{port}/{unit}/{loop}"
    return WatlowF4T(
        url=url.text,
        address=address,
        link=link,
        framer=framer,
        registers=registers,
        resolution_c=resolution_c,
        on_notice=on_notice,
    )
