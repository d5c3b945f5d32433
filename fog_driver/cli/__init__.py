"""The ``fog-driver`` command line.

``main`` is the command (the console script and ``python -m fog_driver`` call it with no arguments): a ``run``
defers SIGHUP first thing, before the command line's own imports (about 0.1 s; ``fog_driver.signals``); the
command itself is ``fog_driver.cli.app.main``.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence

from ..signals import defer_hangups

__all__ = ["main"]


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command ``argv`` names (default: the process's arguments) and return its exit status.

    With no ``argv`` this is the whole process: if ``run`` may be the command, SIGHUP is deferred at once (its
    default action would end the daemon while it loads); ``app.main`` undoes it for any other command."""
    if argv is None and "run" in sys.argv[1:]:
        defer_hangups()
    from .app import main as command  # start-up time: the command line's imports (structlog, argparse)

    return command(argv)
