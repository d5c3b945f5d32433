"""The daemon's web listener: a live page for the operator and Prometheus metrics (the optional ``web`` extra).

Off by default; ``http: 127.0.0.1:8948`` in the config turns it on.  It runs an aiohttp server on an asyncio
loop in its own thread (``listener.Listener``, as the NDJSON hub's), so neither a browser nor a scrape ever runs
on the acquisition thread or the NDJSON hub's loop.  Its parts, one job each:

- this module: the listener (its life cycle, its connections and their limits, the screen every request passes);
- ``routes.py``: the read-only routes (the page, ``/ws``, ``/api/view``, ``/metrics``, ``/static/...``);
- ``auth.py``: who has the token (``Authorization: Bearer``, the ``/login`` form's session cookie, the backoff);
- ``fanout.py``: the pages' WebSockets, one encoding of each update for all;
- ``answers.py``: every answer's headers, aiohttp's own error answers and log records;
- ``access.py`` (the ``Host``, ``Origin`` and proxy rules, the sessions), ``connections.py`` (each connection
  counted and tracked), ``view.py`` (what the page shows), ``metrics.py`` (the Prometheus collector).

Data in: the acquisition thread calls ``publish_angles(objs)`` with each published batch and ``publish(obj)``
with every other object; both append to a deque and return (no wake-up, no lock); the listener's loop takes
them ``update_hz`` times a second.  A loop that falls behind by more than ``WEB_MAX_INBOX_BATCHES`` batches loses the
oldest (counted: ``inbox_dropped``), never the acquisition's time.

What every request must pass, token or not (``_screen``; ``access.py`` has the rules): its method (405), a target
that is a path (400), a ``Host`` that names this listener (400/421: no DNS rebinding), a request carrying an
``Origin`` must come from the page's own (403).  Behind a reverse proxy listed in ``trusted_proxies`` the
client's address is taken from ``X-Forwarded-For`` (for its slots and its backoff); from any other address the
header is ignored.  Then the token (``auth.py``), but for ``auth.OPEN_PATHS``.

Limits (a misbehaving client costs itself, never the instrument): ``WEB_MAX_CONNECTIONS`` connections and
``WEB_MAX_CONNECTIONS_PER_PEER`` per address (beyond them the connection is closed at once), of which those without
the token hold at most half (``guards.Slots``: a newcomer closes the oldest of them, so a client with the token
finds a slot) and each lives at most ``WEB_UNAUTHORIZED_LIFETIME_S`` after its first request; request line and
each header at most ``WEB_MAX_LINE_BYTES``, ``WEB_MAX_HEADERS`` headers (414 for the request line, 431 for the
headers; a malformed head 400: ``connections.bad_request``), a body at most ``WEB_MAX_BODY_BYTES`` (413); a
request head must be complete within ``WEB_REQUEST_HEAD_TIMEOUT_S`` of the connection (the first) or of its first
byte (the next ones on a kept-alive connection), and a request must be answered within
``WEB_REQUEST_TIMEOUT_S`` (a client that does not read its response is closed); idle keep-alive connections
close after ``WEB_KEEPALIVE_S``; a WebSocket peer may send at most ``WEB_MAX_WS_MESSAGE_BYTES`` per
message and ``WEB_MAX_WS_MESSAGES_PER_S`` messages a second (``fanout.py``), and one that does not read
is dropped when its oldest unsent update is older than ``max_client_backlog_s``, like an NDJSON client.  Every
client-caused log line is rate-limited as the NDJSON listener's (``DEFAULT_LOG_LINES_PER_S`` a second per event,
the rest counted in ``log_lines_suppressed``).
"""

from __future__ import annotations

import asyncio
import functools
import importlib.util
import math
import time
from collections import deque
from collections.abc import Callable, Hashable, Mapping
from typing import Any

import structlog

