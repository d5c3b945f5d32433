"""The daemon's client multiplexer: JSON lines over TCP, in the manner of gpsd.

Client protocol (version 1)
===========================

Transport: TCP, by default on the loopback interface only.  Every message in
either direction is one line of UTF-8 text ending in ``\\n``.

Server to client: every line is one JSON object with a ``"class"`` key naming
what it is.  Absent values are *omitted*, never ``null`` (a thermometer with no
valid reading simply has no key); numbers are always finite.  Clients must
ignore keys (and classes) they do not know: new keys may appear in any minor
version, ``proto_major`` changes only when a key changes meaning or goes away.

=========  =================================================================
class      sent when
=========  =================================================================
VERSION    first line on every connection, and in answer to ``?VERSION;``:
           ``release``, ``proto_major``, ``proto_minor`` and the instrument's
           identity (filled in by the service)
DEVICE     second line on connect when an instrument is known, and to every
           authorized client whenever the instrument (or its link state)
           changes; on a token-protected daemon, right after a successful
           ``?AUTH`` instead of on connect
STATUS     to every authorized client (watching or not), periodic summaries
ANGLE      one per instrument sample, only to clients with an enabled WATCH,
           decimated per client (see ``?WATCH``); always carries ``t_s``
           (device time, s)
WATCH      answer to ``?WATCH``: the client's policy now in force
AUTH       answer to a successful ``?AUTH``: ``{"class":"AUTH","authorized":true}``
ERROR      a command failed: ``message``, and ``command`` when the command's
           name could be read
(other)    answers to control commands (the service's; a reply without a
           class takes the command's name as its class)
=========  =================================================================

Client to server: commands, one per line, ``?NAME;`` or ``?NAME={json object};``
where NAME is upper-case ASCII letters and the trailing ``;`` is optional
(``\\r`` before the newline is tolerated; empty lines are ignored, but count
against the rate limit).  Every command is answered by exactly one line (its
reply or an ``ERROR``), in the order the commands were sent; ANGLE/STATUS/DEVICE
lines may be interleaved.

- ``?WATCH;`` reports the current policy; ``?WATCH={"enable": true, "rate_hz": 10};``
  sets it.  The object *is* the whole policy: ``enable`` defaults to true,
  ``rate_hz`` omitted means every sample; otherwise it is a number with
  ``0 < rate_hz <= 10000`` (``MAX_WATCH_RATE_HZ``).  With ``rate_hz`` the client
  gets the first sample of each period ``[k / rate_hz, (k + 1) / rate_hz)`` of
  device time ``t_s`` (``k = floor(t_s * rate_hz)``): a decimation on the
  instrument's clock, not the host's.  A new ``?WATCH`` restarts the decimation.
- ``?VERSION;`` sends the VERSION object again.
- ``?AUTH={"token": "..."};`` authorizes this connection, needed only when the
  daemon was configured with a token (which it must be to listen beyond
  loopback).  Until then a client gets VERSION (and the answers to its
  ``?WATCH``, ``?VERSION`` and ``?AUTH``, and ANGLE lines it watches) but no
  DEVICE or STATUS, and every control command is refused.  Failed attempts are
  throttled per peer address (see Limits); five failed or refused attempts
  close the connection.  When the daemon's token changes, every connection is
  closed (``ERROR`` "the client token changed: connect again").
- Any other NAME is a control command handed to the service (for example
  ``?ZERO;`` or ``?MARK={"label": "stop 3"};``); an unknown one is answered
  with ``ERROR`` ``"unknown command ?NAME"``; without a prior successful
  ``?AUTH`` on a token-protected daemon every one is refused with ``ERROR``
  ``"unauthorized"``.  A command that gets no answer in time (``control_timeout_s``,
  30 s, unless the service gave it a deadline of its own) is answered with
  ``ERROR`` ``"no answer within N s"``; the command itself is not undone and
  runs to its end.  A command that takes longer (``?BIAS`` over N seconds of
  data) is answered at once (``"state": "started"``) and publishes its result
  later as an event of its own class (``BIAS`` ``"state": "done"``): the hub
  never holds a connection's answers for it.

Limits (a misbehaving client costs the daemon a bounded amount and never
delays anybody else).  Each is a module constant or a :class:`Hub` argument
(named here, with its default):

- a line longer than ``max_line_bytes`` (4096) is answered with ``ERROR`` and
  discarded up to its newline; 64 KiB (``MAX_UNTERMINATED_BYTES``) without any
  newline closes the connection;
- invalid JSON, a JSON value that is not an object, a malformed line or an
  unknown command: ``ERROR``, and the connection stays open;
- at most 100 lines per second per client (``MAX_COMMANDS_PER_S``; commands,
  and empty or oversized lines alike): the excess is answered with ``ERROR``,
  and 1000 excess lines (``MAX_EXCESS_COMMANDS``) close the connection.  The hub
  handles one 64 KiB chunk of a client's input at a time, then serves the others;
- a client that does not read is dropped: when the oldest line queued for it
  (not yet accepted by the kernel) is older than ``max_backlog_s`` (2 s) the
  connection is closed, logged, and counted.  Data has a short shelf life: the
  daemon never buffers old samples for a slow reader;
- at most ``max_clients`` (64) connections, and ``max_clients_per_peer`` (16)
  from one peer address (an IPv4 address; an IPv6 /64): one more gets one
  ``ERROR`` line and is closed;
- on a token-protected daemon a client that has not authorized within
  ``auth_deadline_s`` (10 s) of connecting gets ``ERROR`` and is closed;
- failed ``?AUTH`` attempts are counted per peer address, across connections:
  after 3 (``AUTH_FAILURES_BEFORE_BACKOFF``) each further failure blocks the
  address for ``auth_backoff_base_s`` (1 s), doubled each time up to
  ``auth_backoff_max_s`` (300 s); while blocked, ``?AUTH`` is refused with
  ``ERROR`` "too many failed attempts, retry in N s" without looking at the
  token.  An address is forgotten after a success, and ``auth_backoff_max_s``
  after its last failure or block ended (at most 4096 addresses are remembered,
  ``MAX_THROTTLED_PEERS``; the least recently failed are forgotten first);
- a control command waits ``control_timeout_s`` (30 s) for its answer;
- per-client log lines (connected, disconnected, refused, dropped, failed,
  auth failures, errors of the loop such as failed accepts when out of file
  descriptors) are limited to ``log_lines_per_s`` (5) per event and second,
  and the ones left out are counted in a ``log_lines_suppressed`` line (one a
  second per event at most).

Example session (``nc 127.0.0.1 2948``)::

    {"class":"VERSION","release":"0.1.0","proto_major":1,"proto_minor":0,...}
    {"class":"DEVICE","serial":"FOG-SYN-0001",...}
    ?WATCH={"enable":true,"rate_hz":1}
    {"class":"WATCH","enable":true,"rate_hz":1}
    {"class":"ANGLE","t_s":12.0,"angle_arcsec":3.25,...}

Threading: :class:`Hub` runs an asyncio loop in its own daemon thread.  The
acquisition thread calls :meth:`Hub.publish_angles` / :meth:`Hub.publish`,
which never block (objects are serialized in the caller's thread and handed to
the loop with one ``call_soon_threadsafe`` per call).  The ``version`` and
``device`` callbacks run on the hub's loop thread and must return promptly.
The ``control`` callback runs in one of the hub's own worker threads
(``CONTROL_WORKERS``), never on the loop, so a slow command (a model reload)
delays nobody's ANGLE lines; commands of one client are still answered one at a
time, in order.  A command whose answer comes later returns a
:class:`concurrent.futures.Future` (answered within ``control_timeout_s``; a
longer task answers at once and publishes its result as an event).  The hub only ever
*waits* for such a Future: a timeout or the client hanging up abandons the
wait, and the Future's owner may complete it whenever it likes (the hub never
cancels it).
"""

