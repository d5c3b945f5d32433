"""The command line: inspect and record, as a user runs them, including every kind of bad input."""

from __future__ import annotations

import hashlib
import io
import json
import os
import re
import socket
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
import structlog
import yaml
from cli_run import assert_one_line_error, run_cli

from fog_driver.client.display import Progress
from fog_driver.protocol import decode_bytes, encode_sample
from fog_driver.samples.captures import inspect_capture, read_provenance, sidecar_path, summarize
from fog_driver.samples.record import record
from fog_driver.transport import PtyPair

DATA = Path(__file__).resolve().parents[1] / "data"
FIXTURES = ("synthetic-clean", "synthetic-faults")


# --- fixtures ----------------------------------------------------------------------------------


def test_fixtures_are_small_and_reproducible():
    sys.path.insert(0, str(DATA))
    try:
        import make_fixtures
    finally:
        sys.path.remove(str(DATA))
    for name, make in make_fixtures.FIXTURES.items():
        data, truth = make()
        assert (DATA / f"{name}.bin").read_bytes() == data, f"{name}.bin differs from its generator"
        assert read_provenance(DATA / f"{name}.bin")["truth"] == truth
        assert len(data) < 1 << 20


# --- inspect -----------------------------------------------------------------------------------


@pytest.mark.parametrize("name", FIXTURES)
def test_inspect_json_matches_the_truth_written_by_construction(name):
    proc = run_cli("inspect", str(DATA / f"{name}.bin"), "--json")
    assert proc.returncode == 0, proc.stderr
    report = json.loads(proc.stdout)
    provenance = yaml.safe_load((DATA / f"{name}.bin.yaml").read_text())
    truth = provenance["truth"]
    for key in (
        "sample_frames",
        "identity_frames",
        "missing_frames",
        "seq_gaps",
        "crc_errors",
        "bytes_discarded",
        "thermometer_faults",
        "t_us_wraps",
    ):
        assert report[key] == truth[key], key
    instrument = provenance["instrument"]
    assert report["serial"] == instrument["serial"]
    assert report["firmware"] == instrument["firmware"]
    assert report["rate_hz"] == instrument["rate_hz"]
    # The wire carries a float32; JSON gives it exactly, widened to double.
    assert report["scale_arcsec_per_count"] == float(np.float32(instrument["scale_arcsec_per_count"]))
    assert report["duration_s"] == pytest.approx((1200 - 1) / 100)
    assert report["bytes"] == (DATA / f"{name}.bin").stat().st_size
    assert report["sha256"] == hashlib.sha256((DATA / f"{name}.bin").read_bytes()).hexdigest()
    required = {
        "sample_frames",
        "identity_frames",
        "crc_errors",
        "bytes_discarded",
        "seq_gaps",
        "missing_frames",
        "serial",
        "firmware",
        "rate_hz",
        "scale_arcsec_per_count",
        "duration_s",
        "thermometer_faults",
    }
    assert required <= report.keys()
    assert None not in report.values()  # absent values are omitted, never null


def test_inspect_reports_faults_flags_tail_and_temperatures():
    report = json.loads(run_cli("inspect", str(DATA / "synthetic-faults.bin"), "--json").stdout)
    truth = read_provenance(DATA / "synthetic-faults.bin")["truth"]
    assert report["tail_bytes_discarded"] == truth["tail_bytes"]
    assert report["truncated_frames"] == 1
    assert report["status_flags_seen"] == {"thermometer_fault": truth["thermometer_faults"]}
    top_lo, top_hi = report["temperature_range_c"]["top"]
    assert top_lo == 20.0 and top_hi == pytest.approx(20.0 + 0.05 * 11.99, abs=1 / 256)
    assert report["problems"]


