"""The daemon's web listener: a live page for the operator and Prometheus metrics (the optional ``web`` extra).

Off by default; ``http: 127.0.0.1:8948`` in the config turns it on.  It runs an aiohttp server on an asyncio
loop in its own thread, so neither a browser nor a scrape ever runs on the acquisition thread or the NDJSON
hub's loop.

Routes (all read-only; the page offers no command):

====================  =========================================================================================
``GET /``             the page (``static/index.html``, with ``view.js`` and ``view.css``)
``GET /ws``           WebSocket: one ``snapshot`` when it opens, then an ``update`` every ``1/update_hz`` s
                      (``view.ViewState``: the latest sample, decimated here, the new plot points, the banners)
``GET /api/view``     the same snapshot as one JSON document (scripts, ``curl``)
``GET /metrics``      Prometheus text exposition (``metrics.DaemonCollector``)
``GET /static/...``   the page's assets; ``plotly.min.js`` comes from the installed ``plotly`` package (no CDN)
``GET|POST /login``   the token form, when the daemon has a token (below)
``POST /logout``      ends the browser's session
====================  =========================================================================================

Data in: the acquisition thread calls ``publish_angles(objs)`` with each published batch and ``publish(obj)``
with every other object; both append to a deque and return (no wake-up, no lock); the listener's loop takes
them ``update_hz`` times a second.  A loop that falls behind by more than ``WEB_MAX_INBOX_BATCHES`` batches loses the
oldest (counted: ``inbox_dropped``), never the acquisition's time.

Who may ask (``access.py`` has the rules).  Every request's ``Host`` must name this listener (400/421: no DNS
rebinding), and a request carrying an ``Origin`` must come from the page's own (403).  Listening beyond loopback
needs the daemon's ``token`` (the config refuses to start otherwise); once the daemon has one, on loopback too,
every request must carry it: ``Authorization: Bearer <token>`` (the scheme in any case; Prometheus'
``authorization`` setting, ``curl -H``), or the session cookie the ``/login`` form sets (a browser; never the
token in a URL).  Open without it: the login form and what it loads (``OPEN_PATHS``); with ``open_stream``, a
WebSocket that gets the angles only (``{"type": ..., "angle": {...}}``, the ANGLE object the page shows).
Without it a request gets 401 (a browser asking for the page: the login form).  Wrong tokens are counted per
address as on the NDJSON listener (``guards.AuthThrottle``: after ``AUTH_FAILURES_BEFORE_BACKOFF`` the address
waits 1 s, doubling up to 300 s, and while it waits every token from it, the right one too, is answered 429 unread).
The session
cookie is HttpOnly, SameSite=Strict, lasts ``WEB_SESSION_MAX_AGE_S``, is ``Secure`` when ``secure_cookies`` (the
config's ``http_secure_cookies``: TLS is in front), and a new token voids every one.  Behind a reverse proxy
listed in ``trusted_proxies`` the client's address is taken from ``X-Forwarded-For`` (for its slots and its
backoff); from any other address the header is ignored.  Every answer carries ``SECURITY_HEADERS`` (a Content
Security Policy, ``nosniff``, ``no-store``) and ``Server: fog-driver``, redirects and errors included.  The CSP
allows inline styles: plotly sets them (``style`` attributes, inserted ``<style>`` rules); the page's own are
in ``view.css``.

Logs: every client-caused event is one structlog line of its kind through ``_log`` (``guards.LogRateLimiter``,
as the NDJSON listener's: ``DEFAULT_LOG_LINES_PER_S`` a second per event, the rest counted in
``log_lines_suppressed``); a request aiohttp cannot parse included (``_handler_class``), and whatever aiohttp's
loggers say (``_AiohttpLogBridge``): never a traceback on stderr.

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
message and ``WEB_MAX_WS_MESSAGES_PER_S`` messages a second, pings included (the page sends none; a flood is
closed with 1008 rather than answered), and one that does not read
is dropped when its oldest unsent update is older than ``max_client_backlog_s``, like an NDJSON client.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import gzip
import hashlib
import importlib.resources
import importlib.util
import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from typing import Any

import structlog

from ...extras import EXTRAS, missing_message
from ...ndjson import encode
from ..guards import AuthThrottle, LogRateLimiter, Slots, check_token, is_loopback_host, peer_address, token_matches
from ..limits import (
    DEFAULT_AUTH_BACKOFF_BASE_S,
    DEFAULT_AUTH_BACKOFF_MAX_S,
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
    WEB_MAX_WS_MESSAGE_BYTES,
    WEB_MAX_WS_MESSAGES_PER_S,
    WEB_REQUEST_HEAD_TIMEOUT_S,
    WEB_REQUEST_TIMEOUT_S,
    WEB_SESSION_MAX_AGE_S,
    WEB_SHUTDOWN_TIMEOUT_S,
    WEB_START_TIMEOUT_S,
    WEB_STOP_TIMEOUT_S,
    WEB_SWEEP_EVERY_S,
    WEB_UNAUTHORIZED_LIFETIME_S,
    WEB_WS_HEARTBEAT_S,
    WEB_WS_WINDOW_S,
)
from ..loops import apply_on_loop
from .access import AddressSet, Sessions, forwarded_client, host_name, normalize_name, origin_problem
from .connections import CountedProtocol, TrackedConnection, bad_request
from .metrics import DaemonCollector, LatencyHistogram
from .view import DEFAULT_HISTORY_MIN, ViewState

log = structlog.get_logger("fog_driver.web")

DEFAULT_HTTP_PORT = 8948
COOKIE = "fog_driver_token"
#: The page's assets: name -> (package, resource path, content type).
ASSETS = {
    "view.js": ("fog_driver.daemon.web", "static/view.js", "text/javascript"),
    "view.css": ("fog_driver.daemon.web", "static/view.css", "text/css"),
    "plotly.min.js": ("plotly", "package_data/plotly.min.js", "text/javascript"),
}
#: Every answer's headers (a static asset's ``Cache-Control`` excepted: it is revalidated by its ETag).
SECURITY_HEADERS = {
    "Content-Security-Policy": "default-src 'self'; img-src 'self' data:; style-src 'self' 'unsafe-inline'; "
    "connect-src 'self'; form-action 'self'; base-uri 'none'; frame-ancestors 'none'",
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "same-origin",  # not no-referrer: its forms would post "Origin: null"
    "Cache-Control": "no-store",
}
#: Every answer's ``Server`` header (aiohttp's own would name Python's and aiohttp's versions).
SERVER_HEADER = "fog-driver"
#: What a request needs no token for: the login form, the logout, and what the form loads.
OPEN_PATHS = frozenset({"/login", "/logout", "/static/view.css", "/favicon.ico"})
#: Names a ``Host`` header may always give (with the listener's own addresses).
LOCAL_NAMES = frozenset({"localhost"})


class WebUnavailable(RuntimeError):
    """The ``web`` extra (aiohttp, plotly, prometheus-client) is not installed."""


def check_web_extra() -> None:
    """WebUnavailable naming what is missing, unless aiohttp, plotly and prometheus-client import."""
    missing = [name for module, name in EXTRAS["web"] if importlib.util.find_spec(module) is None]
    if missing:
        raise WebUnavailable(missing_message("web", "the web view", missing))


class _Asset:
    __slots__ = ("body", "gzipped", "content_type", "etag")

    def __init__(self, body: bytes, content_type: str) -> None:
        self.body = body
        self.gzipped = gzip.compress(body, compresslevel=6, mtime=0)
        self.content_type = content_type
        self.etag = '"' + hashlib.sha256(body).hexdigest()[:32] + '"'


def _load_assets() -> dict[str, _Asset]:
    assets = {}
    for name, (package, path, content_type) in ASSETS.items():
        body = importlib.resources.files(package).joinpath(path).read_bytes()
        assets[name] = _Asset(body, content_type)
    return assets


def _index_html() -> bytes:
    return importlib.resources.files("fog_driver.daemon.web").joinpath("static/index.html").read_bytes()


class _Browser:
    """One WebSocket peer: its queue of encoded updates (with the host time each was queued); ``full``: the page's
    updates, else the angles only (an open-stream reader without the token)."""

    __slots__ = ("peer", "queue", "wakeup", "ws", "transport", "gone", "full")

    def __init__(self, peer: str, ws: Any, transport: Any, full: bool = True) -> None:
        self.peer = peer
        self.ws = ws
        self.transport = transport
        self.full = full
        self.queue: deque[tuple[float, str]] = deque()
        self.wakeup = asyncio.Event()
        self.gone = False


class WebView:
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
        _check_web_token(token, host)
        if not (math.isfinite(update_hz) and 0 < update_hz <= WEB_MAX_UPDATE_HZ):
            raise ValueError(f"update_hz must be in (0, 50], got {update_hz!r}")
        self.host, self.port = host, port
        self.token = token
        self.open_stream = open_stream
        self.secure_cookies = secure_cookies
        self.trusted_proxies = AddressSet(trusted_proxies)
        bound = () if host in ("", "0.0.0.0", "::") else (host,)
        self.host_names = LOCAL_NAMES | {normalize_name(name) for name in (*bound, *http_hosts)}
        self.read_status = read_status or (lambda: {})
        self.latency = latency or LatencyHistogram()
        self.max_backlog_s = max_backlog_s
        self.update_hz = update_hz
        self.view = ViewState(history_min, control_address)
        self.inbox: deque[tuple[str, Any, float]] = deque(maxlen=WEB_MAX_INBOX_BATCHES)
        self.inbox_dropped = 0
        self.browsers: set[_Browser] = set()
        self.dropped_browsers = 0
        self.requests = 0
        self.refused_connections = 0
        self._sessions = Sessions()  # what the cookies hold: never the token itself
        self._throttle = AuthThrottle(DEFAULT_AUTH_BACKOFF_BASE_S, DEFAULT_AUTH_BACKOFF_MAX_S)
        self._log_limiter = LogRateLimiter(DEFAULT_LOG_LINES_PER_S)
        self._assets: dict[str, _Asset] = {}
        self._index = b""
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._ready = threading.Event()
        self._start_error: BaseException | None = None
        self._stop_event: asyncio.Event | None = None
        self._address: tuple[str, int] | None = None
        self._connections: dict[Any, TrackedConnection] = {}  # aiohttp's handler -> what the sweeper needs
        self.slots = Slots(WEB_MAX_CONNECTIONS, WEB_MAX_CONNECTIONS_PER_PEER)  # by aiohttp's handler
        self._registry = None
        #: device times of the newest point and mean the pages were sent (a page dedups by device time)
        self._sent_after: tuple[float | None, float | None] = (None, None)
        self._sent_restarts = 0

    # ------------------------------------------------------------------ life cycle (any thread)

    @property
    def address(self) -> tuple[str, int] | None:
        return self._address

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def start(self, timeout_s: float = WEB_START_TIMEOUT_S) -> tuple[str, int]:
        """Load the assets, listen, serve in a thread; returns the address (OSError when it cannot listen)."""
        self._assets = _load_assets()
        self._index = _index_html()
        self._thread = threading.Thread(target=self._run, name="web", daemon=True)
        self._thread.start()
        if not self._ready.wait(timeout_s):
            raise OSError(f"the web listener did not start within {timeout_s:g} s")
        if self._start_error is not None:
            raise self._start_error
        assert self._address is not None
        return self._address

    def stop(self, timeout_s: float = WEB_STOP_TIMEOUT_S) -> None:
        loop = self._loop
        if loop is not None and self._stop_event is not None:
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(self._stop_event.set)
        if self._thread is not None:
            self._thread.join(timeout_s)

    @property
    def need_token(self) -> bool:
        """Every request but ``OPEN_PATHS`` needs the token: the daemon has one."""
        return self.token is not None

    def check_token(self, token: str | None) -> None:
        """``ValueError`` when ``set_token(token)`` would refuse it (checked before a reload applies anything)."""
        _check_web_token(token, self.host)

    def set_token(self, token: str | None) -> None:
        """A new token (SIGHUP; any thread): the sessions and the connections of the old one end (a token is
        rotated because it may have leaked); the same token again changes nothing."""
        _check_web_token(token, self.host)
        if token != self.token:
            self._on_loop(functools.partial(self._token_changed, token))

    def _on_loop(self, apply: Callable[[], None]) -> None:
        """``apply()`` on the listener's loop, waiting for it (``WEB_STOP_TIMEOUT_S`` at most); at once when the
        listener does not run."""
        apply_on_loop(self._loop, self._thread, apply, WEB_STOP_TIMEOUT_S)

    def _token_changed(self, token: str | None) -> None:
        """The token and the sessions change together, on the loop: no request sees the new token with an old
        session, nor the old one after."""
        self.token = token
        self._sessions.clear()
        closed = len(self._connections)
        for handler in list(self._connections):
            self._close(handler)
        log.warning("web_token_changed", auth=self.token is not None, connections_closed=closed)

    # ------------------------------------------------------------------ connections (the listener's loop)

    def open_connection(self, handler: Any, ip: str) -> TrackedConnection | None:
        """Track a new connection from ``ip`` (``guards.Slots``: the oldest connection without the token may be
        closed to make room); None (counted in ``refused_connections``) when every slot in the way is held by
        authorized ones.  A trusted proxy's connection counts against its client's address from its first
        request on (``_screen``)."""
        proxied = ip in self.trusted_proxies
        peer = peer_address(ip)
        admission = self.slots.admit(handler, None if proxied else peer, authorized=not self.need_token)
        if admission.refused is not None:
            self.refused_connections += 1
            self._log("warning", "web_connection_refused", peer=peer, cap=admission.refused)
            return None
        self._make_room(admission.evicted)
        connection = self._connections[handler] = TrackedConnection(peer, time.monotonic(), proxied=proxied)
        return connection

    def close_connection(self, handler: Any) -> None:
        """Forget a connection ``open_connection`` tracked."""
        self._connections.pop(handler, None)
        self.slots.release(handler)

    def _make_room(self, handlers: tuple[Any, ...]) -> None:
        for handler in handlers:
            connection = self._connections.get(handler)
            self._log("info", "web_connection_closed", peer=connection and connection.peer, reason="made room")
            self._close(handler)

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

    # ------------------------------------------------------------------ the loop

    def _run(self) -> None:
        loop = asyncio.new_event_loop()
        self._loop = loop
        try:
            loop.run_until_complete(self._main())
        except BaseException as exc:  # noqa: BLE001 - reported to start(), or logged once the listener ran
            if not self._ready.is_set():
                self._start_error = exc
            else:
                log.exception("web_listener_failed", reason=str(exc))
        finally:
            self._ready.set()
            loop.close()

    async def _main(self) -> None:
        from aiohttp import web  # optional extra: web
        from prometheus_client import CollectorRegistry  # optional extra: web

        self._registry = CollectorRegistry(auto_describe=False)
        self._registry.register(DaemonCollector(self._metrics_state, self.latency))
        self._stop_event = asyncio.Event()

        @web.middleware
        async def guard(request: Any, handler: Callable) -> Any:
            return await self._guard(request, handler)

        async def headers(request: Any, response: Any) -> None:
            _add_security_headers(response)

        app = web.Application(client_max_size=WEB_MAX_BODY_BYTES, middlewares=[guard])
        app.on_response_prepare.append(headers)  # every answer the app gives, redirects and errors included
        app.router.add_get("/", self._page)
        app.router.add_get("/ws", self._websocket)
        app.router.add_get("/api/view", self._api_view)
        app.router.add_get("/metrics", self._metrics)
        app.router.add_get("/static/{name}", self._static)
        app.router.add_get("/login", self._login_form)
        app.router.add_get("/favicon.ico", self._no_icon)
        app.router.add_post("/login", self._login)
        app.router.add_post("/logout", self._logout)
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

        handler_class = _handler_class(self)
        _route_aiohttp_logs(self)

        def protocol() -> Any:
            handler = factory()
            handler.__class__ = handler_class  # its own error answers (a malformed request) get the headers too
            return CountedProtocol(self, handler)

        try:
            server = await loop.create_server(protocol, self.host, self.port, reuse_address=True)
        except BaseException:
            await runner.cleanup()
            raise
        sock = server.sockets[0].getsockname()
        self._address = (sock[0], sock[1])
        self._ready.set()  # (the service logs web_listening once everything it starts has started)
        ticker = asyncio.create_task(self._tick())
        sweeper = asyncio.create_task(self._sweep())
        try:
            await self._stop_event.wait()
        finally:
            ticker.cancel()
            sweeper.cancel()
            server.close()
            for browser in list(self.browsers):
                browser.gone = True
                browser.wakeup.set()
                await browser.ws.close()
            await runner.cleanup()
            if _AIOHTTP_LOGS.view is self:
                _AIOHTTP_LOGS.view = None
            self._log_limiter.log_suppressed(log, math.inf)  # the last counts too: every line left out is counted once

    def _drain(self) -> None:
        view, inbox = self.view, self.inbox
        while inbox:
            kind, payload, at_s = inbox.popleft()
            if kind == "angles":
                view.add_angles(payload, at_s)
            else:
                view.add_object(payload, at_s)

    async def _tick(self) -> None:
        """Take what was published; send every page an update (one encoding for all)."""
        period = 1.0 / self.update_hz
        while True:
            await asyncio.sleep(period)
            try:
                self._drain()
                if not self.browsers:
                    continue
                now = time.monotonic()
                if self.view.restarts != self._sent_restarts:  # the series started afresh: the pages too
                    self._sent_after, self._sent_restarts = (None, None), self.view.restarts
                update = self.view.update(now, *self._sent_after)
                self._sent_after = (
                    update["points"][-1]["t_s"] if update["points"] else self._sent_after[0],
                    update["minutes"][-1]["t_s"] if update["minutes"] else self._sent_after[1],
                )
                text = _text(update)
                angles = _text(_angles_only(update)) if not all(b.full for b in self.browsers) else ""
                for browser in list(self.browsers):
                    self._queue(browser, text if browser.full else angles, now)
            except Exception:  # noqa: BLE001 - one bad object must not end the page's updates
                self._log("exception", "web_update_failed")

    def _queue(self, browser: _Browser, text: str, now: float) -> None:
        if browser.queue and now - browser.queue[0][0] > self.max_backlog_s:
            self._drop(browser, f"not reading: its oldest update is {now - browser.queue[0][0]:.1f} s old")
            return
        browser.queue.append((now, text))
        browser.wakeup.set()

    def _drop(self, browser: _Browser, reason: str) -> None:
        if browser.gone:
            return
        browser.gone = True
        self.browsers.discard(browser)
        self.dropped_browsers += 1
        self._log("warning", "web_client_dropped", peer=browser.peer, reason=reason)
        browser.wakeup.set()
        if browser.transport is not None:
            browser.transport.abort()  # its socket buffer is full: a close handshake would wait on it

    def _log(self, level: str, event: str, **fields: Any) -> None:
        """A per-client line, at most ``DEFAULT_LOG_LINES_PER_S`` of each event a second (the rest counted and
        summarized by the sweeper in one ``log_lines_suppressed`` line), as on the NDJSON listener."""
        if self._log_limiter.allow(event, time.monotonic()):
            getattr(log, level)(event, **fields)

    async def _sweep(self) -> None:
        """Close connections that send no request head in time, or whose request is not done in time;
        summarize the log lines left out."""
        while True:
            await asyncio.sleep(min(WEB_SWEEP_EVERY_S, WEB_REQUEST_HEAD_TIMEOUT_S / 2, WEB_UNAUTHORIZED_LIFETIME_S / 2))
            now = time.monotonic()
            self._log_limiter.log_suppressed(log, now)
            for handler, c in list(self._connections.items()):
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

    def _web(self):
        from aiohttp import web  # optional extra: web

        return web

    async def _guard(self, request: Any, handler: Callable) -> Any:
        """Middleware: timing for the sweeper, then who may ask (``_screen``, ``_authorize``), then the route."""
        self.requests += 1
        connection = self._connections.get(request.protocol)
        now = time.monotonic()
        if connection is not None:
            connection.head_since_s, connection.request_since_s = None, now
            if connection.first_request_s is None:
                connection.first_request_s = now
        try:
            response, peer = self._screen(request, connection)
            if connection is not None and connection.proxied:  # the forwarded client, from here on (``_peer``)
                request = request.clone(remote=peer)
            if response is None and self.need_token and request.path not in OPEN_PATHS:
                response = self._authorize(request, now)
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
        Returns the response refusing it (None: it passes) and the client's address (``_peer``)."""
        web = self._web()
        peer = _peer(request)
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
            admission = self.slots.move(request.protocol, peer)
            if admission.refused is not None:
                self.refused_connections += 1
                request.protocol.force_close()
                return web.Response(status=503, text=f"503: too many connections from {peer}\n"), peer
            self._make_room(admission.evicted)
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

    def _credentials(self, request: Any, now: float) -> str:
        """``session`` (a live session's cookie: no guess of the token), ``bearer`` (an ``Authorization`` header:
        its token is judged by ``_bearer``) or ``none`` (no credentials, or only a cookie no longer valid)."""
        if self._sessions.valid(request.cookies.get(COOKIE), now):
            return "session"
        if request.headers.get("Authorization") is None:  # no token; a stale cookie (a token rotated) is no guess
            return "none"
        return "bearer"

    def _bearer_matches(self, request: Any) -> bool:
        """The request's ``Authorization`` is ``Bearer <the token>`` (the scheme in any case)."""
        scheme, _, given = request.headers.get("Authorization", "").strip().partition(" ")
        return scheme.lower() == "bearer" and token_matches(given.strip(), self.token)

    def _authorize(self, request: Any, now: float) -> Any:
        """None when the request carries the token (or a session's cookie), or may read the open stream; else the
        response refusing it.  A token is judged by the backoff (``guards.AuthThrottle``): while the address
        waits it is not compared, and the right one gets the same 429 as a wrong one."""
        web = self._web()
        peer = _peer(request)
        verdict = self._credentials(request, now)
        if verdict == "none":
            return self._refuse(request)
        if verdict == "session":
            self.slots.authorize(request.protocol)
            return None
        judged, seconds = self._throttle.judge(peer, functools.partial(self._bearer_matches, request), now)
        if judged == "ok":
            self.slots.authorize(request.protocol)
            return None
        if judged == "blocked":
            return self._wait_response(peer, seconds)
        self._log("warning", "web_token_refused", peer=peer, path=request.path)
        return web.Response(
            status=401, text="401: wrong token\n", headers={"WWW-Authenticate": 'Bearer realm="fog-driver"'}
        )

    def _refuse(self, request: Any) -> Any:
        """A request without credentials: the open stream's reader passes; a browser asking for the page is sent to
        the login form; anything else gets 401."""
        web = self._web()
        if self.open_stream and request.path == "/ws":
            return None  # the angles only (``_websocket``)
        if "text/html" in request.headers.get("Accept", "") and request.path == "/":
            raise web.HTTPFound("/login")
        self._log("info", "web_unauthorized", peer=_peer(request), path=request.path)
        return web.Response(
            status=401,
            text="401: this daemon's web view needs its token (Authorization: Bearer <token>, or the form at /login)\n",
            headers={"WWW-Authenticate": 'Bearer realm="fog-driver"'},
        )

    def _wait_response(self, peer: str, wait_s: float, *, page: bool = False) -> Any:
        """429: ``peer`` is blocked for wrong tokens (``wait_s`` more seconds); the login form when ``page``."""
        seconds = math.ceil(wait_s)
        text = f"too many wrong tokens from {peer}: try again in {seconds} s"
        headers = {"Retry-After": str(seconds)}
        if page:
            return self._web().Response(status=429, content_type="text/html", text=_login_page(text), headers=headers)
        return self._web().Response(status=429, text=f"429: {text}\n", headers=headers)

    async def _login_form(self, request: Any) -> Any:
        web = self._web()
        if not self.need_token:
            raise web.HTTPFound("/")
        return web.Response(content_type="text/html", text=_login_page(None))

    async def _login(self, request: Any) -> Any:
        """The form's token: a session cookie and the page (303), or the form again saying why not."""
        web = self._web()
        if not self.need_token:
            raise web.HTTPFound("/")
        form = await request.post()  # at most WEB_MAX_BODY_BYTES (413 beyond)
        token = form.get("token")
        if not isinstance(token, str) or not token:
            return web.Response(status=400, content_type="text/html", text=_login_page("no token given"))
        peer, now = _peer(request), time.monotonic()
        expected = self.token
        judged, seconds = self._throttle.judge(peer, lambda: token_matches(token, expected), now)
        if judged == "blocked":
            return self._wait_response(peer, seconds, page=True)
        if judged == "wrong":
            self._log("warning", "web_login_refused", peer=peer)
            return web.Response(status=401, content_type="text/html", text=_login_page("wrong token"))
        self.slots.authorize(request.protocol)
        response = web.Response(status=303, headers={"Location": "/"})
        response.set_cookie(
            COOKIE,
            self._sessions.start(now),
            max_age=WEB_SESSION_MAX_AGE_S,
            path="/",
            httponly=True,
            samesite="Strict",
            secure=self.secure_cookies,
        )
        self._log("info", "web_login", peer=peer)
        return response

    async def _logout(self, request: Any) -> Any:
        """End the browser's session (its cookie is void here and deleted there); back to the login form."""
        self._sessions.end(request.cookies.get(COOKIE))
        response = self._web().Response(status=303, headers={"Location": "/login" if self.need_token else "/"})
        response.del_cookie(COOKIE, path="/", httponly=True, samesite="Strict", secure=self.secure_cookies)
        return response

    async def _page(self, request: Any) -> Any:
        return self._web().Response(body=self._index, content_type="text/html", charset="utf-8")

    async def _static(self, request: Any) -> Any:
        web = self._web()
        asset = self._assets.get(request.match_info["name"])
        if asset is None:
            raise web.HTTPNotFound(text="404: no such asset\n")
        headers = {"ETag": asset.etag, "Cache-Control": "no-cache", "Vary": "Accept-Encoding"}
        if request.headers.get("If-None-Match") == asset.etag:
            return web.Response(status=304, headers=headers)
        if "gzip" in request.headers.get("Accept-Encoding", ""):
            headers["Content-Encoding"] = "gzip"
            body = asset.gzipped
        else:
            body = asset.body
        return web.Response(body=body, headers={**headers, "Content-Type": asset.content_type})

    async def _no_icon(self, request: Any) -> Any:
        return self._web().Response(status=204)

    async def _api_view(self, request: Any) -> Any:
        web = self._web()
        self._drain()
        snapshot = self.view.snapshot(time.monotonic())
        return web.Response(text=_text(snapshot), content_type="application/json")

    def _metrics_state(self) -> Mapping[str, Any]:
        state = dict(self.read_status())
        self._drain()
        view = self.view
        now = time.monotonic()
        state.update(
            angle=view.angle or {},
            rate_1s_dph=view.rate_1s_dph,
            web_clients=len(self.browsers),
            web_dropped=self.dropped_browsers,
            angle_age_s=None if view.angle_host_s is None else now - view.angle_host_s,
        )
        for cls, key in (("DEVICE", "device"), ("VERSION", "version")):
            state.setdefault(key, view.objects.get(cls, {}))
        return state

    async def _metrics(self, request: Any) -> Any:
        web = self._web()
        from prometheus_client import CONTENT_TYPE_LATEST, generate_latest  # optional extra: web

        body = generate_latest(self._registry)
        return web.Response(body=body, headers={"Content-Type": CONTENT_TYPE_LATEST})

    async def _websocket(self, request: Any) -> Any:
        """The page's updates (the angles only for an open-stream reader without the token: ``_refuse``)."""
        web = self._web()
        ws = web.WebSocketResponse(
            max_msg_size=WEB_MAX_WS_MESSAGE_BYTES, heartbeat=WEB_WS_HEARTBEAT_S, compress=False, autoping=False
        )
        if not ws.can_prepare(request).ok:
            return web.Response(status=400, text="400: /ws takes a WebSocket upgrade\n")
        await ws.prepare(request)
        reader = self.need_token and self._credentials(request, time.monotonic()) == "none"  # ``_refuse`` let it in
        connection = self._connections.get(request.protocol)
        if connection is not None:  # a WebSocket is a long exchange of frames, neither a slow request nor a head
            connection.request_since_s, connection.websocket, connection.reader = None, True, reader
        if reader:
            self.slots.set_reader(request.protocol)
        browser = _Browser(_peer(request), ws, request.transport, full=not reader)
        self._drain()
        now = time.monotonic()
        snapshot = self.view.snapshot(now)
        if not self.browsers:  # the first page: updates carry what comes after its snapshot
            self._sent_after = (
                snapshot["points"][-1]["t_s"] if snapshot["points"] else None,
                snapshot["minutes"][-1]["t_s"] if snapshot["minutes"] else None,
            )
            self._sent_restarts = self.view.restarts
        first = {**snapshot, "login": self.need_token} if browser.full else _angles_only(snapshot)
        browser.queue.append((now, _text(first)))
        self.browsers.add(browser)
        self._log("info", "web_client_connected", peer=browser.peer, clients=len(self.browsers))
        sender = asyncio.create_task(self._send_loop(browser))
        try:
            await self._receive_loop(browser)
        finally:
            browser.gone = True
            browser.wakeup.set()
            self.browsers.discard(browser)
            sender.cancel()
            self._log("info", "web_client_disconnected", peer=browser.peer, clients=len(self.browsers))
        return ws

    async def _receive_loop(self, browser: _Browser) -> None:
        """The page sends nothing but its answers to the heartbeat's pings; a peer that sends more (messages,
        pings, pongs alike) is limited to ``WEB_MAX_WS_MESSAGES_PER_S``, then closed (1008): a flood is never
        answered frame by frame."""
        from aiohttp import WSMsgType  # optional extra: web

        window_start, count = time.monotonic(), 0
        async for message in browser.ws:
            now = time.monotonic()
            if now - window_start >= WEB_WS_WINDOW_S:
                window_start, count = now, 0
            count += 1
            if count > WEB_MAX_WS_MESSAGES_PER_S:
                self._log("warning", "web_client_flood", peer=browser.peer, kind=message.type.name)
                await browser.ws.close(code=1008, message=b"too many messages")
                break
            if message.type is WSMsgType.PING:
                await browser.ws.pong(message.data)
            # read-only: nothing else a page sends changes anything

    async def _send_loop(self, browser: _Browser) -> None:
        ws = browser.ws
        try:
            while not browser.gone:
                await browser.wakeup.wait()
                browser.wakeup.clear()
                while browser.queue and not browser.gone:
                    _, text = browser.queue[0]
                    await ws.send_str(text)
                    browser.queue.popleft()
        except (ConnectionError, RuntimeError, asyncio.CancelledError):
            pass


