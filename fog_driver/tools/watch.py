"""``fog-driver watch``: a live view of a running daemon, over its NDJSON client protocol.

The client connects to the daemon (default ``127.0.0.1:2948``) through the client library
(``fog_driver.client.Client``, without reconnecting: a lost connection ends the watch), reads the
``VERSION`` greeting, sends
``?WATCH={"enable":true,"rate_hz":R};`` and then shows what arrives: the instrument's identity and the
device state, the latest ``ANGLE`` (compensated and raw, in arcsec and in deg-min-sec; the rate averaged
over the last second of device time, the drift in deg/h; the three temperatures; the flags), the latest
``STATUS`` counters (every scalar key, sorted), the last ``ERROR`` and how many ``ANGLE`` objects arrive
per second.  Banners above it say what the operator must know first: ``LINK DOWN`` (the daemon's port is
closed), ``NO DATA for N s`` (no ANGLE for ``NO_DATA_S`` or more), and ``bias not removed`` while the
daemon's STATUS says no ``?BIAS`` capture was made (at rest the angle then climbs with Earth rate plus
the gyro's bias), or how far a running capture is.

The rate shown is the mean of *every* frame's rate over the last ``RATE_AVERAGE_S`` (1 s) of device time, the
decimated ones included (``client.display.RateAverage``, the web view's code too: between two decimated ANGLE
objects the angle's difference over the device time, 1 arcsec/s = 1 deg/h), which a single sample's
``rate_dph`` (quantized to one count per frame period: 1 deg/h steps at 100 Hz) is not.  It is shown to
0.01 deg/h.  The average starts again after frames were lost (the first sample flagged ``gap``; the samples
flagged while the estimate settles afterwards are averaged), device time going backwards, and this watch's
``?ZERO``.

On a terminal the view is a fixed block redrawn in place (cursor home, clear to end of line and of
screen; at most 10 redraws a second), and when stdin is a terminal too, keys act at once (stdin in
cbreak mode, restored on every exit, Ctrl-Z included): ``q`` quits, ``z`` sends ``?ZERO``, ``b`` sends
``?BIAS`` (``bias_s`` seconds, 60 by default), whose result shows in the banner.  Anywhere else (a pipe,
a log file, a test) it prints one line when the server says who it is, one per ``DEVICE`` change,
``ERROR`` and ``BIAS`` event, and one compact line per second.  With ``json_lines`` it prints the
daemon's lines themselves, unchanged, one per line and flushed (like ``gpspipe -w``).

The reader is defensive: a line is at most 64 KiB (longer ones, which the client library reports as a
``ProtocolError``, are skipped up to their newline and counted), lines
that are not a JSON object with a string ``"class"`` are skipped and counted, unknown classes are
counted and ignored, unknown keys are ignored (except in ``STATUS``, whose scalar keys are all shown),
and absent or ``null`` values show as ``-``, never ``None``.

No samples: the view says so (``NO DATA for N s (REASON)``, the reason from what the daemon said last:
``link down`` from DEVICE ``deactivated`` or STATUS ``port_state``, ``port open, no samples from the
instrument``, ``?WATCH refused, unauthorized``) and waits, as an operator watching a daemon whose link is
down wants: the daemon reconnects by itself.  A bounded watch does not wait for ever: with ``count`` or
``duration_s`` (a script's form), at a terminal or not, ``idle_s`` (``DEFAULT_IDLE_S``, 10 s) of host time
without an ANGLE (since the last one, or since the watch started) ends it with a ``TemporaryFailure``
(exit 75) ``no samples for N s from HOST:PORT: REASON``, after the last view.  Without ``count`` and
``duration_s`` it waits as long as it runs, at a terminal and elsewhere alike (a log of one line a second
that carries on through a link's outage, as a logger under ``nohup`` or a service wants), unless ``idle_s``
is given: then it bounds that watch too.

``run_watch`` returns 0 when ``count`` ANGLE objects were shown, ``duration_s`` elapsed, the user pressed
``q`` or Ctrl-C, or the reader of ``--json`` output went away; 1 (after a one-line note) when the
server closed or lost the connection.  A daemon that refuses the ``?WATCH`` itself (its ``rate_hz``, say: a
daemon takes ``0 < rate_hz <= 10000``) ends it at once with a ``CommandRefused`` (exit 65) ``the daemon at
HOST:PORT refused ?WATCH: MESSAGE``, after the view's last line; ``unauthorized`` does not (above).  A
daemon that cannot be reached (refused, or a peer that closes or never greets) is a one-line ``DeviceError``
at once.  ``format_dms``, ``render`` and ``compact_line`` are pure and tested on their own.
"""

