"""The client library's bounds (``fog_driver.client``), blocking and asyncio, against a fake daemon in this test:
memory bounded in bytes (unknown classes dropped, the queue trimmed, a line over 64 KiB a ``ProtocolError``, a
line without end no memory growth), deadlines that bytes arriving do not extend, the idle timeout of a watching
client, and the token sent before the watch to a daemon whose greeting carries no instrument.

The fake daemon listens on 127.0.0.1 port 0 and serves each connection with a script in a thread.  No sleeps:
the scripts wait on the client's command lines and on its end of the connection; ``GUARD_S`` only bounds a
failure (a client that would wait for ever is closed from a timer and the test fails)."""

from __future__ import annotations

import asyncio
import contextlib
import json
import socket
import threading
from collections.abc import Callable, Iterator

import pytest

from fog_driver.client import Angle, AsyncClient, Client, ConnectionLost, ProtocolError
from fog_driver.client.protocol import MESSAGE_OVERHEAD_BYTES, MIN_BUFFERED_BYTES, MessageQueue
from fog_driver.client.wire import MAX_LINE_BYTES

GUARD_S = 30.0
#: A greeting without the instrument (what a token daemon may send a client that has not authorized).
VERSION = {"class": "VERSION", "release": "test", "proto_major": 1, "proto_minor": 1}
DEVICE = {"class": "DEVICE", "path": "/dev/test", "state": "activated", "serial": "FOG-7", "rate_hz": 100}


def line(obj: dict) -> bytes:
    return json.dumps(obj, separators=(",", ":")).encode() + b"\n"


def angle(seq: int) -> bytes:
    return line({"class": "ANGLE", "seq": seq, "t_s": seq / 100, "angle_arcsec": seq * 0.5, "drift_dph": 0.25})


UNKNOWN_60KB = b'{"class":"FUTURE","pad":"' + b"x" * 60_000 + b'"}\n'


class Peer:
    """One connection of the fake daemon: lines out, command lines in (``commands`` records their names)."""

    def __init__(self, conn: socket.socket) -> None:
        self.conn = conn
        self.file = conn.makefile("rb")
        self.commands: list[str] = []

    def send(self, *items: bytes | dict) -> None:
        self.conn.sendall(b"".join(item if isinstance(item, bytes) else line(item) for item in items))

    def command(self) -> tuple[str, dict]:
        """The next command line's name and argument object ("" at the client's end of the connection)."""
        raw = self.file.readline(4096).strip()
        if not raw:
            return "", {}
        name, _, args = raw.decode().rstrip(";").partition("=")
        self.commands.append(name.lstrip("?"))
        return name.lstrip("?"), json.loads(args) if args else {}

    def expect(self, name: str) -> dict:
        got, args = self.command()
        assert got == name, f"expected ?{name}, got {got!r}"
        return args

    def wait_for_the_end(self) -> None:
        """Until the client closes its end (or ``GUARD_S``): what a daemon with nothing more to say does, each
        command answered with an object of its class (``?WATCH`` with the policy)."""
        self.conn.settimeout(GUARD_S)
        while (command := self.command())[0]:
            self.send({"class": command[0], **command[1]})


class FakeDaemon:
    """Listens on 127.0.0.1 port 0; connection number n (from 0) is served by ``script(peer, n)``.  ``peers``
    holds every connection served; a script's assertion failure is kept in ``failures``."""

    def __init__(self, script: Callable[[Peer, int], None]) -> None:
        self.script = script
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.address = self.listener.getsockname()[:2]
        self.peers: list[Peer] = []
        self.failures: list[BaseException] = []
        self.threads = [threading.Thread(target=self._accept, daemon=True)]
        self.threads[0].start()

    def _accept(self) -> None:
        while True:
            try:
                conn, _ = self.listener.accept()
            except OSError:
                return
            peer = Peer(conn)
            self.peers.append(peer)
            thread = threading.Thread(target=self._serve, args=(peer, len(self.peers) - 1), daemon=True)
            self.threads.append(thread)
            thread.start()

    def _serve(self, peer: Peer, n: int) -> None:
        try:
            self.script(peer, n)
        except (OSError, ValueError):
            pass  # the client went away mid-script
        except BaseException as exc:  # an assertion in the script: reported by close()
            self.failures.append(exc)
        finally:
            with contextlib.suppress(OSError):
                peer.conn.close()

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.listener.shutdown(socket.SHUT_RDWR)
        self.listener.close()
        for thread in self.threads:
            thread.join(GUARD_S)
        assert not self.failures, self.failures


