"""``fog-driver run`` and the signals a person or systemd sends it at its start and at its stop.

Before: a SIGHUP in the daemon's first half second (imports, the model, the start) killed it by SIGHUP's
default action, with no log line; Ctrl-C twice (or a SIGTERM, then Ctrl-C) while it stopped could end it by
SIGINT halfway through its exit.  Now SIGHUP is deferred from the command's first line (one reload once it
runs), and a stopping daemon leaves every signal to the stop under way (``already_stopping``, said once).

No sleeps: the tests wait on the daemon's lines (its first log line, its readiness line, its status lines);
signals are sent in a loop between two of those, to land in every phase of the start or of the stop.
"""

from __future__ import annotations

import contextlib
import json
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

from fog_driver.protocol import decode_bytes

GUARD_S = 60.0  # hang guards only
BETWEEN_SIGNALS_S = 0.002  # how long each wait on the next line lasts between two signals of a loop


class Daemon:
    """``fog-driver run --simulate`` in ``cwd``, its stdout and stderr read line by line by two threads."""

    def __init__(self, cwd: Path, *args: str) -> None:
        env = {k: v for k, v in os.environ.items() if k != "NOTIFY_SOCKET"}
        command = [sys.executable, "-m", "fog_driver", "run", "--simulate", "--listen", "127.0.0.1:0"]
        self.proc = subprocess.Popen(
            [*command, "--capture-dir", "c", *args],
            cwd=cwd,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
        )
        self.capture_dir = cwd / "c"
        self.ready = threading.Event()
        self.logged = threading.Event()  # the first log line came
        self.err_lines: list[str] = []
        self.status: queue.Queue[dict] = queue.Queue()
        threading.Thread(target=self._read_stdout, daemon=True).start()
        threading.Thread(target=self._read_stderr, daemon=True).start()

    def _read_stdout(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            if "listening on" in line:
                self.ready.set()

    def _read_stderr(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            self.err_lines.append(line)
            self.logged.set()
            if '"event": "status"' in line:
                self.status.put(json.loads(line))

    def sighup_handled(self) -> bool:
        """The process catches SIGHUP (``SigCgt`` of /proc/PID/status): its own handler is in place."""
        try:
            text = Path(f"/proc/{self.proc.pid}/status").read_text()
        except OSError:
            return False
        caught = next(line for line in text.splitlines() if line.startswith("SigCgt:"))
        return bool(int(caught.split()[1], 16) & (1 << (signal.SIGHUP - 1)))

    def events(self, name: str) -> list[dict]:
        return [json.loads(line) for line in self.err_lines if f'"event": "{name}"' in line]

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait(GUARD_S)


def test_a_daemon_sent_sighup_over_and_over_from_its_start_to_its_ready_line_runs_and_stops_with_0(tmp_path):
    daemon = Daemon(tmp_path)
    try:
        sent = 0
        deadline = time.monotonic() + GUARD_S
        # From the moment the process has a SIGHUP handler, or has logged a line (the embedded simulator's,
        # before the model loads): the imports, the simulator, the model, the start.
        while not daemon.ready.is_set() and daemon.proc.poll() is None and time.monotonic() < deadline:
            if daemon.logged.is_set() or daemon.sighup_handled():
                daemon.proc.send_signal(signal.SIGHUP)
                sent += 1
            daemon.ready.wait(BETWEEN_SIGNALS_S)
        assert daemon.ready.is_set(), (daemon.proc.poll(), "".join(daemon.err_lines)[-2000:])
        assert sent > 0
        assert daemon.proc.poll() is None  # it runs
        daemon.proc.send_signal(signal.SIGTERM)
        assert daemon.proc.wait(GUARD_S) == 0
    finally:
        daemon.kill()
    log = "".join(daemon.err_lines)
    assert "Traceback" not in log and "config_reload_failed" not in log
    for deferred in daemon.events("sighup_during_start"):  # the ones that came before its dispatcher: one reload
        assert 1 <= deferred["count"] <= sent


def test_ctrl_c_again_and_again_while_the_daemon_stops_exits_0_with_its_capture_whole(tmp_path):
    (tmp_path / "fog.yaml").write_text("status_every_s: 0.2\n")
    daemon = Daemon(tmp_path, "--config", "fog.yaml")
    try:
        assert daemon.ready.wait(GUARD_S), "".join(daemon.err_lines)[-2000:]
        published = 0
        while published == 0:  # until frames have been read (and so captured)
            published = daemon.status.get(timeout=GUARD_S)["frames"]
        daemon.proc.send_signal(signal.SIGINT)  # Ctrl-C ...
        deadline = time.monotonic() + GUARD_S
        while daemon.proc.poll() is None and time.monotonic() < deadline:  # ... and again, until it has exited
            daemon.proc.send_signal(signal.SIGINT)
            with contextlib.suppress(subprocess.TimeoutExpired):
                daemon.proc.wait(BETWEEN_SIGNALS_S)
        assert daemon.proc.wait(GUARD_S) == 0
    finally:
        daemon.kill()
    log = "".join(daemon.err_lines)
    assert "Traceback" not in log and "KeyboardInterrupt" not in log
    assert len(daemon.events("already_stopping")) <= 1  # said once at most (later ones find it exiting)
    captured = b"".join(path.read_bytes() for path in sorted(daemon.capture_dir.glob("*.bin")))
    decoded = decode_bytes(captured)
    counters = decoded.counters
    assert counters.crc_errors == 0 and counters.length_errors == 0 and counters.truncated_frames == 0
    assert counters.bytes_discarded == 0  # every byte in a whole frame: none lost, none cut off at the end
    assert len(decoded.samples) >= published  # at least every frame the daemon had published
