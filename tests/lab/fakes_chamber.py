"""An in-memory chamber for the runner's tests, on a fake clock: no sleeps, a wait advances time.

``FakeClock.wait`` moves its time on by the timeout (or to a scheduled stop); ``FakeChamber``'s air follows its
set point at ``rate_c_per_s`` on that clock's time, and it misbehaves on demand: link-loss windows (every call
inside one raises ``ControllerUnreachable``), refused writes, a set point someone else overrides, an exception
answer, a slow write (the clock moved on inside it).
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta

from fog_driver.lab.controllers.base import (
    ChamberRange,
    ChamberStatus,
    ControllerProtocolError,
    ControllerRefused,
    ControllerUnreachable,
)

EPOCH = datetime(2026, 12, 7, 12, 0, 0, tzinfo=UTC)


class FakeClock:
    """Monotonic time from 0; ``wait`` advances it (to ``stop_at_s`` at most, where it sets the stop event)."""

    def __init__(self) -> None:
        self.now_s = 0.0
        self.stop_at_s: float | None = None
        self.waits = 0

    def monotonic(self) -> float:
        return self.now_s

    def utc_now(self) -> datetime:
        return EPOCH + timedelta(seconds=self.now_s)

    def advance(self, seconds: float) -> None:
        self.now_s += max(0.0, seconds)

    def wait(self, stop: threading.Event, timeout_s: float) -> bool:
        self.waits += 1
        if stop.is_set():
            return True
        target_s = self.now_s + max(0.0, timeout_s)
        if self.stop_at_s is not None and target_s >= self.stop_at_s:
            self.now_s = max(self.now_s, self.stop_at_s)
            stop.set()
            return True
        self.now_s = target_s
        return False


@dataclass
class FakeChamber:
    """A ``ChamberController`` in memory, its air following the set point on ``clock``'s time."""

    clock: FakeClock
    air_c: float = 20.0
    setpoint_c: float = 20.0
    resolution_c: float = 0.1
    range_c: ChamberRange = field(default_factory=lambda: ChamberRange(-70.0, 180.0))
    rate_c_per_s: float = 1.0
    url: str = "fake://chamber"
    address: str = "fake:chamber"
    link_lost_windows: list[tuple[float, float]] = field(default_factory=list)
    refuse_writes: bool = False
    override_c: float | None = None  # someone else holds this set point
    exception_on_write: bool = False
    write_delay_s: float = 0.0  # the clock moves on inside each write
    writes: list[tuple[float, float]] = field(default_factory=list)  # (time, value)
    connects: list[float] = field(default_factory=list)  # times of connection attempts
    safe_stops: int = 0
    connected: bool = True
    _updated_s: float = 0.0

    def _follow(self) -> None:
        dt = self.clock.now_s - self._updated_s
        self._updated_s = self.clock.now_s
        gap = self.setpoint_c - self.air_c
        self.air_c += math.copysign(min(abs(gap), self.rate_c_per_s * dt), gap)

    def _link(self) -> None:
        now = self.clock.now_s
        if any(a <= now < b for a, b in self.link_lost_windows):
            self.connected = False
        if not self.connected:
            raise ControllerUnreachable(f"{self.url}: link lost")

    def connect(self) -> None:
        self.connects.append(self.clock.now_s)
        now = self.clock.now_s
        if any(a <= now < b for a, b in self.link_lost_windows):
            raise ControllerUnreachable(f"{self.url}: no connection")
        self.connected = True

    def close(self) -> None:
        self.connected = False

    def safe_stop(self) -> None:
        self._link()
        self.safe_stops += 1

    def read_air_c(self) -> float:
        self._link()
        self._follow()
        return self.air_c

    def read_setpoint_c(self) -> float:
        self._link()
        return self.setpoint_c if self.override_c is None else self.override_c

    def write_setpoint_c(self, setpoint_c: float) -> None:
        self._link()
        if self.refuse_writes:
            raise ControllerRefused(f"{self.url}: the controller is in local mode: remote writes refused")
        if self.exception_on_write:
            raise ControllerProtocolError(f"{self.url}: the controller answered exception 2 (illegal address)")
        self._follow()
        self.writes.append((self.clock.now_s, setpoint_c))
        self.setpoint_c = setpoint_c
        self.clock.advance(self.write_delay_s)

    def read_range_c(self) -> ChamberRange:
        self._link()
        return self.range_c

    def read_status(self) -> ChamberStatus:
        self._link()
        return ChamberStatus("constant")
