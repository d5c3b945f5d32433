"""The daemon's protocol objects as typed, frozen values (units in the field names).

``message_from(obj, line)`` turns one parsed protocol line into an ``Angle``, ``Device``, ``Status`` or
``Version`` (both with the model in use, a ``ModelInUse``), ``Bias``, ``Reply`` (the answer to ``?WATCH``,
``?AUTH``, ``?ZERO``, ``?ADAPT``, ``?SAVE``, ``?RELOAD``), ``ErrorReply`` or, for a class this library does not
know, ``Other`` (the protocol says a client ignores classes and keys it does not know: the sample iterators do).
A value that is absent, or of the wrong type, is ``None`` in the typed field: the daemon omits absent values
rather than sending ``null``.  Every message keeps the daemon's object (``raw``) and its line as received
(``line``), for keys a newer daemon adds.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

__all__ = [
    "Angle",
    "Bias",
    "Device",
    "ErrorReply",
    "Gap",
    "Message",
    "ModelInUse",
    "Other",
    "Reply",
    "Status",
    "Version",
    "message_from",
    "since_bias_sigma_dph",
]

_EMPTY: Mapping[str, Any] = MappingProxyType({})


def _finite(value: Any) -> float | None:
    """A finite number (int or float, not bool) as float, else None (an int beyond float's range too)."""
    if not isinstance(value, (int, float)) or isinstance(value, bool):
        return None
    try:
        value = float(value)
    except OverflowError:
        return None
    return value if math.isfinite(value) else None


def _number(obj: Mapping[str, Any], key: str) -> float | None:
    return _finite(obj.get(key))


def _integer(obj: Mapping[str, Any], key: str) -> int | None:
    value = obj.get(key)
    return value if isinstance(value, int) and not isinstance(value, bool) else None


def _text(obj: Mapping[str, Any], key: str) -> str | None:
    value = obj.get(key)
    return value if isinstance(value, str) else None


def _flag(obj: Mapping[str, Any], key: str) -> bool | None:
    value = obj.get(key)
    return value if isinstance(value, bool) else None


def _numbers(obj: Mapping[str, Any], key: str) -> Mapping[str, float]:
    """A mapping of names to finite numbers (others dropped), read-only."""
    value = obj.get(key)
    if not isinstance(value, Mapping):
        return _EMPTY
    numbers = ((k, _finite(v)) for k, v in value.items() if isinstance(k, str))
    return MappingProxyType({k: v for k, v in numbers if v is not None})


def _mapping(obj: Mapping[str, Any], key: str) -> Mapping[str, Any] | None:
    value = obj.get(key)
    return MappingProxyType(dict(value)) if isinstance(value, Mapping) else None


@dataclass(frozen=True, slots=True)
class Gap:
    """Samples this client did not receive: the connection was lost and made again between ``last_seq`` and
    ``seq``.  ``missed`` is the instrument's samples in between (``seq - last_seq - 1``; with a decimated
    watch that includes those the decimation would have skipped), ``None`` when it cannot be told (the daemon
    restarted: its sequence went back).  ``down_s`` is how long the client was without a connection."""

    last_seq: int
    seq: int
    missed: int | None
    down_s: float
    reason: str


@dataclass(frozen=True, slots=True)
class _Base:
    raw: Mapping[str, Any] = field(default_factory=lambda: _EMPTY, repr=False, compare=False)  #: the daemon's object
    line: bytes = field(default=b"", repr=False, compare=False)  #: the line as received


@dataclass(frozen=True, slots=True)
class Angle(_Base):
    """One sample (``ANGLE``): the compensated angle since start (or the last ``?ZERO``), arcsec."""

    seq: int = 0  #: the sample's sequence number (monotonic while the daemon runs)
    t_s: float = 0.0  #: device time, s
    angle_arcsec: float | None = None  #: compensated, cumulative
    angle_raw_arcsec: float | None = None  #: uncompensated, cumulative
    rate_dph: float | None = None  #: compensated rate of this sample, deg/h
    rate_raw_dph: float | None = None
    #: the model's drift estimate, deg/h; None while there is none (the sample flagged ``uncompensated``: the first
    #: block of a run, after a long gap, a thermometer never valid; ``angle_arcsec`` then integrates the raw rate)
    drift_dph: float | None = None
    #: the 1-sigma of the drift estimate's error as a 1-min mean, about its mean over the run (the bias), deg/h;
    #: None while there is no estimate, and from a daemon older than protocol 1.1 (keyword-only: added in 1.1)
    drift_sigma_dph: float | None = field(default=None, kw_only=True)
    temps_c: Mapping[str, float] = field(default_factory=lambda: _EMPTY)  #: the format's temperature channels, degC
    flags: tuple[str, ...] = ()  #: e.g. gap, thermometer_fault, extrapolating
    utc: str | None = None  #: the host's UTC time when the daemon read the sample (ISO 8601)
    axes_rate_raw_dph: Mapping[str, float] | None = None  #: x, y, z (a daemon with publish_axes)
    gap_before: Gap | None = None  #: set on the first sample after a reconnect

    @property
    def angle_deg(self) -> float | None:
        return None if self.angle_arcsec is None else self.angle_arcsec / 3600.0


@dataclass(frozen=True, slots=True)
class ModelInUse:
    """The model the daemon compensates with (STATUS's and VERSION's ``model_file``, protocol 1.2): after a
    reload, the next STATUS names the new one."""

    path: str | None = None  #: the model file, an absolute path on the daemon's host
    sha256: str | None = None  #: of the file's bytes (hex)
    kind: str | None = None  #: wesn, polynomial, ...
    created_utc: str | None = None  #: when it was fitted (ISO 8601)
    serial: str | None = None  #: the instrument serial it was fitted for


def _model_file(obj: Mapping[str, Any]) -> ModelInUse | None:
    """``model_file`` as a ``ModelInUse``; None when absent (a daemon before protocol 1.2, or on a daemon with a
    token a VERSION before ``?AUTH``) or not an object."""
    value = obj.get("model_file")
    if not isinstance(value, Mapping):
        return None
    return ModelInUse(**{name: _text(value, name) for name in ("path", "sha256", "kind", "created_utc", "serial")})


@dataclass(frozen=True, slots=True)
class Version(_Base):
    """The greeting (``VERSION``)."""

    release: str | None = None
    proto_major: int | None = None
    proto_minor: int | None = None
    model: str | None = None  #: the kind of drift model in use
    instrument: Mapping[str, Any] | None = None  #: serial, firmware, rate_hz, scale_arcsec_per_count
    #: the model in use (protocol 1.2; None from an older daemon, and before ``?AUTH`` on one with a token)
    model_file: ModelInUse | None = field(default=None, kw_only=True)


@dataclass(frozen=True, slots=True)
class Device(_Base):
    """The instrument's port and identity (``DEVICE``), sent on connect and on every change."""

    path: str | None = None
    state: str | None = None  #: ``activated`` (the port is open) or ``deactivated``
    format: str | None = None  #: the frame format, e.g. fog-v1, kvh-a
    serial: str | None = None
    firmware: int | None = None
    rate_hz: float | None = None
    scale_arcsec_per_count: float | None = None
    capture: str | None = None  #: the raw capture's state

    @property
    def activated(self) -> bool:
        return self.state == "activated"


@dataclass(frozen=True, slots=True)
class Status(_Base):
    """The daemon's state (``STATUS``, every second and on ``?STATUS``); every other key is in ``raw``."""

    uptime_s: float | None = None
    port_state: str | None = None  #: open, lost, retry_wait, ...
    bytes_in: int | None = None
    frames: int | None = None
    crc_errors: int | None = None
    bytes_discarded: int | None = None
    seq_gaps: int | None = None
    missing_frames: int | None = None
    published: int | None = None
    clients: int | None = None
    dropped_clients: int | None = None
    cpu_percent: float | None = None
    rss_mb: float | None = None
    bias_dph: float | None = None
    bias_captured: bool | None = None
    adapting: bool | None = None
    capture_state: str | None = None
    capture_bytes_lost: int | None = None
    noise_1min_dph: float | None = None  #: the loaded model's gyro white noise at 1 min, deg/h (when it has one)
    #: the drift's sigma during the last ``?BIAS`` capture, sigma(t_b), deg/h (protocol 1.1; None: no capture,
    #: or no sigma then); ``since_bias_sigma_dph`` combines it with an ``Angle``'s
    bias_sigma_dph: float | None = None
    #: the model in use (protocol 1.2; None from an older daemon)
    model_file: ModelInUse | None = field(default=None, kw_only=True)


@dataclass(frozen=True, slots=True)
class Bias(_Base):
    """A ``?BIAS`` capture: its acknowledgement (``state`` ``started``) or its result (``done``, ``failed``)."""

    state: str | None = None
    capture_id: int | None = None
    seconds: float | None = None
    timeout_s: float | None = None  #: (started) the result comes within this many seconds
    bias_dph: float | None = None  #: (done) the bias now removed from rate_dph and angle_arcsec
    reason: str | None = None  #: (failed)
    bias_sigma_dph: float | None = None  #: (done) the drift's sigma during the capture, deg/h (protocol 1.1)


@dataclass(frozen=True, slots=True)
class Reply(_Base):
    """The answer to ``?WATCH``, ``?AUTH``, ``?ZERO``, ``?ADAPT``, ``?SAVE`` or ``?RELOAD``: its class (the
    command's name) and its keys."""

    kind: str = ""

    def get(self, key: str, default: Any = None) -> Any:
        return self.raw.get(key, default)


@dataclass(frozen=True, slots=True)
class ErrorReply(_Base):
    """An ``ERROR``: a refused command (``command`` names it, when the daemon says) or a protocol error."""

    message: str = ""
    command: str | None = None


@dataclass(frozen=True, slots=True)
class Other(_Base):
    """An object of a class this library does not know (a newer daemon's): ``kind`` is its class.  The
    iterators of samples skip it; ``messages()`` yields it, so a pass-through loses nothing."""

    kind: str = ""


Message = Angle | Version | Device | Status | Bias | Reply | ErrorReply | Other

_REPLY_CLASSES = frozenset({"WATCH", "AUTH", "ZERO", "ADAPT", "TABLE", "SAVE", "RELOAD"})


def since_bias_sigma_dph(drift_sigma_dph: float | None, bias_sigma_dph: float | None) -> float | None:
    """The 1-sigma of the drift error a station reads since it captured the bias at t_b (``?BIAS``)::

        sigma_since_bias(t) = sqrt(sigma(t)**2 + sigma(t_b)**2)

    ``drift_sigma_dph`` is sigma(t) (an ``Angle``'s), ``bias_sigma_dph`` sigma(t_b) (``Status``'s or the
    ``Bias`` event's): the bias captured at t_b holds the drift estimate's error then, and the two errors are
    taken as independent.  None when either is absent (or not a finite number)."""
    a, b = _finite(drift_sigma_dph), _finite(bias_sigma_dph)
    return None if a is None or b is None else math.hypot(a, b)


def message_from(obj: Mapping[str, Any], line: bytes = b"") -> Message | None:
    """The typed message of one protocol object (``class`` a string); None for an ``ANGLE`` without an
    integer ``seq`` and a finite ``t_s`` (not usable as a sample)."""
    cls = obj.get("class")
    base: dict[str, Any] = {"raw": MappingProxyType(dict(obj)), "line": bytes(line)}
    if cls == "ANGLE":
        seq, t_s = _integer(obj, "seq"), _number(obj, "t_s")
        if seq is None or t_s is None:
            return None
        flags = obj.get("flags")
        flags = tuple(f for f in flags if isinstance(f, str)) if isinstance(flags, list) else ()
        axes = _numbers(obj, "axes_rate_raw_dph") if "axes_rate_raw_dph" in obj else None
        return Angle(
            **base,
            seq=seq,
            t_s=t_s,
            angle_arcsec=_number(obj, "angle_arcsec"),
            angle_raw_arcsec=_number(obj, "angle_raw_arcsec"),
            rate_dph=_number(obj, "rate_dph"),
            rate_raw_dph=_number(obj, "rate_raw_dph"),
            drift_dph=_number(obj, "drift_dph"),
            drift_sigma_dph=_number(obj, "drift_sigma_dph"),
            temps_c=_numbers(obj, "temps_c"),
            flags=flags,
            utc=_text(obj, "utc"),
            axes_rate_raw_dph=axes,
        )
    if cls == "STATUS":
        fields = {name: _read(obj, name, kind) for name, kind in _STATUS_FIELDS}
        return Status(**base, **fields, model_file=_model_file(obj))
    if cls == "DEVICE":
        return Device(
            **base,
            path=_text(obj, "path"),
            state=_text(obj, "state"),
            format=_text(obj, "format"),
            serial=_text(obj, "serial"),
            firmware=_integer(obj, "firmware"),
            rate_hz=_number(obj, "rate_hz"),
            scale_arcsec_per_count=_number(obj, "scale_arcsec_per_count"),
            capture=_text(obj, "capture"),
        )
    if cls == "VERSION":
        return Version(
            **base,
            release=_text(obj, "release"),
            proto_major=_integer(obj, "proto_major"),
            proto_minor=_integer(obj, "proto_minor"),
            model=_text(obj, "model"),
            instrument=_mapping(obj, "instrument"),
            model_file=_model_file(obj),
        )
    if cls == "BIAS":
        return Bias(
            **base,
            state=_text(obj, "state"),
            capture_id=_integer(obj, "capture_id"),
            seconds=_number(obj, "seconds"),
            timeout_s=_number(obj, "timeout_s"),
            bias_dph=_number(obj, "bias_dph"),
            reason=_text(obj, "reason"),
            bias_sigma_dph=_number(obj, "bias_sigma_dph"),
        )
    if cls == "ERROR":
        return ErrorReply(**base, message=_text(obj, "message") or "", command=_text(obj, "command"))
    if cls in _REPLY_CLASSES:
        return Reply(**base, kind=cls)
    return Other(**base, kind=str(cls))


_STATUS_FIELDS = (
    ("uptime_s", float),
    ("port_state", str),
    ("bytes_in", int),
    ("frames", int),
    ("crc_errors", int),
    ("bytes_discarded", int),
    ("seq_gaps", int),
    ("missing_frames", int),
    ("published", int),
    ("clients", int),
    ("dropped_clients", int),
    ("cpu_percent", float),
    ("rss_mb", float),
    ("bias_dph", float),
    ("bias_captured", bool),
    ("adapting", bool),
    ("capture_state", str),
    ("capture_bytes_lost", int),
    ("noise_1min_dph", float),
    ("bias_sigma_dph", float),
)


def _read(obj: Mapping[str, Any], key: str, kind: type) -> Any:
    if kind is float:
        return _number(obj, key)
    if kind is int:
        return _integer(obj, key)
    if kind is bool:
        return _flag(obj, key)
    return _text(obj, key)
