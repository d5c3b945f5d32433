"""The ``fog-driver`` argument tree: the options of every command, the table of commands, and each command's
own arguments, added by its group's module (``captures``, ``plan``, ``lab``, ``calibrate``, ``calibration``,
``daemon``, ``tools``).

A group's module is imported only when its command is parsed: ``fog-driver ctl --help`` or ``fog-driver watch``
import neither numpy nor the compensation (start-up time).
"""

from __future__ import annotations

import argparse
import importlib
from collections.abc import Iterable, Sequence

from .. import __version__
from ..console import LOG_FORMATS

#: Every command, in the order ``fog-driver --help`` lists them: the module of ``fog_driver.cli`` whose
#: ``add_<command>(parser)`` adds its arguments and its function, and its one-line help.
COMMANDS: dict[str, tuple[str, str]] = {
    "inspect": ("captures", "check a capture file and summarize what it holds"),
    "record": ("captures", "record a port's raw bytes to a capture file with a provenance sidecar"),
    "simulate": ("captures", "simulate the instrument: write a capture with its truth, or serve it live"),
    "plan": ("plan", "design a calibration program for your chamber: a profile that pins the drift model down"),
    "chamber": ("lab", "drive a thermal chamber: read its controller (status), run a program on it (run)"),
    "calibrate": (
        "calibrate",
        "a calibration in one command: record the gyro, run the program on the chamber, log it, fit at the end",
    ),
    "fit": ("calibration", "fit a drift model to static chamber captures"),
    "compensate": ("calibration", "apply a drift model to a capture; write a CSV row per period"),
    "run": ("daemon", "the headless daemon: live compensation, publishing, control, raw capture"),
    "watch": ("tools", "live view of a running daemon (fog-driver run): angle, rate, temperatures, counters"),
    "ctl": ("tools", "send one control command to a running daemon: zero, bias, adapt, reload, status, save"),
    "evaluate": ("calibration", "a report: Allan deviation, drift before and after, positioning accuracy, plots"),
}


def command_in(argv: Sequence[str]) -> str | None:
    """The command ``argv`` names: its first word that is one (no option before a command takes a command's
    name as its value), or None (``--help``, ``--version``, a word that is not a command)."""
    return next((word for word in argv if word in COMMANDS), None)


def build_parser(commands: Iterable[str] | None = None) -> argparse.ArgumentParser:
    """The parser of every command; with ``commands``, only those get their own arguments (the others are
    listed in ``--help`` all the same): ``main`` builds only the command it is given."""
    wanted = set(COMMANDS if commands is None else commands)
    parser = argparse.ArgumentParser(
        prog="fog-driver",
        description="Fiber-optic-gyro instrument driver and temperature-drift compensator.",
    )
    parser.add_argument("--version", action="version", version=f"fog-driver {__version__}")
    # The logging options, before or after the command: `fog-driver -v run` and `fog-driver run -v`.
    logging_options = argparse.ArgumentParser(add_help=False)
    for where, default in ((parser, {"verbose": 0, "log_format": "auto"}), (logging_options, None)):
        where.add_argument(
            "-v",
            "--verbose",
            action="count",
            default=default["verbose"] if default else argparse.SUPPRESS,
            help="more log output on stderr (-v info, -vv debug)",
        )
        where.add_argument(
            "--log-format",
            choices=LOG_FORMATS,
            default=default["log_format"] if default else argparse.SUPPRESS,
            help="log lines for a person (human) or a machine (json); auto: human on a terminal, "
            "json elsewhere (journald, pipes)",
        )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, (group, text) in COMMANDS.items():
        p = sub.add_parser(name, parents=[logging_options], help=text)
        if name in wanted:
            module = importlib.import_module(f".{group}", __package__)  # start-up time: only the command's group
            getattr(module, f"add_{name}")(p)
    return parser
