"""Terminal niceties: a one-line progress display shown only on a terminal, and logging set-up."""

from __future__ import annotations

import logging
import sys
from typing import TextIO

import structlog
from structlog.tracebacks import ExceptionDictTransformer

LOG_FORMATS = ("auto", "human", "json")


def log_format_for(stream: TextIO, requested: str = "auto") -> str:
    """``human`` on a terminal, ``json`` anywhere else (journald, a pipe, a file), unless ``requested``.

    One rule for every command: a person at a terminal reads lines, a machine parses JSON objects.
    """
    if requested not in LOG_FORMATS:
        raise ValueError(f"log format must be one of {', '.join(LOG_FORMATS)}, got {requested!r}")
    if requested != "auto":
        return requested
    return "human" if bool(getattr(stream, "isatty", lambda: False)()) else "json"


def _human_value(value: object) -> str:
    text = str(value)
    if text == "" or any(c.isspace() or c in "\"'=" for c in text):
        return repr(text)
    return text


def render_human(_logger: object, _name: str, event: dict) -> str:
    """``HH:MM:SS level   event key=value ...``: one line a person reads at a glance (the exception,
    if any, on the lines after it)."""
    when = event.pop("timestamp", "")
    level = event.pop("level", "")
    name = event.pop("event", "")
    exception = event.pop("exception", None)
    fields = " ".join(f"{key}={_human_value(value)}" for key, value in event.items())
    line = f"{when} {level:<7} {name}" + (f"  {fields}" if fields else "")
    return line + (f"\n{exception}" if exception else "")


def configure_logging(verbosity: int = 0, fmt: str = "auto", *, service: bool = False) -> str:
    """Log lines on stderr, in the format that fits where they go (:func:`log_format_for`): returns it.

    Levels: ``verbosity`` 0 = warnings, 1 = info, 2 = debug.  A ``service`` (the daemon) logging to
    journald or a pipe logs at info from 0 (its per-second status lines are its record); at a terminal it
    stays quiet (its banner first, status lines only with ``-v``).

    ``log.exception(...)`` (or ``exc_info=True``) carries the exception: as JSON, an ``exception`` list of
    ``{exc_type, exc_value, frames: [{filename, lineno, name}, ...]}`` (no local variables: they may hold
    a token); for a person, the formatted traceback on the lines after the event.
    """
    fmt = log_format_for(sys.stderr, fmt)
    if service and fmt == "json":
        verbosity = max(verbosity, 1)
    level = {0: logging.WARNING, 1: logging.INFO}.get(verbosity, logging.DEBUG)
    if fmt == "json":
        stamp = structlog.processors.TimeStamper(fmt="iso", utc=True)
        exceptions = structlog.processors.ExceptionRenderer(ExceptionDictTransformer(show_locals=False))
        renderer = structlog.processors.JSONRenderer()
    else:
        stamp = structlog.processors.TimeStamper(fmt="%H:%M:%S", utc=False)
        exceptions = structlog.processors.format_exc_info
        renderer = render_human
    structlog.configure(
        processors=[structlog.processors.add_log_level, stamp, exceptions, renderer],
        wrapper_class=structlog.make_filtering_bound_logger(level),
        # sys.stderr looked up at each use, not bound now: it may be replaced later (a test's capture)
        logger_factory=lambda *_: structlog.PrintLogger(file=sys.stderr),
        cache_logger_on_first_use=False,
    )
    return fmt
