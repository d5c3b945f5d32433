"""A calibration program for the user's chamber: the chamber run from which the drift model's every time scale
and term can be identified (``fog-driver plan``; the built-in profile ``calibration`` is its default design).

What the ``wesn`` model fits, and what a run must hold for the fit to tell it apart
(``fog_driver.compensation.fitting.wesn``; ``fog_driver.compensation.models.wesn``):

* the coil's lag, from ``COIL_LAG_GRID_S`` (1 to 87 min), tried only up to ``LAG_FRACTION`` (a tenth)
  of the run (a fifth when the residual still falls at the tenth: not to be planned on).  A first-order
  lag tau shows in the settling after the temperature stops moving,
  ``exp(-t / tau)``: a soak after a ramp, as long as the lag (``soak >= tau``) sees 63 % of it;
  a fast ramp into the soak makes its start step-like (the largest transient per degC);
* the coil's stages in series (2 or 3): tried only in runs of ``NOTED_LAG_S / LAG_FRACTION`` (250 min);
* the thermal history, neurons at 30, 60 and 120 min (``WESN_DEFAULTS.history_s``): each only in runs
  of ``1 / HISTORY_FRACTION`` (three) times its time scale;
* the bias curve's shape (the coil temperature's powers): a ring temperature span of ``MIN_SPAN_C``
  (5 degC); the program spans twice that, the ring lagging the air;
* the temperature-rate terms (the coil's own rate: its Shupe and radial-gradient terms) against the
  lag: a lag makes a drift r tau dB/dT, a rate term k r; at one rate both are proportional to r and
  the fit trades one for the other.  They separate where the rate itself varies: ramps at several
  rates (``RATE_RATIO`` apart at least) in each direction, and a rate that changes within the run
  (ramps in a row at different rates, a sinusoid).  The fastest ramp must make the Shupe term of a
  good coil (0.03 deg/h per degC/min, ``fog_driver.sim.population``) stand above the gyro's 1-min
  noise (0.02 deg/h): ``MIN_FAST_RATE_C_PER_MIN`` (1 degC/min);
* the thermal history against the bias curve: the same temperature reached warming and cooling
  (hysteresis; a one-way staircase, as the paper's, confounds it with the bias curve).

The design (``design_program``; the knobs in ``Design``, measured by
``benchmarks/bench_plan.py``): start at room temperature (20 degC, or the nearest limit), a
warm-up hold, then one whole cycle, up to the maximum, down to the minimum, back to the start, so
that every temperature is crossed in both directions.  Each leg is cut into ramps ``plateau_step_c``
apart; the ramp into each extreme is the fastest of the rate ladder (``max_rate * rate_fractions``),
the ones before it take the ladder's rates in turn, so each leg ramps at every rate.  The extremes get
long soaks (``LAG_FRACTION`` of the run: at least the longest lag the fit tries), the other plateaus
short holds sharing what time is left.  With ``varying_rate`` the return leg chains its ramps
without holds (rate steps) and a sinusoid of peak rate ``max_rate * sine_rate_fraction`` ends the
run, one whole period.  When the limits do not leave time for all of it, the design is simplified
step by step (plateaus farther apart, then no sinusoid, then shorter soaks, then a smaller cycle)
until it fits, and ``identifiability_gaps`` says what the program written leaves unidentified.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from ..compensation.fitting import program as terms
from ..compensation.fitting.wesn import HISTORY_FRACTION, LAG_FRACTION, MIN_SPAN_C, NOTED_LAG_S
from ..compensation.models.wesn import COIL_LAG_GRID_S, WESN_DEFAULTS
from .checks import check_number
from .program import ChamberProfile, Hold, Ramp, Segment, Sinusoid

__all__ = [
    "DEFAULT_LIMITS",
    "DESIGN",
    "ChamberLimits",
    "Design",
    "Gap",
    "Plan",
    "design_program",
    "identifiability_gaps",
]

ROOM_C = 20.0  #: where the instrument is mounted and the program starts (clamped into the limits)
ABSOLUTE_ZERO_C = -273.15
MAX_LIMIT_C = 1000.0  #: temperatures beyond this are not a chamber's
MAX_RATE_C_PER_MIN = 100.0  #: faster is not a chamber's (liquid-nitrogen chambers do tens of degC/min)
MAX_MINUTES = 7 * 24 * 60.0  #: one week
WARMUP_MIN = 20.0  #: the warm-up hold at room temperature (the instrument's self-heating settles) ...
WARMUP_FRACTION = 0.05  #: ... at most this fraction of the run
MIN_HOLD_MIN = 10.0  #: a plateau's hold is at least this (or a fortieth of the run, if shorter)
RAMP_SHARE = 0.6  #: a cycle shrunk to fit a short budget ramps for at most this share of the run
RATE_RATIO = 2.0  #: two ramp rates tell a rate term from a lag when at least this far apart
MIN_FAST_RATE_C_PER_MIN = 1.0  #: the fastest ramp makes a good coil's Shupe term show above the 1-min noise
SINE_MAX_AMPLITUDE_C = 8.0
MIN_CYCLE_C = 0.1  #: a cycle spanning less is no program: about what a chamber's control holds a temperature to


@dataclass(frozen=True)
class ChamberLimits:
    """What the chamber can do: its temperature range, its fastest ramp (either way) and the time budget."""

    min_c: float = -40.0
    max_c: float = 55.0
    max_rate_c_per_min: float = 3.0
    minutes: float = 440.0

    def __post_init__(self) -> None:
        for name in ("min_c", "max_c", "max_rate_c_per_min", "minutes"):
            check_number(name, getattr(self, name))
        if not (ABSOLUTE_ZERO_C < self.min_c <= MAX_LIMIT_C and ABSOLUTE_ZERO_C < self.max_c <= MAX_LIMIT_C):
            raise ValueError(
                f"temperatures must lie between {ABSOLUTE_ZERO_C:g} and {MAX_LIMIT_C:g} degC, "
                f"got {self.min_c:g} .. {self.max_c:g}"
            )
        if not self.min_c < self.max_c:
            raise ValueError(f"min_c must be below max_c, got {self.min_c:g} >= {self.max_c:g}")
        if not 0 < self.max_rate_c_per_min <= MAX_RATE_C_PER_MIN:
            raise ValueError(
                f"max_rate_c_per_min must be in (0, {MAX_RATE_C_PER_MIN:g}], got {self.max_rate_c_per_min:g}"
            )
        if not 0 < self.minutes <= MAX_MINUTES:
            raise ValueError(f"minutes must be in (0, {MAX_MINUTES:g}] (a week), got {self.minutes:g}")
        span = self.max_c - self.min_c
        if span < MIN_CYCLE_C:
            raise ValueError(
                f"min_c {self.min_c:g} .. max_c {self.max_c:g} span {span:.3g} degC, under the {MIN_CYCLE_C:g} degC "
                "a chamber holds a temperature to: no program is possible"
            )
        reach = _smallest_cycle_c(self)
        if reach < MIN_CYCLE_C:
            raise ValueError(
                f"minutes {self.minutes:g} at max_rate_c_per_min {self.max_rate_c_per_min:g}: a cycle ramping for "
                f"{RAMP_SHARE:g} of the time spans {reach:.3g} degC, under the {MIN_CYCLE_C:g} degC a chamber holds a "
                "temperature to: no program is possible (more minutes, or a faster max_rate_c_per_min)"
            )


def _warmup_min(total_min: float) -> float:
    """The warm-up hold of a run of ``total_min``: ``WARMUP_MIN``, at most ``WARMUP_FRACTION`` of the run."""
    return min(WARMUP_MIN, WARMUP_FRACTION * total_min)


def _smallest_cycle_c(limits: ChamberLimits) -> float:
    """The span of the design's last resort (``_layouts``): the whole range, or the cycle whose ramps at the
    fastest rate (out, through, back: twice the span) take ``RAMP_SHARE`` of the time after the warm-up."""
    ramp_min = RAMP_SHARE * (limits.minutes - _warmup_min(limits.minutes))
    return min(limits.max_c - limits.min_c, ramp_min * limits.max_rate_c_per_min / 2.0)


#: The paper's chamber range and program length, and a chamber's usual fastest ramp.
DEFAULT_LIMITS = ChamberLimits()


@dataclass(frozen=True)
class Design:
    """The design's knobs (module docstring)."""

    name: str = "calibration"
    rate_fractions: tuple[float, ...] = (1.0, 0.5, 0.25)  #: the rate ladder, fractions of the fastest
    plateau_step_c: float = 15.0  #: plateaus about this far apart along each leg
    long_soaks: bool = True  #: soaks of LAG_FRACTION of the run at the extremes
    varying_rate: bool = True  #: the return leg's ramps chained, and a closing sinusoid
    sine_rate_fraction: float = 0.5  #: the sinusoid's peak rate, a fraction of the fastest


