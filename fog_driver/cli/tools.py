"""``fog-driver watch`` and ``ctl``: the operator's clients of a running daemon (``fog_driver.tools``)."""

from __future__ import annotations

import argparse
import signal

from ..tools.ctl import ctl_command
from ..tools.watch import watch_command
from .argtypes import MAX_REPLY_TIMEOUT_S, positive_float, positive_int, reply_timeout_s, watch_rate_hz


def cmd_watch(args: argparse.Namespace) -> int:
    previous = signal.signal(signal.SIGTERM, signal.default_int_handler)  # SIGTERM ends it as Ctrl-C does
    try:
        return watch_command(
            args.connect or args.address,
            rate_hz=args.rate_hz,
            count=args.count,
            duration_s=args.duration,
            json_lines=args.json,
            token_file=args.token_file,
            idle_s=args.idle_s,
        )
    finally:
        signal.signal(signal.SIGTERM, previous)


def cmd_ctl(args: argparse.Namespace) -> int:
    return ctl_command(
        [args.ctl_first, *args.ctl_args] if args.ctl_first is not None else [],
        address=args.connect,
        token_file=args.token_file,
        json_out=args.json,
        reference_dph=args.reference_dph,
        timeout_s=args.timeout,
        dwell_s=args.dwell,
        angle_start_deg=args.angle_start,
    )


def add_watch(p: argparse.ArgumentParser) -> None:
    """``fog-driver watch``: its arguments and its function."""
    p.add_argument(
        "address",
        nargs="?",
        metavar="HOST:PORT",
        help="the daemon's client address (default 127.0.0.1:2948; also HOST, :PORT, [IPV6]:PORT)",
    )
    p.add_argument(
        "--rate-hz",
        type=watch_rate_hz,
        default=10.0,
        metavar="R",
        help="ANGLE updates a second to ask the daemon for, > 0 and at most 10000 (default 10)",
    )
    p.add_argument("--count", type=positive_int, metavar="N", help="stop after N ANGLE updates")
    p.add_argument("--duration", type=positive_float, metavar="S", help="stop after S seconds")
    p.add_argument(
        "--idle-s",
        type=positive_float,
        metavar="S",
        help="end with exit 75 after S seconds without a sample (default 10 with --count or --duration; "
        "without them it waits on, unless given)",
    )
    p.add_argument("--connect", metavar="HOST:PORT", help="the daemon's client address (as the positional HOST:PORT)")
    p.add_argument(
        "--json",
        action="store_true",
        help="print the daemon's NDJSON lines unchanged, one per line, flushed (like gpspipe -w)",
    )
    p.add_argument(
        "--token-file",
        metavar="FILE",
        help="read the daemon's client token from FILE's first line (default: $FOG_DRIVER_TOKEN)",
    )
    p.set_defaults(func=cmd_watch)


def add_ctl(p: argparse.ArgumentParser) -> None:
    """``fog-driver ctl``: its arguments, the exit statuses in its description, and its function."""
    p.description = (
        "zero | bias [SECONDS] | adapt on|off | table ANGLE | reload | status | save, after the daemon's "
        "HOST:PORT when given (as watch takes it; or --connect).  Exit 0 done; 64 bad arguments or unknown to "
        "the daemon; 65 refused or the bias capture failed; 69 unreachable or the connection lost; 77 the "
        "token refused or needed."
    )
    p.usage = "%(prog)s [options] [HOST:PORT] COMMAND [ARG ...]"
    p.add_argument(
        "ctl_first",
        nargs="?",
        metavar="[HOST:PORT] COMMAND",
        help="the daemon's client address (default 127.0.0.1:2948; also HOST, :PORT, [IPV6]:PORT) when the first "
        "word is not a command, then COMMAND: zero, bias, adapt, table, reload, status or save",
    )
    p.add_argument(
        "ctl_args",
        nargs="*",
        metavar="ARG",
        help="bias: SECONDS (default 60, 1..86400); adapt: on or off; table: the table's ANGLE (degrees)",
    )
    p.add_argument(
        "--connect",
        metavar="HOST:PORT",
        help="the daemon's client address (as the first word HOST:PORT)",
    )
    p.add_argument(
        "--token-file",
        metavar="FILE",
        help="read the daemon's client token from FILE's first line (default: $FOG_DRIVER_TOKEN)",
    )
    p.add_argument(
        "--json", action="store_true", help="print the daemon's answer (and bias's result event) as JSON lines"
    )
    p.add_argument(
        "--reference-dph",
        type=float,
        metavar="DPH",
        help="adapt on: the known input rate while static (deg/h; default 0, a table at rest)",
    )
    p.add_argument(
        "--dwell",
        type=float,
        metavar="S",
        help="table: the seconds the table has stood at ANGLE (default 12, the least a dwell may be)",
    )
    p.add_argument(
        "--angle-start",
        type=float,
        metavar="DEG",
        help="table: the angle the dwell began at, when the table moved within it (a creep)",
    )
    p.add_argument(
        "--timeout",
        type=reply_timeout_s,
        default=35.0,
        metavar="S",
        help=f"how long to wait for the answer, > 0 and at most {MAX_REPLY_TIMEOUT_S:g} s (default 35 s; bias waits "
        "for its result besides)",
    )
    p.set_defaults(func=cmd_ctl)