from ...extras import EXTRAS, missing_message
from ..guards import peer_address
from ..limits import (
    DEFAULT_LOG_LINES_PER_S,
    WEB_DEFAULT_MAX_BACKLOG_S,
    WEB_DEFAULT_UPDATE_HZ,
    WEB_KEEPALIVE_S,
    WEB_MAX_BODY_BYTES,
    WEB_MAX_CONNECTIONS,
    WEB_MAX_CONNECTIONS_PER_PEER,
    WEB_MAX_HEADERS,
    WEB_MAX_INBOX_BATCHES,
    WEB_MAX_LINE_BYTES,
    WEB_MAX_UPDATE_HZ,
    WEB_REQUEST_HEAD_TIMEOUT_S,
    WEB_REQUEST_TIMEOUT_S,
    WEB_SHUTDOWN_TIMEOUT_S,
    WEB_START_TIMEOUT_S,
    WEB_STOP_TIMEOUT_S,
    WEB_SWEEP_EVERY_S,
    WEB_UNAUTHORIZED_LIFETIME_S,
)
from ..listener import Listener
from .access import AddressSet, forwarded_client, host_name, normalize_name, origin_problem
from .answers import add_security_headers, handler_class, route_aiohttp_logs, unroute_aiohttp_logs
from .auth import OPEN_PATHS, WebAuth, check_web_token
from .connections import CountedProtocol, TrackedConnection, aiohttp_web, request_peer
from .fanout import FanOut
from .metrics import DaemonCollector, LatencyHistogram
from .routes import Routes
from .view import DEFAULT_HISTORY_MIN, ViewState

log = structlog.get_logger("fog_driver.web")

DEFAULT_HTTP_PORT = 8948
#: Names a ``Host`` header may always give (with the listener's own addresses).
LOCAL_NAMES = frozenset({"localhost"})


class WebUnavailable(RuntimeError):
    """The ``web`` extra (aiohttp, plotly, prometheus-client) is not installed."""


def check_web_extra() -> None:
    """WebUnavailable naming what is missing, unless aiohttp, plotly and prometheus-client import."""
    missing = [name for module, name in EXTRAS["web"] if importlib.util.find_spec(module) is None]
    if missing:
        raise WebUnavailable(missing_message("web", "the web view", missing))