DESIGN = Design()


@dataclass(frozen=True)
class Gap:
    """A time scale or term a program leaves unidentified: what, and why; ``term``, what it is about (one of
    ``compensation.fitting.program``'s terms), and for coil lags the range of them (``lags_s``: the first and
    the last of ``COIL_LAG_GRID_S`` left unidentified), which the fit's lag warning weighs."""

    what: str
    why: str
    term: str = ""
    lags_s: tuple[float, float] | None = None

    def __str__(self) -> str:
        return f"{self.what}: {self.why}"


@dataclass(frozen=True)
class Plan:
    """A designed program, what it leaves unidentified, and the simplifications its limits forced."""

    chamber: ChamberProfile
    gaps: tuple[Gap, ...]
    simplified: tuple[str, ...]


# --- the design ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Layout:
    step_c: float
    ladder: tuple[float, ...]
    long_soaks: bool
    sine: bool
    sine_rate_fraction: float
    soak_scale: float = 1.0  #: the long soaks' length, a fraction of LAG_FRACTION of the run
    span_scale: float = 1.0  #: the cycle's excursions, a fraction of the limits'


def _grid_c(step_c: float) -> float:
    """The rounding of plateau temperatures: 5 degC for plateaus 15 or more apart, finer for closer ones."""
    return next((g for g in (5.0, 1.0, 0.5, 0.1) if g * 3.0 <= step_c), 0.0)


