"""Chamber temperature profiles and turntable motion plans: what one chamber run does to the instrument.

A ``SimProfile`` is the chamber's air temperature over time (``ChamberProfile.air_temp_c(t_s)``) and
the turntable's rotation about the instrument's sensitive axis (``MotionPlan.rate_dps(t_s)``,
``MotionPlan.angle_deg(t_s)``).  Both are exact closed forms, vectorized over numpy arrays with one
``np.searchsorted`` over the segment boundaries (the simulator evaluates millions of frame times at
once).  Times are seconds from the start of the run.

Chamber segments, applied in order from ``start_c``; T0 is the temperature when a segment starts and
t the time since it started::

    Hold(duration_s)                           T = T0                                for duration_s
    Ramp(rate_c_per_min, target_c)             T = T0 + sign(target - T0) rate/60 t  for |target - T0| / rate * 60 s
    Step(target_c)                             T = target_c from the step on         (zero duration)
    Sinusoid(amplitude_c, period_s, duration_s) T = T0 + A sin(2 pi t / P)            for duration_s

A ramp ends exactly at its target; a step is instantaneous (the instrument's thermal model smooths
it) and at the step instant the value is already the new one; a sinusoid oscillates around the
temperature it starts from, and the next segment starts from the value it ends at,
T0 + A sin(2 pi D / P), which is T0 only when D is a whole number of periods.  Before t = 0 the air
is at ``start_c``; after the end it stays at the last value.

Turntable motion (the sensitive axis is parallel to the table axis); theta is the cumulative
commanded table angle, 0 before the first move::

    static          omega = 0
    constant_rate   omega = rate_dps for start_s <= t < stop_s (stop_s None: for ever); the rate
                    steps instantly, the angle stays continuous
    positioning     dwell_s, then ``moves`` times (move of step_deg, dwell_s).  Each move is a
                    trapezoid in omega with acceleration a and top rate v:
                        t_a = v / a,  t_c = (|d| - v^2 / a) / v,  T = 2 t_a + t_c
                    or a triangle when |d| < v^2 / a (the top rate is never reached):
                        peak = sqrt(a |d|),  t_a = sqrt(|d| / a),  t_c = 0,  T = 2 t_a

so theta(t) = theta_k + omega_k (t - t_k) + alpha_k (t - t_k)^2 / 2 on each piece k (piecewise
quadratic), exactly the integral of omega: a frame's true angle increment is
``angle_deg(t1) - angle_deg(t0)`` with no discretisation error.  During every dwell the angle is
exactly ``base + k * step_deg``.  With the defaults (36 deg, 20 deg/s, 10 deg/s^2) a move is
triangular: 36 < 20^2 / 10 = 40 deg, peak 18.97 deg/s, 3.795 s per move, and a 10-move sequence
lasts 60 + 10 * (3.795 + 60) = 697.9 s.

Built-in profiles (``load_profile("paper")``, ``load_profile("paper-validation")``):

- ``paper``: the paper's 440-minute chamber experiment.  20 degC, 30 min warm-up; +1 degC/min to
  25, 30, ..., 55 degC with 15 min at each; back to 20 degC at 2 degC/min (the paper only says
  "quickly"; 2 degC/min is a realistic chamber cooling rate) and 12.5 min at 20 degC, which makes
  the total exactly 440 min; then -1 degC/min to 15, 10, ..., -40 degC with 15 min at each.
  Static table.  ``configs/profiles/paper.yaml`` is the same profile in the file format.
- ``paper-validation``: the paper's validation experiment.  20 degC, 30 min warm-up; down to -40 degC
  at 1 degC/min, then up through -30, -20, -10, 0, 10, 20, 25, 30, 40, 55 degC at 1 degC/min (one
  cool-down, then always warming, so the chamber never overshoots back and forth); 75 min at each
  temperature: 60 min to settle, then the 10 x 36 deg positioning sequence (697.9 s), and 202 s of
  margin before the next ramp.  1010 min in total.

YAML profile files (read with ``yaml.safe_load``; unknown keys are errors; indices in messages and
``at_plateau`` count from 0, as ``plateaus()`` does)::

    name: fast-ramps                  # optional, default the file's stem
    start_c: 20
    segments:
      - hold: {duration_min: 10}      # or duration_s, exactly one
      - ramp: {rate_c_per_min: 2.0, target_c: 40}
      - step: {target_c: 30}
      - sinusoid: {amplitude_c: 5, period_min: 30, duration_min: 60}
    motion:                           # optional, default static; a mapping or a list of them
      kind: positioning               # static | constant_rate | positioning
      at_plateau: 1                   # or start_s; settle_s (default 600) after the plateau starts
      moves: 10                       # step_deg 36, dwell_s 60, max_rate_dps 20, accel_dps2 10
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from ..errors import InputFileError
from ..files.yamlio import MAX_YAML_BYTES, read_yaml

__all__ = [
    "BUILTIN_PROFILES",
    "ChamberProfile",
    "ConstantRate",
    "Hold",
    "MAX_PROFILE_BYTES",
    "MAX_SEGMENTS",
    "MotionPlan",
    "Plateau",
    "Positioning",
    "Ramp",
    "Segment",
    "SegmentSpan",
    "SimProfile",
    "Sinusoid",
    "Step",
    "Stop",
    "dump_profile",
    "load_profile",
    "paper_profile",
    "paper_validation_profile",
    "parse_profile",
    "positioning_at_plateau",
    "profile_to_doc",
]

MAX_PROFILE_BYTES = MAX_YAML_BYTES
MAX_SEGMENTS = 10_000


def _number(name: str, value: Any, *, positive: bool = False, nonnegative: bool = False) -> float:
    """``value`` as a finite float, or ``ValueError`` naming ``name``."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ValueError(f"{name} must be a finite number, got {value!r}")
    if positive and value <= 0:
        raise ValueError(f"{name} must be positive, got {value!r}")
    if nonnegative and value < 0:
        raise ValueError(f"{name} must not be negative, got {value!r}")
    return float(value)