from __future__ import annotations

import asyncio
import collections
import concurrent.futures
import contextlib
import hmac
import ipaddress
import json
import math
import re
import socket
import threading
import time
from collections.abc import Callable
from typing import Any, Self

import structlog

from .limits import (
    AUTH_FAILURES_BEFORE_BACKOFF,
    COMMAND_WINDOW_S,
    CONTROL_WORKERS,
    DEFAULT_AUTH_BACKOFF_BASE_S,
    DEFAULT_AUTH_BACKOFF_MAX_S,
    DEFAULT_AUTH_DEADLINE_S,
    DEFAULT_CONTROL_TIMEOUT_S,
    DEFAULT_LOG_LINES_PER_S,
    DEFAULT_MAX_BACKLOG_S,
    DEFAULT_MAX_CLIENTS,
    DEFAULT_MAX_CLIENTS_PER_PEER,
    DEFAULT_MAX_LINE_BYTES,
    LOG_WINDOW_S,
    MAX_AUTH_FAILURES,
    MAX_COMMANDS_PER_S,
    MAX_EXCESS_COMMANDS,
    MAX_THROTTLED_PEERS,
    MAX_UNTERMINATED_BYTES,
    MAX_WATCH_RATE_HZ,
    MIN_MAX_LINE_BYTES,
    READ_CHUNK_BYTES,
    SETTING_WAIT_S,
    SWEEP_EVERY_S,
)
from .web.metrics import LatencyHistogram

__all__ = [
    "DEFAULT_AUTH_BACKOFF_BASE_S",
    "DEFAULT_AUTH_BACKOFF_MAX_S",
    "DEFAULT_AUTH_DEADLINE_S",
    "DEFAULT_CONTROL_TIMEOUT_S",
    "DEFAULT_LOG_LINES_PER_S",
    "DEFAULT_MAX_BACKLOG_S",
    "DEFAULT_MAX_CLIENTS",
    "DEFAULT_MAX_CLIENTS_PER_PEER",
    "DEFAULT_MAX_LINE_BYTES",
    "MAX_WATCH_RATE_HZ",
    "Hub",
    "clean",
    "encode",
    "is_loopback_host",
]

log = structlog.get_logger("fog_driver.daemon")

_COMMAND_RE = re.compile(r"\?([A-Z]+)(?:=(.*))?\Z", re.DOTALL)
_HUB_COMMANDS = frozenset({"WATCH", "VERSION", "AUTH"})


def clean(obj: Any) -> Any:
    """``obj`` without None values and non-finite floats, recursively (dict values, list items).

    Absent values are omitted from the protocol, never sent as ``null``; numpy
    scalars become Python numbers and numpy arrays lists.  Dict keys are kept as given.
    """
    if isinstance(obj, dict):
        out = {}
        for key, value in obj.items():
            value = clean(value)
            if value is not _ABSENT:
                out[key] = value
        return out
    return _clean_value(obj)


def _check_token(token: str | None, host: str) -> None:
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


def _check_max_backlog_s(seconds: float) -> None:
    if not (seconds > 0):  # inf is allowed: never drop a client that does not read
        raise ValueError("max_backlog_s must be > 0")


class _Absent:
    __slots__ = ()


_ABSENT: Any = _Absent()


def _clean_value(value: Any) -> Any:
    if value is None:
        return _ABSENT
    if isinstance(value, bool):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else _ABSENT
    if isinstance(value, (int, str)):
        return value
    if isinstance(value, dict):
        return clean(value)
    if isinstance(value, (list, tuple)):
        items = (_clean_value(v) for v in value)
        return [v for v in items if v is not _ABSENT]
    # numpy scalars and arrays, without importing numpy here
    tolist = getattr(value, "tolist", None)
    if tolist is not None and hasattr(value, "dtype"):
        return _clean_value(tolist())
    return value