def test_inspect_text_report_and_strict_exit():
    clean = run_cli("inspect", str(DATA / "synthetic-clean.bin"))
    assert clean.returncode == 0
    assert "verdict       clean" in clean.stdout
    assert "serial FOG-SYN-0001, firmware 1.2, 100 Hz nominal, scale 0.0125 arcsec/count" in clean.stdout
    assert run_cli("inspect", "--strict", str(DATA / "synthetic-clean.bin")).returncode == 0
    faults = run_cli("inspect", "--strict", str(DATA / "synthetic-faults.bin"))
    assert faults.returncode == 1
    assert "3 CRC errors" in faults.stdout and "capture ends inside a frame" in faults.stdout


def test_inspect_progress_only_on_a_terminal():
    class FakeTty(io.StringIO):
        def isatty(self) -> bool:
            return True

    piped = io.StringIO()
    inspect_capture(DATA / "synthetic-clean.bin", progress=Progress(piped, min_interval_s=0).bytes_done)
    assert piped.getvalue() == ""
    tty = FakeTty()
    progress = Progress(tty, min_interval_s=0)
    inspect_capture(DATA / "synthetic-clean.bin", progress=progress.bytes_done)
    assert "decoding" in tty.getvalue() and "(100 %)" in tty.getvalue()
    progress.clear()
    assert tty.getvalue().endswith("\r")


@pytest.mark.parametrize(
    "make, needle",
    [
        (lambda p: None, "no such capture file"),
        (lambda p: p.write_bytes(b""), "empty file"),
        (lambda p: p.write_bytes(encode_sample(1, 2, 3, 4, 5, 6)[:20]), "too short to hold one"),
        (lambda p: p.write_bytes(os.urandom(5000).replace(b"\xaa", b"\x00")), "no valid frame in 5000 bytes"),
        (lambda p: p.write_text("time,rate\n0,1\n" * 200), "not a protocol v1 capture"),
        (lambda p: p.mkdir(), "is a directory"),
    ],
    ids=["missing", "empty", "truncated", "random", "text", "directory"],
)
def test_inspect_bad_files_give_one_line_errors(tmp_path, make, needle):
    path = tmp_path / "bad.bin"
    make(path)
    assert_one_line_error(run_cli("inspect", str(path)), 65, str(path), needle)


@pytest.mark.parametrize(
    "sidecar, needle",
    [
        ("capture: [unclosed\n", "not valid YAML"),
        ("just a string\n", "not a YAML mapping"),
        ("x: !!python/object/apply:os.system ['echo pwned']\n", "not valid YAML"),
    ],
    ids=["malformed", "not-mapping", "python-tag"],
)
def test_inspect_bad_sidecar_is_one_line_error_and_never_executed(tmp_path, sidecar, needle):
    capture = tmp_path / "c.bin"
    capture.write_bytes((DATA / "synthetic-clean.bin").read_bytes())
    (tmp_path / "c.bin.yaml").write_text(sidecar)
    proc = run_cli("inspect", str(capture))
    assert_one_line_error(proc, 65, "c.bin.yaml", needle)
    assert "pwned" not in proc.stdout


def test_usage_errors():
    proc = run_cli("inspect")
    assert proc.returncode == 2 and "usage:" in proc.stderr and "Traceback" not in proc.stderr
    assert_one_line_error(run_cli("record", "loop://", "--out", "x.txt"), 64, "must end in .bin")
    proc = run_cli("record", "loop://", "--out", "x.bin", "--duration", "-1")
    assert proc.returncode == 2 and "must be > 0" in proc.stderr


# --- record ------------------------------------------------------------------------------------


