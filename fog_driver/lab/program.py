"""The chamber program: the chamber's air temperature over one run (``ChamberProfile.air_temp_c(t_s)``), an exact
closed form vectorized over numpy arrays with one ``np.searchsorted`` over the segment boundaries (the simulator
evaluates millions of frame times at once).  Times are seconds from the start of the run.

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
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from .checks import check_number

# --- chamber segments --------------------------------------------------------------------------


@dataclass(frozen=True)
class Hold:
    """T = T0 for ``duration_s``."""

    duration_s: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "duration_s", check_number("duration_s", self.duration_s, positive=True))


@dataclass(frozen=True)
class Ramp:
    """T = T0 + sign(target_c - T0) * rate_c_per_min / 60 * t, until T reaches ``target_c``."""

    rate_c_per_min: float
    target_c: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "rate_c_per_min", check_number("rate_c_per_min", self.rate_c_per_min, positive=True))
        object.__setattr__(self, "target_c", check_number("target_c", self.target_c))


@dataclass(frozen=True)
class Step:
    """T jumps to ``target_c`` (zero duration)."""

    target_c: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "target_c", check_number("target_c", self.target_c))


@dataclass(frozen=True)
class Sinusoid:
    """T = T0 + amplitude_c * sin(2 pi t / period_s) for ``duration_s``; the next segment starts from the end value."""

    amplitude_c: float
    period_s: float
    duration_s: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "amplitude_c", check_number("amplitude_c", self.amplitude_c, nonnegative=True))
        object.__setattr__(self, "period_s", check_number("period_s", self.period_s, positive=True))
        object.__setattr__(self, "duration_s", check_number("duration_s", self.duration_s, positive=True))

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
SEGMENT_KINDS: dict[str, type] = {"hold": Hold, "ramp": Ramp, "step": Step, "sinusoid": Sinusoid}
KIND_OF = {cls: kind for kind, cls in SEGMENT_KINDS.items()}


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
        return KIND_OF[type(self.segment)]


@dataclass(frozen=True)
class ChamberProfile:
    """A chamber air-temperature program: ``start_c`` then ``segments`` in order (see the module docstring)."""

    name: str
    start_c: float
    segments: tuple[Segment, ...]
    _spans: tuple[SegmentSpan, ...] = field(init=False, repr=False, compare=False)
    _table: dict[str, np.ndarray] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "start_c", check_number("start_c", self.start_c))
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

    def until(self, t_s: float) -> ChamberProfile:
        """The program's first ``t_s`` seconds as a program of its own: the segments that end by then, and the one
        running at ``t_s`` cut there (a hold or a sinusoid shortened, a ramp ending where the air is at ``t_s``);
        the whole program when it ends by ``t_s``."""
        if t_s >= self.duration_s:
            return self
        segments: list[Segment] = []
        for s in self._spans:
            if s.t_end_s <= t_s:
                segments.append(s.segment)
                continue
            left_s = t_s - s.t_start_s
            seg = s.segment
            if left_s > 0 and isinstance(seg, Hold | Sinusoid):
                segments.append(replace(seg, duration_s=left_s))
            elif left_s > 0 and isinstance(seg, Ramp):
                segments.append(Ramp(seg.rate_c_per_min, float(self.air_temp_c(np.array(t_s)))))
            break
        return ChamberProfile(self.name, self.start_c, tuple(segments))

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
