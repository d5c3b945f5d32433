"""Who may ask the web listener what: the token for reading too, the open stream, ``Host`` and ``Origin``, the
connection slots, the wrong-token backoff, a trusted proxy, the sessions and every answer's headers.

The listener in-process on a free loopback port (the ``web`` fixture), raw sockets and the helpers of
test_daemon_web.py.  Each test names what it holds; each failed on the code before its fix.  Nothing waits on a
clock: the backoff is made long (300 s) where a test needs an address to stay blocked, and a wait for a closed
socket is bounded by the socket's timeout.
"""

from __future__ import annotations

import socket

import pytest
from web_helpers import TIMEOUT_S, WsClient, get, host_of, http, login, post, stream

from fog_driver.daemon.limits import AUTH_FAILURES_BEFORE_BACKOFF, WEB_MAX_WS_MESSAGES_PER_S
from fog_driver.daemon.limits import WEB_MAX_CONNECTIONS_PER_PEER as MAX_PER_PEER
from fog_driver.daemon.web.access import AddressSet, Sessions, forwarded_client, host_name, origin_problem
from fog_driver.daemon.web.answers import SECURITY_HEADERS

TOKEN = "s3cret-token"
BEARER = f"Authorization: Bearer {TOKEN}"


@pytest.fixture
def long_backoff(monkeypatch):
    """An address in its backoff stays there for the test (300 s, not 1 s: no race with the clock)."""
    monkeypatch.setattr("fog_driver.daemon.web.auth.DEFAULT_AUTH_BACKOFF_BASE_S", 300.0)


class KeptAlive:
    """A kept-alive HTTP connection: requests one after another, each response read whole."""

    def __init__(self, address, source: str | None = None) -> None:
        self.address = address
        self.sock = socket.create_connection(address, timeout=TIMEOUT_S, source_address=(source, 0) if source else None)
        self.buffer = b""

    def get(self, path: str, *extra: str) -> int | None:
        """The response's status, or None when the listener closed the connection."""
        head = "".join(f"{h}\r\n" for h in extra)
        try:
            self.sock.sendall(f"GET {path} HTTP/1.1\r\nHost: {host_of(self.address)}\r\n{head}\r\n".encode())
            while b"\r\n\r\n" not in self.buffer:
                chunk = self.sock.recv(65536)
                if not chunk:
                    return None
                self.buffer += chunk
        except (ConnectionResetError, BrokenPipeError):
            return None
        head_bytes, _, self.buffer = self.buffer.partition(b"\r\n\r\n")
        lines = head_bytes.decode("latin-1").split("\r\n")
        length = next(int(v) for k, _, v in (line.partition(":") for line in lines) if k.lower() == "content-length")
        while len(self.buffer) < length:
            self.buffer += self.sock.recv(65536)
        self.buffer = self.buffer[length:]
        return int(lines[0].split()[1])

    def closed(self) -> bool:
        """Wait (at most the socket's timeout) for the listener to close the connection."""
        try:
            return self.sock.recv(1) == b""
        except ConnectionResetError:
            return True

    def close(self) -> None:
        self.sock.close()


# ---------------------------------------------------------------------------------------------- M1: one policy


def test_with_a_token_reading_needs_it_on_loopback_too(web):
    """On loopback the web view asked for nothing, token or not: the page, /api/view, /metrics and the WebSocket
    were anybody's."""
    view = web(token=TOKEN)
    for path in ("/", "/api/view", "/metrics", "/static/view.js", "/static/plotly.min.js"):
        assert get(view.address, path)[0] == 401, path
        assert get(view.address, path, BEARER)[0] == 200, path
    assert WsClient(view.address).status == 401
    ws = WsClient(view.address, headers=[BEARER])
    assert ws.status == 101 and ws.message()["type"] == "snapshot"
    ws.close()
    status, headers, _ = get(view.address, "/", "Accept: text/html")
    assert status == 302 and headers["location"] == "/login"
    # the login form and what it loads stay open: its CSS loaded only with the token
    assert get(view.address, "/login")[0] == 200
    status, headers, body = get(view.address, "/static/view.css")
    assert status == 200 and headers["content-type"].startswith("text/css") and b"{" in body
    # without a token, loopback stays open as it was
    open_view = web()
    assert [get(open_view.address, p)[0] for p in ("/", "/api/view", "/metrics")] == [200, 200, 200]


