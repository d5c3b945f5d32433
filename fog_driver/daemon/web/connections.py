"""The web listener's connections: each one counted against the limits before aiohttp sees a byte of it, and
tracked for the sweeper that closes slow requests (``server.WebView``)."""

from __future__ import annotations

import asyncio
import time
from typing import Any

__all__ = ["CountedProtocol", "TrackedConnection"]


class TrackedConnection:
    """What the sweeper knows of one connection: its client's address (``peer``: the socket's, or behind a
    trusted proxy, ``proxied``, the forwarded one once a request said it), since when a request head is awaited
    (None: not now), since when a request runs (None: none), when its first request came (None: not yet),
    whether it became a WebSocket, and one that reads the open stream without the token (``reader``)."""

    __slots__ = ("peer", "proxied", "head_since_s", "request_since_s", "first_request_s", "websocket", "reader")

    def __init__(self, peer: str, connected_s: float, *, proxied: bool = False) -> None:
        self.peer = peer
        self.proxied = proxied
        self.head_since_s: float | None = connected_s  # a new connection owes its first request head
        self.request_since_s: float | None = None
        self.first_request_s: float | None = None
        self.websocket = False
        self.reader = False


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
