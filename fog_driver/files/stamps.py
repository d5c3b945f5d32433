"""The time stamps the project's files carry (a leaf: the standard library only)."""

from __future__ import annotations

import datetime as _dt


def utc_now_iso() -> str:
    """Now, UTC, ISO 8601 to the millisecond with a ``Z``: ``2026-12-04T11:05:07.123Z``."""
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")
