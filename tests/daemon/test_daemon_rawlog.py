"""The daemon's raw capture (rotating files + sidecars) and its systemd notifier (the unit file: test_daemon_deploy.py).

No sleeps anywhere: time-based behaviour runs on an injected clock.
"""

from __future__ import annotations

import hashlib
import os
import random
import re
import socket
from pathlib import Path

import pytest

from fog_driver.daemon import rawlog
from fog_driver.daemon.rawlog import RotatingCapture
from fog_driver.daemon.sdnotify import Notifier
from fog_driver.errors import OutputFileError
from fog_driver.protocol import decode_bytes, decode_file, encode_identity, encode_sample
from fog_driver.samples.captures import legacy_sidecar_path, read_provenance, sidecar_path

NAME = re.compile(r"^fog-(\d{6,})-(\d{8}T\d{6}Z)\.bin$")


class FakeClock:
    def __init__(self, t: float = 1000.0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


def _chunks(seed: int, n: int, lo: int = 1, hi: int = 300) -> list[bytes]:
    rng = random.Random(seed)
    return [rng.randbytes(rng.randint(lo, hi)) for _ in range(n)]


def _concat(paths: list[Path]) -> bytes:
    return b"".join(p.read_bytes() for p in paths)


def _frames(n: int) -> list[bytes]:
    """An IDENTITY frame, then ``n`` SAMPLE frames, each as its own bytes."""
    out = [encode_identity("FOG-TEST-0001", 0x0102, 100, 0.0125)]
    out += [encode_sample(i, 10_000 * i, 40 + i % 7, 5120, 5100, 5000) for i in range(n)]
    return out


# -- the bytes -------------------------------------------------------------------------------------


def test_files_concatenate_to_exactly_the_bytes_written(tmp_path):
    chunks = _chunks(1, 400)
    with RotatingCapture(tmp_path, max_bytes=2000, clock=FakeClock()) as cap:
        for chunk in chunks:
            cap.write(chunk)
        assert cap.bytes_written == sum(map(len, chunks))
    data = b"".join(chunks)
    assert len(cap.files) > 10
    assert _concat(cap.files) == data
    # Name order is write order, so `cat fog-*.bin` restores the stream.
    assert sorted(cap.files, key=lambda p: p.name) == cap.files
    assert sorted(tmp_path.glob("*.bin")) == sorted(cap.files)
    assert cap.current_path is None and cap.closed


def test_file_names_follow_the_pattern(tmp_path):
    with RotatingCapture(tmp_path / "raw", max_bytes=10, clock=FakeClock()) as cap:
        for chunk in _chunks(2, 5, 10, 10):
            cap.write(chunk)
    assert [int(NAME.match(p.name)[1]) for p in cap.files] == [0, 1, 2, 3, 4]
    for p in cap.files:
        assert p.parent == tmp_path / "raw"
        assert sidecar_path(p).exists()


def test_size_rotation_never_splits_a_chunk_and_respects_max_bytes(tmp_path):
    chunks = _chunks(3, 500, 1, 250)
    max_bytes = 1000
    with RotatingCapture(tmp_path, max_bytes=max_bytes, clock=FakeClock()) as cap:
        for chunk in chunks:
            cap.write(chunk)
    sizes = [p.stat().st_size for p in cap.files]
    assert max(sizes) <= max_bytes
    # Every file is a run of whole chunks, and it rotated only when the next chunk would not fit.
    i = 0
    for k, path in enumerate(cap.files):
        content = path.read_bytes()
        held = 0
        while i < len(chunks) and held + len(chunks[i]) <= len(content):
            assert content[held : held + len(chunks[i])] == chunks[i]
            held += len(chunks[i])
            i += 1
        assert held == len(content), f"{path.name} ends inside a chunk"
        if k + 1 < len(cap.files):
            assert held + len(chunks[i]) > max_bytes  # rotated only when it had to
    assert i == len(chunks)


def test_a_chunk_of_exactly_max_bytes_fills_a_file(tmp_path):
    with RotatingCapture(tmp_path, max_bytes=100, clock=FakeClock()) as cap:
        cap.write(b"a" * 100)
        cap.write(b"b" * 100)
        cap.write(b"c" * 40)
        cap.write(b"d" * 60)
    assert [p.read_bytes() for p in cap.files] == [b"a" * 100, b"b" * 100, b"c" * 40 + b"d" * 60]


def test_a_chunk_larger_than_max_bytes_is_written_whole_alone_in_its_file(tmp_path):
    """The one documented exception to max_bytes: a single oversized chunk is not split."""
    big = bytes(range(256)) * 2
    with RotatingCapture(tmp_path, max_bytes=100, clock=FakeClock()) as cap:
        cap.write(b"x" * 30)
        cap.write(big)
        cap.write(b"y" * 30)
    assert [p.read_bytes() for p in cap.files] == [b"x" * 30, big, b"y" * 30]
    assert read_provenance(cap.files[1])["bytes"] == len(big)


def test_empty_writes_open_no_file(tmp_path):
    with RotatingCapture(tmp_path, clock=FakeClock()) as cap:
        cap.write(b"")
        assert cap.current_path is None
    assert cap.files == [] and list(tmp_path.iterdir()) == []


def test_write_after_close_is_an_error_and_close_is_idempotent(tmp_path):
    cap = RotatingCapture(tmp_path, clock=FakeClock())
    cap.write(b"abc")
    cap.close()
    cap.close()
    with pytest.raises(ValueError):
        cap.write(b"more")
    assert _concat(cap.files) == b"abc"


@pytest.mark.parametrize("kwargs", [{"max_bytes": 0}, {"max_age_s": 0}, {"prefix": ""}, {"prefix": "a/b"}])
def test_bad_arguments_are_value_errors(tmp_path, kwargs):
    with pytest.raises(ValueError):
        RotatingCapture(tmp_path, **kwargs)


# -- time ------------------------------------------------------------------------------------------


def test_age_rotation_with_an_injected_clock(tmp_path):
    clock = FakeClock(500.0)
    with RotatingCapture(tmp_path, max_age_s=60.0, clock=clock) as cap:
        cap.write(b"a")  # opens the first file at t=500
        clock.t = 559.9
        cap.write(b"b")
        assert len(cap.files) == 1
        clock.t = 560.0  # 60 s since the file opened
        cap.write(b"c")
        assert len(cap.files) == 2
        clock.t = 619.0
        cap.write(b"d")
        clock.t = 620.0
        cap.write(b"e")
    assert [p.read_bytes() for p in cap.files] == [b"ab", b"cd", b"e"]
    reasons = [read_provenance(p)["end_reason"] for p in cap.files]
    assert reasons == ["max_age_s", "max_age_s", "close"]


def test_poll_closes_an_old_file_on_a_quiet_port(tmp_path):
    clock = FakeClock(0.0)
    with RotatingCapture(tmp_path, max_age_s=10.0, clock=clock) as cap:
        cap.write(b"first")
        clock.t = 9.0
        cap.poll()
        assert cap.current_path == cap.files[0]
        clock.t = 10.0
        cap.poll()
        assert cap.current_path is None  # closed and described, no empty successor
        assert read_provenance(cap.files[0])["status"] == "complete"
        clock.t = 500.0
        cap.poll()
        assert len(cap.files) == 1
        cap.write(b"second")
    assert [p.read_bytes() for p in cap.files] == [b"first", b"second"]


def test_every_write_reaches_the_os_at_once_and_sync_fsyncs(tmp_path, monkeypatch):
    """Unbuffered: a process killed right after a write loses nothing it wrote."""
    cap = RotatingCapture(tmp_path, clock=FakeClock())
    for k in range(1, 4):
        cap.write(b"z" * 10)
        assert os.stat(cap.current_path).st_size == 10 * k
    synced = []
    monkeypatch.setattr(os, "fsync", lambda fd: synced.append(fd))
    cap.sync()
    assert len(synced) == 1
    cap.close()


# -- sidecars --------------------------------------------------------------------------------------


def test_sidecars_say_recording_then_complete_with_bytes_and_sha256(tmp_path):
    provenance = {"port": "/dev/ttyUSB0", "baud": 921600, "instrument": "chamber1"}
    chunks = _chunks(4, 60, 50, 150)
    cap = RotatingCapture(tmp_path, max_bytes=2000, provenance=provenance, clock=FakeClock())
    cap.write(chunks[0])
    open_side = read_provenance(cap.current_path)
    assert open_side["status"] == "recording"
    assert open_side["port"] == "/dev/ttyUSB0" and open_side["instrument"] == "chamber1"
    assert open_side["source"] == "daemon" and "start_utc" in open_side and "sha256" not in open_side
    for chunk in chunks[1:]:
        cap.write(chunk)
    cap.close()
    total = 0
    for k, path in enumerate(cap.files):
        side = read_provenance(path)
        data = path.read_bytes()
        assert side["status"] == "complete"
        assert side["capture"] == path.name
        assert side["bytes"] == len(data)
        assert side["sha256"] == hashlib.sha256(data).hexdigest()
        assert side["baud"] == 921600 and side["port"] == "/dev/ttyUSB0"
        assert side["segment"] == k
        assert side.get("previous_capture") == (cap.files[k - 1].name if k else None)
        assert side["start_utc"].endswith("Z") and side["end_utc"] >= side["start_utc"]
        assert side["rotation"] == {"max_bytes": 2000, "max_age_s": 3600.0}
        total += side["bytes"]
    assert total == cap.bytes_written == sum(map(len, chunks))
    assert not list(tmp_path.glob("*.tmp"))


def test_update_provenance_reaches_the_current_and_later_sidecars(tmp_path):
    cap = RotatingCapture(tmp_path, max_bytes=10, provenance={"port": "p"}, clock=FakeClock())
    cap.write(b"0123456789")
    cap.update_provenance({"instrument": {"serial": "FOG-1"}})
    assert read_provenance(cap.current_path)["instrument"] == {"serial": "FOG-1"}
    cap.write(b"abc")
    cap.close()
    for path in cap.files:
        assert read_provenance(path)["instrument"] == {"serial": "FOG-1"}
        assert read_provenance(path)["port"] == "p"


def test_names_sort_in_opening_order_across_restarts_whatever_the_clock_says(tmp_path, monkeypatch):
    """The number continues from the directory's highest: a restart within the same second, or after the
    wall clock stepped back (no RTC at boot, then NTP), still sorts after the earlier files."""
    monkeypatch.setattr(rawlog, "utc_now_iso", lambda: "2024-05-06T07:08:09.000Z")
    with RotatingCapture(tmp_path, clock=FakeClock()) as first:
        first.write(b"first run")
    with RotatingCapture(tmp_path, clock=FakeClock()) as second:  # a restart within the same second
        second.write(b"second run")
    monkeypatch.setattr(rawlog, "utc_now_iso", lambda: "1970-01-01T00:00:05.000Z")
    with RotatingCapture(tmp_path, clock=FakeClock()) as third:  # the clock went back
        third.write(b"third run")
    assert [p.name for p in first.files] == ["fog-000000-20240506T070809Z.bin"]
    assert [p.name for p in second.files] == ["fog-000001-20240506T070809Z.bin"]
    assert [p.name for p in third.files] == ["fog-000002-19700101T000005Z.bin"]
    assert _concat(sorted(tmp_path.glob("*.bin"))) == b"first runsecond runthird run"
    assert first.files[0].read_bytes() == b"first run"


def test_sidecars_never_write_through_a_symlink_planted_at_a_predictable_name(tmp_path, monkeypatch):
    """The review's E15: with the capture directory writable by someone else, a symlink planted as
    ``<capture>.yaml.tmp`` (the name is the UTC second) made the daemon overwrite the link's target."""
    monkeypatch.setattr(rawlog, "utc_now_iso", lambda: "2024-05-06T07:08:09.000Z")
    victim = tmp_path / "victim.conf"
    victim.write_text("important: config\n")
    captures = tmp_path / "captures"
    captures.mkdir()
    (captures / "fog-20240506T070809Z-0000.yaml.tmp").symlink_to(victim)
    with RotatingCapture(captures, clock=FakeClock()) as cap:
        cap.write(b"\xaa\x55")
    assert victim.read_text() == "important: config\n"
    assert read_provenance(cap.files[0])["status"] == "complete"


# -- failures --------------------------------------------------------------------------------------


def test_directory_is_created_with_its_parents(tmp_path):
    target = tmp_path / "var" / "lib" / "fog-driver"
    RotatingCapture(target).close()
    assert target.is_dir()


@pytest.mark.parametrize("where", ["under_a_file", "is_a_file"])
def test_a_directory_that_cannot_be_created_is_a_one_line_error(tmp_path, where):
    blocker = tmp_path / "plain-file"
    blocker.write_text("not a directory")
    target = blocker / "captures" if where == "under_a_file" else blocker
    with pytest.raises(OutputFileError) as info:
        RotatingCapture(target)
    message = str(info.value)
    assert "\n" not in message and str(target) in message
    assert info.value.exit_status == 73


class _FullDisk:
    """Wraps a capture file whose disk has just filled up: every write, flush and fsync fails."""

    def __init__(self, real):
        self.real = real

    @property
    def closed(self):
        return self.real.closed

    def write(self, data):
        raise OSError(28, "No space left on device")

    def flush(self):
        raise OSError(28, "No space left on device")

    def fileno(self):
        raise OSError(28, "No space left on device")

    def close(self):
        self.real.close()


def test_a_full_disk_is_a_one_line_error_and_the_sidecar_says_failed(tmp_path):
    cap = RotatingCapture(tmp_path, clock=FakeClock())
    cap.write(b"kept")
    cap.flush()
    failing = cap.current_path
    cap._writer._file = _FullDisk(cap._writer._file)  # the CaptureWriter's file: the disk fills up
    with pytest.raises(OutputFileError) as info:
        cap.write(b"lost")
    assert "\n" not in str(info.value) and "No space left on device" in str(info.value)
    side = read_provenance(failing)
    assert side["status"].startswith("failed: ") and "No space left" in side["status"]
    assert side["bytes"] == 4 and failing.read_bytes() == b"kept"
    # The service decides: writing again starts a new file.
    assert cap.current_path is None
    cap.write(b"after")
    cap.close()
    assert cap.files[1].read_bytes() == b"after" and read_provenance(cap.files[1])["status"] == "complete"


# -- frames ----------------------------------------------------------------------------------------


def test_every_file_decodes_when_fed_whole_frames(tmp_path):
    frames = _frames(400)
    with RotatingCapture(tmp_path, max_bytes=1000, clock=FakeClock()) as cap:
        for frame in frames:
            cap.write(frame)
    assert len(cap.files) > 5
    samples = 0
    for path in cap.files:
        decoded = decode_file(path)
        c = decoded.counters
        assert c.crc_errors == c.length_errors == c.bytes_discarded == 0
        assert c.bytes_in == path.stat().st_size
        samples += c.sample_frames
    assert samples == 400
    assert decode_file(cap.files[0]).identities[0].serial == "FOG-TEST-0001"


def test_files_cut_inside_frames_still_decode_as_one_stream_when_concatenated(tmp_path):
    stream = b"".join(_frames(300))
    rng = random.Random(5)
    with RotatingCapture(tmp_path, max_bytes=700, clock=FakeClock()) as cap:
        i = 0
        while i < len(stream):
            n = rng.randint(1, 64)
            cap.write(stream[i : i + n])
            i += n
    whole = decode_bytes(_concat(cap.files))
    assert whole.counters.sample_frames == 300 and whole.counters.bytes_discarded == 0
    assert whole.counters.as_dict() == decode_bytes(stream).counters.as_dict()


# -- sdnotify --------------------------------------------------------------------------------------


@pytest.fixture
def notify_socket(tmp_path):
    path = tmp_path / "n.sock"
    if len(str(path)) > 100:
        pytest.skip("tmp_path too long for an AF_UNIX address")
    server = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    server.bind(str(path))
    server.settimeout(5)
    yield path, server
    server.close()


def _nothing_waiting(server: socket.socket) -> bool:
    server.setblocking(False)
    try:
        server.recv(4096)
    except BlockingIOError:
        return True
    finally:
        server.settimeout(5)
    return False


def test_sdnotify_sends_the_messages_systemd_expects(notify_socket, monkeypatch):
    path, server = notify_socket
    monkeypatch.setenv("NOTIFY_SOCKET", str(path))
    monkeypatch.setenv("WATCHDOG_USEC", "10000000")
    monkeypatch.delenv("WATCHDOG_PID", raising=False)
    with Notifier.from_environment() as n:
        assert n.enabled and n.watchdog_interval_s == 5.0
        assert n.ready()
        assert server.recv(4096) == b"READY=1"
        assert n.status("recording chamber1: 1,234 frames\nok")
        assert server.recv(4096) == b"STATUS=recording chamber1: 1,234 frames ok"
        assert n.watchdog()
        assert server.recv(4096) == b"WATCHDOG=1"
        assert n.stopping()
        assert server.recv(4096) == b"STOPPING=1"
        n.ready("up")
        assert server.recv(4096) == b"READY=1\nSTATUS=up"
        assert n.sent == 5 and n.send_errors == 0
        assert _nothing_waiting(server)


def test_sdnotify_watchdog_is_rate_limited_to_half_the_period(notify_socket, monkeypatch):
    path, server = notify_socket
    monkeypatch.setenv("NOTIFY_SOCKET", str(path))
    monkeypatch.setenv("WATCHDOG_USEC", "10000000")  # WatchdogSec=10: ping at most every 5 s
    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid()))
    n = Notifier.from_environment()
    sent = [t for t in (0.0, 1.0, 4.99, 5.0, 6.0, 9.99, 10.0, 10.5, 20.0) if n.maybe_watchdog(t)]
    assert sent == [0.0, 5.0, 10.0, 20.0]
    for _ in sent:
        assert server.recv(4096) == b"WATCHDOG=1"
    assert _nothing_waiting(server)
    # The notifier's own clock when no time is given.
    clock = FakeClock(100.0)
    n2 = Notifier(str(path), 2_000_000, clock=clock)
    assert n2.maybe_watchdog() and not n2.maybe_watchdog()
    clock.t = 101.0
    assert n2.maybe_watchdog()
    assert [server.recv(4096) for _ in range(2)] == [b"WATCHDOG=1"] * 2
    n.close()
    n2.close()


