"""The web listener's fan-out to browsers: one WebSocket a page, one encoding of each update for all of them.

A page gets one ``snapshot`` when its WebSocket opens, then an ``update`` every ``1/update_hz`` s
(``view.ViewState``: the latest sample, the new plot points, the banners); an open-stream reader without the
token gets the angles only (``angles_only``: the ANGLE object the page shows).  Each page has its queue of encoded
updates, sent by a task of its own; one that does not read is dropped when its oldest unsent update is older
than ``max_backlog_s``, like an NDJSON client.  A peer may send at most ``WEB_MAX_WS_MESSAGES_PER_S`` messages a
second, pings included (the page sends none; a flood is closed with 1008 rather than answered).
"""

from __future__ import annotations

import asyncio
import time
from collections import deque
from collections.abc import Callable
from typing import Any

from ...ndjson import encode
from ..limits import WEB_MAX_WS_MESSAGES_PER_S, WEB_WS_WINDOW_S
from .view import ViewState


def text(obj: dict) -> str:
    """JSON as the NDJSON listener writes it (``ndjson.encode``: non-finite numbers and None left out)."""
    return encode(obj).decode().rstrip("\n")


def angles_only(message: dict) -> dict:
    """What an open-stream reader without the token gets of a snapshot or an update: the latest ANGLE object."""
    return {"type": message["type"], "angle": message["angle"]}


class Browser:
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


class FanOut:
    """The pages connected to one listener (see the module docstring); on the listener's loop only.

    ``view``: what the pages show; ``drain()`` brings it up to date with what was published; ``log``: the
    listener's rate-limited ``_log``."""

    def __init__(
        self, view: ViewState, drain: Callable[[], None], log: Callable[..., None], *, max_backlog_s: float
    ) -> None:
        self.view = view
        self.drain = drain
        self.max_backlog_s = max_backlog_s
        self.browsers: set[Browser] = set()
        self.dropped_browsers = 0
        self._log = log
        #: device times of the newest point and mean the pages were sent (a page dedups by device time)
        self._sent_after: tuple[float | None, float | None] = (None, None)
        self._sent_restarts = 0

    async def serve(self, browser: Browser, *, login: bool) -> None:
        """Serve one page until its WebSocket closes: its snapshot (``login``: the page offers a logout), then the
        updates ``tick`` queues for it."""
        self.drain()
        now = time.monotonic()
        snapshot = self.view.snapshot(now)
        if not self.browsers:  # the first page: updates carry what comes after its snapshot
            self._sent_after = (
                snapshot["points"][-1]["t_s"] if snapshot["points"] else None,
                snapshot["minutes"][-1]["t_s"] if snapshot["minutes"] else None,
            )
            self._sent_restarts = self.view.restarts
        first = {**snapshot, "login": login} if browser.full else angles_only(snapshot)
        browser.queue.append((now, text(first)))
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

    async def tick(self, update_hz: float) -> None:
        """Take what was published; send every page an update (one encoding for all), ``update_hz`` times a
        second."""
        period = 1.0 / update_hz
        while True:
            await asyncio.sleep(period)
            try:
                self.drain()
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
                full = text(update)
                angles = text(angles_only(update)) if not all(b.full for b in self.browsers) else ""
                for browser in list(self.browsers):
                    self._queue(browser, full if browser.full else angles, now)
            except Exception:  # noqa: BLE001 - one bad object must not end the page's updates
                self._log("exception", "web_update_failed")

    async def close_all(self) -> None:
        """Close every page's WebSocket (the listener stops)."""
        for browser in list(self.browsers):
            browser.gone = True
            browser.wakeup.set()
            await browser.ws.close()

    def _queue(self, browser: Browser, update: str, now: float) -> None:
        if browser.queue and now - browser.queue[0][0] > self.max_backlog_s:
            self._drop(browser, f"not reading: its oldest update is {now - browser.queue[0][0]:.1f} s old")
            return
        browser.queue.append((now, update))
        browser.wakeup.set()

    def _drop(self, browser: Browser, reason: str) -> None:
        if browser.gone:
            return
        browser.gone = True
        self.browsers.discard(browser)
        self.dropped_browsers += 1
        self._log("warning", "web_client_dropped", peer=browser.peer, reason=reason)
        browser.wakeup.set()
        if browser.transport is not None:
            browser.transport.abort()  # its socket buffer is full: a close handshake would wait on it

    async def _receive_loop(self, browser: Browser) -> None:
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

    async def _send_loop(self, browser: Browser) -> None:
        ws = browser.ws
        try:
            while not browser.gone:
                await browser.wakeup.wait()
                browser.wakeup.clear()
                while browser.queue and not browser.gone:
                    _, update = browser.queue[0]
                    await ws.send_str(update)
                    browser.queue.popleft()
        except (ConnectionError, RuntimeError, asyncio.CancelledError):
            pass


__all__ = ["Browser", "FanOut", "angles_only", "text"]
