"""The chamber runner (fog_driver.lab.runner) on a fake clock and an in-memory chamber: every rule of its
docstring, and a property test over drawn programs, steps and link losses."""

from __future__ import annotations

import itertools
import threading
from datetime import datetime
from pathlib import Path

import numpy as np
import pytest
from fakes_chamber import EPOCH, FakeChamber, FakeClock
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fog_driver.errors import InputFileError
from fog_driver.lab.chamberlog import ChamberLogWriter, LogHeader, LogRow, program_sha256, read_chamber_log
from fog_driver.lab.controllers.base import (
    ChamberRange,
    ControllerProtocolError,
    ControllerRefused,
    ProgramOutOfRange,
)
from fog_driver.lab.program import ChamberProfile, Hold, Ramp, Sinusoid, Step
from fog_driver.lab.runner import (
    OnStop,
    RunOptions,
    RunResult,
    SetpointOverridden,
    SystemClock,
    parse_on_stop,
    resume_point,
    run_program,
)

RAMP = ChamberProfile("ramp", 20.0, (Hold(10.0), Ramp(6.0, 25.0), Hold(10.0)))  # 0.1 degC/s: 50 s of ramp


def host_s(row: LogRow) -> float:
    """The fake clock's time of a row, from its t_utc."""
    return (datetime.fromisoformat(row.t_utc.replace("Z", "+00:00")) - EPOCH).total_seconds()


def run(
    chamber: FakeChamber,
    program: ChamberProfile,
    path: Path,
    *,
    gyro: object = None,
    resume_t_s: float | None = None,
    stop: threading.Event | None = None,
    **options: object,
) -> tuple[RunResult, list[LogRow]]:
    log = ChamberLogWriter(path, LogHeader(program.name, program_sha256(program), chamber.url, "run-1", None))
    rows: list[LogRow] = []  # as written (exact: the file's number format is the log writer's)
    try:
        result = run_program(
            chamber,  # type: ignore[arg-type]
            program,
            log,
            options=RunOptions(**options),  # type: ignore[arg-type]
            clock=chamber.clock,
            stop=stop or threading.Event(),
            gyro=gyro,  # type: ignore[arg-type]
            resume_t_s=resume_t_s,
            on_row=rows.append,
        )
    finally:
        log.close()
    assert [row.state for row in read_chamber_log(path).rows] == [row.state for row in rows]
    return result, rows


def program_at(program: ChamberProfile, t_s: float) -> float:
    return float(program.air_temp_c(np.array([t_s]))[0])


def test_a_ramp_writes_the_program_at_each_step_rounded_to_the_resolution(tmp_path: Path) -> None:
    chamber = FakeChamber(FakeClock(), resolution_c=0.1)
    result, rows = run(chamber, RAMP, tmp_path / "log.csv", step_s=1.0)
    running = [r for r in rows if r.state == "running"]
    assert [r.t_s for r in running] == [float(k) for k in range(int(RAMP.duration_s) + 1)]
    for row, (when_s, written_c) in zip(running, chamber.writes, strict=True):
        assert row.program_c == written_c
        assert abs(written_c - program_at(RAMP, row.t_s)) <= 0.05 + 1e-9
        assert when_s == host_s(row) == row.t_s  # no settling: the program starts at host time 0
        assert row.setpoint_c == written_c
        assert abs(written_c / 0.1 - round(written_c / 0.1)) < 1e-9  # a multiple of the resolution
    assert rows[-1].state == "done" and result.status == "done" and result.program_t_s == RAMP.duration_s
    assert result.lateness_s == [0.0] * len(running)
    assert running[15].segment == 1 and running[0].segment == 0


def test_a_chamber_far_from_the_start_settles_first_outside_the_program_clock(tmp_path: Path) -> None:
    chamber = FakeChamber(FakeClock(), air_c=10.0, rate_c_per_s=1.0)  # 10 degC off: about 10 s to settle
    _, rows = run(chamber, RAMP, tmp_path / "log.csv")
    settling = [r for r in rows if r.state == "settling"]
    assert settling and all(r.t_s is None and r.program_c == 20.0 for r in settling)
    assert abs(settling[-1].air_c - 20.0) <= 0.5 and all(abs(r.air_c - 20.0) > 0.5 for r in settling[:-1])
    first = next(r for r in rows if r.state == "running")
    assert first.t_s == 0.0 and host_s(first) == host_s(settling[-1]) + 1.0
    assert rows.index(first) == len(settling)


