"""``AsyncClient``: the asyncio client of ``fog-driver run`` (see ``fog_driver.client``).

One reader task per client reads the connection, feeds the ``Session`` and hands each message on: samples
to ``angles()``, every message to ``messages()`` (from its first call on), answers to the commands waiting
for them, BIAS results to ``bias()``.  So a task can iterate the samples while another sends ``zero()``.  A
lost connection is made again with backoff (each attempt logged), ``?AUTH`` and ``?WATCH`` are sent again,
and the first sample after it carries the ``Gap``; commands waiting when it went raise ``ConnectionLost``.

Bounded as ``Client`` is: the line being read and the two queues (the samples for ``angles()``, and every
message for ``messages()`` from its first call on: then each queue gets half the room) hold at most
``max_buffered_bytes`` together, the oldest dropped beyond it (counted); messages of an unknown class are
dropped unless ``keep_unknown``; a line over 64 KiB is a ``ProtocolError`` the iterators raise in its place.
While watching, no line of a known class for ``idle_timeout_s()`` is a dead daemon: the reader drops the
connection and makes it again (or ends the iterators with ``ConnectionLost`` when ``reconnect=False``).
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import AsyncIterator
from typing import Any

from .errors import ConnectError, ConnectionLost, NoReply, ProtocolError
from .messages import Angle, Bias, Message, Reply, Status, Version
from .protocol import (
    ClientBase,
    MessageQueue,
    Reconnection,
    answer_as,
    bias_args,
    check_bias,
    check_reply,
    control_args,
    table_args,
)
from .session import Received, Request

__all__ = ["AsyncClient"]

_RECV_BYTES = 65536


class _End:
    """What a queue gives once it was ended (the client closed, or the connection went for good) and drained."""


_END = _End()


class _Inbox:
    """A ``MessageQueue`` a coroutine can wait on, and its end."""

    def __init__(self, max_bytes: int) -> None:
        self.queue = MessageQueue(max_bytes)
        self.ended = False
        self._changed = asyncio.Event()

    def put(self, item: Received) -> list[Message]:
        """Hold ``item``; the messages dropped to make room (``MessageQueue.put``)."""
        dropped = self.queue.put(item)
        self._changed.set()
        return dropped

    def end(self) -> None:
        """Nothing more comes: ``get`` gives ``_END`` once the queue is drained."""
        self.ended = True
        self._changed.set()

    async def get(self, timeout_s: float | None) -> Received | _End | None:
        """The next item, waiting up to ``timeout_s`` (None: no limit); None when none came in time."""
        loop = asyncio.get_running_loop()
        deadline = None if timeout_s is None else loop.time() + timeout_s
        while not self.queue:
            if self.ended:
                return _END
            self._changed.clear()
            if deadline is None:
                await self._changed.wait()
                continue
            remaining = deadline - loop.time()
            if remaining <= 0:
                return None
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(remaining):
                    await self._changed.wait()
        return self.queue.popleft()


class AsyncClient(ClientBase):
    """As ``Client``, for asyncio::

        async with AsyncClient("127.0.0.1:2948") as c:
            async for a in c.angles(rate_hz=10):
                ...

    Every method is a coroutine but ``angles`` and ``messages`` (async iterators).  The parameters, the
    counters and ``buffered_bytes`` are ``Client``'s."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._reader: asyncio.StreamReader | None = None
        self._writer: asyncio.StreamWriter | None = None
        self._task: asyncio.Task[None] | None = None
        self._waiting: list[tuple[Request, asyncio.Future[Message]]] = []
        self._angles = _Inbox(self._queue_budget())  # Angle and ProtocolError
        self._messages: _Inbox | None = None  # made by the first messages()
        self._bias_changed: asyncio.Event | None = None
        self._closed = False
        self._failure: BaseException | None = None

    def _queues(self) -> list[MessageQueue]:
        return [self._angles.queue] + ([] if self._messages is None else [self._messages.queue])

    async def __aenter__(self) -> AsyncClient:
        await self.connect()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    # -- connection -------------------------------------------------------------------------------------

    async def connect(self) -> Version:
        """Connect, read the greeting, authorize; start the reader.  ``ConnectError`` / ``Unauthorized``."""
        if self._closed:
            raise ConnectionLost(f"{self.address}: the client was closed")
        await self._open()
        self._bias_changed = asyncio.Event()
        self._task = asyncio.create_task(self._read_loop(), name=f"fog-driver client {self.address}")
        version = self.session.version
        assert version is not None  # _open read the greeting, or raised
        return version

    async def close(self) -> None:
        """Close the connection and end the iterators (``ConnectionLost`` in whoever waits)."""
        self._closed = True
        task, self._task = self._task, None
        if task is not None and task is not asyncio.current_task():
            task.cancel()
            await asyncio.wait({task})  # its end (a cancellation of this task still ends this task)
            if not task.cancelled():
                task.exception()  # retrieved: _end gave it to the iterators
        await self._drop()
        self._end(ConnectionLost(f"{self.address}: the client was closed"))

    async def _open(self) -> None:
        hint = "(is `fog-driver run` running?)"
        try:
            async with asyncio.timeout(self.timeout_s):
                reader, writer = await asyncio.open_connection(self.host, self.port)
        except (TimeoutError, OSError) as exc:
            reason = "timed out" if isinstance(exc, TimeoutError) else (exc.strerror or str(exc))
            raise ConnectError(f"could not connect to {self.address}: {reason} {hint}") from None
        self._reader, self._writer = reader, writer
        self.session.connection_made()
        self._connected()
        try:
            greeting = self.session.request("VERSION")[0]  # the greeting answers it (nothing is sent)
            hello = await self._read_until(greeting, "VERSION greeting (not a fog-driver daemon?)")
            if not isinstance(hello, Version):
                raise ConnectError(
                    f"could not connect to {self.address}: the daemon refused the connection: "
                    f"{getattr(hello, 'message', '')}"
                )
            if self.token is not None:
                await self._direct("AUTH", {"token": self.token})
                # the greeting before ?AUTH held the release only: VERSION again, whole (model, instrument)
                await self._direct("VERSION")
            if self._watch is not None:
                await self._direct("WATCH", self._watch)
        except BaseException:
            await self._drop()
            raise

    async def _direct(self, name: str, args: dict[str, Any] | None = None) -> Message:
        """A command while connecting (the reader task is not reading): sent and read here."""
        request, data = self.session.request(name, args)
        await self._send(data)
        return check_reply(name, await self._read_until(request, f"answer to ?{name}"))

    async def _read_until(self, request: Request, what: str) -> Message:
        loop = asyncio.get_running_loop()
        deadline = loop.time() + self.timeout_s
        while request.reply is None:
            remaining = deadline - loop.time()
            if remaining <= 0:
                raise ConnectError(f"{self.address}: no {what} within {self.timeout_s:g} s")
            try:
                assert self._reader is not None  # _open set it; nothing drops it meanwhile
                async with asyncio.timeout(remaining):
                    data = await self._reader.read(_RECV_BYTES)
            except TimeoutError:
                continue
            except OSError as exc:
                raise ConnectError(f"{self.address}: lost the connection while waiting for {what}: {exc}") from None
            if not data:
                raise ConnectError(f"{self.address}: the daemon closed the connection before the {what}")
            for item in self._received(data):
                if item is not request.reply:
                    self._hand_on(item)
            self._note_peak()
        return request.reply

    async def _send(self, data: bytes) -> None:
        writer = self._writer
        if writer is None:
            raise ConnectionLost(f"{self.address}: not connected")
        try:
            writer.write(data)
            async with asyncio.timeout(self.timeout_s):
                await writer.drain()
        except (TimeoutError, OSError) as exc:
            raise ConnectionLost(f"{self.address}: lost the connection: {exc or 'the daemon does not read'}") from None

    async def _drop(self) -> None:
        writer, self._writer, self._reader = self._writer, None, None
        if writer is not None:
            writer.close()
            with contextlib.suppress(Exception):
                async with asyncio.timeout(1.0):
                    await writer.wait_closed()
        self.session.connection_lost()
        waiting, self._waiting = self._waiting, []
        for _, future in waiting:
            if not future.done():
                future.set_exception(ConnectionLost(f"{self.address}: the connection was lost before the answer"))

    def _ended(self) -> BaseException:
        """What the iterators raise after the last message: the failure ``_end`` was given."""
        return self._failure if self._failure is not None else ConnectionLost(f"{self.address}: the client was closed")

    def _end(self, failure: BaseException) -> None:
        """No more messages: the iterators raise ``failure`` once they have taken what came before."""
        self._failure = failure
        self._angles.end()
        if self._messages is not None:
            self._messages.end()
        if self._bias_changed is not None:
            self._bias_changed.set()

    # -- the reader task --------------------------------------------------------------------------------

    async def _read_loop(self) -> None:
        while True:
            reader = self._reader
            assert reader is not None  # _open set it; _drop below is followed by _open or the end
            idle_s = self.idle_timeout_s()
            reason = None
            try:
                # asyncio.timeout, not wait_for: wait_for can drop a cancellation that comes as the read ends
                async with asyncio.timeout(
                    None if idle_s is None else max(0.0, self._heard_at + idle_s - time.monotonic())
                ):
                    data = await reader.read(_RECV_BYTES)
                reason = None if data else "the daemon closed the connection"
            except TimeoutError:
                data = b""
            except OSError as exc:
                data, reason = b"", f"lost the connection: {exc.strerror or exc}"
            if data:
                for item in self._received(data):
                    self._hand_on(item)
                self._note_peak()
                self._answer()
            if reason is None and idle_s is not None and time.monotonic() >= self._heard_at + idle_s:
                reason = self._idle_reason(idle_s)
            if reason is None:
                continue
            await self._drop()
            if not self.reconnect or self._closed:
                self._end(ConnectionLost(f"{self.address}: {reason}"))
                return
            try:
                await self._reconnect(reason)
            except ConnectionLost as exc:
                self._end(exc)
                return

    async def _reconnect(self, reason: str) -> None:
        backoff = Reconnection(self, reason)
        while True:
            await asyncio.sleep(backoff.delay)
            if self._closed:
                raise ConnectionLost(f"{self.address}: {reason}; closed while reconnecting")
            try:
                await self._open()
            except (ConnectError, ConnectionLost) as exc:
                backoff.failed(exc)
                continue
            backoff.succeeded()
            return

    def _hand_on(self, item: Received) -> None:
        """``item`` to the queues: a sample (or a ``ProtocolError``) to ``angles()``'s, everything to
        ``messages()``'s once someone iterates it; a BIAS result wakes ``bias()``."""
        if isinstance(item, (Angle, ProtocolError)):
            self._dropped(self._angles.put(item))
        if isinstance(item, Bias) and item.state in ("done", "failed") and self._bias_changed is not None:
            self._bias_changed.set()
        if self._messages is not None:
            dropped = self._messages.put(item)
            self.messages_dropped += len(dropped)

    def _answer(self) -> None:
        still = []
        for request, future in self._waiting:
            if request.reply is None:
                still.append((request, future))
            elif not future.done():
                future.set_result(request.reply)
        self._waiting = still

    # -- iterators --------------------------------------------------------------------------------------

    async def angles(self, rate_hz: float | None = None, *, timeout_s: float | None = None) -> AsyncIterator[Angle]:
        """Watch the samples (decimated by the daemon to ``rate_hz``; None: every sample) and yield them; ends
        when no sample came for ``timeout_s`` (None: never), whatever else came.  ``ProtocolError`` for a line
        over 64 KiB (after the samples before it; not reconnected); ``ConnectionLost`` when the connection went
        for good."""
        await self.watch(rate_hz)
        async for item in self._take(self._angles, timeout_s):
            if isinstance(item, Angle):
                yield item

    def messages(self, *, timeout_s: float | None = None) -> AsyncIterator[Message]:
        """Every message from this call on, as it comes; ends when nothing came for ``timeout_s`` (None: never).
        From the first call on, the samples' queue and this one share ``max_buffered_bytes`` half and half."""
        if self._messages is None:
            half = self._queue_budget() // 2
            self._messages = _Inbox(half)
            self._angles.queue.max_bytes = half
            self._dropped(self._angles.queue.trim())
            if self._failure is not None:
                self._messages.end()
        return self._take(self._messages, timeout_s)

    async def _take(self, inbox: _Inbox, timeout_s: float | None) -> AsyncIterator[Message]:
        """The messages of ``inbox`` as they come, until none came for ``timeout_s``; raises what ended it."""
        while True:
            item = await inbox.get(timeout_s)
            if item is None:
                return
            if isinstance(item, _End):
                raise self._ended()
            if isinstance(item, ProtocolError):
                raise item
            yield item

    async def watch(self, rate_hz: float | None = None) -> Reply:
        args = self.session.watch_args(rate_hz)
        reply = answer_as(Reply, await self._command("WATCH", args))
        self._watch = args
        return reply

    # -- commands ---------------------------------------------------------------------------------------

    async def _command(self, name: str, args: dict[str, Any] | None = None) -> Message:
        if self._task is None:
            if self._closed:
                raise ConnectionLost(f"{self.address}: the client was closed")
            await self.connect()
        if self._writer is None:
            raise ConnectionLost(f"{self.address}: not connected (reconnecting)")
        request, data = self.session.request(name, args)
        future = asyncio.get_running_loop().create_future()
        self._waiting.append((request, future))
        await self._send(data)
        try:
            async with asyncio.timeout(self.reply_timeout_s):
                reply = await future
        except TimeoutError:
            raise NoReply(f"{self.address}: no answer to ?{name} within {self.reply_timeout_s:g} s") from None
        return check_reply(name, reply)

    async def status(self) -> Status:
        return answer_as(Status, await self._command("STATUS"))

    async def zero(self) -> Reply:
        return answer_as(Reply, await self._command("ZERO"))

    async def adapt(self, enable: bool = True, reference_dph: float = 0.0) -> Reply:
        return answer_as(Reply, await self._command("ADAPT", control_args(enable, reference_dph)))

    async def table(self, angle_deg: float, dwell_s: float, angle_start_deg: float | None = None) -> Reply:
        """As ``Client.table``."""
        return answer_as(Reply, await self._command("TABLE", table_args(angle_deg, dwell_s, angle_start_deg)))

    async def save(self) -> Reply:
        return answer_as(Reply, await self._command("SAVE"))

    async def reload(self) -> Reply:
        return answer_as(Reply, await self._command("RELOAD"))

    async def bias(self, seconds: float = 60.0, *, wait: bool = True) -> Bias:
        """As ``Client.bias``."""
        started = answer_as(Bias, await self._command("BIAS", bias_args(seconds)))
        if not wait:
            return started
        loop = asyncio.get_running_loop()
        deadline = loop.time() + (started.timeout_s or seconds + 30.0) + 5.0
        while started.capture_id not in self._bias_results:
            if self._failure is not None:
                raise self._ended()
            remaining = deadline - loop.time()
            if remaining <= 0:
                raise NoReply(f"{self.address}: no result of the bias capture {started.capture_id} in time")
            changed = self._bias_changed
            assert changed is not None  # connect made it, before any command
            changed.clear()
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(remaining):
                    await changed.wait()
        return check_bias(self._bias_results.pop(started.capture_id))