def _integer(name: str, value: Any, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return value


# --- chamber segments --------------------------------------------------------------------------


@dataclass(frozen=True)
class Hold:
    """T = T0 for ``duration_s``."""

    duration_s: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "duration_s", _number("duration_s", self.duration_s, positive=True))


@dataclass(frozen=True)
class Ramp:
    """T = T0 + sign(target_c - T0) * rate_c_per_min / 60 * t, until T reaches ``target_c``."""

    rate_c_per_min: float
    target_c: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "rate_c_per_min", _number("rate_c_per_min", self.rate_c_per_min, positive=True))
        object.__setattr__(self, "target_c", _number("target_c", self.target_c))


@dataclass(frozen=True)
class Step:
    """T jumps to ``target_c`` (zero duration)."""

    target_c: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "target_c", _number("target_c", self.target_c))


@dataclass(frozen=True)
class Sinusoid:
    """T = T0 + amplitude_c * sin(2 pi t / period_s) for ``duration_s``; the next segment starts from the end value."""

    amplitude_c: float
    period_s: float
    duration_s: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "amplitude_c", _number("amplitude_c", self.amplitude_c, nonnegative=True))
        object.__setattr__(self, "period_s", _number("period_s", self.period_s, positive=True))
        object.__setattr__(self, "duration_s", _number("duration_s", self.duration_s, positive=True))

    @property
    def whole_periods(self) -> bool:
        q = self.duration_s / self.period_s
        return q == round(q)

    def end_offset_c(self) -> float:
        """T(end) - T0: exactly 0 for a whole number of periods, else A sin(2 pi D / P)."""
        if self.whole_periods:
            return 0.0
        return self.amplitude_c * math.sin(2.0 * math.pi * self.duration_s / self.period_s)


Segment = Hold | Ramp | Step | Sinusoid
_SEGMENT_KINDS: dict[str, type] = {"hold": Hold, "ramp": Ramp, "step": Step, "sinusoid": Sinusoid}
_KIND_OF = {cls: kind for kind, cls in _SEGMENT_KINDS.items()}


@dataclass(frozen=True)
class Plateau:
    """A Hold segment: the air is at ``temp_c`` from ``t_start_s`` to ``t_end_s``."""

    t_start_s: float
    t_end_s: float
    temp_c: float


@dataclass(frozen=True)
class SegmentSpan:
    """Where a segment sits in a profile: its times and the temperatures it starts and ends at."""

    index: int
    segment: Segment
    t_start_s: float
    t_end_s: float
    start_c: float
    end_c: float

    @property
    def kind(self) -> str:
        return _KIND_OF[type(self.segment)]


