"""Loopback hardware-in-the-loop: the whole daemon as a process, fed through a real pty or replay://.

Readiness comes from the daemon's "listening on HOST:PORT" line on its stdout and from the
DEVICE object saying the port is activated: never from sleeps.
"""

from __future__ import annotations

import json
import math
import os
import re
import signal
import socket
import subprocess
import sys

import golden
import pytest
from daemon_hil import DATA, GUARD_S, Client, Daemon, offline_angles

from fog_driver.protocol import decode_bytes, decode_file
from fog_driver.tools.watch import parse_address
from fog_driver.transport import PtyPair

pytestmark = pytest.mark.serial  # pty timing and signals: run apart from the suite's parallel part

GOLDEN = DATA / "golden" / "sim-faults.watch-1hz.ndjson"
#: ANGLE's ``utc``: ISO 8601 UTC to the millisecond.
UTC_RE = re.compile(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}Z")


def without_utc(raw: bytes) -> str:
    """An ANGLE line without its ``utc`` (host time, which no replay reproduces), checked to be there."""
    obj = json.loads(raw)
    assert UTC_RE.fullmatch(obj.pop("utc")), raw
    return json.dumps(obj)


@pytest.mark.determinism
def test_pty_daemon_publishes_every_sample_and_replays_bit_identically(tmp_path):
    data = (DATA / "sim-faults.bin").read_bytes()
    n_samples = decode_bytes(data).counters.sample_frames
    with PtyPair() as pty:
        daemon = Daemon(tmp_path, pty.slave_path)
        try:
            client = Client(daemon.address)
            assert client.next()["class"] == "VERSION"
            client.send('?WATCH={"enable":true};')
            assert client.next("WATCH")["enable"] is True
            slow = Client(daemon.address)  # a station that wants 1 Hz: compared with the golden file
            slow.send('?WATCH={"enable":true,"rate_hz":1};')
            slow.next("WATCH")
            client.wait_device("activated")  # the port is open: no byte can be flushed away now
            pty.write(data)
            received = [client.next("ANGLE") for _ in range(n_samples)]
            n_golden = len(golden.read_golden_lines(GOLDEN))
            got = []
            while len(got) < n_golden:
                raw = slow.file.readline()
                if raw.startswith(b'{"class":"ANGLE"'):
                    got.append(raw)
            # Within the stated tolerance on any machine; regenerate only on purpose (tests/data/make_goldens.py).
            # ``utc`` is the host's clock when the sample was read: the one key a replay cannot reproduce, so it
            # is checked for its form and left out of the comparison explicitly.
            golden.assert_matches_ndjson([without_utc(raw) for raw in got], GOLDEN)
            assert all(UTC_RE.fullmatch(o["utc"]) for o in received)
            # Bad and oversized commands are answered, and never stop the stream.
            client.send("?NOPE;")
            assert client.next("ERROR")["message"]
            client.send("?WATCH={not json};")
            assert client.next("ERROR")
            client.send("?" + "A" * 10000 + ";")
            assert client.next("ERROR")
            status = client.next("STATUS")
            assert status["frames"] == n_samples and status["clients"] >= 1
            assert daemon.terminate() == 0  # SIGTERM: flush, exit 0
        finally:
            daemon.kill()
    # Nothing lost: the raw capture is every byte written.
    assert daemon.raw_capture() == data
    # Replay determinism: the published angles equal `compensate` on the daemon's own capture.
    offline = offline_angles(daemon.raw_capture(), tmp_path)
    assert [o["angle_arcsec"] for o in received] == [offline[o["seq"]] for o in received]
    assert any("gap" in o["flags"] for o in received)


