"""What the NDJSON hub and the web view share to guard themselves: the token rule and its comparison, the
backoff on wrong tokens per peer address, the connection slots (``Slots``: clients without the token never
starve those with it), peer addresses, and the log rate limit (sans-IO: times are arguments)."""

from __future__ import annotations

import collections
import hmac
import ipaddress
import socket
from collections.abc import Callable, Hashable
from dataclasses import dataclass
from typing import Any

from .limits import AUTH_FAILURES_BEFORE_BACKOFF, LOG_WINDOW_S, MAX_THROTTLED_PEERS

__all__ = [
    "Admission",
    "AuthThrottle",
    "LogRateLimiter",
    "Slots",
    "check_token",
    "is_loopback_host",
    "peer_address",
    "token_matches",
]


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


def token_matches(given: Any, token: str | None) -> bool:
    """True when ``given`` is the text ``token`` (compared in constant time); never for a ``None`` token, and a
    ``given`` that is not text or has a lone surrogate is a wrong token like any other, never an exception."""
    if token is None or not isinstance(given, str):
        return False
    return hmac.compare_digest(given.encode("utf-8", "surrogatepass"), token.encode("utf-8"))


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

    def log_suppressed(self, log: Any, now: float) -> None:
        """One ``log_lines_suppressed`` warning on ``log`` (a structlog logger) per event with lines left out
        since its last (``take_suppressed``); ``now=math.inf`` (a listener stopping): every count left."""
        for event, count in self.take_suppressed(now):
            log.warning("log_lines_suppressed", suppressed_event=event, count=count)


class _PeerAuthFailures:
    __slots__ = ("blocked_until", "failures")

    def __init__(self, now: float) -> None:
        self.failures = 0
        self.blocked_until = now


class AuthThrottle:
    """Wrong tokens per peer address across connections (``?AUTH`` and the web listener's), with exponential
    backoff; ``judge`` says what one attempt gets.

    The first ``AUTH_FAILURES_BEFORE_BACKOFF`` wrong tokens of an address cost nothing; the
    next one blocks the address for ``base_s``, and each further one for twice as long as
    the one before (at most ``max_s``).  While an address is blocked no token from it is
    compared, right or wrong: every attempt is refused alike ("retry in N s") and not
    counted, so the answer tells a guesser nothing and its guesses are held to one per
    block (with 1 s doubling to 300 s: 288 a day once at the cap, at most 2,142 a day
    from one address whatever it does, ``guesses_per_day``).  The backoff is the
    address's alone: a guesser elsewhere cannot lock out a station, one sharing its
    address (a host's users, a NAT, a proxy) can, for as long as it guesses.  An address
    is forgotten on a right token from it and ``max_s`` after its last failure or block
    ended; at most ``MAX_THROTTLED_PEERS`` addresses are remembered (the least recently
    failed go first).
    """

    def __init__(self, base_s: float, max_s: float) -> None:
        self.base_s = base_s
        self.max_s = max_s
        self._peers: collections.OrderedDict[str, _PeerAuthFailures] = collections.OrderedDict()

    def judge(self, peer: str, right: Callable[[], bool], now: float) -> tuple[str, float]:
        """One attempt from ``peer``: ``("blocked", seconds still to wait)`` while the address is blocked (the
        token not compared: ``right`` is not called; refused, not counted); else ``right()`` (``token_matches``)
        decides: ``("ok", 0)`` or ``("wrong", seconds the address is now blocked for)`` (counted)."""
        wait_s = self.blocked_for_s(peer, now)
        if wait_s > 0:
            return "blocked", wait_s
        if right():
            self.succeeded(peer)
            return "ok", 0.0
        return "wrong", self.failed(peer, now)

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


# -- connection slots -------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Admission:
    """What ``Slots.admit`` decided: ``refused`` (None when let in: ``"total"`` or ``"peer"``, the cap reached),
    and the connections to close to make room (already forgotten by the slots)."""

    refused: str | None
    evicted: tuple[Hashable, ...] = ()


class _Slot:
    __slots__ = ("authorized", "peer", "reader")

    def __init__(self, peer: str, authorized: bool) -> None:
        self.peer = peer
        self.authorized = authorized
        self.reader = False


