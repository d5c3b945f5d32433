"""A simulated thermal chamber: its air follows the set point through a rate limit and a first-order lag.

The rule, integrated exactly (closed form, not a numerical step):

- the *command* ``c(t)`` moves towards the set point at most ``rate_c_per_min`` (0: no limit, a step), and holds
  it once reached; so ``c`` is piecewise linear, with a knot at each set-point write and at each ramp's end;
- the air follows the command through a first-order lag ``tau_s``: ``dA/dt = (c - A) / tau``; on a piece
  ``c = c0 + s t``, ``A(t) = c(t) - s tau + (A0 - c0 + s tau) exp(-t / tau)`` (``tau_s`` 0: ``A = c``).

Time comes from ``now_s`` (a callable: a test's fake clock, or wall time times a speed factor); the chamber
advances to ``now_s()`` whenever it is asked (a write, a read), so its history is exact whatever the asking.
``air_c_at(t)`` evaluates that history at any past time; a time beyond the chamber's present holds the present
air (the chamber cannot know a set point not yet written).  Modes: ``constant`` (follows the set point),
``standby`` (the command goes to ``ambient_c`` at the same rate: the chamber is off), ``local`` (follows the
set point, but remote writes are refused: ``ControllerRefused``).  The range (default -70..180 degC) bounds the
set points accepted.  ``unit`` (C or F) is the unit the served protocols speak (the chamber works in degC).

``SimChamberController`` is the in-process ``ChamberController`` of ``sim://``, opened by ``open_sim_controller``
(options ``speed``, ``start_c``, ``rate_c_per_min``, ``tau_s``, ``low_c``, ``high_c``; chamber time = the host's
monotonic seconds since the open times ``speed``).
"""

from __future__ import annotations

import itertools
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..errors import UsageError
from ..lab.controllers.base import ChamberRange, ChamberStatus, ControllerRefused, Notice
from ..lab.controllers.url import ControllerURL

CHAMBER_MODES = ("constant", "standby", "local")
CHAMBER_UNITS = ("C", "F")
SIM_OPTIONS = "speed, start_c, rate_c_per_min, tau_s, low_c, high_c"


@dataclass(frozen=True)
class ChamberParams:
    """The simulated chamber's constants: start (and ambient) temperature, rate limit (degC/min, 0: none),
    lag (s, 0: none), range, unit and the mode it starts in."""

    start_c: float = 20.0
    rate_c_per_min: float = 3.0
    tau_s: float = 60.0
    low_c: float = -70.0
    high_c: float = 180.0
    unit: str = "C"
    mode: str = "constant"

    def __post_init__(self) -> None:
        if not (math.isfinite(self.rate_c_per_min) and self.rate_c_per_min >= 0):
            raise ValueError("rate_c_per_min must be finite and >= 0 (0: no limit)")
        if not (math.isfinite(self.tau_s) and self.tau_s >= 0):
            raise ValueError("tau_s must be finite and >= 0")
        if not (math.isfinite(self.low_c) and math.isfinite(self.high_c) and self.low_c < self.high_c):
            raise ValueError("low_c must be below high_c")
        if not (math.isfinite(self.start_c) and self.low_c <= self.start_c <= self.high_c):
            raise ValueError("start_c must lie in low_c..high_c")
        if self.unit not in CHAMBER_UNITS:
            raise ValueError(f"unit must be one of {', '.join(CHAMBER_UNITS)}")
        if self.mode not in CHAMBER_MODES:
            raise ValueError(f"mode must be one of {', '.join(CHAMBER_MODES)}")


