"""Whether the chamber ran its program as designed: synthetic chamber logs of a good chamber and of slow ones."""

from __future__ import annotations

import datetime as _dt

import numpy as np
import pytest

from fog_driver.errors import InputFileError
from fog_driver.lab.chamberlog import ChamberLogWriter, LogHeader, LogRow, format_utc, read_chamber_log
from fog_driver.lab.program import ChamberProfile, Hold, Ramp, Step
from fog_driver.offline.chamber import find_chamber_log, lag_stretches, program_warnings

PROGRAM = ChamberProfile("ramps", 20.0, (Hold(600.0), Ramp(1.0, 80.0), Hold(3600.0), Ramp(1.0, 20.0), Hold(1800.0)))
T0 = _dt.datetime(2026, 12, 7, 12, 0, tzinfo=_dt.UTC)


def chamber_air(program_c: np.ndarray, dt_s: float, tau_s: float, max_rate_c_per_min: float) -> np.ndarray:
    """A chamber: the air follows the set point through a rate limit and a first-order lag (an independent
    model of the one the fit's warning assumes)."""
    air = np.empty_like(program_c)
    driven = air_now = program_c[0]
    for k, target in enumerate(program_c):
        step = max_rate_c_per_min / 60.0 * dt_s
        driven += float(np.clip(target - driven, -step, step))
        air_now += (driven - air_now) * (1.0 - np.exp(-dt_s / tau_s))
        air[k] = air_now
    return air


def write_log(path, program: ChamberProfile, *, tau_s: float, max_rate: float, dt_s: float = 10.0, daemon=False):
    t = np.arange(0.0, program.duration_s, dt_s)
    program_c = program.air_temp_c(t)
    air = chamber_air(program_c, dt_s, tau_s, max_rate)
    with ChamberLogWriter(path, LogHeader(program.name, "0" * 64, "sim://", "run", None)) as log:
        for k, t_k in enumerate(t):
            log.write(
                LogRow(
                    format_utc(T0 + _dt.timedelta(seconds=float(t_k))),
                    None if daemon else float(t_k),
                    None,
                    float(program_c[k]),
                    float(air[k]),
                    "running",
                    None if daemon else float(program_c[k]),
                    None if daemon else 0,
                )
            )
    return read_chamber_log(path)


@pytest.mark.parametrize("tau_s", [60.0, 300.0])
def test_a_good_chamber_lagging_its_ramps_by_its_own_time_constant_is_not_warned_of(tmp_path, tau_s):
    log = write_log(tmp_path / "run.chamber.csv", PROGRAM, tau_s=tau_s, max_rate=5.0)
    lag = np.nanmax(np.abs(log.air_c - log.program_c))
    assert lag > 0.9 * tau_s / 60.0  # it does lag by about tau x rate (1 or 5 degC)
    assert lag_stretches(log) == []
    assert program_warnings("run.bin", log) == []


def test_a_chamber_too_slow_for_the_designed_ramps_is_warned_of_with_the_stretch(tmp_path):
    log = write_log(tmp_path / "run.chamber.csv", PROGRAM, tau_s=120.0, max_rate=0.5)
    stretches = lag_stretches(log)
    assert len(stretches) == 2  # the ramp up and the ramp down
    up = stretches[0]
    # the program's ramp runs from 600 s to 4200 s; at 0.5 degC/min the air leaves the 15-min window plus
    # 2 degC about 34 min into it, and catches up about 60 min after the ramp's end
    assert up.program_time and 600 + 30 * 60 < up.start_s < 600 + 40 * 60
    assert up.end_s > 4200 and up.duration_s > 30 * 60
    assert up.worst_lag_c == pytest.approx(30.0, abs=2.0)  # half of 60 degC behind at the ramp's end
    (line,) = program_warnings("run.bin", log)
    assert "did not run its program as designed" in line and "run.bin" in line and "up to 3" in line
    assert "ramps run at their rates" in line and "\n" not in line


def test_a_designed_step_the_chamber_settles_after_is_not_a_lag(tmp_path):
    program = ChamberProfile("step", 20.0, (Hold(600.0), Step(80.0), Hold(7200.0)))
    log = write_log(tmp_path / "run.chamber.csv", program, tau_s=300.0, max_rate=60.0)
    assert lag_stretches(log) == []


def test_a_daemon_log_without_a_program_is_judged_on_the_read_back_set_point(tmp_path):
    log = write_log(tmp_path / "run.chamber.csv", PROGRAM, tau_s=120.0, max_rate=0.5, daemon=True)
    stretches = lag_stretches(log)
    assert len(stretches) == 2 and not stretches[0].program_time
    assert 600 + 30 * 60 < stretches[0].start_s < 600 + 40 * 60  # seconds from the log's start: the same here


def test_a_lost_link_ends_a_stretch(tmp_path):
    path = tmp_path / "a.chamber.csv"
    log = write_log(path, PROGRAM, tau_s=120.0, max_rate=0.5)
    rows = [
        r if not 5000 <= (r.t_s or 0) < 5010 else LogRow(r.t_utc, r.t_s, None, None, None, "link_lost", r.program_c, 0)
        for r in log.rows
    ]
    log.rows[:] = rows
    assert len(lag_stretches(log)) == 3  # the ramp up's stretch cut in two by the row without air


def test_the_chamber_log_is_found_from_the_sidecar_or_beside_the_capture(tmp_path):
    capture = tmp_path / "run.bin"
    capture.write_bytes(b"")
    assert find_chamber_log(capture) is None
    beside = tmp_path / "run.chamber.csv"
    beside.write_text("x")
    assert find_chamber_log(capture) == beside
    (tmp_path / "logs").mkdir()
    named = tmp_path / "logs" / "chamber.csv"
    named.write_text("x")
    sidecar = tmp_path / "run.bin.yaml"
    sidecar.write_text("format: fog_driver capture provenance\ncapture: run.bin\nchamber_log: logs/chamber.csv\n")
    assert find_chamber_log(capture) == named
    sidecar.write_text("format: fog_driver capture provenance\ncapture: run.bin\nchamber_log: gone.csv\n")
    with pytest.raises(InputFileError, match="names the chamber log .*gone.csv, which is not there"):
        find_chamber_log(capture)
