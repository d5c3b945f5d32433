"""The daemon's client multiplexer: JSON lines over TCP, in the manner of gpsd.

The protocol clients speak (what each line means, the commands and the answers) is written in
``docs/reference/ndjson.md``; ``connection.py`` is its state machine, sans-IO, and its limits are in
``limits.py``.  This module is the I/O only:
it listens, reads each client's bytes and hands them to the client's ``Connection``, carries out the actions
that come back (queue a line, run a control command in a worker thread, close), and writes each client's
queue, dropping a client that does not read.

Threading: :class:`Hub` runs an asyncio loop in its own daemon thread.  The
acquisition thread calls :meth:`Hub.publish_angles` / :meth:`Hub.publish`,
which never block (objects are serialized in the caller's thread and handed to
the loop with one ``call_soon_threadsafe`` per call).  The ``version`` and
``device`` callbacks run on the hub's loop thread and must return promptly.
The ``control`` callback runs in one of the hub's own worker threads
(``CONTROL_WORKERS``), never on the loop, so a slow command (a model reload)
delays nobody's ANGLE lines; commands of one client are still answered one at a
time, in order.  A command whose answer comes later returns a
:class:`concurrent.futures.Future` (answered within ``control_timeout_s``; a
longer task answers at once and publishes its result as an event).  The hub only ever
*waits* for such a Future: a timeout or the client hanging up abandons the
wait, and the Future's owner may complete it whenever it likes (the hub never
cancels it).
"""

from __future__ import annotations

import asyncio
import collections
import concurrent.futures
import contextlib
import functools
import math
import socket
import time
from collections.abc import Callable, Hashable, Iterable
from typing import Any, Self

import structlog

from ..ndjson import clean, encode
from .connection import (
    Action,
    AuthGate,
    Authorized,
    Close,
    Connection,
    Control,
    Log,
    Send,
    SendDevice,
    SendVersion,
    WatchChanged,
    is_positive_finite,
)
from .control import control_answer
from .guards import AuthThrottle, check_token, is_loopback_host, peer_address
from .limits import (
    CONTROL_WORKERS,
    DEFAULT_AUTH_BACKOFF_BASE_S,
    DEFAULT_AUTH_BACKOFF_MAX_S,
    DEFAULT_AUTH_DEADLINE_S,
    DEFAULT_CONTROL_TIMEOUT_S,
    DEFAULT_LOG_LINES_PER_S,
    DEFAULT_MAX_BACKLOG_S,
    DEFAULT_MAX_CLIENTS,
    DEFAULT_MAX_CLIENTS_PER_PEER,
    DEFAULT_MAX_LINE_BYTES,
    HUB_STOP_TIMEOUT_S,
    MAX_WATCH_RATE_HZ,
    MIN_MAX_LINE_BYTES,
    READ_CHUNK_BYTES,
    SETTING_WAIT_S,
    SWEEP_EVERY_S,
)
from .listener import Listener
from .web.metrics import LatencyHistogram

__all__ = [
    "DEFAULT_AUTH_BACKOFF_BASE_S",
    "DEFAULT_AUTH_BACKOFF_MAX_S",
    "DEFAULT_AUTH_DEADLINE_S",
    "DEFAULT_CONTROL_TIMEOUT_S",
    "DEFAULT_LOG_LINES_PER_S",
    "DEFAULT_MAX_BACKLOG_S",
    "DEFAULT_MAX_CLIENTS",
    "DEFAULT_MAX_CLIENTS_PER_PEER",
    "DEFAULT_MAX_LINE_BYTES",
    "MAX_WATCH_RATE_HZ",
    "Hub",
    "clean",
    "encode",
    "is_loopback_host",
]

log = structlog.get_logger("fog_driver.daemon")

#: The VERSION keys a client that has not authorized on a token-protected hub gets (no instrument identity).
PUBLIC_VERSION_KEYS = ("release", "proto_major", "proto_minor")


def _check_max_backlog_s(seconds: float) -> None:
    if not (seconds > 0):  # inf is allowed: never drop a client that does not read
        raise ValueError("max_backlog_s must be > 0")


