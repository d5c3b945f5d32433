"""``PtyPair``: a pseudo-terminal that stands in for a USB serial adapter in tests and demos.

The slave side is a real tty path that pyserial opens like ``/dev/ttyUSB0``;
whatever is written to the master side arrives there, and closing the master
reproduces an unplug exactly (the slave's reads fail with EIO).

Both ends are put in raw mode: a fresh pty runs the line discipline (echo,
CR/LF translation, XON/XOFF, signal characters) which would mangle binary
frames.  The helper keeps its own slave fd open until ``close()`` so the pty
exists, with raw settings, before and between openings by a reader.

pyserial flushes the input when it opens a port, so bytes written to the
master before the reader has opened the slave may be dropped: wait for the
reader's "open" state before writing.
"""

from __future__ import annotations

import os
import select
import time
import tty
from pathlib import Path
from types import TracebackType

__all__ = ["PtyPair"]


class PtyPair:
    """A raw-mode pty: write to ``master_fd`` (``write``), open ``slave_path`` as the port."""

    def __init__(self) -> None:
        master_fd, slave_fd = os.openpty()
        try:
            tty.setraw(master_fd)
            tty.setraw(slave_fd)
            os.set_blocking(master_fd, False)  # so write/read_available can time out
            self.slave_path: str = os.ttyname(slave_fd)
        except BaseException:
            os.close(master_fd)
            os.close(slave_fd)
            raise
        self.master_fd: int = master_fd  #: -1 once unplugged or closed
        self.slave_fd: int = slave_fd  #: the helper's own slave fd, -1 once closed
        self._symlinks: list[Path] = []

    def __enter__(self) -> PtyPair:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def write(self, data: bytes, timeout_s: float = 10.0) -> None:
        """Write all of ``data`` to the master (the "instrument" side), waiting while the pty is full.

        Raises ``TimeoutError`` if the slave side does not drain the pty within
        ``timeout_s`` (nobody reading), and ``OSError`` after ``unplug``.
        """
        if self.master_fd < 0:
            raise OSError("pty master is closed (unplugged)")
        view = memoryview(data)
        deadline_s = time.monotonic() + timeout_s
        while view:
            try:
                written = os.write(self.master_fd, view)
            except BlockingIOError:
                written = 0
            view = view[written:]
            if view and written == 0:
                left_s = deadline_s - time.monotonic()
                if left_s <= 0:
                    raise TimeoutError(f"pty {self.slave_path}: {len(view)} bytes not accepted within {timeout_s} s")
                select.select([], [self.master_fd], [], left_s)

    def read_available(self, timeout_s: float = 0.0) -> bytes:
        """What the slave side wrote (what a driver sent to the "instrument"), waiting up to ``timeout_s``."""
        if self.master_fd < 0:
            return b""
        readable, _, _ = select.select([self.master_fd], [], [], timeout_s)
        if not readable:
            return b""
        try:
            return os.read(self.master_fd, 65536)
        except (BlockingIOError, OSError):  # EIO when no slave is open: nothing to read
            return b""

    def unplug(self) -> None:
        """Close the master: readers of the slave now get EIO, exactly as from a pulled USB adapter."""
        if self.master_fd >= 0:
            os.close(self.master_fd)
            self.master_fd = -1

    def symlink(self, path: str | os.PathLike[str]) -> Path:
        """Make ``path`` a symlink to the slave (a stable name, like a udev rule's); removed on ``close``."""
        link = Path(path)
        link.symlink_to(self.slave_path)
        self._symlinks.append(link)
        return link

    def close(self) -> None:
        """Unplug, close the helper's slave fd and remove the symlinks; safe to call twice."""
        self.unplug()
        if self.slave_fd >= 0:
            os.close(self.slave_fd)
            self.slave_fd = -1
        while self._symlinks:
            self._symlinks.pop().unlink(missing_ok=True)
