"""The web view of a started daemon (``fog-driver run --http``) under requests aiohttp cannot parse, and the
answers every request gets: one rate-limited JSON log line per kind of bad request (never a traceback), the
``Server`` header, a refused absolute-form target, 414/431 for what is too long.

The daemon is a subprocess replaying a short capture; it is ready when its banner names the web view's
address (its first stdout line), and its stderr is read once it has exited.  Nothing waits on a clock.
"""

from __future__ import annotations

import json
import math
import re
import signal
import sys
import time
from collections import Counter
from pathlib import Path

import pytest
from daemon_process import GUARD_S, daemon_process
from web_helpers import get, host_of, http

from fog_driver.daemon.limits import DEFAULT_LOG_LINES_PER_S, LOG_WINDOW_S, WEB_MAX_HEADERS, WEB_MAX_LINE_BYTES

pytest.importorskip("aiohttp", reason="the web extra")

DATA = Path(__file__).resolve().parents[2] / "data"
REPLAY = f"replay://{DATA / 'sim-short.bin'}?rate=10"
#: How many times each kind of bad request is sent.
REPEATS = 200


def bad_requests(address) -> dict[str, tuple[bytes, int]]:
    """Each kind of request aiohttp cannot parse: its log event -> (the request, the status it must get)."""
    host = f"Host: {host_of(address)}\r\n".encode()
    many = b"".join(f"X-H{i}: 1\r\n".encode() for i in range(WEB_MAX_HEADERS))  # with Host: one too many
    return {
        "web_request_without_host": (b"GET / HTTP/1.1\r\n\r\n", 400),
        "web_request_duplicate_header": (b"GET / HTTP/1.1\r\n" + host + host + b"\r\n", 400),
        "web_request_line_too_long": (
            b"GET /" + b"a" * (WEB_MAX_LINE_BYTES + 1) + b" HTTP/1.1\r\n" + host + b"\r\n",
            414,
        ),
        "web_request_header_too_long": (
            b"GET / HTTP/1.1\r\n" + host + b"X-Junk: " + b"a" * (WEB_MAX_LINE_BYTES + 1) + b"\r\n\r\n",
            431,
        ),
        "web_request_too_many_headers": (b"GET / HTTP/1.1\r\n" + host + many + b"\r\n", 431),
    }


class Daemon:
    """``fog-driver run`` replaying a capture, with the web view on a free loopback port."""

    def __init__(self, tmp_path: Path, *extra: str) -> None:
        self.log = tmp_path / "daemon.err"
        self._context = daemon_process(
            [
                sys.executable,
                "-m",
                "fog_driver",
                "run",
                "--port",
                REPLAY,
                "--listen",
                "127.0.0.1:0",
                "--http",
                "127.0.0.1:0",
                "--capture-dir",
                str(tmp_path / "captures"),
                *extra,
            ],
            cwd=tmp_path,
            log=self.log,
        )
        self.proc = self._context.__enter__()
        self._open = True
        banner = self.proc.stdout.readline()
        found = re.search(r"web view on http://127\.0\.0\.1:(\d+)/", banner)
        assert found, (banner, self.log.read_text()[-3000:])
        self.address = ("127.0.0.1", int(found.group(1)))

    def stop(self) -> list[dict]:
        """SIGTERM, exit 0; every stderr line, each parsed as the JSON object it must be."""
        self.proc.send_signal(signal.SIGTERM)
        assert self.proc.wait(GUARD_S) == 0, self.log.read_text()[-3000:]
        self.close()
        text = self.log.read_text()
        assert "Traceback" not in text, text[-3000:]
        lines = [json.loads(line) for line in text.splitlines()]
        assert all(isinstance(line, dict) for line in lines)
        return lines

    def close(self) -> None:
        """Kill the daemon if it still runs (once)."""
        if self._open:
            self._open = False
            self._context.__exit__(None, None, None)


@pytest.fixture
def daemon(tmp_path):
    started: list[Daemon] = []

    def start(*extra: str) -> Daemon:
        started.append(Daemon(tmp_path, *extra))
        return started[-1]

    yield start
    for d in started:
        d.close()


def test_a_flood_of_malformed_requests_logs_a_few_json_lines_per_kind_and_counts_the_rest(daemon):
    """Each request aiohttp could not parse was a 10-line traceback on stderr (not JSON, not limited: 89,606
    lines in 5 s).  Now each kind is an event of its own, at most ``DEFAULT_LOG_LINES_PER_S`` lines of it per
    window, and the lines left out are counted in ``log_lines_suppressed``: the lines and the counts add up
    to the requests sent."""
    d = daemon()
    windows: dict[str, int] = {}
    for event, (request, status) in bad_requests(d.address).items():
        start_s = time.monotonic()
        for _ in range(REPEATS):
            got, headers, _ = http(d.address, request)
            assert got == status, (event, got)
            assert headers["server"] == "fog-driver", event
        windows[event] = math.ceil((time.monotonic() - start_s) / LOG_WINDOW_S) + 1
    lines = d.stop()
    logged = Counter(line["event"] for line in lines)
    suppressed = Counter()
    for line in lines:
        if line["event"] == "log_lines_suppressed":
            suppressed[line["suppressed_event"]] += line["count"]
    for event, (_, status) in bad_requests(d.address).items():
        assert logged[event] + suppressed[event] == REPEATS, (event, logged[event], suppressed[event])
        assert 1 <= logged[event] <= DEFAULT_LOG_LINES_PER_S * windows[event], (event, logged[event])
        assert {line["status"] for line in lines if line["event"] == event} == {status}
    assert not logged["web_aiohttp_message"]


