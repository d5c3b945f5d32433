"""A capture's chamber log (``fog_driver.lab.chamberlog``), found beside it, and whether the chamber ran its
program as designed.

``find_chamber_log(capture)``: the log the capture's sidecar names (``chamber_log``, a path relative to the
capture's folder: ``calibrate`` writes it), else ``<capture stem>.chamber.csv`` beside the capture (the daemon's
and ``calibrate``'s name for it), else None.

``lag_stretches(log)``: where the air did not follow the program.  The program's worth is its identifiability: a
coil lag is pinned only by ramps run at the designed rates, so ``fit`` says when the air stayed away from the
program's set point for long (``program_warnings``).  The rule, for every row with an air reading:

- the reference is the program's set point (``program_c``, what the runner wrote), else the read-back set point
  (``setpoint_c``: a daemon's log, where someone else drives the chamber);
- the air is *following* when it lies within ``LAG_TOLERANCE_C`` (2 degC) of the set points of the last
  ``LAG_WINDOW_S`` (15 min) of host time (between their lowest and highest, widened by the tolerance);
- a *stretch* is a run of rows not following that lasts longer than ``MIN_STRETCH_S`` (10 min); a row without an
  air reading (``link_lost``) ends a stretch (nothing is known there).

Why these numbers: a good chamber's air is a first-order lag of its set point with a time constant tau of about
1 to 5 min.  On a ramp at rate r its air lags by tau * r (5 degC at 1 degC/min for tau = 5 min), which is the
set point of tau ago: inside a 15-min window for any tau up to 5 min, whatever the rate, so a chamber's own lag
never counts.  After a step of dT its air is within 2 degC of the new set point once dT * exp(-t / tau) < 2:
for tau = 5 min and a 60-degC step 17 min, of which the window covers the first 15 (3 tau): 2 min left, under
the 10-min stretch.  2 degC is well above a controller's regulation (+-0.5 degC) and the runner's settle
tolerance (0.5 degC).  A ramp the chamber could not follow (its heater or compressor too weak: a designed
1 degC/min run at 0.5) leaves the window 30 min into a 60-degC ramp at 1 degC/min and is 2 degC beyond it at
34 min: a stretch of 26 min to the ramp's end, and more while the air catches up.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputFileError
from ..lab.chamberlog import ChamberLog, read_chamber_log
from ..lab.controllers.base import ChamberController, Notice
from ..lab.controllers.registry import DEFAULT_TIMEOUT_S, open_controller
from ..lab.controllers.url import ControllerURL
from ..samples.captures import read_provenance

__all__ = [
    "CHAMBER_LOG_SUFFIX",
    "LAG_TOLERANCE_C",
    "LAG_WINDOW_S",
    "MIN_STRETCH_S",
    "LagStretch",
    "capture_program_warnings",
    "chamber_log_and_warnings",
    "find_chamber_log",
    "lag_stretches",
    "program_warnings",
]

#: The suffix of a capture's chamber log: ``run.bin`` -> ``run.chamber.csv``.
CHAMBER_LOG_SUFFIX = ".chamber.csv"
LAG_TOLERANCE_C = 2.0
LAG_WINDOW_S = 900.0
MIN_STRETCH_S = 600.0


def _open_sim(url: ControllerURL, **settings: Any) -> ChamberController:
    """``sim://``: the simulated lab's chamber, imported only when a URL names it."""
    from ..sim.chamber import open_sim_controller  # start-up time: the simulator is imported only for sim://

    return open_sim_controller(url, **settings)


def open_lab_controller(
    url: str, *, overrides: Mapping[str, Any] | None = None, on_notice: Notice, timeout_s: float = DEFAULT_TIMEOUT_S
) -> ChamberController:
    """The controller ``url`` names, ``sim://`` (the simulated lab's chamber) included, not connected: the one
    way the commands and the daemon open a chamber (``UsageError``: an unknown scheme or option)."""
    return open_controller(
        url, overrides=overrides, on_notice=on_notice, timeout_s=timeout_s, extra_schemes={"sim": _open_sim}
    )


def chamber_log_beside(capture: str | Path) -> Path:
    """``<capture stem>.chamber.csv`` beside ``capture``."""
    capture = Path(capture)
    return capture.with_name(capture.stem + CHAMBER_LOG_SUFFIX)


def find_chamber_log(capture: str | Path) -> Path | None:
    """The capture's chamber log (the module docstring), or None.  A sidecar whose ``chamber_log`` is not a
    string, or names a file that is not there, is a one-line ``InputFileError``."""
    capture = Path(capture)
    named = (read_provenance(capture) or {}).get("chamber_log")
    if named is not None:
        if not isinstance(named, str) or not named:
            raise InputFileError(f"{capture}: its sidecar's chamber_log is not a file name: {named!r}")
        path = capture.parent / named
        if not path.exists():
            raise InputFileError(f"{capture}: its sidecar names the chamber log {path}, which is not there")
        return path
    beside = chamber_log_beside(capture)
    return beside if beside.exists() else None