def test_record_from_replay_url_keeps_every_byte(tmp_path):
    source = DATA / "synthetic-faults.bin"
    out = tmp_path / "rec.bin"
    proc = run_cli("record", f"replay://{source}?unplug=1", "--out", str(out), "--no-reconnect", "--notes", "unit test")
    assert proc.returncode == 0, proc.stderr
    assert out.read_bytes() == source.read_bytes()  # garbage, corrupt frames and the cut-off tail included
    sidecar = read_provenance(out)
    assert sidecar["status"] == "complete"
    assert sidecar["sha256"] == hashlib.sha256(source.read_bytes()).hexdigest()
    assert sidecar["bytes"] == source.stat().st_size
    assert sidecar["instrument"]["serial"] == "FOG-SYN-0001"
    assert sidecar["notes"] == "unit test"
    assert [e["state"] for e in sidecar["port_events"]] == ["opening", "open", "lost", "closed"]
    assert sidecar["decoded_while_recording"]["crc_errors"] == 3
    assert "recorded 31,551 bytes" in proc.stdout
    # The recording inspects exactly like its source.
    a = json.loads(run_cli("inspect", "--json", str(out)).stdout)
    b = json.loads(run_cli("inspect", "--json", str(source)).stdout)
    for key in ("sample_frames", "crc_errors", "missing_frames", "bytes_discarded", "thermometer_faults"):
        assert a[key] == b[key]


def test_record_missing_device_without_reconnect_is_a_one_line_error_and_leaves_nothing(tmp_path):
    out = tmp_path / "rec.bin"
    proc = run_cli("record", str(tmp_path / "ttyNOPE"), "--out", str(out), "--no-reconnect")
    assert_one_line_error(proc, 69, "ttyNOPE")
    assert not out.exists() and not sidecar_path(out).exists()


@pytest.mark.parametrize("name, serial", [("synthetic-clean", "FOG-SYN-0001"), ("sim-faults", "FOG-SIM-0001")])
def test_record_through_a_real_pty_until_unplug(tmp_path, name, serial):
    data = (DATA / f"{name}.bin").read_bytes()
    out = tmp_path / "pty.bin"
    opened = threading.Event()
    all_read = threading.Event()
    result = {}

    def on_state(event):
        if event.state == "open":
            opened.set()

    def on_progress(p):
        if p.bytes_written == len(data):
            all_read.set()

    with PtyPair() as pty:
        stop = threading.Event()

        def run():
            result["r"] = record(
                pty.slave_path,
                str(out),
                reconnect=False,
                stop=stop,
                on_state=on_state,
                on_progress=on_progress,
                progress_every_s=0,
            )

        thread = threading.Thread(target=run)
        thread.start()
        assert opened.wait(30), "recorder never opened the pty"
        pty.write(data)
        assert all_read.wait(30), "recorder did not read every byte"
        pty.unplug()
        thread.join(30)
        assert not thread.is_alive()
    r = result["r"]
    assert out.read_bytes() == data
    assert r.bytes_written == len(data) and r.identity.serial == serial
    assert r.counters == decode_bytes(data, final=False).counters
    assert read_provenance(out)["port_events"][-2]["state"] == "lost"


def test_record_duration_stops_an_idle_port(tmp_path):
    # A replay that goes idle at its end: only --duration ends the recording.
    source = DATA / "synthetic-clean.bin"
    out = tmp_path / "idle.bin"
    proc = run_cli("record", f"replay://{source}", "--out", str(out), "--duration", "0.3")
    assert proc.returncode == 0, proc.stderr
    assert out.read_bytes() == source.read_bytes()
    assert read_provenance(out)["host_duration_s"] >= 0.3


@pytest.mark.parametrize("name", FIXTURES)
def test_inspect_block_by_block_equals_one_shot(name):
    path = DATA / f"{name}.bin"
    one_shot = summarize(decode_bytes(path.read_bytes()), path=str(path))
    for block in (7, 97, 4096):  # 7: every frame straddles a block boundary
        blockwise = inspect_capture(path, block_bytes=block)
        blockwise.sha256 = one_shot.sha256 = ""
        blockwise.provenance = None
        assert blockwise == one_shot, block


def test_record_refuses_to_overwrite_a_capture_unless_forced(tmp_path):
    source = DATA / "synthetic-clean.bin"
    out = tmp_path / "precious.bin"
    out.write_bytes(b"a 440-minute chamber run")
    proc = run_cli("record", f"replay://{source}?unplug=1", "--out", str(out), "--no-reconnect")
    assert_one_line_error(proc, 73, "precious.bin", "refusing to overwrite", "--force")
    assert out.read_bytes() == b"a 440-minute chamber run"
    proc = run_cli("record", f"replay://{source}?unplug=1", "--out", str(out), "--no-reconnect", "--force")
    assert proc.returncode == 0, proc.stderr
    assert out.read_bytes() == source.read_bytes()