def test_the_open_stream_opens_the_angles_alone(web):
    view = web(token=TOKEN, open_stream=True, update_hz=20.0)
    view.publish({"class": "DEVICE", "state": "activated", "serial": "S9", "format": "fog-v1"})
    view.publish({"class": "STATUS", "port_state": "open"})
    view.publish_angles(stream(300))
    reader = WsClient(view.address)
    assert reader.status == 101
    first = reader.message()
    assert set(first) == {"type", "angle"} and first["angle"]["seq"] == 299
    view.publish_angles(stream(600)[300:])
    update = reader.message()
    while update["angle"].get("seq") == 299:
        update = reader.message()
    assert set(update) == {"type", "angle"} and update["type"] == "update" and update["angle"]["seq"] == 599
    reader.close()
    for path in ("/", "/api/view", "/metrics"):  # nothing else opens with it
        assert get(view.address, path)[0] == 401, path
    page = WsClient(view.address, headers=[BEARER])  # with the token, the whole page
    snapshot = page.message()
    assert snapshot["text"]["instrument"] == "S9 fog-v1" and snapshot["status"]["port_state"] == "open"
    page.close()


# ---------------------------------------------------------------------------------------------- M2: Host


def test_a_foreign_or_missing_host_is_refused(web):
    """Any Host was served: a page of another domain whose DNS points to 127.0.0.1 read everything."""
    view = web(http_hosts=("fog-bench1.lab",))
    port = view.address[1]
    assert get(view.address, "/api/view", host=f"evil.example:{port}")[0] == 421
    assert get(view.address, "/api/view", host=None)[0] == 400
    assert get(view.address, "/api/view", host="a:b:c")[0] == 400
    rebinding = (f"Origin: http://evil.example:{port}",)  # the page's own origin, as far as the browser knows
    assert get(view.address, "/api/view", *rebinding, host=f"evil.example:{port}")[0] == 421
    assert WsClient(view.address, origin=f"http://evil.example:{port}", host=f"evil.example:{port}").status == 421
    for host in (f"127.0.0.1:{port}", "127.0.0.1", f"localhost:{port}", "LOCALHOST.", "fog-bench1.lab:8948"):
        assert get(view.address, "/api/view", host=host)[0] == 200, host
    assert get(view.address, "/api/view", host="fog-bench1.lab.evil.example")[0] == 421


def test_an_ipv6_literal_host_is_read_in_brackets(web):
    view = web("::1")
    assert get(view.address, "/api/view")[0] == 200  # Host: [::1]:port
    assert get(view.address, "/api/view", host=f"[::2]:{view.address[1]}")[0] == 421


def test_host_and_origin_parsing():
    assert host_name("[::1]:8948") == "::1" and host_name("[0:0::1]") == "::1"
    assert host_name("Fog-Bench1.LAB.:80") == "fog-bench1.lab" and host_name("127.0.0.1:1") == "127.0.0.1"
    for bad in ("", "::1", "[::1", "[::1]x", "[nope]", "a:b", "a:80:90", "a b", "user@host"):
        assert host_name(bad) is None, bad
    assert origin_problem("http://127.0.0.1:8948", "127.0.0.1:8948", https=False) is None
    assert origin_problem("https://station.lab", "station.lab:443", https=True) is None
    assert "serves http" in origin_problem("https://127.0.0.1:8948", "127.0.0.1:8948", https=False)
    assert "serves https" in origin_problem("http://station.lab", "station.lab", https=True)
    for bad in ("null", "http://127.0.0.1:8949", "http://evil.example:8948", "ftp://127.0.0.1:8948"):
        assert origin_problem(bad, "127.0.0.1:8948", https=False) is not None, bad


# ---------------------------------------------------------------------------------------------- Origin


