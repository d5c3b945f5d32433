"""``Client``: the blocking client of ``fog-driver run`` (one thread; see ``fog_driver.client``).

The client reads only when asked: ``angles()`` and ``messages()`` read as they yield; a command sends its
line and reads until its answer, keeping what arrives meanwhile (samples, events) for the iterators.  A lost
connection while iterating is made again with backoff (``backoff_initial_s`` doubling up to ``backoff_max_s``,
each attempt logged), ``?AUTH`` and ``?WATCH`` are sent again, and the first sample after it carries the
``Gap``; a lost connection while a command waits raises ``ConnectionLost`` (the command is not sent again: it
may have been carried out).

Bounded: what the client holds for its caller (the line being read, the messages not taken yet) is at most
``max_buffered_bytes``, the oldest messages dropped beyond it (counted); messages of a class the library does
not know are dropped (counted in ``unknown``) unless ``keep_unknown``; a line over 64 KiB is a
``ProtocolError``.  Every wait has a deadline that holds while bytes keep arriving: a daemon trickling junk
keeps no call alive.  While watching, a daemon that sends no line of a known class for ``idle_timeout_s()``
is taken for dead: the connection is dropped and made again (``ConnectionLost`` with ``reconnect=False``).
"""

from __future__ import annotations

import contextlib
import select
import socket
import threading
import time
from collections.abc import Iterator
from typing import Any

from .errors import ClientError, ConnectError, ConnectionLost, NoReply, ProtocolError
from .messages import Angle, Bias, ErrorReply, Message, Reply, Status, Version
from .protocol import (
    ClientBase,
    MessageQueue,
    Reconnection,
    answer_as,
    bias_args,
    check_bias,
    check_reply,
    control_args,
    printable,
    table_args,
)
from .session import Request

__all__ = ["Client"]

_RECV_BYTES = 65536
#: The longest one wait on the socket lasts; a longer timeout is waited in several (``select`` takes no timeout
#: beyond the platform's ``time_t``: 1e10 s was an ``OverflowError``, and infinity is none).
_LONGEST_WAIT_S = 3600.0