def test_record_disk_full_is_one_error_and_the_sidecar_says_how_far_it_got(tmp_path, monkeypatch):
    import errno

    import fog_driver.samples.record as record_module
    from fog_driver.errors import OutputFileError
    from fog_driver.samples.captures import CaptureWriter

    class FullAfter:
        """A file that takes the first write, then fails like a full disk."""

        def __init__(self, real):
            self.real, self.writes = real, 0

        def write(self, chunk):
            self.writes += 1
            if self.writes > 1:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            return self.real.write(chunk)

        def __getattr__(self, name):
            return getattr(self.real, name)

    class FullDiskWriter(CaptureWriter):
        def __init__(self, path, overwrite=False):
            super().__init__(path, overwrite)
            self._file = FullAfter(self._file)

    monkeypatch.setattr(record_module, "CaptureWriter", FullDiskWriter)
    source = DATA / "synthetic-clean.bin"
    out = tmp_path / "full.bin"
    # Paced over 12 s, so the recorder reads more than one chunk; the second write fills the disk.
    with pytest.raises(OutputFileError, match="No space left on device"):
        record(f"replay://{source}?rate=100&unplug=1", out, reconnect=False)
    sidecar = read_provenance(out)
    assert sidecar["status"].startswith("failed: ") and "No space left" in sidecar["status"]
    assert 0 < sidecar["bytes"] < source.stat().st_size
    assert out.read_bytes() == source.read_bytes()[: sidecar["bytes"]]  # what was written is intact


def test_inspect_flags_an_identity_change_mid_capture(tmp_path):
    from fog_driver.protocol import encode_identity

    data = (
        encode_identity("FOG-A", 0x0102, 100, 0.01)
        + b"".join(encode_sample(i, i * 10_000, 1, 5000, 5000, 5000) for i in range(10))
        + encode_identity("FOG-B", 0x0102, 100, 0.01)
        + b"".join(encode_sample(i, i * 10_000, 1, 5000, 5000, 5000) for i in range(10, 20))
    )
    path = tmp_path / "two.bin"
    path.write_bytes(data)
    summary = inspect_capture(path)
    assert summary.serial == "FOG-B" and summary.identity_changes == 2
    assert summary.problems == ["1 identity change"]


# --- bugs: a traceback in the log, one line and exit 70 for the user ----------------------------


def _crash_in_a_helper() -> None:
    raise ZeroDivisionError("the helper divided by zero")


def test_json_logs_carry_the_exception_type_and_stack_without_locals(capsys):
    from fog_driver.console import configure_logging

    configure_logging(0, "json")
    secret = "a-long-token"  # a local variable of a frame in the traceback: never in the log
    try:
        _crash_in_a_helper()
    except ZeroDivisionError:
        structlog.get_logger("test").exception("acquisition_crashed", reason="x")
    (line,) = capsys.readouterr().err.splitlines()
    entry = json.loads(line)
    assert entry["event"] == "acquisition_crashed" and entry["level"] == "error"
    (exception,) = entry["exception"]
    assert exception["exc_type"] == "ZeroDivisionError"
    assert exception["exc_value"] == "the helper divided by zero"
    names = [frame["name"] for frame in exception["frames"]]
    assert names == ["test_json_logs_carry_the_exception_type_and_stack_without_locals", "_crash_in_a_helper"]
    assert secret not in line and all("locals" not in frame for frame in exception["frames"])


