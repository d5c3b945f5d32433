"""``fog-driver run`` as a person at a terminal meets it, and as systemd starts it: a missing port is said at
once at a terminal (``--wait`` waits) and waited for under systemd; the web extra is checked before any work;
the demonstration does not warn about its own simulator."""

from __future__ import annotations

import contextlib
import os
import secrets
import signal
import socket
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

GUARD_S = 60.0


def _run(*args: str) -> list[str]:
    return [sys.executable, "-m", "fog_driver", "run", "--listen", "127.0.0.1:0", "--capture-dir", "c", *args]


def _environment(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k != "NOTIFY_SOCKET"}
    return {**env, **extra}


@contextlib.contextmanager
def _terminal() -> Iterator[int]:
    """A pty's far end, to give a command as its stdin: what a person at a terminal gives it."""
    mine, theirs = os.openpty()
    try:
        yield theirs
    finally:
        os.close(mine)
        os.close(theirs)


@contextlib.contextmanager
def _started(command: list[str], *, cwd: Path, stdin: int, env: dict[str, str]) -> Iterator[subprocess.Popen]:
    proc = subprocess.Popen(
        command, cwd=cwd, stdin=stdin, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env
    )
    try:
        yield proc
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.communicate(timeout=GUARD_S)


def _ready_then_terminated(proc: subprocess.Popen) -> None:
    """The readiness line comes (the daemon waits for its port, serving its clients), then SIGTERM: exit 0."""
    line = proc.stdout.readline()
    assert "listening on" in line, (line, proc.stderr.read() if proc.poll() is not None else "")
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(GUARD_S) == 0


def _run_at_a_terminal(cwd: Path, *args: str) -> subprocess.CompletedProcess[str]:
    """``fog-driver run ARGS`` to its end, its stdin a terminal (as a user types it)."""
    with _terminal() as stdin:
        return subprocess.run(
            _run(*args), cwd=cwd, stdin=stdin, capture_output=True, text=True, env=_environment(), timeout=GUARD_S
        )


def test_at_a_terminal_a_missing_port_is_an_error_at_once(tmp_path):
    """Before: at a terminal, ``run --port /dev/ttyUSB9`` (a typo, an adapter not plugged in) printed its
    readiness line and retried for ever, a warning every 2 s; ``record`` says so at once (exit 69)."""
    port = tmp_path / "ttyUSB9"
    proc = _run_at_a_terminal(tmp_path, "--port", str(port))
    assert proc.returncode == 69, proc.stderr
    assert proc.stdout == ""
    assert proc.stderr.splitlines() == [f"fog-driver: error: cannot open {port}: no such device (--wait waits for it)"]
    assert not (tmp_path / "c").exists()  # nothing started, nothing written


@pytest.mark.parametrize("what", ["/dev/null", "a regular file", "a directory"])
@pytest.mark.parametrize("wait", [False, True])
def test_run_port_dev_null_at_a_terminal_is_an_error_at_once(tmp_path, what, wait):
    """The review's finding 11: ``run --port /dev/null`` at a terminal retried for ever with "(25,
    'Inappropriate ioctl for device')".  A path that is there but is no serial device: one line, exit 69, at
    once, even with --wait (waiting cannot make it one)."""
    kinds = {
        "/dev/null": "a character device that is not a terminal",
        "a regular file": "a regular file",
        "a directory": "a directory",
    }
    port = Path("/dev/null") if what == "/dev/null" else tmp_path / "ttyUSB0"
    if what == "a regular file":
        port.write_bytes(b"\xaa\x55" * 100)
    elif what == "a directory":
        port.mkdir()
    proc = _run_at_a_terminal(tmp_path, "--port", str(port), *(["--wait"] if wait else []))
    assert proc.returncode == 69, proc.stderr
    assert proc.stdout == ""
    assert proc.stderr.splitlines() == [f"fog-driver: error: cannot open {port}: {kinds[what]}, not a serial device"]
    assert not (tmp_path / "c").exists()


def test_at_a_terminal_a_pty_is_a_serial_device(tmp_path):
    """The tests and ``--simulate`` serve on ptys: at a terminal a pty's path is taken as a port."""
    from fog_driver.transport import PtyPair

    with (
        PtyPair() as pty,
        _terminal() as stdin,
        _started(_run("--port", pty.slave_path), cwd=tmp_path, stdin=stdin, env=_environment()) as proc,
    ):
        _ready_then_terminated(proc)


