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
"""

from __future__ import annotations

import signal
import socket
import threading
from collections.abc import Callable, Iterable
from types import FrameType

import structlog

log = structlog.get_logger("fog_driver.signals")

InHandler = Callable[[int, FrameType | None], None]


def _ignore(_signum: int, _frame: FrameType | None) -> None:
    """The Python-level handler: nothing (the number already went to the wake-up socket)."""


class SignalDispatcher:
    """Deliver ``signals`` to ``on_signal(signum)`` in a dispatcher thread, while in a ``with`` block.

    ``in_handler`` (optional) runs inside the Python-level handler in the main thread: keep it to
    what is safe at any bytecode (reading a flag, raising ``KeyboardInterrupt``). Must be entered
    from the main thread, as :func:`signal.signal` requires. On exit the previous handlers and
    wake-up descriptor are restored, and the dispatcher is joined (it finishes the call in progress).
    """

    def __init__(
        self,
        signals: Iterable[int],
        on_signal: Callable[[int], None],
        *,
        in_handler: InHandler | None = None,
        join_timeout_s: float = 30.0,
    ) -> None:
        self.signals = tuple(signals)
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

    def __exit__(self, *exc: object) -> None:
        for s, handler in self._previous.items():
            signal.signal(s, handler)
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
                    log.exception("signal_action_failed", signal=signal.Signals(signum).name, reason=str(exc))


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
