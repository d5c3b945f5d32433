"""What the web listener's tests share: raw HTTP and WebSocket clients (as a browser speaks), the state a
scrape reads, the exposition's check, and a headless Chromium page."""

from __future__ import annotations

import base64
import json
import math
import os
import shutil
import socket
import subprocess

from prometheus_client.parser import text_string_to_metric_families

TIMEOUT_S = 20.0


#: STATUS's ``model_file`` in the collector's tests (a path with a space and a quote: labels are escaped).
MODEL_FILE = {
    "path": '/etc/fog-driver/"bench 1"/model.yaml',
    "sha256": "0123456789abcdef" * 4,
    "kind": "wesn",
    "created_utc": "2026-12-04T14:19:12.370Z",
    "serial": "FOG-SIM-0001",
}


#: What the collector reads at a scrape, with every metric present (test_metric_names.py scrapes it too).
SCRAPED_STATUS = {
    "uptime_s": 12.5,
    "port_state": "lost",
    "bytes_in": 123456,
    "frames": 4000,
    "crc_errors": 3,
    "bytes_discarded": 77,
    "missing_frames": 12,
    "published": 3990,
    "clients": 2,
    "dropped_clients": 1,
    "capture_state": "failed",
    "capture_bytes_lost": 999,
    "bias_dph": 0.25,
    "bias_sigma_dph": 0.0125,
    "adapting": True,
    "flagged": {"gap": 2, "extrapolating": 5},
    "model_file": MODEL_FILE,
    "chamber": {
        "url": "sim://",
        "state": "link_lost",
        "link_up": False,
        "air_c": 61.5,
        "setpoint_c": 60.0,
        "age_s": 7.5,
    },
}


SCRAPED_STATE = {
    "status": SCRAPED_STATUS,
    "device": {"format": "kvh-a", "serial": "S1", "firmware": "2"},
    "version": {"release": "9.9"},
    "reconnects": 4,
    "capture_failures": 6,
    "model_age_s": 86400.0,
    "angle": {
        "drift_dph": -1.5,
        "drift_sigma_dph": 0.0375,
        "temps_c": {"top": 30.5, "bottom": 31.0},
        "flags": ["extrapolating"],
    },
    "angle_age_s": 0.25,
    "rate_1s_dph": 14.9,
    "web_clients": 3,
    "web_dropped": 2,
}


def http(address, request: bytes, *, read_all: bool = True) -> tuple[int, dict, bytes]:
    with socket.create_connection(address, timeout=TIMEOUT_S) as s:
        s.sendall(request)
        data = b""
        while True:
            chunk = s.recv(1 << 20)
            if not chunk:
                break
            data += chunk
            if not read_all and b"\r\n\r\n" in data:
                break
    head, _, body = data.partition(b"\r\n\r\n")
    lines = head.decode("latin-1").split("\r\n")
    headers = {}
    for line in lines[1:]:
        key, _, value = line.partition(":")
        headers.setdefault(key.strip().lower(), value.strip())
    return int(lines[0].split()[1]), headers, body


def host_of(address) -> str:
    """The ``Host`` header a browser sends to ``address`` (an IPv6 literal in brackets)."""
    return f"[{address[0]}]:{address[1]}" if ":" in address[0] else f"{address[0]}:{address[1]}"


def get(address, path: str, *extra: str, host: str | None = "") -> tuple[int, dict, bytes]:
    """GET ``path`` with ``address``'s own Host (``host``: another one; None: no Host at all)."""
    host_line = f"Host: {host or host_of(address)}\r\n" if host is not None else ""
    head = "".join(f"{h}\r\n" for h in extra)
    return http(address, f"GET {path} HTTP/1.1\r\n{host_line}Connection: close\r\n{head}\r\n".encode())


def post(address, path: str, body: bytes = b"", *extra: str) -> tuple[int, dict, bytes]:
    """POST a form ``body`` to ``path`` (its own Host)."""
    head = "".join(f"{h}\r\n" for h in extra)
    return http(
        address,
        f"POST {path} HTTP/1.1\r\nHost: {host_of(address)}\r\nConnection: close\r\n"
        f"Content-Type: application/x-www-form-urlencoded\r\nContent-Length: {len(body)}\r\n{head}\r\n".encode()
        + body,
    )


def login(address, token: str) -> str:
    """Log in with the form: the session cookie (``name=value``)."""
    status, headers, _ = post(address, "/login", b"token=" + token.encode())
    assert status == 303 and headers["location"] == "/", status
    return headers["set-cookie"].split(";")[0]