class _Client:
    """One connection's I/O: its socket, its outgoing queue and its two tasks; its protocol state is ``conn``."""

    __slots__ = (
        "auth_deadline",
        "closing",
        "conn",
        "gone",
        "id",
        "inflight_t",
        "lines_queued",
        "peer",
        "queue",
        "reader",
        "reader_task",
        "wakeup",
        "writer",
        "writer_task",
    )

    def __init__(
        self, cid: int, peer: Any, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, conn: Connection
    ) -> None:
        self.id = cid
        self.peer = peer
        self.conn = conn
        self.auth_deadline: asyncio.TimerHandle | None = None
        self.reader = reader
        self.writer = writer
        self.queue: collections.deque[tuple[float, bytes | None]] = collections.deque()
        self.wakeup = asyncio.Event()
        self.inflight_t: float | None = None  # enqueue time of the oldest bytes being drained
        self.closing = False
        self.reader_task: asyncio.Task | None = None
        self.writer_task: asyncio.Task | None = None
        self.gone = False
        self.lines_queued = 0

    @property
    def rate_hz(self) -> float | None:
        return self.conn.rate_hz

    @rate_hz.setter
    def rate_hz(self, value: float | None) -> None:
        self.conn.rate_hz = value

    def oldest_t(self) -> float | None:
        if self.inflight_t is not None:
            return self.inflight_t
        return self.queue[0][0] if self.queue else None