@dataclass(frozen=True)
class ChamberProfile:
    """A chamber air-temperature program: ``start_c`` then ``segments`` in order (see the module docstring)."""

    name: str
    start_c: float
    segments: tuple[Segment, ...]
    _spans: tuple[SegmentSpan, ...] = field(init=False, repr=False, compare=False)
    _table: dict[str, np.ndarray] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "start_c", _number("start_c", self.start_c))
        segments = tuple(self.segments)
        object.__setattr__(self, "segments", segments)
        spans = []
        t_s, temp_c = 0.0, self.start_c
        for i, seg in enumerate(segments):
            if isinstance(seg, Hold):
                end_t, end_c = t_s + seg.duration_s, temp_c
            elif isinstance(seg, Ramp):
                end_t, end_c = t_s + abs(seg.target_c - temp_c) / seg.rate_c_per_min * 60.0, seg.target_c
            elif isinstance(seg, Step):
                end_t, end_c = t_s, seg.target_c
            elif isinstance(seg, Sinusoid):
                end_t, end_c = t_s + seg.duration_s, temp_c + seg.end_offset_c()
            else:
                raise TypeError(f"segments[{i}]: not a chamber segment: {seg!r}")
            spans.append(SegmentSpan(i, seg, t_s, end_t, temp_c, end_c))
            t_s, temp_c = end_t, end_c
        object.__setattr__(self, "_spans", tuple(spans))
        object.__setattr__(self, "_table", self._build_table())

    def _build_table(self) -> dict[str, np.ndarray]:
        # Piece 0 is "before t = 0" (constant start_c), pieces 1..n the segments, piece n+1 "after the
        # end" (constant last value).  Piece k >= 1 starts at starts[k - 1]; searchsorted(side="right")
        # picks the last piece starting at or before t, so a zero-length Step piece is never the
        # one evaluated, and at a step instant the value is the new one.
        n = len(self._spans)
        starts = np.array([s.t_start_s for s in self._spans] + [self.duration_s], dtype=np.float64)
        t0 = np.empty(n + 2)
        base = np.empty(n + 2)
        slope = np.zeros(n + 2)  # degC per s
        amp = np.zeros(n + 2)
        omega = np.zeros(n + 2)  # rad per s
        t0[0], base[0] = 0.0, self.start_c
        for k, span in enumerate(self._spans, start=1):
            t0[k], base[k] = span.t_start_s, span.start_c
            seg = span.segment
            if isinstance(seg, Ramp) and span.t_end_s > span.t_start_s:
                slope[k] = math.copysign(seg.rate_c_per_min / 60.0, seg.target_c - span.start_c)
            elif isinstance(seg, Sinusoid):
                amp[k], omega[k] = seg.amplitude_c, 2.0 * math.pi / seg.period_s
        t0[n + 1], base[n + 1] = self.duration_s, self.end_c
        return {
            "starts": starts,
            "t0": t0,
            "base": base,
            "slope": slope,
            "amp": amp,
            "omega": omega,
            "any_sin": np.array(bool(np.any(amp != 0))),
        }

    @property
    def duration_s(self) -> float:
        return self._spans[-1].t_end_s if self._spans else 0.0

    @property
    def end_c(self) -> float:
        return self._spans[-1].end_c if self._spans else self.start_c

    def air_temp_c(self, t_s: np.ndarray) -> np.ndarray:
        """The chamber air temperature at times ``t_s`` (any shape), exactly piecewise (see the module docstring)."""
        t = np.asarray(t_s, dtype=np.float64)
        flat = t.reshape(-1)
        tab = self._table
        k = np.searchsorted(tab["starts"], flat, side="right")
        dt = flat - tab["t0"][k]
        out = tab["base"][k] + tab["slope"][k] * dt
        if tab["any_sin"]:
            amp = tab["amp"][k]
            on = np.flatnonzero(amp)
            if len(on):
                out[on] = tab["base"][k[on]] + amp[on] * np.sin(tab["omega"][k[on]] * dt[on])
        return out.reshape(t.shape)

    def spans(self) -> list[SegmentSpan]:
        """Every segment with its start and end time and temperature."""
        return list(self._spans)

    def plateaus(self) -> list[Plateau]:
        """Each Hold segment, in order (``at_plateau: K`` refers to ``plateaus()[K]``)."""
        return [Plateau(s.t_start_s, s.t_end_s, s.start_c) for s in self._spans if isinstance(s.segment, Hold)]

    def step_times_s(self) -> list[float]:
        """The times of the Step segments whose target differs from the temperature before them."""
        return [s.t_start_s for s in self._spans if isinstance(s.segment, Step) and s.end_c != s.start_c]

    def segment_table(self) -> str:
        """A printable table: one line per segment with its times (min), temperatures and plateau index."""
        lines = [
            f"profile {self.name}: start {self.start_c:g} degC, {self.duration_s / 60:g} min",
            "    #  kind      start_min    end_min   from_c     to_c  detail",
        ]
        plateau = 0
        for s in self._spans:
            seg = s.segment
            if isinstance(seg, Hold):
                detail = f"plateau {plateau}"
                plateau += 1
            elif isinstance(seg, Ramp):
                detail = f"{seg.rate_c_per_min:g} degC/min"
            elif isinstance(seg, Sinusoid):
                detail = f"+-{seg.amplitude_c:g} degC, period {seg.period_s / 60:g} min"
            else:
                detail = "instantaneous"
            lines.append(
                f"{s.index:5d}  {s.kind:8s} {s.t_start_s / 60:10.2f} {s.t_end_s / 60:10.2f}"
                f" {s.start_c:8.2f} {s.end_c:8.2f}  {detail}"
            )
        return "\n".join(lines)


# --- turntable motion --------------------------------------------------------------------------