class WsClient:
    """A minimal WebSocket client on a raw socket (the page's protocol as a browser speaks it)."""

    def __init__(
        self, address, *, origin: str | None = None, rcvbuf: int | None = None, headers=(), host: str | None = None
    ) -> None:
        self.sock = socket.socket()
        if rcvbuf:
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
        self.sock.settimeout(TIMEOUT_S)
        self.sock.connect(address)
        key = base64.b64encode(os.urandom(16)).decode()
        extra = "".join(f"{h}\r\n" for h in headers) + (f"Origin: {origin}\r\n" if origin else "")
        self.sock.sendall(
            f"GET /ws HTTP/1.1\r\nHost: {host or host_of(address)}\r\nUpgrade: websocket\r\n"
            f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n"
            f"{extra}\r\n".encode()
        )
        self.buffer = b""
        while b"\r\n\r\n" not in self.buffer:
            chunk = self.sock.recv(65536)
            if not chunk:
                break
            self.buffer += chunk
        head, _, self.buffer = self.buffer.partition(b"\r\n\r\n")
        self.status = int(head.split()[1])

    def _read(self, n: int) -> bytes:
        while len(self.buffer) < n:
            chunk = self.sock.recv(1 << 20)
            if not chunk:
                raise ConnectionError("closed")
            self.buffer += chunk
        out, self.buffer = self.buffer[:n], self.buffer[n:]
        return out

    def frame(self) -> tuple[int, bytes]:
        b0, b1 = self._read(2)
        n = b1 & 0x7F
        if n == 126:
            n = int.from_bytes(self._read(2), "big")
        elif n == 127:
            n = int.from_bytes(self._read(8), "big")
        return b0 & 0x0F, self._read(n)

    def message(self) -> dict:
        while True:
            opcode, payload = self.frame()
            if opcode == 1:
                return json.loads(payload)
            if opcode == 8:
                raise ConnectionError(f"closed by the server: {payload!r}")

    def send_text(self, text: str) -> None:
        self.send_frame(0x1, text.encode())

    def send_frame(self, opcode: int, payload: bytes) -> None:
        """One masked frame (a client's), FIN set: ``opcode`` 0x1 text, 0x9 ping, 0xA pong."""
        mask = os.urandom(4)
        masked = bytes(b ^ mask[i % 4] for i, b in enumerate(payload))
        self.sock.sendall(bytes([0x80 | opcode, 0x80 | len(payload)]) + mask + masked)

    def close(self) -> None:
        self.sock.close()


def check_exposition(text: str) -> list:
    """``promtool check metrics`` on ``text`` when it is installed (it must pass, lint included), and the
    prometheus-client parser always; the families parsed."""
    promtool = shutil.which("promtool")
    if promtool is not None:
        done = subprocess.run([promtool, "check", "metrics"], input=text, capture_output=True, text=True, timeout=60)
        assert done.returncode == 0, done.stdout + done.stderr
    return list(text_string_to_metric_families(text))


WAIT_MS = 20_000


def chromium() -> str:
    path = os.environ.get("FOG_CHROMIUM") or shutil.which("chromium") or shutil.which("chromium-browser")
    assert path, "the browser test needs Chromium: apt-get install chromium (or FOG_CHROMIUM=/path/to/chrome)"
    return path


def open_page(playwright, problems: list[str]):
    """Headless Chromium and a page whose console errors and warnings, and uncaught errors, go to ``problems``."""
    browser = playwright.chromium.launch(executable_path=chromium(), args=["--no-sandbox"])
    page = browser.new_page(viewport={"width": 1280, "height": 860})
    page.on("console", lambda m: problems.append(m.text) if m.type in ("error", "warning") else None)
    page.on("pageerror", lambda e: problems.append(str(e)))
    return browser, page


def angle(seq: int, t_s: float, *, rate: float | None = None, **extra) -> dict:
    rate = 10.0 + math.sin(seq / 37.0) * 3 if rate is None else rate
    return {
        "class": "ANGLE",
        "seq": seq,
        "t_s": t_s,
        "angle_arcsec": seq * 0.1 - 50.0,
        "angle_raw_arcsec": seq * 0.11,
        "rate_dph": rate,
        "rate_raw_dph": rate + 1.5,
        "drift_dph": -0.5 + seq * 1e-4,
        "temps_c": {"top": 20 + seq * 1e-3, "bottom": 21.0, "housing": 22.0},
        "flags": [],
        "utc": f"2026-12-03T00:00:{seq % 60:02d}.000Z",
        **extra,
    }


def stream(n: int, rate_hz: float = 100.0, t0: float = 3.0) -> list[dict]:
    return [angle(i, t0 + i / rate_hz) for i in range(n)]
