"""``AsyncClient``: the asyncio client of ``fog-driver run`` (see ``fog_driver.client``).

One reader task per client reads the connection, feeds the ``Session`` and hands each message on: samples
to ``angles()``, every message to ``messages()`` (once someone iterates it), answers to the commands waiting
for them, BIAS results to ``bias()``.  So a task can iterate the samples while another sends ``zero()``.  A
lost connection is made again with backoff (each attempt logged), ``?AUTH`` and ``?WATCH`` are sent again,
and the first sample after it carries the ``Gap``; commands waiting when it went raise ``ConnectionLost``.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator
from typing import Any

from .errors import ConnectError, ConnectionLost, NoReply
from .messages import Angle, Bias, Message, Reply, Status, Version
from .protocol import (
    MAX_BUFFERED_ANGLES,
    ClientBase,
    Reconnection,
    answer_as,
    bias_args,
    check_bias,
    check_reply,
    control_args,
)
from .session import Request

__all__ = ["AsyncClient"]

_RECV_BYTES = 65536
_END = object()  # put in the queues when the client closed or the connection went for good


class AsyncClient(ClientBase):
    """As ``Client``, for asyncio::

        async with AsyncClient("127.0.0.1:2948") as c:
            async for a in c.angles(rate_hz=10):
                ...

    Every method is a coroutine but ``angles`` and ``messages`` (async iterators)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._reader: asyncio.StreamReader | None = None
        self._writer: asyncio.StreamWriter | None = None
        self._task: asyncio.Task[None] | None = None
        self._waiting: list[tuple[Request, asyncio.Future[Message]]] = []
        self._angles: asyncio.Queue[Any] = asyncio.Queue(MAX_BUFFERED_ANGLES)  # Angle, or _END
        self._messages: asyncio.Queue[Any] | None = None  # made by the first messages()
        self._bias_results: dict[int | None, Bias] = {}
        self._bias_changed: asyncio.Event | None = None
        self._closed = False
        self._failure: BaseException | None = None

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
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task
        await self._drop()
        self._end(ConnectionLost(f"{self.address}: the client was closed"))

    async def _open(self) -> None:
        hint = "(is `fog-driver run` running?)"
        try:
            reader, writer = await asyncio.wait_for(asyncio.open_connection(self.host, self.port), self.timeout_s)
        except (TimeoutError, OSError) as exc:
            reason = "timed out" if isinstance(exc, asyncio.TimeoutError) else (exc.strerror or str(exc))
            raise ConnectError(f"could not connect to {self.address}: {reason} {hint}") from None
        self._reader, self._writer = reader, writer
        self.session.connection_made()
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
            if self._watch is not None:
                await self._direct("WATCH", self._watch)
        except BaseException:
            await self._drop()
            raise

    async def _direct(self, name: str, args: dict[str, Any]) -> Message:
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
                data = await asyncio.wait_for(self._reader.read(_RECV_BYTES), remaining)
            except TimeoutError:
                continue
            except OSError as exc:
                raise ConnectError(f"{self.address}: lost the connection while waiting for {what}: {exc}") from None
            if not data:
                raise ConnectError(f"{self.address}: the daemon closed the connection before the {what}")
            for message in self.session.receive(data):
                if message is not request.reply:
                    self._hand_on(message)
        return request.reply

    async def _send(self, data: bytes) -> None:
        writer = self._writer
        if writer is None:
            raise ConnectionLost(f"{self.address}: not connected")
        try:
            writer.write(data)
            await asyncio.wait_for(writer.drain(), self.timeout_s)
        except (TimeoutError, OSError) as exc:
            raise ConnectionLost(f"{self.address}: lost the connection: {exc or 'the daemon does not read'}") from None

    async def _drop(self) -> None:
        writer, self._writer, self._reader = self._writer, None, None
        if writer is not None:
            writer.close()
            with contextlib.suppress(Exception):
                await asyncio.wait_for(writer.wait_closed(), 1.0)
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
        for queue in (self._angles, self._messages):
            if queue is not None:
                _put_dropping(queue, _END)
        if self._bias_changed is not None:
            self._bias_changed.set()

    # -- the reader task --------------------------------------------------------------------------------

    async def _read_loop(self) -> None:
        while True:
            assert self._reader is not None  # _open set it; _drop below is followed by _open or the end
            try:
                data = await self._reader.read(_RECV_BYTES)
                reason = None if data else "the daemon closed the connection"
            except OSError as exc:
                data, reason = b"", f"lost the connection: {exc.strerror or exc}"
            if reason is None:
                for message in self.session.receive(data):
                    self._hand_on(message)
                self._answer()
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

    def _hand_on(self, message: Message) -> None:
        if isinstance(message, Angle) and _put_dropping(self._angles, message):
            self.angles_dropped += 1
        if isinstance(message, Bias) and message.state in ("done", "failed"):
            self._bias_results[message.capture_id] = message
            if self._bias_changed is not None:
                self._bias_changed.set()
        if self._messages is not None:
            _put_dropping(self._messages, message)

    def _answer(self) -> None:
        still = []
        for request, future in self._waiting:
            if request.reply is None:
                still.append((request, future))
            elif not future.done():
                future.set_result(request.reply)
        self._waiting = still

    # -- iterators --------------------------------------------------------------------------------------

    async def angles(self, rate_hz: float | None = None) -> AsyncIterator[Angle]:
        """Watch the samples (decimated by the daemon to ``rate_hz``; None: every sample) and yield them."""
        await self.watch(rate_hz)
        while True:
            item = await self._angles.get()
            if item is _END:
                _put_dropping(self._angles, _END)  # for the next reader too
                raise self._ended()
            yield item

    async def messages(self) -> AsyncIterator[Message]:
        """Every message from now on, as it comes."""
        if self._messages is None:
            self._messages = asyncio.Queue(MAX_BUFFERED_ANGLES)
            if self._failure is not None:
                _put_dropping(self._messages, _END)
        while True:
            item = await self._messages.get()
            if item is _END:
                _put_dropping(self._messages, _END)
                raise self._ended()
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
            reply = await asyncio.wait_for(future, self.reply_timeout_s)
        except TimeoutError:
            raise NoReply(f"{self.address}: no answer to ?{name} within {self.reply_timeout_s:g} s") from None
        return check_reply(name, reply)

    async def status(self) -> Status:
        return answer_as(Status, await self._command("STATUS"))

    async def zero(self) -> Reply:
        return answer_as(Reply, await self._command("ZERO"))

    async def adapt(self, enable: bool = True, reference_dph: float = 0.0) -> Reply:
        return answer_as(Reply, await self._command("ADAPT", control_args(enable, reference_dph)))

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
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(changed.wait(), remaining)
        return check_bias(self._bias_results.pop(started.capture_id))


def _put_dropping(queue: asyncio.Queue[Any], item: Any) -> bool:
    """Put ``item``; when the queue is full, drop its oldest first.  True when one was dropped."""
    try:
        queue.put_nowait(item)
        return False
    except asyncio.QueueFull:
        with contextlib.suppress(asyncio.QueueEmpty):
            queue.get_nowait()
        queue.put_nowait(item)
        return True