class Hub(Listener):
    """TCP server speaking the client protocol (``connection.py``); see the module docstring.

    ``version()`` returns the VERSION object (the hub adds ``class``), ``device()``
    the current DEVICE object or None, ``control(name, args, client_id)`` answers
    every command the hub does not handle itself, with a dict or a
    :class:`concurrent.futures.Future` of one (``None`` for a
    command it does not know: the client gets ``ERROR`` "unknown command ?NAME"; an
    exception, raised or set on the Future, becomes an ``ERROR`` carrying its
    message).  ``control`` runs in the hub's worker threads, at most
    ``CONTROL_WORKERS`` at a time.  A reply without ``class`` gets the command's
    name, and an ``ERROR`` reply without ``command`` gets the command's name there.

    ``sndbuf_bytes`` sets SO_SNDBUF on accepted connections: the kernel then
    absorbs at most that much for a client that does not read (by default, on
    loopback, megabytes: tens of seconds of ANGLE lines before the backlog age
    policy can even see the client is stuck).

    ``open_stream``: on a token-protected hub, clients that have not authorized get the ANGLE lines they watch
    too (and no auth deadline while they watch); nothing else opens with it.

    The other arguments are the limits ``limits.py`` names and explains (``auth_deadline_s`` None: no deadline).

    While it runs, :meth:`set_token` and :meth:`set_max_backlog_s` change the token
    and the backlog limit from any thread (the service calls them on SIGHUP).
    """

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 0,
        *,
        version: Callable[[], dict],
        device: Callable[[], dict | None],
        control: Callable[[str, dict, int], dict | concurrent.futures.Future | None],
        token: str | None = None,
        open_stream: bool = False,
        max_line_bytes: int = DEFAULT_MAX_LINE_BYTES,
        max_backlog_s: float = DEFAULT_MAX_BACKLOG_S,
        control_timeout_s: float = DEFAULT_CONTROL_TIMEOUT_S,
        sndbuf_bytes: int | None = None,
        max_clients: int = DEFAULT_MAX_CLIENTS,
        max_clients_per_peer: int = DEFAULT_MAX_CLIENTS_PER_PEER,
        auth_deadline_s: float | None = DEFAULT_AUTH_DEADLINE_S,
        auth_backoff_base_s: float = DEFAULT_AUTH_BACKOFF_BASE_S,
        auth_backoff_max_s: float = DEFAULT_AUTH_BACKOFF_MAX_S,
        log_lines_per_s: int = DEFAULT_LOG_LINES_PER_S,
        latency: LatencyHistogram | None = None,
    ) -> None:
        check_token(token, host)
        if max_line_bytes < MIN_MAX_LINE_BYTES:
            raise ValueError(f"max_line_bytes must be at least {MIN_MAX_LINE_BYTES}")
        _check_max_backlog_s(max_backlog_s)
        if not is_positive_finite(control_timeout_s):
            raise ValueError("control_timeout_s must be a finite number of seconds > 0")
        for name, count in (
            ("max_clients", max_clients),
            ("max_clients_per_peer", max_clients_per_peer),
            ("log_lines_per_s", log_lines_per_s),
        ):
            if not isinstance(count, int) or isinstance(count, bool) or count < 1:
                raise ValueError(f"{name} must be an integer >= 1")
        if auth_deadline_s is not None and not is_positive_finite(auth_deadline_s):
            raise ValueError("auth_deadline_s must be a finite number of seconds > 0, or None")
        if not (
            is_positive_finite(auth_backoff_base_s)
            and is_positive_finite(auth_backoff_max_s)
            and auth_backoff_base_s <= auth_backoff_max_s
        ):
            raise ValueError("auth backoff: need 0 < auth_backoff_base_s <= auth_backoff_max_s < inf")
        super().__init__(
            thread_name="fog-hub",
            logger=log,
            log_lines_per_s=log_lines_per_s,
            max_connections=max_clients,
            max_per_peer=max_clients_per_peer,
        )
        self.host = host
        self.port = port
        self._version = version
        self._device = device
        self._control = control
        self.max_line_bytes = max_line_bytes
        self.max_backlog_s = float(max_backlog_s)
        self.control_timeout_s = control_timeout_s
        self.sndbuf_bytes = sndbuf_bytes
        self.max_clients = max_clients
        self.max_clients_per_peer = max_clients_per_peer
        self.auth_deadline_s = auth_deadline_s
        self._gate = AuthGate(token, AuthThrottle(auth_backoff_base_s, auth_backoff_max_s), open_stream=open_stream)
        self.latency = latency  #: frame-to-publish latency, observed once per published batch (None: not measured)

        self._clients: dict[int, _Client] = {}  # (``slots``: by client id)
        self._next_id = 1
        self._watchers = 0
        self._dropped = 0
        self._bytes_sent = 0
        self._server: asyncio.AbstractServer | None = None
        self._control_pool: concurrent.futures.ThreadPoolExecutor | None = None

    # ------------------------------------------------------------------ properties

    @property
    def clients(self) -> int:
        """Connected clients."""
        return len(self._clients)

    @property
    def watchers(self) -> int:
        """Connected clients with an enabled WATCH."""
        return self._watchers

    @property
    def dropped_clients(self) -> int:
        """Clients dropped because their backlog grew older than ``max_backlog_s``."""
        return self._dropped

    @property
    def refused_clients(self) -> int:
        """Connections refused because of ``max_clients`` or ``max_clients_per_peer``."""
        return self._refused

    @property
    def bytes_sent(self) -> int:
        """Bytes handed to client sockets."""
        return self._bytes_sent

    def check_token(self, token: str | None) -> None:
        """``ValueError`` when ``set_token(token)`` would refuse it (checked before a reload applies anything)."""
        check_token(token, self.host)

    # ------------------------------------------------------------------ settings (any thread)

    def set_token(self, token: str | None) -> None:
        """Use ``token`` for ``?AUTH`` from now on (the service calls this on SIGHUP); thread-safe.

        Validated as in the constructor (ValueError; None only on a loopback address).  A
        changed token closes every connection open at the time, with ``ERROR`` "the client
        token changed: connect again": a token is rotated because it may have leaked, so no
        session authorized by the old one may outlive it, and the clients that had not
        authorized meet the new rules from their first line.  The same token again changes
        nothing.  Returns once the hub's loop has applied it (waiting 5 s at most).
        """
        check_token(token, self.host)
        self._apply_on_loop(self._replace_token, token)

    def set_max_backlog_s(self, seconds: float) -> None:
        """The backlog age after which a client that does not read is dropped, from now on, for the
        clients connected too (checked at least every ``SWEEP_EVERY_S``); thread-safe, ValueError unless > 0."""
        _check_max_backlog_s(seconds)
        self._apply_on_loop(setattr, self, "max_backlog_s", float(seconds))

    def _apply_on_loop(self, apply: Callable[..., None], *args: Any) -> None:
        """``apply(*args)`` on the loop thread, waiting for it (5 s at most); directly when no loop runs."""
        if not self._call_on_loop(functools.partial(apply, *args), SETTING_WAIT_S):
            log.warning("hub_setting_late", setting=getattr(apply, "__name__", repr(apply)))

    def _replace_token(self, token: str | None) -> None:
        if token == self._gate.token:
            return
        self._gate.token = token
        for client in list(self._clients.values()):
            self._perform_now(client, client.conn.token_changed())
        log.warning("client_token_changed", auth=token is not None, clients_closed=len(self._clients))

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> tuple[str, int]:
        """Start the loop thread; return ``(host, port)`` once the socket listens (raises OSError if it cannot)."""
        if self._thread is not None:
            raise RuntimeError("hub already started")
        self._control_pool = concurrent.futures.ThreadPoolExecutor(
            CONTROL_WORKERS, thread_name_prefix="fog-hub-control"
        )
        try:
            return self._start_thread()
        except BaseException:
            self._shut_down_control_pool()
            raise

    def stop(self, timeout: float = HUB_STOP_TIMEOUT_S) -> None:
        """Close every client and the server, join the loop thread, and shut the control workers down
        without waiting for a command still running there (idempotent)."""
        self._stop_thread(timeout)
        self._shut_down_control_pool()

    def _shut_down_control_pool(self) -> None:
        pool, self._control_pool = self._control_pool, None
        if pool is not None:
            pool.shutdown(wait=False, cancel_futures=True)

    def __enter__(self) -> Self:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _prepare_loop(self, loop: asyncio.AbstractEventLoop) -> None:
        loop.set_exception_handler(self._on_loop_error)

    def _failed(self, exc: BaseException) -> None:
        log.error("hub_failed", error=repr(exc))

    async def _main(self) -> None:
        self._stop_event = asyncio.Event()
        self._server = await asyncio.start_server(self._on_connect, self.host, self.port, limit=READ_CHUNK_BYTES)
        sockname = self._server.sockets[0].getsockname()
        address = (sockname[0], sockname[1])
        log.info("hub_listening", host=address[0], port=address[1], auth=self._gate.token is not None)
        self._listening(address)
        try:
            await self._serve_until_stopped([self._sweep_loop()], self._close_all)
        finally:
            log.info("hub_stopped", dropped_clients=self._dropped, bytes_sent=self._bytes_sent)

    async def _close_all(self) -> None:
        """Stop listening, close every client and wait for their tasks."""
        assert self._server is not None
        self._server.close()
        clients = list(self._clients.values())
        tasks = [t for c in clients for t in (c.reader_task, c.writer_task) if t is not None]
        for client in clients:
            self._discard(client, "hub_stopped")
        if tasks:
            await asyncio.gather(*tasks, return_exceptions=True)
        await self._server.wait_closed()

    def _sweep_period(self) -> float:
        return min(SWEEP_EVERY_S, self.max_backlog_s / 4)

    def _sweep(self, now: float) -> None:
        """Drop stalled clients even when nothing new is being published; summarize suppressed log lines."""
        for client in list(self._clients.values()):
            self._check_backlog(client, now)
        self._log_limiter.log_suppressed(log, now)

    def _on_loop_error(self, loop: asyncio.AbstractEventLoop, context: dict) -> None:
        """The loop's exception handler: one short, rate-limited line instead of a traceback each time.

        Out of descriptors, asyncio reports every failed accept (up to 100 per retry, a retry a
        second); the default handler's traceback each time would fill the disk.  The hub serves
        its connected clients meanwhile, and accepts again once descriptors are free."""
        exc = context.get("exception")
        self._log("error", "hub_loop_error", message=context.get("message"), error=repr(exc) if exc else None)

    # ------------------------------------------------------------------ publishing (any thread)

    def publish_angles(self, objs: list[dict], read_monotonic_s: float | None = None) -> None:
        """Send ANGLE objects (each with ``t_s``) to every watching client, decimated per client.

        Thread-safe and non-blocking: each object is serialized once here, and
        the batch goes to the loop in one ``call_soon_threadsafe``.  A batch
        published while nobody watches is skipped without serializing it.
        ``read_monotonic_s``: when the bytes that completed the batch were read
        (``time.monotonic()``); with a ``latency`` histogram, the time from then
        to the batch's lines queued for every watching client is observed.
        """
        if not objs or self._loop is None or self._watchers == 0:
            return
        items: list[tuple[float, bytes]] = []
        for obj in objs:
            t_s = obj.get("t_s")
            if t_s is None or not math.isfinite(t_s):
                raise ValueError(f"an ANGLE object needs a finite t_s: {obj!r}")
            if "class" not in obj:
                obj = {"class": "ANGLE", **obj}
            items.append((float(t_s), encode(obj)))
        self._hand_over(self._deliver_angles, (items, read_monotonic_s))

    def publish(self, obj: dict) -> None:
        """Send one object (DEVICE, STATUS, ...) to every authorized client, watching or not.

        Thread-safe and non-blocking.
        """
        if self._loop is None:
            return
        self._hand_over(self._deliver_all, encode(obj))

    def _hand_over(self, fn: Callable[[Any], None], arg: Any) -> None:
        loop = self._loop
        if loop is None:
            return
        with contextlib.suppress(RuntimeError):  # the loop closed between the check and the call: the hub is stopping
            loop.call_soon_threadsafe(fn, arg)

    def _deliver_angles(self, batch: tuple[list[tuple[float, bytes]], float | None]) -> None:
        items, read_monotonic_s = batch
        now = time.monotonic()
        for client in list(self._clients.values()):
            if client.conn.reads_angles and not client.closing:
                self._for_one_client(self._send_angles, client, items, now)
        if read_monotonic_s is not None and self.latency is not None:
            self.latency.observe(time.monotonic() - read_monotonic_s)

    def _send_angles(self, client: _Client, items: list[tuple[float, bytes]], now: float) -> None:
        """Queue the ANGLE lines of one batch that ``client``'s WATCH policy keeps."""
        kept = client.conn.keep_angles(items)
        if kept:
            self._enqueue(client, b"".join(kept), now, len(kept))

    def _deliver_all(self, line: bytes) -> None:
        now = time.monotonic()
        for client in list(self._clients.values()):
            if client.conn.authorized and not client.closing:
                self._for_one_client(self._enqueue, client, line, now, 1)

    def _for_one_client(self, deliver: Callable[..., None], client: _Client, *args: Any) -> None:
        """``deliver(client, *args)``: an exception costs this client its connection, never another its lines."""
        try:
            deliver(client, *args)
        except Exception as exc:  # noqa: BLE001 - a bug must cost one client, never the hub
            self._client_failed(client, exc)

    def _client_failed(self, client: _Client, exc: Exception) -> None:
        """Log a bug met while serving ``client`` (once: the client is discarded) and discard it.  A client
        that hung up (connection reset, broken pipe) is no bug: that is logged at info."""
        if not client.gone:
            if isinstance(exc, ConnectionError):
                self._log("info", "client_hung_up", client=client.id, peer=str(client.peer), error=repr(exc))
            else:
                self._log("error", "client_failed", client=client.id, peer=str(client.peer), error=repr(exc))
        self._discard(client, "failed")

    # ------------------------------------------------------------------ per-client output

    def _enqueue(self, client: _Client, data: bytes, now: float | None = None, lines: int = 1) -> None:
        if client.gone or client.closing:
            return
        if now is None:
            now = time.monotonic()
        client.queue.append((now, data))
        client.lines_queued += lines
        client.wakeup.set()
        self._check_backlog(client, now)

    def _send_obj(self, client: _Client, obj: dict) -> None:
        try:
            line = encode(obj)
        except (TypeError, ValueError) as exc:
            line = encode({"class": "ERROR", "message": f"internal: reply not serializable: {exc}"})
        self._enqueue(client, line)

    def _close_after_flush(self, client: _Client) -> None:
        """Send what is queued, then close (used after a final ERROR)."""
        if client.gone or client.closing:
            return
        client.queue.append((time.monotonic(), None))
        client.closing = True
        client.wakeup.set()

    def _check_backlog(self, client: _Client, now: float) -> None:
        oldest = client.oldest_t()
        if oldest is None or client.gone:
            return
        age = now - oldest
        if age > self.max_backlog_s:
            self._dropped += 1
            queued = sum(len(b) for _, b in client.queue if b is not None)
            self._log(
                "warning",
                "client_dropped",
                client=client.id,
                peer=str(client.peer),
                backlog_s=round(age, 3),
                queued_bytes=queued,
                reason="not reading",
                dropped_clients=self._dropped,
            )
            self._discard(client, "dropped")

    async def _write_loop(self, client: _Client) -> None:
        writer = client.writer
        try:
            while True:
                while not client.queue:
                    client.wakeup.clear()
                    await client.wakeup.wait()
                batch = []
                close = False
                while client.queue:
                    t, data = client.queue.popleft()
                    if data is None:
                        close = True
                        break
                    if not batch:
                        client.inflight_t = t
                    batch.append(data)
                if batch:
                    payload = b"".join(batch)
                    writer.write(payload)
                    self._bytes_sent += len(payload)
                    await writer.drain()
                client.inflight_t = None
                if close:
                    self._discard(client, "closed_by_server", graceful=True)
                    return
        except (ConnectionError, OSError):
            self._discard(client, "connection_lost")
        except asyncio.CancelledError:
            pass

    def _discard(self, client: _Client, reason: str, graceful: bool = False) -> None:
        """Forget a client: remove it, stop its tasks, close its socket (abort unless ``graceful``)."""
        if client.gone:
            return
        client.gone = True
        client.queue.clear()
        if client.auth_deadline is not None:
            client.auth_deadline.cancel()
        self.slots.release(client.id)
        if self._clients.pop(client.id, None) is not None and client.conn.watch:
            self._watchers -= 1
        current = asyncio.current_task()
        for task in (client.reader_task, client.writer_task):
            if task is not None and task is not current and not task.done():
                task.cancel()
        transport = client.writer.transport
        if graceful:
            client.writer.close()
        else:
            transport.abort()
        self._log(
            "info",
            "client_disconnected",
            client=client.id,
            peer=str(client.peer),
            reason=reason,
            lines_queued=client.lines_queued,
        )

    # ------------------------------------------------------------------ per-client input

    async def _on_connect(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        peer = writer.get_extra_info("peername")
        address = peer_address(peer)
        cid = self._next_id
        refused = self._admit(cid, address, authorized=self._gate.token is None)
        if refused is not None:
            refusal = self._refusal(refused, address)
            self._log("warning", "client_refused", peer=str(peer), reason=refusal, refused_clients=self._refused)
            writer.write(encode({"class": "ERROR", "message": refusal}))
            writer.close()
            return
        self._next_id += 1
        sock = writer.get_extra_info("socket")
        if self.sndbuf_bytes is not None and sock is not None:
            with contextlib.suppress(OSError):
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, self.sndbuf_bytes)
        conn = Connection(address, self._gate, max_line_bytes=self.max_line_bytes)
        client = _Client(cid, peer, reader, writer, conn)
        self._clients[cid] = client
        client.reader_task = asyncio.current_task()
        client.writer_task = asyncio.create_task(self._write_loop(client))
        if not client.conn.authorized and self.auth_deadline_s is not None:
            client.auth_deadline = asyncio.get_running_loop().call_later(
                self.auth_deadline_s, self._auth_deadline_passed, client
            )
        self._log("info", "client_connected", client=cid, peer=str(peer), clients=len(self._clients))
        try:
            self._perform_now(client, conn.greeting())
            await self._read_loop(client)
        except asyncio.CancelledError:
            pass
        except Exception as exc:  # noqa: BLE001 - a bug must cost one client, never the hub
            self._client_failed(client, exc)
        finally:
            if not client.closing:
                self._discard(client, "client_closed")
            # after _close_after_flush the writer task sends what is queued, then closes

    def _refusal(self, cap: str, peer_address: str) -> str:
        """Why a new connection from ``peer_address`` is refused: the ``cap`` (``Slots.admit``) is reached."""
        if cap == "total":
            return f"too many clients ({self.max_clients}): try again later"
        return f"too many connections from {peer_address} ({self.max_clients_per_peer}): try again later"

    def _make_room(self, key: Hashable) -> None:
        """Close the oldest unauthorized client (id ``key``): a new connection needs its slot (``Slots``)."""
        client = self._clients.get(key)  # type: ignore[call-overload]
        if client is None or client.gone or client.closing:
            return
        self._log("info", "client_made_room", client=client.id, peer=str(client.peer))
        self._send_obj(client, {"class": "ERROR", "message": "closed to make room for a new client: authorize sooner"})
        self._close_after_flush(client)

    def _auth_deadline_passed(self, client: _Client) -> None:
        client.auth_deadline = None
        if client.gone or client.closing:
            return
        self._perform_now(client, client.conn.auth_deadline_passed(self.auth_deadline_s))

    async def _read_loop(self, client: _Client) -> None:
        """Read the client's bytes, one chunk at a time, and carry out what they mean (``Connection.receive``)."""
        while not client.closing:
            chunk = await client.reader.read(READ_CHUNK_BYTES)
            if not chunk:  # the client closed its side: send what is queued (replies), then close
                self._perform_now(client, client.conn.end_of_input())
                return
            for action in client.conn.receive(chunk):
                if isinstance(action, Control):
                    await self._control_command(client, action.name, action.args)
                else:
                    self._perform(client, action)
                if client.closing or client.gone:
                    return
            await asyncio.sleep(0)  # one client's chunk (up to 64 KiB of lines) at a time: others get their turn

    def _perform_now(self, client: _Client, actions: Iterable[Action]) -> None:
        for action in actions:
            self._perform(client, action)

    def _perform(self, client: _Client, action: Action) -> None:
        """Carry out one of the connection's actions (all but ``Control``, which is awaited)."""
        if isinstance(action, Send):
            self._send_obj(client, action.obj)
        elif isinstance(action, SendVersion):
            self._send_version(client, action.identity)
        elif isinstance(action, SendDevice):
            device = self._device()
            if device:
                self._send_obj(client, {"class": "DEVICE", **device})
        elif isinstance(action, Close):
            self._close_after_flush(client)
        elif isinstance(action, Authorized):
            self.slots.authorize(client.id)
            if client.auth_deadline is not None:
                client.auth_deadline.cancel()
                client.auth_deadline = None
        elif isinstance(action, WatchChanged):
            self._watchers += 1 if action.enable else -1
            if action.enable and self._gate.open_stream:
                self.slots.set_reader(client.id)  # it reads the open stream: others make room first
        elif isinstance(action, Log):
            self._log(action.level, action.event, client=client.id, peer=str(client.peer), **action.fields)
        else:
            raise TypeError(f"not an action the hub performs here: {action!r}")

    def _send_version(self, client: _Client, identity: bool = True) -> None:
        try:
            obj = {"class": "VERSION", **self._version()}
            if not identity:
                obj = {key: value for key, value in obj.items() if key == "class" or key in PUBLIC_VERSION_KEYS}
        except Exception as exc:  # noqa: BLE001
            obj = {"class": "ERROR", "message": f"version unavailable: {exc}", "command": "VERSION"}
        self._send_obj(client, obj)

    async def _control_command(self, client: _Client, name: str, args: dict) -> None:
        """Hand a command to ``control`` in a worker thread and send its answer (or an ERROR) to ``client``."""
        answer = await control_answer(self._control_pool, self._control, name, args, client.id, self.control_timeout_s)
        self._send_obj(client, answer)
