"""fog_driver: instrument driver and streaming temperature-drift compensator for a fiber-optic gyro."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("fog_driver")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0+unknown"
