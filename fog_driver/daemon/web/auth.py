"""The web listener's authentication: the daemon's token, the login form and its session cookie, the backoff.

Listening beyond loopback needs the daemon's ``token`` (``check_web_token``); once the daemon has one, on
loopback too, every request but ``OPEN_PATHS`` must carry it: ``Authorization: Bearer <token>`` (the scheme in any
case), or the session cookie the ``/login`` form sets (``access.Sessions``: never the token itself, never the
token in a URL).  With ``open_stream``, a WebSocket without it gets the angles only.  Without it a request gets
401 (a browser asking for the page: the login form).  Wrong tokens are counted per address as on the NDJSON
listener (``guards.AuthThrottle``): while an address waits, every token from it, the right one too, is answered
429 unread.  The cookie is HttpOnly, SameSite=Strict, lasts ``WEB_SESSION_MAX_AGE_S``, is ``Secure`` with
``secure_cookies``; a new token (``replace``) voids every session.
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Callable
from typing import Any

from ..guards import AuthThrottle, Slots, check_token, is_loopback_host, token_matches
from ..limits import DEFAULT_AUTH_BACKOFF_BASE_S, DEFAULT_AUTH_BACKOFF_MAX_S, WEB_SESSION_MAX_AGE_S
from .access import Sessions
from .connections import aiohttp_web, request_peer

COOKIE = "fog_driver_token"
#: What a request needs no token for: the login form, the logout, and what the form loads.
OPEN_PATHS = frozenset({"/login", "/logout", "/static/view.css", "/favicon.ico"})
_BEARER_CHALLENGE = {"WWW-Authenticate": 'Bearer realm="fog-driver"'}


def check_web_token(token: str | None, host: str) -> None:
    """ValueError unless there is a token, or ``host`` is loopback (as the NDJSON listener's rule)."""
    if token is None and not is_loopback_host(host):
        raise ValueError(
            f"refusing to serve the web view on {host or 'every interface'!r} without a token: anyone "
            "on the network could read the instrument; set a token or bind 127.0.0.1"
        )
    check_token(token, "127.0.0.1")  # the token itself: non-empty text


class WebAuth:
    """Who has the token: judges each request's credentials, serves ``/login`` and ``/logout`` (see the module
    docstring).  ``slots``: the listener's (a connection that shows the token is authorized there); ``log``:
    the listener's rate-limited ``_log``.  On the listener's loop only."""

    def __init__(
        self,
        token: str | None,
        *,
        slots: Slots,
        log: Callable[..., None],
        open_stream: bool = False,
        secure_cookies: bool = False,
    ) -> None:
        self.token = token
        self.slots = slots
        self.open_stream = open_stream
        self.secure_cookies = secure_cookies
        self.sessions = Sessions()  # what the cookies hold: never the token itself
        self.throttle = AuthThrottle(DEFAULT_AUTH_BACKOFF_BASE_S, DEFAULT_AUTH_BACKOFF_MAX_S)
        self._log = log

    @property
    def need_token(self) -> bool:
        """Every request but ``OPEN_PATHS`` needs the token: the daemon has one."""
        return self.token is not None

    def replace(self, token: str | None) -> None:
        """The token and the sessions change together: no request sees the new token with an old session."""
        self.token = token
        self.sessions.clear()

    def credentials(self, request: Any, now: float) -> str:
        """``session`` (a live session's cookie: no guess of the token), ``bearer`` (an ``Authorization`` header:
        its token is judged by ``_bearer``) or ``none`` (no credentials, or only a cookie no longer valid)."""
        if self.sessions.valid(request.cookies.get(COOKIE), now):
            return "session"
        if request.headers.get("Authorization") is None:  # no token; a stale cookie (a token rotated) is no guess
            return "none"
        return "bearer"

    def _bearer_matches(self, request: Any) -> bool:
        """The request's ``Authorization`` is ``Bearer <the token>`` (the scheme in any case)."""
        scheme, _, given = request.headers.get("Authorization", "").strip().partition(" ")
        return scheme.lower() == "bearer" and token_matches(given.strip(), self.token)

    def authorize(self, request: Any, now: float) -> Any:
        """None when the request carries the token (or a session's cookie), or may read the open stream; else the
        response refusing it.  A token is judged by the backoff (``guards.AuthThrottle``): while the address
        waits it is not compared, and the right one gets the same 429 as a wrong one."""
        web = aiohttp_web()
        peer = request_peer(request)
        verdict = self.credentials(request, now)
        if verdict == "none":
            return self._refuse(request)
        if verdict == "session":
            self.slots.authorize(request.protocol)
            return None
        judged, seconds = self.throttle.judge(peer, functools.partial(self._bearer_matches, request), now)
        if judged == "ok":
            self.slots.authorize(request.protocol)
            return None
        if judged == "blocked":
            return self._wait_response(peer, seconds)
        self._log("warning", "web_token_refused", peer=peer, path=request.path)
        return web.Response(status=401, text="401: wrong token\n", headers=_BEARER_CHALLENGE)

    def _refuse(self, request: Any) -> Any:
        """A request without credentials: the open stream's reader passes; a browser asking for the page is sent to
        the login form; anything else gets 401."""
        web = aiohttp_web()
        if self.open_stream and request.path == "/ws":
            return None  # the angles only (``routes.Routes.websocket``)
        if "text/html" in request.headers.get("Accept", "") and request.path == "/":
            raise web.HTTPFound("/login")
        self._log("info", "web_unauthorized", peer=request_peer(request), path=request.path)
        return web.Response(
            status=401,
            text="401: this daemon's web view needs its token (Authorization: Bearer <token>, or the form at /login)\n",
            headers=_BEARER_CHALLENGE,
        )

    def _wait_response(self, peer: str, wait_s: float, *, page: bool = False) -> Any:
        """429: ``peer`` is blocked for wrong tokens (``wait_s`` more seconds); the login form when ``page``."""
        web = aiohttp_web()
        seconds = math.ceil(wait_s)
        text = f"too many wrong tokens from {peer}: try again in {seconds} s"
        headers = {"Retry-After": str(seconds)}
        if page:
            return web.Response(status=429, content_type="text/html", text=login_page(text), headers=headers)
        return web.Response(status=429, text=f"429: {text}\n", headers=headers)

    # ------------------------------------------------------------------ the routes

    async def login_form(self, request: Any) -> Any:
        web = aiohttp_web()
        if not self.need_token:
            raise web.HTTPFound("/")
        return web.Response(content_type="text/html", text=login_page(None))

    async def login(self, request: Any) -> Any:
        """The form's token: a session cookie and the page (303), or the form again saying why not."""
        web = aiohttp_web()
        if not self.need_token:
            raise web.HTTPFound("/")
        form = await request.post()  # at most WEB_MAX_BODY_BYTES (413 beyond)
        token = form.get("token")
        if not isinstance(token, str) or not token:
            return web.Response(status=400, content_type="text/html", text=login_page("no token given"))
        peer, now = request_peer(request), time.monotonic()
        expected = self.token
        judged, seconds = self.throttle.judge(peer, lambda: token_matches(token, expected), now)
        if judged == "blocked":
            return self._wait_response(peer, seconds, page=True)
        if judged == "wrong":
            self._log("warning", "web_login_refused", peer=peer)
            return web.Response(status=401, content_type="text/html", text=login_page("wrong token"))
        self.slots.authorize(request.protocol)
        response = web.Response(status=303, headers={"Location": "/"})
        response.set_cookie(
            COOKIE,
            self.sessions.start(now),
            max_age=WEB_SESSION_MAX_AGE_S,
            path="/",
            httponly=True,
            samesite="Strict",
            secure=self.secure_cookies,
        )
        self._log("info", "web_login", peer=peer)
        return response

    async def logout(self, request: Any) -> Any:
        """End the browser's session (its cookie is void here and deleted there); back to the login form."""
        self.sessions.end(request.cookies.get(COOKIE))
        response = aiohttp_web().Response(status=303, headers={"Location": "/login" if self.need_token else "/"})
        response.del_cookie(COOKIE, path="/", httponly=True, samesite="Strict", secure=self.secure_cookies)
        return response

    def add_routes(self, router: Any) -> None:
        router.add_get("/login", self.login_form)
        router.add_post("/login", self.login)
        router.add_post("/logout", self.logout)


def login_page(problem: str | None) -> str:
    note = f'<p class="problem">{problem}</p>' if problem else ""
    return (
        "<!doctype html><html><head><meta charset=utf-8><title>fog-driver: token</title>"
        '<link rel=stylesheet href="/static/view.css"></head><body class=login><h1>fog-driver</h1>'
        f"<p>This daemon's web view needs its token.</p>{note}"
        '<form method=post action="/login"><input type=password name=token autofocus '
        "autocomplete=current-password aria-label=token><button type=submit>Open</button></form>"
        "</body></html>"
    )


__all__ = ["COOKIE", "OPEN_PATHS", "WebAuth", "check_web_token", "login_page"]