@pytest.mark.parametrize(
    "status_every_s, watchdog_usec, wait_s",
    [(3.0, 2_000_000, 0.5), (1.0, 10_000_000, 1.0), (10.0, 10_000_000, 2.5), (3.0, None, 3.0)],
)
def test_sdnotify_loop_wait_is_the_status_period_or_a_quarter_of_the_watchdog(
    notify_socket, status_every_s, watchdog_usec, wait_s
):
    path, _ = notify_socket
    assert Notifier(str(path), watchdog_usec).loop_wait_s(status_every_s) == wait_s


def test_sdnotify_a_loop_waking_at_loop_wait_pings_within_the_period(notify_socket):
    """The review's E11: status_every_s 3 under WatchdogSec=2 pinged every 3 s, and systemd would have
    killed a healthy daemon.  A loop waiting ``loop_wait_s`` pings every 1 to 1.5 s, even when each
    wake-up comes up to 10 % early or late."""
    path, server = notify_socket
    clock = FakeClock(0.0)
    n = Notifier(str(path), 2_000_000, clock=clock)
    wait_s = n.loop_wait_s(3.0)
    jitter = random.Random(11)
    pings = []
    for _ in range(200):
        clock.t += wait_s * jitter.uniform(0.9, 1.1)
        if n.maybe_watchdog():
            pings.append(clock.t)
            assert server.recv(4096) == b"WATCHDOG=1"
    gaps = [b - a for a, b in zip(pings, pings[1:])]
    assert pings[0] <= wait_s * 1.1 and len(gaps) > 50
    assert min(gaps) >= 1.0 and max(gaps) <= 1.5 * 1.1 < 2.0
    n.close()


