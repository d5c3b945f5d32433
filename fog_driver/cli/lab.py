"""``fog-driver chamber status`` and ``chamber run``: a thermal chamber's controller read, and a program run on it
by the host (``fog_driver.lab.runner``), a set point a step, logged to a chamber log CSV.

Both need the ``lab`` extra (checked first: one line with the pip command, exit 64); ``--help`` does not.  The
checks before any chamber is touched, in order: the profile (65), ``--resume``'s log (65: not a log, or another
run's), the log's path (73 if it exists without ``--force``), the URL (64: unknown scheme or option); then the
controller is locked (69 if another run drives it) and connected (69 if unreachable).
"""

from __future__ import annotations

import argparse
import sys
import threading
import uuid
from pathlib import Path
from typing import Any

from ..errors import InputFileError, OutputFileError, UsageError
from ..extras import require_extra
from ..files.yamlio import read_yaml
from ..lab.chamberlog import ChamberLogWriter, LogHeader, LogRow, program_sha256, read_chamber_log
from ..lab.controllers.base import ChamberController
from ..lab.lock import ControllerLock
from ..lab.profiles import SimProfile, load_profile
from ..lab.program import ChamberProfile
from ..lab.runner import OnStop, RunOptions, SystemClock, check_range, parse_on_stop, resume_point, run_program
from ..offline.chamber import open_lab_controller
from ..signals import stop_on_signals
from .argtypes import positive_float

EXIT_INTERRUPTED = 130  # as simulate and fit: stopped by Ctrl-C (SIGINT) or SIGTERM


def _notice(line: str) -> None:
    print(f"fog-driver: {line}", file=sys.stderr, flush=True)


def chamber_overrides(path: str | None) -> dict[str, Any]:
    """``--chamber-config FILE``: the driver's settings (register addresses, word order...) under the file's
    ``chamber: overrides:``, the daemon config's own shape, so one file serves the daemon and the commands (the
    section's ``url`` and ``poll_s`` are the daemon's and are not read here); none without a file."""
    if path is None:
        return {}
    doc = read_yaml(path, "chamber config file")
    section = doc.get("chamber") if isinstance(doc, dict) else None
    if not isinstance(section, dict):
        raise InputFileError(f"{path}: a chamber config file needs a 'chamber:' mapping (with 'overrides:')")
    unknown = sorted(set(section) - {"url", "poll_s", "overrides"})
    if unknown:
        raise InputFileError(f"{path}: chamber: unknown key {', '.join(unknown)} (keys: url, poll_s, overrides)")
    overrides = section.get("overrides", {})
    if not isinstance(overrides, dict):
        raise InputFileError(f"{path}: chamber: overrides: must be a mapping of the driver's settings")
    return dict(overrides)


def open_chamber(url: str, config: str | None) -> ChamberController:
    """The controller ``url`` names (``sim://`` from the simulator), not yet connected."""
    return open_lab_controller(url, overrides=chamber_overrides(config), on_notice=_notice)


def status_line(controller: ChamberController) -> str:
    """One line: the air, the set point, the state (and alarms) and the range."""
    air_c = controller.read_air_c()
    setpoint_c = controller.read_setpoint_c()
    status = controller.read_status()
    rng = controller.read_range_c()
    alarms = f" (alarms: {', '.join(status.alarms)})" if status.alarms else ""
    return (
        f"{controller.url}: air {air_c:.2f} degC, set point {setpoint_c:.2f} degC, state {status.state}{alarms}, "
        f"range {rng.low_c:g} .. {rng.high_c:g} degC"
    )


def cmd_chamber_status(args: argparse.Namespace) -> int:
    require_extra("lab", "fog-driver chamber")
    controller = open_chamber(args.url, args.chamber_config)
    controller.connect()
    try:
        print(status_line(controller))
    finally:
        controller.close()
    return 0


def _progress(row: LogRow) -> None:
    if row.state == "settling":
        text = f"settling: set point {row.program_c} degC, air {row.air_c:.2f} degC"
    elif row.setpoint_c is None or row.air_c is None:
        text = f"{row.state}: program at {row.t_s:g} s"
    else:
        text = (
            f"{row.state}: program at {row.t_s:g} s, segment {row.segment}, set point {row.setpoint_c:g} degC, "
            f"air {row.air_c:.2f} degC"
        )
    if sys.stderr.isatty():
        print(f"\r{text}\033[K", end="", file=sys.stderr, flush=True)


def load_program(name_or_path: str) -> tuple[SimProfile, ChamberProfile]:
    """``PROFILE`` (``chamber run``) or ``--profile`` (``calibrate``): the profile and its chamber program."""
    profile = load_profile(name_or_path)
    if not profile.chamber.segments:
        raise InputFileError(f"{name_or_path}: the profile has no chamber program")
    return profile, profile.chamber