class SimChamber:
    """The chamber's state and its exact history (knots of the piecewise-linear command), thread-safe."""

    def __init__(self, now_s: Callable[[], float], params: ChamberParams | None = None) -> None:
        self.params = params if params is not None else ChamberParams()
        self.now_s = now_s
        self.mode = self.params.mode
        self.alarms: tuple[str, ...] = ()
        self._lock = threading.Lock()
        p = self.params
        self._setpoint_c = p.start_c
        t0 = float(now_s())
        # knots: time, command, air, command slope (degC/s) on [t_k, t_k+1)
        self._t = [t0]
        self._c = [p.start_c]
        self._a = [p.start_c]
        self._s = [0.0]
        self._arrays: tuple[np.ndarray, ...] | None = None
        self._t_now = t0

    # -- the closed form ---------------------------------------------------------------------------------------
    def _air_after(self, k: int, dt: np.ndarray | float) -> np.ndarray | float:
        tau = self.params.tau_s
        c0, a0, s = self._c[k], self._a[k], self._s[k]
        if tau == 0:
            return c0 + s * dt
        return c0 + s * dt - s * tau + (a0 - c0 + s * tau) * np.exp(-np.asarray(dt) / tau)

    def _target_c(self) -> float:
        return self.params.start_c if self.mode == "standby" else self._setpoint_c

    def _knot(self, t: float, slope: float) -> None:
        """A knot at ``t`` (not before the last one): the command's slope changes there; a knot at the last
        knot's time replaces its slope."""
        k = len(self._t) - 1
        dt = t - self._t[k]
        if dt <= 0:
            self._s[k] = slope
        else:
            self._t.append(t)
            self._c.append(self._c[k] + self._s[k] * dt)
            self._a.append(float(self._air_after(k, dt)))
            self._s.append(slope)
        self._arrays = None

    def _slope_to(self, command_c: float, target_c: float) -> float:
        rate = self.params.rate_c_per_min / 60.0
        if command_c == target_c:
            return 0.0
        if rate == 0:
            return math.inf  # a step: handled by the caller
        return math.copysign(rate, target_c - command_c)

    def _advance(self, t: float) -> None:
        """Move the present to ``t`` (not backwards), adding a knot where a ramp ends."""
        t = max(t, self._t_now)
        k = len(self._t) - 1
        s = self._s[k]
        if s != 0:
            target = self._target_c()
            t_end = self._t[k] + (target - self._c[k]) / s
            if t_end <= t:
                self._knot(t_end, 0.0)
                self._c[-1] = target
        self._t_now = t

    def _retarget(self) -> None:
        """A knot now, with the command's new slope towards the target (a step when there is no rate limit)."""
        t = self._t_now
        k = len(self._t) - 1
        command = self._c[k] + self._s[k] * (t - self._t[k])
        slope = self._slope_to(command, self._target_c())
        if math.isinf(slope):
            self._knot(t, 0.0)
            self._c[-1] = self._target_c()
        else:
            self._knot(t, slope)

    # -- the chamber's face ------------------------------------------------------------------------------------
    def air_c(self) -> float:
        """The air now."""
        with self._lock:
            self._advance(float(self.now_s()))
            return float(self._air_after(len(self._t) - 1, self._t_now - self._t[-1]))

    def air_c_at(self, t_s: np.ndarray) -> np.ndarray:
        """The air at times ``t_s`` (chamber time); a time beyond the present holds the present air."""
        with self._lock:
            self._advance(float(self.now_s()))
            if self._arrays is None:
                self._arrays = (np.array(self._t), np.array(self._c), np.array(self._a), np.array(self._s))
            t_k, c_k, a_k, s_k = self._arrays
            t = np.minimum(np.asarray(t_s, dtype=float), self._t_now)
            k = np.clip(np.searchsorted(t_k, t, side="right") - 1, 0, len(t_k) - 1)
            dt = np.maximum(t - t_k[k], 0.0)
            c0, a0, s = c_k[k], a_k[k], s_k[k]
            tau = self.params.tau_s
            if tau == 0:
                return c0 + s * dt
            return c0 + s * dt - s * tau + (a0 - c0 + s * tau) * np.exp(-dt / tau)

    def setpoint_c(self) -> float:
        with self._lock:
            return self._setpoint_c

    def write_setpoint_c(self, setpoint_c: float, *, remote: bool = True) -> None:
        """Set the set point (``ValueError`` outside the range; ``ControllerRefused`` for a remote write in
        local mode)."""
        if remote and self.mode == "local":
            raise ControllerRefused("the chamber is in local mode: remote writes refused")
        if not (math.isfinite(setpoint_c) and self.params.low_c <= setpoint_c <= self.params.high_c):
            raise ValueError(f"set point {setpoint_c:g} degC outside {self.params.low_c:g}..{self.params.high_c:g}")
        with self._lock:
            self._advance(float(self.now_s()))
            self._setpoint_c = float(setpoint_c)
            self._retarget()

    def set_mode(self, mode: str) -> None:
        if mode not in CHAMBER_MODES:
            raise ValueError(f"mode must be one of {', '.join(CHAMBER_MODES)}")
        with self._lock:
            self._advance(float(self.now_s()))
            self.mode = mode
            self._retarget()

    def range_c(self) -> ChamberRange:
        return ChamberRange(self.params.low_c, self.params.high_c)

    def status(self) -> ChamberStatus:
        if self.alarms:
            return ChamberStatus("alarm", self.alarms)
        return ChamberStatus(self.mode)