class Client(ClientBase):
    """A connection to a daemon (``address`` ``HOST:PORT``, default ``127.0.0.1:2948``), its token, and its
    reconnection policy.  Use it as a context manager (``connect`` on enter, ``close`` on exit)::

        with Client("127.0.0.1:2948", token=os.environ.get("FOG_DRIVER_TOKEN")) as c:
            for a in c.angles(rate_hz=10):
                print(a.seq, a.angle_arcsec, a.drift_dph)

    Parameters (``ClientBase``): ``address``; ``token`` (sent with ``?AUTH`` on every connection, before
    ``?WATCH``); ``timeout_s`` (5: to connect, for the greeting, ``?AUTH`` and sending a command);
    ``reconnect`` (True); ``backoff_initial_s`` (0.5) and ``backoff_max_s`` (30); ``reply_timeout_s`` (35: for
    a command's answer); ``max_buffered_bytes`` (4 MiB, at least 256 KiB: the line being read and the
    messages not taken yet, each counting its line and 256 bytes; beyond it the oldest are dropped);
    ``idle_periods`` (5; None: no idle timeout) and ``idle_min_s`` (5): while watching, no line of a known
    class for ``max(idle_min_s, idle_periods * period)`` (``idle_timeout_s()``) is a dead daemon, handled as a
    lost connection; ``keep_unknown`` (False: messages of an unknown class are dropped, not queued; True:
    ``messages`` and ``poll`` give them as ``Other``).  ``version``, ``device`` and ``status_seen`` hold the
    latest of each the daemon sent.  Counters: ``reconnects``, ``angles_dropped`` (samples the caller did not
    take in time), ``messages_dropped`` (of every class), ``malformed`` and ``unknown`` lines;
    ``buffered_bytes`` (now) and ``buffered_bytes_peak``.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._sock: socket.socket | None = None
        self._inbox = MessageQueue(self._queue_budget())
        self._closed = threading.Event()

    def _queues(self) -> list[MessageQueue]:
        return [self._inbox]

    # -- connection -------------------------------------------------------------------------------------

    def __enter__(self) -> Client:
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def connect(self) -> Version:
        """Connect, read the VERSION greeting, authorize with the token (and then ask for VERSION again: the
        greeting before ``?AUTH`` held the release only); ``ConnectError`` when the daemon cannot be reached (at
        once: a first connection is not retried), ``Unauthorized`` when it refuses the token."""
        if self._closed.is_set():
            raise ConnectionLost(f"{self.address}: the client was closed")
        self._open()
        version = self.session.version
        assert version is not None  # _open read the greeting, or raised
        return version

    def close(self) -> None:
        """Close the connection (from any thread: an iteration or a reconnect wait in progress ends with
        ``ConnectionLost``)."""
        self._closed.set()
        self._close_socket()

    def fileno(self) -> int:
        """The socket's descriptor (for a caller's own ``select``; then ``poll(0)`` reads what it holds)."""
        if self._sock is None:
            raise ConnectionLost(f"{self.address}: not connected")
        return self._sock.fileno()

    def _open(self) -> socket.socket:
        """Connect, greet, authorize and watch again; the socket (also ``self._sock``), or an error raised."""
        hint = "(is `fog-driver run` running?)"
        try:
            sock = socket.create_connection((self.host, self.port), timeout=min(self.timeout_s, _LONGEST_WAIT_S))
        except OSError as exc:
            raise ConnectError(f"could not connect to {self.address}: {_reason(exc)} {hint}") from None
        sock.setblocking(False)
        self._sock = sock
        self.session.connection_made()
        self._connected()
        try:
            self._greeting(hint)
            if self.token is not None:
                self._command("AUTH", {"token": self.token}, connecting=True)
                # the greeting before ?AUTH held the release only: VERSION again, whole (model, instrument)
                self._command("VERSION", connecting=True)
            if self._watch is not None:
                self._command("WATCH", self._watch, connecting=True)
        except BaseException:
            self._drop()
            raise
        return sock

    def _greeting(self, hint: str) -> None:
        """Read up to the VERSION greeting (kept with anything before it for ``messages``)."""
        greeting = self.session.request("VERSION")[0]  # the greeting answers it (nothing is sent)
        deadline = time.monotonic() + self.timeout_s
        while greeting.reply is None:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise ConnectError(
                    f"could not connect to {self.address}: no VERSION greeting within "
                    f"{self.timeout_s:g} s (not a fog-driver daemon?)"
                )
            try:
                self._read_once(remaining)
            except _Lost as exc:
                raise ConnectError(
                    f"could not connect to {self.address}: {exc.reason} before the VERSION greeting {hint}"
                ) from None
        if isinstance(greeting.reply, ErrorReply):  # refused at once: too many clients
            raise ConnectError(
                f"could not connect to {self.address}: the daemon refused the connection: "
                f"{printable(greeting.reply.message)}"
            )

    def _close_socket(self) -> None:
        sock, self._sock = self._sock, None
        if sock is not None:
            with contextlib.suppress(OSError):
                sock.shutdown(socket.SHUT_RDWR)  # wakes a select on it in another thread (close alone does not)
            with contextlib.suppress(OSError):
                sock.close()

    def _drop(self) -> None:
        self._close_socket()
        self.session.connection_lost()

    def _reconnect(self, reason: str) -> None:
        """Connect again with backoff until it works or the client is closed (``ConnectionLost`` then)."""
        self._drop()
        if self._closed.is_set():  # by close(), maybe from another thread: the reason is that
            raise ConnectionLost(f"{self.address}: the client was closed")
        if not self.reconnect:
            raise ConnectionLost(f"{self.address}: {reason}", reason)
        backoff = Reconnection(self, reason)
        while True:
            if self._closed.wait(backoff.delay):
                raise ConnectionLost(f"{self.address}: {reason}; closed while reconnecting")
            try:
                self._open()
            except (ConnectError, ConnectionLost, NoReply) as exc:
                backoff.failed(exc)
                continue
            backoff.succeeded()
            return

    # -- reading ----------------------------------------------------------------------------------------

    def _read_once(self, timeout_s: float | None) -> bool:
        """Read what the socket holds, waiting up to ``timeout_s`` for it (at most ``_LONGEST_WAIT_S``: the
        callers wait again until their deadline); False when nothing came.  ``_Lost`` when the connection went."""
        sock = self._sock
        if sock is None:
            raise _Lost("not connected")
        try:
            if not select.select(
                [sock], [], [], _LONGEST_WAIT_S if timeout_s is None else min(timeout_s, _LONGEST_WAIT_S)
            )[0]:
                return False
            data = sock.recv(_RECV_BYTES)
        except BlockingIOError:
            return False
        except (OSError, ValueError) as exc:  # ValueError: closed from another thread (fd -1)
            raise _Lost(f"lost the connection: {_reason(exc) if isinstance(exc, OSError) else 'closed'}") from None
        if not data:
            raise _Lost("the daemon closed the connection")
        for item in self._received(data):
            self._dropped(self._inbox.put(item))
        self._note_peak()
        return True

    def _next(self, timeout_s: float | None) -> Message | None:
        """The next message received (None when none within ``timeout_s``, however many bytes came meanwhile);
        reconnects when allowed, also when the daemon is idle while watching (``idle_timeout_s``).
        ``ProtocolError`` in the place of an over-long line."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while not self._inbox:
            if self._closed.is_set():
                raise ConnectionLost(f"{self.address}: the client was closed")
            idle_s = self.idle_timeout_s()
            ends = [end for end in (deadline, None if idle_s is None else self._heard_at + idle_s) if end is not None]
            try:
                self._read_once(None if not ends else max(0.0, min(ends) - time.monotonic()))
            except _Lost as exc:
                self._reconnect(exc.reason)
                continue
            if self._inbox:
                break
            now = time.monotonic()
            if idle_s is not None and now >= self._heard_at + idle_s:
                self._reconnect(self._idle_reason(idle_s))
            elif deadline is not None and now >= deadline:
                return None
        item = self._inbox.popleft()
        if isinstance(item, ProtocolError):
            raise item
        return item

    def poll(self, timeout_s: float | None = 0.0) -> Message | None:
        """The next message of any kind, waiting up to ``timeout_s`` (0: only what has arrived; None: no limit)."""
        return self._next(timeout_s)

    def messages(self, timeout_s: float | None = None) -> Iterator[Message]:
        """Every message as it comes (``Angle``, ``Device``, ``Status``, ``Bias`` events, ``ErrorReply`` ...);
        ends when nothing came for ``timeout_s`` (None: never)."""
        while (message := self._next(timeout_s)) is not None:
            yield message

    def angles(self, rate_hz: float | None = None, *, timeout_s: float | None = None) -> Iterator[Angle]:
        """Watch the samples (``?WATCH``, decimated by the daemon to ``rate_hz`` by device time; None: every
        sample) and yield them; ends when no sample came for ``timeout_s`` (None: never), whatever else
        came.  Other messages update ``device`` and ``status_seen``; a BIAS result is kept for ``bias``.
        ``ProtocolError`` for a line over 64 KiB (after the samples before it; not reconnected)."""
        self.watch(rate_hz)
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while True:
            message = self._next(None if deadline is None else max(0.0, deadline - time.monotonic()))
            if message is None:
                return
            if isinstance(message, Angle):
                yield message
                if timeout_s is not None:
                    deadline = time.monotonic() + timeout_s
            elif deadline is not None and time.monotonic() >= deadline:
                return

    def watch(self, rate_hz: float | None = None) -> Reply:
        """Start (or change) the watch without reading samples yet (``angles`` does it for you)."""
        args = self.session.watch_args(rate_hz)
        reply = answer_as(Reply, self._command("WATCH", args))
        self._watch = args
        return reply

    # -- commands ---------------------------------------------------------------------------------------

    def _wait(
        self, request: Request, timeout_s: float, what: str, *, keep: bool = False, connecting: bool = False
    ) -> Message:
        deadline = time.monotonic() + timeout_s
        error: type[ClientError]
        while request.reply is None:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                error = ConnectError if connecting else NoReply
                raise error(f"{self.address}: no {what} within {timeout_s:g} s")
            try:
                self._read_once(remaining)
            except _Lost as exc:
                self._drop()
                error = ConnectError if connecting else ConnectionLost
                raise error(f"{self.address}: {exc.reason} while waiting for {what}") from None
        reply = request.reply
        if not keep:  # the answer is returned, not also queued for the iterators
            self._inbox.remove(reply)
        return reply

    def _command(
        self, name: str, args: dict[str, Any] | None = None, *, connecting: bool = False, timeout_s: float | None = None
    ) -> Message:
        sock = self._sock
        if sock is None:
            if connecting or self._closed.is_set():
                raise ConnectionLost(f"{self.address}: not connected")
            sock = self._open()
        request, data = self.session.request(name, args)
        try:
            _send_all(sock, data, self.timeout_s)
        except OSError as exc:
            self._drop()
            raise ConnectionLost(f"{self.address}: lost the connection: {_reason(exc)}") from None
        timeout = self.timeout_s if connecting else (timeout_s or self.reply_timeout_s)
        reply = self._wait(request, timeout, f"answer to ?{name}", connecting=connecting)
        return check_reply(name, reply)

    def send(self, name: str, args: dict[str, Any] | None = None) -> Request:
        """Send a command without waiting: its answer comes through ``poll``/``messages`` like any message
        (and in ``request.reply``); for a caller with a loop of its own, such as ``fog-driver watch``."""
        if self._sock is None:
            raise ConnectionLost(f"{self.address}: not connected")
        request, data = self.session.request(name, args)
        try:
            _send_all(self._sock, data, self.timeout_s)
        except OSError as exc:
            raise ConnectionLost(f"{self.address}: lost the connection: {_reason(exc)}") from None
        if name == "WATCH" and args is not None:
            self._watch = args
        return request

    def command(self, name: str, args: dict[str, Any] | None = None) -> Message:
        """Any command (``?NAME;`` or ``?NAME={args};``) and its answer; a refusal raises as the methods do."""
        return self._command(name, args)

    def status(self) -> Status:
        """``?STATUS``: the daemon's state now."""
        return answer_as(Status, self._command("STATUS"))

    def zero(self) -> Reply:
        """``?ZERO``: the published angles start again from 0 here."""
        return answer_as(Reply, self._command("ZERO"))

    def adapt(self, enable: bool = True, reference_dph: float = 0.0) -> Reply:
        """``?ADAPT``: adapt the model's weights online against ``reference_dph`` (0: the table at rest), or
        freeze them again (``enable=False``)."""
        return answer_as(Reply, self._command("ADAPT", control_args(enable, reference_dph)))

    def table(self, angle_deg: float, dwell_s: float, angle_start_deg: float | None = None) -> Reply:
        """``?TABLE``: the table has stood at ``angle_deg`` (cumulative, or the encoder's [0, 360)) for the last
        ``dwell_s`` seconds (12 or more; moving from ``angle_start_deg`` when given): the daemon adapts from the
        table's angles.  The reply has the dwell's device times (``t_start_s``, ``t_end_s``); what the gyro said
        of it is in STATUS ``table`` a second later.  At most one per 2 s."""
        return answer_as(Reply, self._command("TABLE", table_args(angle_deg, dwell_s, angle_start_deg)))

    def save(self) -> Reply:
        """``?SAVE``: save the adaptation state to the daemon's configured file."""
        return answer_as(Reply, self._command("SAVE"))

    def reload(self) -> Reply:
        """``?RELOAD``: load the model file again (``reply.get("changed")`` says whether it was another)."""
        return answer_as(Reply, self._command("RELOAD"))

    def bias(self, seconds: float = 60.0, *, wait: bool = True) -> Bias:
        """``?BIAS``: the mean compensated rate over ``seconds`` of device data (keep the table still) becomes
        the bias removed from then on.  With ``wait`` (default) returns the result (``state`` ``done``,
        ``bias_dph``), or raises ``BiasFailed``; else the acknowledgement (``state`` ``started``)."""
        started = answer_as(Bias, self._command("BIAS", bias_args(seconds)))
        if not wait:
            return started
        deadline = time.monotonic() + (started.timeout_s or seconds + 30.0) + 5.0
        while True:
            result = self._bias_results.pop(started.capture_id, None)
            if result is not None:
                self._inbox.remove(result)  # returned, not also queued for the iterators
                return check_bias(result)
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise NoReply(f"{self.address}: no result of the bias capture {started.capture_id} in time")
            try:
                self._read_once(remaining)
            except _Lost as exc:
                self._drop()
                raise ConnectionLost(f"{self.address}: {exc.reason} while waiting for the bias result") from None


class _Lost(Exception):
    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


def _send_all(sock: socket.socket, data: bytes, timeout_s: float) -> None:
    """``sendall`` on a non-blocking socket within ``timeout_s``: wait for room between sends (a command line
    is small); ``TimeoutError`` when the daemon does not read it in time."""
    deadline = time.monotonic() + timeout_s
    view = memoryview(data)
    while view:
        wait_s = min(max(0.0, deadline - time.monotonic()), _LONGEST_WAIT_S)
        if not select.select([], [sock], [], wait_s)[1]:
            if time.monotonic() < deadline:
                continue
            raise TimeoutError("the daemon does not read")
        try:
            sent = sock.send(view)
        except BlockingIOError:
            continue
        view = view[sent:]


def _reason(exc: OSError) -> str:
    if isinstance(exc, TimeoutError):
        return "timed out"
    return exc.strerror or str(exc) or type(exc).__name__