from __future__ import annotations

import contextlib
import math
import os
import select
import sys
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, TextIO

from ..client import Client, CommandRefused, ConnectionLost, Message, ProtocolError
from ..client.display import DEFAULT_BIAS_S, NO_DATA_S, format_arcsec, format_dms, no_samples_reason
from ..client.protocol import printable
from ..client.wire import (
    DEFAULT_HOST,
    DEFAULT_PORT,
    MAX_LINE_BYTES,
    TOKEN_ENV,
    LineReader,
    format_address,
    parse_address,
    parse_line,
    read_token,
)
from ..errors import TemporaryFailure, UsageError
from .live import RATE_AVERAGE_S, LiveView
from .render import compact_line, render
from .terminal import Keys, isatty

__all__ = [
    "DEFAULT_BIAS_S",
    "DEFAULT_HOST",
    "DEFAULT_IDLE_S",
    "DEFAULT_PORT",
    "MAX_LINE_BYTES",
    "NO_DATA_S",
    "RATE_AVERAGE_S",
    "TOKEN_ENV",
    "LineReader",
    "compact_line",
    "format_arcsec",
    "format_address",
    "format_dms",
    "idle_limit_s",
    "parse_address",
    "parse_line",
    "render",
    "run_watch",
    "watch_command",
]

EXIT_OK = 0
EXIT_CONNECTION_CLOSED = 1

#: A watch with ``count`` or ``duration_s`` ends (exit 75) after this many host seconds without an ANGLE.
DEFAULT_IDLE_S = 10.0

_POLL_S = 0.1  # longest a wait for the socket or a key lasts before the view gets a chance to refresh


def _watch_request(rate_hz: float | None) -> dict[str, Any]:
    request: dict[str, Any] = {"enable": True}
    if rate_hz is not None:
        request["rate_hz"] = int(rate_hz) if float(rate_hz).is_integer() else float(rate_hz)
    return request


def idle_limit_s(count: int | None, duration_s: float | None, idle_s: float | None) -> float | None:
    """How long a watch waits without a sample before it ends (exit 75): ``idle_s`` when given, else
    ``DEFAULT_IDLE_S`` for a bounded watch (``count`` or ``duration_s``), else None (it waits on)."""
    if idle_s is not None:
        return idle_s
    return DEFAULT_IDLE_S if count is not None or duration_s is not None else None


def _idle_error(address: str, idle_s: float, state: dict[str, Any]) -> TemporaryFailure:
    """``no samples for IDLE_S s from ADDRESS: REASON`` (the limit reached, not the host time measured)."""
    reason = no_samples_reason(state) or "the daemon said nothing of its instrument"
    seconds = f"{idle_s:.0f}" if idle_s >= 10 else f"{idle_s:.1f}"
    return TemporaryFailure(f"no samples for {seconds} s from {address}: {reason}")