def test_a_chamber_within_half_a_degree_starts_the_program_at_once(tmp_path: Path) -> None:
    chamber = FakeChamber(FakeClock(), air_c=20.4)
    _, rows = run(chamber, RAMP, tmp_path / "log.csv")
    assert rows[0].state == "running" and rows[0].t_s == 0.0


def test_a_program_beyond_the_range_is_refused_with_nothing_written(tmp_path: Path) -> None:
    chamber = FakeChamber(FakeClock(), range_c=ChamberRange(-10.0, 24.0))
    with pytest.raises(ProgramOutOfRange, match="20 .. 25 degC"):
        run(chamber, RAMP, tmp_path / "log.csv")
    assert chamber.writes == [] and read_chamber_log(tmp_path / "log.csv").rows == []


def test_a_sinusoid_beyond_the_range_by_its_crest_is_refused(tmp_path: Path) -> None:
    program = ChamberProfile("sine", 20.0, (Sinusoid(5.0, 100.0, 100.0),))
    chamber = FakeChamber(FakeClock(), range_c=ChamberRange(0.0, 24.0))
    with pytest.raises(ProgramOutOfRange):
        run(chamber, program, tmp_path / "log.csv")
    assert chamber.writes == []


def test_an_on_stop_target_beyond_the_range_is_refused_with_nothing_written(tmp_path: Path) -> None:
    chamber = FakeChamber(FakeClock(), range_c=ChamberRange(-10.0, 40.0))
    with pytest.raises(ProgramOutOfRange, match="--on-stop 90"):
        run(chamber, RAMP, tmp_path / "log.csv", on_stop=OnStop("goto", 90.0))
    assert chamber.writes == []


def test_someone_overriding_the_set_point_stops_the_run_with_nothing_more_written(tmp_path: Path) -> None:
    chamber = FakeChamber(FakeClock())
    chamber.override_c = 30.0
    with pytest.raises(SetpointOverridden, match="reads 30 degC") as info:
        run(chamber, RAMP, tmp_path / "log.csv")
    assert info.value.exit_status == 65
    assert len(chamber.writes) == 1
    assert [r.state for r in read_chamber_log(tmp_path / "log.csv").rows] == ["stopped"]


def test_a_read_back_within_half_the_resolution_is_not_an_override(tmp_path: Path) -> None:
    chamber = FakeChamber(FakeClock(), resolution_c=0.1)
    chamber.override_c = 20.04  # the controller's own rounding of 20.0
    _, rows = run(chamber, ChamberProfile("h", 20.0, (Hold(5.0),)), tmp_path / "log.csv")
    assert rows[-1].state == "done"


@pytest.mark.parametrize(
    ("switch", "error"), [("refuse_writes", ControllerRefused), ("exception_on_write", ControllerProtocolError)]
)
def test_a_refused_or_excepted_write_stops_with_nothing_more_written(tmp_path: Path, switch: str, error: type) -> None:
    chamber = FakeChamber(FakeClock())
    setattr(chamber, switch, True)
    with pytest.raises(error):
        run(chamber, RAMP, tmp_path / "log.csv", on_stop=OnStop("goto", 0.0))
    assert chamber.writes == [] and chamber.safe_stops == 0
    assert [r.state for r in read_chamber_log(tmp_path / "log.csv").rows] == ["stopped"]