def resume_from(resume: str | None, new_log: Path, program: ChamberProfile, give: str) -> tuple[float | None, str]:
    """``--resume OLD.csv``: where the program's clock goes on (None: a new run) and the run's id (the old log's:
    the same run, a new log); the old log may not be the new one (``give``: what to give instead)."""
    if resume is None:
        return None, uuid.uuid4().hex
    if Path(resume).resolve() == new_log.resolve():
        raise UsageError(f"--resume: the old log cannot be the new one ({new_log}: give another {give})")
    try:
        old = read_chamber_log(resume)
        return resume_point(old, program), old.header.run_id
    except InputFileError as exc:
        raise InputFileError(f"--resume {resume}: {exc}") from None


def cmd_chamber_run(args: argparse.Namespace) -> int:
    require_extra("lab", "fog-driver chamber")
    profile, program = load_program(args.profile)
    log_path = Path(args.log)
    resume_t_s, run_id = resume_from(args.resume, log_path, program, "--log")
    if log_path.exists() and not args.force:
        raise OutputFileError(f"{log_path}: exists (give --force to overwrite it)")
    controller = open_chamber(args.chamber, args.chamber_config)
    options = RunOptions(step_s=args.step_s, on_stop=args.on_stop)
    with ControllerLock(controller.address):
        controller.connect()
        check_range(program, controller.read_range_c(), options.on_stop)  # before the log: nothing to log
        header = LogHeader(profile.name, program_sha256(program), args.chamber, run_id, args.resume)
        log = ChamberLogWriter(log_path, header, force=args.force)
        stop = threading.Event()
        try:
            with stop_on_signals(stop):
                print(
                    f"chamber run: {profile.name} ({program.duration_s:g} s) on {args.chamber}, log {log_path}"
                    f"{f', resumed at {resume_t_s:g} s' if resume_t_s is not None else ''}; Ctrl-C to stop",
                    file=sys.stderr,
                    flush=True,
                )
                result = run_program(
                    controller,
                    program,
                    log,
                    options=options,
                    clock=SystemClock(),
                    stop=stop,
                    resume_t_s=resume_t_s,
                    on_row=_progress,
                )
        finally:
            log.close()
            controller.close()
    if sys.stderr.isatty():
        print(file=sys.stderr)
    print(
        f"chamber run {result.status} at {result.program_t_s:g} s of {program.duration_s:g} s: {result.rows} rows "
        f"-> {log_path}"
    )
    return EXIT_INTERRUPTED if result.status == "interrupted" else 0


def on_stop_option(text: str) -> OnStop:
    try:
        return parse_on_stop(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


CONFIG_HELP = (
    "a YAML file whose 'chamber: overrides:' mapping (the daemon config's shape) overrides the driver's settings"
)


def add_program_options(p: argparse.ArgumentParser, *, resume_help: str) -> None:
    """The options ``chamber run`` and ``calibrate`` share: ``--step-s``, ``--on-stop``, ``--resume`` and
    ``--chamber-config``."""
    p.add_argument("--step-s", type=positive_float, default=1.0, metavar="S", help="seconds between set points")
    p.add_argument(
        "--on-stop",
        type=on_stop_option,
        default=OnStop("hold"),
        metavar="hold|standby|C",
        help="at the end or on Ctrl-C: hold (write nothing more), standby, or go to C degC at the program's "
        "slowest ramp rate and hold (default: hold)",
    )
    p.add_argument("--resume", metavar="LOG.csv", help=resume_help)
    p.add_argument("--chamber-config", metavar="FILE", help=CONFIG_HELP)


def add_chamber(p: argparse.ArgumentParser) -> None:
    """``fog-driver chamber``: its subcommands ``status`` and ``run``."""
    sub = p.add_subparsers(dest="chamber_command", metavar="SUBCOMMAND", required=True)
    s = sub.add_parser("status", help="one line: the air, the set point, the state and the range")
    s.add_argument("url", metavar="URL", help="the controller, e.g. espec://HOST, watlow-f4t://HOST, sim://")
    s.add_argument("--chamber-config", metavar="FILE", help=CONFIG_HELP)
    s.set_defaults(func=cmd_chamber_status)
    r = sub.add_parser("run", help="run a program on the chamber: a set point a step, logged")
    r.add_argument("profile", metavar="PROFILE", help="a profile file (as plan writes) or a built-in profile name")
    r.add_argument("--chamber", required=True, metavar="URL", help="the controller, e.g. espec://HOST, sim://")
    r.add_argument("--log", required=True, metavar="LOG.csv", help="the chamber log to write (a row a step)")
    add_program_options(r, resume_help="go on from an interrupted run's log, into --log")
    r.add_argument("--force", action="store_true", help="overwrite --log if it exists")
    r.set_defaults(func=cmd_chamber_run)
