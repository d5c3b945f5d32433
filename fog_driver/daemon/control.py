"""A control command's answer, waited for on the hub's loop without blocking it (asyncio; no socket).

The service's ``control(name, args, client_id)`` runs in one of the hub's worker threads (never on the loop, so a
slow command delays nobody's ANGLE lines) and returns a dict, or a ``concurrent.futures.Future`` of one that its
owner completes later.  The callback and the Future share one deadline, ``control_timeout_s``.  The hub only
ever *waits* for a Future: a timeout or the client hanging up abandons the wait, and the Future's owner may
complete it whenever it likes (the hub never cancels it).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
from collections.abc import Callable
from typing import Any

from .connection import control_error, control_reply

__all__ = ["NoAnswer", "answer_of", "control_answer"]

Control = Callable[[str, dict, int], "dict | concurrent.futures.Future | None"]


class NoAnswer(Exception):
    """A control command's answer did not come before its deadline."""


async def control_answer(
    pool: concurrent.futures.Executor | None, control: Control, name: str, args: dict, client_id: int, timeout_s: float
) -> dict:
    """The line answering ``?NAME``: ``control``'s reply run in ``pool`` (``connection.control_reply``), or the
    ERROR saying why there is none (no answer within ``timeout_s``, cancelled, the service's exception)."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout_s
    try:
        if pool is None:
            raise RuntimeError("the hub is stopping")
        reply = await answer_of(pool.submit(control, name, args, client_id), deadline)
        if isinstance(reply, concurrent.futures.Future):
            reply = await answer_of(reply, deadline)
    except NoAnswer:
        return {"class": "ERROR", "message": f"no answer within {timeout_s:g} s", "command": name}
    except concurrent.futures.CancelledError:
        return {"class": "ERROR", "message": "the command was cancelled", "command": name}
    except Exception as exc:  # noqa: BLE001 - the service's error becomes the client's ERROR
        return control_error(name, exc)
    return control_reply(name, reply)


async def answer_of(future: concurrent.futures.Future, deadline: float) -> Any:
    """``future``'s result (its exception raised), waited for until ``deadline`` (loop time).

    Raises ``NoAnswer`` when the deadline passes first.  Only the *wait* ends on a
    timeout or when the calling task is cancelled (the client hung up): ``future``
    itself is never cancelled, so whoever completes it later (the acquisition
    thread) never finds it cancelled.  (``asyncio.wrap_future`` would cancel it.)
    """
    loop = asyncio.get_running_loop()
    settled: asyncio.Future = loop.create_future()

    def on_done(_: concurrent.futures.Future) -> None:  # in whichever thread completed ``future``
        with contextlib.suppress(RuntimeError):  # the loop has closed: the hub stopped, nobody waits any more
            loop.call_soon_threadsafe(_settle, settled)

    if not future.done():
        future.add_done_callback(on_done)
        try:
            await asyncio.wait_for(settled, max(0.0, deadline - loop.time()))
        except TimeoutError:
            raise NoAnswer from None
    return future.result()


def _settle(waiter: asyncio.Future) -> None:
    """Mark ``waiter`` done, unless its wait was abandoned (cancelled) already."""
    if not waiter.done():
        waiter.set_result(None)
