"""The Weiss / Voetsch SIMSERV driver: ``simserv://HOST[:2049][?loop=1]``, the codec ``codecs.simserv`` over a
``StreamLink``.

Options: ``loop`` (the SIMSERV channel, default 1 the temperature: only that channel is read and written),
``chamber`` (the chamber's index on the server, default 1), ``unit=C|F`` (not read: degC assumed, said once),
and the command numbers of the range reads ``lower_limit_command`` / ``upper_limit_command`` (defaults 11007
and 11009) for a controller whose interface numbers them otherwise.

The first set point written on a connection is followed by ``14001 CHB 1`` (start manual mode); the safe stop
is ``14001 CHB 0``.  The driver reads no state (``unknown``, said once).
"""

from __future__ import annotations

from typing import Any

from .ascii import AsciiChamber, parse_index, with_overrides
from .base import ChamberRange, ChamberStatus, Notice
from .codecs import simserv as codec
from .url import ControllerURL

DEFAULT_PORT = 2049


def parse_command(text: str) -> int:
    if not text.isdigit() or not 10000 <= int(text) <= 99999:
        raise ValueError("a SIMSERV command number 10000..99999")
    return int(text)


class SimservController(AsciiChamber):
    who = "simserv"
    terminator = codec.TERMINATOR
    default_port = DEFAULT_PORT
    known = "loop, chamber, unit, lower_limit_command, upper_limit_command, baud"

    def __init__(self, url: ControllerURL, *, timeout_s: float, on_notice: Notice) -> None:
        super().__init__(url, timeout_s=timeout_s, on_notice=on_notice)
        self.loop = url.take("loop", parse_index, 1)
        self.chamber = url.take("chamber", parse_index, 1)
        self.lower_limit_command = url.take("lower_limit_command", parse_command, codec.GET_LOWER_LIMIT)
        self.upper_limit_command = url.take("upper_limit_command", parse_command, codec.GET_UPPER_LIMIT)
        self.finish_options()

    def _read(self, command: int, what: str) -> float:
        reply = self.ask(codec.encode_read(command, self.chamber, self.loop))
        return self.to_c(codec.decode_value(reply, what=what))

    def read_air_c(self) -> float:
        return self._read(codec.GET_ACTUAL, "the actual value")

    def read_setpoint_c(self) -> float:
        return self._read(codec.GET_SETPOINT, "the set point")

    def read_range_c(self) -> ChamberRange:
        low_c = self._read(self.lower_limit_command, "the lower limit")
        high_c = self._read(self.upper_limit_command, "the upper limit")
        return ChamberRange(low_c=low_c, high_c=high_c)

    def write_setpoint_c(self, setpoint_c: float) -> None:
        codec.decode_ack(self.ask(codec.encode_write_setpoint(self.chamber, self.loop, self.from_c(setpoint_c))))
        self.start_once(lambda: codec.decode_ack(self.ask(codec.encode_manual_mode(self.chamber, start=True))))

    def safe_stop(self) -> None:
        codec.decode_ack(self.ask(codec.encode_manual_mode(self.chamber, start=False)))

    def read_status(self) -> ChamberStatus:
        self.notice_once("state", "simserv: the driver reads no state from SIMSERV: state unknown")
        return ChamberStatus()


def open_controller(
    url: ControllerURL, *, overrides: dict[str, Any], on_notice: Notice, timeout_s: float
) -> SimservController:
    """The SIMSERV controller ``url`` names, not connected (options under ``overrides``; the URL wins)."""
    return SimservController(with_overrides(url, overrides), timeout_s=timeout_s, on_notice=on_notice)