def test_human_logs_carry_the_traceback_after_the_event(capsys):
    from fog_driver.console import configure_logging

    assert configure_logging(0, "human") == "human"
    try:
        _crash_in_a_helper()
    except ZeroDivisionError:
        structlog.get_logger("test").exception("crashed", port="/dev/ttyUSB0", detail="a b")
    first, *rest = capsys.readouterr().err.splitlines()
    assert re.fullmatch(r"\d\d:\d\d:\d\d error   crashed  port=/dev/ttyUSB0 detail='a b'", first)
    assert rest[0] == "Traceback (most recent call last):" and any("in _crash_in_a_helper" in r for r in rest)
    assert rest[-1] == "ZeroDivisionError: the helper divided by zero"


def test_log_format_follows_where_the_lines_go(monkeypatch):
    """One rule for every command: lines for a person on a terminal, JSON for journald and pipes."""
    from fog_driver.console import configure_logging, log_format_for

    master, slave = os.openpty()
    with open(slave, "w", closefd=True) as tty, open(os.devnull, "w") as pipe:
        assert log_format_for(tty) == "human" and log_format_for(pipe) == "json"
        assert log_format_for(tty, "json") == "json" and log_format_for(pipe, "human") == "human"
        monkeypatch.setattr(sys, "stderr", tty)
        assert configure_logging(0) == "human"
        monkeypatch.setattr(sys, "stderr", pipe)
        assert configure_logging(0) == "json"
    os.close(master)
    with pytest.raises(ValueError, match="log format"):
        log_format_for(sys.stdout, "xml")


def test_an_unexpected_exception_is_one_line_exit_70_and_a_logged_traceback(monkeypatch, capsys):
    from fog_driver.cli import app as cli
    from fog_driver.cli import captures

    def broken_inspect(args):
        raise ValueError("a\nmulti-line message")

    monkeypatch.setattr(captures, "cmd_inspect", broken_inspect)
    assert cli.main(["inspect", "x.bin"]) == 70
    lines = capsys.readouterr().err.splitlines()
    assert lines[-1] == "fog-driver: error: internal error: ValueError: a multi-line message"
    assert [line for line in lines if line.startswith("fog-driver:")] == lines[-1:]
    entry = json.loads(lines[0])  # stderr is a capture, not a terminal: the log is JSON
    assert entry["event"] == "internal_error" and "broken_inspect" in [
        f["name"] for f in entry["exception"][0]["frames"]
    ]


def test_run_exits_70_when_acquisition_crashes_on_a_bug(tmp_path, monkeypatch, capsys):
    """An exception from a bug in the acquisition thread ended the daemon with exit 1 and no
    ``fog-driver: error:`` line; now 70 (EX_SOFTWARE), one line, and the traceback in the JSON log."""
    from fog_driver.cli import app as cli
    from fog_driver.daemon.service import Service

    def broken_process(self, chunk):
        raise RuntimeError("a bug in the pipeline")

    monkeypatch.setattr(Service, "process", broken_process)
    status = cli.main(
        [
            "run",
            "--port",
            f"replay://{DATA / 'synthetic-clean.bin'}",
            "--listen",
            "127.0.0.1:0",
            "--capture-dir",
            str(tmp_path / "captures"),
        ]
    )
    assert status == 70
    err = capsys.readouterr().err.splitlines()
    assert err[-1] == "fog-driver: error: internal error: RuntimeError: a bug in the pipeline"
    crashes = [json.loads(line) for line in err if '"acquisition_crashed"' in line]
    assert [c["exception"][0]["exc_type"] for c in crashes] == ["RuntimeError"]
    assert crashes[0]["exception"][0]["frames"][-1]["name"] == "broken_process"


def test_a_demo_that_fails_to_start_leaves_no_simulator_running(tmp_path):
    """A demonstration ``run`` whose listen address is taken had already started its simulator, which
    went on serving its pty after the failure; now it is stopped before the error is reported."""
    from fog_driver.cli import app as cli

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        host, port = taken.getsockname()
        status = cli.main(["run", "--simulate", "--listen", f"{host}:{port}", "--capture-dir", str(tmp_path / "c")])
    assert status == 75
    assert not [t for t in threading.enumerate() if t.name == "simulator"]