def test_sdnotify_abstract_socket_address(monkeypatch):
    name = f"fog-driver-test-{os.getpid()}"
    server = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    server.bind("\0" + name)
    server.settimeout(5)
    try:
        monkeypatch.setenv("NOTIFY_SOCKET", "@" + name)
        with Notifier.from_environment() as n:
            assert n.ready("abstract")
            assert server.recv(4096) == b"READY=1\nSTATUS=abstract"
    finally:
        server.close()


def test_sdnotify_without_a_socket_is_a_no_op(monkeypatch):
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    monkeypatch.delenv("WATCHDOG_USEC", raising=False)
    n = Notifier.from_environment()
    assert not n.enabled and n.watchdog_interval_s is None
    assert not n.ready("x") and not n.status("x") and not n.watchdog() and not n.stopping()
    assert not n.maybe_watchdog(0.0)
    assert n.sent == n.send_errors == 0
    for address in ("", "relative/path", "vsock:2:1234", "@"):
        assert not Notifier.from_environment({"NOTIFY_SOCKET": address}).enabled
    no_socket = Notifier.from_environment({"WATCHDOG_USEC": "2000000"})  # nothing to ping: no watchdog
    assert no_socket.watchdog_interval_s is None and no_socket.loop_wait_s(3.0) == 3.0


