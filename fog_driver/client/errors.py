"""What the client library raises.  Each is a ``FogDriverError``: one line of text, and the sysexits status
``fog-driver watch`` and ``fog-driver ctl`` exit with."""

from __future__ import annotations

import os

from ..errors import DeviceError, FogDriverError

__all__ = [
    "BiasFailed",
    "ClientError",
    "CommandRefused",
    "ConnectError",
    "ConnectionLost",
    "NoReply",
    "ProtocolError",
    "Unauthorized",
    "UnknownCommand",
]


class ClientError(FogDriverError):
    """Base of the client library's errors."""

    exit_status = os.EX_UNAVAILABLE  # 69


class ConnectError(ClientError, DeviceError):
    """The daemon cannot be reached: refused, no route, a peer that closes or never sends its VERSION
    greeting, or the daemon's refusal of another connection (too many clients)."""


class ConnectionLost(ClientError, DeviceError):
    """The connection went while a command waited for its answer (a command is never sent twice: it may have
    been carried out), or for good (a client made with ``reconnect=False``, or closed).  ``reason`` says how,
    in words (``the daemon closed the connection``, ``lost the connection: ...``)."""

    def __init__(self, text: str, reason: str = "") -> None:
        super().__init__(text)
        self.reason = reason or text


class NoReply(ClientError):
    """No answer within the time allowed."""


class ProtocolError(ClientError):
    """The daemon broke the protocol: a line over 64 KiB (``wire.MAX_LINE_BYTES``), or that many bytes without
    a newline.  The line is dropped up to its newline, the connection stays open and is not made again for it
    (a peer that sends such lines would send them again): the reading call raises it once, in the place of
    the line, after the messages that came before it; a caller that wants to may go on reading.  Exit 76
    (EX_PROTOCOL)."""

    exit_status = os.EX_PROTOCOL  # 76


class CommandRefused(ClientError):
    """The daemon refused a command (its ``ERROR``): ``message`` is its reason, ``command`` the command."""

    exit_status = os.EX_DATAERR  # 65

    def __init__(self, text: str, *, message: str = "", command: str | None = None) -> None:
        super().__init__(text)
        self.message = message
        self.command = command


class Unauthorized(CommandRefused):
    """The daemon wants a token for this, or refused the one given."""

    exit_status = os.EX_NOPERM  # 77


class UnknownCommand(CommandRefused):
    """The daemon does not know the command (an older fog-driver)."""

    exit_status = os.EX_USAGE  # 64


class BiasFailed(CommandRefused):
    """A ``?BIAS`` capture was started and then abandoned (its data did not come in time); the bias in use
    was kept."""
