"""A network serial connection cut without being closed (a cable pulled between the host and the device server,
a server losing power, a NAT dropping the flow) is silence on an open socket.  The daemon and ``record`` take
``port_silence_s`` of it, after bytes, as the port's loss, and reconnect; TCP keepalive is on for the rest.

The device server here is a loopback TCP server (raw, or RFC 2217 through pyserial's ``PortManager``) that
sends one part of a capture per connection, once the reader's port is open (pyserial's open of a network port
discards what came before it), and then stops writing and holds the connection open: a half-open peer.  Every
wait is on a readiness signal (a port state, a DEVICE line, a log line, the server's accept); ``GUARD_S``
only turns a hang into a failure.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
from pathlib import Path

import pytest
import serial
import serial.rfc2217
import yaml
from readerthread import Reader

from fog_driver.protocol import FrameDecoder, SampleFrame
from fog_driver.samples.record import record
from fog_driver.transport import PortReader
from fog_driver.transport.port import (
    KEEPALIVE_IDLE_S,
    KEEPALIVE_INTERVAL_S,
    KEEPALIVE_PROBES,
    network_socket,
    silence_text,
)

#: pyserial's RFC 2217 client names its reader thread the old way
pytestmark = pytest.mark.filterwarnings(r"ignore:set(Daemon|Name)\(\) is deprecated:DeprecationWarning")

DATA = Path(__file__).resolve().parents[1] / "data"
GUARD_S = 30.0
#: The silence taken as a loss in these tests (the default is 5 s): short, so a test takes about a second.
SILENCE_S = 0.5
#: Frames of the capture the device "sent" while nobody was connected: left out between the two parts.
FRAMES_LOST = 37


def two_parts() -> tuple[bytes, bytes, int]:
    """The capture's first 400 frames, the frames from ``FRAMES_LOST`` frames later on, and the SAMPLE frames
    lost between them (from the frames' sequence numbers: the independent reference for the gap)."""
    data = (DATA / "sim-short.bin").read_bytes()
    decoder = FrameDecoder()
    frames = decoder.feed(data) + decoder.close()
    cut, resume = frames[400].offset, frames[400 + FRAMES_LOST].offset
    first, second = data[:cut], data[resume : frames[800].offset]
    last_seq = [f.seq for f in frames[:400] if isinstance(f, SampleFrame)][-1]
    next_seq = next(f.seq for f in frames[400 + FRAMES_LOST :] if isinstance(f, SampleFrame))
    return first, second, next_seq - last_seq - 1


class _Telnet:
    """What pyserial's ``PortManager`` writes its answers to: the accepted connection."""

    def __init__(self, connection: socket.socket) -> None:
        self.connection = connection

    def write(self, data: bytes) -> None:
        self.connection.sendall(data)


class HalfOpenServer:
    """A device server on loopback: connection i gets ``parts[i]`` once ``port_opened`` has been called for it,
    then nothing more, its socket held open until the reader closes it (the server never closes first).

    ``rfc2217``: the server speaks RFC 2217 (pyserial's ``PortManager`` answers the client's negotiation; the
    part goes out escaped).  ``accepted`` counts the connections."""

    def __init__(self, parts: list[bytes], *, rfc2217: bool = False) -> None:
        self.parts = parts
        self.rfc2217 = rfc2217
        self.listener = socket.create_server(("127.0.0.1", 0))
        scheme = "rfc2217" if rfc2217 else "socket"
        self.url = f"{scheme}://127.0.0.1:{self.listener.getsockname()[1]}"
        self.opened = threading.Semaphore(0)  # one release per open port
        self.accepted = 0
        self.accept_seen = threading.Condition()
        self.closing = threading.Event()
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def port_opened(self) -> None:
        """The reader's port is open (its "open" state, or DEVICE activated): the part may go."""
        self.opened.release()

    def wait_accepted(self, n: int) -> None:
        with self.accept_seen:
            assert self.accept_seen.wait_for(lambda: self.accepted >= n, GUARD_S), f"no connection {n}"

    def _serve(self) -> None:
        self.listener.settimeout(GUARD_S)
        for part in self.parts:
            try:
                connection, _ = self.listener.accept()
            except OSError:  # closed by close(), or the guard
                return
            with self.accept_seen:
                self.accepted += 1
                self.accept_seen.notify_all()
            self._hold(connection, part)
            if self.closing.is_set():
                return

    def _hold(self, connection: socket.socket, part: bytes) -> None:
        """Send ``part`` once the port is open, then read (answering RFC 2217 negotiation) until the peer
        closes: the half-open peer that stopped writing."""
        line = serial.serial_for_url("loop://")  # the serial side of an RFC 2217 server (unused: no data)
        manager = serial.rfc2217.PortManager(line, _Telnet(connection)) if self.rfc2217 else None
        peer_closed = threading.Event()

        def read_until_closed() -> None:
            connection.settimeout(GUARD_S)
            try:
                while data := connection.recv(4096):
                    if manager is not None:
                        for _ in manager.filter(data):  # the client's data bytes: none are expected
                            pass
            except OSError:
                pass
            peer_closed.set()

        reader = threading.Thread(target=read_until_closed, daemon=True)
        reader.start()
        with connection:
            if self.opened.acquire(timeout=GUARD_S) and not peer_closed.is_set():
                connection.sendall(b"".join(manager.escape(part)) if manager is not None else part)
            peer_closed.wait(GUARD_S)  # silent from here on; the reader closes, not us
            reader.join(GUARD_S)
        line.close()

    def close(self) -> None:
        self.closing.set()
        self.listener.close()
        for _ in self.parts:
            self.opened.release()  # a server waiting for an open that will not come
        self.thread.join(GUARD_S)


# -- the transport ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("rfc2217", [False, True], ids=["socket", "rfc2217"])
def test_a_network_port_has_tcp_keepalive_on_when_it_opens(rfc2217):
    """A half-open connection that never delivered a byte is keepalive's to end: it is on, with short timing."""
    server = HalfOpenServer([b""], rfc2217=rfc2217)
    stop = threading.Event()
    seen: dict[str, int] = {}

    def on_open(port) -> bytes:
        sock = network_socket(port)
        assert sock is not None
        seen["keepalive"] = sock.getsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE)
        if hasattr(socket, "TCP_KEEPIDLE"):  # Linux; elsewhere the options the platform has
            seen["idle_s"] = sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPIDLE)
            seen["interval_s"] = sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPINTVL)
            seen["probes"] = sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPCNT)
        stop.set()
        return b""

    try:
        for _ in PortReader(server.url, on_open=on_open, reconnect=False).chunks(stop):
            pass
    finally:
        server.close()
    assert seen.pop("keepalive") != 0
    expected = {"idle_s": KEEPALIVE_IDLE_S, "interval_s": KEEPALIVE_INTERVAL_S, "probes": KEEPALIVE_PROBES}
    assert seen == (expected if hasattr(socket, "TCP_KEEPIDLE") else {})


