"""Signals acted on in an ordinary thread, never inside the signal handler.

A Python signal handler runs in the main thread between two bytecodes, wherever that thread happens
to be: inside ``threading.Event.wait`` holding the event's non-reentrant lock, inside the service's
lock, halfway through a reload. A handler that sets an ``Event``, takes a lock or reloads a model
can deadlock the process on its own thread. (Seen: a SIGTERM that landed in ``Event.wait`` while the
status loop held the event's condition; the daemon never exited.)

So the Python-level handler does nothing (or only what is safe anywhere, such as raising
``KeyboardInterrupt``). The interpreter's C-level handler writes the signal's number to a wake-up
socket (:func:`signal.set_wakeup_fd`); a dispatcher thread reads the numbers and calls
``on_signal(signum)`` one after another, in arrival order. A burst of SIGHUPs is a queue of
reloads, never a re-entry; SIGTERM during a reload is acted on when the reload ends.

A process that is to be the daemon calls :func:`defer_hangups` first thing: SIGHUP's default action ends the
process, and the daemon takes half a second or more to import, load its model and start its dispatcher.  Until
the dispatcher takes it over a SIGHUP is counted (:func:`deferred_hangups`), not acted on.
"""

from __future__ import annotations

import os
import signal
import socket
import threading
from collections.abc import Callable, Iterable
from types import FrameType

InHandler = Callable[[int, FrameType | None], None]


def _ignore(_signum: int, _frame: FrameType | None) -> None:
    """The Python-level handler: nothing (the number already went to the wake-up socket)."""


#: SIGHUPs counted since ``defer_hangups`` (None: not deferring).
_hangups: list[int] | None = None


def _count_hangup(_signum: int, _frame: FrameType | None) -> None:
    """SIGHUP before the dispatcher: counted (plain arithmetic on a list: safe at any bytecode)."""
    if _hangups is not None:
        _hangups[0] += 1


def defer_hangups() -> None:
    """From now on a SIGHUP is counted, not fatal, until a ``SignalDispatcher`` takes it over (and again after
    it, if the dispatcher gives back this handler).  For a process that is to be the daemon, first thing; main
    thread only.  Called again: nothing changes (the count goes on)."""
    global _hangups
    if _hangups is None:
        _hangups = [0]
        signal.signal(signal.SIGHUP, _count_hangup)


def undefer_hangups() -> None:
    """Undo ``defer_hangups`` (the process is not the daemon after all): SIGHUP's default action again, and a
    SIGHUP that came meanwhile is acted on now, as it would have been."""
    global _hangups
    if _hangups is not None:
        came, _hangups = _hangups[0], None
        signal.signal(signal.SIGHUP, signal.SIG_DFL)
        if came:
            os.kill(os.getpid(), signal.SIGHUP)


def deferred_hangups() -> int | None:
    """How many SIGHUPs ``defer_hangups``'s handler has counted; None if it was never installed."""
    return None if _hangups is None else _hangups[0]


class SignalDispatcher:
    """Deliver ``signals`` to ``on_signal(signum)`` in a dispatcher thread, while in a ``with`` block.

    ``in_handler`` (optional) runs inside the Python-level handler in the main thread: keep it to
    what is safe at any bytecode (reading a flag, raising ``KeyboardInterrupt``). Must be entered
    from the main thread, as :func:`signal.signal` requires. On exit the previous handlers and
    wake-up descriptor are restored, and the dispatcher is joined (it finishes the call in progress).
    ``ignore_after``: on exit the signals are ignored (``SIG_IGN``) instead of given back their previous
    handlers: for a process that ends there, where a signal (a second Ctrl-C) must not end it halfway.
    ``deliver(signum)`` queues an action as if the signal had come.
    """

    def __init__(
        self,
        signals: Iterable[int],
        on_signal: Callable[[int], None],
        *,
        in_handler: InHandler | None = None,
        join_timeout_s: float = 30.0,
        ignore_after: bool = False,
    ) -> None:
        self.signals = tuple(signals)
        self.ignore_after = ignore_after
        self.on_signal = on_signal
        self.in_handler = in_handler or _ignore
        self.join_timeout_s = join_timeout_s
        self._previous: dict[int, object] = {}
        self._previous_fd = -1
        self._read: socket.socket | None = None
        self._write: socket.socket | None = None
        self._thread: threading.Thread | None = None

    def __enter__(self) -> SignalDispatcher:
        self._read, self._write = socket.socketpair()
        self._write.setblocking(False)  # set_wakeup_fd requires it: the C handler must never block
        self._thread = threading.Thread(target=self._dispatch, name="signals", daemon=True)
        self._thread.start()
        self._previous_fd = signal.set_wakeup_fd(self._write.fileno(), warn_on_full_buffer=False)
        self._previous = {s: signal.signal(s, self.in_handler) for s in self.signals}
        return self

    def deliver(self, signum: int) -> None:
        """Queue ``on_signal(signum)`` behind the actions already queued, as the signal would (inside the block)."""
        assert self._write is not None
        self._write.send(bytes([signum]))

    def __exit__(self, *exc: object) -> None:
        for s, handler in self._previous.items():
            signal.signal(s, signal.SIG_IGN if self.ignore_after else handler)
        signal.set_wakeup_fd(self._previous_fd)
        assert self._write is not None and self._read is not None and self._thread is not None
        self._write.close()  # the dispatcher reads end-of-file and returns
        self._thread.join(self.join_timeout_s)
        self._read.close()

    def _dispatch(self) -> None:
        assert self._read is not None
        while True:
            try:
                numbers = self._read.recv(256)
            except OSError:
                return
            if not numbers:
                return
            for signum in numbers:
                if signum not in self.signals:
                    continue  # another signal with a Python handler also reaches the wake-up socket
                try:
                    self.on_signal(signum)
                except Exception as exc:  # noqa: BLE001 - a failed action must not end signal handling
                    import structlog  # here: the command line imports this module before anything heavy

                    structlog.get_logger("fog_driver.signals").exception(
                        "signal_action_failed", signal=signal.Signals(signum).name, reason=str(exc)
                    )


def stop_on_signals(
    stop: threading.Event, signals: Iterable[int] = (signal.SIGINT, signal.SIGTERM)
) -> SignalDispatcher:
    """The first signal sets ``stop`` (a clean end); one more after that raises ``KeyboardInterrupt``.

    The handler counts the signals itself: it must not read ``stop``, which the dispatcher thread may
    already have set for this very signal (the wake-up byte reaches it at once, while the Python handler
    waits for the main thread's next bytecode), and a first SIGTERM would then end as an interrupt."""
    received = [0]

    def force(_signum: int, _frame: FrameType | None) -> None:
        received[0] += 1  # plain arithmetic on a list: safe at any bytecode, unlike Event.set
        if received[0] > 1:
            raise KeyboardInterrupt

    return SignalDispatcher(signals, lambda _signum: stop.set(), in_handler=force)
