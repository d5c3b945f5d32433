"""``fog-driver calibrate`` against the simulated lab (``simulate --serve pty --chamber-serve URL``), in real time:
the calibration tutorial's session as written, and a short run on every other protocol.

Readiness is the served lines (the chamber's URL, then the pty's), never a sleep."""

from __future__ import annotations

import re
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from cli_run import run_cli
from sim_serving import GUARD_S, _next_line, start_fog_driver

from fog_driver.lab.chamberlog import read_chamber_log
from fog_driver.lab.profiles import load_profile
from fog_driver.samples.captures import read_provenance, sidecar_path

ROOT = Path(__file__).resolve().parents[2]
TUTORIAL = ROOT / "docs" / "tutorials" / "calibrate-with-a-chamber.md"
RUN_GUARD_S = 120  # a failure guard for a calibrate run, as cli_run's


def blocks(kind: str) -> list[str]:
    return re.findall(rf"^```{kind}\n(.*?)^```", TUTORIAL.read_text(), flags=re.S | re.M)


class Lab:
    """``fog-driver simulate --serve pty --chamber-serve URL`` as a process: its chamber's URL and its link."""

    def __init__(self, argv: list[str]) -> None:
        self.proc, self.lines = start_fog_driver(*argv)
        first = _next_line(self.proc, self.lines)
        found = re.match(r"serving the chamber on (\S+)", first)
        assert found, first
        self.chamber_url = found[1]
        second = _next_line(self.proc, self.lines)  # the pty is served: the device time runs
        assert " on /dev/" in second, second

    def stop(self) -> None:
        self.proc.terminate()
        self.proc.wait(GUARD_S)
        while self.lines.get(timeout=GUARD_S) is not None:  # the pump has read to the end of stdout
            pass
        self.proc.stdout.close()
        self.proc.stderr.close()


def check_run(folder: Path, out: str, program_path: Path, chamber_url: str) -> None:
    """The capture, its sidecar naming the log, the program and the controller, and a complete chamber log."""
    capture = folder / out
    sidecar = read_provenance(sidecar_path(capture))
    log_path = folder / sidecar["chamber_log"]
    assert log_path == capture.with_name(capture.stem + ".chamber.csv")
    program = load_profile(str(program_path)).chamber
    log = read_chamber_log(log_path)
    assert sidecar["chamber"] == chamber_url and sidecar["program"]["program_sha256"] == log.header.program_sha256
    assert log.rows[-1].state == "done" and sidecar.get("status") != "interrupted"
    running = [row for row in log.rows if row.state == "running"]
    assert running[-1].t_s == program.duration_s
    device_t_s = np.array([row.device_t_s for row in running])
    assert np.all(np.diff(device_t_s) > 0)  # the gyro's frames arrived all along
    expected = program.air_temp_c(np.array([row.t_s for row in running]))
    assert np.abs(np.array([row.setpoint_c for row in running]) - expected).max() <= 0.05 + 1e-9
    assert capture.stat().st_size > 0
    inspect = run_cli("inspect", str(capture))
    assert inspect.returncode == 0, inspect.stderr


def test_the_calibration_tutorials_session_runs_as_written(tmp_path: Path) -> None:
    (program,) = blocks("yaml")
    (tmp_path / "short.yaml").write_text(program)
    yaml.safe_load(program)
    serve, calibrate, resume, inspect = (shlex.split(block.strip()) for block in blocks("sh"))
    assert serve[:2] == ["fog-driver", "simulate"] and calibrate[:2] == ["fog-driver", "calibrate"]
    assert (
        resume[:2] == ["fog-driver", "calibrate"] and "--resume" in resume and inspect[:2] == ["fog-driver", "inspect"]
    )
    # the test's own port and link, so that it runs beside others: everything else as the page says
    link = str(tmp_path / "sim.tty")
    served = [re.sub(r":10001", ":0", word) for word in serve[1:]] + ["--link", link]
    lab = Lab(served)
    try:
        port_url = re.sub(r"\?.*", "", lab.chamber_url)
        argv = [
            link if w == "/tmp/fog-driver-sim.tty" else w.replace("espec://127.0.0.1:10001", port_url)
            for w in calibrate[1:]
        ]
        proc = subprocess.run(
            [sys.executable, "-m", "fog_driver", *argv],
            cwd=tmp_path,
            capture_output=True,
            text=True,
            timeout=RUN_GUARD_S,
        )
    finally:
        lab.stop()
    assert proc.returncode == 0, proc.stderr
    assert "degC assumed" in proc.stderr  # the page says it is said once
    check_run(tmp_path, "run.bin", tmp_path / "short.yaml", port_url)


#: a 1.5-s program at the served chamber's start temperature (20 degC): a hold, a ramp of 0.25 degC, a hold
SHORT = (
    "name: s\nstart_c: 20\nsegments:\n"
    "- hold: {duration_s: 0.5}\n- ramp: {rate_c_per_min: 30, target_c: 20.25}\n- hold: {duration_s: 0.5}\n"
)
OPTIONS = {"thermotron": "?range=-70:180", "simserv": "", "watlow-f4t": ""}


@pytest.mark.parametrize("scheme", sorted(OPTIONS))
def test_calibrate_runs_on_each_protocols_simulated_lab(scheme: str, tmp_path: Path) -> None:
    (tmp_path / "s.yaml").write_text(SHORT)
    link = str(tmp_path / "sim.tty")
    lab = Lab(["simulate", "--serve", "pty", "--chamber-serve", f"{scheme}://127.0.0.1:0?start_c=20", "--link", link])
    try:
        url = re.sub(r"\?.*", "", lab.chamber_url) + OPTIONS[scheme]
        proc = run_cli(
            "calibrate", link, "--chamber", url, "--profile", str(tmp_path / "s.yaml"), "--out", str(tmp_path / "r.bin")
        )
    finally:
        lab.stop()
    assert proc.returncode == 0, proc.stderr
    check_run(tmp_path, "r.bin", tmp_path / "s.yaml", url)
