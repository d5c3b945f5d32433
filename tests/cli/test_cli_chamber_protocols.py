"""``fog-driver chamber status`` and ``chamber run`` against the simulated lab on every protocol, in real time:
the chamber served in this process (its clock the host's), the command a subprocess, as a user runs it."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from cli_run import run_cli

from fog_driver.lab.chamberlog import read_chamber_log
from fog_driver.lab.profiles import load_profile
from fog_driver.sim.chamber import ChamberParams, SimChamber, StartedClock
from fog_driver.sim.chamber_serve import ChamberFaults, serve_chamber

#: scheme -> the URL options its driver needs (Thermotron has no range read)
OPTIONS = {"espec": "", "thermotron": "?range=-70:180", "simserv": "", "watlow-f4t": ""}

#: 1.5 s of program: a hold, a ramp of 0.5 degC, a hold (the chamber follows at once: no lag, 120 degC/min)
PROGRAM = (
    "name: short\nstart_c: 20.0\nsegments:\n"
    "- hold: {duration_s: 0.5}\n- ramp: {rate_c_per_min: 60, target_c: 20.5}\n- hold: {duration_s: 0.5}\n"
)


@pytest.fixture
def served(request: pytest.FixtureRequest):
    clock = StartedClock(1.0)
    clock.start()
    chamber = SimChamber(clock, ChamberParams(start_c=20.0, rate_c_per_min=120.0, tau_s=0.0))
    with serve_chamber(f"{request.param}://127.0.0.1:0", chamber) as server:
        yield server.url + OPTIONS[request.param], chamber


@pytest.mark.parametrize("served", sorted(OPTIONS), indirect=True)
def test_chamber_status_and_a_short_run_on_each_protocols_simulated_chamber(served, tmp_path: Path) -> None:
    url, chamber = served
    status = run_cli("chamber", "status", url)
    assert status.returncode == 0, status.stderr
    line = status.stdout.strip()
    assert "\n" not in line and re.search(r"air 20\.0+ degC", line), line
    assert "-70" in line and "180" in line, line  # the range

    (tmp_path / "p.yaml").write_text(PROGRAM)
    log_path = tmp_path / "run.csv"
    proc = run_cli(
        "chamber", "run", str(tmp_path / "p.yaml"), "--chamber", url, "--log", str(log_path), "--step-s", "0.5"
    )
    assert proc.returncode == 0, proc.stderr
    log = read_chamber_log(log_path)
    running = [row for row in log.rows if row.state == "running"]
    assert log.rows[-1].state == "done"
    assert [row.t_s for row in running] == [0.5 * k for k in range(len(running))] and running[-1].t_s == 1.5
    program = load_profile(str(tmp_path / "p.yaml")).chamber
    expected = program.air_temp_c(np.array([row.t_s for row in running]))
    written = np.array([row.setpoint_c for row in running])
    assert np.abs(written - expected).max() <= 0.05 + 1e-9  # half the ASCII protocols' 0.1 degC
    assert chamber.setpoint_c() == pytest.approx(20.5, abs=0.05)


@pytest.mark.parametrize(
    ("scheme", "faults", "needle"),
    [
        ("espec", ChamberFaults(garbage=True), "espec"),
        ("watlow-f4t", ChamberFaults(exception_code=2), "Modbus exception 2"),
        ("espec", ChamberFaults(drop_mid_reply=True), "link lost"),
        ("simserv", ChamberFaults(local=True), "simserv"),
    ],
)
def test_a_controller_that_answers_garbage_an_exception_or_refuses_is_one_line_and_nothing_written(
    scheme: str, faults: ChamberFaults, needle: str, tmp_path: Path
) -> None:
    """A required read answered with garbage, a Modbus exception or a reply cut off, or a write refused (local
    mode): ``chamber run`` stops with one error line and exit 69, and the chamber's set point is the one it had."""
    clock = StartedClock(1.0)
    clock.start()
    chamber = SimChamber(clock, ChamberParams(start_c=20.0, rate_c_per_min=120.0, tau_s=0.0))
    (tmp_path / "p.yaml").write_text(PROGRAM.replace("target_c: 20.5", "target_c: 25"))
    with serve_chamber(f"{scheme}://127.0.0.1:0", chamber, faults) as server:
        proc = run_cli(
            "chamber", "run", str(tmp_path / "p.yaml"), "--chamber", server.url, "--log", str(tmp_path / "l.csv")
        )
    assert proc.returncode == 69 and "Traceback" not in proc.stderr, proc.stderr
    lines = proc.stderr.strip().splitlines()  # (a notice said once, the run's start line may come before it)
    errors = [line for line in lines if line.startswith("fog-driver: error: ")]
    assert errors == [lines[-1]] and needle in errors[0], proc.stderr
    assert chamber.setpoint_c() == 20.0