def _check_web_token(token: str | None, host: str) -> None:
    """ValueError unless there is a token, or ``host`` is loopback (as the NDJSON listener's rule)."""
    if token is None and not is_loopback_host(host):
        raise ValueError(
            f"refusing to serve the web view on {host or 'every interface'!r} without a token: anyone "
            "on the network could read the instrument; set a token or bind 127.0.0.1"
        )
    check_token(token, "127.0.0.1")  # the token itself: non-empty text


def _text(obj: dict) -> str:
    """JSON as the NDJSON listener writes it (``ndjson.encode``: non-finite numbers and None left out)."""
    return encode(obj).decode().rstrip("\n")


def _peer(request: Any) -> str:
    """The address a request's client is counted on (``guards.peer_address``; behind a trusted proxy, the
    forwarded one: ``_guard`` puts it in ``remote``)."""
    return peer_address(request.remote or "?")


def _angles_only(message: dict) -> dict:
    """What an open-stream reader without the token gets of a snapshot or an update: the latest ANGLE object."""
    return {"type": message["type"], "angle": message["angle"]}


def _add_security_headers(response: Any) -> None:
    """``SECURITY_HEADERS`` on ``response``, unless it set one of them itself (a static asset's cache rule), and
    ``Server: fog-driver`` in place of aiohttp's."""
    for key, value in SECURITY_HEADERS.items():
        response.headers.setdefault(key, value)
    response.headers["Server"] = SERVER_HEADER


