"""The chamber program run by the host: the set point stepped every ``step_s`` along the program, so any
controller that takes a set point runs any program (holds, ramps, sinusoids).

The rules ``run_program`` follows:

- **Range first.** Before any write it reads the controller's range and refuses a program (and an ``--on-stop C``
  target) outside it: ``ProgramOutOfRange`` (exit 65), nothing written.  The whole program is checked, also when
  resuming; a sinusoid by the extremes it reaches.
- **Settling.** If the air is more than ``settle_tolerance_c`` from the program's temperature at its start (or at
  the resume point), the runner holds that temperature, one ``settling`` row a step, until a step reads the air
  within it; the program's clock starts at the next step (``t_s`` 0: its first write after settling).
- **Steps.** Each step writes the program's set point at the step's program time, rounded to the controller's
  ``resolution_c``, reads back the set point and the air, and writes one log row.  Steps are due on absolute
  times, ``due_k = anchor + k * step_s`` on the host's monotonic clock (no drift); a late step is written at once
  with the program time of its due time, and its lateness (seconds after its due time) is recorded; the next keeps
  its schedule.  A step later than a whole step: the steps missed are skipped (no rows), the program's clock runs on.
- **Overridden.** A read-back set point more than ``resolution_c / 2`` from the one written (someone else drives
  the chamber): a ``stopped`` row, then ``SetpointOverridden`` (exit 65); nothing more is written.
- **Link lost** (``ControllerUnreachable``): the controller holds its last set point; ``link_lost`` rows, one at
  each reconnection attempt, at ``reconnect_first_s`` after the loss, then doubling to ``reconnect_max_s``.  The
  program's clock is paused from the due time of the step that failed: the step after the reconnection writes
  that step's program time at once (a ramp resumes where it stopped) and the schedule is anchored there.
- **Gyro silent** (``gyro`` given, no frame yet or none for more than ``pause_after_s``): ``holding`` rows, the
  set point of the paused program time written again each step, the program's clock paused until frames come
  back.
- **Refused or garbage** (``ControllerRefused``, ``ControllerProtocolError``): a ``stopped`` row, the error raised
  (one line); nothing more written.
- **The end** (the program's end, or ``stop`` set: SIGINT/SIGTERM): ``on_stop``; ``hold`` writes nothing more,
  ``standby`` calls ``controller.safe_stop()`` (on a lost link: once reconnected), ``goto`` ramps from the last
  set point to its target at the program's slowest ramp rate (1 degC/min if it has no ramp), stepping every
  ``step_s`` (rows ``stopped``, ``t_s`` the program time where it stopped), and returns once the target is
  written (the controller holds it).  The ramp to the target does not end at ``stop`` (a second Ctrl-C ends the
  process).  Then a final row ``done`` or ``interrupted`` with the set point and air read back (empty if the
  link is lost).

``resume_point`` gives the program time an interrupted run's log stops at; ``run_program(resume_t_s=...)`` goes on
from there into a new log.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Literal, Protocol

import numpy as np

from ..errors import InputFileError
from .chamberlog import ChamberLog, ChamberLogWriter, LogRow, format_utc, program_sha256
from .controllers.base import (
    ChamberController,
    ChamberRange,
    ControllerProtocolError,
    ControllerRefused,
    ControllerUnreachable,
    ProgramOutOfRange,
)
from .program import ChamberProfile, Ramp, Sinusoid

#: The ramp rate of ``--on-stop C`` for a program without a ramp, degC/min.
DEFAULT_GOTO_RATE_C_PER_MIN = 1.0


class SetpointOverridden(InputFileError):
    """The set point read back is not the one written (someone else drives the chamber): exit 65."""


class Clock(Protocol):
    def monotonic(self) -> float: ...

    def utc_now(self) -> datetime: ...  # aware, UTC

    def wait(self, stop: threading.Event, timeout_s: float) -> bool: ...  # True if stop was set


class SystemClock:
    """The host's clocks: ``time.monotonic``, the UTC wall clock, and ``Event.wait``."""

    def monotonic(self) -> float:
        return time.monotonic()

    def utc_now(self) -> datetime:
        return datetime.now(UTC)

    def wait(self, stop: threading.Event, timeout_s: float) -> bool:
        return stop.wait(max(0.0, timeout_s))


@dataclass(frozen=True)
class OnStop:
    """What the runner does at the program's end or a stop: ``hold`` (write nothing more), ``standby``
    (``safe_stop``), ``goto`` ``target_c`` (ramp there and hold)."""

    kind: Literal["hold", "standby", "goto"]
    target_c: float | None = None

    def __post_init__(self) -> None:
        if (self.kind == "goto") != (self.target_c is not None):
            raise ValueError("on-stop goto takes a target temperature, hold and standby none")