def test_a_slow_write_is_late_once_and_the_next_step_keeps_its_schedule(tmp_path: Path) -> None:
    chamber = FakeChamber(FakeClock(), write_delay_s=0.0)
    original = chamber.write_setpoint_c

    def slow_fifth(value_c: float) -> None:
        original(value_c)
        if len(chamber.writes) == 5:
            chamber.clock.advance(1.3)  # the write returns 1.3 s late: step 5 (due at 5 s) runs at once, 0.3 s late

    chamber.write_setpoint_c = slow_fifth  # type: ignore[method-assign]
    result, rows = run(chamber, ChamberProfile("h", 20.0, (Hold(10.0),)), tmp_path / "log.csv")
    times = [when for when, _ in chamber.writes]
    assert times[:5] == [0.0, 1.0, 2.0, 3.0, 4.0]
    assert times[5] == pytest.approx(5.3) and times[6:] == [6.0, 7.0, 8.0, 9.0, 10.0]
    assert result.lateness_s[5] == pytest.approx(0.3) and max(result.lateness_s[6:]) == 0.0
    assert [r.t_s for r in rows if r.state == "running"] == [float(k) for k in range(11)]


def test_a_lost_link_pauses_the_program_clock_and_reconnects_with_a_doubling_backoff(tmp_path: Path) -> None:
    chamber = FakeChamber(FakeClock(), link_lost_windows=[(20.5, 40.0)])
    _, rows = run(chamber, RAMP, tmp_path / "log.csv", reconnect_first_s=0.5, reconnect_max_s=4.0)
    lost = [r for r in rows if r.state == "link_lost"]
    assert lost and all(r.setpoint_c is None and r.air_c is None and r.t_s == 21.0 for r in lost)
    # the step due at 21 s fails; attempts 0.5, 1, 2, 4, 4, ... s apart until one lands after 40 s
    gaps = np.diff([21.0, *chamber.connects])
    expected = list(itertools.islice(itertools.chain([0.5, 1.0, 2.0], itertools.repeat(4.0)), len(gaps)))
    assert gaps.tolist() == expected and chamber.connects[-1] >= 40.0 > chamber.connects[-2]
    running = [r for r in rows if r.state == "running"]
    assert [r.t_s for r in running] == [float(k) for k in range(int(RAMP.duration_s) + 1)]  # the ramp resumes
    after = next(r for r in running if r.t_s == 21.0)
    assert host_s(after) == chamber.connects[-1]  # written at once on reconnecting
    paused_s = chamber.connects[-1] - 21.0
    assert all(host_s(r) - r.t_s == paused_s for r in running if r.t_s >= 21.0)


class Gyro:
    """A gyro feed silent during ``silent`` windows of the fake clock's time."""

    def __init__(self, clock: FakeClock, silent: tuple[float, float]) -> None:
        self.clock, self.silent = clock, silent

    def device_t_s(self) -> float | None:
        return min(self.clock.now_s, self.silent[0]) if self.clock.now_s < self.silent[1] else self.clock.now_s

    def seconds_since_frame(self) -> float | None:
        a, b = self.silent
        return self.clock.now_s - a if a <= self.clock.now_s < b else 0.0


def test_a_silent_gyro_holds_the_program_until_frames_come_back(tmp_path: Path) -> None:
    clock = FakeClock()
    chamber = FakeChamber(clock)
    _, rows = run(chamber, RAMP, tmp_path / "log.csv", gyro=Gyro(clock, (15.0, 40.0)), pause_after_s=10.0)
    holding = [r for r in rows if r.state == "holding"]
    # silent from 15 s: more than 10 s from 26 s on (exclusive), until 40 s
    assert [host_s(r) for r in holding] == [float(k) for k in range(26, 40)]
    assert {r.t_s for r in holding} == {26.0} and {r.program_c for r in holding} == {round(program_at(RAMP, 26.0), 1)}
    running = [r for r in rows if r.state == "running"]
    assert [r.t_s for r in running] == [float(k) for k in range(int(RAMP.duration_s) + 1)]
    assert all(r.device_t_s is not None for r in rows)


def test_the_end_with_on_stop_hold_writes_nothing_more(tmp_path: Path) -> None:
    chamber = FakeChamber(FakeClock())
    _, rows = run(chamber, RAMP, tmp_path / "log.csv", on_stop=OnStop("hold"))
    assert len(chamber.writes) == len([r for r in rows if r.state == "running"]) and chamber.safe_stops == 0
    assert rows[-1].state == "done" and rows[-1].program_c is None


