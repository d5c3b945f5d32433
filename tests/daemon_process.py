"""A command (a daemon as deployed) running with its stdout piped and its stderr in a log, killed at the end."""

from __future__ import annotations

import contextlib
import subprocess
from collections.abc import Iterator
from pathlib import Path

GUARD_S = 60.0


@contextlib.contextmanager
def daemon_process(
    command: list[str],
    *,
    cwd: Path,
    log: Path,
    env: dict[str, str] | None = None,
    stdin: int = subprocess.DEVNULL,
    umask: int = -1,
) -> Iterator[subprocess.Popen]:
    """``command`` running with its stdout piped and its stderr in ``log``; killed if still running at the end."""
    with log.open("w") as stderr:
        proc = subprocess.Popen(
            command, cwd=cwd, env=env, stdin=stdin, stdout=subprocess.PIPE, stderr=stderr, text=True, umask=umask
        )
        try:
            yield proc
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait(GUARD_S)