def test_sdnotify_watchdog_for_another_process_or_malformed_is_off(tmp_path):
    env = {"NOTIFY_SOCKET": str(tmp_path / "n.sock"), "WATCHDOG_USEC": "10000000", "WATCHDOG_PID": "1"}
    assert os.getpid() != 1
    assert Notifier.from_environment(env).watchdog_interval_s is None
    env.update(WATCHDOG_PID="", WATCHDOG_USEC="soon")
    assert Notifier.from_environment(env).watchdog_interval_s is None


def test_sdnotify_send_errors_never_raise(tmp_path):
    n = Notifier(str(tmp_path / "nobody-listens.sock"), 1_000_000)
    assert not n.ready() and not n.maybe_watchdog(0.0) and not n.stopping()
    assert n.send_errors == 3 and n.sent == 0
    assert "nobody-listens.sock" in n.last_error and "\n" not in n.last_error
    n.close()


# --------------------------------------------------------------------------- retention


def test_retention_by_total_size_deletes_the_oldest_closed_captures_and_their_sidecars(tmp_path):
    """``capture_max_gb``: after each file closes, the oldest captures go until the directory's captures
    total at most the limit; what stays is the stream's tail, exactly, and never the file being written."""
    stranger = tmp_path / "notes.bin"  # a file of another name is never touched
    stranger.write_bytes(b"x" * 5000)
    chunks = _chunks(7, 200, 50, 150)  # about 20 kB in files of at most 1000 bytes
    with RotatingCapture(tmp_path, max_bytes=1000, max_total_bytes=3500) as cap:
        for chunk in chunks:
            cap.write(chunk)
            on_disk = sorted(tmp_path.glob("fog-*.bin"))
            closed = [p for p in on_disk if p != cap.current_path]
            assert sum(p.stat().st_size for p in closed) <= 3500
            assert cap.current_path is None or cap.current_path.exists()
    kept = sorted(tmp_path.glob("fog-*.bin"))
    assert cap.pruned and cap.pruned == sorted(cap.pruned) and not set(cap.pruned) & set(kept)
    assert cap.pruned[-1] < kept[0]  # the oldest went first
    assert b"".join(chunks).endswith(_concat(kept))
    assert sum(p.stat().st_size for p in kept) <= 3500
    assert all(not sidecar_path(p).exists() for p in cap.pruned) and all(sidecar_path(p).exists() for p in kept)
    assert stranger.read_bytes() == b"x" * 5000