class WebView(Listener):
    """The web listener of one daemon (see the module docstring).

    ``read_status()`` (any thread; called on this listener's thread at each scrape) returns the mapping
    ``metrics.DaemonCollector`` reads, without ``angle``/``web_*`` keys: those are filled in here.

    ``open_stream``: with a token, a WebSocket without it gets the angles only.  ``http_hosts``: names a ``Host``
    header may give besides the listener's addresses and ``localhost``.  ``trusted_proxies``: addresses (or
    networks) whose ``X-Forwarded-For`` is believed.  ``secure_cookies``: TLS is in front (a proxy): the cookie is
    ``Secure`` and the page's origin is ``https``.
    """

    def __init__(
        self,
        host: str,
        port: int,
        *,
        token: str | None = None,
        read_status: Callable[[], Mapping[str, Any]] | None = None,
        latency: LatencyHistogram | None = None,
        max_backlog_s: float = WEB_DEFAULT_MAX_BACKLOG_S,
        history_min: float = DEFAULT_HISTORY_MIN,
        update_hz: float = WEB_DEFAULT_UPDATE_HZ,
        control_address: str | None = None,
        open_stream: bool = False,
        http_hosts: tuple[str, ...] = (),
        trusted_proxies: tuple[str, ...] = (),
        secure_cookies: bool = False,
    ) -> None:
        check_web_extra()
        check_web_token(token, host)
        if not (math.isfinite(update_hz) and 0 < update_hz <= WEB_MAX_UPDATE_HZ):
            raise ValueError(f"update_hz must be in (0, 50], got {update_hz!r}")
        super().__init__(
            thread_name="web",
            logger=log,
            log_lines_per_s=DEFAULT_LOG_LINES_PER_S,
            max_connections=WEB_MAX_CONNECTIONS,
            max_per_peer=WEB_MAX_CONNECTIONS_PER_PEER,
        )  # ``slots``: by aiohttp's handler
        self.host, self.port = host, port
        self.secure_cookies = secure_cookies
        self.trusted_proxies = AddressSet(trusted_proxies)
        bound = () if host in ("", "0.0.0.0", "::") else (host,)
        self.host_names = LOCAL_NAMES | {normalize_name(name) for name in (*bound, *http_hosts)}
        self.read_status = read_status or (lambda: {})
        self.latency = latency or LatencyHistogram()
        self.update_hz = update_hz
        self.view = ViewState(history_min, control_address)
        self.inbox: deque[tuple[str, Any, float]] = deque(maxlen=WEB_MAX_INBOX_BATCHES)
        self.inbox_dropped = 0
        self.requests = 0
        self.auth = WebAuth(
            token, slots=self.slots, log=self._log, open_stream=open_stream, secure_cookies=secure_cookies
        )
        self.fanout = FanOut(self.view, self.drain, self._log, max_backlog_s=max_backlog_s)
        self.routes = Routes(self)
        self.connections: dict[Any, TrackedConnection] = {}  # aiohttp's handler -> what the sweeper needs
        self.registry: Any = None  # the /metrics collector's (prometheus_client), made on the loop

    # ------------------------------------------------------------------ life cycle and settings (any thread)

    @property
    def refused_connections(self) -> int:
        """Connections closed at once: no slot was left for them (``guards.Slots``)."""
        return self._refused

    @property
    def max_backlog_s(self) -> float:
        """A page that does not read is dropped once its oldest unsent update is older (settable: SIGHUP)."""
        return self.fanout.max_backlog_s

    @max_backlog_s.setter
    def max_backlog_s(self, seconds: float) -> None:
        self.fanout.max_backlog_s = seconds

    @property
    def need_token(self) -> bool:
        """Every request but ``OPEN_PATHS`` needs the token: the daemon has one."""
        return self.auth.need_token

    def start(self, timeout_s: float = WEB_START_TIMEOUT_S) -> tuple[str, int]:
        """Load the assets, listen, serve in a thread; returns the address (OSError when it cannot listen)."""
        self.routes.load()
        return self._start_thread(timeout_s)

    def stop(self, timeout_s: float = WEB_STOP_TIMEOUT_S) -> None:
        self._stop_thread(timeout_s)

    def check_token(self, token: str | None) -> None:
        """``ValueError`` when ``set_token(token)`` would refuse it (checked before a reload applies anything)."""
        check_web_token(token, self.host)

    def set_token(self, token: str | None) -> None:
        """A new token (SIGHUP; any thread): the sessions and the connections of the old one end (a token is
        rotated because it may have leaked); the same token again changes nothing."""
        check_web_token(token, self.host)
        if token != self.auth.token:
            self._call_on_loop(functools.partial(self._token_changed, token), WEB_STOP_TIMEOUT_S)

    def _token_changed(self, token: str | None) -> None:
        """The token and the sessions change together, on the loop: no request sees the new token with an old
        session, nor the old one after."""
        self.auth.replace(token)
        closed = len(self.connections)
        for handler in list(self.connections):
            self._close(handler)
        log.warning("web_token_changed", auth=self.auth.token is not None, connections_closed=closed)

    # ------------------------------------------------------------------ connections (the listener's loop)

    def open_connection(self, handler: Any, ip: str) -> TrackedConnection | None:
        """Track a new connection from ``ip`` (``guards.Slots``: the oldest connection without the token may be
        closed to make room); None (counted in ``refused_connections``) when every slot in the way is held by
        authorized ones.  A trusted proxy's connection counts against its client's address from its first
        request on (``_screen``)."""
        proxied = ip in self.trusted_proxies
        peer = peer_address(ip)
        refused = self._admit(handler, None if proxied else peer, authorized=not self.auth.need_token)
        if refused is not None:
            self._log("warning", "web_connection_refused", peer=peer, cap=refused)
            return None
        connection = self.connections[handler] = TrackedConnection(peer, time.monotonic(), proxied=proxied)
        return connection

    def close_connection(self, handler: Any) -> None:
        """Forget a connection ``open_connection`` tracked."""
        self.connections.pop(handler, None)
        self.slots.release(handler)

    def _make_room(self, key: Hashable) -> None:
        connection = self.connections.get(key)
        self._log("info", "web_connection_closed", peer=connection and connection.peer, reason="made room")
        self._close(key)

    def _close(self, handler: Any) -> None:
        """Close a connection now (and forget it)."""
        handler.force_close()
        if handler.transport is not None:
            handler.transport.abort()
        self.close_connection(handler)

    # ------------------------------------------------------------------ data in (the acquisition's thread)

    def publish_angles(self, objs: list[dict]) -> None:
        """A batch of published ANGLE objects: O(1), never waits (the objects must not change afterwards)."""
        if objs:
            if len(self.inbox) == WEB_MAX_INBOX_BATCHES:
                self.inbox_dropped += 1
            self.inbox.append(("angles", objs, time.monotonic()))

    def publish(self, obj: dict | None) -> None:
        """Another published object (STATUS, DEVICE, VERSION, BIAS, ...): O(1), never waits."""
        if obj is not None:
            self.inbox.append(("object", obj, time.monotonic()))

    def drain(self) -> None:
        """Bring the page's view up to date with what was published (on the loop)."""
        view, inbox = self.view, self.inbox
        while inbox:
            kind, payload, at_s = inbox.popleft()
            if kind == "angles":
                view.add_angles(payload, at_s)
            else:
                view.add_object(payload, at_s)

    # ------------------------------------------------------------------ the loop

    def _failed(self, exc: BaseException) -> None:
        log.exception("web_listener_failed", reason=str(exc))

    async def _main(self) -> None:
        from prometheus_client import CollectorRegistry  # optional extra: web

        web = aiohttp_web()
        self.registry = CollectorRegistry(auto_describe=False)
        self.registry.register(DaemonCollector(self.routes.metrics_state, self.latency))
        self._stop_event = asyncio.Event()

        @web.middleware
        async def guard(request: Any, handler: Callable) -> Any:
            return await self._guard(request, handler)

        async def headers(request: Any, response: Any) -> None:
            add_security_headers(response)

        app = web.Application(client_max_size=WEB_MAX_BODY_BYTES, middlewares=[guard])
        app.on_response_prepare.append(headers)  # every answer the app gives, redirects and errors included
        self.routes.add_routes(app.router)
        self.auth.add_routes(app.router)
        runner = web.AppRunner(
            app,
            handle_signals=False,
            access_log=None,
            keepalive_timeout=WEB_KEEPALIVE_S,
            max_line_size=WEB_MAX_LINE_BYTES,
            max_field_size=WEB_MAX_LINE_BYTES,
            max_headers=WEB_MAX_HEADERS,
            shutdown_timeout=WEB_SHUTDOWN_TIMEOUT_S,
        )
        await runner.setup()
        loop = asyncio.get_running_loop()
        factory = runner.server

        handler_type = handler_class(self.connections, self._log)
        route_aiohttp_logs(self)

        def protocol() -> Any:
            handler = factory()
            handler.__class__ = handler_type  # its own error answers (a malformed request) get the headers too
            return CountedProtocol(self, handler)

        try:
            server = await loop.create_server(protocol, self.host, self.port, reuse_address=True)
        except BaseException:
            await runner.cleanup()
            raise
        sock = server.sockets[0].getsockname()
        self._listening((sock[0], sock[1]))  # (the service logs web_listening once everything it starts has started)

        async def close() -> None:
            server.close()
            await self.fanout.close_all()
            await runner.cleanup()
            unroute_aiohttp_logs(self)

        await self._serve_until_stopped([self.fanout.tick(self.update_hz), self._sweep_loop()], close)

    def _sweep_period(self) -> float:
        return min(WEB_SWEEP_EVERY_S, WEB_REQUEST_HEAD_TIMEOUT_S / 2, WEB_UNAUTHORIZED_LIFETIME_S / 2)

    def _sweep(self, now: float) -> None:
        """Close connections that send no request head in time, or whose request is not done in time;
        summarize the log lines left out."""
        self._log_limiter.log_suppressed(log, now)
        for handler, c in list(self.connections.items()):
            if c.head_since_s is not None and now - c.head_since_s > WEB_REQUEST_HEAD_TIMEOUT_S:
                reason = f"no complete request head within {WEB_REQUEST_HEAD_TIMEOUT_S:g} s"
            elif c.request_since_s is not None and now - c.request_since_s > WEB_REQUEST_TIMEOUT_S:
                reason = f"request not done within {WEB_REQUEST_TIMEOUT_S:g} s"
            elif (
                c.first_request_s is not None
                and not c.reader
                and not self.slots.authorized(handler)
                and now - c.first_request_s > WEB_UNAUTHORIZED_LIFETIME_S
            ):
                reason = f"no token within {WEB_UNAUTHORIZED_LIFETIME_S:g} s of its first request"
            else:
                continue
            self._log("info", "web_connection_closed", peer=c.peer, reason=reason)
            self._close(handler)

    # ------------------------------------------------------------------ requests

    async def _guard(self, request: Any, handler: Callable) -> Any:
        """Middleware: timing for the sweeper, then who may ask (``_screen``, ``auth.authorize``), then the route."""
        self.requests += 1
        connection = self.connections.get(request.protocol)
        now = time.monotonic()
        if connection is not None:
            connection.head_since_s, connection.request_since_s = None, now
            if connection.first_request_s is None:
                connection.first_request_s = now
        try:
            response, peer = self._screen(request, connection)
            if connection is not None and connection.proxied:  # the forwarded client, from here on (``request_peer``)
                request = request.clone(remote=peer)
            if response is None and self.auth.need_token and request.path not in OPEN_PATHS:
                response = self.auth.authorize(request, now)
            if response is None:
                response = await handler(request)
            return response
        finally:
            if connection is not None:
                connection.request_since_s = None

    def _screen(self, request: Any, connection: TrackedConnection | None) -> tuple[Any, str]:
        """What every request must pass, token or not: its method (405), its target (400 unless a path: an
        absolute-form target names an authority the ``Host`` check never saw), its ``Host`` (400, 421), the
        client's address behind a trusted proxy (400: a bad ``X-Forwarded-For``; 503: no slot for it), its
        ``Origin`` (403).
        Returns the response refusing it (None: it passes) and the client's address (``request_peer``)."""
        web = aiohttp_web()
        peer = request_peer(request)
        if request.method not in ("GET", "HEAD", "POST"):
            raise web.HTTPMethodNotAllowed(request.method, ["GET", "HEAD", "POST"])
        if not request.raw_path.startswith("/"):  # absolute form (``GET http://host/path``): another authority
            self._log("warning", "web_absolute_target_refused", peer=peer, target=request.raw_path[:100])
            return web.Response(status=400, text="400: a request target must be a path (no scheme, no host)\n"), peer
        hosts = request.headers.getall("Host", [])
        if len(hosts) != 1 or host_name(hosts[0]) is None:
            return web.Response(status=400, text="400: a request needs one valid Host header\n"), peer
        if not self._host_allowed(host_name(hosts[0]), request):
            self._log("warning", "web_host_refused", peer=peer, host=hosts[0][:100])
            return web.Response(status=421, text="421: this listener does not serve that Host (see http_hosts)\n"), peer
        if connection is not None and connection.proxied:
            client = forwarded_client(request.headers.getall("X-Forwarded-For", []), self.trusted_proxies)
            if client is None:
                return web.Response(status=400, text="400: X-Forwarded-For holds a hop that is no IP address\n"), peer
            peer = client or peer
            if self._settle(self.slots.move(request.protocol, peer)) is not None:
                request.protocol.force_close()
                return web.Response(status=503, text=f"503: too many connections from {peer}\n"), peer
            connection.peer = peer
        origin = request.headers.get("Origin")
        problem = None if origin is None else origin_problem(origin, hosts[0], https=self.secure_cookies)
        if problem is not None:
            self._log("warning", "web_origin_refused", peer=peer, origin=origin[:100])
            return web.Response(status=403, text=f"403: {problem}\n"), peer
        return None, peer

    def _host_allowed(self, name: str, request: Any) -> bool:
        """``name`` (a ``Host`` header's) is this listener's: a configured name, or the address the connection came
        in on."""
        if name in self.host_names:
            return True
        transport = request.transport
        local = transport.get_extra_info("sockname") if transport is not None else None
        return isinstance(local, tuple) and bool(local) and name == normalize_name(str(local[0]).split("%")[0])


__all__ = ["DEFAULT_HTTP_PORT", "WebUnavailable", "WebView", "check_web_extra"]
