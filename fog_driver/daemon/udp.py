"""Optional UDP datagrams, one per sample: the daemon's sender.  The layout and its decoder are
``fog_driver.client.udp`` (re-exported here).

The sender never blocks and never raises on a failed send (no listener, a full
socket buffer, an unreachable network, a name that does not resolve yet):
failures are counted in ``send_errors``.  A destination name is resolved when
the publisher is made; if that fails (the network is not up yet), it is tried
again in a background thread, at most every ``retry_resolve_s``, while the
samples meanwhile are counted as send errors.  IPv4 sockets have
``SO_BROADCAST`` set, so a broadcast destination (``255.255.255.255``, a
subnet's ``x.y.z.255``) works like any other.
"""

from __future__ import annotations

import math
import socket
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from typing import Any, Self

from ..client.udp import (
    DATAGRAM_FORMAT,
    DATAGRAM_SIZE,
    DATAGRAM_STRUCT,
    DATAGRAM_V2_FORMAT,
    DATAGRAM_V2_SIZE,
    DATAGRAM_V2_STRUCT,
    DATAGRAM_VERSION,
    DATAGRAM_VERSIONS,
    FIELDS,
    FIELDS_V2,
    MAGIC,
    decode_datagram,
)
from ..flags import FLAG_BITS

__all__ = [
    "DATAGRAM_FORMAT",
    "DATAGRAM_SIZE",
    "DATAGRAM_STRUCT",
    "DATAGRAM_V2_FORMAT",
    "DATAGRAM_V2_SIZE",
    "DATAGRAM_V2_STRUCT",
    "DATAGRAM_VERSION",
    "DATAGRAM_VERSIONS",
    "FIELDS",
    "FIELDS_V2",
    "MAGIC",
    "UdpPublisher",
    "decode_datagram",
    "encode_datagram",
    "fields_from_angle",
]

_FLOAT_FIELDS = FIELDS_V2[2:]
_NAN = math.nan


def _f(value: Any) -> float:
    return _NAN if value is None else float(value)


def _layout(version: int) -> Any:
    """The ``struct.Struct`` of a datagram version; ValueError for a version this module does not send."""
    layout = DATAGRAM_VERSIONS.get(version)
    if layout is None:
        raise ValueError(f"UDP datagram version must be one of {sorted(DATAGRAM_VERSIONS)}, got {version!r}")
    return layout


def encode_datagram(
    *,
    seq: int,
    t_s: float | None = None,
    angle_arcsec: float | None = None,
    angle_raw_arcsec: float | None = None,
    rate_dph: float | None = None,
    drift_dph: float | None = None,
    t_top_c: float | None = None,
    t_bottom_c: float | None = None,
    t_housing_c: float | None = None,
    flags: int = 0,
    drift_sigma_dph: float | None = None,
    version: int = DATAGRAM_VERSION,
) -> bytes:
    """One datagram of layout ``version`` (1: ``drift_sigma_dph`` is not sent; 2: appended); None (absent)
    becomes NaN, ``seq`` is taken modulo 2**64, ``flags`` modulo 2**16."""
    layout = _layout(version)
    values = [
        MAGIC,
        version,
        int(flags) & 0xFFFF,
        int(seq) & 0xFFFF_FFFF_FFFF_FFFF,
        _f(t_s),
        _f(angle_arcsec),
        _f(angle_raw_arcsec),
        _f(rate_dph),
        _f(drift_dph),
        _f(t_top_c),
        _f(t_bottom_c),
        _f(t_housing_c),
    ]
    if version >= 2:
        values.append(_f(drift_sigma_dph))
    return layout.pack(*values)


def fields_from_angle(obj: Mapping[str, Any]) -> dict:
    """The datagram fields of an ANGLE object (a mapping; keys absent or None become NaN, others are ignored).

    Thermometers come from ``t_top_c``/``t_bottom_c``/``t_housing_c`` or from a
    ``temps_c`` mapping with ``top``/``bottom``/``housing``; ``flags`` is an int
    or a list of flag names (unknown names are ignored).  ``seq`` is required.
    """
    fields = {name: obj.get(name) for name in _FLOAT_FIELDS}
    temps = obj.get("temps_c")
    if isinstance(temps, Mapping):
        for key in ("top", "bottom", "housing"):
            if fields[f"t_{key}_c"] is None:
                fields[f"t_{key}_c"] = temps.get(key)
    flags = obj.get("flags") or 0
    if not isinstance(flags, int):
        flags = sum(FLAG_BITS.get(name, 0) for name in set(flags))
    return {"seq": obj["seq"], "flags": flags, **fields}


