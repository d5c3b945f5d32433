"""Driver configuration: a YAML file read with ``yaml.safe_load`` only, checked against ``DriverConfig``.

``configs/default.yaml`` lists every key with its default.  The document's shape (unknown keys, types,
finite numbers) is checked by a msgspec schema derived from the dataclasses below
(``files.typed_mapping``); their ``__post_init__`` checks the ranges.  Unknown keys are errors, so a typo
never silently falls back to a default; every problem is one line naming the file and the key path
(``badval.yaml: baud: expected an integer, got 'fast'``).  ``fog-driver run`` flags override the file.
"""

from __future__ import annotations

import ipaddress
import math
import re
from dataclasses import dataclass, field
from importlib.resources import files
from pathlib import Path
from typing import Any

from ..client.address import DEFAULT_PORT, parse_host_port
from ..client.address import format_address as format_address  # re-exported: service.py reads it here
from ..errors import InputFileError, UsageError
from ..files.typed_mapping import dataclass_from_mapping
from ..files.yamlio import read_yaml
from ..lab.controllers.registry import SCHEMES
from ..lab.controllers.url import parse_controller_url
from ..samples.sources import WireSettings
from ..samples.stream import DEFAULT_SCALE_ARCSEC_PER_COUNT, SampleStream
from ..transport.port import DEFAULT_SILENCE_S, check_silence_s
from ..transport.setup import DeviceSetup, validate_command

#: The shipped drift model (``fog_driver/data/models/default.yaml``): package data, so a wheel or any
#: other install finds it as a source checkout does.
DEFAULT_MODEL = Path(str(files("fog_driver").joinpath("data", "models", "default.yaml")))

#: A token's minimum length: a shorter one is accepted with a warning this release (``token_warnings``), and
#: one under ``TOKEN_REFUSED_BELOW_CHARS`` is refused.
TOKEN_MIN_CHARS = 16
TOKEN_REFUSED_BELOW_CHARS = 8


def token_warnings(token: str | None) -> list[str]:
    """The warning a token shorter than ``TOKEN_MIN_CHARS`` gets at start (none for a long enough one)."""
    if token is None or len(token) >= TOKEN_MIN_CHARS:
        return []
    return [
        f"the client token has {len(token)} characters; the minimum is now {TOKEN_MIN_CHARS} "
        "(accepted in this release, refused in the next): make one with `openssl rand -hex 16`"
    ]


#: The web view's port when ``http`` gives a host only.
DEFAULT_HTTP_PORT = 8948

#: A DNS name ``http_hosts`` may list: dot-separated labels of letters, digits and inner hyphens.
_HOST_NAME = re.compile(
    r"(?=.{1,253}\.?$)([a-z0-9]([a-z0-9-]{0,61}[a-z0-9])?)(\.[a-z0-9]([a-z0-9-]{0,61}[a-z0-9])?)*\.?", re.I
)


def _check_http_host(name: str) -> None:
    """ValueError unless ``name`` is a DNS name or an IP address (``http_hosts``)."""
    try:
        ipaddress.ip_address(name.strip("[]"))
        return
    except ValueError:
        pass
    if not _HOST_NAME.fullmatch(name):
        raise ValueError(
            f"http_hosts: {name!r} is not a host name (letters, digits, hyphens and dots) or an IP address"
        )


def _check_proxy(entry: str) -> None:
    """ValueError unless ``entry`` is an IP address or network (``http_trusted_proxies``)."""
    try:
        ipaddress.ip_network(entry.strip(), strict=False)
    except ValueError:
        raise ValueError(
            f"http_trusted_proxies: {entry!r} is not an IP address or network (10.0.0.5, 10.1.0.0/16, ::1)"
        ) from None


@dataclass(frozen=True)
class DeviceConfig:
    """How the instrument is set, for a frame format whose frames do not say it (``format`` other than
    fog-v1): ``sources.WireSettings``'s keys, and the commands sent to the device on every open."""

    rate_hz: int | None = None  #: the device's output rate (KVH ``=DR``), Hz
    rot_format: str = "delta"  #: KVH ``=ROTFMT``: delta (angle increments) or rate
    rot_units: str = "rad"  #: KVH ``=ROTUNITS``: rad or deg
    temp_units: str = "c"  #: KVH ``=TEMPUNITS``: c (whole degC) or c_100 (0.01 degC)
    serial: str = ""  #: the instrument's serial number (a model records the serial it was fitted on)
    setup: tuple[str, ...] = ()  #: commands sent on every open (KVH: inside =CONFIG,1 ... =CONFIG,0)
    setup_reply_timeout_s: float = 1.0  #: how long to wait for the device's answer to each setup command

    def __post_init__(self) -> None:
        for command in self.setup:
            validate_command(command)  # InvalidSetupCommand is a ValueError: "config: device: setup command ..."
        if not 0 < self.setup_reply_timeout_s <= 30:
            raise ValueError("setup_reply_timeout_s must be in (0, 30] s")

    def device_setup(self):
        """``transport.setup.DeviceSetup`` of the commands, or None when there are none."""
        return DeviceSetup(commands=self.setup, reply_timeout_s=self.setup_reply_timeout_s) if self.setup else None