def _check_arguments(
    count: int | None, duration_s: float | None, idle_s: float | None, rate_hz: float | None, bias_s: float
) -> None:
    if count is not None and (isinstance(count, bool) or not isinstance(count, int) or count < 1):
        raise UsageError(f"--count must be a whole number >= 1, not {count!r}")
    if duration_s is not None and not duration_s > 0:
        raise UsageError(f"--duration must be > 0 s, not {duration_s!r}")
    if idle_s is not None and not (idle_s > 0 and math.isfinite(idle_s)):
        raise UsageError(f"--idle-s must be > 0 s, not {idle_s!r}")
    if rate_hz is not None and not (rate_hz > 0 and math.isfinite(rate_hz)):
        raise UsageError(f"--rate-hz must be > 0, not {rate_hz!r}")
    if not 1 <= bias_s <= 86400:
        raise UsageError(f"the bias seconds must be between 1 and 86400, not {bias_s!r}")


def run_watch(
    host: str = DEFAULT_HOST,
    port: int = DEFAULT_PORT,
    *,
    rate_hz: float | None = 10.0,
    count: int | None = None,
    duration_s: float | None = None,
    out: TextIO | None = None,
    timeout_s: float = 5.0,
    token: str | None = None,
    json_lines: bool = False,
    keys: TextIO | None = None,
    bias_s: float = DEFAULT_BIAS_S,
    idle_s: float | None = None,
) -> int:
    """Watch a running daemon until ``count`` ANGLE objects, ``duration_s`` seconds, ``q``, Ctrl-C or disconnect.

    ``out`` defaults to ``sys.stdout`` (looked up at call time).  ``timeout_s`` bounds the connection attempt
    and the wait for the daemon's VERSION greeting.  ``token``: sent with ``?AUTH`` first (a daemon with a
    token closes a client that has not authorized within its auth deadline).  ``json_lines``: print the
    daemon's lines unchanged instead of the view.  ``keys``: a terminal to read keys from (``q``, ``z``, ``b``
    with ``bias_s``); it is put in cbreak mode and restored on every exit.  ``idle_s``: the host seconds without
    an ANGLE that end the watch (``idle_limit_s``: 10 with ``count`` or ``duration_s``, else none unless given).
    Returns 0 (count reached, duration elapsed, ``q``, Ctrl-C, the reader of ``json_lines`` gone) or 1 (the
    server closed or lost the connection; a one-line note says so).  Raises ``DeviceError`` when the daemon
    cannot be reached, ``TemporaryFailure`` (exit 75) after ``idle_s`` without a sample, ``CommandRefused``
    (exit 65) when the daemon refuses the ``?WATCH`` (but for ``unauthorized``), ``UsageError`` for bad
    arguments.
    """
    if out is None:
        out = sys.stdout
    _check_arguments(count, duration_s, idle_s, rate_hz, bias_s)
    idle_limit = idle_limit_s(count, duration_s, idle_s)
    # keep_unknown: the view counts unknown classes and --json passes them on; idle_periods None: the view shows
    # how long no data came (NO DATA) and waits on, as an operator watching a stopped daemon wants
    conn = Client((host, port), timeout_s=timeout_s, reconnect=False, keep_unknown=True, idle_periods=None)
    conn.connect()  # ConnectError (a DeviceError): exit 69, at once
    watch: LiveView | None = None
    key_reader: Keys | None = None
    try:
        started = time.monotonic()
        ends = _Ends(count, None if duration_s is None else started + duration_s, idle_limit)
        if json_lines:
            return _pass_through(conn, out, token, rate_hz, ends, started)
        watch = LiveView(conn.address, out, started, keys=keys is not None)
        if keys is not None:
            key_reader = Keys(keys, on_resume=watch.redraw_all)
        return _view(conn, watch, key_reader, token, rate_hz, ends, bias_s)
    except KeyboardInterrupt:
        if watch is not None:
            with contextlib.suppress(OSError, ValueError, KeyboardInterrupt):
                watch.finish(time.monotonic())
        return EXIT_OK
    finally:
        if key_reader is not None:
            key_reader.restore()
        if watch is not None:
            watch.restore()
        conn.close()


