"""The daemon under faults, as a process: a full disk, an instrument that changes or lies, signal bursts
during reloads and rotations, a port lost during a reload, a client that leaves mid-command.

For each: a well-behaved watcher keeps receiving every sample (its largest gap in device time is
asserted against the frame period, never a wall-clock timing), and SIGTERM still exits 0 with the
capture intact.  Readiness from the daemon's own lines, never sleeps (see test_daemon_hil)."""

from __future__ import annotations

import hashlib
import resource
import signal
import time
from pathlib import Path

import pytest
import structlog
from daemon_hil import (
    N_SHORT,
    SHORT,
    Client,
    Daemon,
    next_status,
    offline_angles,
    start_watching,
    watch_all,
    watched_daemon,
)
from framegen import with_identities

from fog_driver.protocol import decode_bytes
from fog_driver.samples.captures import read_provenance
from fog_driver.transport import PtyPair


def test_a_full_disk_degrades_the_capture_and_never_the_live_angle(tmp_path):
    """The review's E7: RLIMIT_FSIZE (CPython ignores SIGXFSZ, so writes fail as on a full disk) made the
    daemon stop publishing and exit 73, and the failed sidecar over-stated the bytes on disk."""
    limit = 40_000

    def small_files() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    with watched_daemon(tmp_path, preexec=small_files) as (pty, daemon, client):
        first = 50_000
        pty.write(SHORT[:first])  # the file fills at 40 kB: the capture fails...
        angles = watch_all(client, decode_bytes(SHORT[:first], final=False).counters.sample_frames)
        status = next_status(client, lambda s: s["capture_state"] != "recording", "the capture failed")
        assert status["capture_state"] in ("failed", "retrying") and "File too large" in status["capture_error"]
        # ...and tries a new file after its backoff (1 s)
        next_status(client, lambda s: s["capture_state"] == "retrying", "the capture retrying")
        pty.write(SHORT[first:])
        angles += watch_all(client, N_SHORT - len(angles))  # the live angle never stopped
        assert angles[-1]["seq"] == angles[0]["seq"] + N_SHORT - 1
        status = next_status(
            client,
            lambda s: s["capture_bytes"] + s["capture_bytes_lost"] >= len(SHORT),
            "every byte captured or counted lost",
        )
        assert status["capture_state"] == "recording" and status["capture_bytes_lost"] > 0
        assert daemon.proc.poll() is None
        assert daemon.terminate() == 0
    files = sorted(daemon.capture_dir.glob("*.bin"))
    assert len(files) >= 2
    captured = 0
    for path in files:
        side, data = read_provenance(path), path.read_bytes()
        assert side["bytes"] == len(data) and side["sha256"] == hashlib.sha256(data).hexdigest()  # true to the disk
        captured += len(data)
    assert captured + status["capture_bytes_lost"] == len(SHORT)
    assert any(e["event"] == "bytes_lost" for p in files for e in read_provenance(p).get("events", []))


