"""``fog-driver watch``'s terminal: the escape sequences of the redrawn block, the terminal's size and encoding,
and single keys from stdin in cbreak mode (``Keys``, restored on every exit and around Ctrl-Z)."""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import termios
import tty
from typing import Any, TextIO

from ..client.display import DEGREE

__all__ = [
    "CLEAR_EOL",
    "CLEAR_EOS",
    "CLEAR_SCREEN",
    "HIDE_CURSOR",
    "HOME",
    "SHOW_CURSOR",
    "Keys",
    "degree_for",
    "isatty",
    "terminal_size",
]

HIDE_CURSOR = "\x1b[?25l"
SHOW_CURSOR = "\x1b[?25h"
HOME = "\x1b[H"
CLEAR_SCREEN = "\x1b[2J"
CLEAR_EOL = "\x1b[K"
CLEAR_EOS = "\x1b[J"


def degree_for(out: TextIO) -> str:
    encoding = getattr(out, "encoding", None) or "utf-8"
    try:
        DEGREE.encode(encoding)
    except (UnicodeEncodeError, LookupError):
        return "d"
    return DEGREE


def isatty(out: TextIO) -> bool:
    try:
        return bool(out.isatty())
    except (AttributeError, ValueError, OSError):
        return False


def terminal_size(out: TextIO) -> tuple[int, int]:
    """(columns, lines) of the terminal ``out`` writes to; 80 x 24 when it does not say (0 x 0 ptys)."""
    try:
        size = os.get_terminal_size(out.fileno())
    except (AttributeError, ValueError, OSError):  # io.UnsupportedOperation is both
        size = shutil.get_terminal_size()
    return size.columns or 80, size.lines or 24


class Keys:
    """Single keys from a terminal on stdin: cbreak mode (no echo, no line buffering; Ctrl-C still
    interrupts) while the watch runs, the terminal's settings restored by ``restore`` (call it in a
    ``finally``), and around Ctrl-Z (the shell gets its terminal back; ``fg`` resumes cbreak mode)."""

    def __init__(self, stream: TextIO, on_resume: Any = None) -> None:
        self._termios = termios
        self.fd = stream.fileno()
        self._saved = termios.tcgetattr(self.fd)
        self._on_resume = on_resume
        self._previous_tstp: Any = None
        tty.setcbreak(self.fd, termios.TCSANOW)
        try:
            self._previous_tstp = signal.signal(signal.SIGTSTP, self._suspend)
        except (ValueError, OSError):  # not the main thread: no job-control handling, the rest works
            self._previous_tstp = None

    def read(self) -> bytes:
        try:
            return os.read(self.fd, 64)
        except OSError:
            return b""

    def _suspend(self, signum: int, frame: Any) -> None:
        self._set(self._saved)
        signal.signal(signal.SIGTSTP, signal.SIG_DFL)
        os.kill(os.getpid(), signal.SIGTSTP)  # stopped here until SIGCONT
        signal.signal(signal.SIGTSTP, self._suspend)
        tty.setcbreak(self.fd, self._termios.TCSANOW)
        if self._on_resume is not None:
            self._on_resume()

    def _set(self, attributes: list) -> None:
        with contextlib.suppress(OSError, self._termios.error):
            self._termios.tcsetattr(self.fd, self._termios.TCSADRAIN, attributes)

    def restore(self) -> None:
        self._set(self._saved)
        if self._previous_tstp is not None:
            with contextlib.suppress(ValueError, OSError):
                signal.signal(signal.SIGTSTP, self._previous_tstp)
            self._previous_tstp = None
