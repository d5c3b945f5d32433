"""What the blocking and the asyncio client share beyond the ``Session``: reading an address, checking the
arguments of the control commands, and turning the daemon's answers into values or typed errors."""

from __future__ import annotations

import logging
import math
from typing import Any, TypeVar, cast

from .errors import BiasFailed, CommandRefused, Unauthorized, UnknownCommand
from .messages import Angle, Bias, Device, ErrorReply, Message, Other, Reply, Status, Version
from .session import Session
from .wire import DEFAULT_HOST, DEFAULT_PORT, GREETING_TIMEOUT_S, format_address, parse_address

__all__ = [
    "MAX_BIAS_S",
    "MAX_BUFFERED_ANGLES",
    "MAX_REFERENCE_DPH",
    "REPLY_TIMEOUT_S",
    "ClientBase",
    "answer_as",
    "bias_args",
    "Reconnection",
    "check_bias",
    "check_reply",
    "control_args",
    "parse_target",
    "printable",
]

#: The standard library's logger (no structlog here: the client needs the standard library only).  Each record's
#: message is the event and its ``key=value`` pairs; the pairs are also the record's attributes (``extra``), so a
#: structlog ``ProcessorFormatter`` with ``ExtraAdder`` routes them as fields.
log = logging.getLogger("fog_driver.client")


def _log(level: int, event: str, **fields: Any) -> None:
    """One log line: ``event key=value ...`` (values as ``repr`` for strings, else as text), fields in ``extra``."""
    if log.isEnabledFor(level):
        pairs = " ".join(
            f"{key}={value!r}" if isinstance(value, str) else f"{key}={value}" for key, value in fields.items()
        )
        log.log(level, "%s %s", event, pairs, extra={"event": event, **fields})


MAX_BIAS_S = 86400
MAX_REFERENCE_DPH = 1e7
#: Samples kept for the iterator while nobody takes them (a command waiting, a slow caller); beyond this the
#: oldest are dropped and counted in ``angles_dropped``.
MAX_BUFFERED_ANGLES = 100_000
#: How long a command's answer is waited for by default: the daemon answers every control command within 30 s.
REPLY_TIMEOUT_S = 35.0


class ClientBase:
    """What ``Client`` and ``AsyncClient`` hold alike: the address, the token, the timeouts and the reconnection
    policy (checked here), the ``Session``, the latest ``Version``/``Device``/``Status`` and the counters."""

    def __init__(
        self,
        address: str | tuple[str, int] | None = None,
        *,
        token: str | None = None,
        timeout_s: float = GREETING_TIMEOUT_S,
        reconnect: bool = True,
        backoff_initial_s: float = 0.5,
        backoff_max_s: float = 30.0,
        reply_timeout_s: float = REPLY_TIMEOUT_S,
    ) -> None:
        self.host, self.port = parse_target(address)
        self.address = format_address(self.host, self.port)
        if token is not None and (not isinstance(token, str) or not token):
            raise ValueError("token must be a non-empty string (or None)")
        if not (0 < backoff_initial_s <= backoff_max_s) or not timeout_s > 0 or not reply_timeout_s > 0:
            raise ValueError("timeouts and 0 < backoff_initial_s <= backoff_max_s must be positive")
        self.token = token
        self.timeout_s = float(timeout_s)
        self.reconnect = reconnect
        self.backoff_initial_s = float(backoff_initial_s)
        self.backoff_max_s = float(backoff_max_s)
        self.reply_timeout_s = float(reply_timeout_s)
        self.session = Session()
        self.reconnects = 0  #: connections made again after a loss
        self.angles_dropped = 0  #: samples dropped because the caller did not take them in time
        self._watch: dict[str, Any] | None = None  # the ?WATCH in force, sent again after a reconnect

    @property
    def version(self) -> Version | None:
        """The daemon's greeting."""
        return self.session.version

    @property
    def device(self) -> Device | None:
        """The latest DEVICE: the port's state and the instrument."""
        return self.session.device

    @property
    def status_seen(self) -> Status | None:
        """The latest STATUS received (every second from the daemon); ``status()`` asks for one now."""
        return self.session.status

    @property
    def malformed(self) -> int:
        return self.session.malformed

    @property
    def unknown(self) -> int:
        return self.session.unknown