def test_an_origin_of_another_scheme_is_refused(web):
    """Only the Origin's host and port were compared: an https page was taken for the plain-http listener's."""
    view = web(token=TOKEN)
    ours = f"http://{host_of(view.address)}"
    theirs = f"https://{host_of(view.address)}"
    assert WsClient(view.address, origin=theirs, headers=[BEARER]).status == 403
    assert post(view.address, "/login", f"token={TOKEN}".encode(), f"Origin: {theirs}")[0] == 403
    ws = WsClient(view.address, origin=ours, headers=[BEARER])
    assert ws.status == 101
    ws.close()
    assert post(view.address, "/login", f"token={TOKEN}".encode(), f"Origin: {ours}")[0] == 303
    assert get(view.address, "/api/view", BEARER, "Origin: null")[0] == 403
    behind_tls = web(token=TOKEN, secure_cookies=True)  # TLS in front: the page's origin is https
    assert get(behind_tls.address, "/api/view", BEARER, f"Origin: https://{host_of(behind_tls.address)}")[0] == 200
    assert get(behind_tls.address, "/api/view", BEARER, f"Origin: http://{host_of(behind_tls.address)}")[0] == 403


# ---------------------------------------------------------------------------------------------- M3: slots


def test_idle_unauthorized_connections_cannot_starve_a_client_with_the_token(web):
    """100 connections that got 401 and stay open filled the address's 24 places: the operator was refused."""
    view = web(token=TOKEN)
    idle = []
    for _ in range(100):
        c = KeptAlive(view.address)
        c.get("/metrics")  # 401 (or None: closed to make room for the next one)
        idle.append(c)
    status, _, body = get(view.address, "/metrics", BEARER)
    assert status == 200 and b"fog_driver_" in body
    assert view.slots.unauthorized("127.0.0.1") <= MAX_PER_PEER // 2  # they hold half the address's places at most
    assert view.refused_connections == 0
    for c in idle:
        c.close()


def test_an_unauthorized_connection_lives_a_few_seconds_after_its_first_request(web, monkeypatch):
    monkeypatch.setattr("fog_driver.daemon.web.server.WEB_UNAUTHORIZED_LIFETIME_S", 0.3)
    view = web(token=TOKEN)
    operator = KeptAlive(view.address)
    assert operator.get("/metrics", BEARER) == 200
    stranger = KeptAlive(view.address)  # its first request comes after the operator's
    assert stranger.get("/metrics") == 401
    assert stranger.closed()
    assert operator.get("/metrics", BEARER) == 200  # past the same lifetime, still served
    operator.close()
    stranger.close()


# ---------------------------------------------------------------------------------------------- M4: backoff


def test_a_guesser_in_its_backoff_gets_429_for_the_right_token_as_for_a_wrong_one(web, long_backoff):
    """The right token was accepted during the backoff (200, a login's 303) while a wrong one got 429: each
    guess had its verdict.  Now every token from a blocked address gets the same 429, unread."""
    view = web(token=TOKEN)
    wrong = [
        get(view.address, "/metrics", "Authorization: Bearer guess")[0] for _ in range(AUTH_FAILURES_BEFORE_BACKOFF + 1)
    ]
    assert wrong == [401] * (AUTH_FAILURES_BEFORE_BACKOFF + 1)  # the backoff has started: blocked for 300 s
    right, right_headers, _ = get(view.address, "/metrics", BEARER)
    guess, guess_headers, _ = get(view.address, "/metrics", "Authorization: Bearer guess")
    assert right == guess == 429 and int(right_headers["retry-after"]) == int(guess_headers["retry-after"]) > 1
    assert post(view.address, "/login", b"token=" + TOKEN.encode())[0] == 429
    assert post(view.address, "/login", b"token=guess")[0] == 429
    elsewhere = KeptAlive(view.address, source="127.0.0.2")  # another address is not blocked
    assert elsewhere.get("/metrics", BEARER) == 200
    elsewhere.close()


def test_after_the_backoff_the_right_token_works(web):
    view = web(token=TOKEN)
    for _ in range(AUTH_FAILURES_BEFORE_BACKOFF + 1):
        get(view.address, "/metrics", "Authorization: Bearer guess")
    view.auth.throttle._peers["127.0.0.1"].blocked_until = 0.0  # the block is over (no waiting on the clock)
    assert get(view.address, "/metrics", BEARER)[0] == 200