def test_the_end_with_on_stop_standby_puts_the_chamber_in_standby(tmp_path: Path) -> None:
    chamber = FakeChamber(FakeClock())
    _, rows = run(chamber, RAMP, tmp_path / "log.csv", on_stop=parse_on_stop("standby"))
    assert chamber.safe_stops == 1 and rows[-1].state == "done"


def test_standby_at_the_end_on_a_lost_link_is_reached_once_the_link_is_back(tmp_path: Path) -> None:
    program = ChamberProfile("h", 20.0, (Hold(10.0),))
    chamber = FakeChamber(FakeClock(), link_lost_windows=[(10.5, 20.0)])
    original = chamber.read_air_c

    def lose_after_the_last_step() -> float:
        value = original()
        if len(chamber.writes) == 11:
            chamber.clock.advance(0.6)  # the link goes in the window just after the program's last step
        return value

    chamber.read_air_c = lose_after_the_last_step  # type: ignore[method-assign]
    _, rows = run(chamber, program, tmp_path / "log.csv", on_stop=OnStop("standby"))
    assert chamber.safe_stops == 1 and chamber.connects[-1] >= 20.0
    assert "link_lost" in [r.state for r in rows] and rows[-1].state == "done"


def test_an_interrupt_with_on_stop_c_ramps_there_at_the_slowest_rate_and_holds(tmp_path: Path) -> None:
    program = ChamberProfile("two", 20.0, (Ramp(6.0, 30.0), Ramp(3.0, 20.0), Hold(100.0)))  # slowest 3 degC/min
    chamber = FakeChamber(FakeClock())
    chamber.clock.stop_at_s = 60.5
    stop = threading.Event()
    result, rows = run(chamber, program, tmp_path / "log.csv", on_stop=parse_on_stop("25"), stop=stop)
    assert result.status == "interrupted" and rows[-1].state == "interrupted" and result.program_t_s == 60.0
    stopped = [r for r in rows if r.state == "stopped"]
    from_c = program_at(program, 60.0)  # 28 degC
    for k, row in enumerate(stopped):
        expected = max(25.0, from_c - 0.05 * k)  # 3 degC/min down to 25
        assert abs(row.program_c - expected) <= 0.05 + 1e-9 and row.t_s == 60.0
    assert stopped[-1].program_c == 25.0 and len(stopped) == round((from_c - 25.0) / 0.05) + 1
    assert chamber.writes[-1][1] == 25.0


def test_on_stop_c_without_a_ramp_goes_at_one_degree_a_minute(tmp_path: Path) -> None:
    chamber = FakeChamber(FakeClock())
    _, rows = run(chamber, ChamberProfile("h", 20.0, (Hold(3.0),)), tmp_path / "log.csv", on_stop=OnStop("goto", 21.0))
    stopped = [r for r in rows if r.state == "stopped"]
    assert len(stopped) == 61 and stopped[-1].program_c == 21.0


def test_parse_on_stop_takes_hold_standby_or_a_temperature() -> None:
    assert parse_on_stop("hold") == OnStop("hold") and parse_on_stop("-12.5") == OnStop("goto", -12.5)
    for bad in ("warm", "nan", "inf"):
        with pytest.raises(ValueError):
            parse_on_stop(bad)


def test_an_interrupted_run_resumes_from_its_log_where_the_program_clock_stopped(tmp_path: Path) -> None:
    chamber = FakeChamber(FakeClock())
    chamber.clock.stop_at_s = 30.5
    run(chamber, RAMP, tmp_path / "first.csv")
    t_s = resume_point(read_chamber_log(tmp_path / "first.csv"), RAMP)
    assert t_s == 30.0
    again = FakeChamber(FakeClock(), air_c=chamber.air_c, setpoint_c=chamber.setpoint_c)
    _, rows = run(again, RAMP, tmp_path / "second.csv", resume_t_s=t_s)
    running = [r for r in rows if r.state == "running"]
    assert [r.t_s for r in running] == [float(k) for k in range(30, int(RAMP.duration_s) + 1)]