def test_retention_by_age_at_start_and_never_a_live_recording(tmp_path):
    """``capture_keep_days``: captures whose last byte is older go at start (and as files close), with their
    sidecar of either name; one whose sidecar says another live process is recording it stays, and so does a
    user's file that merely has an old sidecar's name."""
    with RotatingCapture(tmp_path, max_bytes=100) as cap:
        for chunk in (b"a" * 100, b"b" * 100, b"c" * 100, b"d" * 100):
            cap.write(chunk)
    old, old_legacy, live, recent = cap.files
    now = 1_900_000_000.0
    for path, age_days in ((old, 40), (old_legacy, 40), (live, 40), (recent, 10)):
        os.utime(path, (now - age_days * 86400, now - age_days * 86400))
    sidecar_path(old_legacy).rename(legacy_sidecar_path(old_legacy))  # a capture from before X.bin.yaml: X.yaml
    model_like = legacy_sidecar_path(old)
    model_like.write_text("format: fog_driver drift model\n")  # a user's file of the old sidecar's name: not ours
    doc = read_provenance(live)
    doc.update(status="recording", pid=os.getppid())  # another process, alive, still writing it
    rawlog.write_provenance(live, {k: v for k, v in doc.items() if k not in ("format", "schema_version", "capture")})
    cap2 = RotatingCapture(tmp_path, keep_days=30, wall_clock=lambda: now)
    assert cap2.pruned == [old, old_legacy]
    assert not old.exists() and not sidecar_path(old).exists() and model_like.exists()
    assert not old_legacy.exists() and not legacy_sidecar_path(old_legacy).exists()
    assert live.exists() and recent.exists()
    cap2.close()


