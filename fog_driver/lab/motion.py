"""The turntable's motion plan: its rotation about the instrument's sensitive axis over one run
(``MotionPlan.rate_dps(t_s)``, ``MotionPlan.angle_deg(t_s)``), exact closed forms vectorized over numpy arrays
with one ``np.searchsorted`` over the pieces' boundaries.  Times are seconds from the start of the run.

Turntable motion (the sensitive axis is parallel to the table axis); theta is the cumulative
commanded table angle, 0 before the first move::

    static          omega = 0
    constant_rate   omega = rate_dps for start_s <= t < stop_s (stop_s None: for ever); the rate
                    steps instantly, the angle stays continuous
    positioning     dwell_s, then ``moves`` times (move of step_deg, dwell_s); step_deg may be a list,
                    taken in turn (move k: step_deg[k % len]), each move shaped by its own size.  Each move is a
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
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np

from ..dwells import Dwell
from .checks import check_integer, check_number
from .program import ChamberProfile

# --- turntable motion --------------------------------------------------------------------------


#: A turntable's rate: at most this (deg/s), for every item; a positioning sequence has at most MAX_MOVES moves.
MAX_TABLE_RATE_DPS = 1000.0
MAX_MOVES = 10_000


def _check_table_rate(name: str, rate_dps: float, shown: float) -> None:
    if abs(rate_dps) > MAX_TABLE_RATE_DPS:
        raise ValueError(f"{name} {shown:g} is beyond a turntable's {MAX_TABLE_RATE_DPS:g} deg/s")


def _check_rate_span(item: Any, rate_name: str) -> None:
    """A rate item's fields checked in place: a finite rate a table can turn at, ``start_s`` >= 0, ``stop_s``
    (None: open) after it."""
    rate = check_number(rate_name, getattr(item, rate_name))
    _check_table_rate(rate_name, rate / 3600.0 if rate_name == "rate_dph" else rate, rate)
    object.__setattr__(item, rate_name, rate)
    object.__setattr__(item, "start_s", check_number("start_s", item.start_s, nonnegative=True))
    if item.stop_s is not None:
        stop = check_number("stop_s", item.stop_s)
        if stop <= item.start_s:
            raise ValueError(f"stop_s ({stop:g}) must be after start_s ({item.start_s:g})")
        object.__setattr__(item, "stop_s", stop)


@dataclass(frozen=True)
class ConstantRate:
    """omega = ``rate_dps`` from ``start_s`` until ``stop_s`` (None: for ever)."""

    rate_dps: float
    start_s: float = 0.0
    stop_s: float | None = None

    def __post_init__(self) -> None:
        _check_rate_span(self, "rate_dps")

    @property
    def end_s(self) -> float:
        return math.inf if self.stop_s is None else self.stop_s


@dataclass(frozen=True)
class MoveShape:
    """One move of ``step_deg`` at top rate v and acceleration a: a trapezoid in omega, or a triangle when
    |d| < v^2 / a (the top rate is never reached)."""

    step_deg: float
    peak_rate_dps: float  #: v, or sqrt(a |d|) for a triangular move
    accel_time_s: float  #: t_a = peak / a
    cruise_time_s: float  #: t_c = (|d| - v^2 / a) / v, 0 for a triangle
    triangular: bool

    @classmethod
    def of(cls, step_deg: float, max_rate_dps: float, accel_dps2: float) -> MoveShape:
        d = abs(step_deg)
        triangular = d < max_rate_dps**2 / accel_dps2
        peak = math.sqrt(accel_dps2 * d) if triangular else max_rate_dps
        cruise = 0.0 if triangular else (d - max_rate_dps**2 / accel_dps2) / max_rate_dps
        return cls(step_deg, peak, peak / accel_dps2, cruise, triangular)

    @property
    def move_time_s(self) -> float:
        """T = 2 t_a + t_c."""
        return 2.0 * self.accel_time_s + self.cruise_time_s


@dataclass(frozen=True)
class Positioning:
    """From ``start_s``: dwell, then ``moves`` x (move, dwell); trapezoidal or triangular moves.

    ``step_deg`` is one step for every move, or a list of steps (both signs, several sizes) taken in
    turn: move k steps ``step_deg[k % len(step_deg)]``, so a scale-factor error can be told from a
    drift over the dwells between them."""

    start_s: float
    moves: int = 10
    step_deg: float | tuple[float, ...] = 36.0
    dwell_s: float = 60.0
    max_rate_dps: float = 20.0
    accel_dps2: float = 10.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "start_s", check_number("start_s", self.start_s, nonnegative=True))
        object.__setattr__(self, "moves", check_integer("moves", self.moves, 1))
        if self.moves > MAX_MOVES or (isinstance(self.step_deg, (list, tuple)) and len(self.step_deg) > MAX_MOVES):
            raise ValueError(f"moves and the list of steps must not exceed {MAX_MOVES:,}")
        if isinstance(self.step_deg, (list, tuple)):
            if not self.step_deg:
                raise ValueError("step_deg must not be an empty list")
            steps = tuple(check_number("step_deg", v) for v in self.step_deg)
            step: float | tuple[float, ...] = steps[0] if len(steps) == 1 else steps
        else:
            step = check_number("step_deg", self.step_deg)
            steps = (step,)
        if any(v == 0 for v in steps):
            raise ValueError("step_deg must not be 0")
        object.__setattr__(self, "step_deg", step)
        object.__setattr__(self, "dwell_s", check_number("dwell_s", self.dwell_s, positive=True))
        object.__setattr__(self, "max_rate_dps", check_number("max_rate_dps", self.max_rate_dps, positive=True))
        _check_table_rate("max_rate_dps", self.max_rate_dps, self.max_rate_dps)
        object.__setattr__(self, "accel_dps2", check_number("accel_dps2", self.accel_dps2, positive=True))

    @cached_property
    def steps_deg(self) -> tuple[float, ...]:
        """Each move's step, in order (``moves`` of them; computed once: the sequence is frozen)."""
        cycle = self.step_deg if isinstance(self.step_deg, tuple) else (self.step_deg,)
        return tuple(cycle[k % len(cycle)] for k in range(self.moves))

    def shape(self, k: int) -> MoveShape:
        """Move k's shape (0-based)."""
        return self.shapes[k]

    @cached_property
    def shapes(self) -> tuple[MoveShape, ...]:
        """Each move's shape, in order (computed once: the sequence is frozen)."""
        cycle = self.step_deg if isinstance(self.step_deg, tuple) else (self.step_deg,)
        once = [MoveShape.of(v, self.max_rate_dps, self.accel_dps2) for v in cycle]
        return tuple(once[k % len(once)] for k in range(self.moves))

    # The first move's shape: every move's when step_deg is one number.
    @property
    def triangular(self) -> bool:
        """True when move 0 is too short to reach ``max_rate_dps``: |step| < v^2 / a."""
        return self.shape(0).triangular

    @property
    def peak_rate_dps(self) -> float:
        """The highest |omega| of any move: v, or sqrt(a |d|) for triangular moves."""
        return max(s.peak_rate_dps for s in self.shapes)

    @property
    def accel_time_s(self) -> float:
        return self.shape(0).accel_time_s

    @property
    def cruise_time_s(self) -> float:
        return self.shape(0).cruise_time_s

    @property
    def move_time_s(self) -> float:
        return self.shape(0).move_time_s

    @property
    def duration_s(self) -> float:
        """dwell + moves (move + dwell), or over a list of steps dwell + the sum of (move + dwell)."""
        if not isinstance(self.step_deg, tuple):
            return self.dwell_s + self.moves * (self.move_time_s + self.dwell_s)
        total = self.dwell_s
        for move in self.shapes:
            total += move.move_time_s + self.dwell_s
        return total

    @property
    def end_s(self) -> float:
        return self.start_s + self.duration_s

    def move_start_s(self, k: int) -> float:
        """When move k (0-based) starts: start + dwell + k (move + dwell), or over a list of steps
        start + dwell + the (move + dwell) of the moves before it, summed in order (``moves``: the end)."""
        if not isinstance(self.step_deg, tuple):
            return self.start_s + self.dwell_s + k * (self.move_time_s + self.dwell_s)
        return self._list_move_starts[k]

    @cached_property
    def _list_move_starts(self) -> tuple[float, ...]:
        """``move_start_s(k)`` for k = 0..moves over a list of steps, summed once, in order."""
        t = self.start_s + self.dwell_s
        starts = [t]
        for move in self.shapes:
            t += move.move_time_s + self.dwell_s
            starts.append(t)
        return tuple(starts)