_ENCODER = json.JSONEncoder(separators=(",", ":"), allow_nan=False)


def encode(obj: dict) -> bytes:
    """One protocol line: ``clean(obj)`` as compact JSON plus ``\\n`` (raises on unserializable values).

    Most objects are clean already (every ANGLE the daemon makes): they are encoded as they are, and
    ``clean`` runs only when that fails or might differ, i.e. when the object holds a non-finite float
    (ValueError), a numpy integer or array (TypeError) or a ``null`` (None; the text ``null`` inside a
    string also takes the slow path, which gives the same line)."""
    try:
        text = _ENCODER.encode(obj)
    except (ValueError, TypeError):
        text = None
    if text is None or "null" in text:
        text = _ENCODER.encode(clean(obj))
    return text.encode() + b"\n"


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


def _is_positive_finite(value: Any) -> bool:
    """True for an int or float (not a bool) with ``0 < value < inf``."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and 0 < value < math.inf


class _NoAnswer(Exception):
    """A control command's answer did not come before its deadline."""


def _settle(waiter: asyncio.Future) -> None:
    """Mark ``waiter`` done, unless its wait was abandoned (cancelled) already."""
    if not waiter.done():
        waiter.set_result(None)


def _peer_address(peer: Any) -> str:
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


class _LogRateLimiter:
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


class _AuthThrottle:
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


class _Client:
    """One connection: its policy, its outgoing queue and its two tasks."""

    __slots__ = (
        "auth_deadline",
        "auth_failures",
        "authorized",
        "closing",
        "excess",
        "gone",
        "id",
        "inflight_t",
        "last_bucket",
        "lines_queued",
        "peer",
        "peer_address",
        "queue",
        "rate_hz",
        "reader",
        "reader_task",
        "wakeup",
        "watch",
        "window_count",
        "window_start",
        "writer",
        "writer_task",
    )

    def __init__(
        self, cid: int, peer: Any, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, authorized: bool
    ) -> None:
        self.id = cid
        self.peer = peer
        self.peer_address = _peer_address(peer)
        self.auth_deadline: asyncio.TimerHandle | None = None
        self.reader = reader
        self.writer = writer
        self.queue: collections.deque[tuple[float, bytes | None]] = collections.deque()
        self.wakeup = asyncio.Event()
        self.inflight_t: float | None = None  # enqueue time of the oldest bytes being drained
        self.closing = False
        self.watch = False
        self.rate_hz: float | None = None
        self.last_bucket: int | None = None
        self.authorized = authorized
        self.auth_failures = 0
        self.window_start = time.monotonic()
        self.window_count = 0
        self.excess = 0
        self.reader_task: asyncio.Task | None = None
        self.writer_task: asyncio.Task | None = None
        self.gone = False
        self.lines_queued = 0

    def oldest_t(self) -> float | None:
        if self.inflight_t is not None:
            return self.inflight_t
        return self.queue[0][0] if self.queue else None


