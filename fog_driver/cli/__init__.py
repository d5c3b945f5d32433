"""The ``fog-driver`` command line."""

from .app import main

__all__ = ["main"]