@pytest.mark.parametrize("kwargs", [{"keep_days": 0}, {"keep_days": -1.0}, {"max_total_bytes": 0}])
def test_retention_limits_must_be_positive(tmp_path, kwargs):
    with pytest.raises(ValueError, match="must be positive"):
        RotatingCapture(tmp_path, **kwargs)


def test_events_past_the_limit_are_summarized_and_the_sidecar_stays_bounded(tmp_path, monkeypatch):
    """A client repeating a command: the first MAX_EVENTS_PER_FILE events are listed, the rest counted per kind
    with their first and last byte, so the sidecar (rewritten at each listed event) stays bounded; a new file
    starts its own list, and events noted before any file opens are bounded the same way."""
    monkeypatch.setattr(rawlog, "MAX_EVENTS_PER_FILE", 5)
    cap = RotatingCapture(tmp_path, max_bytes=1000, clock=FakeClock())
    for _ in range(7):  # before any byte: pending for the first file
        cap.note({"event": "zero"})
    cap.write(b"x" * 10)
    for k in range(20):
        cap.note({"event": "zero" if k % 2 else "bias", "k": k})
        cap.write(b"y")
    size_then = sidecar_path(cap.current_path).stat().st_size
    for _ in range(200):
        cap.note({"event": "zero"})
        cap.write(b"z")
    assert sidecar_path(cap.current_path).stat().st_size == size_then  # past the limit: not rewritten per event
    for _ in range(3):  # lost bytes past the limit keep their total, so the file still says what it misses
        cap.note({"event": "bytes_lost", "bytes": 7})
    first = cap.current_path
    cap.write(b"w" * 1000)  # rotates: the next file lists its own events
    cap.note({"event": "adapt"})
    cap.close()
    doc = read_provenance(first)
    assert [e["event"] for e in doc["events"]] == ["zero"] * 5 and [e["at_byte"] for e in doc["events"]] == [0] * 5
    summary = doc["events_summary"]
    assert summary["zero"] == {"count": 2 + 10 + 200, "first_at_byte": 0, "last_at_byte": 10 + 20 + 199}
    assert summary["bias"] == {"count": 10, "first_at_byte": 10, "last_at_byte": 10 + 18}
    assert summary["bytes_lost"] == {"count": 3, "first_at_byte": 230, "last_at_byte": 230, "bytes": 21}
    later = read_provenance(cap.files[-1])
    assert [e["event"] for e in later["events"]] == ["adapt"] and "events_summary" not in later


