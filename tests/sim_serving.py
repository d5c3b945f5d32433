"""``fog-driver simulate --serve pty`` as a separate process, its stdout read line by line in a thread."""

from __future__ import annotations

import queue
import subprocess
import sys
import threading
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent


SHORT_TEST = REPO / "configs" / "profiles" / "short-test.yaml"


GUARD_S = 30.0  # failure guard only: nothing is expected to take anywhere near this long


def start_fog_driver(*argv: str, cwd: Path = REPO) -> tuple[subprocess.Popen, queue.Queue]:
    """``python -m fog_driver ARGV...`` as a process whose stdout lines a thread puts on a queue (None at its
    end): read them with ``_next_line``, which gives up after ``GUARD_S``."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "fog_driver", *argv],
        cwd=cwd,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    lines: queue.Queue = queue.Queue()

    def pump() -> None:
        for line in proc.stdout:
            lines.put(line)
        lines.put(None)

    threading.Thread(target=pump, daemon=True).start()
    return proc, lines


def _start_cli(*extra: str, link: Path) -> tuple[subprocess.Popen, queue.Queue]:
    return start_fog_driver("simulate", "--serve", "pty", "--link", str(link), "--profile", str(SHORT_TEST), *extra)


def _next_line(proc: subprocess.Popen, lines: queue.Queue) -> str:
    try:
        line = lines.get(timeout=GUARD_S)
    except queue.Empty:
        proc.kill()
        raise
    assert line is not None, f"no more output; stderr: {proc.stderr.read()}"
    return line
