"""The client side of the daemon's protocol without I/O (the ``Client`` and ``AsyncClient`` wrap it).

``Session`` turns received bytes into typed messages (``receive``) and requests into bytes (``request``),
and keeps what a client must: the latest ``Version``, ``Device`` and ``Status``; which message answers
which request (the daemon answers each command with one line, in order; events such as a ``BIAS`` result
or the periodic ``STATUS`` come in between); and the sequence of the samples across connections, so the
first ``Angle`` after a reconnect carries the ``Gap`` (``connection_made`` and ``connection_lost`` say when
the I/O layer's connection changed).  Defensive as the protocol asks: a line that is not a JSON object with a
string ``class``, and an unusable ``ANGLE``, are skipped and counted (``malformed``); objects of classes this
library does not know are counted (``unknown``) and passed on as ``Other`` (the clients drop them); a line over
64 KiB (or that many bytes without a newline) is dropped up to its newline and passed on, in its place, as a
``ProtocolError`` for the client to raise.  The bytes held for a line being read are at most 64 KiB + 1.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable
from dataclasses import replace
from typing import Any

from .errors import ProtocolError
from .messages import Angle, Bias, Device, ErrorReply, Gap, Message, Other, Reply, Status, Version, message_from
from .wire import MAX_LINE_BYTES, LineReader, command_line, parse_line

__all__ = ["MAX_WATCH_RATE_HZ", "Received", "Request", "Session"]

#: The highest ``?WATCH`` ``rate_hz`` a daemon takes (the protocol's bound, ``0 < rate_hz <= 10000``).
MAX_WATCH_RATE_HZ = 10_000

#: What ``Session.receive`` gives: a message, or the ``ProtocolError`` of an over-long line in its place.
Received = Message | ProtocolError


class Request:
    """One command sent: its name and, once it came, the message that answers it."""

    __slots__ = ("args", "name", "reply")

    def __init__(self, name: str, args: dict[str, Any] | None) -> None:
        self.name = name
        self.args = args
        self.reply: Message | None = None

    def __repr__(self) -> str:
        return f"Request({self.name!r}, {self.args!r}, reply={self.reply!r})"


def answers(name: str, message: Message) -> bool:
    """Whether ``message`` is the answer to the command ``name`` (a BIAS result is an event, not the answer
    to ``?BIAS``: its ``started`` acknowledgement is; a periodic STATUS answers ``?STATUS`` as well as the
    one asked for would, being no older)."""
    if isinstance(message, ErrorReply):
        return message.command in (name, None)
    if isinstance(message, Reply):
        return message.kind == name
    if isinstance(message, Bias):
        return name == "BIAS" and message.state == "started"
    if isinstance(message, Status):
        return name == "STATUS"
    if isinstance(message, Version):
        return name == "VERSION"
    return False


class Session:
    """See the module docstring.  ``clock`` (monotonic seconds) times the outages reported in ``Gap``."""

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self.clock = clock
        self.reader = LineReader()
        self.version: Version | None = None
        self.device: Device | None = None
        self.status: Status | None = None
        self.malformed = 0  #: lines skipped: oversized, not JSON, not a protocol object, an unusable ANGLE
        self.unknown = 0  #: objects of classes this library does not know (ignored)
        self.connections = 0  #: connections made (``connection_made``)
        self.last_seq: int | None = None  #: the last sample's ``seq``
        self._pending: deque[Request] = deque()
        self._lost_at: float | None = None  # when the connection before this one was lost

    # -- connection state -----------------------------------------------------------------------------

    def connection_made(self) -> None:
        """A new connection (the first, or one after a loss): the line buffer starts empty, and the first
        sample on it will carry the ``Gap`` since the last one received, if any was."""
        self.connections += 1
        self.reader = LineReader()
        self._pending.clear()

    def connection_lost(self) -> None:
        """The connection went: unanswered requests stay unanswered (the caller raises for them)."""
        if self._lost_at is None:
            self._lost_at = self.clock()
        for request in self._pending:
            request.reply = None
        self._pending.clear()

    # -- requests -------------------------------------------------------------------------------------

    def request(self, name: str, args: dict[str, Any] | None = None) -> tuple[Request, bytes]:
        """A command (``?NAME;`` or ``?NAME={json};``) to send, and its ``Request``, answered when a received
        message answers it (``request.reply``)."""
        data = command_line(name, args)
        request = Request(name, args)
        self._pending.append(request)
        return request, data

    # -- received bytes -------------------------------------------------------------------------------

    def receive(self, data: bytes) -> list[Received]:
        """The messages in ``data`` (bytes as read; a line may be split anywhere), in order, with a
        ``ProtocolError`` in the place of each line over ``MAX_LINE_BYTES``."""
        out: list[Received] = []
        for line in self.reader.events(data):
            if not isinstance(line, bytes):  # OVERLONG: at its newline, or once its bytes passed the bound
                out.append(
                    ProtocolError(f"the daemon sent a line over {MAX_LINE_BYTES} bytes (not the protocol; dropped)")
                )
                continue
            if not line.strip():
                continue  # an empty line is a keep-alive, not an error
            obj = parse_line(line)
            if obj is None:
                self.malformed += 1
                continue
            message = message_from(obj, line.rstrip(b"\r"))
            if message is None:  # an ANGLE that is no usable sample
                self.malformed += 1
                continue
            if isinstance(message, Other):
                self.unknown += 1
            out.append(self._observe(message))
        return out

    def _observe(self, message: Message) -> Message:
        if isinstance(message, Angle):
            message = self._sequence(message)
        elif isinstance(message, Version):
            self.version = message
        elif isinstance(message, Device):
            self.device = message
        elif isinstance(message, Status):
            self.status = message
        if self._pending and answers(self._pending[0].name, message):
            self._pending.popleft().reply = message
        return message

    def _sequence(self, angle: Angle) -> Angle:
        last, lost_at = self.last_seq, self._lost_at
        self.last_seq = angle.seq
        if lost_at is None:
            return angle
        self._lost_at = None
        if last is None:
            return angle
        down_s = max(0.0, self.clock() - lost_at)
        if angle.seq > last:
            gap = Gap(last, angle.seq, angle.seq - last - 1, down_s, "the connection was lost and made again")
        else:
            gap = Gap(last, angle.seq, None, down_s, "the daemon's sequence went back: it restarted")
        return replace(angle, gap_before=gap)

    @staticmethod
    def watch_args(rate_hz: float | None) -> dict[str, Any]:
        """``?WATCH``'s argument for a watch at ``rate_hz`` (None: every sample)."""
        if rate_hz is None:
            return {"enable": True}
        if not (
            isinstance(rate_hz, (int, float)) and not isinstance(rate_hz, bool) and 0 < rate_hz <= MAX_WATCH_RATE_HZ
        ):
            raise ValueError(f"rate_hz must be a number, 0 < rate_hz <= {MAX_WATCH_RATE_HZ}, not {rate_hz!r}")
        return {"enable": True, "rate_hz": rate_hz}
