"""``fog-driver calibrate``: its argument errors, a held port refused, and a whole run against the simulated
chamber (``sim://``) with the gyro replayed from a capture.

Needs, at merge, H4's ``lab/runner.py``, ``lab/lock.py`` and ``cli/lab.py``, H5's ``lab/chamberlog.py`` and
H3's ``sim/chamber.py`` (every test but the held port's and ``--out``'s)."""

from __future__ import annotations

import csv
from pathlib import Path

import serial
from cli_run import assert_one_line_error, run_cli

from fog_driver.samples.captures import read_provenance
from fog_driver.transport import PtyPair
from fog_driver.transport.port import open_port

DATA = Path(__file__).resolve().parents[1] / "data"

SHORT_PROGRAM = """name: two-steps
start_c: 20
segments:
- hold: {duration_min: 0.02}
- ramp: {rate_c_per_min: 60, target_c: 21}
"""


def _program(tmp_path: Path) -> Path:
    path = tmp_path / "short.yaml"
    path.write_text(SHORT_PROGRAM)
    return path


def _calibrate(tmp_path: Path, port: str = "loop://", chamber: str = "sim://", profile: str | None = None):
    """``fog-driver calibrate PORT --chamber CHAMBER --profile PROFILE --out tmp_path/r.bin``."""
    profile = str(_program(tmp_path)) if profile is None else profile
    return run_cli("calibrate", port, "--chamber", chamber, "--profile", profile, "--out", str(tmp_path / "r.bin"))


def test_calibrate_with_an_out_not_a_capture_name_is_a_usage_error(tmp_path):
    proc = run_cli("calibrate", "loop://", "--chamber", "sim://", "--profile", "x", "--out", str(tmp_path / "x.txt"))
    assert_one_line_error(proc, 64, "must end in .bin")


def test_calibrate_with_a_profile_that_is_not_one_is_bad_input(tmp_path):
    proc = run_cli(
        "calibrate",
        "loop://",
        "--chamber",
        "sim://",
        "--profile",
        str(tmp_path / "no.yaml"),
        "--out",
        str(tmp_path / "r.bin"),
    )
    assert_one_line_error(proc, 65)


def test_calibrate_with_an_unknown_chamber_scheme_is_a_usage_error(tmp_path):
    proc = _calibrate(tmp_path, chamber="nochamber://x")
    assert_one_line_error(proc, 64)
    assert not (tmp_path / "r.bin").exists()


def test_calibrate_onto_an_existing_chamber_log_is_refused_without_force(tmp_path):
    (tmp_path / "r.chamber.csv").write_text("old\n")
    proc = _calibrate(tmp_path)
    assert_one_line_error(proc, 73, "r.chamber.csv")
    assert (tmp_path / "r.chamber.csv").read_text() == "old\n"


def test_calibrate_with_a_program_beyond_the_chamber_range_records_nothing(tmp_path):
    proc = _calibrate(tmp_path, chamber="sim://?high_c=20.5")
    assert_one_line_error(proc, 65)
    assert not (tmp_path / "r.bin").exists() and not (tmp_path / "r.chamber.csv").exists()


def test_a_port_another_program_holds_is_refused_on_open():
    with PtyPair() as pty:
        first = open_port(pty.slave_path)
        try:
            try:
                open_port(pty.slave_path)
            except serial.SerialException as exc:
                assert "held by another program" in str(exc)
            else:
                raise AssertionError("the second open of a held port succeeded")
        finally:
            first.close()
        open_port(pty.slave_path).close()  # free again once closed


def test_calibrate_on_a_port_a_daemon_holds_is_refused_with_one_line(tmp_path):
    with PtyPair() as pty:
        held = open_port(pty.slave_path)
        try:
            proc = _calibrate(tmp_path, port=pty.slave_path)
        finally:
            held.close()
    assert_one_line_error(proc, 69, "held by another program")
    assert not (tmp_path / "r.bin").exists()


def test_calibrate_against_the_simulated_chamber_writes_the_capture_the_log_and_the_sidecar(tmp_path):
    out = tmp_path / "run.bin"
    proc = run_cli(
        "calibrate",
        f"replay://{DATA / 'sim-short.bin'}?rate=200",
        "--chamber",
        "sim://?speed=1",
        "--profile",
        str(_program(tmp_path)),
        "--out",
        str(out),
        "--step-s",
        "0.25",
    )
    assert proc.returncode == 0, proc.stderr
    sidecar = read_provenance(out)
    assert sidecar["chamber_log"] == "run.chamber.csv"
    assert sidecar["program"]["name"] == "two-steps" and len(sidecar["program"]["program_sha256"]) == 64
    assert sidecar["chamber"] == "sim://?speed=1"
    assert sidecar["status"] == "complete" and sidecar["bytes"] == out.stat().st_size > 0
    lines = [line for line in (tmp_path / "run.chamber.csv").read_text().splitlines() if not line.startswith("#")]
    rows = list(csv.DictReader(lines))
    assert rows[-1]["state"] == "done"
    running = [r for r in rows if r["state"] == "running"]
    assert running and all(r["device_t_s"] != "" for r in running)  # the gyro's clock beside each step
    device_t = [float(r["device_t_s"]) for r in running]
    assert device_t == sorted(device_t)
    assert float(running[-1]["program_c"]) == 21.0 or float(running[-1]["program_c"]) <= 21.0


def test_calibrate_stopped_with_ctrl_c_exits_130_and_says_interrupted_in_its_sidecar(tmp_path):
    import os
    import signal
    import subprocess
    import sys

    out = tmp_path / "run.bin"
    program = tmp_path / "long.yaml"
    program.write_text("name: long\nstart_c: 20\nsegments:\n- hold: {duration_min: 10}\n")
    argv = [sys.executable, "-m", "fog_driver", "calibrate", f"replay://{DATA / 'sim-short.bin'}?rate=200"]
    argv += ["--chamber", "sim://", "--profile", str(program), "--out", str(out), "--step-s", "0.2"]
    proc = subprocess.Popen(argv, stderr=subprocess.PIPE, text=True, env=os.environ)
    assert proc.stderr is not None
    for line in proc.stderr:  # the readiness line: the program has started
        if "Ctrl-C to stop" in line:
            break
    proc.send_signal(signal.SIGINT)
    proc.communicate(timeout=30)
    assert proc.returncode == 130
    assert read_provenance(out)["status"] == "interrupted"
    lines = [line for line in (tmp_path / "run.chamber.csv").read_text().splitlines() if not line.startswith("#")]
    assert list(csv.DictReader(lines))[-1]["state"] == "interrupted"
