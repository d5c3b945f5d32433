"""What the NDJSON hub and the web view share to guard themselves: the token rule, the backoff on failed
attempts per peer address, peer addresses, and the log rate limit (sans-IO: times are arguments)."""

from __future__ import annotations

import collections
import ipaddress
import socket
from typing import Any

from .limits import AUTH_FAILURES_BEFORE_BACKOFF, LOG_WINDOW_S, MAX_THROTTLED_PEERS

__all__ = ["AuthThrottle", "LogRateLimiter", "check_token", "is_loopback_host", "peer_address"]


def check_token(token: str | None, host: str) -> None:
    """ValueError unless ``token`` is a non-empty string that encodes as UTF-8, or None on a loopback ``host``."""
    if token is None:
        if not is_loopback_host(host):
            raise ValueError(
                f"refusing to listen on {host or 'every interface'!r} without a client token: "
                "anyone on the network could control the instrument; set a token or bind 127.0.0.1"
            )
        return
    if not isinstance(token, str) or not token:
        raise ValueError("the client token must be a non-empty string")
    try:
        token.encode("utf-8")
    except UnicodeEncodeError:
        raise ValueError("the client token must be valid text (it has a lone surrogate)") from None


def is_loopback_host(host: str | None) -> bool:
    """True when binding ``host`` listens on loopback only ("", None and 0.0.0.0 mean every interface)."""
    if not host:
        return False
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        pass
    try:
        infos = socket.getaddrinfo(host, None, type=socket.SOCK_STREAM)
    except OSError:
        return False
    addresses = {info[4][0] for info in infos}
    return bool(addresses) and all(ipaddress.ip_address(a.split("%")[0]).is_loopback for a in addresses)


def peer_address(peer: Any) -> str:
    """The address a client's connection and ``?AUTH`` limits are counted on: its IPv4 address (an
    IPv4-mapped IPv6 one too), its IPv6 /64 (what one host or user usually holds), or the text of
    anything else."""
    host = peer[0] if isinstance(peer, tuple) and peer else peer
    try:
        ip = ipaddress.ip_address(str(host).split("%")[0])
    except ValueError:
        return str(host)
    if isinstance(ip, ipaddress.IPv6Address):
        if ip.ipv4_mapped is not None:
            return str(ip.ipv4_mapped)
        if not ip.is_loopback:
            return str(ipaddress.IPv6Network((ip, 64), strict=False))
    return str(ip)


class _LogWindow:
    __slots__ = ("logged", "start_s", "summarized_s", "suppressed")

    def __init__(self, start_s: float) -> None:
        self.start_s = start_s
        self.logged = 0
        self.suppressed = 0
        self.summarized_s = start_s


class LogRateLimiter:
    """At most ``lines_per_s`` lines of each event per 1 s window; the others are counted.

    ``take_suppressed(now)`` hands out (and forgets) the counts not yet handed out, for
    each event at most once a second, so a summary costs one line per event and second
    at most, and every suppressed line is counted in one.
    """

    WINDOW_S = LOG_WINDOW_S

    def __init__(self, lines_per_s: int) -> None:
        self.lines_per_s = lines_per_s
        self._windows: dict[str, _LogWindow] = {}

    def allow(self, event: str, now: float) -> bool:
        window = self._windows.get(event)
        if window is None:
            window = self._windows[event] = _LogWindow(now)
        elif now - window.start_s >= self.WINDOW_S:
            window.start_s, window.logged = now, 0
        if window.logged < self.lines_per_s:
            window.logged += 1
            return True
        window.suppressed += 1
        return False

    def take_suppressed(self, now: float) -> list[tuple[str, int]]:
        taken = []
        for event, window in self._windows.items():
            if window.suppressed and now - window.summarized_s >= self.WINDOW_S:
                taken.append((event, window.suppressed))
                window.suppressed = 0
                window.summarized_s = now
        return taken


class _PeerAuthFailures:
    __slots__ = ("blocked_until", "failures")

    def __init__(self, now: float) -> None:
        self.failures = 0
        self.blocked_until = now


class AuthThrottle:
    """Failed ``?AUTH`` attempts per peer address across connections, with exponential backoff.

    The first ``AUTH_FAILURES_BEFORE_BACKOFF`` failures of an address cost nothing; the
    next one blocks the address for ``base_s``, and each further one for twice as long as
    the one before (at most ``max_s``).  While an address is blocked its attempts are
    refused without comparing the token.  An address is forgotten on a successful
    ``?AUTH`` from it and ``max_s`` after its last failure or block ended; at most
    ``MAX_THROTTLED_PEERS`` addresses are remembered (the least recently failed go first).
    """

    def __init__(self, base_s: float, max_s: float) -> None:
        self.base_s = base_s
        self.max_s = max_s
        self._peers: collections.OrderedDict[str, _PeerAuthFailures] = collections.OrderedDict()

    def blocked_for_s(self, peer: str, now: float) -> float:
        """Seconds ``peer`` must still wait before its next attempt is compared (0: not blocked)."""
        record = self._peers.get(peer)
        if record is None:
            return 0.0
        if now >= record.blocked_until + self.max_s:
            del self._peers[peer]
            return 0.0
        return max(0.0, record.blocked_until - now)

    def failed(self, peer: str, now: float) -> float:
        """Count a failed attempt from ``peer``; returns the seconds it is now blocked for (0: none)."""
        record = self._peers.pop(peer, None) or _PeerAuthFailures(now)
        self._peers[peer] = record  # the most recent failure last
        while len(self._peers) > MAX_THROTTLED_PEERS:
            self._peers.popitem(last=False)
        record.failures += 1
        beyond = record.failures - AUTH_FAILURES_BEFORE_BACKOFF
        blocked_s = min(self.base_s * 2.0 ** min(beyond - 1, 62), self.max_s) if beyond > 0 else 0.0
        record.blocked_until = now + blocked_s
        return blocked_s

    def succeeded(self, peer: str) -> None:
        self._peers.pop(peer, None)
