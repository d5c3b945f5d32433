"""The Thermotron 8800 / 8200 driver: ``thermotron://HOST[:8888]?range=LOW:HIGH``, the codec
``codecs.thermotron`` over a ``StreamLink``.

Options: ``range=LOW:HIGH`` (degC, required: the interface has no read of the set point's range, and the
driver refuses to open without one rather than invent it; the chamber's rated range from its nameplate or
manual), ``loop`` (1..8, default 1: only that loop is read and written), ``unit=C|F`` (the interface does not
say it: degC assumed, said once), ``ramp_rate`` (degC per minute, sent as ``MRMPn`` with the first set point
of a connection; absent: the controller's own manual ramp rate is left as it is).

A setting with data (``SETPn,x``, ``MRMPn,x``) is answered with its value, as the 8200 manual's example shows
(``SETP1,22.000`` -> ``22.000``); ``write_echo=0`` for an interface that answers nothing.  ``RUNM``, ``HOLD``
and ``STOP`` have no answer.  The first set point written on a connection is followed by ``RUNM`` (run
manual); the safe stop is ``STOP``.  State from ``SCOD?`` (an error or garbage answer: ``unknown``, said once); the
interface's alarms are not read (none listed).
"""

from __future__ import annotations

from typing import Any

from ...errors import UsageError
from .ascii import AsciiChamber, parse_index, with_overrides
from .base import ChamberRange, ChamberStatus, Notice
from .codecs import thermotron as codec
from .url import ControllerURL

DEFAULT_PORT = 8888


def parse_range(text: str) -> ChamberRange:
    """``LOW:HIGH`` in degC, LOW < HIGH."""
    low, sep, high = text.partition(":")
    if not sep:
        raise ValueError("LOW:HIGH in degC")
    try:
        return ChamberRange(low_c=float(low), high_c=float(high))
    except Exception:
        raise ValueError("LOW:HIGH in degC, LOW < HIGH") from None


def parse_flag(text: str) -> bool:
    """``1``/``0`` (also ``true``/``false``, ``yes``/``no``: a YAML boolean in a config file)."""
    word = text.strip().lower()
    if word not in ("0", "1", "true", "false", "yes", "no"):
        raise ValueError("0 or 1")
    return word in ("1", "true", "yes")


def parse_rate(text: str) -> float:
    rate = float(text)
    if not 0.0 < rate < 1000.0:
        raise ValueError("a rate in degC per minute, above 0")
    return rate


class ThermotronController(AsciiChamber):
    who = "thermotron"
    terminator = codec.TERMINATOR
    default_port = DEFAULT_PORT
    known = "range, loop, unit, ramp_rate, write_echo, baud"

    def __init__(self, url: ControllerURL, *, timeout_s: float, on_notice: Notice) -> None:
        super().__init__(url, timeout_s=timeout_s, on_notice=on_notice)
        self.loop = url.take("loop", parse_index, 1)
        self.ramp_rate_c_per_min = url.take("ramp_rate", parse_rate, None)
        self.write_echo = url.take("write_echo", parse_flag, True)
        range_c = url.take("range", parse_range, None)
        self.finish_options()
        if range_c is None:
            raise UsageError(
                f"controller URL {url.text}: a Thermotron does not say its range: give range=LOW:HIGH (degC)"
            )
        self._range_c = range_c

    def read_air_c(self) -> float:
        return self.to_c(codec.decode_number(self.ask(codec.encode_read_air(self.loop)), what="the air"))

    def read_setpoint_c(self) -> float:
        reply = self.ask(codec.encode_read_setpoint(self.loop))
        return self.to_c(codec.decode_number(reply, what="the set point"))

    def read_range_c(self) -> ChamberRange:
        return self._range_c

    def _set(self, request: bytes, what: str) -> None:
        """A setting with data: its echo read (and checked to be a number) unless ``write_echo=0``."""
        if self.write_echo:
            codec.decode_number(self.ask(request), what=f"the echo of {what}")
        else:
            self.tell(request)

    def write_setpoint_c(self, setpoint_c: float) -> None:
        self._set(codec.encode_write_setpoint(self.loop, self.from_c(setpoint_c)), "the set point")
        self.start_once(self._run_manual)

    def _run_manual(self) -> None:
        if self.ramp_rate_c_per_min is not None:
            rate = self.ramp_rate_c_per_min * (9.0 / 5.0 if self.unit == "F" else 1.0)
            self._set(codec.encode_ramp_rate(self.loop, rate), "the ramp rate")
        self.tell(codec.encode_run_manual())

    def safe_stop(self) -> None:
        self.tell(codec.encode_stop())

    def read_status(self) -> ChamberStatus:
        state = self.optional_read(
            "state", lambda: codec.decode_status(self.ask(codec.encode_read_status())), "unknown"
        )
        return ChamberStatus(state=state)


def open_controller(
    url: ControllerURL, *, overrides: dict[str, Any], on_notice: Notice, timeout_s: float
) -> ThermotronController:
    """The Thermotron controller ``url`` names, not connected (options under ``overrides``; the URL wins)."""
    return ThermotronController(with_overrides(url, overrides), timeout_s=timeout_s, on_notice=on_notice)
