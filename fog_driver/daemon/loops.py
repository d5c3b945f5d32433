"""Handing a change to a listener's event loop from another thread (the NDJSON hub's and the web view's)."""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Callable


def apply_on_loop(
    loop: asyncio.AbstractEventLoop | None,
    thread: threading.Thread | None,
    apply: Callable[[], None],
    timeout_s: float,
) -> bool:
    """``apply()`` on ``loop`` (run by ``thread``), waiting ``timeout_s`` at most for it to run; at once, here,
    when no loop runs (none, not running yet or any more, closed meanwhile) or when called on the loop's own
    thread.  False when the wait ran out (``apply`` still runs when the loop gets to it)."""
    if loop is None or not loop.is_running() or threading.current_thread() is thread:
        apply()
        return True
    applied = threading.Event()

    def run() -> None:
        try:
            apply()
        finally:
            applied.set()

    try:
        loop.call_soon_threadsafe(run)
    except RuntimeError:  # the loop closed meanwhile: no client is left to apply it to
        apply()
        return True
    return applied.wait(timeout_s)