#: The daemon's chamber poll period when ``chamber.poll_s`` is not given, and its bounds (s).
DEFAULT_CHAMBER_POLL_S = 5.0
CHAMBER_POLL_RANGE_S = (0.5, 3600.0)


@dataclass(frozen=True)
class ChamberConfig:
    """The daemon's read-only chamber (the ``chamber:`` section): the controller's URL (``fog-driver chamber
    status URL``'s), how often its air and set point are read (``poll_s``), and the driver's settings from a
    file (``overrides``: register addresses, word order...; the URL's options win over them).  The daemon only
    reads: it never writes a set point."""

    url: str = ""
    poll_s: float = DEFAULT_CHAMBER_POLL_S
    overrides: dict[str, str | bool | int | float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not self.url:
            raise ValueError("url: the chamber controller's URL is needed (watlow-f4t://HOST, espec://HOST, sim://)")
        try:
            scheme = parse_controller_url(self.url).scheme
        except UsageError as exc:
            raise ValueError(f"url: {exc}") from None
        if scheme not in SCHEMES and scheme != "sim":
            known = ", ".join(sorted([*SCHEMES, "sim"]))
            raise ValueError(f"url: {self.url}: unknown scheme {scheme!r} (known: {known})")
        low, high = CHAMBER_POLL_RANGE_S
        if not low <= self.poll_s <= high:
            raise ValueError(f"poll_s must be in [{low:g}, {high:g}] s, got {self.poll_s!r}")


@dataclass(frozen=True)
class DriverConfig:
    """Every setting of the driver and the daemon (``configs/default.yaml`` documents each)."""

    port: str | None = None  #: device path or URL; None: none (``fog-driver run`` needs ``--port``, or ``--simulate``)
    baud: int = 460800
    #: a network port (socket://, rfc2217://) silent this long after bytes is taken as lost (None: never)
    port_silence_s: float | None = DEFAULT_SILENCE_S
    scale_arcsec_per_count: float = DEFAULT_SCALE_ARCSEC_PER_COUNT
    scale_override_arcsec_per_count: float | None = None
    model: str | None = None  #: model file; None: the shipped default
    listen: str = f"127.0.0.1:{DEFAULT_PORT}"
    token: str | None = None  #: needed to read and to control (both listeners); required beyond loopback
    open_stream: bool = False  #: with a token, ANGLE (alone) is open to clients without it, on both listeners
    udp: str | None = None  #: HOST:PORT to send one datagram per sample to (None: off)
    udp_version: int = 1  #: the datagram's layout: 1 (68 bytes) or 2 (72: with drift_sigma_dph)
    http: str | None = None  #: HOST:PORT of the web view and /metrics (None: off); beyond loopback needs token
    http_history_min: float = 60.0  #: minutes of plots the web view keeps
    http_hosts: tuple[str, ...] = ()  #: names the web view answers to (Host), beyond its address and localhost
    http_trusted_proxies: tuple[str, ...] = ()  #: addresses whose X-Forwarded-For is believed (a reverse proxy)
    http_secure_cookies: bool = False  #: TLS is in front (a proxy): Secure cookies, https origins
    capture_dir: str = "fog-captures"
    capture_rotate_mb: float = 256.0
    capture_rotate_s: float = 3600.0
    capture_keep_days: float | None = None  #: delete captures older than this (None: keep them all)
    capture_max_gb: float | None = None  #: delete the oldest captures beyond this total (None: no limit)
    status_every_s: float = 1.0
    max_client_backlog_s: float = 2.0
    adapt_reference_dph: float | None = None  #: adapt from the start against this rate (None: frozen)
    adapt_state: str | None = None  #: restore the adaptation state from here at start, save it here
    force_model: bool = False  #: apply the model even when it was fitted for another instrument serial
    format: str = "fog-v1"  #: the instrument's frame format (``formats.registry.FORMATS``), or auto: sniffed
    axis: str = "z"  #: the instrument's angle axis, for a format with three (x, y or z)
    device: DeviceConfig = DeviceConfig()  #: the device's settings, for a format other than fog-v1
    publish_axes: bool = False  #: ANGLE carries the three axes' raw rates (a three-axis format's)
    chamber: ChamberConfig | None = None  #: a chamber to log read-only beside the capture (None: none)

    def __post_init__(self) -> None:
        if self.port is not None and not self.port:
            raise ValueError("port must be a device path or URL string")
        if not 50 <= self.baud <= 12_000_000:
            raise ValueError(f"baud must be an integer baud rate, got {self.baud!r}")
        self._check_port_silence()
        for name in ("scale_arcsec_per_count", "scale_override_arcsec_per_count"):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number of arcsec per count, got {value!r}")
        for name in ("capture_rotate_mb", "capture_rotate_s", "status_every_s", "max_client_backlog_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0")
        for name in ("capture_keep_days", "capture_max_gb"):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number (or null: no limit), got {value!r}")
        parse_host_port(self.listen)
        if self.udp is not None:
            parse_host_port(self.udp, allow_zero=False)
        if self.udp_version not in (1, 2):
            raise ValueError(f"udp_version must be 1 or 2, got {self.udp_version!r}")
        if self.http is not None:
            parse_host_port(self.http, default_port=DEFAULT_HTTP_PORT)
        if not (math.isfinite(self.http_history_min) and 0 < self.http_history_min <= 24 * 60):
            raise ValueError(f"http_history_min must be in (0, 1440] minutes, got {self.http_history_min!r}")
        for name in self.http_hosts:
            _check_http_host(name)
        for entry in self.http_trusted_proxies:
            _check_proxy(entry)
        if self.token is not None and len(self.token) < TOKEN_REFUSED_BELOW_CHARS:
            raise ValueError(f"token must be at least {TOKEN_REFUSED_BELOW_CHARS} characters")
        if self.format != "auto":
            self.wire_settings(self.format)  # a format other than fog-v1 needs device.rate_hz, ...
        if self.device.setup and not self.format.startswith("kvh-"):
            raise ValueError(
                f"device.setup: setup commands are sent to a KVH device (format kvh-a, kvh-b or kvh-c), "
                f"not with format {self.format}"
            )

    def _check_port_silence(self) -> None:
        """``port_silence_s``: null, or seconds > 0 and, when ``device.rate_hz`` says the device's rate, at least
        two of its frame periods (a shorter silence is the device's own pace, not a lost connection)."""
        silence_s = self.port_silence_s
        check_silence_s(silence_s, "port_silence_s")
        rate_hz = self.device.rate_hz
        if silence_s is not None and isinstance(rate_hz, int) and rate_hz > 0 and silence_s * rate_hz < 2:
            raise ValueError(
                f"port_silence_s {silence_s:g} s is shorter than two frame periods at device.rate_hz {rate_hz} "
                f"({2 / rate_hz:g} s): the device's own pace would be taken for a lost connection"
            )

    def wire_settings(self, name: str | None = None):
        """``sources.WireSettings`` of the configured format (``name``: the one the bytes showed, for auto)."""
        name = name or self.format
        d = self.device
        try:
            return WireSettings(
                format=name,
                axis=self.axis,
                rate_hz=d.rate_hz,
                rot_format=d.rot_format,
                rot_units=d.rot_units,
                temp_units=d.temp_units,
                serial=d.serial,
            )
        except ValueError as exc:
            where = "" if str(exc).startswith(("format", "axis")) else "device."
            raise ValueError(f"{where}{exc}") from None

    def sample_stream(self) -> SampleStream:
        """A ``SampleStream`` applying this configuration's scale-factor rule."""
        return SampleStream(self.scale_arcsec_per_count, self.scale_override_arcsec_per_count)

    @property
    def model_path(self) -> Path:
        return Path(self.model) if self.model else DEFAULT_MODEL


def parse_config(doc: Any, where: str = "config") -> DriverConfig:
    """Validate a parsed YAML document into a ``DriverConfig`` (one-line ``InputFileError``s)."""
    if doc is None:
        return DriverConfig()
    if not isinstance(doc, dict):
        raise InputFileError(f"{where}: expected a YAML mapping of settings")
    return dataclass_from_mapping(DriverConfig, doc, where)


def load_config(path: str | Path) -> DriverConfig:
    """Read and validate a config file; every problem is a one-line ``InputFileError``."""
    return parse_config(read_yaml(path, "config file"), str(path))
