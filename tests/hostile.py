"""Hostile clients of the daemon, for the soak test and ``benchmarks/bench_daemon.py --hostile``.

Each ``Hostile`` is a thread that misbehaves in one way (``KINDS``), from its own loopback address
(127.0.0.10 + i: the daemon's per-address limits then fall on it, not on the well-behaved clients),
paced at 50 rounds a second, and reconnects whenever it is thrown out.  Given the daemon's token, the client
that never reads authorizes first (a station whose reader hung: on a token-protected daemon the stream, and so
the backlog it leaves behind, is for authorized clients only); the others never have it.

    python tests/hostile.py HOST PORT N [TOKEN]   # N of them (the kinds in turn) until stdin closes; prints
                                                  # "ready", then at the end one JSON line: connections and
                                                  # refusals per kind
"""

from __future__ import annotations

import json
import random
import socket
import sys
import threading

KINDS = ("empty", "junk", "oversized", "badjson", "auth", "overflow", "nonreader", "idle")


class Hostile(threading.Thread):
    """One misbehaving client, reconnecting whenever it is thrown out, until ``stop``."""

    def __init__(
        self, kind: str, address: tuple[str, int], source: str, stop: threading.Event, token: str | None = None
    ) -> None:
        """``token``: the daemon's, sent by the ``nonreader`` alone before its ``?WATCH``."""
        super().__init__(name=f"hostile-{kind}", daemon=True)
        self.kind, self.address, self.source, self.stop = kind, address, source, stop
        self.token = token
        self.connections = self.refused = 0
        self.rng = random.Random(kind)

    def connect(self) -> socket.socket | None:
        try:
            sock = socket.create_connection(self.address, timeout=2.0, source_address=(self.source, 0))
        except OSError:
            self.refused += 1
            return None
        self.connections += 1
        return sock

    def payload(self) -> bytes:
        r = self.rng
        return {
            "empty": b"\n" * 2000,
            "junk": bytes(r.randrange(256) for _ in range(300)) + b"\n",
            "oversized": b"?WATCH=" + b"x" * 6000 + b"\n",
            "badjson": b'?WATCH={"enable":tru\n?ZERO={[[[[\n?NOPE;\n',
            "auth": b'?AUTH={"token":"guess-%d"};\n' % r.randrange(10**9),
            "overflow": b'?WATCH={"rate_hz":1e308};\n?WATCH={"rate_hz":' + b"9" * 4000 + b"};\n",
            "nonreader": b'?WATCH={"enable":true};\n',
            "idle": b"",
        }[self.kind]

    def run(self) -> None:
        while not self.stop.is_set():
            sock = self.connect()
            if sock is None:
                self.stop.wait(0.2)
                continue
            try:
                if self.kind == "nonreader":
                    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
                    if self.token is not None:
                        sock.sendall(b"?AUTH=" + json.dumps({"token": self.token}).encode() + b";\n")
                while not self.stop.is_set():
                    data = self.payload()
                    if data:
                        sock.sendall(data)
                    if self.kind not in ("nonreader", "idle"):
                        sock.recv(65536)  # read what comes (replies, errors): only the hostility counts
                    self.stop.wait(0.02)  # the attack's pace: 50 rounds a second per client
            except OSError:
                pass  # thrown out: come back
            finally:
                sock.close()


def start(address: tuple[str, int], n: int, stop: threading.Event, token: str | None = None) -> list[Hostile]:
    """``n`` hostile clients (the kinds in turn), started; ``token``: the daemon's, for the ``nonreader``."""
    clients = [Hostile(KINDS[i % len(KINDS)], address, f"127.0.0.{10 + i}", stop, token) for i in range(n)]
    for client in clients:
        client.start()
    return clients


def main() -> None:
    host, port, n = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
    token = sys.argv[4] if len(sys.argv) > 4 else None
    stop = threading.Event()
    clients = start((host, port), n, stop, token)
    print("ready", flush=True)
    sys.stdin.read()  # until the caller closes our stdin
    stop.set()
    for client in clients:
        client.join(10)
    print(json.dumps({c.kind: {"connections": c.connections, "refused": c.refused} for c in clients}), flush=True)


if __name__ == "__main__":
    main()