@dataclass(frozen=True)
class ConstantRate:
    """omega = ``rate_dps`` from ``start_s`` until ``stop_s`` (None: for ever)."""

    rate_dps: float
    start_s: float = 0.0
    stop_s: float | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "rate_dps", _number("rate_dps", self.rate_dps))
        object.__setattr__(self, "start_s", _number("start_s", self.start_s, nonnegative=True))
        if self.stop_s is not None:
            stop = _number("stop_s", self.stop_s)
            if stop <= self.start_s:
                raise ValueError(f"stop_s ({stop:g}) must be after start_s ({self.start_s:g})")
            object.__setattr__(self, "stop_s", stop)

    @property
    def end_s(self) -> float:
        return math.inf if self.stop_s is None else self.stop_s


@dataclass(frozen=True)
class Positioning:
    """From ``start_s``: dwell, then ``moves`` x (move of ``step_deg``, dwell); trapezoidal or triangular moves."""

    start_s: float
    moves: int = 10
    step_deg: float = 36.0
    dwell_s: float = 60.0
    max_rate_dps: float = 20.0
    accel_dps2: float = 10.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "start_s", _number("start_s", self.start_s, nonnegative=True))
        object.__setattr__(self, "moves", _integer("moves", self.moves, 1))
        step = _number("step_deg", self.step_deg)
        if step == 0:
            raise ValueError("step_deg must not be 0")
        object.__setattr__(self, "step_deg", step)
        object.__setattr__(self, "dwell_s", _number("dwell_s", self.dwell_s, positive=True))
        object.__setattr__(self, "max_rate_dps", _number("max_rate_dps", self.max_rate_dps, positive=True))
        object.__setattr__(self, "accel_dps2", _number("accel_dps2", self.accel_dps2, positive=True))

    @property
    def triangular(self) -> bool:
        """True when a move is too short to reach ``max_rate_dps``: |step| < v^2 / a."""
        return abs(self.step_deg) < self.max_rate_dps**2 / self.accel_dps2

    @property
    def peak_rate_dps(self) -> float:
        """The highest |omega| in a move: v, or sqrt(a |d|) for a triangular move."""
        return math.sqrt(self.accel_dps2 * abs(self.step_deg)) if self.triangular else self.max_rate_dps

    @property
    def accel_time_s(self) -> float:
        return self.peak_rate_dps / self.accel_dps2

    @property
    def cruise_time_s(self) -> float:
        if self.triangular:
            return 0.0
        return (abs(self.step_deg) - self.max_rate_dps**2 / self.accel_dps2) / self.max_rate_dps

    @property
    def move_time_s(self) -> float:
        return 2.0 * self.accel_time_s + self.cruise_time_s

    @property
    def duration_s(self) -> float:
        """dwell + moves * (move + dwell)."""
        return self.dwell_s + self.moves * (self.move_time_s + self.dwell_s)

    @property
    def end_s(self) -> float:
        return self.start_s + self.duration_s

    def move_start_s(self, k: int) -> float:
        """When move k (0-based) starts: start + dwell + k (move + dwell)."""
        return self.start_s + self.dwell_s + k * (self.move_time_s + self.dwell_s)


MotionItem = ConstantRate | Positioning


@dataclass(frozen=True)
class Stop:
    """A dwell of a positioning sequence: the table is still from ``t_start_s`` to ``t_end_s`` at ``angle_deg``."""

    t_start_s: float
    t_end_s: float
    angle_deg: float