@dataclass(frozen=True)
class _Ends:
    """What ends a watch besides ``q``, Ctrl-C and the server: ``count`` ANGLE objects, the host ``deadline``,
    ``idle_s`` without an ANGLE (None: no such end)."""

    count: int | None
    deadline: float | None
    idle_s: float | None

    def wait_s(self, now: float) -> float:
        """How long a wait for the socket or a key may last (``_POLL_S``, less before the deadline)."""
        return _POLL_S if self.deadline is None else max(0.001, min(_POLL_S, self.deadline - now))


def _refused(conn: Client, obj: Mapping[str, Any]) -> CommandRefused | None:
    """The daemon's ``ERROR`` to ``?WATCH`` as the error that ends the watch (exit 65, ``the daemon at ADDRESS
    refused ?WATCH: MESSAGE``: asked again it would refuse again), or None: another line, or ``unauthorized``
    (the watch waits on, saying so, as for a link that is down)."""
    if not (obj.get("class") == "ERROR" and obj.get("command") == "WATCH"):
        return None
    message = obj.get("message")
    if message == "unauthorized":
        return None
    shown = printable(message) if isinstance(message, str) else "(no message)"
    return CommandRefused(f"the daemon at {conn.address} refused ?WATCH: {shown}", message=shown, command="WATCH")


def _greet(conn: Client, token: str | None, rate_hz: float | None) -> None:
    """?AUTH (when there is a token) and ?WATCH, without waiting: their answers come with the rest."""
    try:
        if token:
            conn.send("AUTH", {"token": token})
        conn.send("WATCH", _watch_request(rate_hz))
    except ConnectionLost:
        pass  # the server went away at once: what it sent is still read, then EOF


def _counts(watch: LiveView, conn: Client) -> None:
    """The lines the client library skipped: malformed, and oversized among them."""
    watch.state["malformed"] = conn.malformed
    if conn.session.reader.oversized:
        watch.state["oversized"] = conn.session.reader.oversized


def _poll(conn: Client, timeout_s: float | None) -> Message | None:
    """``conn.poll``; None for an over-long line too (skipped: the client library counts it in
    ``session.reader.oversized``)."""
    try:
        return conn.poll(timeout_s)
    except ProtocolError:
        return None


def _lost(watch: LiveView, conn: Client, exc: ConnectionLost) -> int:
    what = "closed the connection" if exc.reason.endswith("closed the connection") else exc.reason
    watch.finish(
        time.monotonic(), f"fog-driver watch: {conn.address} {what} ({watch.state['angles']:,} ANGLE received)"
    )
    return EXIT_CONNECTION_CLOSED


def _view(
    conn: Client,
    watch: LiveView,
    keys: Keys | None,
    token: str | None,
    rate_hz: float | None,
    ends: _Ends,
    bias_s: float,
) -> int:
    """The view's loop: messages from the daemon, keys from the terminal, a redraw or a log line when due."""
    _greet(conn, token, rate_hz)
    watch.tick(time.monotonic())
    while True:
        now = time.monotonic()
        try:
            while (message := _poll(conn, 0)) is not None:  # what has arrived, without waiting
                _counts(watch, conn)
                watch.handle(dict(message.raw), now)
                if (refusal := _refused(conn, message.raw)) is not None:
                    watch.finish(now)
                    raise refusal
                if ends.count is not None and watch.state["angles"] >= ends.count:
                    watch.finish(now)
                    return EXIT_OK
            _counts(watch, conn)
        except ConnectionLost as exc:
            _counts(watch, conn)
            return _lost(watch, conn, exc)
        if ends.deadline is not None and now >= ends.deadline:
            watch.finish(now)
            return EXIT_OK
        if ends.idle_s is not None and watch.idle_s(now) >= ends.idle_s:
            watch.finish(now)
            raise _idle_error(conn.address, ends.idle_s, watch.state)
        watch.tick(now)
        readable = select.select([conn] + ([keys.fd] if keys else []), [], [], ends.wait_s(now))[0]
        if keys is not None and keys.fd in readable:
            for key in keys.read().decode("ascii", "replace").lower():
                if key == "q":
                    watch.finish(time.monotonic())
                    return EXIT_OK
                command = {"z": ("ZERO", None), "b": ("BIAS", {"seconds": bias_s})}.get(key)
                if command is not None:
                    watch.state["action"] = f"?{command[0]} sent"
                    with contextlib.suppress(ConnectionLost):  # the next read says so
                        conn.send(*command)


