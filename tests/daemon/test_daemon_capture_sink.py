"""The raw capture's own thread (``rawlog.CaptureSink``): the reader never waits for the disk, a failing disk
degrades the capture and never the daemon, and the sidecars say exactly what the files hold.

No sleeps: the tests wait on the sink's status changes (its ``on_status`` callback) with bounded timeouts."""

from __future__ import annotations

import hashlib
import os
import queue
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from fog_driver.daemon import rawlog
from fog_driver.daemon.rawlog import CaptureSink, RotatingCapture, repair_interrupted
from fog_driver.samples.captures import read_provenance, write_provenance

TIMEOUT_S = 20.0


class Disk:
    """A disk that fills up at ``free`` bytes (writes take what fits, then fail with ``error``) and can stall."""

    def __init__(self, free: int | None = None) -> None:
        self.free = free
        self.error = OSError(28, "No space left on device")
        self.open = threading.Event()
        self.open.set()

    def wrap(self, real):
        disk = self

        class File:
            closed = property(lambda self: real.closed)

            def write(self, data):
                disk.open.wait(TIMEOUT_S)
                if disk.free is not None:
                    if disk.free == 0:
                        raise disk.error
                    data = bytes(data)[: disk.free]
                    disk.free -= len(data)
                return real.write(data)

            def fileno(self):
                return real.fileno()

            def close(self):
                real.close()

        return File()


@pytest.fixture
def disk(monkeypatch):
    d = Disk()
    real_init = rawlog.CaptureWriter.__init__

    def init(self, *args, **kwargs):
        real_init(self, *args, **kwargs)
        self._file = d.wrap(self._file)

    monkeypatch.setattr(rawlog.CaptureWriter, "__init__", init)
    return d


def statuses() -> tuple[queue.Queue, callable]:
    q: queue.Queue = queue.Queue()
    return q, q.put


def until(q: queue.Queue, status: str) -> list[str]:
    """The statuses seen up to and including ``status`` (bounded wait)."""
    seen = []
    while not seen or seen[-1] != status:
        seen.append(q.get(timeout=TIMEOUT_S))
    return seen


def test_bytes_and_events_land_in_order_with_their_byte_offsets(tmp_path):
    q, on_status = statuses()
    sink = CaptureSink(RotatingCapture(tmp_path, max_bytes=1000), on_status=on_status)
    sink.note({"event": "model", "sha256": "ab"})  # before any byte: at byte 0 of the first file
    sink.put(b"a" * 600)
    sink.note({"event": "adapt", "reference_dph": 0.0})
    sink.put(b"b" * 600)  # rotates: a new file
    sink.note({"event": "zero"})
    assert sink.close()
    files = sink.capture.files
    assert [p.read_bytes() for p in files] == [b"a" * 600, b"b" * 600]
    first, second = (read_provenance(p) for p in files)
    assert [(e["event"], e["at_byte"]) for e in first["events"]] == [("model", 0), ("adapt", 600)]
    assert [(e["event"], e["at_byte"]) for e in second["events"]] == [("zero", 600)]
    assert first["status"] == second["status"] == "complete"
    assert until(q, "closed") == ["recording", "closed"]
    assert sink.status_fields() == {"status": "closed", "bytes": 1200, "bytes_lost": 0, "failures": 0}


@pytest.mark.parametrize("error", [OSError(28, "No space left on device"), OSError(5, "Input/output error")])
def test_a_full_disk_degrades_the_capture_the_sidecar_stays_true_and_a_new_file_follows(tmp_path, disk, error):
    """The review's E7: the failed sidecar claimed bytes that never reached the disk, and the daemon stopped.
    A full disk, or one that fails (EIO)."""
    disk.free, disk.error = 1000, error
    q, on_status = statuses()
    sink = CaptureSink(RotatingCapture(tmp_path), retry_first_s=0.05, on_status=on_status)
    sink.put(b"x" * 700)
    sink.put(b"y" * 700)  # 300 fit, then the disk is full
    assert until(q, "failed") == ["recording", "failed"]
    failed = sink.capture.files[0]
    side = read_provenance(failed)
    data = failed.read_bytes()
    assert side["status"].startswith("failed: ") and error.strerror in side["status"]
    assert side["bytes"] == len(data) == 1000 and side["sha256"] == hashlib.sha256(data).hexdigest()
    assert (
        sink.status_fields()["status"] in ("failed", "retrying")
        and error.strerror in sink.status_fields()["last_error"]
    )
    disk.free = None  # space again
    until(q, "retrying")
    sink.put(b"z" * 50)  # tries a new file
    until(q, "recording")
    assert sink.close()
    second = sink.capture.files[1]
    assert second.read_bytes() == b"z" * 50
    events = read_provenance(second)["events"]
    assert [(e["event"], e["bytes"], e["at_byte"]) for e in events] == [("bytes_lost", 400, 0)]
    assert sink.bytes_lost == 400 and sink.bytes_put == 1000 + 400 + 50  # captured + lost = put
    assert sink.failures == 1


def test_a_stalled_disk_never_blocks_put_and_the_overflow_is_counted(tmp_path, disk):
    disk.open.clear()  # the disk stalls
    sink = CaptureSink(RotatingCapture(tmp_path), max_queue_bytes=1000)
    putter_done = threading.Event()

    def putter():
        for _ in range(50):
            sink.put(b"p" * 100)
        putter_done.set()

    threading.Thread(target=putter).start()
    assert putter_done.wait(TIMEOUT_S)  # put() returned while the writer thread was stuck on the disk
    disk.open.set()
    assert sink.close()
    captured = b"".join(p.read_bytes() for p in sink.capture.files)
    assert sink.bytes_lost > 0 and len(captured) + sink.bytes_lost == 5000
    assert sink.status_fields()["bytes"] == len(captured)