@dataclass(frozen=True)
class Creep:
    """The table creeping at ``rate_dph`` (deg/h) from ``start_s`` to ``stop_s``: motion, not a link fault
    (the table really turns).  It may overlap any other item: its angle adds to theirs, so a positioning's
    dwells then drift by ``rate_dph`` while the station believes the table still."""

    rate_dph: float
    start_s: float
    stop_s: float

    def __post_init__(self) -> None:
        if self.stop_s is None:
            raise ValueError("stop_s: a creep lasts a span of time")
        _check_rate_span(self, "rate_dph")

    @property
    def end_s(self) -> float:
        return self.stop_s

    @property
    def rate_dps(self) -> float:
        return self.rate_dph / 3600.0


MotionItem = ConstantRate | Positioning | Creep


@dataclass(frozen=True)
class MotionPlan:
    """The turntable's motion: non-overlapping items in time order, the table still between them, and
    creeps (``Creep``) on top of them, overlapping anything."""

    items: tuple[MotionItem, ...] = ()
    _pieces: dict[str, np.ndarray] = field(init=False, repr=False, compare=False)
    _dwells: tuple[Dwell, ...] = field(init=False, repr=False, compare=False)
    _creeps: tuple[Creep, ...] = field(init=False, repr=False, compare=False)

    @classmethod
    def static(cls) -> MotionPlan:
        return cls(())

    def __post_init__(self) -> None:
        items = tuple(sorted(self.items, key=lambda it: it.start_s))
        for item in items:
            if not isinstance(item, (ConstantRate, Positioning, Creep)):
                raise TypeError(f"not a motion item: {item!r}")
        moving = [it for it in items if not isinstance(it, Creep)]
        for a, b in zip(moving, moving[1:]):
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
        dwells: list[Dwell] = []
        angle = 0.0

        def piece(t: float, theta: float, omega: float, alpha: float) -> None:
            pieces.append((t, theta, omega, alpha))

        for item in self.items:
            if isinstance(item, Creep):  # added on top of the pieces (``_creep_deg``)
                continue
            if isinstance(item, ConstantRate):
                piece(item.start_s, angle, item.rate_dps, 0.0)
                if item.stop_s is not None:
                    angle = angle + item.rate_dps * (item.stop_s - item.start_s)
                    piece(item.stop_s, angle, 0.0, 0.0)
                continue
            a = item.accel_dps2
            base = angle
            piece(item.start_s, base, 0.0, 0.0)
            dwells.append(Dwell(item.start_s, item.move_start_s(0), base))
            shapes = item.shapes
            for k, move in enumerate(shapes):
                t0 = item.move_start_s(k)
                sign = math.copysign(1.0, move.step_deg)
                peak, t_a, t_c, t_m = move.peak_rate_dps, move.accel_time_s, move.cruise_time_s, move.move_time_s
                half = 0.5 * a * t_a * t_a  # angle covered while accelerating (and while decelerating)
                start_deg = angle
                # one step: base + (k + 1) step, as before lists of steps (the same bits); a list: the running sum
                end_deg = angle + move.step_deg if isinstance(item.step_deg, tuple) else base + (k + 1) * item.step_deg
                piece(t0, start_deg, 0.0, sign * a)
                if t_c > 0:
                    piece(t0 + t_a, start_deg + sign * half, sign * peak, 0.0)
                piece(t0 + t_a + t_c, end_deg - sign * half, sign * peak, -sign * a)
                dwell_end = item.move_start_s(k + 1) if k + 1 < len(shapes) else item.end_s
                piece(t0 + t_m, end_deg, 0.0, 0.0)
                dwells.append(Dwell(t0 + t_m, dwell_end, end_deg))
                angle = end_deg
        t0, theta, omega, alpha = (np.array(column, dtype=np.float64) for column in zip(*pieces))
        object.__setattr__(
            self, "_pieces", {"starts": t0[1:], "t0": t0, "theta": theta, "omega": omega, "alpha": alpha}
        )
        creeps = [it for it in self.items if isinstance(it, Creep)]
        object.__setattr__(self, "_creeps", tuple(creeps))
        if creeps:  # the dwells' true angles, creep included
            dwells = [
                Dwell(s.t_start_s, s.t_end_s, float(self.angle_deg(s.t_start_s)), float(self.angle_deg(s.t_end_s)))
                for s in dwells
            ]
        object.__setattr__(self, "_dwells", tuple(dwells))

    @property
    def kind(self) -> str:
        """``static``, ``constant_rate``, ``positioning``, ``creep``, or ``mixed``."""
        kinds = {_KIND[type(it)] for it in self.items}
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
        """The table rate omega(t) in deg/s at times ``t_s`` (any shape): omega_k + alpha_k (t - t_k), plus
        each creep's rate while it lasts (``start_s <= t < stop_s``)."""
        k, dt = self._lookup(t_s)
        omega = self._pieces["omega"][k] + self._pieces["alpha"][k] * dt
        for c in self._creeps:
            t = np.asarray(t_s, dtype=np.float64)
            omega = omega + np.where((t >= c.start_s) & (t < c.stop_s), c.rate_dps, 0.0)
        return omega

    def angle_deg(self, t_s: np.ndarray) -> np.ndarray:
        """The cumulative table angle theta(t) = theta_k + omega_k (t - t_k) + alpha_k (t - t_k)^2 / 2, exactly,
        plus each creep's ``rate (clip(t, start, stop) - start)``."""
        k, dt = self._lookup(t_s)
        p = self._pieces
        theta = p["theta"][k] + dt * (p["omega"][k] + 0.5 * p["alpha"][k] * dt)
        for c in self._creeps:
            t = np.asarray(t_s, dtype=np.float64)
            theta = theta + c.rate_dps * (np.clip(t, c.start_s, c.stop_s) - c.start_s)
        return theta

    def dwells(self) -> list[Dwell]:
        """Every dwell of every positioning sequence, in time order, with its commanded cumulative angle; under
        a creep, the true angles at the dwell's start and end (``angle_end_deg``)."""
        return list(self._dwells)

    def describe(self) -> str:
        return "static" if not self.items else "; ".join(_describe_item(it) for it in self.items)


