"""``fog-driver chamber status`` and ``chamber run`` as a user runs them: bad input is one line and its exit status,
nothing is written to a chamber before the checks pass, and Ctrl-C ends a run as interrupted (exit 130).

The tests that open ``sim://`` run the simulated lab (``fog_driver.sim.chamber``); ``espec://`` the Espec driver."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from cli_run import assert_one_line_error, run_cli

from fog_driver.lab.chamberlog import ChamberLogWriter, LogHeader, LogRow, program_sha256, read_chamber_log
from fog_driver.lab.lock import ControllerLock
from fog_driver.lab.profiles import load_profile

SHORT = """\
name: short
start_c: 20
segments:
- hold: {duration_s: 2}
- ramp: {rate_c_per_min: 60, target_c: 21}
"""
LONG_HOLD = "name: long-hold\nstart_c: 20\nsegments:\n- hold: {duration_s: 3600}\n"
TOO_HOT = "name: too-hot\nstart_c: 20\nsegments:\n- ramp: {rate_c_per_min: 60, target_c: 500}\n"


def profile(tmp_path: Path, text: str = SHORT, name: str = "p.yaml") -> str:
    path = tmp_path / name
    path.write_text(text)
    return str(path)


def a_log(path: Path, profile_path: str) -> Path:
    """A chamber log of a run of ``profile_path``, as the runner writes it."""
    program = load_profile(profile_path).chamber
    log = ChamberLogWriter(path, LogHeader("short", program_sha256(program), "sim://", "r1", None))
    log.write(LogRow("2026-12-07T12:00:00.000Z", 0.0, None, 20.0, 20.0, "running", 20.0, 0))
    log.write(LogRow("2026-12-07T12:00:01.000Z", 1.0, None, 20.0, 20.0, "interrupted", None, None))
    log.close()
    return path


def test_chamber_help_works_without_the_lab_extra_and_running_says_how_to_install_it(tmp_path: Path) -> None:
    code = (
        "import sys\nsys.modules['pymodbus'] = None\nfrom fog_driver.cli.app import main\n"
        "sys.exit(main(sys.argv[1:]))\n"
    )
    for argv in (["chamber", "--help"], ["chamber", "run", "--help"], ["chamber", "status", "--help"]):
        proc = subprocess.run([sys.executable, "-c", code, *argv], capture_output=True, text=True, timeout=60)
        assert proc.returncode == 0 and "usage: fog-driver chamber" in proc.stdout
    proc = subprocess.run(
        [sys.executable, "-c", code, "chamber", "status", "sim://"], capture_output=True, text=True, timeout=60
    )
    assert_one_line_error(proc, 64, "pip install -e '.[lab]'")


def test_an_unknown_scheme_is_one_line_and_exit_64(tmp_path: Path) -> None:
    assert_one_line_error(run_cli("chamber", "status", "modbus-magic://host"), 64, "unknown scheme 'modbus-magic'")
    proc = run_cli("chamber", "run", profile(tmp_path), "--chamber", "nope://x", "--log", str(tmp_path / "log.csv"))
    assert_one_line_error(proc, 64, "unknown scheme 'nope'")
    assert not (tmp_path / "log.csv").exists()


def test_a_file_that_is_not_a_profile_is_one_line_and_exit_65(tmp_path: Path) -> None:
    bad = profile(tmp_path, "- just\n- a list\n", "bad.yaml")
    proc = run_cli("chamber", "run", bad, "--chamber", "sim://", "--log", str(tmp_path / "log.csv"))
    assert_one_line_error(proc, 65, "bad.yaml")
    assert not (tmp_path / "log.csv").exists()


def test_a_log_that_exists_is_refused_without_force_and_left_as_it_was(tmp_path: Path) -> None:
    log = tmp_path / "log.csv"
    log.write_text("earlier data\n")
    proc = run_cli("chamber", "run", profile(tmp_path), "--chamber", "sim://", "--log", str(log))
    assert_one_line_error(proc, 73, "exists", "--force")
    assert log.read_text() == "earlier data\n"


def test_resuming_with_another_runs_log_is_one_line_and_exit_65(tmp_path: Path) -> None:
    other = a_log(tmp_path / "old.csv", profile(tmp_path, SHORT.replace("target_c: 21", "target_c: 23"), "o.yaml"))
    proc = run_cli(
        "chamber",
        "run",
        profile(tmp_path),
        "--chamber",
        "sim://",
        "--log",
        str(tmp_path / "new.csv"),
        "--resume",
        str(other),
    )
    assert_one_line_error(proc, 65, "another run's")
    assert not (tmp_path / "new.csv").exists()


def test_resuming_from_a_file_that_is_not_a_chamber_log_is_one_line_and_exit_65(tmp_path: Path) -> None:
    (tmp_path / "old.csv").write_text("t,x\n1,2\n")
    proc = run_cli(
        "chamber",
        "run",
        profile(tmp_path),
        "--chamber",
        "sim://",
        "--log",
        str(tmp_path / "new.csv"),
        "--resume",
        str(tmp_path / "old.csv"),
    )
    assert_one_line_error(proc, 65, "not a chamber log")


def test_a_bad_on_stop_is_a_usage_error(tmp_path: Path) -> None:
    proc = run_cli("chamber", "run", "x", "--chamber", "sim://", "--log", "l.csv", "--on-stop", "warm")
    assert proc.returncode == 2 and "on-stop must be hold, standby or a finite temperature" in proc.stderr


# --- against a controller (sim:// needs fog_driver.sim.chamber; espec:// the Espec driver) ------------------------


def test_an_unreachable_controller_is_one_line_and_exit_69(tmp_path: Path) -> None:
    assert_one_line_error(run_cli("chamber", "status", "espec://127.0.0.1:1"), 69)
    log = tmp_path / "log.csv"
    proc = run_cli("chamber", "run", profile(tmp_path), "--chamber", "espec://127.0.0.1:1", "--log", str(log))
    assert_one_line_error(proc, 69)
    assert not log.exists()


def test_chamber_status_of_the_simulated_chamber_is_one_line() -> None:
    proc = run_cli("chamber", "status", "sim://")
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    assert len(lines) == 1 and all(word in lines[0] for word in ("air", "set point", "state", "range"))


def test_a_program_beyond_the_range_is_exit_65_with_nothing_written(tmp_path: Path) -> None:
    log = tmp_path / "log.csv"
    proc = run_cli("chamber", "run", profile(tmp_path, TOO_HOT), "--chamber", "sim://", "--log", str(log))
    assert_one_line_error(proc, 65, "outside the controller's range", "nothing written")
    assert not log.exists()


def test_a_short_program_runs_to_its_end_and_logs_each_step(tmp_path: Path) -> None:
    log = tmp_path / "log.csv"
    status = run_cli("chamber", "status", "sim://")
    air_c = round(float(re.search(r"air (-?[0-9.]+) degC", status.stdout)[1]), 1)  # start there: no settling
    tiny = profile(
        tmp_path,
        f"name: short\nstart_c: {air_c}\nsegments:\n- hold: {{duration_s: 0.5}}\n"
        f"- ramp: {{rate_c_per_min: 60, target_c: {air_c + 0.5}}}\n",
    )
    proc = run_cli("chamber", "run", tiny, "--chamber", "sim://", "--log", str(log), "--step-s", "0.25")
    assert proc.returncode == 0, proc.stderr
    rows = read_chamber_log(log).rows
    running = [r for r in rows if r.state == "running"]
    assert [r.t_s for r in running] == [0.25 * k for k in range(5)] and rows[-1].state == "done"
    assert running[-1].program_c == pytest.approx(air_c + 0.5) and read_chamber_log(log).header.program_name == "short"


def test_a_second_run_on_a_chamber_another_run_drives_is_one_line_and_exit_69(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))  # the lock folder, here and in the command's process
    from fog_driver.cli.lab import open_chamber

    url = "espec://127.0.0.1:1"  # (every sim:// is a chamber of its own: the lock is for a real address)
    with ControllerLock(open_chamber(url, None).address):
        proc = run_cli("chamber", "run", profile(tmp_path), "--chamber", url, "--log", str(tmp_path / "l.csv"))
    assert_one_line_error(proc, 69, "another chamber run drives")
    assert not (tmp_path / "l.csv").exists()


def test_resuming_goes_on_from_the_old_log_into_a_new_one_of_the_same_run(tmp_path: Path) -> None:
    status = run_cli("chamber", "status", "sim://")
    air_c = round(float(re.search(r"air (-?[0-9.]+) degC", status.stdout)[1]), 1)
    text = f"name: r\nstart_c: {air_c}\nsegments:\n- hold: {{duration_s: 1.5}}\n"
    old = tmp_path / "old.csv"
    program = load_profile(profile(tmp_path, text)).chamber
    log = ChamberLogWriter(old, LogHeader("r", program_sha256(program), "sim://", "run-7", None))
    log.write(LogRow("2026-12-07T12:00:00.000Z", 1.0, None, air_c, air_c, "running", air_c, 0))
    log.write(LogRow("2026-12-07T12:00:01.000Z", 1.0, None, air_c, air_c, "interrupted", None, None))
    log.close()
    new = tmp_path / "new.csv"
    proc = run_cli(
        "chamber",
        "run",
        str(tmp_path / "p.yaml"),
        "--chamber",
        "sim://",
        "--log",
        str(new),
        "--step-s",
        "0.25",
        "--resume",
        str(old),
    )
    assert proc.returncode == 0, proc.stderr
    resumed = read_chamber_log(new)
    assert resumed.header.resumed_from == str(old) and resumed.header.run_id == "run-7"
    assert [r.t_s for r in resumed.rows if r.state == "running"] == [1.0, 1.25, 1.5]


def test_ctrl_c_ends_a_run_as_interrupted_with_exit_130(tmp_path: Path) -> None:
    log = tmp_path / "log.csv"
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "fog_driver",
            "chamber",
            "run",
            profile(tmp_path, LONG_HOLD),
            "--chamber",
            "sim://",
            "--log",
            str(log),
            "--step-s",
            "0.2",
        ],
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={k: v for k, v in os.environ.items() if k != "NOTIFY_SOCKET"},
    )
    try:
        assert proc.stderr is not None
        line = proc.stderr.readline()  # the readiness line, printed once the signal handlers are in place
        assert "Ctrl-C to stop" in line, line
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
        proc.wait(timeout=30)
    assert proc.returncode == 130, err
    rows = read_chamber_log(log).rows
    assert rows[-1].state == "interrupted" and "Traceback" not in err


def test_a_chamber_config_file_is_the_daemon_configs_shape_and_its_overrides_are_read(tmp_path):
    """``--chamber-config`` reads ``chamber: overrides:`` as the daemon's config does, so one file serves both;
    anything else under ``chamber:`` is refused in one line."""
    from fog_driver.cli.lab import chamber_overrides
    from fog_driver.errors import InputFileError

    good = tmp_path / "daemon.yaml"
    good.write_text("port: /dev/ttyUSB0\nchamber:\n  url: watlow-f4t://10.0.0.5\n  overrides: {word_order: high}\n")
    assert chamber_overrides(str(good)) == {"word_order": "high"}
    assert chamber_overrides(None) == {}
    for text, needle in [
        ("chamber:\n  word_order: high\n", "unknown key word_order"),
        ("chamber:\n  overrides: [1, 2]\n", "must be a mapping"),
        ("other: 1\n", "needs a 'chamber:' mapping"),
    ]:
        bad = tmp_path / "bad.yaml"
        bad.write_text(text)
        with pytest.raises(InputFileError, match=needle):
            chamber_overrides(str(bad))
