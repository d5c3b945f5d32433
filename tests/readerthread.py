"""``Reader``: a ``PortReader`` in a thread, for tests; its state events and data chunks in one ordered queue.

No test sleeps to synchronise on it: the reading thread puts each event and chunk on ``items`` in the
order they happened, and a test waits on that queue; ``GUARD_S`` only turns a hang into a failure.
"""

from __future__ import annotations

import queue
import threading

from fog_driver.transport import PortEvent, PortReader

GUARD_S = 30.0  #: failure guard for waits on the reading thread; never reached when things work


class Reader:
    """A ``PortReader`` in a thread; data chunks and state events in one queue, in the order they happened.

    ``items`` holds ``("state", PortEvent)`` and ``("data", bytes)``; ``opened`` is set at the first
    ``open`` state and ``done`` when ``chunks`` returned (``error`` holds what it raised, if anything).
    """

    def __init__(self, url: str, **kwargs) -> None:
        self.items: queue.Queue[tuple[str, object]] = queue.Queue()
        self.opened = threading.Event()
        self.stop = threading.Event()
        self.done = threading.Event()
        self.error: BaseException | None = None
        kwargs.setdefault("read_timeout_s", 0.02)
        self.reader = PortReader(url, on_state=self._on_state, **kwargs)
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _on_state(self, event: PortEvent) -> None:
        self.items.put(("state", event))
        if event.state == "open":
            self.opened.set()

    def _on_chunk(self, chunk: bytes) -> None:
        self.items.put(("data", chunk))

    def _run(self) -> None:
        try:
            for chunk in self.reader.chunks(self.stop):
                self._on_chunk(chunk)
        except BaseException as exc:  # handed to the test thread
            self.error = exc
        finally:
            self.done.set()

    def receive(self, n_bytes: int) -> bytes:
        """Collect exactly ``n_bytes`` of data (fails on a guard timeout or on extra bytes)."""
        got = bytearray()
        while len(got) < n_bytes:
            kind, item = self.items.get(timeout=GUARD_S)
            if kind == "data":
                got += item
        assert len(got) == n_bytes
        return bytes(got)

    def until_state(self, state: str) -> tuple[list[PortEvent], bytes]:
        """The events up to and including the next ``state``, and the data that came before it."""
        events: list[PortEvent] = []
        data = bytearray()
        while True:
            kind, item = self.items.get(timeout=GUARD_S)
            if kind == "data":
                data += item
                continue
            events.append(item)
            if item.state == state:
                return events, bytes(data)

    def next_item(self) -> tuple[str, object]:
        """The next event or chunk, whichever came first."""
        return self.items.get(timeout=GUARD_S)

    def join(self) -> None:
        """Stop (if not finished already), join, re-raise a reader error."""
        self.stop.set()
        assert self.done.wait(GUARD_S), "reader did not return after stop"
        self.thread.join(GUARD_S)
        if self.error is not None:
            raise self.error

    def finish(self) -> list[tuple[str, object]]:
        """``join``, then everything not yet taken from ``items``."""
        self.join()
        rest = []
        while not self.items.empty():
            rest.append(self.items.get_nowait())
        return rest