class SteppingClock:
    """``port.py``'s clock in a test: each reading is 1 s after the one before (so any read that finds nothing
    comes after more than ``SILENCE_S`` of silence), and a test can wait until it has been read ``n`` times."""

    def __init__(self) -> None:
        self.now_s = 0.0
        self.reads = 0
        self.changed = threading.Condition()

    def monotonic(self) -> float:
        with self.changed:
            self.now_s += 1.0
            self.reads += 1
            self.changed.notify_all()
            return self.now_s

    def wait_reads(self, n: int) -> None:
        with self.changed:
            assert self.changed.wait_for(lambda: self.reads >= n, GUARD_S)


@pytest.mark.parametrize("kind", ["tty", "socket"])
def test_a_silent_usb_adapter_stays_open_and_a_silent_network_port_is_lost(monkeypatch, kind):
    """The choice for a local tty: its silence is the instrument's (switched off behind a USB adapter), which a
    reopen cannot end, so it is no loss.  The same silence on a network port is."""

    import fog_driver.transport.port as port_module
    from fog_driver.transport import PtyPair

    first, second = b"\xaa" * 64, b"\x55" * 64
    clock = SteppingClock()
    monkeypatch.setattr(port_module, "time", clock)
    pty = server = None
    if kind == "tty":
        pty = PtyPair()
        url = pty.slave_path
    else:
        server = HalfOpenServer([first])
        url = server.url
    reader = Reader(url, silence_s=SILENCE_S)
    try:
        assert reader.opened.wait(GUARD_S)
        if pty is not None:
            pty.write(first)
        else:
            server.port_opened()
        states, got = [], b""
        while len(got) < len(first):
            what, item = reader.next_item()
            if what == "data":
                got += item
            else:
                states.append(item)
        clock.wait_reads(clock.reads + 2)  # a read that found nothing, and its silence check, are done
        if pty is not None:
            pty.write(second)
            while len(got) < len(first) + len(second):
                what, item = reader.next_item()
                if what == "data":
                    got += item
                else:
                    states.append(item)
            assert got == first + second and [e.state for e in states] == ["opening", "open"]  # no loss
        else:
            events, _ = reader.until_state("lost")
            assert got == first and events[-1].detail == silence_text(SILENCE_S)
    finally:
        reader.join()
        if pty is not None:
            pty.close()
        if server is not None:
            server.close()


