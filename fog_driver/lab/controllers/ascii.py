"""What the ASCII chamber drivers (Espec, Thermotron, SIMSERV) share: their options, their link and the
request/answer exchange, the unit at the interface's edge, the things said once.

- Options: the URL's, over the ``overrides`` mapping (a config file's ``chamber:`` section; the URL wins).
  ``unit=C|F`` is the unit the controller is set to (none of the three protocols reads it): when neither the
  URL nor the overrides give it, degC is assumed and said once through ``on_notice``.  ``baud`` for a serial
  line.  Anything else a driver does not take: one-line ``UsageError``.
- ``address``: ``SCHEME://HOST:PORT`` for a network controller, the device path for a serial one (the lock's
  key: one runner per controller).
- Every answer is read up to the protocol's line end and at most ``MAX_LINE_BYTES`` (``StreamLink``); a link
  lost mid-answer is ``ControllerUnreachable``.
- A set point goes out with one decimal in the controller's unit (``codecs.lines.one_decimal``, half away
  from zero), so ``resolution_c`` is 0.1 degC, or 0.1 degF (0.0556 degC) on a controller set to degF.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any, TypeVar

from ...errors import UsageError
from .base import ControllerProtocolError, Notice, c_to_f, f_to_c
from .codecs.lines import MAX_LINE_BYTES
from .links import StreamLink
from .url import ControllerURL

T = TypeVar("T")

UNITS = ("C", "F")


def with_overrides(url: ControllerURL, overrides: Mapping[str, Any]) -> ControllerURL:
    """``url`` with each override it does not give itself added to its options (as text: the URL wins; a
    YAML list such as ``range: [-40, 120]`` becomes ``-40:120``)."""
    for name, value in overrides.items():
        if str(name) not in url.options:
            text = ":".join(str(item) for item in value) if isinstance(value, list | tuple) else str(value)
            url.options[str(name)] = text
    return url


def parse_unit(text: str) -> str:
    unit = text.strip().upper().removeprefix("DEG")
    if unit not in UNITS:
        raise ValueError("C or F")
    return unit


def parse_index(text: str) -> int:
    """A loop or chamber index: a whole number 1..99."""
    if not text.isdigit() or not 1 <= int(text) <= 99:
        raise ValueError("a whole number 1..99")
    return int(text)


def parse_baud(text: str) -> int:
    if not text.isdigit() or not 300 <= int(text) <= 921600:
        raise ValueError("a baud rate 300..921600")
    return int(text)


class AsciiChamber:
    """The common part of an ASCII chamber driver: the link, the exchange, the unit, the notices.  Not
    connected until ``connect()``.  ``terminator``: the line end of the protocol's answers."""

    who = "ascii"
    terminator = b"\r\n"
    default_port = 0
    #: the options the driver takes, for the message refusing the others
    known = "unit, baud"

    def __init__(self, url: ControllerURL, *, timeout_s: float, on_notice: Notice) -> None:
        self.url = url.text
        self._on_notice = on_notice
        self._said: set[str] = set()
        unit = url.take("unit", parse_unit, None)
        baud = url.take("baud", parse_baud, None)
        if baud is not None and url.device is None:
            raise UsageError(f"controller URL {url.text}: baud is for a serial line (SCHEME:///dev/DEVICE)")
        self._options_url = url
        if url.device is not None:
            self.address = url.device
            self.link = StreamLink(
                where=f"{url.scheme}://{url.device}", device=url.device, baud=baud or 9600, timeout_s=timeout_s
            )
        else:
            port = url.port if url.port is not None else self.default_port
            self.address = f"{url.scheme}://{url.host}:{port}"
            self.link = StreamLink(where=self.address, host=url.host, port=port, timeout_s=timeout_s)
        self._unit_assumed = unit is None
        self.unit = unit or "C"
        self.resolution_c = 0.1 if self.unit == "C" else 0.1 * 5.0 / 9.0
        self._started = False

    def finish_options(self) -> None:
        """Refuse the options left untaken (call once the subclass has taken its own)."""
        self._options_url.refuse_unknown(self.known)

    def notice_once(self, key: str, line: str) -> None:
        if key not in self._said:
            self._said.add(key)
            self._on_notice(line)

    # ------------------------------------------------------------------ the link

    def connect(self) -> None:
        """Open the link; the unit assumed is said once, on the first connection that works (a controller
        that cannot be reached gets its one error line alone)."""
        self.link.connect()
        self._started = False
        if self._unit_assumed:
            self.notice_once("unit", f"{self.who}: the protocol does not say its unit: degC assumed (unit=F if not)")

    def close(self) -> None:
        self.link.close()

    def ask(self, request: bytes) -> bytes:
        """Send ``request`` and return its answer line (with its line end); whatever arrived unasked before
        (a late or unexpected answer) is dropped first, so it is never taken for this one."""
        self.link.discard_input()
        self.link.send(request)
        return self.link.read_until(self.terminator, MAX_LINE_BYTES)

    def tell(self, request: bytes) -> None:
        """Send a command that has no answer."""
        self.link.send(request)

    # ------------------------------------------------------------------ units

    def to_c(self, value: float) -> float:
        return f_to_c(value) if self.unit == "F" else value

    def from_c(self, value_c: float) -> float:
        return c_to_f(value_c) if self.unit == "F" else value_c

    def optional_read(self, key: str, read: Callable[[], T], fallback: T) -> T:
        """``read()``, or ``fallback`` (said once) when the controller answers it an error or garbage."""
        try:
            return read()
        except ControllerProtocolError as exc:
            self.notice_once(key, f"{exc} (taken as not known)")
            return fallback

    def start_once(self, start: Callable[[], None]) -> None:
        """Put the controller into remote constant control (``start``) once per connection, after the first
        set point is written."""
        if not self._started:
            start()
            self._started = True