def _handler_class(view: WebView) -> type:
    """aiohttp's connection handler for ``view``'s connections, with its own error answers: a request aiohttp
    could not parse (before any route) gets its status (``connections.bad_request``: 400, 414 or 431) and one
    line of its kind through ``view._log`` (rate-limited), never aiohttp's traceback; a route that failed (500)
    or timed out (504) gets one rate-limited line too.  Every such answer carries ``SECURITY_HEADERS``."""
    from aiohttp import web  # optional extra: web
    from aiohttp.http_exceptions import HttpProcessingError  # optional extra: web
    from aiohttp.web_protocol import RequestHandler  # optional extra: web

    class _Handler(RequestHandler):
        __slots__ = ()  # the instance is aiohttp's, its class swapped: the same layout

        def handle_error(self, request: Any, status: int = 500, exc: Any = None, message: Any = None) -> Any:
            if request.writer.output_size > 0:  # (as aiohttp's) a response began: none can follow
                raise ConnectionError("a response was sent already: no error answer can follow it")
            peer = peer_address(request.remote or "?")
            if isinstance(exc, HttpProcessingError):
                connection = view._connections.get(self)
                status, event, fields = bad_request(exc, connection.head_start if connection else b"")
                view._log("warning", event, peer=peer, status=status, **fields)
                text = f"{status}: {_BAD_REQUEST_TEXT.get(event, 'a malformed request')}\n"
            elif status == 504:
                view._log("warning", "web_request_timed_out", peer=peer, path=request.path[:100])
                text = "504: the request was not answered in time\n"
            else:
                view._log("error", "web_request_failed", peer=peer, path=request.path[:100], error=repr(exc)[:300])
                text = f"{status}: internal error (the daemon's log says which)\n"
            response = web.Response(status=status, text=text)
            response.force_close()
            _add_security_headers(response)
            return response

    return _Handler