def _leg_points(start_c: float, end_c: float, step_c: float) -> list[float]:
    """The plateau temperatures from ``start_c`` (excluded) to ``end_c`` (included): ``ceil(|span| / step)``
    equal parts, the inner ones rounded to ``_grid_c``."""
    n = max(1, math.ceil(abs(end_c - start_c) / step_c - 1e-9))
    grid = _grid_c(abs(end_c - start_c) / n)
    points = []
    for k in range(1, n):
        t = start_c + (end_c - start_c) * k / n
        points.append(round(t / grid) * grid if grid else t)
    points.append(end_c)
    out = [p for i, p in enumerate(points) if p != (points[i - 1] if i else start_c)]
    return out


def _leg_rates(n: int, ladder: tuple[float, ...]) -> list[float]:
    """The rates of a leg's ``n`` ramps: the last the fastest, the ones before it the ladder's in turn."""
    return [ladder[(n - 1 - i) % len(ladder)] for i in range(n)]


def _layout_segments(limits: ChamberLimits, layout: _Layout) -> tuple[float, list[Segment]] | None:
    """The program of ``layout`` within ``limits``, or None when its holds would come out under the minimum."""
    total = limits.minutes
    lo, hi = limits.min_c, limits.max_c
    start = min(max(ROOM_C, lo), hi)
    top = start + layout.span_scale * (hi - start)
    bottom = start - layout.span_scale * (start - lo)
    warmup = _warmup_min(total)
    soak = layout.soak_scale * LAG_FRACTION * total
    min_hold = min(MIN_HOLD_MIN, total / 40.0)
    # (kind, value): ("ramp", (rate, target)), ("short", None), ("long", None), ("sine", (amplitude, period))
    plan: list[tuple[str, object]] = []
    legs = [(start, top, "long"), (top, bottom, "long"), (bottom, start, "short")]
    here = start
    for i, (a, b, end_hold) in enumerate(legs):
        if b == a:
            continue
        points = _leg_points(a, b, layout.step_c)
        rates = _leg_rates(len(points), layout.ladder)
        chained = layout.sine and i == 2  # the return leg: rate steps, no holds
        for k, (point, rate) in enumerate(zip(points, rates)):
            plan.append(("ramp", (rate, point)))
            last = k == len(points) - 1
            if last:
                plan.append(("long" if layout.long_soaks and end_hold == "long" else "short", None))
            elif not chained:
                plan.append(("short", None))
        here = b
    if layout.sine:
        amplitude = min(SINE_MAX_AMPLITUDE_C, (hi - lo) / 4.0, layout.step_c / 2.0)
        centre = min(max(here, lo + amplitude), hi - amplitude)
        if centre != here:
            plan.append(("ramp", (layout.ladder[0], centre)))
            here = centre
        peak_rate = limits.max_rate_c_per_min * layout.sine_rate_fraction
        # the peak rate of A sin(2 pi t / P) is 2 pi A / P; the period rounded up to 0.1 min
        period = math.ceil(2.0 * math.pi * amplitude / peak_rate * 10.0) / 10.0
        plan.append(("sine", (amplitude, period)))
        plan.append(("short", None))
    if not plan or plan[-1][0] == "ramp":
        plan.append(("short", None))
    fixed = warmup
    temp = start
    for kind, value in plan:
        if kind == "ramp":
            rate, target = value  # type: ignore[misc]
            fixed += abs(target - temp) / rate
            temp = target
        elif kind == "long":
            fixed += soak
        elif kind == "sine":
            fixed += value[1]  # type: ignore[index]
    shorts = sum(kind == "short" for kind, _ in plan)
    spare = total - fixed
    if not shorts:  # only long soaks (room temperature at a limit, no sinusoid): the last takes the spare time
        if spare < 0:
            return None
        hold = 0.0
    else:
        hold = spare / shorts
        if hold < min_hold and not (layout.span_scale < 1.0 and hold > 0):
            return None
    if hold >= 1.0:  # whole tenths of a minute, the last hold taking what is left
        hold = math.floor(hold * 10.0) / 10.0
    segments: list[Segment] = [Hold(warmup * 60.0)] if warmup > 0 else []
    for kind, value in plan:
        if kind == "ramp":
            segments.append(Ramp(*value))  # type: ignore[misc]
        elif kind == "sine":
            amplitude, period = value  # type: ignore[misc]
            segments.append(Sinusoid(amplitude, period * 60.0, period * 60.0))
        else:
            segments.append(Hold((soak if kind == "long" else hold) * 60.0))
    used_s = ChamberProfile("", start, tuple(segments[:-1])).duration_s
    segments[-1] = Hold(total * 60.0 - used_s)
    return start, segments