def test_kept_models_go_when_no_capture_left_names_them(tmp_path):
    """``keep_model``: each model once, by its SHA-256, its bytes checked; the retention deletes a kept model
    once the captures whose sidecars named it are gone, and keeps the one the captures left still name."""
    import hashlib

    from fog_driver.samples.captures import kept_model_path

    old, new = b"format: old model\n", b"format: new model\n"
    sha_old, sha_new = hashlib.sha256(old).hexdigest(), hashlib.sha256(new).hexdigest()
    with RotatingCapture(tmp_path, max_bytes=1000, max_total_bytes=3500) as cap:
        with pytest.raises(ValueError, match="SHA-256"):
            cap.keep_model(sha_old, new)
        cap.write(b"x" * 100)
        cap.note({"event": "model", "sha256": sha_old})
        assert cap.keep_model(sha_old, old).read_bytes() == old
        assert cap.keep_model(sha_old, old) == kept_model_path(cap.current_path, sha_old)  # once
        cap.write(b"x" * 900)
        cap.note({"event": "model", "sha256": sha_new})
        cap.update_provenance({"model": {"sha256": sha_new}}, current_file=False)  # in every later sidecar
        cap.keep_model(sha_new, new)
        for _ in range(3):
            cap.write(b"y" * 1000)  # the first files go: no sidecar left names the old model
            assert kept_model_path(tmp_path / "f.bin", sha_new).exists()
    assert cap.pruned and not kept_model_path(tmp_path / "f.bin", sha_old).exists()
    assert all(read_provenance(p)["model"]["sha256"] == sha_new for p in tmp_path.glob("fog-*.bin"))
    assert sorted(p.name for p in (tmp_path / "models").glob("*.yaml")) == [f"{sha_new}.yaml"]  # (and the index)


def test_provenance_for_later_files_leaves_the_current_one_as_it_began(tmp_path):
    with RotatingCapture(tmp_path, max_bytes=1000, provenance={"model": {"sha256": "a"}}) as cap:
        cap.write(b"x" * 600)
        cap.update_provenance({"model": {"sha256": "b"}}, current_file=False)
        cap.write(b"x" * 600)
    assert [read_provenance(p)["model"]["sha256"] for p in cap.files] == ["a", "b"]
