"""A controller's URL: ``SCHEME://HOST[:PORT][?OPTIONS]`` over a network, ``SCHEME:///dev/DEVICE[?OPTIONS]`` over
a serial line, ``sim://[?OPTIONS]`` in-process.

``parse_controller_url`` splits it and checks only its shape (one line, ``UsageError``, on anything else); each
driver then takes the options it knows with ``ControllerURL.take`` and refuses the rest with ``refuse_unknown``,
so a misspelt option is an error, never silently ignored.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TypeVar
from urllib.parse import parse_qsl, urlsplit

from ...errors import UsageError

T = TypeVar("T")

MAX_URL_CHARS = 2048


@dataclass
class ControllerURL:
    """A parsed controller URL.  ``host``/``port``: a network controller (port None: the scheme's default);
    ``device``: a serial one (``/dev/ttyUSB1``); ``options``: the query, one value per name."""

    text: str
    scheme: str
    host: str | None
    port: int | None
    device: str | None
    options: dict[str, str] = field(default_factory=dict)

    def take(self, name: str, convert: Callable[[str], T], default: T) -> T:
        """Remove option ``name`` and return it converted (``convert`` raises ``ValueError`` on a bad value,
        which becomes a one-line ``UsageError``), or ``default`` when the URL does not give it."""
        if name not in self.options:
            return default
        raw = self.options.pop(name)
        try:
            return convert(raw)
        except ValueError as exc:
            detail = f": {exc}" if str(exc) else ""
            raise UsageError(f"controller URL {self.text}: bad {name}={raw!r}{detail}") from None

    def refuse_unknown(self, known: str) -> None:
        """A ``UsageError`` naming the options left untaken (``known``: the driver's options, for the message)."""
        if self.options:
            names = ", ".join(sorted(self.options))
            raise UsageError(f"controller URL {self.text}: unknown option {names} (this scheme takes: {known})")

    def where(self, default_port: int | None) -> str:
        """``HOST:PORT`` or the device path, for messages and the lock's key."""
        if self.device is not None:
            return self.device
        return f"{self.host}:{self.port if self.port is not None else default_port}"


def parse_controller_url(text: str) -> ControllerURL:
    """Split ``text``; a ``UsageError`` if it is not ``SCHEME://...`` with a host or a device path."""
    if len(text) > MAX_URL_CHARS:
        raise UsageError(f"controller URL longer than {MAX_URL_CHARS} characters")
    if "://" not in text:
        raise UsageError(f"controller URL {text!r}: not SCHEME://HOST[:PORT] or SCHEME:///dev/DEVICE")
    parts = urlsplit(text)
    scheme = parts.scheme.lower()
    if not scheme:
        raise UsageError(f"controller URL {text!r}: no scheme")
    try:
        pairs = parse_qsl(parts.query, keep_blank_values=True, strict_parsing=bool(parts.query))
    except ValueError:
        raise UsageError(f"controller URL {text}: the options are not NAME=VALUE&...") from None
    options: dict[str, str] = {}
    for name, value in pairs:
        if name in options:
            raise UsageError(f"controller URL {text}: option {name} given twice")
        options[name] = value
    if parts.fragment:
        raise UsageError(f"controller URL {text}: a '#' has no meaning here")
    host = parts.hostname
    device = None
    port = None
    if parts.netloc:
        try:
            port = parts.port
        except ValueError:
            raise UsageError(f"controller URL {text}: the port is not a number 0..65535") from None
        if not host:
            raise UsageError(f"controller URL {text}: no host")
        if parts.path not in ("", "/"):
            raise UsageError(f"controller URL {text}: a network controller has no path ({parts.path!r})")
    elif parts.path:
        device = parts.path
    elif scheme != "sim":
        raise UsageError(f"controller URL {text}: no host and no device path")
    return ControllerURL(text=text, scheme=scheme, host=host, port=port, device=device, options=options)