def test_unplug_and_replug_through_a_stable_link(tmp_path):
    data = (DATA / "sim-short.bin").read_bytes()
    half = len(data) // 2
    first_half, second_half = decode_bytes(data[:half], final=False), decode_bytes(data[half:])
    link = tmp_path / "ttyFOG0"
    pty = PtyPair()
    pty.symlink(link)
    daemon = Daemon(tmp_path, str(link))
    try:
        client = Client(daemon.address)
        client.send('?WATCH={"enable":true};')
        client.wait_device("activated")
        pty.write(data[:half])
        last = [client.next("ANGLE") for _ in range(first_half.counters.sample_frames)][-1]
        pty.unplug()
        client.wait_device("deactivated")
        pty.close()
        pty = PtyPair()  # the adapter comes back (a new /dev/pts, the same link)
        pty.symlink(link)
        client.wait_device("activated")  # reconnected (backoff <= 1 s)
        pty.write(data[half:])
        after = client.next("ANGLE")
        # The angle carries on from the last frame received; the lost bytes are a flagged gap.
        assert after["seq"] > last["seq"]
        assert abs(after["angle_arcsec"] - last["angle_arcsec"]) < 50.0
        assert second_half.counters.sample_frames > 0
        assert daemon.terminate() == 0
    finally:
        pty.close()
        daemon.kill()


def test_stalled_client_is_dropped_and_the_live_one_gets_everything(tmp_path):
    data = (DATA / "sim-short.bin").read_bytes()
    n_samples = decode_bytes(data).counters.sample_frames
    with PtyPair() as pty:
        daemon = Daemon(tmp_path, pty.slave_path)
        try:
            stalled = socket.socket()
            stalled.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
            stalled.connect(daemon.address)
            stalled.sendall(b'?WATCH={"enable":true};\n')  # ...and never reads
            live = Client(daemon.address)
            live.send('?WATCH={"enable":true};')
            live.wait_device("activated")
            pty.write(data)
            seqs = [live.next("ANGLE")["seq"] for _ in range(n_samples)]
            assert seqs == list(range(seqs[0], seqs[0] + n_samples))
            while live.next("STATUS").get("dropped_clients", 0) < 1:  # dropped within max backlog age
                pass
            assert daemon.terminate() == 0
        finally:
            daemon.kill()


def test_sigkill_leaves_a_decodable_capture(tmp_path):
    data = (DATA / "sim-short.bin").read_bytes()
    with PtyPair() as pty:
        daemon = Daemon(tmp_path, pty.slave_path)
        try:
            client = Client(daemon.address)
            client.wait_device("activated")
            pty.write(data[:20000])
            while client.next("STATUS").get("capture_bytes", 0) < 20000:  # written (unbuffered) by the capture thread
                pass
            os.kill(daemon.proc.pid, signal.SIGKILL)
            daemon.proc.wait(GUARD_S)
        finally:
            daemon.kill()
    files = sorted(daemon.capture_dir.glob("*.bin"))
    on_disk = files[0].read_bytes()
    assert on_disk == data[:20000]  # everything written, byte for byte: nothing waits in a buffer
    assert decode_file(files[0]).counters.sample_frames == decode_bytes(data[:20000]).counters.sample_frames


def test_an_ipv6_listener_is_announced_in_brackets(tmp_path):
    # before: "listening on ::1:PORT ... fog-driver watch ::1:PORT", which reads back as host "::1:PORT"
    daemon = Daemon(tmp_path, f"replay://{DATA / 'sim-short.bin'}?rate=100", "--listen", "[::1]:0")
    try:
        announced = daemon.readiness.split("listening on ")[1].split(";")[0]
        hint = daemon.readiness.split("fog-driver watch ")[1].split()[0]
        assert hint == announced == f"[::1]:{daemon.address[1]}"
        client = Client(parse_address(hint))
        assert client.next()["class"] == "VERSION"
        client.close()
    finally:
        assert daemon.terminate() == 0


