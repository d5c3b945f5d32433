"""The ``fog-driver`` command line: thin subcommands that parse, call the library, and print.

Errors the user can act on are printed as one line on stderr with a non-zero
exit status (see ``fog_driver.errors``); they never show a traceback.  Any other
exception is a bug: one line ``fog-driver: error: internal error: <type>: <message>``,
exit 70 (EX_SOFTWARE), and its traceback in the log on stderr.

The commands live by group: ``captures`` (inspect, record, simulate), ``plan`` (plan), ``calibration`` (fit,
compensate, evaluate), ``daemon`` (run), ``tools`` (watch, ctl); ``parser`` holds the argument tree.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence

import structlog

from ..console import configure_logging
from ..errors import FogDriverError, InternalError
from ..signals import defer_hangups, undefer_hangups
from .parser import build_parser, command_in


def main(argv: Sequence[str] | None = None) -> int:
    """Parse ``argv`` (default: the process's arguments), run the command, and return the exit status.

    With no ``argv`` this is the whole process (the ``fog-driver`` command, ``python -m fog_driver``): ``run``
    then defers SIGHUP before its modules load (its default action would end the daemon while it loads; see
    ``fog_driver.signals.defer_hangups``).  Called with ``argv`` (in-process) no signal handler is touched here."""
    whole_process = argv is None
    argv = sys.argv[1:] if argv is None else list(argv)
    command = command_in(argv)
    if whole_process and command == "run":
        defer_hangups()  # before the daemon's modules load (about 0.4 s); fog_driver.cli.main may have already
    elif whole_process:
        undefer_hangups()  # "run" was only a word (a file's name): SIGHUP's default action again
    parser = build_parser([] if command is None else [command])
    args = parser.parse_args(argv)
    configure_logging(args.verbose, args.log_format)
    try:
        return args.func(args)
    except FogDriverError as exc:
        print(f"fog-driver: error: {exc}", file=sys.stderr)
        return exc.exit_status
    except KeyboardInterrupt:
        print("fog-driver: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        # The reader of our output went away (e.g. `| head`); nothing more to say.
        sys.stderr.close()
        return 0
    except Exception as exc:  # a bug: the traceback goes to the log, one line to the user, exit 70
        structlog.get_logger("fog_driver").exception("internal_error", command=args.command)
        error = InternalError.from_exception(exc)
        print(f"fog-driver: error: {error}", file=sys.stderr)
        return error.exit_status


if __name__ == "__main__":
    sys.exit(main())
