"""One NDJSON client's connection as a state machine, sans-IO: what the client's bytes mean, and what to do.

The protocol it speaks is written in ``docs/reference/ndjson.md`` (the lines, classes, commands and their
answers); ``limits.py`` holds how much of it a client may use.

``Connection.receive(data)`` reads a client's bytes (``ndjson.LineBuffer``, limited to ``max_line_bytes``) and
yields *actions*, in order, for the I/O layer (``hub.py``) to carry out: ``Send`` an object, ``SendVersion``,
``SendDevice``, hand a ``Control`` command to the service (and send ``control_reply`` of its answer), ``Close``
after what is queued, note that the client is ``Authorized`` or its ``WatchChanged``, or ``Log`` an event.  It
keeps the client's policy (WATCH and its decimation on device time, ``keep_angles``), its authorization, and
its rate limit.  No socket, no event loop: tests drive it with bytes and a clock.

``receive`` is lazy like ``LineBuffer.feed``: each line is read when the previous line's actions are done, so a
``Control`` command is answered before the next line counts against the rate limit.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

from ..ndjson import OVERLONG, UNTERMINATED, Command, CommandError, LineBuffer, parse_command
from .guards import AuthThrottle, token_matches
from .limits import (
    COMMAND_WINDOW_S,
    MAX_AUTH_FAILURES,
    MAX_COMMANDS_PER_S,
    MAX_EXCESS_COMMANDS,
    MAX_UNTERMINATED_BYTES,
    MAX_WATCH_RATE_HZ,
    TABLE_INTERVAL_S,
)

__all__ = [
    "HUB_COMMANDS",
    "Action",
    "AuthGate",
    "Authorized",
    "Close",
    "Connection",
    "Control",
    "Log",
    "Send",
    "SendDevice",
    "SendVersion",
    "WatchChanged",
    "control_error",
    "control_reply",
    "error",
    "is_positive_finite",
]


# -- actions --------------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Send:
    """Queue one object for the client (the I/O layer encodes it)."""

    obj: dict


@dataclass(frozen=True, slots=True)
class SendVersion:
    """Queue the VERSION object (the service's, made on the I/O layer's thread); without ``identity``, its
    release and protocol version only (a client that has not authorized on a token-protected daemon)."""

    identity: bool = True


@dataclass(frozen=True, slots=True)
class SendDevice:
    """Queue the current DEVICE object, when an instrument is known."""


@dataclass(frozen=True, slots=True)
class Control:
    """Hand the command to the service; answer with ``control_reply`` (or ``control_error``) of its answer."""

    name: str
    args: dict


@dataclass(frozen=True, slots=True)
class Close:
    """Send what is queued, then close the connection."""


@dataclass(frozen=True, slots=True)
class Authorized:
    """The connection was authorized just now (its ``?AUTH`` deadline no longer applies)."""


@dataclass(frozen=True, slots=True)
class WatchChanged:
    """The client's WATCH was turned on or off (the hub counts the watching clients)."""

    enable: bool


@dataclass(frozen=True, slots=True)
class Log:
    """A per-client log line (the I/O layer adds the client's id and peer, and rate-limits it)."""

    level: str
    event: str
    fields: dict = field(default_factory=dict)


Action = Send | SendVersion | SendDevice | Control | Close | Authorized | WatchChanged | Log


def error(message: str, command: str | None = None) -> Send:
    """An ERROR line (``command`` omitted when None)."""
    return Send({"class": "ERROR", "message": message, "command": command})


def is_positive_finite(value: Any) -> bool:
    """True for an int or float (not a bool) with ``0 < value < inf``."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and 0 < value < math.inf


def control_reply(name: str, reply: Any) -> dict:
    """The line answering ``?NAME`` from the service's ``reply``: a dict gets ``class`` NAME when it has none,
    an ERROR gets ``command`` NAME when it has none; ``None`` means an unknown command."""
    if not isinstance(reply, dict):
        message = f"unknown command ?{name}" if reply is None else "internal: bad reply"
        return {"class": "ERROR", "message": message, "command": name}
    if "class" not in reply:
        return {"class": name, **reply}
    if reply["class"] == "ERROR" and "command" not in reply:
        return {**reply, "command": name}
    return reply


def control_error(name: str, exc: BaseException) -> dict:
    """The ERROR line for a command whose service call raised ``exc``: its message, else its type's name."""
    return {"class": "ERROR", "message": str(exc) or type(exc).__name__, "command": name}


# -- authorization shared by the connections ------------------------------------------------------------------