def test_replay_url_into_the_daemon(tmp_path):
    capture = DATA / "sim-short.bin"
    daemon = Daemon(tmp_path, f"replay://{capture}?rate=2000")
    try:
        client = Client(daemon.address)
        client.send('?WATCH={"enable":true,"rate_hz":1};')
        angles = [client.next("ANGLE") for _ in range(3)]
        # Decimated to 1 Hz by device time: one line per 1-s period, consecutive periods (the first one may come
        # from anywhere in its period: the watch starts while the replay runs).
        periods = [math.floor(a["t_s"]) for a in angles]
        assert periods == [periods[0], periods[0] + 1, periods[0] + 2], [a["t_s"] for a in angles]
        assert daemon.terminate() == 0
    finally:
        daemon.kill()


@pytest.mark.parametrize(
    "args, needle",
    [
        (["--model", "/nonexistent/model.yaml"], "no such model file"),
        (["--listen", "10.1.2.3:2948"], "token"),
        (["--port", "nosuch://device"], "nosuch"),
        (["--config", "http_trusted_proxies: [proxy.lab]\n"], "http_trusted_proxies: 'proxy.lab' is not an IP"),
    ],
)
def test_bad_config_exits_78_with_one_line(tmp_path, args, needle):
    port = [] if "--port" in args else ["--port", "replay:///nonexistent.bin"]
    if args[0] == "--config":  # a config file of this text
        (tmp_path / "bad.yaml").write_text(args[1])
        args = ["--config", str(tmp_path / "bad.yaml")]
    proc = subprocess.run(
        [sys.executable, "-m", "fog_driver", "run", *port, "--capture-dir", str(tmp_path / "c"), *args],
        capture_output=True,
        text=True,
        timeout=60,
        stdin=subprocess.DEVNULL,
    )
    assert proc.returncode == 78, proc.stderr
    assert needle in proc.stderr and "Traceback" not in proc.stderr
    assert len([line for line in proc.stderr.splitlines() if line.startswith("fog-driver: error:")]) == 1


def test_sighup_reloads_the_config_and_the_model(tmp_path):
    from fog_driver.compensation.fitting.data import FitConfig
    from fog_driver.modelfiles import save_model
    from fog_driver.offline.fit import fit_model_file

    model_file, _ = fit_model_file(
        [DATA / "sim-short.bin"], kind="polynomial", config=FitConfig(warmup_s=30.0), accept_weak=True
    )
    poly = save_model(tmp_path / "poly.yaml", model_file)
    config = tmp_path / "fog.yaml"
    config.write_text("status_every_s: 1.0\n")
    daemon = Daemon(tmp_path, f"replay://{DATA / 'sim-short.bin'}?rate=100", "--config", str(config))
    try:
        client = Client(daemon.address)
        assert client.next("VERSION")["model"] == "wesn"
        config.write_text(f"model: {poly}\n")
        daemon.proc.send_signal(signal.SIGHUP)
        model = None
        for _ in range(10000):  # each answer comes after the previous one: a bounded poll, no sleep
            client.send("?VERSION;")
            model = client.next("VERSION")["model"]
            if model == "polynomial":
                break
        assert model == "polynomial"
        assert daemon.proc.poll() is None  # still running
        assert daemon.terminate() == 0
    finally:
        daemon.kill()


def test_a_burst_of_sighups_then_sigterm_ends_cleanly(tmp_path):
    """Reloads run one after another in the signal dispatcher, never inside a handler (where a second
    SIGHUP once re-entered the reload under its own lock and hung the daemon for good)."""
    config = tmp_path / "fog.yaml"
    config.write_text("status_every_s: 0.2\n")
    daemon = Daemon(tmp_path, f"replay://{DATA / 'sim-short.bin'}?rate=100", "--config", str(config))
    try:
        client = Client(daemon.address)
        client.next("STATUS")
        for _ in range(20):
            daemon.proc.send_signal(signal.SIGHUP)
        client.send("?VERSION;")
        assert client.next("VERSION")["model"] == "wesn"  # the hub answers
        client.next("STATUS")  # and the status loop goes on
        assert daemon.terminate() == 0
    finally:
        daemon.kill()
    assert "config_reload_failed" not in daemon.log_path.read_text()