def parse_on_stop(text: str) -> OnStop:
    """``hold`` | ``standby`` | a finite number of degC (go there); ``ValueError`` otherwise."""
    if text in ("hold", "standby"):
        return OnStop(text)  # type: ignore[arg-type]
    try:
        value = float(text)
        if not math.isfinite(value):
            raise ValueError(text)
    except ValueError:
        raise ValueError(f"on-stop must be hold, standby or a finite temperature in degC: {text!r}") from None
    return OnStop("goto", value)


class GyroFeed(Protocol):
    def device_t_s(self) -> float | None: ...  # device time of the last frame received

    def seconds_since_frame(self) -> float | None: ...  # host seconds since the last frame (None: none yet)


@dataclass(frozen=True)
class RunOptions:
    step_s: float = 1.0
    on_stop: OnStop = OnStop("hold")
    settle_tolerance_c: float = 0.5
    pause_after_s: float = 10.0
    reconnect_first_s: float = 0.5
    reconnect_max_s: float = 30.0

    def __post_init__(self) -> None:
        for name in ("step_s", "reconnect_first_s", "reconnect_max_s"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) > 0):
                raise ValueError(f"{name} must be > 0 and finite")


@dataclass
class RunResult:
    status: str  # "done" | "interrupted"
    program_t_s: float  # the program time reached
    rows: int
    lateness_s: list[float] = field(default_factory=list)  # of each step written on schedule, s after its due time


def round_to_resolution(value_c: float, resolution_c: float) -> float:
    """``value_c`` to the nearest multiple of ``resolution_c`` (12 decimals: no float fuzz in the log)."""
    if resolution_c <= 0:
        return value_c
    return round(round(value_c / resolution_c) * resolution_c, 12)


def program_extremes_c(program: ChamberProfile) -> tuple[float, float]:
    """The lowest and highest temperature the program asks for (a sinusoid by the extremes it reaches)."""
    low = high = program.start_c
    for span in program.spans():
        low, high = min(low, span.start_c, span.end_c), max(high, span.start_c, span.end_c)
        seg = span.segment
        if isinstance(seg, Sinusoid):
            phase = 2 * math.pi * seg.duration_s / seg.period_s
            top = 1.0 if phase >= math.pi / 2 else math.sin(phase)
            bottom = -1.0 if phase >= 3 * math.pi / 2 else min(0.0, math.sin(phase))
            low, high = (
                min(low, span.start_c + seg.amplitude_c * bottom),
                max(high, span.start_c + seg.amplitude_c * top),
            )
    return low, high


def check_range(program: ChamberProfile, rng: ChamberRange, on_stop: OnStop) -> None:
    """``ProgramOutOfRange`` unless the program and the on-stop target are within the controller's range."""
    low, high = program_extremes_c(program)
    where = f"the controller's range {rng.low_c:g} .. {rng.high_c:g} degC; nothing written"
    if low < rng.low_c or high > rng.high_c:
        raise ProgramOutOfRange(f"program {program.name} spans {low:g} .. {high:g} degC, outside {where}")
    if on_stop.target_c is not None and not rng.contains(on_stop.target_c):
        raise ProgramOutOfRange(f"--on-stop {on_stop.target_c:g} degC is outside {where}")


def slowest_ramp_c_per_min(program: ChamberProfile) -> float:
    """The slowest ramp rate of the program, or ``DEFAULT_GOTO_RATE_C_PER_MIN`` if it has no ramp."""
    rates = [seg.rate_c_per_min for seg in program.segments if isinstance(seg, Ramp)]
    return min(rates) if rates else DEFAULT_GOTO_RATE_C_PER_MIN


def resume_point(log: ChamberLog, program: ChamberProfile) -> float:
    """The program time an interrupted run's log stops at: the last ``t_s`` of a ``running`` row (0 if none).
    ``InputFileError`` if the log is another program's (its ``program_sha256`` differs)."""
    if log.header.program_sha256 != program_sha256(program):
        raise InputFileError(
            f"the log is another run's: its program ({log.header.program_name}) is not {program.name} as given"
        )
    times = [row.t_s for row in log.rows if row.state == "running" and row.t_s is not None]
    return max(times) if times else 0.0


class _Stopped(Exception):
    """The run ends here (the stop event is set)."""


