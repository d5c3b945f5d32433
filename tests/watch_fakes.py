"""A fake daemon for ``fog-driver watch``'s tests: one connection that greets, reads the ``?WATCH`` request and
sends scripted chunks (listening before the client runs: the kernel's accept backlog is the readiness), its
lines (VERSION, DEVICE, STATUS, ANGLE), and a stream that says it is a terminal."""

from __future__ import annotations

import io
import json
import socket
import threading

from fog_driver.tools.watch import run_watch

GUARD_S = 30.0  # a hang guard only, never a synchronisation

VERSION = {
    "class": "VERSION",
    "release": "0.1.0",
    "proto_major": 1,
    "proto_minor": 0,
    "instrument": {"serial": "FOG-SYN-0001", "firmware": "1.2", "rate_hz": 100},
}
DEVICE = {
    "class": "DEVICE",
    "path": "/tmp/fog-driver-sim.tty",
    "state": "activated",
    "serial": "FOG-SYN-0001",
    "rate_hz": 100,
}
STATUS = {
    "class": "STATUS",
    "frames": 4242,
    "crc_errors": 3,
    "missing_frames": 7,
    "clients": 1,
    "cpu_percent": 2.5,
    "port_state": "open",
    "some_future_key": "x",
}


def angle(seq: int, **extra) -> dict:
    obj = {
        "class": "ANGLE",
        "seq": seq,
        "t_s": 12.34 + 0.1 * (seq - 1),
        "angle_arcsec": 3723.5 + seq,
        "angle_raw_arcsec": -59.995 - seq,
        "rate_dph": 15.041,
        "drift_dph": 0.1234,
        "temps_c": {"top": 20.25, "bottom": 19.88, "housing": 19.6},
        "flags": ["gap"] if seq == 2 else [],
    }
    obj.update(extra)
    return obj


def ndjson(*objs) -> bytes:
    return b"".join(o if isinstance(o, bytes) else json.dumps(o).encode() + b"\n" for o in objs)


class FakeDaemon:
    """One connection: greet, read the WATCH request, send ``chunks``, then ``then`` ('close' or 'wait')."""

    def __init__(self, chunks: list[bytes], *, then: str = "close") -> None:
        self.listener = socket.create_server(("127.0.0.1", 0))  # listening before the client runs
        self.port = self.listener.getsockname()[1]
        self.chunks, self.then = chunks, then
        self.request = b""
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        try:
            self.listener.settimeout(GUARD_S)
            conn, _ = self.listener.accept()
            with conn:
                conn.settimeout(GUARD_S)
                conn.sendall(ndjson(VERSION, DEVICE))
                while not self.request.endswith(b"\n"):  # the whole request, so close() sends FIN, not RST
                    data = conn.recv(4096)
                    if not data:
                        return
                    self.request += data
                conn.sendall(
                    ndjson({"class": "WATCH", "enable": True, "rate_hz": json.loads(self.request[7:-2])["rate_hz"]})
                )
                for chunk in self.chunks:
                    conn.sendall(chunk)
                if self.then == "wait":  # until the client hangs up
                    try:
                        while conn.recv(4096):
                            pass
                    except ConnectionResetError:
                        # A client that closes with our later lines still unread in its buffer
                        # resets the connection (RST, not FIN): that is hanging up too.
                        pass
        except BaseException as exc:  # noqa: BLE001 - reported by join()
            self.error = exc
        finally:
            self.listener.close()

    def join(self) -> None:
        self.thread.join(GUARD_S)
        assert not self.thread.is_alive()
        if self.error is not None:
            raise self.error


def watch(daemon: FakeDaemon, **kwargs) -> tuple[int, str]:
    out = io.StringIO()
    status = run_watch("127.0.0.1", daemon.port, out=out, **kwargs)
    daemon.join()
    return status, out.getvalue()


class FakeTty(io.StringIO):
    def isatty(self) -> bool:
        return True