class Reconnection:
    """One reconnection's backoff: the wait before the next attempt (``delay``: ``backoff_initial_s``, doubled
    after each failure up to ``backoff_max_s``), the attempts, and their log lines (never silent)."""

    def __init__(self, client: ClientBase, reason: str) -> None:
        self.client = client
        self.delay = client.backoff_initial_s
        self.attempt = 0
        _log(logging.WARNING, "connection_lost", address=client.address, reason=reason, retry_in_s=self.delay)

    def failed(self, exc: BaseException) -> None:
        self.attempt += 1
        self.delay = min(self.delay * 2.0, self.client.backoff_max_s)
        _log(
            logging.WARNING,
            "reconnect_failed",
            address=self.client.address,
            attempt=self.attempt,
            reason=str(exc),
            retry_in_s=self.delay,
        )

    def succeeded(self) -> None:
        self.client.reconnects += 1
        _log(
            logging.INFO,
            "reconnected",
            address=self.client.address,
            attempt=self.attempt + 1,
            reconnects=self.client.reconnects,
        )


def parse_target(address: str | tuple[str, int] | None) -> tuple[str, int]:
    """``"HOST:PORT"`` (or ``HOST``, ``:PORT``, ``[IPV6]:PORT``), ``(host, port)`` or None (``127.0.0.1:2948``)."""
    if isinstance(address, tuple):
        host, port = address
        if not isinstance(host, str) or not isinstance(port, int) or isinstance(port, bool) or not 0 < port < 65536:
            raise ValueError(f"not an address: {address!r}")
        return host, port
    if address is None:
        return DEFAULT_HOST, DEFAULT_PORT
    return parse_address(address)


def control_args(enable: bool, reference_dph: float) -> dict[str, Any]:
    if not isinstance(enable, bool):
        raise ValueError("enable must be true or false")
    if not enable:
        return {"enable": False}
    if (
        isinstance(reference_dph, bool)
        or not isinstance(reference_dph, (int, float))
        or not math.isfinite(reference_dph)
        or abs(reference_dph) > MAX_REFERENCE_DPH
    ):
        raise ValueError(f"reference_dph must be a number within +-{MAX_REFERENCE_DPH:g} deg/h")
    return {"enable": True, "reference_dph": float(reference_dph)}


def bias_args(seconds: float) -> dict[str, Any]:
    if isinstance(seconds, bool) or not isinstance(seconds, (int, float)) or not 1 <= seconds <= MAX_BIAS_S:
        raise ValueError(f"seconds must be a number between 1 and {MAX_BIAS_S}")
    return {"seconds": int(seconds) if float(seconds).is_integer() else float(seconds)}


def check_reply(name: str, reply: Message) -> Message:
    """``reply`` when it is not an ``ERROR``; else the typed error for it."""
    if not isinstance(reply, ErrorReply):
        return reply
    message = reply.message
    if message == "unauthorized" or name == "AUTH":
        raise Unauthorized(
            f"?{name}: the daemon {'refused the token' if name == 'AUTH' else 'needs a token'}: {printable(message)}",
            message=message,
            command=name,
        )
    if message.startswith("unknown command"):
        raise UnknownCommand(f"the daemon does not know ?{name} (an older fog-driver?)", message=message, command=name)
    raise CommandRefused(f"?{name} refused: {printable(message)}", message=message, command=name)


_M = TypeVar("_M", Angle, Version, Device, Status, Bias, Reply, ErrorReply, Other)


def answer_as(kind: type[_M], reply: Message) -> _M:
    """``reply`` typed as the class ``Session`` pairs with the command: ``?STATUS`` is answered by a ``STATUS``,
    ``?BIAS`` by a ``BIAS``, ``?ZERO``/``?ADAPT``/``?SAVE``/``?RELOAD``/``?WATCH`` by a ``Reply`` (an ``ERROR``
    was raised by ``check_reply``).  For the type checker only: nothing is checked at run time."""
    return cast(_M, reply)


def check_bias(result: Bias) -> Bias:
    """A bias capture's result: returned when ``done``, else ``BiasFailed``."""
    if result.state == "done":
        return result
    reason = printable(result.reason or "no reason given")
    raise BiasFailed(f"bias capture {result.capture_id} failed: {reason}", message=reason, command="BIAS")


def printable(text: str) -> str:
    text = "".join(ch if ch.isprintable() else "?" for ch in text)
    return text if len(text) <= 200 else text[:197] + "..."
