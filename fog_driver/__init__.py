"""fog_driver: instrument driver and streaming temperature-drift compensator for a fiber-optic gyro.

Importing the package imports nothing else: ``import fog_driver.client`` needs the standard library only.
``__version__`` is looked up on first use: ``importlib.metadata`` is imported only then, off the start-up path
(``benchmarks/bench_startup.py`` times the start-up).
"""

from __future__ import annotations

__all__ = ["__version__"]


def __getattr__(name: str) -> str:
    """``fog_driver.__version__``: the installed distribution's version, read once on first use."""
    if name != "__version__":
        raise AttributeError(f"module 'fog_driver' has no attribute {name!r}")
    from importlib.metadata import PackageNotFoundError, version  # start-up time

    try:
        value = version("fog_driver")
    except PackageNotFoundError:  # running from a source tree that is not installed
        value = "0.0.0+unknown"
    globals()["__version__"] = value
    return value