class Slots:
    """The connection slots of one listener, shared so that clients without the token never starve those with it.

    At most ``max_total`` connections, and ``max_per_peer`` from one address.  Connections not authorized (new
    ones whose credentials are not known yet, ones refused, open-stream readers) hold at most half of either
    (``max_total // 2``, ``max_per_peer // 2``, at least 1).  A new connection that finds a cap reached is let in
    by closing the oldest unauthorized connection in the way (its address's when the address's cap is reached),
    one that is no reader first; it is refused only when every slot in the way is held by an authorized
    connection.  So an authorized client finds a slot while fewer than the maximum are authorized, whatever the
    others hold.  A connection counts against its address's cap unless admitted with ``peer=None`` (a trusted
    proxy's: ``move`` gives it its client's address once a request says which).  Keys are the listener's
    connection objects; sans-IO.
    """

    def __init__(self, max_total: int, max_per_peer: int) -> None:
        self.max_total = max_total
        self.max_per_peer = max_per_peer
        self.max_unauthorized = max(1, max_total // 2)
        self.max_unauthorized_per_peer = max(1, max_per_peer // 2)
        self._slots: dict[Hashable, _Slot] = {}  # in order of arrival: the oldest first
        self._per_peer: collections.Counter[str] = collections.Counter()
        self._unauthorized_per_peer: collections.Counter[str] = collections.Counter()
        self._unauthorized = 0

    def __len__(self) -> int:
        return len(self._slots)

    def __contains__(self, key: Hashable) -> bool:
        return key in self._slots

    def authorized(self, key: Hashable) -> bool:
        slot = self._slots.get(key)
        return slot is not None and slot.authorized

    def unauthorized(self, peer: str | None = None) -> int:
        """Connections not authorized, of ``peer`` (None: of every address)."""
        return self._unauthorized if peer is None else self._unauthorized_per_peer[peer]

    def admit(self, key: Hashable, peer: str | None, *, authorized: bool = False) -> Admission:
        """Let a new connection in (see the class docstring), or say which cap refuses it."""
        victims: list[Hashable] = []
        if peer is not None:
            peer_full = self._per_peer[peer] >= self.max_per_peer or (
                not authorized and self._unauthorized_per_peer[peer] >= self.max_unauthorized_per_peer
            )
            if peer_full:
                victim = self._victim(peer, victims)
                if victim is None:
                    return Admission("peer")
                victims.append(victim)
        total_full = len(self._slots) - len(victims) >= self.max_total or (
            not authorized and self._unauthorized - len(victims) >= self.max_unauthorized
        )
        if total_full:
            victim = self._victim(None, victims)
            if victim is None:
                return Admission("total")
            victims.append(victim)
        for victim in victims:
            self.release(victim)
        self._slots[key] = _Slot("" if peer is None else peer, authorized)
        self._count(self._slots[key], 1)
        return Admission(None, tuple(victims))

    def move(self, key: Hashable, peer: str) -> Admission:
        """Count a connection admitted without an address (a trusted proxy's) against ``peer``'s cap from now
        on: as ``admit`` would let it in (closing the oldest of ``peer``'s unauthorized ones), or refused."""
        slot = self._slots.get(key)
        if slot is None or slot.peer:
            return Admission(None)
        authorized = slot.authorized
        self.release(key)
        admission = self.admit(key, peer, authorized=authorized)
        if admission.refused is None:
            self._slots[key].reader = slot.reader
        return admission

    def authorize(self, key: Hashable) -> None:
        """The connection carried the token: it holds an authorized slot from now on."""
        slot = self._slots.get(key)
        if slot is not None and not slot.authorized:
            self._count(slot, -1)
            slot.authorized = True
            self._count(slot, 1)

    def set_reader(self, key: Hashable) -> None:
        """The (unauthorized) connection reads the open stream: others are closed before it to make room."""
        slot = self._slots.get(key)
        if slot is not None:
            slot.reader = True

    def release(self, key: Hashable) -> None:
        """Forget a connection (closed, or closed to make room)."""
        slot = self._slots.pop(key, None)
        if slot is not None:
            self._count(slot, -1)

    def _count(self, slot: _Slot, step: int) -> None:
        if slot.peer:
            self._per_peer[slot.peer] += step
            if self._per_peer[slot.peer] <= 0:
                del self._per_peer[slot.peer]
        if not slot.authorized:
            self._unauthorized += step
            if slot.peer:
                self._unauthorized_per_peer[slot.peer] += step
                if self._unauthorized_per_peer[slot.peer] <= 0:
                    del self._unauthorized_per_peer[slot.peer]

    def _victim(self, peer: str | None, taken: list[Hashable]) -> Hashable | None:
        """The oldest unauthorized connection (of ``peer``, None: of any address) not in ``taken``, one that is
        no reader first; None when there is none."""
        reader = None
        for key, slot in self._slots.items():
            if slot.authorized or key in taken or (peer is not None and slot.peer != peer):
                continue
            if not slot.reader:
                return key
            if reader is None:
                reader = key
        return reader
