"""What the blocking and the asyncio client share beyond the ``Session``: reading an address, checking the
arguments of the control commands, turning the daemon's answers into values or typed errors, the queue of
messages received and not taken yet (bounded in bytes), and when a watching client takes the daemon for dead."""

from __future__ import annotations

import logging
import math
import time
from collections import deque
from collections.abc import Iterator
from typing import Any, TypeVar, cast

from .errors import BiasFailed, CommandRefused, ProtocolError, Unauthorized, UnknownCommand
from .messages import Angle, Bias, Device, ErrorReply, Message, Other, Reply, Status, Version
from .session import MAX_WATCH_RATE_HZ, Received, Session
from .wire import DEFAULT_HOST, DEFAULT_PORT, GREETING_TIMEOUT_S, MAX_LINE_BYTES, format_address, parse_address

__all__ = [
    "DEFAULT_IDLE_MIN_S",
    "DEFAULT_IDLE_PERIODS",
    "DEFAULT_MAX_BUFFERED_BYTES",
    "MAX_BIAS_S",
    "MAX_REFERENCE_DPH",
    "MAX_TABLE_ANGLE_DEG",
    "MAX_TABLE_DWELL_S",
    "MAX_WATCH_RATE_HZ",
    "MIN_TABLE_DWELL_S",
    "MESSAGE_OVERHEAD_BYTES",
    "MIN_BUFFERED_BYTES",
    "REPLY_TIMEOUT_S",
    "ClientBase",
    "MessageQueue",
    "answer_as",
    "bias_args",
    "table_args",
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


#: ``?BIAS``: the most seconds of a capture; the daemon's bound too (``daemon.limits`` imports it).
MAX_BIAS_S = 86400
MAX_REFERENCE_DPH = 1e7
#: ``?TABLE``: the largest angle (deg), the shortest and longest dwell (s), as the daemon checks them (the longest
#: is the daemon's own bound: ``daemon.limits`` imports it).
MAX_TABLE_ANGLE_DEG = 1e6
MIN_TABLE_DWELL_S = 12.0
MAX_TABLE_DWELL_S = 86400.0
#: How long a command's answer is waited for by default: the daemon answers every control command within 30 s.
REPLY_TIMEOUT_S = 35.0
#: The bytes a client holds for its caller by default (``max_buffered_bytes``): the line being read and the
#: messages received and not taken yet (a command waiting, a slow caller); beyond it the oldest messages are
#: dropped and counted.  About 7,700 samples of 280 bytes: 7.7 s at 1 kHz, 13 min at 10 Hz.
DEFAULT_MAX_BUFFERED_BYTES = 4 * 1024 * 1024
#: What a held message counts beside its line's bytes: the objects made of it, so that many tiny lines cannot
#: hold much more memory than a few large ones.
MESSAGE_OVERHEAD_BYTES = 256
#: The least ``max_buffered_bytes`` may be: room for the line being read and for two of the longest messages
#: in each of the asyncio client's two queues.
MIN_BUFFERED_BYTES = 256 * 1024
#: A watching client takes the daemon for dead when no line of a known class came for ``idle_periods`` times
#: the expected period between samples, and never sooner than ``idle_min_s``.
DEFAULT_IDLE_PERIODS = 5.0
DEFAULT_IDLE_MIN_S = 5.0
#: The BIAS results kept for ``bias()`` (the latest; a daemon runs one capture at a time).
_MAX_BIAS_RESULTS = 16


class MessageQueue:
    """Messages received and not taken yet, in order, bounded in bytes: each counts its line's bytes plus
    ``MESSAGE_OVERHEAD_BYTES``, and when ``bytes`` would pass ``max_bytes`` the oldest are dropped (``put``
    returns them for counting).  A ``ProtocolError`` takes its line's place (no bytes, never dropped; one at
    a time: another while one waits is only counted by the session)."""

    __slots__ = ("_errors", "_items", "bytes", "max_bytes")

    def __init__(self, max_bytes: int) -> None:
        self.max_bytes = max_bytes
        self.bytes = 0  #: what the messages held count, in bytes
        self._items: deque[Received] = deque()
        self._errors = 0

    @staticmethod
    def cost(item: Received) -> int:
        """What ``item`` counts while held, in bytes."""
        return 0 if isinstance(item, ProtocolError) else len(item.line) + MESSAGE_OVERHEAD_BYTES

    def __len__(self) -> int:
        return len(self._items)

    def __iter__(self) -> Iterator[Received]:
        return iter(self._items)

    def put(self, item: Received) -> list[Message]:
        """Hold ``item``; the messages dropped to stay within ``max_bytes``, oldest first."""
        if isinstance(item, ProtocolError):
            if not self._errors:
                self._items.append(item)
                self._errors += 1
            return []
        self._items.append(item)
        self.bytes += self.cost(item)
        return self.trim()

    def trim(self) -> list[Message]:
        """Drop the oldest messages until ``bytes`` is within ``max_bytes``; the messages dropped."""
        dropped: list[Message] = []
        while self.bytes > self.max_bytes and len(self._items) > 1:
            index = 1 if isinstance(self._items[0], ProtocolError) else 0  # one error at most: the next is not
            message = self._items[index]
            del self._items[index]
            assert not isinstance(message, ProtocolError)  # one at a time (see put)
            self.bytes -= self.cost(message)
            dropped.append(message)
        return dropped

    def popleft(self) -> Received:
        item = self._items.popleft()
        if isinstance(item, ProtocolError):
            self._errors -= 1
        else:
            self.bytes -= self.cost(item)
        return item

    def remove(self, message: Message) -> None:
        """Take ``message`` itself (not an equal one) out, when it is held."""
        for index, held in enumerate(self._items):
            if held is message:
                del self._items[index]
                self.bytes -= self.cost(message)
                return


class ClientBase:
    """What ``Client`` and ``AsyncClient`` hold alike: the address, the token, the timeouts, the memory bound and
    the reconnection policy (checked here), the ``Session``, the latest ``Version``/``Device``/``Status``, the
    BIAS results, the idle clock and the counters."""

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
        max_buffered_bytes: int = DEFAULT_MAX_BUFFERED_BYTES,
        idle_periods: float | None = DEFAULT_IDLE_PERIODS,
        idle_min_s: float = DEFAULT_IDLE_MIN_S,
        keep_unknown: bool = False,
    ) -> None:
        self.host, self.port = parse_target(address)
        self.address = format_address(self.host, self.port)
        if token is not None and (not isinstance(token, str) or not token):
            raise ValueError("token must be a non-empty string (or None)")
        if not (0 < backoff_initial_s <= backoff_max_s) or not timeout_s > 0 or not reply_timeout_s > 0:
            raise ValueError("timeouts and 0 < backoff_initial_s <= backoff_max_s must be positive")
        if isinstance(max_buffered_bytes, bool) or not isinstance(max_buffered_bytes, int):
            raise ValueError(f"max_buffered_bytes must be a whole number of bytes, not {max_buffered_bytes!r}")
        if max_buffered_bytes < MIN_BUFFERED_BYTES:
            raise ValueError(f"max_buffered_bytes must be at least {MIN_BUFFERED_BYTES}, not {max_buffered_bytes}")
        if not idle_min_s > 0 or not math.isfinite(idle_min_s) or not (idle_periods is None or idle_periods > 0):
            raise ValueError("idle_min_s must be positive and finite, idle_periods positive (or None: no idle timeout)")
        self.token = token
        self.timeout_s = float(timeout_s)
        self.reconnect = reconnect
        self.backoff_initial_s = float(backoff_initial_s)
        self.backoff_max_s = float(backoff_max_s)
        self.reply_timeout_s = float(reply_timeout_s)
        self.max_buffered_bytes = max_buffered_bytes
        self.idle_periods = None if idle_periods is None else float(idle_periods)
        self.idle_min_s = float(idle_min_s)
        self.keep_unknown = keep_unknown
        self.session = Session()
        self.reconnects = 0  #: connections made again after a loss
        self.angles_dropped = 0  #: samples dropped because the caller did not take them in time
        self.messages_dropped = 0  #: messages of every class dropped so (the samples among them included)
        self.buffered_bytes_peak = 0  #: the most ``buffered_bytes`` held after a read
        self._watch: dict[str, Any] | None = None  # the ?WATCH in force, sent again after a reconnect
        self._heard_at = time.monotonic()  # when the last message of a known class came (or the connection)
        self._bias_results: dict[int | None, Bias] = {}  # BIAS done/failed events, by capture, for bias()
        self._authorized = False  # an AUTH answer came on this connection

    @property
    def buffered_bytes(self) -> int:
        """The bytes held now: the line being read, and what the messages waiting for the caller count
        (``MessageQueue``); at most ``max_buffered_bytes``."""
        return self.session.reader.buffered_bytes + sum(queue.bytes for queue in self._queues())

    def _queues(self) -> list[MessageQueue]:
        """The queues of messages the client holds for its caller."""
        raise NotImplementedError

    def _queue_budget(self) -> int:
        """The bytes the queues may hold together: ``max_buffered_bytes`` less the line being read."""
        return self.max_buffered_bytes - (MAX_LINE_BYTES + 1)

    def idle_timeout_s(self) -> float | None:
        """How long a watching client waits for a line before it takes the daemon for dead (None: not watching,
        or ``idle_periods`` None)::

            idle_timeout_s = max(idle_min_s, idle_periods * period_s)

        with ``period_s`` the expected time between samples: the longer of the watch's ``1 / rate_hz`` and the
        daemon's sample period (``1 / rate_hz`` of its DEVICE, else of its VERSION's ``instrument``); 0 when
        neither is known.  Only lines of a known class count: a daemon sends STATUS every second to an
        authorized client, so a link that is down is not taken for a dead daemon."""
        watch = self._watch
        if self.idle_periods is None or watch is None or watch.get("enable", True) is False:
            return None
        period_s = 0.0
        for rate_hz in (watch.get("rate_hz"), self._device_rate_hz()):
            if isinstance(rate_hz, (int, float)) and not isinstance(rate_hz, bool) and 0 < rate_hz < math.inf:
                period_s = max(period_s, 1.0 / rate_hz)
        return max(self.idle_min_s, self.idle_periods * period_s)

    def _device_rate_hz(self) -> float | None:
        device, version = self.session.device, self.session.version
        if device is not None and device.rate_hz is not None:
            return device.rate_hz
        instrument = version.instrument if version is not None else None
        rate_hz = instrument.get("rate_hz") if instrument is not None else None
        return float(rate_hz) if isinstance(rate_hz, (int, float)) and not isinstance(rate_hz, bool) else None

    def _idle_reason(self, idle_s: float) -> str:
        hint = (
            ""
            if self._authorized
            else " (no ?AUTH on this connection: a daemon with a token sends no samples before it)"
        )
        return f"no line from the daemon for {idle_s:g} s while watching{hint}"

    def _connected(self) -> None:
        """A new connection: the idle clock starts now, and BIAS results of the connection before are gone."""
        self._heard_at = time.monotonic()
        self._authorized = False
        self._bias_results.clear()

    def _received(self, data: bytes) -> list[Received]:
        """What ``data`` completes, for the caller: the session's messages but those of an unknown class (counted
        in ``unknown``, dropped unless ``keep_unknown``), a ``ProtocolError`` (with the address) in the place of
        an over-long line.  A message of a known class restarts the idle clock; a BIAS result is kept for
        ``bias()``."""
        out: list[Received] = []
        for item in self.session.receive(data):
            if isinstance(item, ProtocolError):
                item = ProtocolError(f"{self.address}: {item}")
            elif isinstance(item, Other):
                if not self.keep_unknown:
                    continue
            else:
                self._heard_at = time.monotonic()
                if isinstance(item, Reply) and item.kind == "AUTH":
                    self._authorized = True
                elif isinstance(item, Bias) and item.state in ("done", "failed"):
                    self._bias_results[item.capture_id] = item
                    while len(self._bias_results) > _MAX_BIAS_RESULTS:
                        del self._bias_results[next(iter(self._bias_results))]
            out.append(item)
        return out

    def _dropped(self, messages: list[Message]) -> None:
        """Count messages the queues dropped to stay within ``max_buffered_bytes``."""
        self.messages_dropped += len(messages)
        self.angles_dropped += sum(isinstance(m, Angle) for m in messages)

    def _note_peak(self) -> None:
        self.buffered_bytes_peak = max(self.buffered_bytes_peak, self.buffered_bytes)

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