def test_every_answer_names_the_server_without_versions(daemon):
    """``Server: Python/3.11 aiohttp/3.14.5`` went out on every answer, errors included."""
    d = daemon()
    answers = {
        "200": get(d.address, "/api/view"),
        "404": get(d.address, "/nothing"),
        "405": http(
            d.address, f"DELETE / HTTP/1.1\r\nHost: {host_of(d.address)}\r\nConnection: close\r\n\r\n".encode()
        ),
        "400": get(d.address, "/", host=None),
        "421": get(d.address, "/", host="evil.example"),
    }
    for expected, (status, headers, _) in answers.items():
        assert str(status) == expected
        assert headers["server"] == "fog-driver", (expected, headers["server"])
    d.stop()


def test_an_absolute_form_target_is_refused_whatever_authority_it_names(daemon):
    """``GET http://evil.example/api/view`` with the listener's own Host was served 200: the authority in the
    target was never checked.  Any absolute-form target is refused, this listener's own address too."""
    d = daemon()
    host = host_of(d.address)
    for target in ("http://evil.example/api/view", f"http://{host}/api/view", "https://evil.example/"):
        status, headers, body = http(
            d.address, f"GET {target} HTTP/1.1\r\nHost: {host}\r\nConnection: close\r\n\r\n".encode()
        )
        assert status == 400, (target, status)
        assert b"must be a path" in body and headers["server"] == "fog-driver"
    assert get(d.address, "/api/view")[0] == 200  # the origin form is served
    lines = d.stop()
    refused = [line for line in lines if line["event"] == "web_absolute_target_refused"]
    assert [line["target"] for line in refused] == [
        "http://evil.example/api/view",
        f"http://{host}/api/view",
        "https://evil.example/",
    ]


def test_an_oversized_header_gets_431_as_documented_and_a_long_request_line_414(daemon):
    """A header over 4 KiB or a 41st header got 400 where the docs said 431; the request line over 4 KiB is
    told apart (414), also when a header of the same request is long too."""
    d = daemon()
    long_value = "a" * (WEB_MAX_LINE_BYTES + 1)
    assert get(d.address, "/", f"X-Junk: {long_value}")[0] == 431
    assert get(d.address, "/", f"X-{long_value}: 1")[0] == 431  # a long header name
    assert get(d.address, "/", *(f"X-H{i}: 1" for i in range(WEB_MAX_HEADERS)))[0] == 431
    assert get(d.address, "/", *(f"X-H{i}: 1" for i in range(WEB_MAX_HEADERS - 2)))[0] == 200  # 39 + Host
    assert get(d.address, "/" + long_value)[0] == 414
    assert get(d.address, "/" + long_value, f"X-Junk: {long_value}")[0] == 414
    assert get(d.address, "/?" + "a" * (WEB_MAX_LINE_BYTES - 100), f"X-Junk: {long_value}")[0] == 431
    d.stop()


def test_what_aiohttp_itself_logs_and_a_failing_route_are_one_json_line_each(capfd, monkeypatch):
    """aiohttp's loggers had no handler: Python's last resort printed each record and its traceback on stderr.
    A route that raised was one of them ("Error handling request", then the traceback)."""
    import logging

    import structlog

    from fog_driver.daemon.web.server import WebView

    events: list[dict] = []

    def keep(_logger, _name, event_dict):
        events.append(dict(event_dict))
        raise structlog.DropEvent

    structlog.configure(processors=[keep])  # conftest resets structlog after the test
    view = WebView("127.0.0.1", 0)

    async def broken(request):
        raise RuntimeError("a bug in a route")

    monkeypatch.setattr(view.routes, "api_view", broken)
    view.start()
    try:
        status, headers, body = get(view.address, "/api/view")
        try:
            raise ValueError("inside aiohttp")
        except ValueError:
            logging.getLogger("aiohttp.server").exception("Unhandled exception")
        logging.getLogger("aiohttp.access").warning("an access line")
    finally:
        view.stop()
    # Nothing on to Python's own handlers: its last resort printed the record and its traceback on stderr.  (Not
    # told by caplog: pytest attaches its capture to loggers that do not propagate, as "aiohttp" now does.)
    printed = capfd.readouterr()
    assert "Unhandled exception" not in printed.err and "Traceback" not in printed.err and printed.out == ""
    assert logging.getLogger("aiohttp").propagate is False
    assert status == 500 and headers["server"] == "fog-driver" and b"internal error" in body
    failed = [e for e in events if e["event"] == "web_request_failed"]
    assert [(e["path"], e["error"]) for e in failed] == [("/api/view", "RuntimeError('a bug in a route')")]
    said = [e for e in events if e["event"] == "web_aiohttp_message"]
    assert [(e["logger"], e["message"], e["error"]) for e in said] == [
        ("aiohttp.server", "Unhandled exception", "ValueError('inside aiohttp')"),
        ("aiohttp.access", "an access line", None),
    ]
