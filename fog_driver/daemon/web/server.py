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
``GET|POST /login``   the token form, when a token is needed (below)
====================  =========================================================================================

Data in: the acquisition thread calls ``publish_angles(objs)`` with each published batch and ``publish(obj)``
with every other object; both append to a deque and return (no wake-up, no lock); the listener's loop takes
them ``update_hz`` times a second.  A loop that falls behind by more than ``WEB_MAX_INBOX_BATCHES`` batches loses the
oldest (counted: ``inbox_dropped``), never the acquisition's time.

Authorization.  Listening beyond loopback needs the daemon's ``token`` (the config refuses to start
otherwise), and then every request must carry it: ``Authorization: Bearer <token>`` (Prometheus'
``authorization`` setting, ``curl -H``), or the cookie the ``/login`` form sets (a browser: open
``/login``, or ``/?token=...`` once, which sets the cookie and redirects to a URL without the token).
Without it a request gets 401 (a browser: the login form); after ``AUTH_FAILURES_BEFORE_BACKOFF`` wrong tokens from
an address it must wait (1 s, doubling up to 300 s: 429), as on the NDJSON listener.  WebSocket upgrades
must come from the page's own origin (a foreign ``Origin``: 403).

Limits (a misbehaving client costs itself, never the instrument): ``WEB_MAX_CONNECTIONS`` connections and
``WEB_MAX_CONNECTIONS_PER_PEER`` per address (beyond them the connection is closed at once); request line and
each header at most ``WEB_MAX_LINE_BYTES``, ``WEB_MAX_HEADERS`` headers (431/400), a body at most ``WEB_MAX_BODY_BYTES``
(413); a request head must be complete within ``WEB_REQUEST_HEAD_TIMEOUT_S`` of the connection (the first) or of
its first byte (the next ones on a kept-alive connection), and a request must be answered within
``WEB_REQUEST_TIMEOUT_S`` (a client that does not read its response is closed); idle keep-alive connections
close after ``WEB_KEEPALIVE_S``; a WebSocket peer may send at most ``WEB_MAX_WS_MESSAGE_BYTES`` per
message and ``WEB_MAX_WS_MESSAGES_PER_S`` messages a second (the page sends none), and one that does not read
is dropped when its oldest unsent update is older than ``max_client_backlog_s``, like an NDJSON client.
"""

from __future__ import annotations

import asyncio
import contextlib
import gzip
import hashlib
import hmac
import importlib.resources
import importlib.util
import math
import secrets
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from typing import Any

import structlog

from ...client.ndjson import encode
from ..guards import AuthThrottle, LogRateLimiter, check_token, is_loopback_host
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
    WEB_SHUTDOWN_TIMEOUT_S,
    WEB_START_TIMEOUT_S,
    WEB_STOP_TIMEOUT_S,
    WEB_SWEEP_EVERY_S,
    WEB_WS_HEARTBEAT_S,
    WEB_WS_WINDOW_S,
)
from .connections import CountedProtocol, TrackedConnection
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
_SECURITY_HEADERS = {
    "Content-Security-Policy": "default-src 'self'; img-src 'self' data:; style-src 'self' 'unsafe-inline'; "
    "connect-src 'self'; frame-ancestors 'none'",
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
    "Cache-Control": "no-store",
}


class WebUnavailable(RuntimeError):
    """The ``web`` extra (aiohttp, plotly, prometheus-client) is not installed."""


def check_web_extra() -> None:
    """WebUnavailable naming what is missing, unless aiohttp, plotly and prometheus-client import."""
    missing = [name for name in ("aiohttp", "plotly", "prometheus_client") if importlib.util.find_spec(name) is None]
    if missing:
        raise WebUnavailable(f"the web view needs {', '.join(missing)}: pip install 'fog_driver[web]'")


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
    """One WebSocket peer: its queue of encoded updates (with the host time each was queued)."""

    __slots__ = ("peer", "queue", "wakeup", "ws", "transport", "gone")

    def __init__(self, peer: str, ws: Any, transport: Any) -> None:
        self.peer = peer
        self.ws = ws
        self.transport = transport
        self.queue: deque[tuple[float, str]] = deque()
        self.wakeup = asyncio.Event()
        self.gone = False


class WebView:
    """The web listener of one daemon (see the module docstring).

    ``read_status()`` (any thread; called on this listener's thread at each scrape) returns the mapping
    ``metrics.DaemonCollector`` reads, without ``angle``/``web_*`` keys: those are filled in here.
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
    ) -> None:
        check_web_extra()
        _check_web_token(token, host)
        if not (math.isfinite(update_hz) and 0 < update_hz <= WEB_MAX_UPDATE_HZ):
            raise ValueError(f"update_hz must be in (0, 50], got {update_hz!r}")
        self.host, self.port = host, port
        self.token = token
        self.need_token = not is_loopback_host(host)
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
        self._cookie_value = secrets.token_urlsafe(24)  # what the cookie holds: never the token itself
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
        self._peers: dict[str, int] = {}
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

    def set_token(self, token: str | None) -> None:
        """A new token (SIGHUP): cookies given for the old one stop working."""
        _check_web_token(token, self.host)
        self.token = token
        self._cookie_value = secrets.token_urlsafe(24)

    # ------------------------------------------------------------------ connections (the listener's loop)

    def open_connection(self, handler: Any, peer: str) -> TrackedConnection | None:
        """Track a new connection from ``peer``; None (counted in ``refused_connections``) beyond
        ``WEB_MAX_CONNECTIONS`` or ``WEB_MAX_CONNECTIONS_PER_PEER``."""
        if len(self._connections) >= WEB_MAX_CONNECTIONS or self._peers.get(peer, 0) >= WEB_MAX_CONNECTIONS_PER_PEER:
            self.refused_connections += 1
            return None
        self._peers[peer] = self._peers.get(peer, 0) + 1
        connection = self._connections[handler] = TrackedConnection(peer, time.monotonic())
        return connection

    def close_connection(self, handler: Any, peer: str) -> None:
        """Forget a connection ``open_connection`` tracked."""
        self._connections.pop(handler, None)
        left = self._peers.get(peer, 1) - 1
        if left > 0:
            self._peers[peer] = left
        else:
            self._peers.pop(peer, None)

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

        app = web.Application(client_max_size=WEB_MAX_BODY_BYTES, middlewares=[guard])
        app.router.add_get("/", self._page)
        app.router.add_get("/ws", self._websocket)
        app.router.add_get("/api/view", self._api_view)
        app.router.add_get("/metrics", self._metrics)
        app.router.add_get("/static/{name}", self._static)
        app.router.add_get("/login", self._login_form)
        app.router.add_get("/favicon.ico", self._no_icon)
        app.router.add_post("/login", self._login)
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

        def protocol() -> Any:
            return CountedProtocol(self, factory())

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
                for browser in list(self.browsers):
                    self._queue(browser, text, now)
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
            await asyncio.sleep(min(WEB_SWEEP_EVERY_S, WEB_REQUEST_HEAD_TIMEOUT_S / 2))
            now = time.monotonic()
            for event, count in self._log_limiter.take_suppressed(now):
                log.warning("log_lines_suppressed", suppressed_event=event, count=count)
            for handler, c in list(self._connections.items()):
                if c.head_since_s is not None and now - c.head_since_s > WEB_REQUEST_HEAD_TIMEOUT_S:
                    reason = f"no complete request head within {WEB_REQUEST_HEAD_TIMEOUT_S:g} s"
                elif c.request_since_s is not None and now - c.request_since_s > WEB_REQUEST_TIMEOUT_S:
                    reason = f"request not done within {WEB_REQUEST_TIMEOUT_S:g} s"
                else:
                    continue
                self._log("info", "web_connection_closed", peer=c.peer, reason=reason)
                handler.force_close()
                if handler.transport is not None:
                    handler.transport.abort()
                self._connections.pop(handler, None)

    # ------------------------------------------------------------------ requests

    def _credentials(self, request: Any) -> str:
        """``ok``, ``wrong`` (an ``Authorization`` token that does not match: counted against the address) or
        ``none`` (no token, or only a cookie that is no longer valid)."""
        header = request.headers.get("Authorization")
        cookie = request.cookies.get(COOKIE)
        if cookie and hmac.compare_digest(cookie.encode("utf-8", "replace"), self._cookie_value.encode()):
            return "ok"
        if header is None:  # no token; a stale cookie (a token rotated since) is no guess: log in again
            return "none"
        given = header[7:] if header.startswith("Bearer ") else ""
        if self.token is not None and hmac.compare_digest(given.encode("utf-8", "replace"), self.token.encode()):
            return "ok"
        return "wrong"

    def _wait_response(self, peer: str, now: float) -> Any:
        """429 while ``peer`` is blocked for wrong tokens, else None."""
        wait_s = self._throttle.blocked_for_s(peer, now)
        if wait_s <= 0:
            return None
        return self._web().Response(
            status=429,
            text=f"429: too many wrong tokens from {peer}: try again in {math.ceil(wait_s)} s\n",
            headers={"Retry-After": str(math.ceil(wait_s))},
        )

    def _web(self):
        from aiohttp import web  # optional extra: web

        return web

    async def _guard(self, request: Any, handler: Callable) -> Any:
        """Middleware: timing for the sweeper, authorization, security headers."""
        web = self._web()
        self.requests += 1
        connection = self._connections.get(request.protocol)
        if connection is not None:
            connection.head_since_s, connection.request_since_s = None, time.monotonic()
        try:
            if request.method not in ("GET", "HEAD", "POST"):
                raise web.HTTPMethodNotAllowed(request.method, ["GET", "HEAD", "POST"])
            response = None
            if self.need_token and request.path != "/login":
                response = await self._authorize(request)
            if response is None:
                response = await handler(request)
            if isinstance(response, web.StreamResponse) and not response.prepared:
                for key, value in _SECURITY_HEADERS.items():
                    response.headers.setdefault(key, value)
            return response
        finally:
            if connection is not None:
                connection.request_since_s = None

    async def _authorize(self, request: Any) -> Any:
        """None when the request carries the token (or the login cookie); else the response refusing it."""
        peer, now = _peer(request), time.monotonic()
        waiting = self._wait_response(peer, now)
        if waiting is not None:
            return waiting
        verdict = self._credentials(request)
        if verdict == "ok":
            self._throttle.succeeded(peer)
            return None
        if verdict == "wrong":
            self._throttle.failed(peer, now)
            self._log("warning", "web_token_refused", peer=peer, path=request.path)
            return self._web().Response(
                status=401, text="401: wrong token\n", headers={"WWW-Authenticate": 'Bearer realm="fog-driver"'}
            )
        return await self._refuse(request)

    async def _refuse(self, request: Any) -> Any:
        web = self._web()
        peer = _peer(request)
        token = request.query.get("token")
        if token is not None and request.path == "/":  # a link with the token: set the cookie, drop the token
            return await self._check_login(request, token)
        if "text/html" in request.headers.get("Accept", "") and request.path == "/":
            raise web.HTTPFound("/login")
        self._log("info", "web_unauthorized", peer=peer, path=request.path)
        return web.Response(
            status=401,
            text="401: this daemon's web view needs its token (Authorization: Bearer <token>, or the form at /login)\n",
            headers={"WWW-Authenticate": 'Bearer realm="fog-driver"'},
        )

    async def _check_login(self, request: Any, token: str) -> Any:
        web = self._web()
        peer = _peer(request)
        now = time.monotonic()
        waiting = self._wait_response(peer, now)
        if waiting is not None:
            return waiting
        if self.token is not None and hmac.compare_digest(token.encode("utf-8", "replace"), self.token.encode()):
            self._throttle.succeeded(peer)
            response = web.Response(status=303, headers={"Location": "/"})
            response.set_cookie(COOKIE, self._cookie_value, httponly=True, samesite="Strict", path="/")
            self._log("info", "web_login", peer=peer)
            return response
        self._throttle.failed(peer, now)
        self._log("warning", "web_login_refused", peer=peer)
        return web.Response(status=401, content_type="text/html", text=_login_page("wrong token"))

    async def _login_form(self, request: Any) -> Any:
        web = self._web()
        if not self.need_token:
            raise web.HTTPFound("/")
        return web.Response(content_type="text/html", text=_login_page(None))

    async def _login(self, request: Any) -> Any:
        web = self._web()
        if not self.need_token:
            raise web.HTTPFound("/")
        form = await request.post()  # at most WEB_MAX_BODY_BYTES (413 beyond)
        token = form.get("token")
        if not isinstance(token, str) or not token:
            return web.Response(status=400, content_type="text/html", text=_login_page("no token given"))
        return await self._check_login(request, token)

    async def _page(self, request: Any) -> Any:
        web = self._web()
        if request.query.get("token") is not None:  # authorized already: keep the token out of the URL bar
            raise web.HTTPSeeOther("/")
        return web.Response(body=self._index, content_type="text/html", charset="utf-8")

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
        web = self._web()
        origin = request.headers.get("Origin")
        if origin is not None and origin.split("://", 1)[-1] != request.host:
            return web.Response(status=403, text="403: a WebSocket from another origin\n")
        ws = web.WebSocketResponse(max_msg_size=WEB_MAX_WS_MESSAGE_BYTES, heartbeat=WEB_WS_HEARTBEAT_S, compress=False)
        if not ws.can_prepare(request).ok:
            return web.Response(status=400, text="400: /ws takes a WebSocket upgrade\n")
        await ws.prepare(request)
        connection = self._connections.get(request.protocol)
        if connection is not None:  # a WebSocket is a long exchange of frames, neither a slow request nor a head
            connection.request_since_s, connection.websocket = None, True
        browser = _Browser(_peer(request), ws, request.transport)
        self._drain()
        now = time.monotonic()
        snapshot = self.view.snapshot(now)
        if not self.browsers:  # the first page: updates carry what comes after its snapshot
            self._sent_after = (
                snapshot["points"][-1]["t_s"] if snapshot["points"] else None,
                snapshot["minutes"][-1]["t_s"] if snapshot["minutes"] else None,
            )
            self._sent_restarts = self.view.restarts
        browser.queue.append((now, _text(snapshot)))
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
        """The page sends nothing; a peer that does is limited, then closed."""
        window_start, count = time.monotonic(), 0
        async for message in browser.ws:
            now = time.monotonic()
            if now - window_start >= WEB_WS_WINDOW_S:
                window_start, count = now, 0
            count += 1
            if count > WEB_MAX_WS_MESSAGES_PER_S:
                await browser.ws.close(code=1008, message=b"too many messages")
                break
            del message  # read-only: nothing a page sends changes anything

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
    return str(request.remote or "?")


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


__all__ = ["DEFAULT_HTTP_PORT", "WebUnavailable", "WebView", "check_web_extra"]