# -- record ----------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("rfc2217", [False, True], ids=["socket", "rfc2217"])
def test_record_from_a_server_that_goes_silent_reconnects_and_keeps_every_byte(tmp_path, rfc2217):
    first, second, lost = two_parts()
    server = HalfOpenServer([first, second], rfc2217=rfc2217)
    stop = threading.Event()

    def on_state(event) -> None:
        if event.state == "open":
            server.port_opened()

    def on_progress(progress) -> None:
        if progress.bytes_written >= len(first) + len(second):
            stop.set()

    out = tmp_path / "rec.bin"
    try:
        result = record(
            server.url,
            out,
            stop=stop,
            on_state=on_state,
            on_progress=on_progress,
            progress_every_s=0.0,
            silence_s=SILENCE_S,
        )
    finally:
        server.close()
    assert out.read_bytes() == first + second
    assert result.counters.missing_frames == lost and result.counters.seq_gaps == 1
    events = yaml.safe_load(result.sidecar.read_text())["port_events"]
    states = [e["state"] for e in events]
    assert states[:3] == ["opening", "open", "lost"]
    assert events[2]["detail"] == silence_text(SILENCE_S) == "no bytes for 0.5 s: the connection is taken as lost"
    assert states[3:6] == ["retry_wait", "opening", "open"]
    assert server.accepted == 2


@pytest.mark.parametrize("how", ["option", "config"])
def test_record_silence_s_or_the_configs_port_silence_s_ends_a_silent_recording(tmp_path, how):
    """``record --no-reconnect`` from a server that goes quiet: the recording ends after the silence, with what
    the server sent, and says why."""
    first, _, _ = two_parts()
    server = HalfOpenServer([first])
    config = tmp_path / "fog.yaml"
    config.write_text(f"port_silence_s: {SILENCE_S}\n")
    choice = ["--silence-s", str(SILENCE_S)] if how == "option" else ["--config", str(config)]
    out = tmp_path / "rec.bin"
    command = [sys.executable, "-m", "fog_driver", "-v", "--log-format", "json", "record", server.url]
    command += ["--out", str(out), "--no-reconnect", *choice]
    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        lost = None
        for line in proc.stderr:
            entry = json.loads(line) if line.startswith("{") else {}
            if entry.get("event") == "port_state" and entry["state"] == "open":
                server.port_opened()
            if entry.get("event") == "port_state" and entry["state"] == "lost":
                lost = entry
        assert proc.wait(GUARD_S) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
        server.close()
    assert lost is not None and lost["detail"] == silence_text(SILENCE_S)
    assert out.read_bytes() == first


# -- the daemon ------------------------------------------------------------------------------------------------