def table_args(angle_deg: float, dwell_s: float, angle_start_deg: float | None = None) -> dict[str, Any]:
    """``?TABLE``'s argument object, checked as the daemon checks it (``ValueError`` when it would refuse)."""

    def number(v: Any) -> bool:
        return not isinstance(v, bool) and isinstance(v, (int, float)) and math.isfinite(v)

    for name, v in (("angle_deg", angle_deg), ("angle_start_deg", angle_start_deg)):
        if v is None and name == "angle_start_deg":
            continue
        if not (number(v) and abs(float(v)) <= MAX_TABLE_ANGLE_DEG):  # type: ignore[arg-type]  # a number
            raise ValueError(f"{name} must be a number within +-{MAX_TABLE_ANGLE_DEG:g} degrees")
    if not (number(dwell_s) and MIN_TABLE_DWELL_S <= dwell_s <= MAX_TABLE_DWELL_S):
        raise ValueError(f"dwell_s must be a number of seconds from {MIN_TABLE_DWELL_S:g} to {MAX_TABLE_DWELL_S:g}")
    args: dict[str, Any] = {"angle_deg": float(angle_deg), "dwell_s": float(dwell_s)}
    if angle_start_deg is not None:
        args["angle_start_deg"] = float(angle_start_deg)
    return args


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
