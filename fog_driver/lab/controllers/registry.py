"""The controller schemes: a URL's scheme names the driver that opens it (``open_controller``).

Each driver module has ``open_controller(url: ControllerURL, *, overrides, on_notice, timeout_s)`` returning a
``ChamberController`` (not yet connected); it takes the URL's options it knows and refuses the rest.  Drivers
are imported when their scheme is opened (the ``lab`` extra's pymodbus is needed only by the simulated lab).
``sim://`` is served by the simulator (``fog_driver.sim``, a layer above this one): the caller passes its
opener in ``extra_schemes``.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from typing import Any

from ...errors import UsageError
from .base import ChamberController, Notice
from .url import ControllerURL, parse_controller_url

#: scheme -> (driver module under fog_driver.lab.controllers, what it drives)
SCHEMES: dict[str, tuple[str, str]] = {
    "watlow-f4t": ("watlow", "Watlow F4T over Modbus TCP"),
    "watlow-f4t+rtu": ("watlow", "Watlow F4T over Modbus RTU (serial)"),
    "espec": ("espec", "Espec P300 / SCP-220 (ASCII over TCP or serial)"),
    "thermotron": ("thermotron", "Thermotron 8800 / 8200 (ASCII over TCP)"),
    "simserv": ("simserv", "Weiss / Voetsch SIMSERV (TCP)"),
}

Opener = Callable[..., ChamberController]

DEFAULT_TIMEOUT_S = 2.0


def _ignore(_line: str) -> None:
    return None


def open_controller(
    text: str,
    *,
    overrides: Mapping[str, Any] | None = None,
    on_notice: Notice = _ignore,
    timeout_s: float = DEFAULT_TIMEOUT_S,
    extra_schemes: Mapping[str, Opener] | None = None,
) -> ChamberController:
    """The controller ``text`` names, not yet connected; ``UsageError`` (one line) on an unknown scheme or option.
    ``overrides``: settings from a config file (register addresses, word order), under the URL's options."""
    url: ControllerURL = parse_controller_url(text)
    extra = dict(extra_schemes or {})
    if url.scheme in extra:
        return extra[url.scheme](url, overrides=dict(overrides or {}), on_notice=on_notice, timeout_s=timeout_s)
    if url.scheme not in SCHEMES:
        known = ", ".join(sorted([*SCHEMES, *extra]))
        raise UsageError(f"controller URL {text}: unknown scheme {url.scheme!r} (known: {known})")
    module = importlib.import_module(f"{__package__}.{SCHEMES[url.scheme][0]}")
    opener: Opener = module.open_controller
    return opener(url, overrides=dict(overrides or {}), on_notice=on_notice, timeout_s=timeout_s)
