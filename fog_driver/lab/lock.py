"""One runner per chamber: an exclusive ``fcntl`` lock per controller address.

The lock file is ``fog-driver-chamber-<sha256 of the address, 16 hex>.lock`` under ``$XDG_RUNTIME_DIR`` (or
``/tmp`` without it); it holds the pid of the runner that has it.  The kernel releases the lock when the process
ends, however it ends, so a stale file never blocks a new run.  A second runner for the same address gets one
line, ``DeviceError`` (exit 69).
"""

from __future__ import annotations

import fcntl
import hashlib
import os
from pathlib import Path
from types import TracebackType

from ..errors import DeviceError


def lock_folder() -> Path:
    """``$XDG_RUNTIME_DIR`` if set (and a folder), else ``/tmp``."""
    runtime = os.environ.get("XDG_RUNTIME_DIR")
    return Path(runtime) if runtime and Path(runtime).is_dir() else Path("/tmp")


def lock_path(address: str, folder: Path | None = None) -> Path:
    digest = hashlib.sha256(address.encode()).hexdigest()[:16]
    return (folder or lock_folder()) / f"fog-driver-chamber-{digest}.lock"


class ControllerLock:
    """The lock of ``address`` while in a ``with`` block (or between ``acquire`` and ``release``)."""

    def __init__(self, address: str, folder: Path | None = None) -> None:
        self.address = address
        self.path = lock_path(address, folder)
        self._fd: int | None = None

    def acquire(self) -> None:
        """Take the lock; ``DeviceError`` (one line, exit 69) if another runner has it."""
        try:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o600)
        except OSError as exc:
            raise DeviceError(f"cannot create the chamber lock {self.path}: {exc.strerror or exc}") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            holder = os.read(fd, 32).decode(errors="replace").strip() or "another process"
            os.close(fd)
            raise DeviceError(
                f"another chamber run drives {self.address} (pid {holder} holds {self.path}); one runner per chamber"
            ) from None
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        self._fd = fd

    def release(self) -> None:
        """Give the lock back (idempotent)."""
        if self._fd is not None:
            fcntl.flock(self._fd, fcntl.LOCK_UN)
            os.close(self._fd)
            self._fd = None

    def __enter__(self) -> ControllerLock:
        self.acquire()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.release()
