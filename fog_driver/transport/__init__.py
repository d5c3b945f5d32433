"""Transport layer: opening ports, reading them through unplugs, device setup on open, the ``replay://`` URL
and a pty helper.

Importing this package registers it with pyserial (``serial.protocol_handler_packages``),
so ``serial.serial_for_url("replay://capture.bin?rate=1000")`` finds
``fog_driver.transport.protocol_replay``.  Layering: this package may import
``fog_driver.protocol`` and nothing above it.
"""

from __future__ import annotations

import serial

_HANDLER_PACKAGE = "fog_driver.transport"
if _HANDLER_PACKAGE not in serial.protocol_handler_packages:  # idempotent across re-imports
    serial.protocol_handler_packages.append(_HANDLER_PACKAGE)

from .port import (  # noqa: E402
    DEFAULT_BAUDRATE,
    DEFAULT_SILENCE_S,
    PortError,
    PortEvent,
    PortReader,
    PortSetupError,
    PortState,
    open_port,
)
from .protocol_replay import ReplayOptions, parse_replay_url, replay_schedule  # noqa: E402
from .setup import DeviceSetup, DeviceSetupError, InvalidSetupCommand, SetupResult, make_on_open, run_setup  # noqa: E402

__all__ = [
    "DEFAULT_BAUDRATE",
    "DEFAULT_SILENCE_S",
    "DeviceSetup",
    "DeviceSetupError",
    "InvalidSetupCommand",
    "PortError",
    "PortEvent",
    "PortReader",
    "PortSetupError",
    "PortState",
    "ReplayOptions",
    "SetupResult",
    "make_on_open",
    "open_port",
    "parse_replay_url",
    "replay_schedule",
    "run_setup",
]

try:  # POSIX only (os.openpty, termios)
    from .pty import PtyPair  # noqa: E402
except ImportError:  # pragma: no cover - non-POSIX
    pass
else:
    __all__ += ["PtyPair"]