class AuthGate:
    """The daemon's client token (None: every connection is authorized), whether the ANGLE stream is open to
    clients without it (``open_stream``), and the per-peer backoff of wrong ``?AUTH`` tokens, shared by every
    connection of one hub."""

    def __init__(self, token: str | None, throttle: AuthThrottle, *, open_stream: bool = False) -> None:
        self.token = token
        self.throttle = throttle
        self.open_stream = open_stream

    def attempt(self, peer: str, token: Any, now: float) -> tuple[str, float]:
        """``("ok", 0)``, ``("blocked", seconds still to wait)`` or ``("wrong", seconds now blocked for)``
        (``AuthThrottle.judge``: while the address is blocked the token is not compared, right or wrong)."""
        if self.token is None:
            return "ok", 0.0
        expected = self.token
        return self.throttle.judge(peer, lambda: token_matches(token, expected), now)


# -- one connection -------------------------------------------------------------------------------------------


class Connection:
    """One client's protocol state (see the module docstring).  ``clock``: monotonic seconds."""

    def __init__(
        self,
        peer_address: str,
        gate: AuthGate,
        *,
        max_line_bytes: int,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.peer_address = peer_address
        self.gate = gate
        self.clock = clock
        self.max_line_bytes = max_line_bytes
        self.lines = LineBuffer(max_line_bytes, MAX_UNTERMINATED_BYTES)
        self.authorized = gate.token is None
        self.auth_failures = 0
        self.watch = False
        self.rate_hz: float | None = None
        self.last_bucket: int | None = None
        self.window_start = clock()
        self.window_count = 0
        self.excess = 0
        self.last_table: float | None = None  #: when this client's last ?TABLE was taken (its clock)
        self.closing = False  #: a Close was given: nothing more is read

    # -- events from the I/O layer ---------------------------------------------------------------------------

    def greeting(self) -> list[Action]:
        """What a new connection gets: VERSION, and DEVICE when it is authorized already."""
        return [SendVersion(), SendDevice()] if self.authorized else [SendVersion(identity=False)]

    def receive(self, data: bytes) -> Iterator[Action]:
        """The actions the client's ``data`` calls for, in order (lazily); none once the connection closes."""
        for item in self.lines.feed(data):
            if item is UNTERMINATED:
                yield error(f"more than {MAX_UNTERMINATED_BYTES} bytes without a newline: closing")
                yield from self._close()
            elif item is OVERLONG:
                admitted = self._admit()
                if admitted is None:
                    yield error(f"line longer than {self.max_line_bytes} bytes: discarded")
                else:
                    yield from admitted
            else:
                yield from self._line(item)
            if self.closing:
                return

    def end_of_input(self) -> list[Action]:
        """The client closed its side: send what is queued (the answers), then close."""
        return self._close()

    @property
    def reads_angles(self) -> bool:
        """The client gets the ANGLE lines its WATCH asks for: it watches, and it is authorized or the daemon
        opens the stream to everyone (``open_stream``)."""
        return self.watch and (self.authorized or self.gate.open_stream)

    def auth_deadline_passed(self, deadline_s: float) -> list[Action]:
        """The client did not authorize within ``deadline_s`` of connecting: ERROR, close (unless it reads the
        open stream: a reader needs no token there)."""
        if self.authorized or self.closing or (self.gate.open_stream and self.watch):
            return []
        return [
            Log("info", "client_unauthorized", {"deadline_s": deadline_s}),
            error(f"not authorized within {deadline_s:g} s: closing", "AUTH"),
            *self._close(),
        ]

    def token_changed(self) -> list[Action]:
        """The daemon's token changed: no session authorized by the old one may outlive it."""
        return [error("the client token changed: connect again", "AUTH"), *self._close()]

    # -- the WATCH policy, on the publishing side ----------------------------------------------------------------

    def keep_angles(self, items: list[tuple[float, bytes]]) -> list[bytes]:
        """The ANGLE lines of one batch (``(t_s, line)``) this client's WATCH keeps: all of them without
        ``rate_hz``, else the first of each period ``[k / rate_hz, (k + 1) / rate_hz)`` of device time,
        ``k = floor(t_s * rate_hz)`` (the decimation carries over from batch to batch)."""
        rate = self.rate_hz
        if rate is None:
            return [line for _, line in items]
        kept = []
        last = self.last_bucket
        for t_s, line in items:
            bucket = math.floor(t_s * rate)
            if bucket != last:
                kept.append(line)
                last = bucket
        self.last_bucket = last
        return kept

    # -- lines ---------------------------------------------------------------------------------------------------

    def _close(self) -> list[Action]:
        if self.closing:
            return []
        self.closing = True
        return [Close()]

    def _admit(self) -> list[Action] | None:
        """Rate limit on every line received: None when it may proceed, else the actions refusing it.  The
        first excess line of a window is answered with ``ERROR``, the others of that window are dropped
        without an answer (a flood must not make the daemon write a line for each of its lines), and the
        ``MAX_EXCESS_COMMANDS``-th excess line closes."""
        now = self.clock()
        if now - self.window_start >= COMMAND_WINDOW_S:
            self.window_start = now
            self.window_count = 0
        self.window_count += 1
        if self.window_count <= MAX_COMMANDS_PER_S:
            return None
        self.excess += 1
        if self.excess >= MAX_EXCESS_COMMANDS:
            return [error(f"{MAX_EXCESS_COMMANDS} commands over the rate limit: closing"), *self._close()]
        if self.window_count > MAX_COMMANDS_PER_S + 1:
            return []  # refused, already told in this window
        return [error(f"more than {MAX_COMMANDS_PER_S} commands per second: refused")]

    def _line(self, raw: bytes) -> list[Action]:
        refused = self._admit()  # every line counts, an empty or blank one too
        if refused is not None:
            return refused
        command = parse_command(raw)
        if command is None:
            return []
        if isinstance(command, CommandError):
            return [error(command.message, command.command)]
        handler = HUB_COMMANDS.get(command.name)
        if handler is not None:
            return handler(self, command)
        if not self.authorized:
            return [error("unauthorized", command.name)]
        if command.name == "TABLE":  # one dwell per TABLE_INTERVAL_S from one client: a dwell lasts 12 s or more
            now = self.clock()
            if self.last_table is not None and now - self.last_table < TABLE_INTERVAL_S:
                return [error(f"at most one ?TABLE per {TABLE_INTERVAL_S:g} s: refused", command.name)]
            self.last_table = now
        return [Control(command.name, command.args)]

    def _watch(self, command: Command) -> list[Action]:
        """``?WATCH;`` reports the policy; ``?WATCH={...};`` replaces it (``enable`` true unless given,
        ``rate_hz`` every sample unless given) and restarts the decimation.  Enabling it needs the token on a
        token-protected daemon (unless ``open_stream``): ``ERROR`` "unauthorized", the policy unchanged."""
        actions: list[Action] = []
        if command.has_args:
            args = command.args
            enable = args.get("enable", True)
            if not isinstance(enable, bool):
                return [error("enable must be true or false", "WATCH")]
            rate = args.get("rate_hz")
            if rate is not None and not (is_positive_finite(rate) and rate <= MAX_WATCH_RATE_HZ):
                return [error(f"rate_hz must be a number > 0 and <= {MAX_WATCH_RATE_HZ}", "WATCH")]
            if enable and not (self.authorized or self.gate.open_stream):
                return [error("unauthorized", "WATCH")]  # reading needs the token: ?AUTH first
            if enable != self.watch:
                actions.append(WatchChanged(enable))
            self.watch = enable
            self.rate_hz = rate
            self.last_bucket = None
        actions.append(Send({"class": "WATCH", "enable": self.watch, "rate_hz": self.rate_hz}))
        return actions

    def _version(self, command: Command) -> list[Action]:
        return [SendVersion(identity=self.authorized)]

    def _auth(self, command: Command) -> list[Action]:
        """``?AUTH``: compare the token (never while the peer address is in its backoff), authorize or refuse."""
        verdict, seconds = self.gate.attempt(self.peer_address, command.args.get("token"), self.clock())
        if verdict == "ok":
            return self._authorize()
        if verdict == "blocked":
            return self._refuse_auth(f"too many failed attempts, retry in {math.ceil(seconds)} s")
        log = Log("warning", "auth_failed", {"failures": self.auth_failures + 1, "blocked_s": seconds})
        return [log, *self._refuse_auth("bad token")]

    def _authorize(self) -> list[Action]:
        """AUTH, then (when this authorized the client) the DEVICE it did not get before."""
        newly = not self.authorized
        self.authorized = True
        actions: list[Action] = [Authorized(), Send({"class": "AUTH", "authorized": True})]
        if newly:
            actions.append(SendDevice())
        return actions

    def _refuse_auth(self, message: str) -> list[Action]:
        """ERROR for a failed or refused ``?AUTH``; the ``MAX_AUTH_FAILURES``-th closes the connection."""
        self.auth_failures += 1
        if self.auth_failures >= MAX_AUTH_FAILURES:
            return [error(f"{message}: closing", "AUTH"), *self._close()]
        return [error(message, "AUTH")]


#: The commands the hub answers itself (every other one goes to the service's table, ``commands.py``).
HUB_COMMANDS: dict[str, Callable[[Connection, Command], list[Action]]] = {
    "WATCH": Connection._watch,
    "VERSION": Connection._version,
    "AUTH": Connection._auth,
}