@dataclass
class _Run:
    """One run's state: the schedule's anchor, the program time and the log."""

    controller: ChamberController
    program: ChamberProfile
    log: ChamberLogWriter
    options: RunOptions
    clock: Clock
    stop: threading.Event
    gyro: GyroFeed | None
    on_row: Callable[[LogRow], None] | None
    rows: int = 0
    lateness_s: list[float] = field(default_factory=list)
    last_written_c: float | None = None
    paused_t_s: float | None = None  # the program time of the last step due (where a pause holds it)

    def __post_init__(self) -> None:
        self._starts = np.array([s.t_start_s for s in self.program.spans()])

    # --- rows --------------------------------------------------------------------------------------
    def segment_at(self, t_s: float) -> int | None:
        if not len(self._starts):
            return None
        return int(np.clip(np.searchsorted(self._starts, t_s, side="right") - 1, 0, len(self._starts) - 1))

    def program_c(self, t_s: float) -> float:
        return float(self.program.air_temp_c(np.array([min(t_s, self.program.duration_s)]))[0])

    def row(
        self,
        state: str,
        t_s: float | None,
        setpoint_c: float | None,
        air_c: float | None,
        program_c: float | None,
        segment: int | None,
    ) -> None:
        device_t_s = self.gyro.device_t_s() if self.gyro is not None else None
        row = LogRow(format_utc(self.clock.utc_now()), t_s, device_t_s, setpoint_c, air_c, state, program_c, segment)
        self.log.write(row)
        self.rows += 1
        if self.on_row is not None:
            self.on_row(row)

    # --- one step ----------------------------------------------------------------------------------
    def drive(self, value_c: float) -> tuple[float, float]:
        """Write ``value_c`` (rounded), read back the set point and the air; ``SetpointOverridden`` if the
        read-back differs by more than half the resolution.  Returns (set point, air)."""
        written_c = round_to_resolution(value_c, self.controller.resolution_c)
        self.controller.write_setpoint_c(written_c)
        self.last_written_c = written_c
        setpoint_c = self.controller.read_setpoint_c()
        air_c = self.controller.read_air_c()
        if abs(setpoint_c - written_c) > self.controller.resolution_c / 2 + 1e-9:
            self.row("stopped", None, setpoint_c, air_c, written_c, None)
            raise SetpointOverridden(
                f"the chamber's set point reads {setpoint_c:g} degC where {written_c:g} was written: someone else "
                "drives it; stopped, nothing more written"
            )
        return setpoint_c, air_c

    def wait_until(self, due_s: float, *, stoppable: bool = True) -> None:
        delay_s = due_s - self.clock.monotonic()
        if stoppable:
            if self.clock.wait(self.stop, delay_s) or self.stop.is_set():
                raise _Stopped
        elif delay_s > 0:
            self.clock.wait(threading.Event(), delay_s)

    def reconnect(self, stoppable: bool = True) -> None:
        """After a lost link: ``link_lost`` rows, one a connection attempt with backoff, until ``connect`` works."""
        self.controller.close()
        backoff_s = self.options.reconnect_first_s
        while True:
            self.wait_until(self.clock.monotonic() + backoff_s, stoppable=stoppable)
            try:
                self.controller.connect()
                return
            except ControllerUnreachable:
                self.row("link_lost", self.paused_t_s, None, None, None, None)
                backoff_s = min(2 * backoff_s, self.options.reconnect_max_s)

    def gyro_silent(self) -> bool:
        if self.gyro is None:
            return False
        since_s = self.gyro.seconds_since_frame()
        return since_s is None or since_s > self.options.pause_after_s

    # --- the phases ---------------------------------------------------------------------------------
    def settle(self, target_c: float) -> None:
        """Hold ``target_c`` until a step reads the air within the tolerance (rows ``settling``)."""
        try:
            air_c = self.controller.read_air_c()
        except ControllerUnreachable:
            self.reconnect()
            air_c = math.inf
        if abs(air_c - target_c) <= self.options.settle_tolerance_c:
            return
        step_s = self.options.step_s
        anchor_s, k = self.clock.monotonic(), 0
        while True:
            self.wait_until(anchor_s + k * step_s)
            try:
                setpoint_c, air_c = self.drive(target_c)
            except ControllerUnreachable:
                self.reconnect()
                anchor_s, k = self.clock.monotonic(), 0
                continue
            self.row(
                "settling", None, setpoint_c, air_c, round_to_resolution(target_c, self.controller.resolution_c), None
            )
            if abs(air_c - target_c) <= self.options.settle_tolerance_c:
                self.wait_until(anchor_s + (k + 1) * step_s)
                return
            k += 1

    def run(self, start_t_s: float) -> float:
        """Step the program from ``start_t_s`` to its end; returns the program time reached (``_Stopped`` on a stop)."""
        step_s, end_s = self.options.step_s, self.program.duration_s
        anchor_s, anchor_t_s, k = self.clock.monotonic(), start_t_s, 0
        self.paused_t_s = start_t_s
        on_time = True  # the step at k is on the schedule (its lateness counts)
        while True:
            due_s = anchor_s + k * step_s
            self.wait_until(due_s)
            now_s = self.clock.monotonic()
            if now_s - due_s >= step_s:  # later than a whole step: skip to the last step due
                k += int((now_s - due_s) // step_s)
                due_s = anchor_s + k * step_s
            t_s = min(anchor_t_s + k * step_s, end_s)
            self.paused_t_s = t_s
            holding = self.gyro_silent()
            value_c = self.program_c(t_s)
            try:
                setpoint_c, air_c = self.drive(value_c)
            except ControllerUnreachable:
                self.row("link_lost", t_s, None, None, None, None)
                self.reconnect()
                anchor_s, anchor_t_s, k, on_time = self.clock.monotonic(), t_s, 0, False
                continue
            if on_time:
                self.lateness_s.append(max(0.0, now_s - due_s))
            on_time = True
            written_c = round_to_resolution(value_c, self.controller.resolution_c)
            self.row("holding" if holding else "running", t_s, setpoint_c, air_c, written_c, self.segment_at(t_s))
            if holding:  # the program's clock paused: the next step (due on schedule) writes this program time again
                anchor_s, anchor_t_s, k = due_s + step_s, t_s, 0
                continue
            if t_s >= end_s:
                return t_s
            k += 1

    def goto(self, target_c: float, t_s: float) -> None:
        """Ramp from the last set point to ``target_c`` at the program's slowest ramp rate, then hold it."""
        rate_c_per_s = slowest_ramp_c_per_min(self.program) / 60.0
        from_c = self.last_written_c if self.last_written_c is not None else self.program_c(t_s)
        duration_s = abs(target_c - from_c) / rate_c_per_s
        step_s = self.options.step_s
        anchor_s, elapsed_s, k = self.clock.monotonic(), 0.0, 0
        while True:
            self.wait_until(anchor_s + k * step_s, stoppable=False)
            ramp_s = min(elapsed_s + k * step_s, duration_s)
            value_c = (
                target_c if ramp_s >= duration_s else from_c + math.copysign(rate_c_per_s * ramp_s, target_c - from_c)
            )
            try:
                setpoint_c, air_c = self.drive(value_c)
            except ControllerUnreachable:
                self.row("link_lost", t_s, None, None, None, None)
                self.reconnect(stoppable=False)
                anchor_s, elapsed_s, k = self.clock.monotonic(), ramp_s, 0
                continue
            written_c = round_to_resolution(value_c, self.controller.resolution_c)
            self.row("stopped", t_s, setpoint_c, air_c, written_c, None)
            if ramp_s >= duration_s:
                return
            k += 1

    def finish(self, status: str, t_s: float) -> None:
        on_stop = self.options.on_stop
        while on_stop.kind == "standby":
            try:
                self.controller.safe_stop()
                break
            except ControllerUnreachable:  # standby is the safe state: reach it once the link is back
                self.row("link_lost", t_s, None, None, None, None)
                self.reconnect(stoppable=False)
        if on_stop.kind == "goto":
            assert on_stop.target_c is not None
            self.goto(on_stop.target_c, t_s)
        try:
            setpoint_c: float | None = self.controller.read_setpoint_c()
            air_c: float | None = self.controller.read_air_c()
        except ControllerUnreachable:
            setpoint_c = air_c = None
        self.row(status, t_s, setpoint_c, air_c, None, None)


def run_program(
    controller: ChamberController,
    program: ChamberProfile,
    log: ChamberLogWriter,
    *,
    options: RunOptions,
    clock: Clock,
    stop: threading.Event,
    gyro: GyroFeed | None = None,
    resume_t_s: float | None = None,
    on_row: Callable[[LogRow], None] | None = None,
) -> RunResult:
    """Run ``program`` on a connected ``controller`` as the module docstring says, a row a step into ``log``.

    Raises ``ProgramOutOfRange`` (nothing written), ``SetpointOverridden``, ``ControllerRefused`` and
    ``ControllerProtocolError`` (nothing more written); ``ControllerUnreachable`` only before the range is read."""
    run = _Run(controller, program, log, options, clock, stop, gyro, on_row)
    check_range(program, controller.read_range_c(), options.on_stop)
    start_t_s = 0.0 if resume_t_s is None else min(max(0.0, resume_t_s), program.duration_s)
    t_s = start_t_s
    status = "done"
    try:
        try:
            run.settle(run.program_c(start_t_s))
            t_s = run.run(start_t_s)
        except _Stopped:
            status = "interrupted"
            t_s = run.paused_t_s if run.paused_t_s is not None else start_t_s
        run.finish(status, t_s)
    except (ControllerRefused, ControllerProtocolError):
        run.row("stopped", run.paused_t_s, None, None, None, None)
        raise
    return RunResult(status, t_s, run.rows, run.lateness_s)