def _layouts(limits: ChamberLimits, design: Design):
    """The layouts to try, the design's first, then ever simpler ones; each with what it gave up."""
    ladder = tuple(limits.max_rate_c_per_min * f for f in design.rate_fractions)
    span = limits.max_c - limits.min_c
    first = _Layout(design.plateau_step_c, ladder, design.long_soaks, design.varying_rate, design.sine_rate_fraction)
    yield first, ()
    layout, said = first, ()
    while layout.step_c < span:  # plateaus farther apart (fewer holds, fewer ramps, fewer rates per leg)
        layout = replace(layout, step_c=layout.step_c * 1.5)
        yield layout, ("plateaus farther apart",)
    if layout.sine:
        layout, said = replace(layout, sine=False), ("no closing sinusoid, no chained ramps",)
        yield layout, said
    if layout.long_soaks:
        for scale in (0.5, 0.25):
            yield replace(layout, soak_scale=scale), (*said, f"soaks at the extremes cut to {scale:g} of their length")
        layout, said = replace(layout, long_soaks=False), (*said, "no long soaks")
        yield layout, said
    # the last resort: a smaller cycle whose ramps take RAMP_SHARE of the run (ChamberLimits refuses limits
    # that leave it under MIN_CYCLE_C)
    scale = _smallest_cycle_c(limits) / span
    yield replace(layout, span_scale=scale * 0.999), (*said, f"the cycle shrunk to {100 * scale:.0f} % of the range")