def test_at_a_terminal_wait_waits_for_the_port_and_says_so_once(tmp_path):
    port = tmp_path / "ttyUSB9"
    with (
        _terminal() as stdin,
        _started(_run("--port", str(port), "--wait"), cwd=tmp_path, stdin=stdin, env=_environment()) as proc,
    ):
        assert proc.stderr.readline() == f"waiting for {port} (now: no such device); Ctrl-C to stop\n"
        _ready_then_terminated(proc)


@pytest.mark.parametrize("how", ["stdin-not-a-terminal", "notify-socket"])
def test_under_systemd_the_daemon_waits_for_its_port_without_being_asked(tmp_path, how):
    """systemd gives no terminal (or, with StandardInput=tty, sets NOTIFY_SOCKET): a device that appears
    late (a USB adapter enumerated after the service started) is waited for, as before."""
    port = tmp_path / "ttyUSB9"
    with contextlib.ExitStack() as stack:
        env = _environment()
        stdin = subprocess.DEVNULL
        if how == "notify-socket":
            stdin = stack.enter_context(_terminal())
            notify = stack.enter_context(socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM))
            address = f"@fog-driver-test-{secrets.token_hex(8)}"
            notify.bind("\0" + address[1:])
            env["NOTIFY_SOCKET"] = address
        proc = stack.enter_context(_started(_run("--port", str(port)), cwd=tmp_path, stdin=stdin, env=env))
        _ready_then_terminated(proc)
        if how == "notify-socket":
            notify.settimeout(GUARD_S)
            assert notify.recv(4096).startswith(b"READY=1")  # systemd was told the service is up


def test_run_http_without_the_web_extra_is_refused_before_any_work(tmp_path, monkeypatch, capsys):
    """Before: the demonstration's simulator started, then the web view found aiohttp missing."""
    from fog_driver.cli import app, daemon

    def no_simulator(stop: threading.Event):
        raise AssertionError("the simulator started before the extra was checked")

    monkeypatch.setattr(daemon, "_start_embedded_simulator", no_simulator)
    monkeypatch.setitem(sys.modules, "aiohttp", None)  # not installed, whatever this process imported
    status = app.main(
        ["run", "--simulate", "--http", "127.0.0.1:0", "--listen", "127.0.0.1:0", "--capture-dir", str(tmp_path / "c")]
    )
    assert status == 64  # a missing extra, as for every command (was 78)
    assert capsys.readouterr().err == (
        "fog-driver: error: the web view and /metrics (http 127.0.0.1:0) needs aiohttp (the 'web' extra); "
        "in the project's virtual environment: pip install -e '.[web]'\n"
    )
    assert not (tmp_path / "c").exists()


def test_the_demonstration_does_not_warn_about_its_own_simulator(monkeypatch):
    """Before: ``run`` with no arguments printed ``serve_behind`` warnings whenever its in-process simulator
    fell behind (the model loading, a busy machine): news about the demonstration, not the instrument."""
    from fog_driver.cli import daemon

    seen = {}

    class Server:
        slave_path = "/dev/pts/test"

    def serve_pty(sim, **kwargs):
        seen.update(kwargs)
        kwargs["on_ready"](Server())

    monkeypatch.setattr(daemon, "serve_pty", serve_pty)
    stop = threading.Event()
    thread, path = daemon._start_embedded_simulator(stop)
    thread.join(GUARD_S)
    assert path == "/dev/pts/test" and seen["warn_behind"] is False


def test_the_demonstrations_log_names_the_pty_it_reads_and_no_link():
    """Before: ``run --simulate -v`` logged ``pty_ready link=/tmp/fog-driver-sim.tty``, a name nobody reads (the
    daemon reads the pty itself) and that another simulator may hold; now the pty's own path, and no link."""
    from structlog.testing import capture_logs

    from fog_driver.cli import daemon

    stop = threading.Event()
    with capture_logs() as logs:
        thread, path = daemon._start_embedded_simulator(stop)
        stop.set()
        thread.join(GUARD_S)
    ready = [entry for entry in logs if entry["event"] == "pty_ready"]
    assert ready == [{"event": "pty_ready", "log_level": "info", "slave": path}]
    assert path.startswith("/dev/pts/")