_ids = itertools.count(1)


class SimChamberController:
    """``ChamberController`` over a ``SimChamber`` in-process (``sim://``); degC, resolution 0.01 degC."""

    resolution_c = 0.01

    def __init__(self, chamber: SimChamber, url: str = "sim://") -> None:
        self.chamber = chamber
        self.url = url
        self.address = f"sim:{id(chamber):x}:{next(_ids)}"  # each in-process chamber is its own
        self.connected = False

    def connect(self) -> None:
        self.connected = True

    def close(self) -> None:
        self.connected = False

    def safe_stop(self) -> None:
        self.chamber.set_mode("standby")

    def read_air_c(self) -> float:
        return self.chamber.air_c()

    def read_setpoint_c(self) -> float:
        return self.chamber.setpoint_c()

    def write_setpoint_c(self, setpoint_c: float) -> None:
        value = round(setpoint_c / self.resolution_c) * self.resolution_c
        try:
            self.chamber.write_setpoint_c(value)
        except ValueError as exc:
            raise ControllerRefused(f"sim chamber: {exc}") from None

    def read_range_c(self) -> ChamberRange:
        return self.chamber.range_c()

    def read_status(self) -> ChamberStatus:
        return self.chamber.status()


def sim_params_from_url(url: ControllerURL, overrides: dict | None = None) -> tuple[ChamberParams, float]:
    """``(params, speed)`` from a URL's options (over ``overrides``); ``UsageError`` on an unknown or bad one."""
    base = dict(overrides or {})

    def opt(name: str, default: float) -> float:
        return url.take(name, _finite, float(base.get(name, default)))

    speed = opt("speed", 1.0)
    d = ChamberParams()
    values = {
        "start_c": opt("start_c", d.start_c),
        "rate_c_per_min": opt("rate_c_per_min", d.rate_c_per_min),
        "tau_s": opt("tau_s", d.tau_s),
        "low_c": opt("low_c", d.low_c),
        "high_c": opt("high_c", d.high_c),
    }
    url.refuse_unknown(SIM_OPTIONS)

    if speed <= 0:
        raise UsageError(f"controller URL {url.text}: speed must be > 0")
    try:
        return ChamberParams(**values), speed  # type: ignore[arg-type]
    except ValueError as exc:
        raise UsageError(f"controller URL {url.text}: {exc}") from None


def _finite(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise ValueError("not a finite number")
    return value


def open_sim_controller(
    url: ControllerURL, *, overrides: dict, on_notice: Notice, timeout_s: float
) -> SimChamberController:
    """``sim://?speed=60&start_c=20&rate_c_per_min=3&tau_s=60&low_c=-70&high_c=180``: a fresh simulated chamber
    whose time is the host's monotonic seconds since this call times ``speed``."""
    params, speed = sim_params_from_url(url, overrides)
    t0 = time.monotonic()
    chamber = SimChamber(lambda: (time.monotonic() - t0) * speed, params)
    return SimChamberController(chamber, url.text)


class ChamberAir:
    """An air source for the instrument (``SimProfile.chamber``'s place): the air of a ``SimChamber`` at the
    instrument's true time, the chamber's clock being the instrument's device time.  A time the chamber has not
    reached yet holds its present air (``SimChamber.air_c_at``); the instrument computes its slow grid a few
    seconds ahead at most in a coupled run (``COUPLED_BLOCK_STEPS``), so its air lags the chamber's by at most
    that."""

    def __init__(self, chamber: SimChamber, duration_s: float) -> None:
        self.chamber = chamber
        self.duration_s = duration_s

    def air_temp_c(self, t_s: np.ndarray) -> np.ndarray:
        return self.chamber.air_c_at(np.asarray(t_s, dtype=float))


#: The instrument's slow-grid block in a coupled run, s (its air is at most this far behind the chamber's).
COUPLED_BLOCK_STEPS = 2


class StartedClock:
    """Chamber time for a coupled run: 0 until ``start()``, then the host's monotonic seconds since times
    ``speed`` (the instrument's device time, which starts when its stream does)."""

    def __init__(self, speed: float) -> None:
        self.speed = speed
        self._t0: float | None = None

    def start(self) -> None:
        self._t0 = time.monotonic()

    def __call__(self) -> float:
        return 0.0 if self._t0 is None else (time.monotonic() - self._t0) * self.speed