@pytest.fixture
def fake():
    made: list[FakeDaemon] = []

    def make(script: Callable[[Peer, int], None]) -> FakeDaemon:
        made.append(FakeDaemon(script))
        return made[-1]

    yield make
    for daemon in made:
        daemon.close()


@contextlib.contextmanager
def guarded(client: Client, daemon: FakeDaemon) -> Iterator[Client]:
    """``client`` connected; after ``GUARD_S`` closed, and the daemon's ends of its connections too (a test that
    would hang fails instead)."""

    gave_up = threading.Event()

    def give_up() -> None:
        gave_up.set()
        client.close()
        for peer in daemon.peers:
            with contextlib.suppress(OSError):
                peer.conn.shutdown(socket.SHUT_RDWR)

    timer = threading.Timer(GUARD_S, give_up)
    timer.start()
    try:
        with client:
            yield client
    finally:
        timer.cancel()
    assert not gave_up.is_set(), f"the test did not end by itself within {GUARD_S:g} s"


def run(coro):
    return asyncio.run(asyncio.wait_for(coro, GUARD_S))


def watched(peer: Peer, *before_reply: bytes) -> dict:
    """The greeting, then ``?WATCH`` answered after ``before_reply``; the watch's argument."""
    peer.send(VERSION, DEVICE)
    args = peer.expect("WATCH")
    peer.send(*before_reply, {"class": "WATCH", **args})
    return args


# --------------------------------------------------------------------------- memory, in bytes

N_UNKNOWN = 20_000