def load_chamber_log(capture: str | Path) -> ChamberLog | None:
    """The capture's chamber log read (``read_chamber_log``), or None when it has none."""
    path = find_chamber_log(capture)
    return None if path is None else read_chamber_log(path)


@dataclass(frozen=True)
class LagStretch:
    """A stretch where the air did not follow the program: its start and end (program seconds ``t_s`` where
    the log has them, else seconds since the log's first row), how long it lasted (host s), and the largest
    distance of the air from the program's set point at that moment in it (degC)."""

    start_s: float
    end_s: float
    duration_s: float
    worst_lag_c: float
    program_time: bool  # start_s/end_s are program time (else seconds from the log's start)


def lag_stretches(
    log: ChamberLog,
    *,
    tolerance_c: float = LAG_TOLERANCE_C,
    window_s: float = LAG_WINDOW_S,
    min_stretch_s: float = MIN_STRETCH_S,
) -> list[LagStretch]:
    """The stretches where the air did not follow the program (the module docstring's rule), in order."""
    if not log.rows:
        return []
    host_s = log.utc_s - log.utc_s[0]
    air = log.air_c
    reference = np.where(np.isfinite(log.program_c), log.program_c, log.setpoint_c)
    t_s = log.t_s
    program_time = bool(np.isfinite(t_s).any())
    label = t_s if program_time else host_s
    following = np.ones(len(air), dtype=bool)
    known = np.isfinite(air)
    start = 0
    for i in range(len(air)):  # the window's first row moves forward with i: O(n) for the bounds' lookups
        while host_s[start] < host_s[i] - window_s:
            start += 1
        window = reference[start : i + 1]
        window = window[np.isfinite(window)]
        if not known[i] or window.size == 0:
            continue
        following[i] = window.min() - tolerance_c <= air[i] <= window.max() + tolerance_c
    stretches: list[LagStretch] = []
    i = 0
    n = len(air)
    while i < n:
        if following[i] or not known[i]:
            i += 1
            continue
        j = i
        while j + 1 < n and known[j + 1] and not following[j + 1]:
            j += 1
        duration_s = float(host_s[j] - host_s[i])
        if duration_s > min_stretch_s:
            lag = np.abs(air[i : j + 1] - reference[i : j + 1])
            stretches.append(
                LagStretch(
                    _first_finite(label[i : j + 1], host_s[i]),
                    _first_finite(label[i : j + 1][::-1], host_s[j]),
                    duration_s,
                    float(np.nanmax(lag)) if np.isfinite(lag).any() else float("nan"),
                    program_time,
                )
            )
        i = j + 1
    return stretches


def _first_finite(values: np.ndarray, default: float) -> float:
    finite = values[np.isfinite(values)]
    return float(finite[0]) if finite.size else float(default)


def program_warnings(capture: str | Path, log: ChamberLog) -> list[str]:
    """One line per capture whose chamber did not run its program as designed (``lag_stretches``), naming the
    stretches (at most three, then how many more), and the log's cut last row if any."""
    out = []
    cut = log.cut_warning()
    if cut:
        out.append(cut)
    stretches = lag_stretches(log)
    if stretches:
        clock = "program time" if stretches[0].program_time else "from the log's start"
        shown = ", ".join(
            f"{s.start_s / 60:.1f}-{s.end_s / 60:.1f} min ({s.duration_s / 60:.0f} min, up to {s.worst_lag_c:.1f} degC)"
            for s in stretches[:3]
        )
        more = f" and {len(stretches) - 3} more" if len(stretches) > 3 else ""
        out.append(
            f"{capture}: the chamber did not run its program as designed: its air stayed more than "
            f"{LAG_TOLERANCE_C:g} degC from the set point (beyond {LAG_WINDOW_S / 60:g} min of the chamber's own "
            f"lag) for over {MIN_STRETCH_S / 60:g} min at {shown}{more} ({clock}; log {log.path}); the coil lag the "
            f"program was designed to identify rests on ramps run at their rates"
        )
    return out


def chamber_log_and_warnings(capture: str | Path) -> tuple[ChamberLog | None, list[str]]:
    """The capture's chamber log (None: none, or one that cannot be read) and its ``program_warnings``; a chamber
    log that cannot be read is a warning too (the capture is still fitted or evaluated: the log only says how
    the program ran)."""
    try:
        log = load_chamber_log(capture)
    except InputFileError as exc:
        return None, [f"{capture}: its chamber log not read: {exc}"]
    return log, ([] if log is None else program_warnings(capture, log))


def capture_program_warnings(captures: Sequence[str | Path]) -> list[str]:
    """``chamber_log_and_warnings``'s warnings of each capture, in order."""
    return [line for capture in captures for line in chamber_log_and_warnings(capture)[1]]