def test_an_instrument_that_changes_rate_mid_run_rebuilds_and_live_equals_offline(tmp_path):
    data = with_identities(SHORT, len(SHORT) // 2, rate_hz=20)
    with watched_daemon(tmp_path) as (pty, daemon, client):
        pty.write(data)
        angles = watch_all(client, N_SHORT)
        client.send("?VERSION;")
        assert client.next("VERSION")["instrument"]["rate_hz"] == 20  # the change was taken...
        next_status(client, lambda s: s["instrument_changes"] == 1, "the change counted")  # ...counted...
        assert daemon.terminate() == 0
    events = [e for p in sorted(daemon.capture_dir.glob("*.bin")) for e in read_provenance(p).get("events", [])]
    assert [e["event"] for e in events if e["event"] == "instrument_changed"] == ["instrument_changed"]  # ...recorded
    offline = offline_angles(daemon.raw_capture(), tmp_path)
    assert {a["seq"]: a["angle_arcsec"] for a in angles} == offline


@pytest.mark.parametrize("fields", [{"rate_hz": 0}, {"scale_arcsec_per_count": float("nan")}])
def test_an_identity_with_a_zero_rate_or_a_nan_scale_is_ignored(tmp_path, fields):
    """Rate 0 crashed the daemon in a restart loop; a NaN scale removed angle_arcsec for good."""
    data = with_identities(SHORT, len(SHORT) // 3, **fields)
    with watched_daemon(tmp_path) as (pty, daemon, client):
        pty.write(data)
        angles = watch_all(client, N_SHORT)
        assert all("angle_arcsec" in a for a in angles)
        assert client.next("STATUS")["identities_rejected"] > 0
        assert daemon.terminate() == 0


def test_a_model_for_another_instrument_stops_the_daemon_with_exit_78_and_one_line(tmp_path):
    data = with_identities(SHORT, 0, serial="FOG-OTHER-9999")
    with PtyPair() as pty:
        daemon = Daemon(tmp_path, pty.slave_path)
        try:
            client = Client(daemon.address)
            client.wait_device("activated")
            pty.write(data[:5000])
            assert daemon.wait() == 78
        finally:
            daemon.kill()
    log = daemon.log_path.read_text()
    assert "FOG-OTHER-9999" in log and "force_model" in log and "Traceback" not in log


def test_signal_bursts_during_reloads_and_rotations_lose_nothing(tmp_path):
    config = tmp_path / "fog.yaml"
    config.write_text("status_every_s: 0.2\ncapture_rotate_s: 0.3\ncapture_rotate_mb: 0.01\n")  # files of 10 kB
    with watched_daemon(tmp_path, "--config", str(config)) as (pty, daemon, client):
        step = len(SHORT) // 8
        received: list[dict] = []
        for k in range(8):
            chunk = SHORT[k * step : (k + 1) * step if k < 7 else len(SHORT)]
            pty.write(chunk)
            for _ in range(5):
                daemon.proc.send_signal(signal.SIGHUP)
            # the samples this chunk completes (the capture rotates every 10 kB, and every 0.3 s)
            done = decode_bytes(SHORT[: k * step + len(chunk)], final=False).counters.sample_frames
            received += watch_all(client, done - len(received))
        assert [a["seq"] for a in received] == list(range(received[0]["seq"], received[0]["seq"] + N_SHORT))
        client.send("?VERSION;")
        assert client.next("VERSION")["model"] == "wesn"
        assert daemon.terminate() == 0
    assert daemon.raw_capture() == SHORT  # every byte, in name order, across every rotation
    assert len(sorted(daemon.capture_dir.glob("*.bin"))) >= 2
    assert len(received) == N_SHORT and "Traceback" not in daemon.log_path.read_text()


def test_a_port_lost_during_a_reload_comes_back_and_the_stream_continues(tmp_path):
    link = tmp_path / "ttyFOG0"
    pty = PtyPair()
    pty.symlink(link)
    daemon = Daemon(tmp_path, str(link))
    try:
        client = start_watching(daemon)
        half = len(SHORT) // 2
        pty.write(SHORT[:half])
        last = watch_all(client, decode_bytes(SHORT[:half], final=False).counters.sample_frames)[-1]
        control = Client(daemon.address)
        control.send("?RELOAD;")
        pty.unplug()
        assert control.next("RELOAD")["changed"] is False  # the same model: nothing to change
        client.wait_device("deactivated")
        pty.close()
        pty = PtyPair()
        pty.symlink(link)
        client.wait_device("activated")
        pty.write(SHORT[half:])
        after = client.next("ANGLE")
        assert after["seq"] == last["seq"] + 1  # nothing written was lost: the frame cut by the unplug completes
        assert daemon.terminate() == 0
    finally:
        pty.close()
        daemon.kill()


def test_a_client_that_asks_for_a_bias_and_hangs_up_does_not_stop_the_daemon(tmp_path):
    """The review's E1: the daemon exited 1 when the capture completed."""
    with watched_daemon(tmp_path) as (pty, daemon, client):
        pty.write(SHORT[:20000])
        watch_all(client, decode_bytes(SHORT[:20000], final=False).counters.sample_frames)
        one_shot = Client(daemon.address)
        one_shot.send('?BIAS={"seconds":3};')
        assert one_shot.next("BIAS")["state"] == "started"  # acknowledged at once
        one_shot.close()  # hangs up before the result...
        next_status(client, lambda s: s["clients"] == 1, "the hang-up noticed")  # ...and the hub notices
        pty.write(SHORT[20000:])  # then the capture completes
        left, events = N_SHORT - decode_bytes(SHORT[:20000], final=False).counters.sample_frames, []
        while left:
            obj = client.next()
            left -= obj["class"] == "ANGLE"
            events += [obj] if obj["class"] == "BIAS" else []
        assert [e["state"] for e in events] == ["done"]  # the result goes to whoever is connected
        status = next_status(client, lambda s: s["bias_dph"] != 0.0, "the bias applied")
        assert abs(status["bias_dph"] - 10.0) < 5.0  # applied: Earth rate and bias at rest
        assert daemon.proc.poll() is None
        assert daemon.terminate() == 0
    assert "acquisition_crashed" not in Path(daemon.log_path).read_text()


def test_the_watchdog_follows_watchdog_usec_not_the_status_period(tmp_path, monkeypatch):
    """The review's E11: pings came once per status period (3 s) against a 2 s watchdog, and systemd killed
    a healthy daemon.  With a status period of 60 s, two pings must come before the first STATUS= line."""
    import socket
    import tempfile

    notify_dir = Path(tempfile.mkdtemp(prefix="fog-wd-"))  # short: an AF_UNIX path has at most 107 bytes
    notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    notify.bind(str(notify_dir / "n"))
    notify.settimeout(30.0)
    config = tmp_path / "fog.yaml"
    config.write_text("status_every_s: 60\n")
    monkeypatch.setenv("NOTIFY_SOCKET", str(notify_dir / "n"))
    monkeypatch.setenv("WATCHDOG_USEC", "2000000")
    monkeypatch.delenv("WATCHDOG_PID", raising=False)
    try:
        with watched_daemon(tmp_path, "--config", str(config)) as (_, daemon, _client):
            messages = []
            while messages.count("WATCHDOG=1") < 2:
                messages.append(notify.recv(4096).decode())
            assert not any(m.startswith("STATUS=") and "frames" in m for m in messages), messages
            assert daemon.terminate() == 0
    finally:
        notify.close()


def test_the_watchdog_is_not_pinged_when_the_reader_or_the_hub_is_stuck():
    from fog_driver.daemon.config import DriverConfig
    from fog_driver.daemon.limits import READER_STALL_S
    from fog_driver.daemon.service import Service

    class Alive:
        running = True

        def is_alive(self):
            return True

    class Reader:
        last_activity_monotonic = 0.0

    service = Service(DriverConfig(), port="unused")
    service._acquisition, service.hub, service.reader = Alive(), Alive(), Reader()
    service.reader.last_activity_monotonic = time.monotonic()
    assert service._making_progress()
    service.reader.last_activity_monotonic = time.monotonic() - READER_STALL_S - 1  # a reader stuck in a read
    assert not service._making_progress()
    service.reader.last_activity_monotonic = time.monotonic()
    service.hub.running = False  # the hub's thread died
    assert not service._making_progress()


def test_a_daemon_started_with_a_12_character_token_warns_of_the_16_character_minimum(log_events_here):
    """A 12-character token was taken silently; the minimum is now 16 (shorter ones accepted this release)."""
    from fog_driver.daemon.config import TOKEN_MIN_CHARS, DriverConfig
    from fog_driver.daemon.service import Service

    Service(DriverConfig(token="twelve-chars"), port="unused")
    Service(DriverConfig(token="sixteen-chars-ok"), port="unused")
    warned = [e for e in log_events_here if e["event"] == "token_too_short"]
    assert len(warned) == 1 and f"minimum is now {TOKEN_MIN_CHARS}" in warned[0]["message"]
    assert f"has {len('twelve-chars')} characters" in warned[0]["message"]


@pytest.fixture
def log_events_here():
    events: list[dict] = []

    def keep(_logger, _name, event_dict):
        events.append(dict(event_dict))
        raise structlog.DropEvent

    structlog.configure(processors=[keep])
    return events  # conftest resets structlog after the test