_KIND = {ConstantRate: "constant_rate", Positioning: "positioning", Creep: "creep"}


def _describe_item(item: MotionItem) -> str:
    if isinstance(item, Creep):
        return f"creep {item.rate_dph:g} deg/h from {item.start_s:g} s to {item.stop_s:g} s"
    if isinstance(item, ConstantRate):
        stop = "on" if item.stop_s is None else f"to {item.stop_s:g} s"
        return f"constant rate {item.rate_dps:g} deg/s from {item.start_s:g} s {stop}"
    if isinstance(item.step_deg, tuple):
        steps = ", ".join(f"{v:g}" for v in item.step_deg)
        return (
            f"positioning {item.moves} moves of [{steps}] deg in turn from {item.start_s:g} s to {item.end_s:g} s"
            f" (dwell {item.dwell_s:g} s)"
        )
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
    plateau = check_integer("at_plateau", plateau, 0)
    if plateau >= len(plateaus):
        if not plateaus:
            raise ValueError(f"at_plateau {plateau} but the chamber profile has no hold segment")
        raise ValueError(
            f"at_plateau {plateau} but the chamber profile has {len(plateaus)} plateaus (0..{len(plateaus) - 1})"
        )
    settle_s = check_number("settle_s", settle_s, nonnegative=True)
    p = plateaus[plateau]
    seq = Positioning(start_s=p.t_start_s + settle_s, **kwargs)
    if seq.end_s > p.t_end_s:
        raise ValueError(
            f"the sequence at plateau {plateau} ({p.temp_c:g} degC) would end at {seq.end_s:g} s, "
            f"after the plateau ends at {p.t_end_s:g} s "
            f"(it needs {settle_s + seq.duration_s:g} s of hold)"
        )
    return seq
