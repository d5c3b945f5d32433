"""A small line server for the ASCII chamber drivers' tests: a thread on 127.0.0.1 (port 0) that splits what
it receives at the request's line end and answers each line with what ``handler`` returns.

The protocols themselves are written in each test file from the manuals (never from the codecs), so a test
of a driver against its server can fail.  ``handler(line) -> reply``: ``None`` (no answer), ``bytes``, a list
of ``bytes`` (sent as separate writes: a reply split across reads), or ``Drop(prefix)`` (send ``prefix``,
then close the connection: a link lost mid-reply).  ``inject(reply)``: the next line is answered ``reply``
instead (a fault).  Ready as soon as it is built (the socket listens before the thread starts); every line
received is kept in ``lines``.
"""

from __future__ import annotations

import contextlib
import socket
import threading
from collections.abc import Callable
from dataclasses import dataclass

import pytest

from fog_driver.lab.controllers.base import ControllerUnreachable


@dataclass(frozen=True)
class Drop:
    prefix: bytes


Reply = bytes | list[bytes] | Drop | None


class LineServer:
    def __init__(self, handler: Callable[[bytes], Reply], request_end: bytes) -> None:
        self.handler = handler
        self.request_end = request_end
        self.lines: list[bytes] = []
        self._injected: list[Reply] = []
        self.sock = socket.create_server(("127.0.0.1", 0))
        self.port = self.sock.getsockname()[1]
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        while True:
            try:
                conn, _ = self.sock.accept()
            except OSError:
                return
            with conn:
                conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                self._talk(conn)

    def _talk(self, conn: socket.socket) -> None:
        pending = b""
        while True:
            try:
                chunk = conn.recv(4096)
            except OSError:
                return
            if not chunk:
                return
            pending += chunk
            while self.request_end in pending:
                line, _, pending = pending.partition(self.request_end)
                self.lines.append(line)
                reply = self._injected.pop(0) if self._injected else self.handler(line)
                if isinstance(reply, Drop):
                    conn.sendall(reply.prefix)
                    return
                for part in [reply] if isinstance(reply, bytes) else reply or []:
                    conn.sendall(part)

    def inject(self, reply: Reply) -> None:
        self._injected.append(reply)

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.sock.shutdown(socket.SHUT_RDWR)  # wakes the accept()
        self.sock.close()
        self._thread.join(timeout=2)


def every_split(reply: bytes) -> list[list[bytes]]:
    """``reply`` cut in two at each point inside it (a reply arriving in two reads)."""
    return [[reply[:at], reply[at:]] for at in range(1, len(reply))]


def assert_every_split_reads_the_same(
    server: LineServer, read: Callable[[], float], reply: bytes, value: float
) -> None:
    """``reply`` arriving in two reads, cut at each point, reads as ``value``."""
    for parts in every_split(reply):
        server.inject(parts)
        assert read() == value


def assert_a_drop_mid_reply_is_unreachable(server: LineServer, controller, read: Callable[[], float], prefix: bytes):
    """The connection closed after ``prefix`` of a reply: ``ControllerUnreachable``; a new connection reads."""
    server.inject(Drop(prefix))
    with pytest.raises(ControllerUnreachable):
        read()
    controller.connect()  # what the runner does after a lost link
    read()
