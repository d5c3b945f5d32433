"""The simulator's stable link: ``run --simulate`` makes none, ``simulate --serve pty`` makes its own and refuses
a path in its way.

Before: ``run --simulate`` beside a ``simulate --serve pty`` re-pointed that command's link at its own pty and
removed it when it stopped; a regular file at the default path stopped the daemon with exit 1 and a thread's
traceback; ``simulate --serve pty`` replaced a symlink to anything, another simulator's live pty included.
Every link here is in ``tmp_path`` (``--link``): the default ``/tmp/fog-driver-sim.tty`` is left to the people
using the machine.  No sleeps: each test waits on a readiness line, and the daemon's simulator on its pty.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

import pytest
from sim_serving import GUARD_S, REPO, SHORT_TEST, _next_line, _start_cli

from fog_driver.transport import PtyPair

LINK_CALLS = ("symlink", "replace", "rename", "unlink", "remove")


def _refuse_link_calls(monkeypatch: pytest.MonkeyPatch) -> list[tuple[str, tuple]]:
    """Record (and refuse, so that nothing is touched) every call that makes, re-points or removes a path."""
    calls: list[tuple[str, tuple]] = []

    def refused(name: str):
        def call(*args, **kwargs):
            calls.append((name, args))
            raise PermissionError(f"the test refuses os.{name}{args}")

        return call

    for name in LINK_CALLS:
        monkeypatch.setattr(os, name, refused(name))
    return calls


def _embedded_simulator_runs(monkeypatch: pytest.MonkeyPatch) -> tuple[str, list[tuple[str, tuple]]]:
    """``run --simulate``'s simulator started and stopped, every path call refused: its pty's path, the calls."""
    from fog_driver.cli import daemon

    calls = _refuse_link_calls(monkeypatch)
    stop = threading.Event()
    try:
        thread, pty_path = daemon._start_embedded_simulator(stop)
    finally:
        stop.set()
    thread.join(GUARD_S)
    monkeypatch.undo()
    return pty_path, calls


def test_run_simulate_beside_simulate_serve_pty_leaves_its_link_alone(tmp_path: Path, monkeypatch) -> None:
    link = tmp_path / "fog-driver-sim.tty"
    proc, lines = _start_cli("--rate-hz", "10", link=link)
    try:
        served = _next_line(proc, lines).split(" on ", 1)[1].split(" (link ", 1)[0]
        assert os.readlink(link) == served
        pty_path, calls = _embedded_simulator_runs(monkeypatch)
        assert calls == []  # no link made, re-pointed or removed, anywhere
        assert pty_path.startswith("/dev/pts/") and pty_path != served
        assert os.readlink(link) == served  # the simulate command's link, after the daemon's simulator stopped
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(GUARD_S) == 0, proc.stderr.read()
    finally:
        if proc.poll() is None:
            proc.kill()
    assert not link.is_symlink()  # removed by the command that made it


def test_run_simulate_with_a_regular_file_at_the_default_link_path_starts_and_leaves_the_file(
    tmp_path: Path, monkeypatch
) -> None:
    from fog_driver.sim import serve

    default = tmp_path / "fog-driver-sim.tty"
    default.write_text("precious")
    monkeypatch.setattr(serve, "DEFAULT_LINK", str(default))  # where simulate --serve pty's link would be
    pty_path, calls = _embedded_simulator_runs(monkeypatch)
    assert pty_path.startswith("/dev/pts/") and calls == []
    assert default.read_text() == "precious"


def _simulate_serve_pty(link: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "fog_driver", "simulate", "--serve", "pty", "--link", str(link)]
        + ["--profile", str(SHORT_TEST), "--rate-hz", "10", "--duration", "1"],
        cwd=REPO,
        capture_output=True,
        text=True,
        stdin=subprocess.DEVNULL,
        timeout=GUARD_S,
    )


@pytest.mark.parametrize("in_the_way", ["a regular file", "a directory", "another simulator's link", "a device's link"])
def test_simulate_serve_pty_with_a_path_in_the_way_of_its_link_says_so_and_exits_73(
    tmp_path: Path, in_the_way: str
) -> None:
    link = tmp_path / "ttyFOG0"
    other = PtyPair()  # a pty another simulator serves
    try:
        if in_the_way == "a regular file":
            link.write_text("precious")
            what = "a regular file"
        elif in_the_way == "a directory":
            link.mkdir()
            what = "a directory"
        else:
            target = other.slave_path if in_the_way == "another simulator's link" else "/dev/null"
            link.symlink_to(target)
            what = f"a symlink to {target}, which exists (another simulator's pty?)"
        proc = _simulate_serve_pty(link)
        assert proc.returncode == 73, proc.stderr
        assert proc.stdout == ""  # no readiness line
        assert proc.stderr.splitlines() == [
            f"fog-driver: error: --link {link}: the path is {what}, not a link of ours; "
            "remove it or give another --link PATH (nothing was replaced)"
        ]
        if in_the_way == "a regular file":
            assert link.read_text() == "precious"
        elif in_the_way == "a directory":
            assert link.is_dir() and not link.is_symlink()
        else:
            assert os.readlink(link) == target
    finally:
        other.close()


def test_simulate_serve_pty_stopped_leaves_a_link_someone_re_pointed(tmp_path: Path) -> None:
    """It removes only the link it made, and only while it still points at its pty."""
    link = tmp_path / "ttyFOG0"
    other = PtyPair()
    proc, lines = _start_cli("--rate-hz", "10", link=link)
    try:
        served = _next_line(proc, lines).split(" on ", 1)[1].split(" (link ", 1)[0]
        assert os.readlink(link) == served
        repointed = tmp_path / "repointed"
        repointed.symlink_to(other.slave_path)
        repointed.replace(link)  # another server took the name
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(GUARD_S) == 0, proc.stderr.read()
        assert os.readlink(link) == other.slave_path
    finally:
        if proc.poll() is None:
            proc.kill()
        other.close()