class Hub:
    """TCP server speaking the client protocol above; see the module docstring.

    ``version()`` returns the VERSION object (the hub adds ``class``), ``device()``
    the current DEVICE object or None, ``control(name, args, client_id)`` answers
    every command the hub does not handle itself, with a dict or a
    :class:`concurrent.futures.Future` of one (``None`` for a
    command it does not know: the client gets ``ERROR`` "unknown command ?NAME"; an
    exception, raised or set on the Future, becomes an ``ERROR`` carrying its
    message).  ``control`` runs in the hub's worker threads, at most
    ``CONTROL_WORKERS`` at a time.  A reply without ``class`` gets the command's
    name, and an ``ERROR`` reply without ``command`` gets the command's name there.

    ``sndbuf_bytes`` sets SO_SNDBUF on accepted connections: the kernel then
    absorbs at most that much for a client that does not read (by default, on
    loopback, megabytes: tens of seconds of ANGLE lines before the backlog age
    policy can even see the client is stuck).

    ``max_clients`` and ``max_clients_per_peer`` cap connections (overall, and per
    IPv4 address or IPv6 /64); ``auth_deadline_s`` (None: no deadline) is how long a
    client of a token-protected hub may stay without ``?AUTH``;
    ``auth_backoff_base_s`` and ``auth_backoff_max_s`` set the backoff on failed
    ``?AUTH`` attempts per peer address; ``log_lines_per_s`` caps the log lines of
    each per-client event.  The module docstring's "Limits" says what each does.

    While it runs, :meth:`set_token` and :meth:`set_max_backlog_s` change the token
    and the backlog limit from any thread (the service calls them on SIGHUP).
    """

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 0,
        *,
        version: Callable[[], dict],
        device: Callable[[], dict | None],
        control: Callable[[str, dict, int], dict | concurrent.futures.Future | None],
        token: str | None = None,
        max_line_bytes: int = DEFAULT_MAX_LINE_BYTES,
        max_backlog_s: float = DEFAULT_MAX_BACKLOG_S,
        control_timeout_s: float = DEFAULT_CONTROL_TIMEOUT_S,
        sndbuf_bytes: int | None = None,
        max_clients: int = DEFAULT_MAX_CLIENTS,
        max_clients_per_peer: int = DEFAULT_MAX_CLIENTS_PER_PEER,
        auth_deadline_s: float | None = DEFAULT_AUTH_DEADLINE_S,
        auth_backoff_base_s: float = DEFAULT_AUTH_BACKOFF_BASE_S,
        auth_backoff_max_s: float = DEFAULT_AUTH_BACKOFF_MAX_S,
        log_lines_per_s: int = DEFAULT_LOG_LINES_PER_S,
        latency: LatencyHistogram | None = None,
    ) -> None:
        _check_token(token, host)
        if max_line_bytes < MIN_MAX_LINE_BYTES:
            raise ValueError(f"max_line_bytes must be at least {MIN_MAX_LINE_BYTES}")
        _check_max_backlog_s(max_backlog_s)
        if not _is_positive_finite(control_timeout_s):
            raise ValueError("control_timeout_s must be a finite number of seconds > 0")
        for name, count in (
            ("max_clients", max_clients),
            ("max_clients_per_peer", max_clients_per_peer),
            ("log_lines_per_s", log_lines_per_s),
        ):
            if not isinstance(count, int) or isinstance(count, bool) or count < 1:
                raise ValueError(f"{name} must be an integer >= 1")
        if auth_deadline_s is not None and not _is_positive_finite(auth_deadline_s):
            raise ValueError("auth_deadline_s must be a finite number of seconds > 0, or None")
        if not (
            _is_positive_finite(auth_backoff_base_s)
            and _is_positive_finite(auth_backoff_max_s)
            and auth_backoff_base_s <= auth_backoff_max_s
        ):
            raise ValueError("auth backoff: need 0 < auth_backoff_base_s <= auth_backoff_max_s < inf")
        self.host = host
        self.port = port
        self._version = version
        self._device = device
        self._control = control
        self._token = token
        self.max_line_bytes = max_line_bytes
        self.max_backlog_s = float(max_backlog_s)
        self.control_timeout_s = control_timeout_s
        self.sndbuf_bytes = sndbuf_bytes
        self.max_clients = max_clients
        self.max_clients_per_peer = max_clients_per_peer
        self.auth_deadline_s = auth_deadline_s
        self._auth_throttle = _AuthThrottle(auth_backoff_base_s, auth_backoff_max_s)
        self._log_limiter = _LogRateLimiter(log_lines_per_s)
        self.latency = latency  #: frame-to-publish latency, observed once per published batch (None: not measured)

        self._clients: dict[int, _Client] = {}
        self._clients_per_peer: collections.Counter[str] = collections.Counter()
        self._refused = 0
        self._next_id = 1
        self._watchers = 0
        self._dropped = 0
        self._bytes_sent = 0
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._server: asyncio.AbstractServer | None = None
        self._stop_event: asyncio.Event | None = None
        self._ready = threading.Event()
        self._start_error: BaseException | None = None
        self._address: tuple[str, int] | None = None
        self._control_pool: concurrent.futures.ThreadPoolExecutor | None = None

    # ------------------------------------------------------------------ properties

    @property
    def clients(self) -> int:
        """Connected clients."""
        return len(self._clients)

    @property
    def watchers(self) -> int:
        """Connected clients with an enabled WATCH."""
        return self._watchers

    @property
    def dropped_clients(self) -> int:
        """Clients dropped because their backlog grew older than ``max_backlog_s``."""
        return self._dropped

    @property
    def refused_clients(self) -> int:
        """Connections refused because of ``max_clients`` or ``max_clients_per_peer``."""
        return self._refused

    @property
    def bytes_sent(self) -> int:
        """Bytes handed to client sockets."""
        return self._bytes_sent

    @property
    def running(self) -> bool:
        """The hub's loop thread is alive (a watchdog pings only while it is)."""
        return self._thread is not None and self._thread.is_alive()

    def check_token(self, token: str | None) -> None:
        """``ValueError`` when ``set_token(token)`` would refuse it (checked before a reload applies anything)."""
        _check_token(token, self.host)

    @property
    def address(self) -> tuple[str, int] | None:
        """``(host, port)`` listened on, once started."""
        return self._address

    # ------------------------------------------------------------------ settings (any thread)

    def set_token(self, token: str | None) -> None:
        """Use ``token`` for ``?AUTH`` from now on (the service calls this on SIGHUP); thread-safe.

        Validated as in the constructor (ValueError; None only on a loopback address).  A
        changed token closes every connection open at the time, with ``ERROR`` "the client
        token changed: connect again": a token is rotated because it may have leaked, so no
        session authorized by the old one may outlive it, and the clients that had not
        authorized meet the new rules from their first line.  The same token again changes
        nothing.  Returns once the hub's loop has applied it (waiting 5 s at most).
        """
        _check_token(token, self.host)
        self._apply_on_loop(self._replace_token, token)

    def set_max_backlog_s(self, seconds: float) -> None:
        """The backlog age after which a client that does not read is dropped, from now on, for the
        clients connected too (checked at least every 0.25 s); thread-safe, ValueError unless > 0."""
        _check_max_backlog_s(seconds)
        self._apply_on_loop(setattr, self, "max_backlog_s", float(seconds))

    def _apply_on_loop(self, apply: Callable[..., None], *args: Any) -> None:
        """``apply(*args)`` on the loop thread, waiting for it (5 s at most); directly when no loop runs."""
        loop, thread = self._loop, self._thread
        if loop is None or threading.current_thread() is thread:
            apply(*args)
            return
        applied = threading.Event()

        def run() -> None:
            try:
                apply(*args)
            finally:
                applied.set()

        try:
            loop.call_soon_threadsafe(run)
        except RuntimeError:  # the loop closed meanwhile: no client is left to apply it to
            apply(*args)
            return
        if not applied.wait(SETTING_WAIT_S):
            log.warning("hub_setting_late", setting=getattr(apply, "__name__", repr(apply)))

    def _replace_token(self, token: str | None) -> None:
        if token == self._token:
            return
        self._token = token
        for client in list(self._clients.values()):
            self._send_error(client, "the client token changed: connect again", "AUTH")
            self._close_after_flush(client)
        log.warning("client_token_changed", auth=token is not None, clients_closed=len(self._clients))

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> tuple[str, int]:
        """Start the loop thread; return ``(host, port)`` once the socket listens (raises OSError if it cannot)."""
        if self._thread is not None:
            raise RuntimeError("hub already started")
        self._control_pool = concurrent.futures.ThreadPoolExecutor(
            CONTROL_WORKERS, thread_name_prefix="fog-hub-control"
        )
        self._thread = threading.Thread(target=self._run, name="fog-hub", daemon=True)
        self._thread.start()
        self._ready.wait()
        if self._start_error is not None:
            self._thread.join()
            self._thread = None
            self._shut_down_control_pool()
            raise self._start_error
        assert self._address is not None
        return self._address

    def stop(self, timeout: float = 5.0) -> None:
        """Close every client and the server, join the loop thread, and shut the control workers down
        without waiting for a command still running there (idempotent)."""
        loop, thread = self._loop, self._thread
        if thread is None:
            return
        if loop is not None:
            with contextlib.suppress(RuntimeError):  # loop already closed
                loop.call_soon_threadsafe(self._request_stop)
        thread.join(timeout)
        self._thread = None
        self._shut_down_control_pool()

    def _shut_down_control_pool(self) -> None:
        pool, self._control_pool = self._control_pool, None
        if pool is not None:
            pool.shutdown(wait=False, cancel_futures=True)

    def __enter__(self) -> Self:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _request_stop(self) -> None:
        if self._stop_event is not None:
            self._stop_event.set()

    def _run(self) -> None:
        loop = asyncio.new_event_loop()
        loop.set_exception_handler(self._on_loop_error)
        try:
            loop.run_until_complete(self._main(loop))
        except BaseException as exc:  # noqa: BLE001 - reported to start() or logged
            if not self._ready.is_set():
                self._start_error = exc
            else:
                log.error("hub_failed", error=repr(exc))
        finally:
            self._ready.set()
            self._loop = None
            try:
                loop.run_until_complete(loop.shutdown_asyncgens())
            finally:
                loop.close()

    async def _main(self, loop: asyncio.AbstractEventLoop) -> None:
        self._stop_event = asyncio.Event()
        self._server = await asyncio.start_server(self._on_connect, self.host, self.port, limit=READ_CHUNK_BYTES)
        sockname = self._server.sockets[0].getsockname()
        self._address = (sockname[0], sockname[1])
        self._loop = loop
        log.info("hub_listening", host=self._address[0], port=self._address[1], auth=self._token is not None)
        self._ready.set()
        sweeper = asyncio.create_task(self._sweep())
        try:
            await self._stop_event.wait()
        finally:
            sweeper.cancel()
            self._server.close()
            clients = list(self._clients.values())
            tasks = [t for c in clients for t in (c.reader_task, c.writer_task) if t is not None]
            for client in clients:
                self._discard(client, "hub_stopped")
            if tasks:
                await asyncio.gather(*tasks, return_exceptions=True)
            await self._server.wait_closed()
            log.info("hub_stopped", dropped_clients=self._dropped, bytes_sent=self._bytes_sent)

    async def _sweep(self) -> None:
        """Drop stalled clients even when nothing new is being published; summarize suppressed log lines."""
        while True:
            await asyncio.sleep(min(SWEEP_EVERY_S, self.max_backlog_s / 4))
            now = time.monotonic()
            for client in list(self._clients.values()):
                self._check_backlog(client, now)
            for event, count in self._log_limiter.take_suppressed(now):
                log.warning("log_lines_suppressed", suppressed_event=event, count=count)

    def _log(self, level: str, event: str, **fields: Any) -> None:
        """Log a per-client ``event``, unless ``log_lines_per_s`` of it were logged in this second (then count it).

        A flood of connections or guesses thus costs the log a few lines a second and one
        ``log_lines_suppressed`` summary line a second per event."""
        if self._log_limiter.allow(event, time.monotonic()):
            getattr(log, level)(event, **fields)

    def _on_loop_error(self, loop: asyncio.AbstractEventLoop, context: dict) -> None:
        """The loop's exception handler: one short, rate-limited line instead of a traceback each time.

        Out of descriptors, asyncio reports every failed accept (up to 100 per retry, a retry a
        second); the default handler's traceback each time would fill the disk.  The hub serves
        its connected clients meanwhile, and accepts again once descriptors are free."""
        exc = context.get("exception")
        self._log("error", "hub_loop_error", message=context.get("message"), error=repr(exc) if exc else None)

    # ------------------------------------------------------------------ publishing (any thread)

    def publish_angles(self, objs: list[dict], read_monotonic_s: float | None = None) -> None:
        """Send ANGLE objects (each with ``t_s``) to every watching client, decimated per client.

        Thread-safe and non-blocking: each object is serialized once here, and
        the batch goes to the loop in one ``call_soon_threadsafe``.  A batch
        published while nobody watches is skipped without serializing it.
        ``read_monotonic_s``: when the bytes that completed the batch were read
        (``time.monotonic()``); with a ``latency`` histogram, the time from then
        to the batch's lines queued for every watching client is observed.
        """
        if not objs or self._loop is None or self._watchers == 0:
            return
        items: list[tuple[float, bytes]] = []
        for obj in objs:
            t_s = obj.get("t_s")
            if t_s is None or not math.isfinite(t_s):
                raise ValueError(f"an ANGLE object needs a finite t_s: {obj!r}")
            if "class" not in obj:
                obj = {"class": "ANGLE", **obj}
            items.append((float(t_s), encode(obj)))
        self._hand_over(self._deliver_angles, (items, read_monotonic_s))

    def publish(self, obj: dict) -> None:
        """Send one object (DEVICE, STATUS, ...) to every authorized client, watching or not.

        Thread-safe and non-blocking.
        """
        if self._loop is None:
            return
        self._hand_over(self._deliver_all, encode(obj))

    def _hand_over(self, fn: Callable[[Any], None], arg: Any) -> None:
        loop = self._loop
        if loop is None:
            return
        with contextlib.suppress(RuntimeError):  # the loop closed between the check and the call: the hub is stopping
            loop.call_soon_threadsafe(fn, arg)

    def _deliver_angles(self, batch: tuple[list[tuple[float, bytes]], float | None]) -> None:
        items, read_monotonic_s = batch
        now = time.monotonic()
        for client in list(self._clients.values()):
            if client.watch and not client.closing:
                self._for_one_client(self._send_angles, client, items, now)
        if read_monotonic_s is not None and self.latency is not None:
            self.latency.observe(time.monotonic() - read_monotonic_s)

    def _send_angles(self, client: _Client, items: list[tuple[float, bytes]], now: float) -> None:
        """Queue the ANGLE lines of one batch that ``client``'s WATCH policy keeps."""
        rate = client.rate_hz
        if rate is None:
            self._enqueue(client, b"".join(line for _, line in items), now, len(items))
            return
        kept = []
        last = client.last_bucket
        for t_s, line in items:
            bucket = math.floor(t_s * rate)
            if bucket != last:
                kept.append(line)
                last = bucket
        client.last_bucket = last
        if kept:
            self._enqueue(client, b"".join(kept), now, len(kept))

    def _deliver_all(self, line: bytes) -> None:
        now = time.monotonic()
        for client in list(self._clients.values()):
            if client.authorized and not client.closing:
                self._for_one_client(self._enqueue, client, line, now, 1)

    def _for_one_client(self, deliver: Callable[..., None], client: _Client, *args: Any) -> None:
        """``deliver(client, *args)``: an exception costs this client its connection, never another its lines."""
        try:
            deliver(client, *args)
        except Exception as exc:  # noqa: BLE001 - a bug must cost one client, never the hub
            self._client_failed(client, exc)

    def _client_failed(self, client: _Client, exc: Exception) -> None:
        """Log a bug met while serving ``client`` (once: the client is discarded) and discard it.  A client
        that hung up (connection reset, broken pipe) is no bug: that is logged at info."""
        if not client.gone:
            if isinstance(exc, ConnectionError):
                self._log("info", "client_hung_up", client=client.id, peer=str(client.peer), error=repr(exc))
            else:
                self._log("error", "client_failed", client=client.id, peer=str(client.peer), error=repr(exc))
        self._discard(client, "failed")

    # ------------------------------------------------------------------ per-client output

    def _enqueue(self, client: _Client, data: bytes, now: float | None = None, lines: int = 1) -> None:
        if client.gone or client.closing:
            return
        if now is None:
            now = time.monotonic()
        client.queue.append((now, data))
        client.lines_queued += lines
        client.wakeup.set()
        self._check_backlog(client, now)

    def _send_obj(self, client: _Client, obj: dict) -> None:
        try:
            line = encode(obj)
        except (TypeError, ValueError) as exc:
            line = encode({"class": "ERROR", "message": f"internal: reply not serializable: {exc}"})
        self._enqueue(client, line)

    def _send_error(self, client: _Client, message: str, command: str | None = None) -> None:
        self._enqueue(client, encode({"class": "ERROR", "message": message, "command": command}))

    def _close_after_flush(self, client: _Client) -> None:
        """Send what is queued, then close (used after a final ERROR)."""
        if client.gone or client.closing:
            return
        client.queue.append((time.monotonic(), None))
        client.closing = True
        client.wakeup.set()

    def _check_backlog(self, client: _Client, now: float) -> None:
        oldest = client.oldest_t()
        if oldest is None or client.gone:
            return
        age = now - oldest
        if age > self.max_backlog_s:
            self._dropped += 1
            queued = sum(len(b) for _, b in client.queue if b is not None)
            self._log(
                "warning",
                "client_dropped",
                client=client.id,
                peer=str(client.peer),
                backlog_s=round(age, 3),
                queued_bytes=queued,
                reason="not reading",
                dropped_clients=self._dropped,
            )
            self._discard(client, "dropped")

    async def _write_loop(self, client: _Client) -> None:
        writer = client.writer
        try:
            while True:
                while not client.queue:
                    client.wakeup.clear()
                    await client.wakeup.wait()
                batch = []
                close = False
                while client.queue:
                    t, data = client.queue.popleft()
                    if data is None:
                        close = True
                        break
                    if not batch:
                        client.inflight_t = t
                    batch.append(data)
                if batch:
                    payload = b"".join(batch)
                    writer.write(payload)
                    self._bytes_sent += len(payload)
                    await writer.drain()
                client.inflight_t = None
                if close:
                    self._discard(client, "closed_by_server", graceful=True)
                    return
        except (ConnectionError, OSError):
            self._discard(client, "connection_lost")
        except asyncio.CancelledError:
            pass

    def _discard(self, client: _Client, reason: str, graceful: bool = False) -> None:
        """Forget a client: remove it, stop its tasks, close its socket (abort unless ``graceful``)."""
        if client.gone:
            return
        client.gone = True
        client.queue.clear()
        if client.auth_deadline is not None:
            client.auth_deadline.cancel()
        if self._clients.pop(client.id, None) is not None:
            self._clients_per_peer[client.peer_address] -= 1
            if not self._clients_per_peer[client.peer_address]:
                del self._clients_per_peer[client.peer_address]
            if client.watch:
                self._watchers -= 1
        current = asyncio.current_task()
        for task in (client.reader_task, client.writer_task):
            if task is not None and task is not current and not task.done():
                task.cancel()
        transport = client.writer.transport
        if graceful:
            client.writer.close()
        else:
            transport.abort()
        self._log(
            "info",
            "client_disconnected",
            client=client.id,
            peer=str(client.peer),
            reason=reason,
            lines_queued=client.lines_queued,
        )

    # ------------------------------------------------------------------ per-client input

    async def _on_connect(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        peer = writer.get_extra_info("peername")
        refusal = self._refusal(_peer_address(peer))
        if refusal is not None:
            self._refused += 1
            self._log("warning", "client_refused", peer=str(peer), reason=refusal, refused_clients=self._refused)
            writer.write(encode({"class": "ERROR", "message": refusal}))
            writer.close()
            return
        cid = self._next_id
        self._next_id += 1
        sock = writer.get_extra_info("socket")
        if self.sndbuf_bytes is not None and sock is not None:
            with contextlib.suppress(OSError):
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, self.sndbuf_bytes)
        client = _Client(cid, peer, reader, writer, authorized=self._token is None)
        self._clients[cid] = client
        self._clients_per_peer[client.peer_address] += 1
        client.reader_task = asyncio.current_task()
        client.writer_task = asyncio.create_task(self._write_loop(client))
        if not client.authorized and self.auth_deadline_s is not None:
            client.auth_deadline = asyncio.get_running_loop().call_later(
                self.auth_deadline_s, self._auth_deadline_passed, client
            )
        self._log("info", "client_connected", client=cid, peer=str(peer), clients=len(self._clients))
        try:
            self._send_version(client)
            if client.authorized:
                self._send_device(client)
            await self._read_loop(client)
        except asyncio.CancelledError:
            pass
        except Exception as exc:  # noqa: BLE001 - a bug must cost one client, never the hub
            self._client_failed(client, exc)
        finally:
            if not client.closing:
                self._discard(client, "client_closed")
            # after _close_after_flush the writer task sends what is queued, then closes

    def _refusal(self, peer_address: str) -> str | None:
        """Why a new connection from ``peer_address`` is refused (a cap is reached), or None."""
        if len(self._clients) >= self.max_clients:
            return f"too many clients ({self.max_clients}): try again later"
        if self._clients_per_peer[peer_address] >= self.max_clients_per_peer:
            return f"too many connections from {peer_address} ({self.max_clients_per_peer}): try again later"
        return None

    def _auth_deadline_passed(self, client: _Client) -> None:
        client.auth_deadline = None
        if client.authorized or client.gone or client.closing:
            return
        self._log(
            "info", "client_unauthorized", client=client.id, peer=str(client.peer), deadline_s=self.auth_deadline_s
        )
        self._send_error(client, f"not authorized within {self.auth_deadline_s:g} s: closing", "AUTH")
        self._close_after_flush(client)

    def _send_device(self, client: _Client) -> None:
        """The current DEVICE object, when an instrument is known."""
        device = self._device()
        if device:
            self._send_obj(client, {"class": "DEVICE", **device})

    def _send_version(self, client: _Client) -> None:
        try:
            obj = {"class": "VERSION", **self._version()}
        except Exception as exc:  # noqa: BLE001
            obj = {"class": "ERROR", "message": f"version unavailable: {exc}", "command": "VERSION"}
        self._send_obj(client, obj)

    async def _read_loop(self, client: _Client) -> None:
        buf = bytearray()
        discarding = False  # inside an oversized line, up to its newline
        unterminated = 0  # bytes since the last newline (discarded ones included)
        limit = self.max_line_bytes
        while not client.closing:
            chunk = await client.reader.read(READ_CHUNK_BYTES)
            if not chunk:  # the client closed its side: send what is queued (replies), then close
                self._close_after_flush(client)
                return
            start = 0
            while True:
                nl = chunk.find(b"\n", start)
                if nl < 0:
                    rest = chunk[start:]
                    unterminated += len(rest)
                    if unterminated > MAX_UNTERMINATED_BYTES:
                        self._send_error(client, f"more than {MAX_UNTERMINATED_BYTES} bytes without a newline: closing")
                        self._close_after_flush(client)
                        return
                    if not discarding:
                        buf += rest
                        if len(buf) > limit:
                            buf.clear()
                            discarding = True
                            if self._admit(client):
                                self._send_error(client, f"line longer than {limit} bytes: discarded")
                            elif client.closing:
                                return
                    break
                piece = chunk[start:nl]
                start = nl + 1
                unterminated = 0
                if discarding:
                    discarding = False
                    continue
                buf += piece
                line = bytes(buf)
                buf.clear()
                if len(line) > limit:
                    if self._admit(client):
                        self._send_error(client, f"line longer than {limit} bytes: discarded")
                    elif client.closing:
                        return
                    continue
                await self._handle_line(client, line)
                if client.closing or client.gone:
                    return
            await asyncio.sleep(0)  # one client's chunk (up to 64 KiB of lines) at a time: others get their turn

    def _admit(self, client: _Client) -> bool:
        """Rate limit on every line received (a command, an empty line, an oversized one): True when it
        may proceed; otherwise it is refused with ERROR (and after MAX_EXCESS_COMMANDS refusals the
        client is closed: ``client.closing``)."""
        now = time.monotonic()
        if now - client.window_start >= COMMAND_WINDOW_S:
            client.window_start = now
            client.window_count = 0
        client.window_count += 1
        if client.window_count <= MAX_COMMANDS_PER_S:
            return True
        client.excess += 1
        if client.excess >= MAX_EXCESS_COMMANDS:
            self._send_error(client, f"{MAX_EXCESS_COMMANDS} commands over the rate limit: closing")
            self._close_after_flush(client)
        else:
            self._send_error(client, f"more than {MAX_COMMANDS_PER_S} commands per second: refused")
        return False

    async def _handle_line(self, client: _Client, raw: bytes) -> None:
        if not self._admit(client):  # every line counts, an empty or blank one too
            return
        text = raw.decode("utf-8", errors="replace").strip()
        if not text:
            return
        if text.endswith(";"):
            text = text[:-1].rstrip()
        m = _COMMAND_RE.match(text)
        if m is None:
            self._send_error(client, "not a command: expected ?NAME; or ?NAME={json object};")
            return
        name, payload = m.group(1), m.group(2)
        args: dict = {}
        if payload is not None and payload.strip():
            try:
                args = json.loads(payload)
            except (ValueError, RecursionError) as exc:  # 4 KiB of "[" nests deeper than Python recurses
                self._send_error(client, f"invalid JSON: {str(exc) or type(exc).__name__}", name)
                return
            if not isinstance(args, dict):
                self._send_error(client, "the argument must be a JSON object", name)
                return
        if name == "WATCH":
            self._cmd_watch(client, args, payload is not None)
        elif name == "VERSION":
            self._send_version(client)
        elif name == "AUTH":
            self._cmd_auth(client, args)
        elif not client.authorized:
            self._send_error(client, "unauthorized", name)
        else:
            await self._cmd_control(client, name, args)

    def _cmd_watch(self, client: _Client, args: dict, has_args: bool) -> None:
        if has_args:
            enable = args.get("enable", True)
            if not isinstance(enable, bool):
                self._send_error(client, "enable must be true or false", "WATCH")
                return
            rate = args.get("rate_hz")
            if rate is not None and not (_is_positive_finite(rate) and rate <= MAX_WATCH_RATE_HZ):
                self._send_error(client, f"rate_hz must be a number > 0 and <= {MAX_WATCH_RATE_HZ}", "WATCH")
                return
            if enable != client.watch:
                self._watchers += 1 if enable else -1
            client.watch = enable
            client.rate_hz = rate
            client.last_bucket = None
        self._send_obj(client, {"class": "WATCH", "enable": client.watch, "rate_hz": client.rate_hz})

    def _cmd_auth(self, client: _Client, args: dict) -> None:
        """``?AUTH``: compare the token (unless the peer address is in its backoff), authorize or refuse."""
        if self._token is None:
            self._authorize(client)
            return
        now = time.monotonic()
        wait_s = self._auth_throttle.blocked_for_s(client.peer_address, now)
        if wait_s > 0:
            self._refuse_auth(client, f"too many failed attempts, retry in {math.ceil(wait_s)} s")
            return
        token = args.get("token")
        # surrogatepass: a lone surrogate ("\ud800") is a wrong token like any other, never an exception
        if isinstance(token, str) and hmac.compare_digest(
            token.encode("utf-8", "surrogatepass"), self._token.encode("utf-8")
        ):
            self._auth_throttle.succeeded(client.peer_address)
            self._authorize(client)
            return
        blocked_s = self._auth_throttle.failed(client.peer_address, now)
        self._log(
            "warning",
            "auth_failed",
            client=client.id,
            peer=str(client.peer),
            failures=client.auth_failures + 1,
            blocked_s=blocked_s,
        )
        self._refuse_auth(client, "bad token")

    def _authorize(self, client: _Client) -> None:
        """AUTH, then (when this authorized the client) the DEVICE it did not get before."""
        newly = not client.authorized
        client.authorized = True
        if client.auth_deadline is not None:
            client.auth_deadline.cancel()
            client.auth_deadline = None
        self._send_obj(client, {"class": "AUTH", "authorized": True})
        if newly:
            self._send_device(client)

    def _refuse_auth(self, client: _Client, message: str) -> None:
        """ERROR for a failed or refused ``?AUTH``; the MAX_AUTH_FAILURES-th closes the connection."""
        client.auth_failures += 1
        if client.auth_failures >= MAX_AUTH_FAILURES:
            self._send_error(client, f"{message}: closing", "AUTH")
            self._close_after_flush(client)
        else:
            self._send_error(client, message, "AUTH")

    async def _cmd_control(self, client: _Client, name: str, args: dict) -> None:
        """Hand a command to ``control`` in a worker thread and send its answer (or an ERROR) to ``client``.

        The callback and a Future it returns share ``control_timeout_s``.
        """
        loop = asyncio.get_running_loop()
        deadline = loop.time() + self.control_timeout_s
        pool = self._control_pool
        try:
            if pool is None:
                raise RuntimeError("the hub is stopping")
            reply = await self._answer_of(pool.submit(self._control, name, args, client.id), deadline)
            if isinstance(reply, concurrent.futures.Future):
                reply = await self._answer_of(reply, deadline)
        except _NoAnswer:
            self._send_error(client, f"no answer within {self.control_timeout_s:g} s", name)
            return
        except concurrent.futures.CancelledError:
            self._send_error(client, "the command was cancelled", name)
            return
        except Exception as exc:  # noqa: BLE001 - the service's error becomes the client's ERROR
            message = str(exc) or type(exc).__name__
            self._send_error(client, message, name)
            return
        if not isinstance(reply, dict):
            self._send_error(client, f"unknown command ?{name}" if reply is None else "internal: bad reply", name)
            return
        if "class" not in reply:
            reply = {"class": name, **reply}
        elif reply["class"] == "ERROR" and "command" not in reply:
            reply = {**reply, "command": name}
        self._send_obj(client, reply)

    @staticmethod
    async def _answer_of(future: concurrent.futures.Future, deadline: float) -> Any:
        """``future``'s result (its exception raised), waited for until ``deadline`` (loop time).

        Raises ``_NoAnswer`` when the deadline passes first.  Only the *wait* ends on a
        timeout or when the calling task is cancelled (the client hung up): ``future``
        itself is never cancelled, so whoever completes it later (the acquisition
        thread) never finds it cancelled.  (``asyncio.wrap_future`` would cancel it.)
        """
        loop = asyncio.get_running_loop()
        settled: asyncio.Future = loop.create_future()

        def on_done(_: concurrent.futures.Future) -> None:  # in whichever thread completed ``future``
            with contextlib.suppress(RuntimeError):  # the loop has closed: the hub stopped, nobody waits any more
                loop.call_soon_threadsafe(_settle, settled)

        if not future.done():
            future.add_done_callback(on_done)
            try:
                await asyncio.wait_for(settled, max(0.0, deadline - loop.time()))
            except TimeoutError:
                raise _NoAnswer from None
        return future.result()
