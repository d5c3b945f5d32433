"""Who may ask the web listener what, sans-IO: the ``Host`` and ``Origin`` rules, a trusted proxy's
``X-Forwarded-For``, and the login sessions (headers and times in, verdicts out; ``server.WebView`` applies them).

* ``Host``: its host part (a port ignored; an IPv6 literal in brackets) must be the address the connection came
  in on, the address the listener is bound to, ``localhost``, or a name of ``http_hosts``.  A page of another
  domain whose DNS points to the daemon (DNS rebinding) sends its own name: refused (421), as is a request with
  no or several ``Host`` headers (400).
* ``Origin`` (sent by browsers on WebSocket upgrades and form posts): when present it must be the listener's
  own origin, scheme included: ``http``, or ``https`` when ``http_secure_cookies`` says TLS is in front.
* ``X-Forwarded-For`` is read only on a connection from ``http_trusted_proxies``: the client is the rightmost
  address that is not one of them.  From anywhere else the header is ignored, and nothing (neither the client's
  address nor the scheme) is ever guessed from forwarded headers.
* A login makes a session: a random cookie value (never the token) valid for ``WEB_SESSION_MAX_AGE_S``, held here
  by its SHA-256; logging out ends it, a new token ends them all.
"""

from __future__ import annotations

import collections
import hashlib
import ipaddress
import secrets
from collections.abc import Iterable

from ..guards import peer_address
from ..limits import WEB_MAX_SESSIONS, WEB_SESSION_MAX_AGE_S

__all__ = [
    "AddressSet",
    "Sessions",
    "forwarded_client",
    "host_name",
    "normalize_name",
    "origin_problem",
]

IpNetwork = ipaddress.IPv4Network | ipaddress.IPv6Network


def normalize_name(name: str) -> str:
    """A host name as compared: lower case, no trailing dot; an IP literal in its canonical form."""
    name = name.strip().lower().rstrip(".")
    try:
        return str(ipaddress.ip_address(name.strip("[]")))
    except ValueError:
        return name


def host_name(value: str) -> str | None:
    """The host part of a ``Host`` header (``name``, ``name:port``, ``[v6]``, ``[v6]:port``), normalized; None
    when it is not one (empty, an unbracketed IPv6 literal, a port that is not a number)."""
    value = value.strip()
    if value.startswith("["):
        literal, bracket, rest = value[1:].partition("]")
        if not bracket or (rest and not (rest.startswith(":") and rest[1:].isdigit())):
            return None
        try:
            return str(ipaddress.IPv6Address(literal))
        except ValueError:
            return None
    name, colon, port = value.partition(":")
    if not name or (colon and not port.isdigit()) or ":" in port or any(c in name for c in "/@\\ \t"):
        return None
    return normalize_name(name)


def _scheme_host_port(scheme: str, host: str) -> tuple[str, str, int] | None:
    """``(scheme, host, port)`` of an origin's parts (a missing port: the scheme's default); None if malformed."""
    name = host_name(host)
    if name is None:
        return None
    port = host.rpartition(":")[2] if not host.endswith("]") and ":" in host else ""
    return scheme, name, int(port) if port else (443 if scheme == "https" else 80)


def origin_problem(origin: str, host: str, *, https: bool) -> str | None:
    """Why a request carrying ``Origin: origin`` to ``Host: host`` comes from another origin (None: its own).

    The page's own origin is ``http://<Host>`` on a plain listener, ``https://<Host>`` when TLS is in front
    (``https``); an origin with another scheme, host or port (a missing port being the scheme's default) or
    ``null`` (a sandboxed frame, a file) is another's."""
    scheme, sep, rest = origin.strip().partition("://")
    scheme = scheme.lower()
    expected = "https" if https else "http"
    if not sep or scheme not in ("http", "https") or "/" in rest:
        return f"Origin {origin!r} is not an origin"
    if scheme != expected:
        return f"Origin {origin!r}: this listener serves {expected}"
    theirs = _scheme_host_port(scheme, rest)
    ours = _scheme_host_port(expected, host)
    if theirs is None or ours is None or theirs != ours:
        return f"Origin {origin!r} is not this listener's"
    return None


class AddressSet:
    """IP addresses and networks (``http_trusted_proxies``: ``10.0.0.5``, ``10.1.0.0/16``, ``::1``)."""

    def __init__(self, entries: Iterable[str]) -> None:
        self.networks: tuple[IpNetwork, ...] = tuple(ipaddress.ip_network(e.strip(), strict=False) for e in entries)

    def __bool__(self) -> bool:
        return bool(self.networks)

    def __contains__(self, address: object) -> bool:
        try:
            ip = ipaddress.ip_address(str(address).split("%")[0])
        except ValueError:
            return False
        if isinstance(ip, ipaddress.IPv6Address) and ip.ipv4_mapped is not None:
            ip = ip.ipv4_mapped
        return any(ip.version == net.version and ip in net for net in self.networks)


def forwarded_client(values: Iterable[str], proxies: AddressSet) -> str | None:
    """The client's address (``guards.peer_address``: an IPv4 address, an IPv6 /64) from the ``X-Forwarded-For``
    header ``values`` of a request that came from a trusted proxy: the rightmost hop that is not one of
    ``proxies``.  ``""`` when there is none (the proxy's own request: its address counts); None when a hop is not
    an IP address (the request is refused: a proxy that forwards garbage is misconfigured)."""
    hops = [hop.strip() for value in values for hop in value.split(",")]
    for hop in reversed(hops):
        try:
            ip = ipaddress.ip_address(hop.strip("[]"))
        except ValueError:
            return None
        if ip not in proxies:
            return peer_address(str(ip))
    return ""


def _digest(value: str) -> bytes:
    return hashlib.sha256(value.encode("utf-8", "surrogatepass")).digest()


class Sessions:
    """The login sessions of one listener: a random cookie value each (never the token), valid
    ``WEB_SESSION_MAX_AGE_S`` from the login, at most ``WEB_MAX_SESSIONS`` (the oldest end first).  Kept by the
    value's SHA-256, so a lookup compares digests, never the secret itself.  Times are arguments (monotonic s)."""

    def __init__(self, max_age_s: float = WEB_SESSION_MAX_AGE_S, max_sessions: int = WEB_MAX_SESSIONS) -> None:
        self.max_age_s = max_age_s
        self.max_sessions = max_sessions
        self._expiry: collections.OrderedDict[bytes, float] = collections.OrderedDict()

    def __len__(self) -> int:
        return len(self._expiry)

    def start(self, now: float) -> str:
        """A new session: its cookie value."""
        value = secrets.token_urlsafe(32)
        self._expiry[_digest(value)] = now + self.max_age_s
        while len(self._expiry) > self.max_sessions:
            self._expiry.popitem(last=False)
        return value

    def valid(self, value: str | None, now: float) -> bool:
        """The cookie ``value`` is a session's that has not expired (an expired one is forgotten)."""
        if not value:
            return False
        digest = _digest(value)
        expiry = self._expiry.get(digest)
        if expiry is None:
            return False
        if now >= expiry:
            del self._expiry[digest]
            return False
        return True

    def end(self, value: str | None) -> None:
        """Log out: the session of ``value`` is over."""
        if value:
            self._expiry.pop(_digest(value), None)

    def clear(self) -> None:
        """Every session is over (a new token)."""
        self._expiry.clear()
