"""The web listener's read-only routes (the page offers no command; ``/login`` and ``/logout``: ``auth.py``).

====================  =========================================================================================
``GET /``             the page (``static/index.html``, with ``view.js`` and ``view.css``)
``GET /ws``           WebSocket: one ``snapshot`` when it opens, then an ``update`` every ``1/update_hz`` s
                      (``fanout.FanOut``)
``GET /api/view``     the same snapshot as one JSON document (scripts, ``curl``)
``GET /metrics``      Prometheus text exposition (``metrics.DaemonCollector``)
``GET /static/...``   the page's assets; ``plotly.min.js`` comes from the installed ``plotly`` package (no CDN),
                      each with its ETag (304 when unchanged) and gzipped when the client takes it
====================  =========================================================================================
"""

from __future__ import annotations

import gzip
import hashlib
import importlib.resources
import time
from collections.abc import Mapping
from typing import Any

from ..limits import WEB_MAX_WS_MESSAGE_BYTES, WEB_WS_HEARTBEAT_S
from .connections import aiohttp_web, request_peer
from .fanout import Browser, text

#: The page's assets: name -> (package, resource path, content type).
ASSETS = {
    "view.js": ("fog_driver.daemon.web", "static/view.js", "text/javascript"),
    "view.css": ("fog_driver.daemon.web", "static/view.css", "text/css"),
    "plotly.min.js": ("plotly", "package_data/plotly.min.js", "text/javascript"),
}


class _Asset:
    __slots__ = ("body", "gzipped", "content_type", "etag")

    def __init__(self, body: bytes, content_type: str) -> None:
        self.body = body
        self.gzipped = gzip.compress(body, compresslevel=6, mtime=0)
        self.content_type = content_type
        self.etag = '"' + hashlib.sha256(body).hexdigest()[:32] + '"'


class Routes:
    """The routes of one web listener (``listener``: its ``WebView``), on the listener's loop."""

    def __init__(self, listener: Any) -> None:
        self.listener = listener
        self._assets: dict[str, _Asset] = {}
        self._index = b""

    def load(self) -> None:
        """Read the page and its assets (once, before the listener starts)."""
        self._assets = {
            name: _Asset(importlib.resources.files(package).joinpath(path).read_bytes(), content_type)
            for name, (package, path, content_type) in ASSETS.items()
        }
        self._index = importlib.resources.files("fog_driver.daemon.web").joinpath("static/index.html").read_bytes()

    def add_routes(self, router: Any) -> None:
        router.add_get("/", self.page)
        router.add_get("/ws", self.websocket)
        router.add_get("/api/view", self.api_view)
        router.add_get("/metrics", self.metrics)
        router.add_get("/static/{name}", self.static)
        router.add_get("/favicon.ico", self.no_icon)

    async def page(self, request: Any) -> Any:
        return aiohttp_web().Response(body=self._index, content_type="text/html", charset="utf-8")

    async def static(self, request: Any) -> Any:
        web = aiohttp_web()
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

    async def no_icon(self, request: Any) -> Any:
        return aiohttp_web().Response(status=204)

    async def api_view(self, request: Any) -> Any:
        self.listener.drain()
        snapshot = self.listener.view.snapshot(time.monotonic())
        return aiohttp_web().Response(text=text(snapshot), content_type="application/json")

    def metrics_state(self) -> Mapping[str, Any]:
        """What ``metrics.DaemonCollector`` reads at a scrape: the daemon's ``read_status()`` with the page's
        ``angle``, rate and ``web_*`` keys."""
        listener = self.listener
        state = dict(listener.read_status())
        listener.drain()
        view = listener.view
        now = time.monotonic()
        state.update(
            angle=view.angle or {},
            rate_1s_dph=view.rate_1s_dph,
            web_clients=len(listener.fanout.browsers),
            web_dropped=listener.fanout.dropped_browsers,
            angle_age_s=None if view.angle_host_s is None else now - view.angle_host_s,
        )
        for cls, key in (("DEVICE", "device"), ("VERSION", "version")):
            state.setdefault(key, view.objects.get(cls, {}))
        return state

    async def metrics(self, request: Any) -> Any:
        from prometheus_client import CONTENT_TYPE_LATEST, generate_latest  # optional extra: web

        body = generate_latest(self.listener.registry)
        return aiohttp_web().Response(body=body, headers={"Content-Type": CONTENT_TYPE_LATEST})

    async def websocket(self, request: Any) -> Any:
        """The page's updates (the angles only for an open-stream reader without the token: ``auth``)."""
        web = aiohttp_web()
        listener, auth = self.listener, self.listener.auth
        ws = web.WebSocketResponse(
            max_msg_size=WEB_MAX_WS_MESSAGE_BYTES, heartbeat=WEB_WS_HEARTBEAT_S, compress=False, autoping=False
        )
        if not ws.can_prepare(request).ok:
            return web.Response(status=400, text="400: /ws takes a WebSocket upgrade\n")
        await ws.prepare(request)
        reader = auth.need_token and auth.credentials(request, time.monotonic()) == "none"  # ``auth`` let it in
        connection = listener.connections.get(request.protocol)
        if connection is not None:  # a WebSocket is a long exchange of frames, neither a slow request nor a head
            connection.request_since_s, connection.websocket, connection.reader = None, True, reader
        if reader:
            listener.slots.set_reader(request.protocol)
        browser = Browser(request_peer(request), ws, request.transport, full=not reader)
        await listener.fanout.serve(browser, login=auth.need_token)
        return ws


__all__ = ["ASSETS", "Routes"]