def design_program(limits: ChamberLimits = DEFAULT_LIMITS, design: Design = DESIGN) -> Plan:
    """The calibration program for ``limits`` (module docstring), what it leaves unidentified, and what the
    limits made it give up."""
    for layout, simplified in _layouts(limits, design):
        built = _layout_segments(limits, layout)
        if built is not None:
            start, segments = built
            chamber = ChamberProfile(design.name, start, tuple(segments))
            return Plan(chamber, identifiability_gaps(chamber), simplified)
    raise AssertionError("the last layout always fits")  # pragma: no cover


# --- what a program leaves unidentified ------------------------------------------------------------


def _fmt_min(seconds: float) -> str:
    return f"{seconds / 60.0:.3g} min"


def identifiability_gaps(chamber: ChamberProfile) -> tuple[Gap, ...]:
    """What the ``wesn`` fit of one run of ``chamber`` cannot identify (module docstring), each with why.

    Coil lags: those of ``COIL_LAG_GRID_S`` above ``LAG_FRACTION`` of the run (not tried) or above the
    longest soak that follows a ramp (no settling that long).  Coil stages: runs under
    ``NOTED_LAG_S / LAG_FRACTION``.  History neurons: over ``HISTORY_FRACTION`` of the run.  The bias
    curve's shape: a span under ``2 MIN_SPAN_C``.  Rate terms: fewer than two rates ``RATE_RATIO`` apart
    in a direction, or the fastest under ``MIN_FAST_RATE_C_PER_MIN``; no rate change within the run.
    Hysteresis: the warming and the cooling ramps overlap over less than half the span."""
    spans = chamber.spans()
    run_s = chamber.duration_s
    gaps: list[Gap] = []
    tried = [lag for lag in COIL_LAG_GRID_S if lag <= LAG_FRACTION * run_s]
    soak_s = 0.0
    moved = False
    for s in spans:
        if s.end_c != s.start_c or isinstance(s.segment, Sinusoid):
            moved = True
        elif isinstance(s.segment, Hold) and moved:
            soak_s = max(soak_s, s.t_end_s - s.t_start_s)
    if max(COIL_LAG_GRID_S) > LAG_FRACTION * run_s:
        gaps.append(
            Gap(
                f"coil lags above {_fmt_min(max(tried)) if tried else 'none'}".replace("above none", "(all)"),
                f"the fit tries lags up to a tenth of the run ({_fmt_min(run_s)}), a fifth only when the "
                f"residual still falls there; the model's, up to {_fmt_min(max(COIL_LAG_GRID_S))}, need "
                f"{_fmt_min(max(COIL_LAG_GRID_S) / LAG_FRACTION)}",
                terms.LAGS_UNTRIED,
                (min(lag for lag in COIL_LAG_GRID_S if lag not in tried), max(COIL_LAG_GRID_S)),
            )
        )
    shown = [lag for lag in tried if lag <= soak_s]
    if tried and len(shown) < len(tried):
        gaps.append(
            Gap(
                f"coil lags {_fmt_min(min(lag for lag in tried if lag > soak_s))} to {_fmt_min(max(tried))}",
                f"the longest soak after a ramp lasts {_fmt_min(soak_s)}: a lag shows in the settling a soak "
                "as long as it sees",
                terms.LAGS_UNSETTLED,
                (min(lag for lag in tried if lag > soak_s), max(tried)),
            )
        )
    if run_s < NOTED_LAG_S / LAG_FRACTION:
        gaps.append(
            Gap(
                "a coil of several stages in series",
                f"the fit tries it in runs of {_fmt_min(NOTED_LAG_S / LAG_FRACTION)} or more",
                terms.COIL_STAGES,
            )
        )
    for history_s in WESN_DEFAULTS.history_s:
        if history_s > HISTORY_FRACTION * run_s:
            gaps.append(
                Gap(
                    f"thermal history at {_fmt_min(history_s)}",
                    f"it needs a run {1 / HISTORY_FRACTION:g} times as long ({_fmt_min(history_s / HISTORY_FRACTION)})",
                    terms.HISTORY,
                )
            )
    temps = [s.start_c for s in spans] + [s.end_c for s in spans]
    sines = [s for s in spans if isinstance(s.segment, Sinusoid)]
    low = min([*temps, *(s.start_c - s.segment.amplitude_c for s in sines)], default=chamber.start_c)
    high = max([*temps, *(s.start_c + s.segment.amplitude_c for s in sines)], default=chamber.start_c)
    if high - low < 2.0 * MIN_SPAN_C:
        gaps.append(
            Gap(
                "the bias curve's shape",
                f"the program spans {high - low:.3g} degC; the fit needs the ring to span {MIN_SPAN_C:g} degC and "
                "the ring lags the air",
                terms.BIAS_SHAPE,
            )
        )
    ramps = [s for s in spans if isinstance(s.segment, Ramp) and s.end_c != s.start_c]
    for direction, sign in (("warming", 1.0), ("cooling", -1.0)):
        rates = sorted({s.segment.rate_c_per_min for s in ramps if (s.end_c - s.start_c) * sign > 0})
        if not rates:
            gaps.append(
                Gap(f"the temperature-rate terms {direction}", f"the program has no {direction} ramp", terms.RATE_TERMS)
            )
        elif rates[-1] < MIN_FAST_RATE_C_PER_MIN:
            gaps.append(
                Gap(
                    f"the temperature-rate terms {direction}",
                    f"the fastest {direction} ramp is {rates[-1]:.3g} degC/min; under {MIN_FAST_RATE_C_PER_MIN:g} "
                    "degC/min a good coil's Shupe term stays under the gyro's 1-min noise",
                    terms.RATE_TERMS_SLOW,
                )
            )
        elif rates[-1] < RATE_RATIO * rates[0]:
            gaps.append(
                Gap(
                    f"the temperature-rate terms {direction}",
                    f"its ramps run at {', '.join(f'{r:.3g}' for r in rates)} degC/min: a rate term is told from a "
                    f"lag by rates at least {RATE_RATIO:g}x apart",
                    terms.RATE_TERMS,
                )
            )
    changes = bool(sines) or any(
        a.end_c != a.start_c
        and b.end_c != b.start_c
        and isinstance(a.segment, Ramp)
        and isinstance(b.segment, Ramp)
        and a.segment.rate_c_per_min != b.segment.rate_c_per_min
        for a, b in zip(ramps, ramps[1:])
        if a.t_end_s == b.t_start_s
    )
    if not changes:
        gaps.append(
            Gap(
                "a rate that varies within the run",
                "no sinusoid and no two ramps in a row at different rates: the coil's rate is seen only at "
                "steady ramps",
                terms.RATE_CHANGE,
            )
        )
    up = [(s.start_c, s.end_c) for s in ramps if s.end_c > s.start_c]
    down = [(s.end_c, s.start_c) for s in ramps if s.end_c < s.start_c]
    overlap = _overlap(up, down)
    if overlap < 0.5 * (high - low):
        gaps.append(
            Gap(
                "the thermal history against the bias curve (hysteresis)",
                f"warming and cooling ramps cross the same temperatures over {overlap:.3g} of the program's "
                f"{high - low:.3g} degC; a temperature reached both ways tells them apart",
                terms.HYSTERESIS,
            )
        )
    return tuple(gaps)


def _overlap(a: list[tuple[float, float]], b: list[tuple[float, float]]) -> float:
    """The length of the temperatures covered both by intervals ``a`` and by intervals ``b``."""

    def union(intervals: list[tuple[float, float]]) -> list[tuple[float, float]]:
        out: list[tuple[float, float]] = []
        for lo, hi in sorted(intervals):
            if out and lo <= out[-1][1]:
                out[-1] = (out[-1][0], max(out[-1][1], hi))
            else:
                out.append((lo, hi))
        return out

    return sum(max(0.0, min(h1, h2) - max(l1, l2)) for l1, h1 in union(a) for l2, h2 in union(b))