def test_no_descriptor_left_at_rotation_is_retried_not_fatal(tmp_path, monkeypatch):
    """The review's E4: idle clients took every descriptor, the rotation could not open its file, exit 73."""
    q, on_status = statuses()
    sink = CaptureSink(RotatingCapture(tmp_path, max_bytes=10), retry_first_s=0.05, on_status=on_status)
    sink.put(b"0123456789")
    until(q, "recording")
    real_init = rawlog.CaptureWriter.__init__
    exhausted = threading.Event()
    exhausted.set()

    def init(self, path, *args, **kwargs):
        if exhausted.is_set():
            raise rawlog.OutputFileError(f"{path}: cannot create capture: Too many open files")
        real_init(self, path, *args, **kwargs)

    monkeypatch.setattr(rawlog.CaptureWriter, "__init__", init)
    sink.put(b"abcdefghij")  # rotation: the next file cannot be opened
    until(q, "failed")
    exhausted.clear()
    until(q, "retrying")
    sink.put(b"k")
    until(q, "recording")
    assert sink.close()
    assert [p.read_bytes() for p in sink.capture.files] == [b"0123456789", b"k"]
    assert read_provenance(sink.capture.files[1])["events"][0] == {
        **read_provenance(sink.capture.files[1])["events"][0],
        "event": "bytes_lost",
        "bytes": 10,
        "at_byte": 0,
    }
    assert not list(tmp_path.glob("*.tmp"))


def test_a_sidecar_a_killed_process_left_recording_is_repaired_and_a_live_one_is_not(tmp_path):
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    dead_pid = int(dead.stdout)
    for name, pid in (("fog-000000-x.bin", dead_pid), ("fog-000001-x.bin", os.getpid())):
        (tmp_path / name).write_bytes(b"partial capture" + name.encode())
        write_provenance(tmp_path / name, {"status": "recording", "pid": pid, "port": "/dev/ttyUSB0"})
    repaired = repair_interrupted(tmp_path)
    assert repaired == [tmp_path / "fog-000000-x.bin"]
    side = read_provenance(tmp_path / "fog-000000-x.bin")
    data = (tmp_path / "fog-000000-x.bin").read_bytes()
    assert side["status"] == "interrupted" and side["bytes"] == len(data) and side["port"] == "/dev/ttyUSB0"
    assert side["sha256"] == hashlib.sha256(data).hexdigest()
    assert read_provenance(tmp_path / "fog-000001-x.bin")["status"] == "recording"  # ours: alive


def test_the_next_run_numbers_its_files_after_the_repaired_ones(tmp_path):
    (tmp_path / "fog-000041-20240101T000000Z.bin").write_bytes(b"old")
    with RotatingCapture(tmp_path) as cap:
        cap.write(b"new")
    assert cap.files[0].name.startswith("fog-000042-")


@pytest.mark.parametrize(
    "kwargs", [{"max_queue_bytes": 0}, {"fsync_every_s": 0}, {"retry_first_s": 2, "retry_max_s": 1}]
)
def test_bad_sink_settings_are_value_errors(tmp_path, kwargs):
    with pytest.raises(ValueError):
        CaptureSink(RotatingCapture(tmp_path), **kwargs)
    assert Path(tmp_path).is_dir()


class CountingCapture(RotatingCapture):
    """A ``RotatingCapture`` that says when it writes (the writer thread's calls, in order)."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.writes: queue.Queue = queue.Queue()

    def write(self, chunk: bytes) -> None:
        super().write(chunk)
        self.writes.put(bytes(chunk))


def test_while_bytes_flow_the_writer_takes_them_in_batches_not_one_wake_per_chunk(tmp_path):
    """The first chunk after a pause is written at once; the chunks that follow while the writer gathers wait
    for its next write (one wake-up per ``write_every_s``, which is set long here so the test does not depend on
    timing); closing writes them all, in order."""
    capture = CountingCapture(tmp_path)
    sink = CaptureSink(capture, write_every_s=3600.0)
    sink.put(b"first")
    assert capture.writes.get(timeout=TIMEOUT_S) == b"first"  # at once: the writer was idle
    for k in range(100):
        sink.put(b"%03d" % k)
    assert capture.writes.empty()  # gathered, not written per chunk
    assert sink.close()
    later = []
    while not capture.writes.empty():
        later.append(capture.writes.get_nowait())
    assert b"".join(later) == b"".join(b"%03d" % k for k in range(100))
    assert capture.files[0].read_bytes() == b"first" + b"".join(b"%03d" % k for k in range(100))


def test_a_batch_of_write_at_bytes_is_written_without_waiting_for_the_interval(tmp_path):
    """An unpaced replay's 64 kB chunks are written as they come, not held for ``write_every_s``."""
    capture = CountingCapture(tmp_path)
    sink = CaptureSink(capture, write_every_s=3600.0)
    sink.put(b"first")
    assert capture.writes.get(timeout=TIMEOUT_S) == b"first"
    big = bytes(range(256)) * (rawlog.WRITE_AT_BYTES // 256)
    sink.put(big)  # the writer gathers for an hour, unless a full batch wakes it
    assert capture.writes.get(timeout=TIMEOUT_S) == big
    assert sink.close()
    assert capture.files[0].read_bytes() == b"first" + big


def test_write_every_s_must_be_positive(tmp_path):
    with pytest.raises(ValueError, match="write_every_s"):
        CaptureSink(RotatingCapture(tmp_path), write_every_s=0.0)