class Client:
    """An NDJSON client of the daemon, watching."""

    def __init__(self, address: tuple[str, int]) -> None:
        self.sock = socket.create_connection(address, timeout=GUARD_S)
        self.file = self.sock.makefile("rb")
        self.sock.sendall(b'?WATCH={"enable":true};\n')

    def next(self, cls: str) -> dict:
        """The next line of class ``cls`` (others skipped)."""
        while True:
            raw = self.file.readline()
            assert raw, "the daemon closed the connection"
            obj = json.loads(raw)
            if obj["class"] == cls:
                return obj

    def wait_device(self, state: str) -> None:
        """Until a DEVICE line says the port is ``state``."""
        while self.next("DEVICE")["state"] != state:
            pass

    def status(self) -> dict:
        self.sock.sendall(b"?STATUS;\n")
        return self.next("STATUS")

    def close(self) -> None:
        self.file.close()
        self.sock.close()


def test_the_daemon_takes_a_silent_network_port_as_lost_and_reconnects(tmp_path):
    """The gap in network-serial.md: a device server cut off without closing left the daemon waiting on the
    dead connection for ever.  Now: silence -> DEVICE deactivated, a port_state warning with the reason, a
    reconnect, DEVICE activated, and the recovery line with the frames the sequence numbers say were lost."""
    first, second, lost = two_parts()
    server = HalfOpenServer([first, second])
    config = tmp_path / "fog.yaml"
    config.write_text(f"port_silence_s: {SILENCE_S}\n")
    log_path = tmp_path / "daemon.log"
    command = [sys.executable, "-m", "fog_driver", "run", "--config", str(config), "--port", server.url]
    command += ["--listen", "127.0.0.1:0", "--capture-dir", str(tmp_path / "captures")]
    with log_path.open("w") as log:
        daemon = subprocess.Popen(
            command,
            stdout=subprocess.PIPE,
            stderr=log,
            stdin=subprocess.DEVNULL,
            text=True,
            env={**os.environ, "PYTHONFAULTHANDLER": "1"},
        )
    client = None
    try:
        line = daemon.stdout.readline()  # the readiness line
        assert "listening on" in line, log_path.read_text()
        host, _, number = line.split("listening on ")[1].split(";")[0].rpartition(":")
        client = Client((host, int(number)))
        client.wait_device("activated")
        server.port_opened()
        first_samples = sum(isinstance(f, SampleFrame) for f in _frames(first))
        before = [client.next("ANGLE") for _ in range(first_samples)][-1]
        client.wait_device("deactivated")  # the silence taken as the loss (before: never)
        server.wait_accepted(2)  # reconnected
        client.wait_device("activated")
        server.port_opened()
        after = client.next("ANGLE")
        assert after["seq"] == before["seq"] + lost + 1 and "gap" in after["flags"]
        status = client.status()
        assert status["missing_frames"] == lost and status["seq_gaps"] == 1
        client.close()
        client = None
        daemon.send_signal(signal.SIGTERM)
        assert daemon.wait(GUARD_S) == 0
    finally:
        if client is not None:
            client.close()
        if daemon.poll() is None:
            daemon.kill()
            daemon.wait(GUARD_S)
        server.close()
    entries = [json.loads(line) for line in log_path.read_text().splitlines() if line.startswith("{")]
    losses = [e for e in entries if e.get("event") == "port_state" and e.get("state") == "lost"]
    assert losses[0]["detail"] == silence_text(SILENCE_S) and losses[0]["level"] == "warning"
    recovered = [e for e in entries if e.get("event") == "port_recovered"]
    assert recovered[0]["frames_missing"] == lost


def _frames(data: bytes) -> list:
    decoder = FrameDecoder()
    return decoder.feed(data) + decoder.close()


def test_a_config_reload_changes_the_running_readers_silence(tmp_path):
    """``port_silence_s`` is applied by SIGHUP or ``ctl reload`` (the reader reads it at each read)."""
    from fog_driver.daemon.config import DriverConfig
    from fog_driver.daemon.service import Service

    service = Service(DriverConfig(), port="unused")
    service.reader = PortReader("loop://", silence_s=service.config.port_silence_s)
    result = service.reload_config(DriverConfig(port_silence_s=SILENCE_S))
    assert service.reader.silence_s == SILENCE_S and "port_silence_s" in result["applied"]
    result = service.reload_config(DriverConfig(port_silence_s=None))
    assert service.reader.silence_s is None and "port_silence_s" in result["applied"]