# ---------------------------------------------------------------------------------------------- proxies


def test_x_forwarded_for_is_believed_from_trusted_proxies_only(web, long_backoff):
    def guesses(view, client: str) -> list[int]:
        return [
            get(view.address, "/metrics", "Authorization: Bearer guess", f"X-Forwarded-For: 203.0.113.9, {client}")[0]
            for _ in range(AUTH_FAILURES_BEFORE_BACKOFF + 2)
        ]

    blocked = [401] * (AUTH_FAILURES_BEFORE_BACKOFF + 1) + [429]
    behind = web(token=TOKEN, trusted_proxies=("127.0.0.0/8",))
    assert guesses(behind, "10.0.0.7") == blocked
    assert guesses(behind, "10.0.0.8") == blocked  # another client behind the proxy has a backoff of its own
    assert get(behind.address, "/metrics", "X-Forwarded-For: not-an-address")[0] == 400
    # the per-address slots are the forwarded client's: 10.0.0.7's unauthorized connections make room among
    # themselves, never at 10.0.0.8's expense
    other = KeptAlive(behind.address)
    assert other.get("/metrics", "X-Forwarded-For: 10.0.0.8") == 401
    held = [KeptAlive(behind.address) for _ in range(MAX_PER_PEER)]
    for c in held:
        c.get("/metrics", "X-Forwarded-For: 10.0.0.7")
    assert behind.slots.unauthorized("10.0.0.7") == MAX_PER_PEER // 2 and behind.slots.unauthorized("10.0.0.8") == 1
    for c in (other, *held):
        c.close()
    direct = web(token=TOKEN)  # no trusted proxy: the header is ignored, the socket's address counts
    assert guesses(direct, "10.0.0.7")[-1] == 429
    assert get(direct.address, "/metrics", "Authorization: Bearer guess", "X-Forwarded-For: 10.0.0.9")[0] == 429


def test_forwarded_client_takes_the_rightmost_untrusted_hop():
    proxies = AddressSet(["10.0.0.1", "192.168.0.0/16"])
    assert forwarded_client(["198.51.100.7, 10.0.0.1"], proxies) == "198.51.100.7"
    assert forwarded_client(["6.6.6.6, 198.51.100.7", "192.168.3.4"], proxies) == "198.51.100.7"  # a forged hop
    assert forwarded_client(["2001:db8:1:2::5"], proxies) == "2001:db8:1:2::/64"
    assert forwarded_client([], proxies) == "" and forwarded_client(["10.0.0.1"], proxies) == ""
    assert forwarded_client(["junk, 198.51.100.7"], proxies) == "198.51.100.7"
    assert forwarded_client(["198.51.100.7, junk"], proxies) is None
    assert "::ffff:10.0.0.1" in proxies and "10.0.0.2" not in proxies and "nope" not in proxies


# ---------------------------------------------------------------------------------------------- sessions


def test_the_session_cookie_lasts_ends_on_logout_and_is_secure_when_told(web):
    """The cookie had no Max-Age, no logout, one value shared by every browser, and the token worked in a URL."""
    view = web(token=TOKEN)
    status, headers, _ = post(view.address, "/login", f"token={TOKEN}".encode())
    cookie_header = headers["set-cookie"]
    assert status == 303 and "Max-Age=43200" in cookie_header and "HttpOnly" in cookie_header
    assert "SameSite=Strict" in cookie_header and "Secure" not in cookie_header
    cookie = cookie_header.split(";")[0]
    other = login(view.address, TOKEN)
    assert other != cookie  # a session each
    assert get(view.address, "/api/view", f"Cookie: {cookie}")[0] == 200
    status, headers, _ = post(view.address, "/logout", b"", f"Cookie: {cookie}")
    assert status == 303 and headers["location"] == "/login"
    assert headers["set-cookie"].startswith('fog_driver_token=""') and "Max-Age=0" in headers["set-cookie"]
    assert get(view.address, "/api/view", f"Cookie: {cookie}")[0] == 401  # void here, whatever the browser keeps
    assert get(view.address, "/api/view", f"Cookie: {other}")[0] == 200  # the other browser's carries on
    # the token in a URL opens nothing (it stays in histories, logs and Referer headers)
    status, headers, _ = get(view.address, f"/?token={TOKEN}")
    assert status == 401 and "set-cookie" not in headers
    status, headers, _ = get(view.address, f"/?token={TOKEN}", "Accept: text/html")
    assert status == 302 and headers["location"] == "/login" and "set-cookie" not in headers
    behind_tls = web(token=TOKEN, secure_cookies=True)
    headers = post(
        behind_tls.address, "/login", f"token={TOKEN}".encode(), f"Origin: https://{host_of(behind_tls.address)}"
    )[1]
    assert "Secure" in headers["set-cookie"]


