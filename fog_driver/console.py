"""Terminal niceties: a one-line progress display shown only on a terminal, and logging set-up."""

from __future__ import annotations

import logging
import sys
import time
from typing import TextIO

import structlog
from structlog.tracebacks import ExceptionDictTransformer


class Progress:
    """Rewrites one status line on a terminal (``\\r``); silent when the stream is not a tty (piped, CI)."""

    def __init__(self, stream: TextIO | None = None, min_interval_s: float = 0.2) -> None:
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = bool(getattr(self.stream, "isatty", lambda: False)())
        self.min_interval_s = min_interval_s
        self._last_shown = 0.0
        self._width = 0

    def show(self, text: str, force: bool = False) -> None:
        if not self.enabled:
            return
        now = time.monotonic()
        if not force and now - self._last_shown < self.min_interval_s:
            return
        self._last_shown = now
        pad = max(0, self._width - len(text))
        self.stream.write("\r" + text + " " * pad)
        self.stream.flush()
        self._width = len(text)

    def clear(self) -> None:
        if self.enabled and self._width:
            self.stream.write("\r" + " " * self._width + "\r")
            self.stream.flush()
            self._width = 0

    def bytes_done(self, done: int, total: int) -> None:
        pct = 100.0 * done / total if total else 100.0
        self.show(f"decoding {done / 1e6:.1f} / {total / 1e6:.1f} MB ({pct:.0f} %)")


def configure_logging(verbosity: int = 0, json: bool = False) -> None:
    """structlog key-value lines on stderr; ``verbosity`` 0 = warnings, 1 = info, 2 = debug.

    ``log.exception(...)`` (or ``exc_info=True``) carries the exception: with ``json``, an
    ``exception`` list of ``{exc_type, exc_value, frames: [{filename, lineno, name}, ...]}`` (no local
    variables: they may hold a token); otherwise the formatted traceback as one escaped value.
    """
    level = {0: logging.WARNING, 1: logging.INFO}.get(verbosity, logging.DEBUG)
    if json:
        renderer = structlog.processors.JSONRenderer()
        exceptions = structlog.processors.ExceptionRenderer(ExceptionDictTransformer(show_locals=False))
    else:
        renderer = structlog.processors.KeyValueRenderer(key_order=["timestamp", "level", "event"], drop_missing=True)
        exceptions = structlog.processors.format_exc_info
    structlog.configure(
        processors=[
            structlog.processors.add_log_level,
            structlog.processors.TimeStamper(fmt="iso", utc=True),
            exceptions,
            renderer,
        ],
        wrapper_class=structlog.make_filtering_bound_logger(level),
        # sys.stderr looked up at each use, not bound now: it may be replaced later (a test's capture)
        logger_factory=lambda *_: structlog.PrintLogger(file=sys.stderr),
        cache_logger_on_first_use=False,
    )
