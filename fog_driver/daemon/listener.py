"""The skeleton both of the daemon's listeners stand on (the NDJSON ``hub.Hub`` and the ``web.server.WebView``).

A listener runs an asyncio loop in a thread of its own.  What they share, written here once:

- readiness: ``_start_thread`` starts the thread and returns the address once the socket listens (the listener's
  ``_main`` calls ``_listening``), or raises what stopped it from listening (OSError: the address is taken...);
- close: ``_stop_thread`` sets the stop event on the loop and joins the thread; ``_serve_until_stopped`` runs the
  listener's background tasks (its sweeper) until then, cancels them, closes what the listener opened and counts
  the log lines left out to the end;
- the limits: ``slots`` (``guards.Slots``) admits each new connection (``_admit``: refused ones are counted in
  ``_refused``; those it evicts to make room go to the listener's ``_make_room``);
- the log: ``_log`` writes a client-caused line at most ``log_lines_per_s`` a second per event
  (``guards.LogRateLimiter``), the sweeper (``_sweep_loop``: ``_sweep(now)`` every ``_sweep_period()`` s)
  summarizes the rest;
- settings from other threads: ``_call_on_loop`` (``loops.apply_on_loop``).
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import threading
import time
from collections.abc import Awaitable, Callable, Coroutine, Hashable
from typing import Any

from .guards import Admission, LogRateLimiter, Slots
from .loops import apply_on_loop


class Listener:
    """A listener's thread, loop, readiness, close, slots and rate-limited log (see the module docstring).

    A subclass writes ``_main`` (listen, call ``_listening``, then ``await _serve_until_stopped(...)``),
    ``_failed`` (the loop ended by an error after it listened), ``_make_room`` and, with a sweeper,
    ``_sweep_period`` and ``_sweep``."""

    def __init__(
        self, *, thread_name: str, logger: Any, log_lines_per_s: int, max_connections: int, max_per_peer: int
    ) -> None:
        self._thread_name = thread_name
        self._logger = logger
        self._log_limiter = LogRateLimiter(log_lines_per_s)
        self.slots = Slots(max_connections, max_per_peer)  #: who holds a connection (``guards.Slots``)
        self._refused = 0
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._ready = threading.Event()
        self._start_error: BaseException | None = None
        self._stop_event: asyncio.Event | None = None
        self._address: tuple[str, int] | None = None

    @property
    def address(self) -> tuple[str, int] | None:
        """``(host, port)`` listened on, once started."""
        return self._address

    @property
    def running(self) -> bool:
        """The listener's loop thread is alive (a watchdog pings only while it is)."""
        return self._thread is not None and self._thread.is_alive()

    # ------------------------------------------------------------------ readiness and close (any thread)

    def _start_thread(self, timeout_s: float | None = None) -> tuple[str, int]:
        """Run the loop in its thread; the address once it listens.  What stopped it from listening is raised
        (the thread joined); OSError when it did not listen within ``timeout_s`` (None: no limit)."""
        self._thread = threading.Thread(target=self._run, name=self._thread_name, daemon=True)
        self._thread.start()
        if not self._ready.wait(timeout_s):
            raise OSError(f"the {self._thread_name} listener did not start within {timeout_s:g} s")
        if self._start_error is not None:
            self._thread.join()
            self._thread = None
            raise self._start_error
        assert self._address is not None
        return self._address

    def _stop_thread(self, timeout_s: float) -> None:
        """Set the stop event on the loop and join the thread (``timeout_s`` at most); nothing when not started."""
        loop, thread = self._loop, self._thread
        if thread is None:
            return
        if loop is not None:
            with contextlib.suppress(RuntimeError):  # loop already closed
                loop.call_soon_threadsafe(self._request_stop)
        thread.join(timeout_s)
        self._thread = None

    def _request_stop(self) -> None:
        if self._stop_event is not None:
            self._stop_event.set()

    def _call_on_loop(self, apply: Callable[[], None], timeout_s: float) -> bool:
        """``apply()`` on the loop, waiting ``timeout_s`` at most (False: it ran out); at once when no loop runs."""
        return apply_on_loop(self._loop, self._thread, apply, timeout_s)

    # ------------------------------------------------------------------ the loop's thread

    def _prepare_loop(self, loop: asyncio.AbstractEventLoop) -> None:
        """Set up the new loop before it runs (an exception handler...); nothing by default."""

    def _failed(self, exc: BaseException) -> None:
        """The loop ended by ``exc`` after the listener listened: log it."""
        raise NotImplementedError

    async def _main(self) -> None:
        raise NotImplementedError

    def _run(self) -> None:
        loop = asyncio.new_event_loop()
        self._prepare_loop(loop)
        try:
            loop.run_until_complete(self._main())
        except BaseException as exc:  # noqa: BLE001 - reported to start(), or logged once the listener ran
            if not self._ready.is_set():
                self._start_error = exc
            else:
                self._failed(exc)
        finally:
            self._ready.set()
            self._loop = None
            try:
                loop.run_until_complete(loop.shutdown_asyncgens())
            finally:
                loop.close()

    def _listening(self, address: tuple[str, int]) -> None:
        """The socket listens on ``address`` (called on the loop): ``_start_thread`` returns it."""
        self._address = address
        self._loop = asyncio.get_running_loop()
        self._ready.set()

    async def _serve_until_stopped(
        self, background: list[Coroutine[Any, Any, None]], close: Callable[[], Awaitable[None]]
    ) -> None:
        """Run the ``background`` tasks until the stop event is set; then cancel them, ``await close()`` and log
        the count of every line left out (the last ones too)."""
        tasks = [asyncio.create_task(coroutine) for coroutine in background]
        try:
            assert self._stop_event is not None
            await self._stop_event.wait()
        finally:
            for task in tasks:
                task.cancel()
            await close()
            self._log_limiter.log_suppressed(self._logger, math.inf)

    # ------------------------------------------------------------------ limits, sweeper and log (the loop)

    def _admit(self, key: Hashable, peer: str | None, *, authorized: bool) -> str | None:
        """Take a slot for a new connection ``key`` from ``peer``: None when it may go on (the connections it
        evicts go to ``_make_room``), else the cap that refuses it (``"total"`` or ``"peer"``, counted)."""
        return self._settle(self.slots.admit(key, peer, authorized=authorized))

    def _settle(self, admission: Admission) -> str | None:
        """Carry out a slot decision (``_admit``'s, or a move to another address): count a refusal, or make room."""
        if admission.refused is not None:
            self._refused += 1
            return admission.refused
        for evicted in admission.evicted:
            self._make_room(evicted)
        return None

    def _make_room(self, key: Hashable) -> None:
        """Close the connection ``key``: a new one needs its slot (``guards.Slots``)."""
        raise NotImplementedError

    def _sweep_period(self) -> float:
        raise NotImplementedError

    def _sweep(self, now: float) -> None:
        raise NotImplementedError

    async def _sweep_loop(self) -> None:
        """``_sweep(now)`` every ``_sweep_period()`` s (read again each time: a limit may change meanwhile)."""
        while True:
            await asyncio.sleep(self._sweep_period())
            self._sweep(time.monotonic())

    def _log(self, level: str, event: str, **fields: Any) -> None:
        """Log a per-client ``event``, unless ``log_lines_per_s`` of it were logged in this second (then count it).

        A flood of connections or guesses thus costs the log a few lines a second and one
        ``log_lines_suppressed`` summary line a second per event."""
        if self._log_limiter.allow(event, time.monotonic()):
            getattr(self._logger, level)(event, **fields)


__all__ = ["Listener"]
