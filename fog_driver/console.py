"""Terminal niceties: a one-line progress display shown only on a terminal, and logging set-up."""

from __future__ import annotations

import logging
import string
import sys
import threading
import time
from collections.abc import Callable
from typing import Any, TextIO

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


#: Events a person reads as a sentence: the event's name -> its text, from the fields it names (those fields are
#: then left out of the ``key=value`` list).
HUMAN_TEXT = {
    "port_recovered": "port open again after {down_s:,.0f} s, {frames_missing:,} frames missing",
}
#: The repeats of a warning held back after one is shown, for this long (s): then the next is shown with their count.
REPEAT_WINDOW_S = 60.0
#: The kinds of line ``RepeatLimiter`` remembers at most (those with nothing held back, older than the window,
#: are forgotten first): a long-running daemon's distinct warnings never grow its memory without bound.
MAX_KINDS = 1024
_LEVELS_LIMITED = ("warning", "error")


def _text_of(name: str, event: dict) -> str:
    """The event's sentence (``HUMAN_TEXT``), taking the fields it uses out of ``event``; else its name."""
    template = HUMAN_TEXT.get(name)
    if template is None:
        return name
    used = {field for _, field, _, _ in string.Formatter().parse(template) if field}
    try:
        text = template.format(**{key: event[key] for key in used})
    except (KeyError, ValueError, TypeError):  # a field missing or of another type: the plain form
        return name
    for key in used:
        del event[key]
    return text


def render_human(_logger: object, _name: str, event: dict) -> str:
    """``HH:MM:SS level   event key=value ...``: one line a person reads at a glance (the exception,
    if any, on the lines after it).  An event of ``HUMAN_TEXT`` is its sentence; the lines ``RepeatLimiter``
    put in ``_held_back`` come first, and its ``_repeats`` count ends the line."""
    held_back = event.pop("_held_back", [])
    repeats = event.pop("_repeats", None)
    when = event.pop("timestamp", "")
    level = event.pop("level", "")
    name = event.pop("event", "")
    exception = event.pop("exception", None)
    text = _text_of(str(name), event)
    fields = " ".join(f"{key}={_human_value(value)}" for key, value in event.items())
    line = f"{when} {level:<7} {text}" + (f"  {fields}" if fields else "")
    if repeats is not None:
        line += f"  ({_repeated(*repeats)})"
    return "".join(f"{before}\n" for before in held_back) + line + (f"\n{exception}" if exception else "")


def _repeated(count: int, since: str) -> str:
    return f"{count:,} more like it since {since} not shown"


class RepeatLimiter:
    """A structlog processor for the human format: a warning (or error) seen again and again is shown once, then
    at most once every ``window_s`` with the count of those held back, so a pulled port's retry warning, once a
    second, is a line a minute.  Two lines are of one kind when their event, level and text fields (``str`` and
    ``bool`` values) are the same; numbers (an attempt, a delay) may differ.  Before any line is shown, the kinds
    with repeats held back since their last line get a line of their own saying how many ("port_state  24 more
    like it since 03:19:12 not shown"), so every line is accounted for and a recovery is read after its failures.

    Info and debug lines pass untouched (the per-second status lines with ``-v`` are their own record).  The JSON
    format does not use it: a machine keeps every event (``configure_logging``).  ``clock``: monotonic seconds."""

    def __init__(self, window_s: float = REPEAT_WINDOW_S, clock: Callable[[], float] = time.monotonic) -> None:
        self.window_s = window_s
        self.clock = clock
        self._lock = threading.Lock()
        #: kind -> [when its last line was shown (clock), that line's timestamp, repeats held back since, level]
        self._kinds: dict[tuple, list] = {}

    @staticmethod
    def kind(event: dict) -> tuple:
        texts = tuple(
            sorted((k, v) for k, v in event.items() if isinstance(v, str | bool) and k not in ("timestamp", "level"))
        )
        return (event.get("level"), texts)

    def __call__(self, _logger: object, _name: str, event: dict) -> dict:
        if event.get("level") not in _LEVELS_LIMITED:
            return self._with_held_back(event, None)
        kind = self.kind(event)
        now = self.clock()
        with self._lock:
            seen = self._kinds.get(kind)
            if seen is not None and now - seen[0] < self.window_s:
                seen[2] += 1
                raise structlog.DropEvent
            if seen is not None and seen[2]:
                event["_repeats"] = (seen[2], seen[1])
            self._kinds[kind] = [now, event.get("timestamp", ""), 0, event.get("level")]
            if len(self._kinds) > MAX_KINDS:
                self._forget(now)
        return self._with_held_back(event, kind)

    def _forget(self, now: float) -> None:
        """Forget the kinds with nothing held back whose window has passed (under the lock); if that is not
        enough, the oldest ones (their counts, if any, are lost: a flood of distinct warnings)."""
        for kind in [k for k, seen in self._kinds.items() if not seen[2] and now - seen[0] >= self.window_s]:
            del self._kinds[kind]
        while len(self._kinds) > MAX_KINDS:
            del self._kinds[next(iter(self._kinds))]

    def _with_held_back(self, event: dict, shown: tuple | None) -> dict:
        """``event`` with a line before it for each other kind whose repeats are held back (then counted as told)."""
        lines = []
        with self._lock:
            for kind, seen in self._kinds.items():
                if kind != shown and seen[2]:
                    name = dict(kind[1]).get("event", "")
                    lines.append(f"{event.get('timestamp', '')} {seen[3]:<7} {name}  {_repeated(seen[2], seen[1])}")
                    seen[2] = 0
        if lines:
            event["_held_back"] = lines
        return event


def configure_logging(verbosity: int = 0, fmt: str = "auto", *, service: bool = False) -> str:
    """Log lines on stderr, in the format that fits where they go (:func:`log_format_for`): returns it.

    Levels: ``verbosity`` 0 = warnings, 1 = info, 2 = debug.  A ``service`` (the daemon) logging to
    journald or a pipe logs at info from 0 (its per-second status lines are its record); at a terminal it
    stays quiet (its banner first, status lines only with ``-v``).

    At a terminal (``human``) a warning repeated again and again is shown once a minute with a count
    (``RepeatLimiter``); the JSON log keeps every event: journald, Loki or a script counts and rate-limits
    as it likes, and the per-attempt detail of a port's retries is there when one needs it.

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
    limit: list[Any] = [RepeatLimiter()] if fmt == "human" else []  # a person skims; a machine counts for itself
    structlog.configure(
        processors=[structlog.processors.add_log_level, stamp, *limit, exceptions, renderer],
        wrapper_class=structlog.make_filtering_bound_logger(level),
        # sys.stderr looked up at each use, not bound now: it may be replaced later (a test's capture)
        logger_factory=lambda *_: structlog.PrintLogger(file=sys.stderr),
        cache_logger_on_first_use=False,
    )
    return fmt
