"""``record`` stopped by a signal or by ``--duration`` ends on a frame boundary, in every frame format: the port
is read on, a byte at a time, until the frame under way is whole; no byte the port delivered is left out.

The port is ``socket://`` to a server in this process that sends a stream in two parts: up to a few bytes into
a frame, then (once the recording was told to stop) the rest."""

from __future__ import annotations

import socket
import threading
from pathlib import Path

import pytest

from fog_driver.samples.captures import inspect_capture
from fog_driver.samples.record import record
from fog_driver.samples.sources import WireSettings

DATA = Path(__file__).resolve().parents[1] / "data"
GUARD_S = 30.0
#: How far into a frame the first part ends.
INTO_FRAME = 5


def stream_of(wire_format: str, tmp_path: Path) -> tuple[bytes, WireSettings]:
    """A clean stream of ``wire_format`` frames and the settings that decode it."""
    if wire_format == "fog-v1":
        return (DATA / "sim-short.bin").read_bytes(), WireSettings()
    from fog_driver.lab.profiles import load_profile
    from fog_driver.sim.capture import simulate_to_file
    from fog_driver.sim.instrument import Simulator

    sim = Simulator(load_profile("paper"), rate_hz=100, seed=0, wire_format=wire_format)
    result = simulate_to_file(sim, tmp_path / "source.bin", duration_s=5)
    return result.capture.read_bytes(), WireSettings(format=wire_format, rate_hz=100)


def frame_starts(data: bytes, wire: WireSettings) -> list[int]:
    """Where each frame of the clean stream ``data`` starts (every byte in a frame: checked)."""
    decoder = wire.make_decoder()
    events = decoder.feed(data) + decoder.close()
    assert decoder.counters.bytes_discarded == 0 and decoder.counters.bytes_in_frames == len(data)
    return [event.offset for event in events]


class TwoPartServer:
    """Accepts one connection; sends ``first`` once the recorder's port is open (``on_state``: pyserial's open of
    a ``socket://`` port discards what came before it), then ``rest`` once ``go`` is set; holds the connection."""

    def __init__(self, first: bytes, rest: bytes, go: threading.Event) -> None:
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.url = f"socket://127.0.0.1:{self.listener.getsockname()[1]}"
        self.first, self.rest, self.go = first, rest, go
        self.opened = threading.Event()
        self.done = threading.Event()
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        connection, _ = self.listener.accept()
        with connection:
            if self.opened.wait(GUARD_S):
                connection.sendall(self.first)
            if self.go.wait(GUARD_S):
                connection.sendall(self.rest)
            self.done.wait(GUARD_S)

    def on_state(self, event) -> None:
        if event.state == "open":
            self.opened.set()

    def close(self) -> None:
        self.done.set()
        self.thread.join(GUARD_S)
        self.listener.close()


@pytest.mark.parametrize("wire_format", ["fog-v1", "kvh-a", "ixblue-stdbin"])
def test_record_stopped_by_a_signal_ends_on_a_frame_boundary(tmp_path, wire_format):
    """The review's finding 16: ``record socket://... --duration 5`` ended mid-frame ("2 bytes discarded, 2 in a
    cut-off last frame"), so ``inspect --strict`` failed a good recording.  Ctrl-C sets the same stop."""
    data, wire = stream_of(wire_format, tmp_path)
    starts = frame_starts(data, wire)
    k = len(starts) // 2
    first = data[: starts[k] + INTO_FRAME]
    stop = threading.Event()
    server = TwoPartServer(first, data[len(first) :], stop)

    def on_progress(progress) -> None:
        if progress.bytes_written >= len(first):  # the first part is in: stop (the server then sends the rest)
            stop.set()

    try:
        out = tmp_path / "rec.bin"
        result = record(
            server.url,
            out,
            stop=stop,
            on_progress=on_progress,
            on_state=server.on_state,
            progress_every_s=0.0,
            wire=wire,
            reconnect=False,
        )
    finally:
        server.close()
    captured = out.read_bytes()
    assert captured == data[: starts[k + 1]]  # the frame under way, whole, and nothing after it
    assert result.bytes_written == len(captured)
    decoder = wire.make_decoder()
    decoder.feed(captured)
    decoder.close()
    assert decoder.counters.truncated_frames == 0 and decoder.counters.bytes_discarded == 0


def test_record_stopped_by_its_duration_ends_on_a_frame_boundary_and_inspects_clean(tmp_path):
    data, wire = stream_of("fog-v1", tmp_path)
    starts = frame_starts(data, wire)
    first = data[: starts[10] + INTO_FRAME]
    stop = threading.Event()
    server = TwoPartServer(first, data[len(first) :], stop)  # the rest once the duration has passed
    try:
        out = tmp_path / "rec.bin"
        record(server.url, out, duration_s=0.2, stop=stop, on_state=server.on_state, reconnect=False)
    finally:
        server.close()
    captured = out.read_bytes()
    assert len(captured) in set(starts) and captured == data[: len(captured)]
    summary = inspect_capture(out)
    assert summary.problems == []  # inspect --strict: clean
