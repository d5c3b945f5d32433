"""``fog-driver plan``: a calibration program for the user's chamber (``fog_driver.lab.plan``), written as a
profile file that ``simulate --profile`` runs and a chamber is programmed from."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from ..errors import UsageError
from ..files.outputs import check_outputs
from ..files.yamlio import write_yaml
from ..lab.motion import MotionPlan
from ..lab.plan import DEFAULT_LIMITS, DESIGN, ChamberLimits, Plan, design_program
from ..lab.profiles import SimProfile, profile_to_doc
from ..lab.program import Ramp

#: The options, each a field of ``ChamberLimits``.
_OPTIONS = {
    "min_c": "--min-c",
    "max_c": "--max-c",
    "max_rate_c_per_min": "--max-rate-c-per-min",
    "minutes": "--minutes",
}


_HELP = {
    "min_c": ("C", "the chamber's lowest temperature, degC"),
    "max_c": ("C", "the chamber's highest temperature, degC"),
    "max_rate_c_per_min": ("R", "the chamber's fastest ramp, heating and cooling, degC/min"),
    "minutes": ("M", "the chamber time the program may take, min (the default is the paper's program)"),
}


def _limits(args: argparse.Namespace) -> ChamberLimits:
    values = {name: getattr(args, name) for name in _OPTIONS}
    try:
        return ChamberLimits(**values)
    except ValueError as exc:
        text = str(exc)
        for name, option in _OPTIONS.items():
            text = text.replace(name, option)
        raise UsageError(f"plan: impossible limits: {text}") from None


def _rates(plan: Plan) -> list[float]:
    return sorted({seg.rate_c_per_min for seg in plan.chamber.segments if isinstance(seg, Ramp)})


def _command(limits: ChamberLimits) -> str:
    options = [
        f"{option} {getattr(limits, name):g}"
        for name, option in _OPTIONS.items()
        if getattr(limits, name) != getattr(DEFAULT_LIMITS, name)
    ]
    return " ".join(["fog-driver plan", *options])


def header(plan: Plan, limits: ChamberLimits) -> str:
    """The comment at the top of the program file: what wrote it, for which limits, what it leaves unidentified."""
    lines = [
        f"A calibration program written by `{_command(limits)}`: a chamber of {limits.min_c:g}..{limits.max_c:g} "
        f"degC, ramps of {limits.max_rate_c_per_min:g} degC/min at most, {limits.minutes:g} min.",
        "Run it once in the chamber with the instrument on a still table, record it (fog-driver record), and",
        "fit it (fog-driver fit).  Every temperature is crossed warming and cooling, at several rates; the",
        "extremes are held long against the coil's lag (docs: reference/commands, fog-driver plan).",
    ]
    if plan.simplified:
        lines.append("Simplified to fit the limits: " + "; ".join(plan.simplified) + ".")
    if plan.gaps:
        lines.append("Left unidentified under these limits:")
        lines += [f"  - {gap}" for gap in plan.gaps]
    return "\n".join(lines)


def cmd_plan(args: argparse.Namespace) -> int:
    limits = _limits(args)
    out = Path(args.out)
    if out.suffix not in (".yaml", ".yml"):
        raise UsageError(f"--out {args.out!r}: a profile file name must end in .yaml")
    check_outputs([out], force=args.force)
    plan = design_program(limits, dataclasses.replace(DESIGN, name=out.stem))
    profile = SimProfile(out.stem, plan.chamber, MotionPlan.static(), "plan")
    write_yaml(out, profile_to_doc(profile), "the program", header=header(plan, limits))
    rates = ", ".join(f"{r:g}" for r in _rates(plan))
    print(
        f"wrote {out}: a {plan.chamber.duration_s / 60:g}-min program, {len(plan.chamber.segments)} segments, "
        f"ramps at {rates or 'no'} degC/min; try it on the simulated instrument with "
        f"fog-driver simulate --profile {out} --out run.bin"
    )
    if plan.simplified:
        print("simplified to fit the limits: " + "; ".join(plan.simplified))
    if plan.gaps:
        print("left unidentified under these limits:")
        for gap in plan.gaps:
            print(f"  - {gap}")
    else:
        print("every time scale the drift model fits is identifiable from it")
    return 0


def add_plan(p: argparse.ArgumentParser) -> None:
    """``fog-driver plan``: its arguments and its function."""
    p.add_argument("--out", required=True, metavar="PROGRAM.yaml", help="the profile file to write")
    for name, option in _OPTIONS.items():
        metavar, text = _HELP[name]
        default = getattr(DEFAULT_LIMITS, name)
        p.add_argument(option, type=float, default=default, metavar=metavar, help=f"{text} (default {default:g})")
    p.add_argument("--force", action="store_true", help="overwrite an existing file")
    p.set_defaults(func=cmd_plan)