def test_sessions_expire_and_are_bounded():
    sessions = Sessions(max_age_s=10.0, max_sessions=2)
    first = sessions.start(0.0)
    assert sessions.valid(first, 9.9) and not sessions.valid(first, 10.0)
    a, b, c = sessions.start(0.0), sessions.start(0.0), sessions.start(0.0)
    assert not sessions.valid(a, 1.0) and sessions.valid(b, 1.0) and sessions.valid(c, 1.0) and len(sessions) == 2
    assert not sessions.valid(None, 0.0) and not sessions.valid("", 0.0) and not sessions.valid("\ud800", 0.0)


# ---------------------------------------------------------------------------------------------- the answers


def test_every_answer_carries_the_security_headers(web):
    """Redirects and errors (401, 404, 405, a malformed request) went out without CSP, nosniff or no-store."""
    view = web(token=TOKEN)
    answers = {
        "302": get(view.address, "/", "Accept: text/html"),
        "303": post(view.address, "/login", f"token={TOKEN}".encode()),
        "401": get(view.address, "/metrics"),
        "404": get(view.address, "/nothing", BEARER),
        "405": http(
            view.address, f"DELETE / HTTP/1.1\r\nHost: {host_of(view.address)}\r\nConnection: close\r\n\r\n".encode()
        ),
        "400": get(view.address, "/metrics", host=None),
        "421": get(view.address, "/metrics", host="evil.example"),
        "431": get(view.address, "/metrics", "X-Junk: " + "a" * 10000),
        "200": get(view.address, "/metrics", BEARER),
    }
    for expected, (status, headers, _) in answers.items():
        assert str(status) == expected, (expected, status)
        for name in ("Content-Security-Policy", "X-Content-Type-Options", "Cache-Control"):
            assert headers.get(name.lower()) == SECURITY_HEADERS[name], (expected, name)


def test_the_bearer_scheme_is_read_in_any_case(web):
    view = web(token=TOKEN)
    for header in (
        f"Authorization: bearer {TOKEN}",
        f"Authorization: BEARER {TOKEN}",
        f"Authorization: Bearer  {TOKEN} ",
    ):
        assert get(view.address, "/metrics", header)[0] == 200, header
    assert get(view.address, "/metrics", f"Authorization: Basic {TOKEN}")[0] == 401


# ---------------------------------------------------------------------------------------------- WebSocket pings


def test_a_ping_flood_is_closed_and_metrics_carry_on(web):
    """Pings were answered one by one and never counted: a flood kept the listener's loop busy."""
    view = web(token=TOKEN, update_hz=50.0)
    ws = WsClient(view.address, headers=[BEARER])
    ws.message()
    for _ in range(WEB_MAX_WS_MESSAGES_PER_S + 5):
        ws.send_frame(0x9, b"ping")
    with pytest.raises(ConnectionError, match="closed"):
        for _ in range(200):  # updates at 50 Hz meanwhile: a listener that never closes fails here
            ws.message()
    ws.close()
    assert get(view.address, "/metrics", BEARER)[0] == 200
    fine = WsClient(view.address, headers=[BEARER])  # a few pings are answered (a pong each)
    fine.message()
    fine.send_frame(0x9, b"are you there")
    while (frame := fine.frame()) != (0xA, b"are you there"):
        assert frame[0] in (0x1, 0xA), frame
    fine.close()