def test_resuming_from_another_programs_log_is_refused(tmp_path: Path) -> None:
    run(FakeChamber(FakeClock()), RAMP, tmp_path / "first.csv")
    other = ChamberProfile("ramp", 20.0, (Hold(10.0), Ramp(6.0, 26.0)))
    with pytest.raises(InputFileError, match="another run's"):
        resume_point(read_chamber_log(tmp_path / "first.csv"), other)


def test_a_days_program_at_one_second_steps_runs_on_the_fake_clock(tmp_path: Path) -> None:
    program = ChamberProfile("long", 20.0, (Ramp(0.5, 60.0), Hold(3600.0), Step(-20.0), Hold(3600.0)))
    chamber = FakeChamber(FakeClock())
    result, _ = run(chamber, program, tmp_path / "log.csv", step_s=1.0)
    assert result.status == "done" and len(chamber.writes) == int(program.duration_s) + 1


def test_the_system_clock_waits_on_the_stop_event() -> None:
    stop = threading.Event()
    stop.set()
    clock = SystemClock()
    assert clock.wait(stop, 5.0) is True and clock.utc_now().tzinfo is not None


DRAWS = itertools.count()
segments = st.one_of(
    st.builds(Hold, st.floats(1.0, 60.0)),
    st.builds(Ramp, st.floats(0.5, 10.0), st.floats(-20.0, 60.0)),
    st.builds(Step, st.floats(-20.0, 60.0)),
    st.builds(Sinusoid, st.floats(0.0, 5.0), st.floats(10.0, 100.0), st.floats(5.0, 60.0)),
)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    start_c=st.floats(-20.0, 60.0),
    segs=st.lists(segments, min_size=1, max_size=5),
    step_s=st.sampled_from([0.5, 1.0, 2.5, 10.0]),
    resolution_c=st.sampled_from([0.1, 0.01, 1.0]),
    windows=st.lists(st.tuples(st.floats(0.01, 300.0), st.floats(0.1, 50.0)), max_size=3),
)
def test_every_written_set_point_is_the_program_at_its_time_and_a_link_loss_pauses_the_clock_exactly(
    tmp_path: Path,
    start_c: float,
    segs: list,
    step_s: float,
    resolution_c: float,
    windows: list[tuple[float, float]],
) -> None:
    program = ChamberProfile("drawn", start_c, tuple(segs))
    chamber = FakeChamber(
        FakeClock(),
        air_c=start_c,
        setpoint_c=start_c,
        resolution_c=resolution_c,
        range_c=ChamberRange(-40.0, 80.0),
        link_lost_windows=[(a, a + d) for a, d in windows],
    )
    path = tmp_path / f"log-{next(DRAWS)}.csv"
    _, rows = run(chamber, program, path, step_s=step_s, reconnect_first_s=0.5, reconnect_max_s=4.0)
    running = [r for r in rows if r.state == "running"]
    for row in running:
        assert abs(row.program_c - program_at(program, row.t_s)) <= resolution_c / 2 + 1e-9
        assert abs(row.program_c / resolution_c - round(row.program_c / resolution_c)) < 1e-6
        assert not any(a <= host_s(row) < a + d for a, d in windows)
    # the program's clock runs a step per step and stands still while the link is lost: no time skipped or repeated
    expected = [min(k * step_s, program.duration_s) for k in range(len(running))]
    assert [r.t_s for r in running] == pytest.approx(expected, abs=1e-9)
    assert running[-1].t_s == program.duration_s and rows[-1].state == "done"
    # and it stands still exactly from the step that failed to the reconnection that drove it again
    for before, after in itertools.pairwise(running[:-1]):  # the last at the end (its program time cut there)
        paused_s = (host_s(after) - after.t_s) - (host_s(before) - before.t_s)
        lost = [r for r in rows[rows.index(before) : rows.index(after)] if r.state == "link_lost"]
        if not lost:
            assert paused_s == pytest.approx(0.0, abs=2e-3)  # t_utc to the millisecond
        else:
            failed_due_s = host_s(before) + step_s
            reconnected_s = next(t for t in chamber.connects if t >= failed_due_s and host_s(after) - t < 1e-3)
            assert paused_s == pytest.approx(reconnected_s - failed_due_s, abs=2e-3)
