"""Reading the project's YAML files (configs, profiles, sidecars): safe loading only, bounded, one-line errors."""

from __future__ import annotations

import errno
import os
import secrets
from pathlib import Path
from typing import Any

import yaml

from ..errors import InputFileError, OutputFileError
from .bounded import FileTooLarge, read_regular
from .outputs import is_capture

#: Every YAML file the project reads is small; a larger one is not what it claims to be.
MAX_YAML_BYTES = 1 << 20


def write_yaml(path: str | Path, doc: Any, what: str, header: str = "") -> Path:
    """Write ``doc`` with ``yaml.safe_dump``, atomically and durably: a crash or a full disk never leaves
    half a file.  A failure is an ``OutputFileError`` naming ``what``.  ``header``: lines of text written
    first, each as a ``# `` comment.

    The text goes to a new temporary file with a random name beside ``path``, created with
    ``O_CREAT | O_EXCL | O_NOFOLLOW`` (a file or symlink planted under any name is never opened, let
    alone written through), and with the process's umask; it is fsynced, renamed onto ``path`` (a
    symlink at ``path`` is replaced, its target untouched), and the directory is fsynced.
    """
    return write_text(path, yaml_text(doc, header), what)


def yaml_text(doc: Any, header: str = "") -> str:
    """The text ``write_yaml`` writes for ``doc`` (``header``: lines of ``# `` comments first)."""
    text = yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=120, allow_unicode=False)
    return "".join(f"# {line}".rstrip() + "\n" for line in header.splitlines()) + text


def write_text(path: str | Path, text: str | bytes, what: str) -> Path:
    """Write ``text`` (UTF-8; bytes as they are) to ``path`` atomically and durably, as ``write_yaml`` does
    (its docstring)."""
    path = Path(path)
    data = text.encode("utf-8") if isinstance(text, str) else text
    tmp: Path | None = None
    try:
        fd, tmp = _create_new_file_beside(path)
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
        tmp = None
        _fsync_directory(path.parent)
    except OSError as exc:
        if tmp is not None:
            tmp.unlink(missing_ok=True)
        raise OutputFileError(f"{path}: cannot write {what}: {exc.strerror or exc}") from None
    return path


def _create_new_file_beside(path: Path, attempts: int = 100) -> tuple[int, Path]:
    """A new, empty, hidden file ``.<name>.<random>.tmp`` in ``path``'s directory, open for writing:
    (descriptor, path).  Never an existing file or a symlink (``O_EXCL | O_NOFOLLOW``); mode 0666 less
    the umask, like any file the process creates."""
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC
    for _ in range(attempts):
        candidate = path.with_name(f".{path.name}.{secrets.token_hex(8)}.tmp")
        try:
            return os.open(candidate, flags, 0o666), candidate
        except FileExistsError:
            continue  # someone else's name: draw another
    raise FileExistsError(errno.EEXIST, f"no free temporary name after {attempts} attempts", str(path.parent))


def _fsync_directory(directory: Path) -> None:
    """Make a rename in ``directory`` durable; a file system that cannot fsync a directory is let be."""
    fd = os.open(directory, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
    try:
        os.fsync(fd)
    except OSError as exc:
        if exc.errno not in (errno.EINVAL, errno.ENOTSUP):
            raise
    finally:
        os.close(fd)


def read_yaml(path: str | Path, what: str, *, missing_ok: bool = False, hint: str = "") -> Any:
    """``yaml.safe_load`` of a file (never a Python object tag, never code).

    Every problem is an ``InputFileError`` naming the file and ``what`` it should
    have been (``"config file"``, ``"profile file"``...); a missing file gives
    None with ``missing_ok``.  ``hint`` is appended to the missing-file message.
    """
    text = read_yaml_text(path, what, missing_ok=missing_ok, hint=hint)
    return None if text is None else parse_yaml(text, path, what)


def read_yaml_text(path: str | Path, what: str, *, missing_ok: bool = False, hint: str = "") -> str | None:
    """A YAML file's text (UTF-8, at most ``MAX_YAML_BYTES``), with ``read_yaml``'s one-line errors: read by
    ``bounded.read_regular`` (a regular file only, never more than the limit read, whatever ``stat`` says)."""
    try:
        data = read_regular(path, what, MAX_YAML_BYTES, missing_ok=missing_ok, hint=hint)
    except FileTooLarge:
        _not_a_capture(Path(path), what)
        raise
    if data is None:
        return None
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        _not_a_capture(Path(path), what)
        raise InputFileError(f"{path}: cannot read {what}: {exc}") from None


def parse_yaml(text: str, path: str | Path, what: str, loader: type[yaml.SafeLoader] = yaml.SafeLoader) -> Any:
    """``yaml.safe_load`` of ``text`` read from ``path`` (or ``loader``'s, a ``SafeLoader`` that refuses more):
    "PATH: WHAT is not valid YAML at line N" if it is not, and one line for an integer too long to read."""
    try:
        if not issubclass(loader, yaml.SafeLoader):  # (safe_load's own steps, with a stricter SafeLoader)
            raise TypeError(f"{loader!r} is no SafeLoader")
        parser = loader(text)
        try:
            return parser.get_single_data()
        finally:
            parser.dispose()
    except yaml.YAMLError as exc:
        _not_a_capture(Path(path), what)
        mark = getattr(exc, "problem_mark", None)
        at = f" at line {mark.line + 1}" if mark is not None else ""
        raise InputFileError(f"{path}: {what} is not valid YAML{at}") from None
    except ValueError as exc:  # an integer of over 4,300 digits (Python's int-from-text limit): no number of ours
        if "integer string conversion" not in str(exc):
            raise
        raise InputFileError(f"{path}: {what} holds an integer of over 4,300 digits") from None


def _not_a_capture(path: Path, what: str) -> None:
    """A file that is no YAML: when it is a raw capture (``outputs.is_capture``; a capture given where a model
    or a config goes), the one-line ``InputFileError`` says so rather than what its bytes fail."""
    if is_capture(path):
        raise InputFileError(f"{path}: is a capture, not a {what}")


def read_tagged_yaml(path: str | Path, kind: str, format_tag: str, schema_version: int) -> dict:
    """A project file that names itself: a mapping with ``format: <format_tag>`` and the expected
    ``schema_version``; anything else is a one-line ``InputFileError`` saying which."""
    return check_tagged(
        read_yaml(path, f"{kind} file" if not kind.endswith("file") else kind), path, kind, format_tag, schema_version
    )


def check_tagged(doc: Any, path: str | Path, kind: str, format_tag: str, schema_version: int) -> dict:
    """``read_tagged_yaml``'s checks of a document read from ``path``."""
    where = str(path)
    if not isinstance(doc, dict) or doc.get("format") != format_tag:
        raise InputFileError(f"{where}: not a fog_driver {kind} (no 'format: {format_tag}')")
    version = doc.get("schema_version")
    if version != schema_version:
        raise InputFileError(
            f"{where}: {kind} schema version {version!r}; this fog_driver reads version {schema_version}"
        )
    return doc
