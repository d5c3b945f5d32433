"""A client library for station software: read the compensated angle from ``fog-driver run`` and control it.

Blocking::

    from fog_driver.client import Client

    with Client("127.0.0.1:2948", token=None) as c:     # token: the daemon's, when it has one
        for a in c.angles(rate_hz=10):                     # ?WATCH, decimated by device time
            print(a.seq, a.t_s, a.angle_arcsec, a.drift_dph, a.drift_sigma_dph, a.temps_c, a.flags)
            if a.gap_before:                               # samples missed across a reconnect
                print("missed", a.gap_before.missed)

asyncio::

    async with AsyncClient("127.0.0.1:2948") as c:
        async for a in c.angles(rate_hz=10):
            ...

Control, each returning the daemon's answer or raising a typed error (``CommandRefused``, ``Unauthorized``,
``UnknownCommand``, ``BiasFailed``, ``ConnectionLost``, ``NoReply``, ``ProtocolError``): ``zero()``,
``bias(seconds)`` (waits for the capture's result), ``adapt(enable, reference_dph)``, ``save()``, ``reload()``,
``status()``.

The objects are frozen dataclasses with units in their field names: ``Angle``, ``Device``, ``Status`` and
``Version`` (both name the model in use: ``model_file``, a ``ModelInUse``), ``Bias``, ``Reply`` (``?ZERO``,
``?ADAPT`` ... answers), ``ErrorReply``, ``Other`` (a class this library does not know); each keeps the
daemon's object (``raw``) for keys a newer daemon adds.  A lost
connection is made again with backoff (0.5 s doubling up to 30 s, each attempt logged as a warning through the
standard ``logging`` module, logger ``fog_driver.client``), never
silently: the first ``Angle`` after it carries ``gap_before`` (``Gap``: the sequence numbers either side, the
samples missed, the time without a connection), and ``reconnects`` counts them.  ``reconnect=False`` raises
``ConnectionLost`` instead.  A daemon that cannot be reached at the first ``connect`` is a ``ConnectError`` at
once.

Bounded memory and time: a client holds at most ``max_buffered_bytes`` (4 MiB by default) for its caller, the
oldest messages dropped beyond it (``angles_dropped``, ``messages_dropped``); messages of an unknown class are
dropped, not queued (``keep_unknown=True`` queues them for ``messages()``); a line over 64 KiB is a
``ProtocolError`` in its place (the connection stays; no reconnection for it).  Every wait has a deadline that
bytes arriving do not extend, ``angles(timeout_s=...)`` in both clients; while watching, a daemon that sends no
line for ``idle_timeout_s()`` (``max(idle_min_s, idle_periods * the period between samples)``, 5 s at least
by default) is taken for dead and handled as a lost connection.

The layers: ``address`` (``HOST:PORT``), ``wire`` (lines, the token file), ``messages`` (typed
objects), ``session`` (the protocol without I/O: bytes in, messages out, which answer belongs to which command,
the gap across connections), ``blocking`` and ``aio`` (the sockets; ``AsyncClient`` and asyncio are imported on
first use).  Beside them: ``udp`` (the UDP datagram's layout and decoder) and ``display`` (how the operator's
views, ``fog-driver watch``, ``ctl`` and the web page, format the numbers).  The standard library only: no
numpy, yaml or structlog.  The protocol itself is the docstring of
``fog_driver/daemon/connection.py``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from .blocking import Client
from .errors import (
    BiasFailed,
    ClientError,
    CommandRefused,
    ConnectError,
    ConnectionLost,
    NoReply,
    ProtocolError,
    Unauthorized,
    UnknownCommand,
)
from .messages import (
    Angle,
    Bias,
    Device,
    ErrorReply,
    Gap,
    Message,
    ModelInUse,
    Other,
    Reply,
    Status,
    Version,
    since_bias_sigma_dph,
)
from .session import Session
from .wire import DEFAULT_HOST, DEFAULT_PORT, TOKEN_ENV, read_token

if TYPE_CHECKING:
    from .aio import AsyncClient

__all__ = [
    "DEFAULT_HOST",
    "DEFAULT_PORT",
    "TOKEN_ENV",
    "Angle",
    "AsyncClient",
    "Bias",
    "BiasFailed",
    "Client",
    "ClientError",
    "CommandRefused",
    "ConnectError",
    "ConnectionLost",
    "Device",
    "ErrorReply",
    "Gap",
    "Message",
    "ModelInUse",
    "NoReply",
    "Other",
    "ProtocolError",
    "Reply",
    "Session",
    "Status",
    "Unauthorized",
    "UnknownCommand",
    "Version",
    "read_token",
    "since_bias_sigma_dph",
]


def __getattr__(name: str) -> object:
    """``AsyncClient`` on first use: asyncio is most of the library's import time, and a blocking client
    (``fog-driver watch``, ``ctl``) never needs it."""
    if name == "AsyncClient":
        from .aio import AsyncClient  # start-up time

        globals()["AsyncClient"] = AsyncClient
        return AsyncClient
    raise AttributeError(f"module 'fog_driver.client' has no attribute {name!r}")