@dataclass(frozen=True)
class MotionPlan:
    """The turntable's motion: non-overlapping items in time order; the table is still between them."""

    items: tuple[MotionItem, ...] = ()
    _pieces: dict[str, np.ndarray] = field(init=False, repr=False, compare=False)
    _stops: tuple[Stop, ...] = field(init=False, repr=False, compare=False)

    @classmethod
    def static(cls) -> MotionPlan:
        return cls(())

    def __post_init__(self) -> None:
        items = tuple(sorted(self.items, key=lambda it: it.start_s))
        for item in items:
            if not isinstance(item, (ConstantRate, Positioning)):
                raise TypeError(f"not a motion item: {item!r}")
        for a, b in zip(items, items[1:]):
            if b.start_s < a.end_s:
                raise ValueError(
                    f"{_describe_item(b)} overlaps {_describe_item(a)}, which ends at "
                    f"{'infinity' if math.isinf(a.end_s) else f'{a.end_s:g} s'}"
                )
        object.__setattr__(self, "items", items)
        self._build()

    def _build(self) -> None:
        # Pieces (t_k, theta_k, omega_k, alpha_k).  Piece 0 is the rest before the first item; piece
        # k >= 1 starts at starts[k - 1].  Dwell pieces carry the commanded angle exactly.
        pieces: list[tuple[float, float, float, float]] = [(0.0, 0.0, 0.0, 0.0)]
        stops: list[Stop] = []
        angle = 0.0

        def piece(t: float, theta: float, omega: float, alpha: float) -> None:
            pieces.append((t, theta, omega, alpha))

        for item in self.items:
            if isinstance(item, ConstantRate):
                piece(item.start_s, angle, item.rate_dps, 0.0)
                if item.stop_s is not None:
                    angle = angle + item.rate_dps * (item.stop_s - item.start_s)
                    piece(item.stop_s, angle, 0.0, 0.0)
                continue
            sign = math.copysign(1.0, item.step_deg)
            a, peak = item.accel_dps2, item.peak_rate_dps
            t_a, t_c, t_m = item.accel_time_s, item.cruise_time_s, item.move_time_s
            half = 0.5 * a * t_a * t_a  # angle covered while accelerating (and while decelerating)
            base = angle
            piece(item.start_s, base, 0.0, 0.0)
            stops.append(Stop(item.start_s, item.move_start_s(0), base))
            for k in range(item.moves):
                t0 = item.move_start_s(k)
                start_deg, end_deg = base + k * item.step_deg, base + (k + 1) * item.step_deg
                piece(t0, start_deg, 0.0, sign * a)
                if t_c > 0:
                    piece(t0 + t_a, start_deg + sign * half, sign * peak, 0.0)
                piece(t0 + t_a + t_c, end_deg - sign * half, sign * peak, -sign * a)
                dwell_end = item.move_start_s(k + 1) if k + 1 < item.moves else item.end_s
                piece(t0 + t_m, end_deg, 0.0, 0.0)
                stops.append(Stop(t0 + t_m, dwell_end, end_deg))
            angle = base + item.moves * item.step_deg
        t0, theta, omega, alpha = (np.array(column, dtype=np.float64) for column in zip(*pieces))
        object.__setattr__(
            self, "_pieces", {"starts": t0[1:], "t0": t0, "theta": theta, "omega": omega, "alpha": alpha}
        )
        object.__setattr__(self, "_stops", tuple(stops))

    @property
    def kind(self) -> str:
        """``static``, ``constant_rate``, ``positioning``, or ``mixed``."""
        kinds = {"constant_rate" if isinstance(it, ConstantRate) else "positioning" for it in self.items}
        return "static" if not kinds else kinds.pop() if len(kinds) == 1 else "mixed"

    @property
    def duration_s(self) -> float:
        """When the last item ends (its last dwell included; 0 for a static plan).

        An open-ended constant rate counts as ending when it starts: from then on the rate stays
        ``final_rate_dps`` for ever, so the duration stays finite.
        """
        ends = [it.end_s for it in self.items if math.isfinite(it.end_s)] + [it.start_s for it in self.items]
        return max(ends, default=0.0)

    @property
    def final_rate_dps(self) -> float:
        """The rate for ever after ``duration_s``: nonzero only when the plan ends with an open-ended constant rate."""
        return float(self._pieces["omega"][-1])

    def _lookup(self, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t = np.asarray(t_s, dtype=np.float64)
        k = np.searchsorted(self._pieces["starts"], t, side="right")
        return k, t - self._pieces["t0"][k]

    def rate_dps(self, t_s: np.ndarray) -> np.ndarray:
        """The table rate omega(t) in deg/s at times ``t_s`` (any shape): omega_k + alpha_k (t - t_k)."""
        k, dt = self._lookup(t_s)
        return self._pieces["omega"][k] + self._pieces["alpha"][k] * dt

    def angle_deg(self, t_s: np.ndarray) -> np.ndarray:
        """The cumulative table angle theta(t) = theta_k + omega_k (t - t_k) + alpha_k (t - t_k)^2 / 2, exactly."""
        k, dt = self._lookup(t_s)
        p = self._pieces
        return p["theta"][k] + dt * (p["omega"][k] + 0.5 * p["alpha"][k] * dt)

    def stops(self) -> list[Stop]:
        """Every dwell of every positioning sequence, in time order, with its commanded cumulative angle."""
        return list(self._stops)

    def describe(self) -> str:
        return "static" if not self.items else "; ".join(_describe_item(it) for it in self.items)


def _describe_item(item: MotionItem) -> str:
    if isinstance(item, ConstantRate):
        stop = "on" if item.stop_s is None else f"to {item.stop_s:g} s"
        return f"constant rate {item.rate_dps:g} deg/s from {item.start_s:g} s {stop}"
    shape = "triangular" if item.triangular else "trapezoidal"
    return (
        f"positioning {item.moves} x {item.step_deg:g} deg from {item.start_s:g} s to {item.end_s:g} s"
        f" ({shape} moves of {item.move_time_s:.3f} s, dwell {item.dwell_s:g} s)"
    )


def positioning_at_plateau(
    chamber: ChamberProfile, plateau: int, settle_s: float = 600.0, **kwargs: Any
) -> Positioning:
    """A ``Positioning`` starting ``settle_s`` after ``chamber.plateaus()[plateau]`` begins; it must end within it.

    ``kwargs`` are the other ``Positioning`` fields (moves, step_deg, dwell_s, max_rate_dps, accel_dps2).
    """
    plateaus = chamber.plateaus()
    plateau = _integer("at_plateau", plateau, 0)
    if plateau >= len(plateaus):
        if not plateaus:
            raise ValueError(f"at_plateau {plateau} but the chamber profile has no hold segment")
        raise ValueError(
            f"at_plateau {plateau} but the chamber profile has {len(plateaus)} plateaus (0..{len(plateaus) - 1})"
        )
    settle_s = _number("settle_s", settle_s, nonnegative=True)
    p = plateaus[plateau]
    seq = Positioning(start_s=p.t_start_s + settle_s, **kwargs)
    if seq.end_s > p.t_end_s:
        raise ValueError(
            f"the sequence at plateau {plateau} ({p.temp_c:g} degC) would end at {seq.end_s:g} s, "
            f"after the plateau ends at {p.t_end_s:g} s "
            f"(it needs {settle_s + seq.duration_s:g} s of hold)"
        )
    return seq


# --- the whole profile -------------------------------------------------------------------------


@dataclass(frozen=True)
class SimProfile:
    """A chamber run: the air temperature program, the turntable motion, and where it came from."""

    name: str
    chamber: ChamberProfile
    motion: MotionPlan
    source: str

    @property
    def duration_s(self) -> float:
        """The longer of the chamber program and the motion plan."""
        return max(self.chamber.duration_s, self.motion.duration_s)


def _paper_chamber() -> ChamberProfile:
    segs: list[Segment] = [Hold(30 * 60.0)]
    for temp_c in range(25, 56, 5):
        segs += [Ramp(1.0, temp_c), Hold(15 * 60.0)]
    segs += [Ramp(2.0, 20.0), Hold(12.5 * 60.0)]  # "quickly" back to 20 degC: 17.5 + 12.5 = 30 min
    for temp_c in range(15, -41, -5):
        segs += [Ramp(1.0, temp_c), Hold(15 * 60.0)]
    return ChamberProfile("paper", 20.0, tuple(segs))


PAPER_VALIDATION_TEMPS_C = (-40, -30, -20, -10, 0, 10, 20, 25, 30, 40, 55)
VALIDATION_SETTLE_S = 3600.0
VALIDATION_HOLD_S = 75 * 60.0


def paper_profile() -> SimProfile:
    """The paper's 440-minute chamber experiment, static table (see the module docstring)."""
    return SimProfile("paper", _paper_chamber(), MotionPlan.static(), "built-in")


def paper_validation_profile() -> SimProfile:
    """The paper's validation run: 11 temperatures, 60 min settle + 10 x 36 deg positioning at each."""
    segs: list[Segment] = [Hold(30 * 60.0)]
    for temp_c in PAPER_VALIDATION_TEMPS_C:
        segs += [Ramp(1.0, temp_c), Hold(VALIDATION_HOLD_S)]
    chamber = ChamberProfile("paper-validation", 20.0, tuple(segs))
    motion = MotionPlan(
        tuple(
            positioning_at_plateau(chamber, k, VALIDATION_SETTLE_S) for k in range(1, len(PAPER_VALIDATION_TEMPS_C) + 1)
        )
    )
    return SimProfile("paper-validation", chamber, motion, "built-in")


BUILTIN_PROFILES = {"paper": paper_profile, "paper-validation": paper_validation_profile}


# --- YAML ----------------------------------------------------------------------------------------

_SEGMENT_KEYS = {
    "hold": ({"duration_min", "duration_s"}, set()),
    "ramp": ({"rate_c_per_min", "target_c"}, {"rate_c_per_min", "target_c"}),
    "step": ({"target_c"}, {"target_c"}),
    "sinusoid": ({"amplitude_c", "period_min", "period_s", "duration_min", "duration_s"}, {"amplitude_c"}),
}
_MOTION_KEYS = {
    "static": (set(), set()),
    "constant_rate": ({"rate_dps", "start_s", "stop_s"}, {"rate_dps"}),
    "positioning": (
        {"start_s", "at_plateau", "settle_s", "moves", "step_deg", "dwell_s", "max_rate_dps", "accel_dps2"},
        set(),
    ),
}


class _Bad(Exception):
    """A problem at a place in the document; becomes ``InputFileError(f"{file}: {where}: {message}")``."""


def _at(where: str) -> str:
    return f"{where}: " if where else ""


def _check_keys(doc: Any, where: str, known: set[str], required: set[str]) -> dict:
    if not isinstance(doc, dict):
        got = "nothing" if doc is None else f"a {type(doc).__name__}"
        raise _Bad(f"{_at(where)}expected a mapping" + ("" if where else " with start_c and segments") + f", got {got}")
    for key in doc:
        if key not in known:
            raise _Bad(f"{_at(where)}unknown key {key!r} (known: {', '.join(sorted(known)) or 'none'})")
    for key in sorted(required):
        if key not in doc:
            raise _Bad(f"{_at(where)}missing {key}")
    return doc


def _field(where: str, name: str, value: Any, **checks: bool) -> float:
    try:
        return _number(name, value, **checks)
    except ValueError as exc:
        raise _Bad(f"{_at(where)}{exc}") from None


def _seconds(doc: dict, where: str, stem: str) -> float:
    given = [k for k in (f"{stem}_min", f"{stem}_s") if k in doc]
    if len(given) != 1:
        raise _Bad(f"{where}: give exactly one of {stem}_min and {stem}_s" + (", not both" if given else ""))
    key = given[0]
    value = _field(where, key, doc[key], positive=True)
    return value * 60.0 if key.endswith("_min") else value


def _parse_segment(item: Any, where: str) -> Segment:
    if not isinstance(item, dict) or len(item) != 1:
        raise _Bad(f"{where}: expected a one-key mapping like {{hold: {{duration_min: 10}}}}")
    ((kind, body),) = item.items()
    if kind not in _SEGMENT_KINDS:
        raise _Bad(f"{where}: unknown segment kind {kind!r} (known: {', '.join(_SEGMENT_KINDS)})")
    where = f"{where} ({kind})"
    known, required = _SEGMENT_KEYS[kind]
    body = _check_keys(body, where, known, required)
    if kind == "hold":
        return Hold(_seconds(body, where, "duration"))
    if kind == "ramp":
        return Ramp(
            _field(where, "rate_c_per_min", body["rate_c_per_min"], positive=True),
            _field(where, "target_c", body["target_c"]),
        )
    if kind == "step":
        return Step(_field(where, "target_c", body["target_c"]))
    return Sinusoid(
        _field(where, "amplitude_c", body["amplitude_c"], nonnegative=True),
        _seconds(body, where, "period"),
        _seconds(body, where, "duration"),
    )


def _parse_motion_item(doc: Any, where: str, chamber: ChamberProfile) -> MotionItem | None:
    if not isinstance(doc, dict):
        raise _Bad(f"{where}: expected a mapping with a kind (static, constant_rate, positioning)")
    if "kind" not in doc:
        raise _Bad(f"{where}: missing kind (static, constant_rate, positioning)")
    kind = doc["kind"]
    if kind not in _MOTION_KEYS:
        raise _Bad(f"{where}: unknown motion kind {kind!r} (known: {', '.join(_MOTION_KEYS)})")
    where = f"{where} ({kind})"
    known, required = _MOTION_KEYS[kind]
    body = {k: v for k, v in _check_keys(doc, where, known | {"kind"}, required).items() if k != "kind"}
    try:
        if kind == "static":
            return None
        if kind == "constant_rate":
            return ConstantRate(**body)
        if ("start_s" in body) == ("at_plateau" in body):
            raise _Bad(f"{where}: give exactly one of start_s and at_plateau")
        if "start_s" in body:
            if "settle_s" in body:
                raise _Bad(f"{where}: settle_s goes with at_plateau, not with start_s")
            return Positioning(**body)
        return positioning_at_plateau(chamber, body.pop("at_plateau"), body.pop("settle_s", 600.0), **body)
    except ValueError as exc:
        raise _Bad(f"{where}: {exc}") from None


def parse_profile(doc: Any, where: str = "profile", default_name: str = "profile") -> SimProfile:
    """Validate a parsed YAML document into a ``SimProfile``; every problem is a one-line ``InputFileError``."""
    try:
        doc = _check_keys(doc, "", {"name", "start_c", "segments", "motion"}, {"start_c", "segments"})
        name = doc.get("name", default_name)
        if not isinstance(name, str) or not name.strip() or "\n" in name:
            raise _Bad(f"name must be a one-line string, got {name!r}")
        start_c = _field("", "start_c", doc["start_c"])
        items = doc["segments"]
        if not isinstance(items, list) or not items:
            raise _Bad("segments must be a non-empty list")
        if len(items) > MAX_SEGMENTS:
            raise _Bad(f"segments: {len(items)} segments, more than the limit of {MAX_SEGMENTS}")
        segments = tuple(_parse_segment(item, f"segments[{i}]") for i, item in enumerate(items))
        chamber = ChamberProfile(name, start_c, segments)
        motion_doc = doc.get("motion")
        if motion_doc is None:
            motion = MotionPlan.static()
        else:
            entries = motion_doc if isinstance(motion_doc, list) else [motion_doc]
            wheres = [f"motion[{i}]" for i in range(len(entries))] if isinstance(motion_doc, list) else ["motion"]
            parsed = [_parse_motion_item(e, w, chamber) for e, w in zip(entries, wheres)]
            try:
                motion = MotionPlan(tuple(p for p in parsed if p is not None))
            except ValueError as exc:
                raise _Bad(f"motion: {exc}") from None
    except _Bad as exc:
        raise InputFileError(f"{where}: {exc}") from None
    return SimProfile(name, chamber, motion, where)


PROFILE_FOLDER = Path("configs") / "profiles"


def profile_folders() -> list[Path]:
    """Where profile names are looked up, in order: ``configs/profiles/`` in the current directory, then
    in the source tree this package runs from (a clone's editable install; absent from a wheel's)."""
    candidates = [Path.cwd() / PROFILE_FOLDER, Path(__file__).resolve().parents[2] / PROFILE_FOLDER]
    folders: list[Path] = []
    for folder in candidates:
        if folder.is_dir() and all(folder.resolve() != f.resolve() for f in folders):
            folders.append(folder)
    return folders


def profile_names() -> list[str]:
    """Every name ``load_profile`` accepts: the built-in profiles, then the profile files' stems."""
    names = list(BUILTIN_PROFILES)
    for folder in profile_folders():
        names += [f.stem for f in sorted(folder.glob("*.yaml")) if f.stem not in names]
    return names


def load_profile(name_or_path: str | Path) -> SimProfile:
    """A profile by name or a YAML profile file, validated.

    A name is a built-in profile (``paper``, ``paper-validation``) or the stem of a file in
    ``configs/profiles/`` (see :func:`profile_folders`): ``fast-ramps`` is ``configs/profiles/fast-ramps.yaml``.
    Anything with a ``/`` or a ``.yaml`` suffix is a path.
    """
    if isinstance(name_or_path, str) and name_or_path in BUILTIN_PROFILES:
        return BUILTIN_PROFILES[name_or_path]()
    path = Path(name_or_path)
    if (
        isinstance(name_or_path, str)
        and "/" not in name_or_path
        and path.suffix not in (".yaml", ".yml")
        and not path.is_file()
    ):
        for folder in profile_folders():
            if (folder / f"{name_or_path}.yaml").is_file():
                path = folder / f"{name_or_path}.yaml"
                break
        else:
            raise InputFileError(
                f"{name_or_path}: no such profile (profiles: {', '.join(profile_names())}; "
                "or give the path of a profile YAML file)"
            )
    doc = read_yaml(path, "profile file", hint=f" (profiles: {', '.join(profile_names())})")
    return parse_profile(doc, str(path), default_name=path.stem)


def _plain(x: float) -> float | int:
    return int(x) if float(x).is_integer() and abs(x) < 2**53 else float(x)


def _time_entry(stem: str, seconds: float) -> dict[str, float | int]:
    minutes = seconds / 60.0
    return {f"{stem}_min": _plain(minutes)} if minutes * 60.0 == seconds else {f"{stem}_s": _plain(seconds)}


def profile_to_doc(profile: SimProfile) -> dict[str, Any]:
    """The YAML document for ``profile`` (``parse_profile`` of it gives an equal chamber and motion)."""
    segments: list[dict[str, Any]] = []
    for seg in profile.chamber.segments:
        if isinstance(seg, Hold):
            body: dict[str, Any] = _time_entry("duration", seg.duration_s)
        elif isinstance(seg, Ramp):
            body = {"rate_c_per_min": _plain(seg.rate_c_per_min), "target_c": _plain(seg.target_c)}
        elif isinstance(seg, Step):
            body = {"target_c": _plain(seg.target_c)}
        else:
            body = {
                "amplitude_c": _plain(seg.amplitude_c),
                **_time_entry("period", seg.period_s),
                **_time_entry("duration", seg.duration_s),
            }
        segments.append({_KIND_OF[type(seg)]: body})
    doc: dict[str, Any] = {"name": profile.name, "start_c": _plain(profile.chamber.start_c), "segments": segments}
    items = []
    for item in profile.motion.items:
        if isinstance(item, ConstantRate):
            entry: dict[str, Any] = {
                "kind": "constant_rate",
                "rate_dps": _plain(item.rate_dps),
                "start_s": _plain(item.start_s),
            }
            if item.stop_s is not None:
                entry["stop_s"] = _plain(item.stop_s)
        else:
            entry = {
                "kind": "positioning",
                "start_s": _plain(item.start_s),
                "moves": item.moves,
                "step_deg": _plain(item.step_deg),
                "dwell_s": _plain(item.dwell_s),
                "max_rate_dps": _plain(item.max_rate_dps),
                "accel_dps2": _plain(item.accel_dps2),
            }
        items.append(entry)
    if items:
        doc["motion"] = items[0] if len(items) == 1 else items
    return doc


def dump_profile(profile: SimProfile) -> str:
    """``profile`` as YAML text in the profile-file format (positioning sequences with their resolved ``start_s``)."""
    return yaml.safe_dump(profile_to_doc(profile), sort_keys=False, default_flow_style=None)
