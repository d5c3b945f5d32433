"""The project's error type: a one-line message for the user and an exit status."""

from __future__ import annotations

import os


class FogDriverError(Exception):
    """An error the user can act on.  The CLI prints ``str(error)`` on one line and exits with ``exit_status``."""

    exit_status = 1


class UsageError(FogDriverError):
    exit_status = os.EX_USAGE  # 64


class InputFileError(FogDriverError):
    """A file the user named is missing, unreadable, empty or not what it should be."""

    exit_status = os.EX_DATAERR  # 65


class DeviceError(FogDriverError):
    """A port could not be opened or was lost for good."""

    exit_status = os.EX_UNAVAILABLE  # 69


class TemporaryFailure(FogDriverError):
    """A failure that may go away by itself, such as a listen address in use or not up yet: exit 75
    (EX_TEMPFAIL), so a service manager starts the daemon again (78 would stop it for good)."""

    exit_status = os.EX_TEMPFAIL  # 75


class OutputFileError(FogDriverError):
    """An output file cannot be created, would overwrite data, or cannot be written (disk full)."""

    exit_status = os.EX_CANTCREAT  # 73


class InternalError(FogDriverError):
    """A bug: an exception nothing expected.  The CLI prints ``internal error: <type>: <message>`` on one
    line and exits 70 (EX_SOFTWARE); the log carries the traceback."""

    exit_status = os.EX_SOFTWARE  # 70

    @classmethod
    def from_exception(cls, exc: BaseException) -> InternalError:
        return cls(f"internal error: {type(exc).__name__}: {' '.join(str(exc).split())}")


def read_error(path: object, what: str, exc: OSError) -> InputFileError:
    """The one-line error for an input file that cannot be read: "<path>: no such <what>", "<path>: is a
    directory, not a <what>", or "<path>: cannot read the <what>: <reason>"."""
    if isinstance(exc, FileNotFoundError):
        return InputFileError(f"{path}: no such {what}")
    if isinstance(exc, IsADirectoryError):
        return InputFileError(f"{path}: is a directory, not a {what}")
    return InputFileError(f"{path}: cannot read the {what}: {exc.strerror or exc}")