def _pass_through(
    conn: Client, out: TextIO, token: str | None, rate_hz: float | None, ends: _Ends, started: float
) -> int:
    """``--json``: every protocol line of the daemon, unchanged, one per line, flushed (``gpspipe -w``);
    malformed lines are dropped.  Ends as the view does (``idle_s`` without an ANGLE too, its reason from the
    last DEVICE, STATUS and refused ``?WATCH`` passed through); a reader that went away (``| head -3``) is exit 0,
    with stdout pointed at /dev/null so the interpreter's last flush cannot complain."""
    _greet(conn, token, rate_hz)
    angles = 0
    last_angle_at = started
    said: dict[str, Any] = {}  # what no_samples_reason reads: the last DEVICE and STATUS, a refused ?WATCH
    try:
        while True:
            now = time.monotonic()
            if ends.deadline is not None and now >= ends.deadline:
                return EXIT_OK
            if ends.idle_s is not None and now - last_angle_at >= ends.idle_s:
                raise _idle_error(conn.address, ends.idle_s, said)
            try:
                limits = [ends.deadline, None if ends.idle_s is None else last_angle_at + ends.idle_s]
                due = [at - now for at in limits if at is not None]
                message = _poll(conn, max(0.001, min(due)) if due else None)
            except ConnectionLost as exc:
                print(f"fog-driver watch: {conn.address} {exc.reason}", file=sys.stderr)
                return EXIT_CONNECTION_CLOSED
            if message is None:
                continue
            out.write(message.line.decode("utf-8") + "\n")
            out.flush()
            cls = message.raw.get("class")
            if cls in ("DEVICE", "STATUS"):
                said[str(cls).lower()] = dict(message.raw)
            elif cls == "ERROR" and message.raw.get("command") == "WATCH":
                if (refusal := _refused(conn, message.raw)) is not None:
                    raise refusal
                said["watch_refused"] = message.raw.get("message")
            elif cls == "ANGLE":
                last_angle_at = time.monotonic()
                angles += 1
                if ends.count is not None and angles >= ends.count:
                    return EXIT_OK
    except BrokenPipeError:
        _stdout_to_devnull(out)
        return EXIT_OK


def _stdout_to_devnull(out: TextIO) -> None:
    """After EPIPE on stdout: point its descriptor at /dev/null, so nothing complains at exit."""
    if out is not sys.stdout:
        return
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError):
        pass


def watch_command(
    address: str | None,
    *,
    rate_hz: float | None = 10.0,
    count: int | None = None,
    duration_s: float | None = None,
    json_lines: bool = False,
    token_file: str | None = None,
    bias_s: float = DEFAULT_BIAS_S,
    idle_s: float | None = None,
) -> int:
    """``fog-driver watch [HOST:PORT]``: parse the address and run the watch on stdout (the token, if the daemon
    has one, from ``token_file`` or the environment variable ``FOG_DRIVER_TOKEN``).  Keys work when stdin and
    stdout are both terminals (and not with ``json_lines``)."""
    host, port = parse_address(address)
    token = read_token(token_file)
    keys = sys.stdin if not json_lines and isatty(sys.stdin) and isatty(sys.stdout) else None
    return run_watch(
        host,
        port,
        rate_hz=rate_hz,
        count=count,
        duration_s=duration_s,
        token=token,
        json_lines=json_lines,
        keys=keys,
        bias_s=bias_s,
        idle_s=idle_s,
    )