def unknown_flood(peer: Peer, n: int) -> None:
    """20,000 lines of 60 KB of an unknown class before the answer to ?WATCH, then three samples."""
    peer.send(VERSION, DEVICE)
    peer.expect("WATCH")
    batch = UNKNOWN_60KB * 50
    for _ in range(N_UNKNOWN // 50):
        peer.send(batch)
    peer.send({"class": "WATCH", "enable": True}, angle(1), angle(2), angle(3))
    peer.wait_for_the_end()


def test_the_blocking_client_drops_unknown_classes_and_holds_less_than_its_bound(fake):
    daemon = fake(unknown_flood)
    with guarded(Client(daemon.address), daemon) as c:
        got = [a.seq for _, a in zip(range(3), c.angles())]
        assert got == [1, 2, 3]
        assert c.unknown == N_UNKNOWN and c.messages_dropped == 0  # dropped as they came, not queued
        assert 0 < c.buffered_bytes_peak <= c.max_buffered_bytes == 4 * 1024 * 1024


def test_the_asyncio_client_drops_unknown_classes_and_holds_less_than_its_bound(fake):
    daemon = fake(unknown_flood)

    async def main():
        async with AsyncClient(daemon.address) as c:
            everything = c.messages(timeout_s=0.1)  # its queue fills too: with the samples' queue, within the bound
            got = []
            async for a in c.angles():
                got.append(a.seq)
                if len(got) == 3:
                    return c, got, [type(m).__name__ async for m in everything]

    c, got, kinds = run(main())
    assert got == [1, 2, 3] and kinds == ["Reply", "Angle", "Angle", "Angle"]
    assert c.unknown == N_UNKNOWN and c.messages_dropped == 0
    assert 0 < c.buffered_bytes_peak <= c.max_buffered_bytes


def test_keep_unknown_gives_them_to_messages_within_the_bound(fake):
    def script(peer: Peer, n: int) -> None:
        peer.send(VERSION, b'{"class":"FUTURE","x":1}\n', DEVICE)
        peer.wait_for_the_end()

    daemon = fake(script)
    with guarded(Client(daemon.address, keep_unknown=True), daemon) as c:
        kinds = [type(m).__name__ for _, m in zip(range(3), c.messages())]
    assert kinds == ["Version", "Other", "Device"] and c.unknown == 1
    with guarded(Client(daemon.address), daemon) as c:
        kinds = [type(m).__name__ for _, m in zip(range(2), c.messages())]
    assert kinds == ["Version", "Device"] and c.unknown == 1


N_QUEUED = 5_000


def samples_before_the_answer(peer: Peer, n: int) -> None:
    """Watch answered, then ?STATUS answered after 5,000 samples (more than the bound holds), then a BIAS
    capture whose result comes after 5,000 more."""
    watched(peer)
    peer.expect("STATUS")
    peer.send(b"".join(angle(seq) for seq in range(1, N_QUEUED + 1)), {"class": "STATUS", "frames": 7})
    args = peer.expect("BIAS")
    peer.send({"class": "BIAS", "state": "started", "capture_id": 4, "seconds": args["seconds"], "timeout_s": 5})
    peer.send(b"".join(angle(seq) for seq in range(N_QUEUED + 1, 2 * N_QUEUED + 1)))
    peer.send({"class": "BIAS", "state": "done", "capture_id": 4, "bias_dph": 0.5, "seconds": args["seconds"]})
    peer.wait_for_the_end()


def test_samples_nobody_takes_are_dropped_oldest_first_within_the_bound_and_a_bias_result_is_kept(fake):
    daemon = fake(samples_before_the_answer)
    with guarded(Client(daemon.address, max_buffered_bytes=MIN_BUFFERED_BYTES), daemon) as c:
        c.watch()
        assert c.status().frames == 7
        held = c.buffered_bytes
        assert MIN_BUFFERED_BYTES // 2 < held <= MIN_BUFFERED_BYTES and c.angles_dropped > 0
        assert c.messages_dropped == c.angles_dropped + 2  # the oldest first: the greeting's VERSION and DEVICE
        kept = [m.seq for m in iter(lambda: c.poll(0), None) if isinstance(m, Angle)]
        assert kept == list(range(N_QUEUED - len(kept) + 1, N_QUEUED + 1))  # the newest, in order
        assert len(kept) + c.angles_dropped == N_QUEUED and c.buffered_bytes == 0
        result = c.bias(2)  # 5,000 samples more came before the result: the result is not dropped with them
        assert result.state == "done" and result.bias_dph == 0.5
        assert c.buffered_bytes_peak <= MIN_BUFFERED_BYTES


def test_the_asyncio_queues_share_the_bound_and_drop_the_oldest(fake):
    daemon = fake(samples_before_the_answer)

    async def main():
        async with AsyncClient(daemon.address, max_buffered_bytes=MIN_BUFFERED_BYTES) as c:
            messages = c.messages()
            await c.watch()
            assert (await c.status()).frames == 7
            first = await anext(messages)  # the WATCH answer went before the samples; the oldest were dropped
            result = await c.bias(2)
            return c, first, result

    c, first, result = run(main())
    assert c.angles_dropped > 0 and c.messages_dropped > c.angles_dropped  # both queues dropped samples
    assert c.buffered_bytes_peak <= MIN_BUFFERED_BYTES and result.bias_dph == 0.5
    assert isinstance(first, Angle) and first.seq > 1


def test_the_queue_counts_bytes_and_keeps_one_protocol_error_in_place():
    def message(seq: int) -> Angle:
        return Angle(seq=seq, t_s=0.0, line=b"x" * 1000)

    queue = MessageQueue(max_bytes=3 * (1000 + MESSAGE_OVERHEAD_BYTES))
    assert queue.put(message(1)) == [] and queue.put(ProtocolError("first")) == []
    assert queue.put(ProtocolError("second")) == []  # one waits already
    assert [m.seq for m in queue.put(message(2)) + queue.put(message(3)) + queue.put(message(4))] == [1]
    assert queue.bytes == 3 * (1000 + MESSAGE_OVERHEAD_BYTES)
    items = [queue.popleft() for _ in range(len(queue))]
    assert [str(i) if isinstance(i, ProtocolError) else i.seq for i in items] == ["first", 2, 3, 4]
    assert queue.bytes == 0


def test_a_buffer_bound_below_the_minimum_is_refused():
    for bad in (MIN_BUFFERED_BYTES - 1, 4.0e6, True):
        with pytest.raises(ValueError, match="max_buffered_bytes"):
            Client(max_buffered_bytes=bad)
    for bad in ({"idle_min_s": 0}, {"idle_periods": 0}, {"idle_min_s": float("inf")}):
        with pytest.raises(ValueError, match="idle"):
            AsyncClient(**bad)


# --------------------------------------------------------------------------- lines over the bound


def oversized(peer: Peer, n: int) -> None:
    """Two samples, a line over 64 KiB, a third sample; the connection stays open."""
    watched(peer)
    peer.send(angle(1), angle(2), b'{"class":"ANGLE","seq":9,"pad":"' + b"y" * 70_000 + b'"}\n', angle(3))
    peer.wait_for_the_end()


def test_a_line_over_64_kib_is_a_protocol_error_from_angles_without_reconnecting(fake):
    daemon = fake(oversized)
    with guarded(Client(daemon.address), daemon) as c:
        got = []
        with pytest.raises(ProtocolError, match="line over 65536 bytes") as raised:
            for a in c.angles():
                got.append(a.seq)
        assert got == [1, 2] and raised.value.exit_status == 76
        assert c.reconnects == 0 and len(daemon.peers) == 1
        assert c.poll(GUARD_S).seq == 3  # the connection stays: a caller may read on


def test_the_asyncio_angles_raise_the_protocol_error_in_its_place(fake):
    daemon = fake(oversized)

    async def main():
        async with AsyncClient(daemon.address) as c:
            got = []
            with pytest.raises(ProtocolError, match="line over 65536 bytes"):
                async for a in c.angles():
                    got.append(a.seq)
            later = await anext(c.angles())  # the connection stays: a caller may read on
            return c, got, later

    c, got, later = run(main())
    assert got == [1, 2] and later.seq == 3 and c.reconnects == 0 and len(daemon.peers) == 1


def endless_line(peer: Peer, n: int) -> None:
    """A sample, then a line that never ends: 1 MiB chunks until the client goes (at most 64 MiB)."""
    watched(peer)
    peer.send(angle(1), b'{"class":"ANGLE","pad":"')
    chunk = b"z" * (1 << 20)
    for _ in range(64):
        peer.send(chunk)
    peer.wait_for_the_end()


@pytest.mark.parametrize("kind", ["blocking", "asyncio"])
def test_a_line_that_never_ends_is_a_protocol_error_once_past_the_bound_not_memory(fake, kind):
    daemon = fake(endless_line)

    async def main():
        async with AsyncClient(daemon.address, reconnect=False) as c:
            got = []
            with pytest.raises(ProtocolError):
                async for a in c.angles():
                    got.append(a.seq)
            return c, got

    if kind == "asyncio":
        c, got = run(main())
    else:
        with guarded(Client(daemon.address, reconnect=False), daemon) as c:
            got = []
            with pytest.raises(ProtocolError):
                for a in c.angles():
                    got.append(a.seq)
    assert got == [1] and c.session.reader.oversized == 1
    assert c.session.reader.buffered_bytes == 0  # the endless line's bytes are dropped as they come
    assert c.buffered_bytes_peak < MAX_LINE_BYTES + 1 + 4096  # the line's bound, and the greeting and a sample


# --------------------------------------------------------------------------- deadlines and the idle timeout


def flood(*lines: bytes) -> Callable[[Peer, int], None]:
    """The watch answered, then ``lines`` over and over until the client goes."""

    def script(peer: Peer, n: int) -> None:
        watched(peer)
        batch = b"".join(lines) * 200
        while True:
            peer.send(batch)

    return script


JUNK = b"not json\n"
UNKNOWN = b'{"class":"FUTURE","x":1}\n'
STATUS = line({"class": "STATUS", "frames": 1})


def test_the_blocking_timeouts_hold_while_junk_keeps_arriving(fake):
    daemon = fake(flood(JUNK, UNKNOWN, STATUS))
    with guarded(Client(daemon.address), daemon) as c:
        assert list(c.angles(timeout_s=0.3)) == []  # no sample: it ends, whatever else came
        assert c.malformed > 0 and c.unknown > 0
    daemon = fake(flood(JUNK, UNKNOWN))
    with guarded(Client(daemon.address), daemon) as c:
        c.watch()
        kinds = [type(m).__name__ for m in c.messages(timeout_s=0.3)]
        assert kinds == ["Version", "Device"] and c.poll(0.1) is None  # then bytes came, and no message
        assert c.malformed > 0


def test_the_asyncio_timeouts_hold_while_junk_keeps_arriving(fake):
    with_status, without = fake(flood(JUNK, UNKNOWN, STATUS)), fake(flood(JUNK, UNKNOWN))

    async def main():
        async with AsyncClient(with_status.address) as c:
            got = [a async for a in c.angles(timeout_s=0.3)]
            counts = c.malformed, c.unknown
        async with AsyncClient(without.address) as c:
            messages = c.messages(timeout_s=0.3)
            await c.watch()
            kinds = [type(m).__name__ async for m in messages]
        return got, counts, kinds

    got, (malformed, unknown), kinds = run(main())
    assert got == [] and malformed > 0 and unknown > 0
    assert kinds == ["Reply"]  # the WATCH answer; nothing else is a message


def silent_after_three(peer: Peer, n: int) -> None:
    """Three samples per connection (from 1, then from 1001), then nothing: a hung daemon."""
    watched(peer)
    peer.send(*(angle(1000 * n + k) for k in (1, 2, 3)))
    peer.wait_for_the_end()


def test_a_silent_daemon_is_an_idle_timeout_without_reconnect(fake):
    daemon = fake(silent_after_three)
    with guarded(Client(daemon.address, reconnect=False, idle_min_s=1.0), daemon) as c:
        got = []
        with pytest.raises(ConnectionLost, match=r"no line from the daemon for 1 s while watching"):
            for a in c.angles(rate_hz=1000):
                got.append(a.seq)
                # the period expected: the longer of the watch's (1 ms) and the device's (10 ms), times 5
                assert c.idle_timeout_s() == max(1.0, 5 * 0.01)
        assert got == [1, 2, 3]
        c.watch(1)  # a watch at 1 Hz: 5 periods of 1 s are more than the floor
        assert c.idle_timeout_s() == 5.0


def test_an_idle_daemon_is_connected_again_with_the_gap_reported(fake):
    daemon = fake(silent_after_three)
    with guarded(Client(daemon.address, idle_min_s=1.0, backoff_initial_s=0.01), daemon) as c:
        got = []
        for a in c.angles():
            got.append(a)
            if len(got) == 4:
                break
    assert [a.seq for a in got] == [1, 2, 3, 1001] and got[3].gap_before.missed == 997 and c.reconnects == 1


def test_the_asyncio_client_takes_an_idle_daemon_for_dead(fake):
    daemon = fake(silent_after_three)

    async def main():
        async with AsyncClient(daemon.address, idle_min_s=1.0, backoff_initial_s=0.01) as c:
            got = []
            async for a in c.angles():
                got.append(a)
                if len(got) == 4:
                    break
        async with AsyncClient(daemon.address, idle_min_s=1.0, reconnect=False) as c:
            with pytest.raises(ConnectionLost, match="no line from the daemon"):
                async for _ in c.angles():
                    pass
        return got

    got = run(main())
    assert [a.seq for a in got] == [1, 2, 3, 1001] and got[3].gap_before.missed == 997
    assert len(daemon.peers) == 3


def test_idle_periods_none_waits_on_a_silent_daemon(fake):
    daemon = fake(silent_after_three)
    with guarded(Client(daemon.address, reconnect=False, idle_periods=None, idle_min_s=0.01), daemon) as c:
        assert [a.seq for a in c.angles(timeout_s=0.3)] == [1, 2, 3]  # ended by the call's own timeout
        assert c.idle_timeout_s() is None


def test_close_from_another_thread_ends_a_read_that_waits_without_limit(fake):
    def script(peer: Peer, n: int) -> None:
        peer.send(VERSION)
        peer.wait_for_the_end()

    daemon = fake(script)
    with guarded(Client(daemon.address, reconnect=False), daemon) as c:
        assert c.poll(GUARD_S).release == "test"
        closer = threading.Timer(0.2, c.close)  # a pace: before the wait or during it, the read must end
        closer.start()
        with pytest.raises(ConnectionLost, match="the client was closed"):
            c.poll(None)  # not watching: no idle timeout either
        closer.join()


# --------------------------------------------------------------------------- the token, before the watch

TOKEN = "a-long-token"


def token_daemon(peer: Peer, n: int) -> None:
    """A daemon with a token: VERSION without the instrument; DEVICE, STATUS and samples only after ?AUTH."""
    peer.send(VERSION)
    authorized = False
    while True:
        name, args = peer.command()
        if name == "":
            return
        if name == "AUTH":
            authorized = args.get("token") == TOKEN
            peer.send({"class": "AUTH", "authorized": True} if authorized else {"class": "ERROR", "message": "no"})
            if authorized:
                peer.send(DEVICE, {"class": "STATUS", "frames": 3})
        elif name == "VERSION":  # after ?AUTH, the instrument too (as the daemon's)
            peer.send({**VERSION, "instrument": {"serial": "FOG-7"}} if authorized else VERSION)
        elif name == "WATCH":
            peer.send({"class": "WATCH", **args})
            if authorized:
                peer.send(angle(1), angle(2))


def test_both_clients_authorize_before_watching_a_daemon_that_greets_without_the_instrument(fake):
    daemon = fake(token_daemon)
    with guarded(Client(daemon.address, token=TOKEN), daemon) as c:
        # the greeting held no instrument; the VERSION asked for after ?AUTH does
        assert c.version.instrument is not None and c.version.instrument["serial"] == "FOG-7"
        assert c.version.release == "test"
        assert [a.seq for _, a in zip(range(2), c.angles())] == [1, 2]
        assert c.device.serial == "FOG-7"

    async def main():
        async with AsyncClient(daemon.address, token=TOKEN) as c:
            seqs = []
            async for a in c.angles():
                seqs.append(a.seq)
                if len(seqs) == 2:
                    return c.version, seqs

    version, seqs = run(main())
    assert version.instrument is not None and version.instrument["serial"] == "FOG-7" and seqs == [1, 2]
    assert [peer.commands for peer in daemon.peers] == [["AUTH", "VERSION", "WATCH"]] * 2


def test_a_watch_without_the_token_ends_with_a_hint_not_a_hang(fake):
    daemon = fake(token_daemon)
    with guarded(Client(daemon.address, reconnect=False, idle_min_s=1.0), daemon) as c:
        with pytest.raises(ConnectionLost, match=r"no \?AUTH on this connection: a daemon with a token sends no"):
            next(c.angles())
        assert c.device is None
