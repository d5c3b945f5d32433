"""Reading an input file: a regular file only, and never more bytes than its kind's limit.

Every file the project reads whole (models, configs, adaptation states, profiles, sidecars, table logs, token
files) comes through ``read_regular``; a capture, read block by block, is opened by ``open_regular``; a file
looked into to tell what it is (``outputs.describe``, ``is_capture``) by ``read_head``.  The rule is the same:

- the file is opened with ``O_NONBLOCK`` (a FIFO never holds the open: no writer needed) and checked with
  ``fstat`` on the open descriptor, so what is checked is what is read: anything but a regular file (a
  directory, a FIFO, a socket, a device such as ``/dev/zero``) is the one line "PATH: not a regular file (it
  is a FIFO): a WHAT must be one".  A symlink to a regular file is a regular file.
- ``read_regular`` reads at most ``limit + 1`` bytes whatever ``fstat`` said: more than ``limit`` is the one
  line "PATH: WHAT larger than LIMIT bytes", so a file that grows while it is read is capped too.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import stat
from pathlib import Path
from typing import BinaryIO

from ..errors import InputFileError

__all__ = ["FileTooLarge", "NotARegularFile", "open_regular", "read_head", "read_regular"]

#: What ``os.read`` asks for at a time (the reads stop at the limit anyway).
_CHUNK_BYTES = 1 << 20


class NotARegularFile(InputFileError):
    """An input path that is a directory, a FIFO, a socket or a device: never read."""


class FileTooLarge(InputFileError):
    """An input file with more bytes than its kind's limit (counted as read, not as ``stat`` says)."""


def _kind(mode: int) -> str:
    """What a file that is not a regular file is, for the one-line error."""
    for test, name in (
        (stat.S_ISDIR, "a directory"),
        (stat.S_ISFIFO, "a FIFO"),
        (stat.S_ISSOCK, "a socket"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
    ):
        if test(mode):
            return name
    return "not a file"


def _article(what: str) -> str:
    return "an" if what[:1].lower() in "aeiou" else "a"


def _check_regular(mode: int, path: Path, what: str) -> None:
    if not stat.S_ISREG(mode):
        raise NotARegularFile(f"{path}: not a regular file (it is {_kind(mode)}): {_article(what)} {what} must be one")


def not_regular_kind(path: str | Path) -> str | None:
    """What ``path`` is when it exists and is not a regular file (a symlink followed): "a directory", "a FIFO",
    "a socket", "a character device", ...; None for a regular file or nothing there.  Only ``stat``: nothing
    is opened."""
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return None
    return None if stat.S_ISREG(mode) else _kind(mode)


def _open_fd(path: Path, what: str) -> int:
    """``path`` opened read-only without blocking, checked to be a regular file (on the descriptor): the
    descriptor, in blocking mode again.  ``FileNotFoundError`` passes; any other problem is a one-line
    ``InputFileError`` (``NotARegularFile`` for a directory, a FIFO, a socket, a device)."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except FileNotFoundError:
        raise
    except OSError as exc:  # a socket cannot be opened at all (ENXIO): say what it is
        with contextlib.suppress(OSError):
            _check_regular(os.stat(path).st_mode, path, what)
        raise InputFileError(f"{path}: cannot read the {what}: {exc.strerror or exc}") from None
    try:
        _check_regular(os.fstat(fd).st_mode, path, what)
        os.set_blocking(fd, True)
    except BaseException:
        os.close(fd)
        raise
    return fd


def read_regular(
    path: str | Path, what: str, limit: int, *, missing_ok: bool = False, hint: str = "", too_large: str = ""
) -> bytes | None:
    """The bytes of the regular file ``path`` (a ``what``: "model file", "reference CSV"...), at most ``limit``.

    A missing file is None with ``missing_ok``, else "PATH: no such WHAT" + ``hint``; not a regular file:
    ``NotARegularFile`` (the module docstring); more than ``limit`` bytes read: ``FileTooLarge``, "PATH: WHAT
    larger than LIMIT bytes" (``too_large``: another text after "PATH: "); a read that fails: "PATH: cannot
    read the WHAT: REASON".  Always one line; the descriptor is always closed."""
    path = Path(path)
    try:
        fd = _open_fd(path, what)
    except FileNotFoundError:
        if missing_ok:
            return None
        raise InputFileError(f"{path}: no such {what}{hint}") from None
    chunks: list[bytes] = []
    total = 0
    try:
        while total <= limit:
            chunk = os.read(fd, min(_CHUNK_BYTES, limit + 1 - total))
            if not chunk:
                break
            chunks.append(chunk)
            total += len(chunk)
    except OSError as exc:
        raise InputFileError(f"{path}: cannot read the {what}: {exc.strerror or exc}") from None
    finally:
        os.close(fd)
    if total > limit:
        raise FileTooLarge(f"{path}: {too_large or f'{what} larger than {limit} bytes'}")
    return b"".join(chunks)


def file_sha256(path: str | Path, what: str, limit: int) -> str:
    """The SHA-256 of the regular file ``path``, read whole through ``read_regular`` (its one-line errors)."""
    return hashlib.sha256(read_regular(path, what, limit) or b"").hexdigest()


def open_regular(path: str | Path, what: str) -> BinaryIO:
    """The regular file ``path`` open for reading (a capture, read block by block: no limit), with
    ``read_regular``'s one-line errors for a missing file ("PATH: no such WHAT"), one that is not a regular
    file, or one that cannot be opened."""
    path = Path(path)
    try:
        fd = _open_fd(path, what)
    except FileNotFoundError:
        raise InputFileError(f"{path}: no such {what}") from None
    return os.fdopen(fd, "rb")


def read_head(path: str | Path, limit: int) -> bytes | None:
    """At most ``limit`` bytes from the start of ``path`` when it is a regular file (a look at what a file is);
    None when it is missing, not a regular file, or cannot be read."""
    try:
        fd = _open_fd(Path(path), "file")
    except (OSError, InputFileError):
        return None
    try:
        with os.fdopen(fd, "rb") as f:
            return f.read(limit)
    except OSError:
        return None
