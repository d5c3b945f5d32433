"""What the web listener answers and logs beside its routes: every answer's headers, the answers aiohttp gives
itself (a request it could not parse, a route that failed or timed out), and aiohttp's own log records.

Every answer carries ``SECURITY_HEADERS`` (a Content Security Policy, ``nosniff``, ``no-store``) and
``Server: fog-driver``, redirects and errors included.  The CSP allows inline styles: plotly sets them
(``style`` attributes, inserted ``<style>`` rules); the page's own are in ``view.css``.  Every client-caused
event is one rate-limited structlog line of its kind through the listener's ``_log``: a request aiohttp cannot
parse included (``handler_class``), and whatever aiohttp's loggers say (``route_aiohttp_logs``): never a
traceback on stderr.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from typing import Any

import structlog

from ..guards import peer_address
from ..limits import WEB_MAX_HEADERS, WEB_MAX_LINE_BYTES
from .connections import TrackedConnection, bad_request

log = structlog.get_logger("fog_driver.web")

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

#: What a request aiohttp could not parse is told, by its log event (``connections.bad_request``).
_BAD_REQUEST_TEXT = {
    "web_request_line_too_long": f"the request line is over {WEB_MAX_LINE_BYTES} bytes",
    "web_request_header_too_long": f"a header is over {WEB_MAX_LINE_BYTES} bytes",
    "web_request_too_many_headers": f"more than {WEB_MAX_HEADERS} headers",
    "web_request_without_host": "a request needs one valid Host header",
    "web_request_duplicate_header": "a header that may come once came twice",
}


def add_security_headers(response: Any) -> None:
    """``SECURITY_HEADERS`` on ``response``, unless it set one of them itself (a static asset's cache rule), and
    ``Server: fog-driver`` in place of aiohttp's."""
    for key, value in SECURITY_HEADERS.items():
        response.headers.setdefault(key, value)
    response.headers["Server"] = SERVER_HEADER


def handler_class(connections: Mapping[Any, TrackedConnection], log_line: Callable[..., None]) -> type:
    """aiohttp's connection handler for a listener's connections (``connections``: the listener's, by handler),
    with its own error answers: a request aiohttp could not parse (before any route) gets its status
    (``connections.bad_request``: 400, 414 or 431) and one line of its kind through ``log_line`` (the listener's
    rate-limited ``_log``), never aiohttp's traceback; a route that failed (500) or timed out (504) gets one
    rate-limited line too.  Every such answer carries ``SECURITY_HEADERS``."""
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
                connection = connections.get(self)
                status, event, fields = bad_request(exc, connection.head_start if connection else b"")
                log_line("warning", event, peer=peer, status=status, **fields)
                text = f"{status}: {_BAD_REQUEST_TEXT.get(event, 'a malformed request')}\n"
            elif status == 504:
                log_line("warning", "web_request_timed_out", peer=peer, path=request.path[:100])
                text = "504: the request was not answered in time\n"
            else:
                log_line("error", "web_request_failed", peer=peer, path=request.path[:100], error=repr(exc)[:300])
                text = f"{status}: internal error (the daemon's log says which)\n"
            response = web.Response(status=status, text=text)
            response.force_close()
            add_security_headers(response)
            return response

    return _Handler


class _AiohttpLogBridge(logging.Handler):
    """What aiohttp itself logs (its ``aiohttp`` loggers: ``aiohttp.server``, ``aiohttp.access``,
    ``aiohttp.web``, ``aiohttp.websocket``, ``aiohttp.internal``), as one rate-limited JSON line each
    (``web_aiohttp_message``, through the running listener's ``_log``), never a traceback: unconfigured,
    Python's last-resort handler would print each record and its traceback on stderr."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.listener: Any = None  # the running web listener (its ``_log``), or None

    def emit(self, record: logging.LogRecord) -> None:
        try:
            message = record.getMessage()
        except Exception:  # noqa: BLE001 - a record that cannot format itself is still one line
            message = str(record.msg)
        error = record.exc_info[1] if record.exc_info else None
        fields = {"logger": record.name, "message": message[:300], "error": repr(error)[:300] if error else None}
        level = "error" if record.levelno >= logging.ERROR else "warning"
        listener = self.listener
        if listener is not None:
            listener._log(level, "web_aiohttp_message", **fields)
        else:
            getattr(log, level)("web_aiohttp_message", **fields)


_AIOHTTP_LOGS = _AiohttpLogBridge()


def route_aiohttp_logs(listener: Any) -> None:
    """Send aiohttp's own log records to the bridge (on ``listener``'s rate limit), and nowhere else."""
    aiohttp_log = logging.getLogger("aiohttp")
    if _AIOHTTP_LOGS not in aiohttp_log.handlers:
        aiohttp_log.addHandler(_AIOHTTP_LOGS)
    aiohttp_log.propagate = False
    aiohttp_log.setLevel(logging.WARNING)
    _AIOHTTP_LOGS.listener = listener


def unroute_aiohttp_logs(listener: Any) -> None:
    """``listener`` stopped: aiohttp's records go to the module's logger again (unless another listener took
    them meanwhile)."""
    if _AIOHTTP_LOGS.listener is listener:
        _AIOHTTP_LOGS.listener = None


__all__ = [
    "SECURITY_HEADERS",
    "SERVER_HEADER",
    "add_security_headers",
    "handler_class",
    "route_aiohttp_logs",
    "unroute_aiohttp_logs",
]
