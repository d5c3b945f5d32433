"""``fog-driver watch`` at a terminal: a pty it runs in, against a real daemon; the keys z, b and q, the
terminal's settings back after q or a signal (Ctrl-Z included), and the reason no samples come on its
banner line."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time

import pytest
from watch_fakes import GUARD_S


class Terminal:
    """A pty for ``fog-driver watch`` to run in: what it drew (escape sequences removed), keys to type."""

    def __init__(self) -> None:
        import os
        import pty
        import termios

        self.master, self.slave = pty.openpty()
        termios.tcsetattr(self.slave, termios.TCSANOW, termios.tcgetattr(self.slave))
        self.screen = ""
        self._os = os

    def wait_for(self, text: str) -> None:
        """Read the output until ``text`` appears in it (GUARD_S at most)."""
        import select

        deadline = time.monotonic() + GUARD_S
        while text not in self.screen:
            assert time.monotonic() < deadline, f"{text!r} never shown; the last screen: {self.screen[-3000:]}"
            if select.select([self.master], [], [], 0.5)[0]:
                data = self._os.read(self.master, 65536).decode("utf-8", "replace")
                self.screen += re.sub(r"\x1b\[[0-9;?]*[A-Za-z]", "", data)

    def type(self, keys: bytes) -> None:
        self._os.write(self.master, keys)

    def close(self) -> None:
        self._os.close(self.master)
        self._os.close(self.slave)


def popen_watch_in(term: Terminal, address: tuple[str, int], **popen) -> subprocess.Popen:
    """``fog-driver watch HOST:PORT`` started in ``term`` (its stdin and stdout), stderr piped."""
    host, port = address
    return subprocess.Popen(
        [sys.executable, "-m", "fog_driver", "watch", f"{host}:{port}"],
        stdin=term.slave,
        stdout=term.slave,
        stderr=subprocess.PIPE,
        **popen,
    )


def press_q(term: Terminal, proc: subprocess.Popen) -> None:
    """q: the watch ends, exit 0, nothing on stderr."""
    term.type(b"q")
    assert proc.wait(GUARD_S) == 0
    assert proc.stderr.read() == b""


def test_keys_z_b_q_on_a_terminal_and_the_terminal_restored(tmp_path):
    """z sends ?ZERO, b ?BIAS (60 s) with its result in the banner, q quits with exit 0; stdin was in cbreak
    mode meanwhile and has its settings back afterwards."""
    import termios

    from daemon_hil import N_SHORT, SHORT, watch_all, watched_daemon

    from fog_driver.protocol import decode_bytes

    head = 20000
    term = Terminal()
    before = termios.tcgetattr(term.slave)
    with watched_daemon(tmp_path) as (pty, daemon, client):
        pty.write(SHORT[:head])
        n_head = decode_bytes(SHORT[:head], final=False).counters.sample_frames
        watch_all(client, n_head)
        proc = popen_watch_in(term, daemon.address)
        try:
            term.wait_for("keys        q quit")
            term.wait_for("bias not removed: at rest the angle climbs with Earth rate + bias; press b")
            assert not termios.tcgetattr(term.slave)[3] & termios.ICANON  # cbreak: one key at a time
            term.type(b"z")
            term.wait_for("zeroed: the angle starts again from 0 here")
            term.type(b"b")
            term.wait_for("bias capture started: 60 s of data; keep the table still")
            pty.write(SHORT[head:])  # 270 s of device data: the capture completes
            term.wait_for("bias captured: ")
            press_q(term, proc)
        finally:
            proc.kill()
            proc.wait(GUARD_S)
        angles = watch_all(client, N_SHORT - n_head)
        assert abs(angles[0]["angle_arcsec"]) < 5.0  # the z reached the daemon
        assert daemon.terminate() == 0
    assert termios.tcgetattr(term.slave) == before  # the terminal's settings are back
    term.close()


def _default_ctrl_c() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


#: How a shell starts a command in the foreground: Ctrl-C at its default (this test run may have inherited it
#: ignored, as a background job does, and Python then installs no KeyboardInterrupt handler), and a process
#: group of its own whose parent is in the same session, so Ctrl-Z stops it (the kernel discards SIGTSTP sent
#: to an orphaned process group, such as a detached CI run's).
AS_A_SHELLS_FOREGROUND_JOB = {"preexec_fn": _default_ctrl_c, "process_group": 0}


@pytest.mark.parametrize("how", ["SIGTERM", "SIGINT", "SIGTSTP"])
def test_the_terminal_is_restored_when_a_signal_ends_or_suspends_the_watch(tmp_path, how):
    import termios

    from daemon_hil import watched_daemon

    term = Terminal()
    before = termios.tcgetattr(term.slave)
    with watched_daemon(tmp_path) as (_, daemon, _client):
        proc = popen_watch_in(term, daemon.address, **AS_A_SHELLS_FOREGROUND_JOB)
        try:
            term.wait_for("keys        q quit")
            assert termios.tcgetattr(term.slave) != before
            proc.send_signal(getattr(signal, how))
            if how == "SIGTSTP":  # Ctrl-Z: the shell gets its terminal back while the watch is stopped
                deadline = time.monotonic() + GUARD_S
                while True:  # until the watch has stopped itself (a SIGCONT before that would be lost)
                    pid, status = os.waitpid(proc.pid, os.WUNTRACED | os.WNOHANG)
                    if pid and os.WIFSTOPPED(status):
                        break
                    assert time.monotonic() < deadline, "never stopped on Ctrl-Z"
                    term.wait_for("")  # (drains the output; returns at once)
                assert termios.tcgetattr(term.slave) == before, "not restored on Ctrl-Z"
                proc.send_signal(signal.SIGCONT)
                term.screen = ""
                term.wait_for("keys        q quit")  # redrawn after fg
                term.type(b"q")
            assert proc.wait(GUARD_S) == 0
        finally:
            proc.kill()
            proc.wait(GUARD_S)
        assert daemon.terminate() == 0
    assert termios.tcgetattr(term.slave) == before
    term.close()


def test_fog_driver_watch_at_a_terminal_without_count_waits_and_says_why_on_its_status_line(tmp_path):
    """At a terminal without --count or --duration it keeps waiting, the reason on the banner line; q ends it."""
    from daemon_hil import watched_daemon

    term = Terminal()
    with watched_daemon(tmp_path) as (_, daemon, _client):
        proc = popen_watch_in(term, daemon.address)
        try:
            term.wait_for("(port open, no samples from the instrument) ***")
            press_q(term, proc)
        finally:
            proc.kill()
            proc.wait(GUARD_S)
        assert daemon.terminate() == 0
    assert re.search(r"\*\*\* NO DATA for \d+ s \(port open, no samples from the instrument\) \*\*\*", term.screen)
    term.close()