class UdpPublisher:
    """Sends one datagram per sample to ``(host, port)``, unicast or broadcast.

    ``send(angle_obj)`` takes an ANGLE object (see :func:`fields_from_angle`),
    ``send(**fields)`` the keyword fields of :func:`encode_datagram`, in layout ``version`` (1, the default,
    or 2: with ``drift_sigma_dph``).  It never
    blocks nor raises on a network failure; ``sent`` and ``send_errors`` count
    datagrams, ``last_error`` describes the last failure (``status_fields()``
    gives all three for a STATUS object).

    ``host`` is resolved now; a name that does not resolve yet is retried in the
    background at most every ``retry_resolve_s`` of ``clock`` (each sample until
    then is a send error).  ``resolved`` is set once the destination is known,
    ``address`` is it (None until then).  ``broadcast`` sets ``SO_BROADCAST`` on
    an IPv4 socket (a unicast destination is unaffected by it).
    """

    def __init__(
        self,
        host: str,
        port: int,
        *,
        broadcast: bool = True,
        retry_resolve_s: float = 5.0,
        clock: Callable[[], float] = time.monotonic,
        version: int = DATAGRAM_VERSION,
    ) -> None:
        _layout(version)  # ValueError now, not at the first sample
        self.version = version
        self.host = host
        self.port = port
        self.broadcast = broadcast
        self.retry_resolve_s = retry_resolve_s
        self.sent = 0
        self.send_errors = 0
        self.last_error: str | None = None
        self.resolved = threading.Event()
        self._clock = clock
        self._destination: tuple[socket.socket, Any] | None = None  # (socket, address), set once
        self._resolver: threading.Thread | None = None
        self._next_resolve_at = 0.0
        self._closed = False
        self._lock = threading.Lock()
        self._resolve()

    @property
    def address(self) -> Any:
        """The resolved destination (a ``sockaddr`` tuple), or None while the name does not resolve."""
        destination = self._destination
        return destination[1] if destination is not None else None

    def status_fields(self) -> dict[str, Any]:
        """``udp_sent``, ``udp_send_errors`` and (after a failure) ``udp_last_error``, for STATUS."""
        fields: dict[str, Any] = {"udp_sent": self.sent, "udp_send_errors": self.send_errors}
        if self.last_error is not None:
            fields["udp_last_error"] = self.last_error
        return fields

    def _resolve(self) -> None:
        """Resolve the destination and open its socket; on failure note why and when to try again."""
        self._next_resolve_at = self._clock() + self.retry_resolve_s
        try:
            family, socktype, proto, _, address = socket.getaddrinfo(self.host, self.port, type=socket.SOCK_DGRAM)[0]
            sock = socket.socket(family, socktype, proto)
        except OSError as exc:  # socket.gaierror: no such name (yet), no network
            self.last_error = f"cannot resolve {self.host}:{self.port}: {exc.strerror or exc}"
            return
        sock.setblocking(False)
        if self.broadcast and family == socket.AF_INET:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)
        with self._lock:  # against a close() meanwhile
            if not self._closed:
                self._destination = (sock, address)
                self.resolved.set()
                return
        sock.close()

    def _resolve_in_background(self) -> None:
        """Start one resolver thread if none is running and the retry delay has passed (never blocks)."""
        if self._closed or self._clock() < self._next_resolve_at:
            return
        if self._resolver is not None and self._resolver.is_alive():
            return
        self._resolver = threading.Thread(target=self._resolve, name="udp-resolve", daemon=True)
        self._resolver.start()

    def send(self, angle_obj: Mapping[str, Any] | None = None, /, **fields: Any) -> bool:
        """Send one sample; True when the datagram left, False (counted) when sending failed."""
        if angle_obj is not None:
            fields = {**fields_from_angle(angle_obj), **fields}
        return self.send_bytes(encode_datagram(**fields, version=self.version))

    def send_many(self, objs: Iterable[Mapping[str, Any]]) -> int:
        """Send one datagram per ANGLE object; returns how many left."""
        return sum(self.send(o) for o in objs)

    def send_bytes(self, datagram: bytes) -> bool:
        """Send one datagram; True when it left, False (counted in ``send_errors``) when it did not."""
        destination = self._destination
        if destination is None:  # not resolved (yet): count it, and perhaps try the name again
            self.send_errors += 1
            self._resolve_in_background()
            return False
        sock, address = destination
        try:
            sock.sendto(datagram, address)
        except OSError as exc:  # EAGAIN (buffer full), ECONNREFUSED (ICMP), ENETUNREACH, closed socket ...
            self.send_errors += 1
            self.last_error = f"{type(exc).__name__}: {exc}"
            return False
        self.sent += 1
        return True

    def close(self) -> None:
        """Close the socket; later sends are counted as errors (a resolver still running closes its own)."""
        with self._lock:
            self._closed = True
            destination = self._destination
        if destination is not None:
            destination[0].close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
