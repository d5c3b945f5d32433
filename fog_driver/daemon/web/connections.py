"""The web listener's connections: each one counted against the limits before aiohttp sees a byte of it, and
tracked for the sweeper that closes slow requests (``server.WebView``)."""

from __future__ import annotations

import asyncio
import re
import time
from typing import Any

from ..guards import peer_address

__all__ = ["CountedProtocol", "TrackedConnection", "HEAD_START_BYTES", "aiohttp_web", "bad_request", "request_peer"]

#: How much of each request head a connection keeps (``TrackedConnection.head_start``): enough to tell a request
#: line too long from a header too long (``bad_request``).
HEAD_START_BYTES = 128


class TrackedConnection:
    """What the sweeper knows of one connection: its client's address (``peer``: the socket's, or behind a
    trusted proxy, ``proxied``, the forwarded one once a request said it), since when a request head is awaited
    (None: not now), since when a request runs (None: none), when its first request came (None: not yet),
    whether it became a WebSocket, one that reads the open stream without the token (``reader``), and the first
    ``HEAD_START_BYTES`` of the request head now awaited or last received (``head_start``: for ``bad_request``)."""

    __slots__ = (
        "peer",
        "proxied",
        "head_since_s",
        "request_since_s",
        "first_request_s",
        "websocket",
        "reader",
        "head_start",
    )

    def __init__(self, peer: str, connected_s: float, *, proxied: bool = False) -> None:
        self.peer = peer
        self.proxied = proxied
        self.head_since_s: float | None = connected_s  # a new connection owes its first request head
        self.request_since_s: float | None = None
        self.first_request_s: float | None = None
        self.websocket = False
        self.reader = False
        self.head_start = b""


class CountedProtocol(asyncio.Protocol):
    """A connection's protocol: aiohttp's handler behind the connection limits, tracked for the sweeper.

    ``view.open_connection`` says whether it may go on (``guards.Slots``): when no slot is left for it the
    connection is closed at once, before aiohttp sees a byte of it."""

    def __init__(self, view: Any, handler: Any) -> None:
        self.view = view
        self.handler = handler
        self.peer: str | None = None
        self.connection: TrackedConnection | None = None

    def connection_made(self, transport: Any) -> None:
        peer = peer_of(transport)
        connection = self.view.open_connection(self.handler, peer)
        if connection is None:
            transport.abort()
            return
        self.peer, self.connection = peer, connection
        self.handler.connection_made(transport)

    def data_received(self, data: bytes) -> None:
        if self.peer is None:
            return
        c = self.connection
        if c.request_since_s is None and c.head_since_s is None and not c.websocket:
            c.head_since_s = time.monotonic()  # the next request's head begins: it has WEB_REQUEST_HEAD_TIMEOUT_S
            c.head_start = b""
        if len(c.head_start) < HEAD_START_BYTES and not c.websocket:
            c.head_start += data[: HEAD_START_BYTES - len(c.head_start)]
        self.handler.data_received(data)

    def eof_received(self) -> bool | None:
        return self.handler.eof_received() if self.peer is not None else None

    def pause_writing(self) -> None:
        if self.peer is not None:
            self.handler.pause_writing()

    def resume_writing(self) -> None:
        if self.peer is not None:
            self.handler.resume_writing()

    def connection_lost(self, exc: BaseException | None) -> None:
        if self.peer is None:
            return
        self.view.close_connection(self.handler)
        self.handler.connection_lost(exc)


def peer_of(transport: Any) -> str:
    """The IP address (text) a connection comes from."""
    peer = transport.get_extra_info("peername")
    return str(peer[0]) if isinstance(peer, tuple) and peer else str(peer)


def request_peer(request: Any) -> str:
    """The address a request's client is counted on (``guards.peer_address``; behind a trusted proxy, the
    forwarded one: ``WebView._guard`` puts it in ``remote``)."""
    return peer_address(request.remote or "?")


def aiohttp_web() -> Any:
    """``aiohttp.web``, imported when a request needs it (the optional ``web`` extra)."""
    from aiohttp import web  # optional extra: web

    return web


def bad_request(exc: BaseException, head_start: bytes) -> tuple[int, str, dict[str, Any]]:
    """What a request aiohttp could not parse (``exc``, its ``HttpProcessingError``) gets: the status, the log
    event (one per kind, each rate-limited on its own) and the event's fields.

    ======================================  ======  ====================================================
    the request                             status  event
    ======================================  ======  ====================================================
    a request line over the limit           414     ``web_request_line_too_long``
    a header over the limit                 431     ``web_request_header_too_long``
    more headers than the limit             431     ``web_request_too_many_headers``
    no ``Host`` (HTTP/1.1)                  400     ``web_request_without_host``
    a header that may come once, twice      400     ``web_request_duplicate_header`` (``header``)
    anything else                           400     ``web_request_malformed`` (``problem``)
    ======================================  ======  ====================================================

    aiohttp says "line too long" for both the request line and a header, with the start of the line it met:
    it is the request line when the head's first line (``head_start``, the head's first bytes as the client
    sent them), or its target, starts with it.
    """
    from aiohttp.http_exceptions import LineTooLong  # optional extra: web

    message = str(getattr(exc, "message", "") or exc)
    if isinstance(exc, LineTooLong):
        line = exc.args[0] if exc.args else b""
        met = (line.encode("latin-1", "replace") if isinstance(line, str) else bytes(line)).removesuffix(b"...")[:32]
        first_line = head_start.split(b"\n", 1)[0]
        target = first_line.split(b" ", 1)[-1]
        if met and (target.startswith(met) or first_line.startswith(met)):
            return 414, "web_request_line_too_long", {}
        return 431, "web_request_header_too_long", {}
    if message.startswith("Too many headers"):
        return 431, "web_request_too_many_headers", {}
    if message.startswith("Missing 'Host' header"):
        return 400, "web_request_without_host", {}
    duplicate = re.match(r"Duplicate '([!-~]{1,40})' header", message)
    if duplicate:
        return 400, "web_request_duplicate_header", {"header": duplicate.group(1)}
    return 400, "web_request_malformed", {"problem": message.splitlines()[0][:100] if message else type(exc).__name__}