#: What a request aiohttp could not parse is told, by its log event (``connections.bad_request``).
_BAD_REQUEST_TEXT = {
    "web_request_line_too_long": f"the request line is over {WEB_MAX_LINE_BYTES} bytes",
    "web_request_header_too_long": f"a header is over {WEB_MAX_LINE_BYTES} bytes",
    "web_request_too_many_headers": f"more than {WEB_MAX_HEADERS} headers",
    "web_request_without_host": "a request needs one valid Host header",
    "web_request_duplicate_header": "a header that may come once came twice",
}


class _AiohttpLogBridge(logging.Handler):
    """What aiohttp itself logs (its ``aiohttp`` loggers: ``aiohttp.server``, ``aiohttp.access``,
    ``aiohttp.web``, ``aiohttp.websocket``, ``aiohttp.internal``), as one rate-limited JSON line each
    (``web_aiohttp_message``, through the running listener's ``_log``), never a traceback: unconfigured,
    Python's last-resort handler would print each record and its traceback on stderr."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.view: WebView | None = None

    def emit(self, record: logging.LogRecord) -> None:
        try:
            message = record.getMessage()
        except Exception:  # noqa: BLE001 - a record that cannot format itself is still one line
            message = str(record.msg)
        error = record.exc_info[1] if record.exc_info else None
        fields = {"logger": record.name, "message": message[:300], "error": repr(error)[:300] if error else None}
        level = "error" if record.levelno >= logging.ERROR else "warning"
        view = self.view
        if view is not None:
            view._log(level, "web_aiohttp_message", **fields)
        else:
            getattr(log, level)("web_aiohttp_message", **fields)


_AIOHTTP_LOGS = _AiohttpLogBridge()


def _route_aiohttp_logs(view: WebView) -> None:
    """Send aiohttp's own log records to ``_AIOHTTP_LOGS`` (on ``view``'s rate limit), and nowhere else."""
    aiohttp_log = logging.getLogger("aiohttp")
    if _AIOHTTP_LOGS not in aiohttp_log.handlers:
        aiohttp_log.addHandler(_AIOHTTP_LOGS)
    aiohttp_log.propagate = False
    aiohttp_log.setLevel(logging.WARNING)
    _AIOHTTP_LOGS.view = view


def _login_page(problem: str | None) -> str:
    note = f'<p class="problem">{problem}</p>' if problem else ""
    return (
        "<!doctype html><html><head><meta charset=utf-8><title>fog-driver: token</title>"
        '<link rel=stylesheet href="/static/view.css"></head><body class=login><h1>fog-driver</h1>'
        f"<p>This daemon's web view needs its token.</p>{note}"
        '<form method=post action="/login"><input type=password name=token autofocus '
        "autocomplete=current-password aria-label=token><button type=submit>Open</button></form>"
        "</body></html>"
    )


__all__ = ["DEFAULT_HTTP_PORT", "OPEN_PATHS", "SECURITY_HEADERS", "WebUnavailable", "WebView", "check_web_extra"]
