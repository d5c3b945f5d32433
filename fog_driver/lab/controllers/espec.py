"""The Espec P-300 / SCP-220 driver: ``espec://HOST[:10001]`` (TCP) or ``espec:///dev/ttyUSB1?baud=9600``
(serial), the codec ``codecs.espec`` over a ``StreamLink``.

Options: ``unit=C|F`` (the unit the controller is set to; the protocol does not say it: degC assumed, said
once), ``baud`` (serial).  The controller has one temperature loop (a humidity one, where fitted, is left
alone).  The air, the set point and the range come from one ``TEMP?``; the first set point written on a
connection is followed by ``MODE, CONSTANT`` unless ``MODE?`` says it already is; the safe stop is
``MODE, STANDBY``.  State from ``MODE?``, alarms from ``ALARM?`` (an error answer to either: not known, said
once).
"""

from __future__ import annotations

from typing import Any

from .ascii import AsciiChamber, with_overrides
from .base import ChamberRange, ChamberStatus, Notice
from .codecs import espec as codec
from .url import ControllerURL

DEFAULT_PORT = 10001


class EspecController(AsciiChamber):
    who = "espec"
    terminator = codec.TERMINATOR
    default_port = DEFAULT_PORT

    def _temp(self) -> codec.TempReply:
        return codec.decode_temp(self.ask(codec.encode_read_temp()))

    def read_air_c(self) -> float:
        return self.to_c(self._temp().air)

    def read_setpoint_c(self) -> float:
        return self.to_c(self._temp().setpoint)

    def read_range_c(self) -> ChamberRange:
        temp = self._temp()
        return ChamberRange(low_c=self.to_c(temp.lower), high_c=self.to_c(temp.upper))

    def write_setpoint_c(self, setpoint_c: float) -> None:
        codec.decode_ok(self.ask(codec.encode_write_setpoint(self.from_c(setpoint_c))))
        self.start_once(self._constant)

    def _constant(self) -> None:
        if codec.decode_mode(self.ask(codec.encode_read_mode())) != "constant":
            codec.decode_ok(self.ask(codec.encode_mode("CONSTANT")))

    def safe_stop(self) -> None:
        codec.decode_ok(self.ask(codec.encode_mode("STANDBY")))

    def read_status(self) -> ChamberStatus:
        state = self.optional_read("mode", lambda: codec.decode_mode(self.ask(codec.encode_read_mode())), "unknown")
        no_alarms: tuple[str, ...] = ()
        alarms = self.optional_read("alarm", lambda: codec.decode_alarm(self.ask(codec.encode_read_alarm())), no_alarms)
        return ChamberStatus(state=state, alarms=alarms)


def open_controller(
    url: ControllerURL, *, overrides: dict[str, Any], on_notice: Notice, timeout_s: float
) -> EspecController:
    """The Espec controller ``url`` names, not connected (options under ``overrides``; the URL wins)."""
    controller = EspecController(with_overrides(url, overrides), timeout_s=timeout_s, on_notice=on_notice)
    controller.finish_options()
    return controller
