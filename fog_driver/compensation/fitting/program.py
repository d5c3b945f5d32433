"""What the fit is told of the runs its captures recorded: each one's chamber program, judged.

The fit reads bytes, not chambers: it cannot tell from a capture which program the chamber ran.  The
program comes from the capture's sidecar (``program``: what ``simulate`` ran, or what a tool that drives a
chamber ran) or from ``fog-driver fit --profile``; ``offline.fit`` finds it, judges it
(``lab.plan.identifiability_gaps`` of the part of it the capture holds) and hands the fit a ``RunProgram``.
The fit's lag warning (``wesn.lag_warning``) then names what the program leaves unidentified that bears on
the coil's lag, and says what else would narrow the lag's interval, never the program just run.

A gap bears on the coil's lag (``bears_on_lag``) when it is the rate terms' (``RATE_TERMS``, ``RATE_TERMS_SLOW``,
``RATE_CHANGE``:
a lag and a rate term both make a drift proportional to the rate, the fit trades one for the other where
the rate does not vary) or a range of lags the program cannot show (``LAGS_UNTRIED``, ``LAGS_UNSETTLED``)
that the interval found reaches: its top at or above the lag tried just below that range.  The other gaps
(the coil's stages, the thermal history, the bias curve's shape, hysteresis) are the model's other terms.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

from ..models.wesn import COIL_LAG_GRID_S

#: The terms a program's gap is about (``lab.plan.Gap.term``).
LAGS_UNTRIED = "coil lags untried"  #: lags above a tenth of the run: not tried
LAGS_UNSETTLED = "coil lags unsettled"  #: lags longer than the longest soak after a ramp
COIL_STAGES = "coil stages"
HISTORY = "thermal history"
BIAS_SHAPE = "bias curve shape"
RATE_TERMS = "rate terms"  #: no ramp, or ramps at too few rates, in a direction
RATE_TERMS_SLOW = "rate terms slow"  #: the fastest ramp in a direction too slow for the rate terms to show
RATE_CHANGE = "rate change"  #: no rate that varies within the run
HYSTERESIS = "hysteresis"


class ProgramGap(Protocol):
    """A time scale or term a program leaves unidentified (``lab.plan.Gap``)."""

    @property
    def what(self) -> str: ...

    @property
    def why(self) -> str: ...

    @property
    def term(self) -> str: ...

    @property
    def lags_s(self) -> tuple[float, float] | None: ...


@dataclass(frozen=True)
class RunProgram:
    """The chamber program a fit capture's run followed, judged (``offline.fit.run_program`` makes it)."""

    name: str
    source: str  #: where it was learned, in words: "chamber.bin's sidecar", "--profile calibration"
    held_min: float  #: the minutes of it the capture holds (judged), at most ``program_min``
    program_min: float  #: the program's own length
    gaps: tuple[ProgramGap, ...]  #: what the part held leaves unidentified (``lab.plan.identifiability_gaps``)
    #: it is the program ``fog-driver plan`` writes for its own limits (extremes, fastest ramp, minutes):
    #: under those limits no program identifies more
    planned: bool = False
    #: a fastest ramp for ``fog-driver plan`` that would narrow the interval (half this program's, when that
    #: is still fast enough for the rate terms); None: none
    slower_max_rate_c_per_min: float | None = None

    @property
    def cut(self) -> bool:
        """Whether the capture holds less than the whole program (the part held was judged)."""
        return self.held_min < self.program_min - 0.5


def _lag_below(lag_s: float) -> float:
    """The longest lag of ``COIL_LAG_GRID_S`` shorter than ``lag_s`` (0 when none is)."""
    return max((v for v in COIL_LAG_GRID_S if v < lag_s), default=0.0)


def bears_on_lag(gap: ProgramGap, interval_s: tuple[float, float]) -> bool:
    """Whether ``gap`` is a reason the coil's lag came out in ``interval_s`` (the module docstring)."""
    if gap.term in (RATE_TERMS, RATE_TERMS_SLOW, RATE_CHANGE):
        return True
    if gap.term in (LAGS_UNTRIED, LAGS_UNSETTLED) and gap.lags_s is not None:
        return interval_s[1] >= _lag_below(gap.lags_s[0])
    return False


def lag_gaps(program: RunProgram, interval_s: tuple[float, float]) -> list[ProgramGap]:
    """The gaps of ``program`` that bear on the coil's lag found in ``interval_s``."""
    return [g for g in program.gaps if bears_on_lag(g, interval_s)]
