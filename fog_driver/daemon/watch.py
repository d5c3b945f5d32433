"""``fog-driver watch``: a live view of a running daemon, over its NDJSON client protocol.

The client connects to the daemon (default ``127.0.0.1:2948``), reads the
``VERSION`` (and possibly ``DEVICE``) greeting, sends
``?WATCH={"enable":true,"rate_hz":R};`` and then shows what arrives: the
instrument's identity and the device state, the latest ``ANGLE`` (compensated
and raw, in arcsec and in deg-min-sec; rate and drift in deg/h; the three
temperatures; the flags), the latest ``STATUS`` counters (every scalar key,
sorted), the last ``ERROR`` and how many ``ANGLE`` objects arrive per second.

On a terminal the view is a fixed block redrawn in place (cursor home, clear to
end of line and of screen; at most 10 redraws a second).  Anywhere else (a pipe,
a log file, a test) it prints one line when the server says who it is, one per
``DEVICE`` change and ``ERROR``, and one compact line per second.

The reader is defensive: a line is at most 64 KiB (longer ones are skipped up
to their newline), lines that are not a JSON object with a string ``"class"``
are skipped and counted, unknown classes are counted and ignored, unknown keys
are ignored (except in ``STATUS``, whose scalar keys are all shown), and absent
or ``null`` values show as ``-``, never ``None``.

``run_watch`` returns 0 when ``count`` ANGLE objects were shown, ``duration_s``
elapsed or the user pressed Ctrl-C, and 1 (after a one-line note) when the
server closed or lost the connection.  A daemon that cannot be reached is a
one-line ``DeviceError``.  ``parse_line``, ``format_dms``, ``render`` and
``compact_line`` are pure and tested on their own.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import socket
import sys
import time
from collections import deque
from collections.abc import Mapping
from decimal import ROUND_HALF_UP, Decimal
from typing import Any, TextIO

from ..config import parse_host_port
from ..errors import DeviceError, UsageError

__all__ = [
    "DEFAULT_HOST",
    "DEFAULT_PORT",
    "MAX_LINE_BYTES",
    "LineReader",
    "compact_line",
    "format_arcsec",
    "format_address",
    "format_dms",
    "parse_address",
    "parse_line",
    "render",
    "run_watch",
    "watch_command",
]

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 2948
MAX_LINE_BYTES = 64 * 1024  # a protocol line longer than this (without its newline) is skipped

EXIT_OK = 0
EXIT_CONNECTION_CLOSED = 1

_TTY_MIN_REDRAW_S = 0.1  # at most 10 redraws a second
_TTY_REFRESH_S = 1.0  # redraw at least this often (ages and rates move even without data)
_LINE_PERIOD_S = 1.0  # non-tty: one compact line per second
_RATE_WINDOW_S = 2.0  # ANGLE objects per second, counted over this window
_POLL_S = 0.1  # longest a recv() waits before the view gets a chance to refresh
_RECV_BYTES = 65536

_HIDE_CURSOR = "\x1b[?25l"
_SHOW_CURSOR = "\x1b[?25h"
_HOME = "\x1b[H"
_CLEAR_SCREEN = "\x1b[2J"
_CLEAR_EOL = "\x1b[K"
_CLEAR_EOS = "\x1b[J"

_MISSING = "-"
_DEGREE = "\u00b0"


# --------------------------------------------------------------------------- pure helpers


def parse_line(line: bytes) -> dict[str, Any] | None:
    """One protocol line -> its JSON object, or ``None`` when it is not a usable protocol object.

    Surrounding whitespace (the newline, a ``\\r``) is ignored.  ``None`` for: an empty line,
    a line over ``MAX_LINE_BYTES``, bytes that are not UTF-8, text that is not JSON, JSON that
    is not an object, and an object without a string ``"class"``.
    """
    if len(line) > MAX_LINE_BYTES + 2:  # room for "\r\n"
        return None
    line = line.strip()
    if not line or len(line) > MAX_LINE_BYTES:
        return None
    try:
        obj = json.loads(line.decode("utf-8"))
    except (UnicodeDecodeError, ValueError, RecursionError):
        return None
    if not isinstance(obj, dict) or not isinstance(obj.get("class"), str):
        return None
    return obj


#: From this size on (arcsec) an angle is shown as it is, not rounded to 0.01": a float's hundredths
#: are noise there, and from 1e26 on the rounding's 28 decimal digits cannot even hold them.
_ROUNDED_BELOW_ARCSEC = 1e15


def _unrounded(arcsec: float) -> str | None:
    """An angle that is not rounded to 0.01" as plain text (``nan``, ``inf``, ``-inf``, ``1e+30``,
    ``1.000000e+400`` for an integer beyond float's range: any number too large for a float), or
    None for one that is."""
    try:
        value = float(arcsec)
    except OverflowError:
        return f"{Decimal(arcsec):.6e}"
    if math.isnan(value):
        return "nan"
    if math.isinf(value):
        return "inf" if value > 0 else "-inf"
    return repr(value) if abs(value) >= _ROUNDED_BELOW_ARCSEC else None


def _hundredths(value: float) -> int:
    """``round(value * 100)``, half away from zero, on the value's shortest decimal form (0.125 -> 13)."""
    return int(Decimal(repr(float(value))).quantize(Decimal("0.01"), rounding=ROUND_HALF_UP).scaleb(2))


def format_arcsec(arcsec: float) -> str:
    """An angle in arcsec to 0.01, rounded as ``format_dms`` rounds it (so the two always agree);
    NaN, infinities and angles of 1e15" or more are shown as they are."""
    if (plain := _unrounded(arcsec)) is not None:
        return plain
    value = float(arcsec)
    hundredths = _hundredths(abs(value))
    sign = "-" if value < 0 and hundredths else ""
    whole, cents = divmod(hundredths, 100)
    return f"{sign}{whole}.{cents:02d}"


def format_dms(arcsec: float, *, degree: str = _DEGREE) -> str:
    """An angle in arcsec as degrees, minutes and seconds to 0.01": ``3723.5`` -> ``1°02'03.50"``.

    The value is rounded (half away from zero, on its shortest decimal form, so 59.995" is
    1'00.00") before it is split, so rounding carries into the minutes and degrees; a negative
    angle gets one leading ``-`` (none when it rounds to zero).  Degrees are not wrapped (an
    integrated angle can be many turns).  NaN, infinities and angles of 1e15" or more (beyond
    any real rotation; a wrong scale factor) are shown as they are, not split.
    """
    if (plain := _unrounded(arcsec)) is not None:
        return plain
    value = float(arcsec)
    hundredths = _hundredths(abs(value))
    sign = "-" if value < 0 and hundredths else ""
    degrees, rest = divmod(hundredths, 3600 * 100)
    minutes, rest = divmod(rest, 60 * 100)
    seconds, cents = divmod(rest, 100)
    return f"{sign}{degrees}{degree}{minutes:02d}'{seconds:02d}.{cents:02d}\""


def parse_address(text: str | None, *, default_host: str = DEFAULT_HOST, default_port: int = DEFAULT_PORT) -> tuple[str, int]:
    """``HOST:PORT``, ``HOST``, ``:PORT``, ``PORT`` or ``[IPV6]:PORT`` -> ``(host, port)``; ``UsageError`` if bad."""
    try:
        return parse_host_port(text, default_host=default_host, default_port=default_port, allow_zero=False)
    except ValueError as exc:
        raise UsageError(str(exc)) from None


def format_address(host: str, port: int) -> str:
    """``HOST:PORT``, with an IPv6 address in brackets (``[::1]:2948``): what ``parse_address`` reads back."""
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _show(value: Any, spec: str = "") -> str:
    """A value for the view: ``-`` when absent (or null), a number in ``spec``, other values as text."""
    if value is None:
        return _MISSING
    if _is_number(value):
        if isinstance(value, float) and not math.isfinite(value):
            return str(value)
        try:
            return format(value, spec)
        except OverflowError:  # an integer beyond float's range, in a float format
            return str(_unrounded(value))
    if isinstance(value, bool):
        return "true" if value else "false"
    text = value if isinstance(value, str) else json.dumps(value, separators=(",", ":"), default=str)
    return _printable(text if len(text) <= 60 else text[:57] + "...")


def _printable(text: str) -> str:
    """No control characters from the server reach the terminal (no newlines, no escape sequences)."""
    return text if text.isprintable() else "".join(ch if ch.isprintable() else "?" for ch in text)


def _dict(value: Any) -> Mapping[str, Any]:
    return value if isinstance(value, Mapping) else {}


def _angle_text(value: Any, degree: str) -> str:
    if value is None:
        return _MISSING
    if _is_number(value):
        return f"{format_arcsec(value)}\" ({format_dms(value, degree=degree)})"
    return _show(value)


def _hz(value: Any) -> str:
    return f"{_show(value, 'g')} Hz" if value is not None else _MISSING


def _identity(version: Mapping[str, Any]) -> str:
    inst = _dict(version.get("instrument"))
    if not inst:
        return _MISSING
    parts = [f"serial {_show(inst.get('serial'))}"]
    if inst.get("firmware") is not None:
        parts.append(f"firmware {_show(inst.get('firmware'))}")
    if inst.get("rate_hz") is not None:
        parts.append(_hz(inst.get("rate_hz")))
    return ", ".join(parts)


def _device(device: Mapping[str, Any]) -> str:
    if not device:
        return _MISSING
    parts = [_show(device.get("path")) if device.get("path") is not None else "(no path)"]
    parts.append(_show(device.get("state")))
    if device.get("serial") is not None:
        parts.append(f"serial {_show(device.get('serial'))}")
    if device.get("rate_hz") is not None:
        parts.append(_hz(device.get("rate_hz")))
    return ", ".join(parts)


def _server(version: Mapping[str, Any]) -> str:
    if not version:
        return "waiting for VERSION"
    text = f"server {_show(version.get('release'))}"
    major, minor = version.get("proto_major"), version.get("proto_minor")
    if major is not None:
        text += f", protocol {_show(major)}.{_show(minor) if minor is not None else 0}"
        if major != 1:
            text += " (this client speaks 1.x)"
    return text


def _temps(temps: Mapping[str, Any], sep: str) -> str:
    if not temps:
        return _MISSING
    names = ["top", "bottom", "housing"] + sorted(k for k in temps if k not in ("top", "bottom", "housing"))
    return sep.join(f"{name} {_show(temps.get(name), '.2f')}" for name in names) + " degC"


def _flags(flags: Any) -> str:
    if flags is None:
        return _MISSING
    if isinstance(flags, list):
        return ", ".join(_show(f) for f in flags) if flags else "none"
    return _show(flags)


def _status_items(status: Mapping[str, Any]) -> list[str]:
    items = []
    for key in sorted(k for k in status if isinstance(k, str) and k != "class"):
        value = status[key]
        if isinstance(value, (str, int, float)):  # scalars only (bool is an int)
            items.append(f"{_printable(key)}={_show(value, 'g' if isinstance(value, float) else '')}")
    return items


def _wrap(label: str, items: list[str], width: int) -> list[str]:
    """``label  a  b  c`` wrapped at ``width``, continuation lines indented under the first item."""
    indent = " " * 12
    lines, current = [], f"{label:<12}"
    for item in items:
        candidate = current + ("  " if current.strip() != label else "") + item
        if len(candidate) > width and current.strip() != label:
            lines.append(current)
            current = indent + item
        else:
            current = candidate
    lines.append(current)
    return lines


def _received(state: Mapping[str, Any]) -> str:
    parts = [f"{_show(state.get('angle_rate_hz'), '.1f')} ANGLE/s", f"{_show(state.get('angles', 0), ',')} ANGLE"]
    for key, name in (("malformed", "malformed"), ("oversized", "oversized"), ("unknown", "unknown class")):
        if state.get(key):
            parts.append(f"{_show(state.get(key), ',')} {name}")
    policy = _dict(state.get("watch"))
    if policy:
        if policy.get("enable") is False:
            parts.append("(WATCH disabled)")
        else:
            rate = policy.get("rate_hz")
            parts.append(f"(WATCH {_show(rate, 'g')} Hz)" if rate is not None else "(WATCH every sample)")
    return "  ".join(parts)


def render(state: Mapping[str, Any], *, width: int = 100, degree: str = _DEGREE) -> list[str]:
    """The live view's lines (no ANSI, no newlines) from a state mapping; every key may be absent.

    Keys read: ``address`` (text), ``elapsed_s``, ``version``/``device``/``angle``/``status``
    (the latest protocol object of that class), ``error`` (the last ERROR message),
    ``watch`` (the server's WATCH answer), ``angles`` (ANGLE objects received), ``angle_rate_hz``, ``angle_age_s`` (seconds since the
    last ANGLE), ``malformed``, ``oversized``, ``unknown``.
    """
    version, device = _dict(state.get("version")), _dict(state.get("device"))
    angle, status = _dict(state.get("angle")), _dict(state.get("status"))
    head = f"fog-driver watch {_show(state.get('address'))}  |  {_server(version)}"
    if state.get("elapsed_s") is not None:
        head += f"  |  {_show(state.get('elapsed_s'), '.1f')} s"
    lines = [head, f"{'instrument':<12}{_identity(version)}", f"{'device':<12}{_device(device)}"]
    if not angle:
        lines.append(f"{'angle':<12}{_MISSING} (waiting for ANGLE)")
    else:
        lines.append(f"{'angle':<12}{_angle_text(angle.get('angle_arcsec'), degree)}"
                     f"    raw {_angle_text(angle.get('angle_raw_arcsec'), degree)}")  # fmt: skip
        lines.append(f"{'rate':<12}{_show(angle.get('rate_dph'), '.4f')} deg/h"
                     f"    drift {_show(angle.get('drift_dph'), '.4f')} deg/h")  # fmt: skip
        lines.append(f"{'temps':<12}{_temps(_dict(angle.get('temps_c')), '  ')}")
        lines.append(f"{'flags':<12}{_flags(angle.get('flags'))}")
        sample = f"seq {_show(angle.get('seq'))}  t {_show(angle.get('t_s'), '.3f')} s"
        if state.get("angle_age_s") is not None:
            sample += f"  (received {_show(state.get('angle_age_s'), '.1f')} s ago)"
        lines.append(f"{'sample':<12}{sample}")
    lines.append(f"{'received':<12}{_received(state)}")
    items = _status_items(status)
    lines.extend(_wrap("status", items, width) if items else [f"{'status':<12}{_MISSING}"])
    if state.get("error") is not None:
        lines.append(f"{'error':<12}{_show(state.get('error'))}")
    return lines


def compact_line(state: Mapping[str, Any], *, degree: str = _DEGREE) -> str:
    """One line of the latest state, for logs (the non-terminal view prints one a second)."""
    angle, status = _dict(state.get("angle")), _dict(state.get("status"))
    parts = [f"[{_show(state.get('elapsed_s'), '7.1f')} s]"]
    if not angle:
        parts.append("waiting for ANGLE")
    else:
        parts += [
            f"seq {_show(angle.get('seq'))}",
            f"t {_show(angle.get('t_s'), '.3f')} s",
            f"angle {_angle_text(angle.get('angle_arcsec'), degree)}",
            f"raw {_angle_text(angle.get('angle_raw_arcsec'), degree)}",
            f"rate {_show(angle.get('rate_dph'), '.4f')} deg/h",
            f"drift {_show(angle.get('drift_dph'), '.4f')} deg/h",
            f"temps {_temps(_dict(angle.get('temps_c')), ' ')}",
            f"flags {_flags(angle.get('flags')).replace(', ', ',')}",
        ]
    parts.append(_received(state))
    items = _status_items(status)
    if items:
        parts.append("status " + " ".join(items))
    return parts[0] + " " + " | ".join(parts[1:])


# --------------------------------------------------------------------------- the stream


class LineReader:
    """Splits a byte stream into lines of at most ``max_line`` bytes; longer ones are dropped and counted."""

    def __init__(self, max_line: int = MAX_LINE_BYTES) -> None:
        self.max_line = max_line
        self.oversized = 0
        self._buf = bytearray()
        self._discarding = False  # inside an oversized line: drop bytes up to its newline

    def feed(self, data: bytes) -> list[bytes]:
        lines: list[bytes] = []
        self._buf += data
        start = 0
        while (nl := self._buf.find(b"\n", start)) >= 0:
            if self._discarding:
                self._discarding = False
            elif nl - start > self.max_line + 1:  # allow a "\r" before the newline
                self.oversized += 1
            else:
                lines.append(bytes(self._buf[start:nl]))
            start = nl + 1
        del self._buf[:start]
        if len(self._buf) > self.max_line + 1:
            if not self._discarding:
                self.oversized += 1
                self._discarding = True
            self._buf.clear()
        return lines


def _degree_for(out: TextIO) -> str:
    encoding = getattr(out, "encoding", None) or "utf-8"
    try:
        _DEGREE.encode(encoding)
    except (UnicodeEncodeError, LookupError):
        return "d"
    return _DEGREE


def _isatty(out: TextIO) -> bool:
    try:
        return bool(out.isatty())
    except (AttributeError, ValueError, OSError):
        return False


def _terminal_size(out: TextIO) -> tuple[int, int]:
    """(columns, lines) of the terminal ``out`` writes to; 80 x 24 when it does not say (0 x 0 ptys)."""
    try:
        size = os.get_terminal_size(out.fileno())
    except (AttributeError, ValueError, OSError):  # io.UnsupportedOperation is both
        size = shutil.get_terminal_size()
    return size.columns or 80, size.lines or 24


class _Watch:
    """The client's state and its two views (terminal block, or log lines)."""

    def __init__(self, address: str, out: TextIO, started: float) -> None:
        self.out = out
        self.tty = _isatty(out)
        self.degree = _degree_for(out)
        self.started = started
        self.state: dict[str, Any] = {"address": address, "angles": 0, "malformed": 0, "unknown": 0}
        self._arrivals: deque[float] = deque()
        self._last_angle_at: float | None = None
        self._dirty = True
        self._last_draw: float | None = None
        self._drawn = False
        self._cursor_hidden = False
        self._next_line = started + _LINE_PERIOD_S
        self._angles_at_last_line = 0
        self._lines_printed = 0

    # -- input

    def handle(self, obj: dict[str, Any], now: float) -> None:
        cls = obj.get("class")
        if cls == "ANGLE":
            self.state["angle"] = obj
            self.state["angles"] += 1
            self._arrivals.append(now)
            self._last_angle_at = now
        elif cls == "STATUS":
            self.state["status"] = obj
        elif cls == "VERSION":
            self.state["version"] = obj
            self._event(f"connected to {self.state['address']}: {_server(obj)}; instrument {_identity(obj)}")
        elif cls == "DEVICE":
            self.state["device"] = obj
            self._event(f"device {_device(obj)}")
        elif cls == "WATCH":  # the server's answer to ?WATCH: the policy in force
            self.state["watch"] = obj
        elif cls == "ERROR":
            message = obj.get("message")
            self.state["error"] = _show(message) if message is not None else "(no message)"
            self._event(f"server error: {self.state['error']}")
        else:
            self.state["unknown"] += 1
        self._dirty = True

    def malformed(self, n: int = 1) -> None:
        self.state["malformed"] += n
        self._dirty = True

    # -- output

    def _snapshot(self, now: float) -> dict[str, Any]:
        while self._arrivals and self._arrivals[0] <= now - _RATE_WINDOW_S:
            self._arrivals.popleft()
        window = min(_RATE_WINDOW_S, now - self.started)
        self.state["elapsed_s"] = now - self.started
        self.state["angle_rate_hz"] = len(self._arrivals) / window if window > 0 else 0.0
        if self._last_angle_at is not None:
            self.state["angle_age_s"] = now - self._last_angle_at
        return self.state

    def _write(self, text: str) -> None:
        self.out.write(text)
        self.out.flush()

    def _event(self, line: str) -> None:
        if not self.tty:
            self._write(line + "\n")

    def _draw(self, now: float) -> None:
        columns, rows = _terminal_size(self.out)
        width, height = max(20, columns), max(3, rows)
        lines = render(self._snapshot(now), width=width - 1, degree=self.degree)[: height - 1]
        prefix = _HIDE_CURSOR + _HOME + _CLEAR_SCREEN if not self._drawn else _HOME
        body = "".join(line[: width - 1] + _CLEAR_EOL + "\n" for line in lines)
        self._drawn = self._cursor_hidden = True
        self._write(prefix + body + _CLEAR_EOS)
        self._last_draw = now
        self._dirty = False

    def _print_line(self, now: float) -> None:
        self._write(compact_line(self._snapshot(now), degree=self.degree) + "\n")
        self._angles_at_last_line = self.state["angles"]
        self._lines_printed += 1

    def tick(self, now: float) -> None:
        if self.tty:
            since = None if self._last_draw is None else now - self._last_draw
            if since is None or (self._dirty and since >= _TTY_MIN_REDRAW_S) or since >= _TTY_REFRESH_S:
                self._draw(now)
        elif now >= self._next_line:
            self._print_line(now)
            # keep the one-a-second cadence; after a stall, start again from now
            self._next_line = max(self._next_line + _LINE_PERIOD_S, now)

    def finish(self, now: float, note: str | None = None) -> None:
        """The last view (so a short run shows what it got), then the note, if any."""
        if self.tty:
            self._draw(now)
            self.restore()
        elif self.state["angles"] > self._angles_at_last_line or (self._lines_printed == 0 and note is None):
            self._print_line(now)
        if note:
            self._write(note + "\n")

    def restore(self) -> None:
        """Show the cursor again (once), however the watch ends."""
        if self._cursor_hidden:
            self._cursor_hidden = False
            try:
                self._write(_SHOW_CURSOR)
            except (OSError, ValueError):
                pass


#: The environment variable ``fog-driver watch`` reads a daemon's client token from (never a command-line
#: argument: those show in every user's process list).
TOKEN_ENV = "FOG_DRIVER_TOKEN"


def _auth_command(token: str) -> bytes:
    return b"?AUTH=" + json.dumps({"token": token}, separators=(",", ":")).encode("utf-8") + b";\n"


def _watch_command(rate_hz: float | None) -> bytes:
    request: dict[str, Any] = {"enable": True}
    if rate_hz is not None:
        request["rate_hz"] = int(rate_hz) if float(rate_hz).is_integer() else float(rate_hz)
    return b"?WATCH=" + json.dumps(request, separators=(",", ":")).encode("ascii") + b";\n"


def _connect(host: str, port: int, timeout_s: float) -> socket.socket:
    try:
        return socket.create_connection((host, port), timeout=timeout_s)
    except OSError as exc:
        if isinstance(exc, TimeoutError):  # socket.timeout is TimeoutError
            reason = "timed out"
        else:
            reason = exc.strerror or str(exc) or type(exc).__name__
        raise DeviceError(
            f"cannot connect to {format_address(host, port)}: {reason} (is `fog-driver run` running?)"
        ) from None


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
) -> int:
    """Watch a running daemon until ``count`` ANGLE objects, ``duration_s`` seconds, Ctrl-C or disconnect.

    ``out`` defaults to ``sys.stdout`` (looked up at call time).  ``timeout_s`` bounds the
    connection attempt and sending the WATCH request.  ``token``: sent with ``?AUTH`` first (a daemon with a
    token closes a client that has not authorized within its auth deadline).  Returns 0 (count reached, duration
    elapsed, Ctrl-C) or 1 (the server closed or lost the connection; a one-line note says so).
    Raises ``DeviceError`` when the daemon cannot be reached, ``UsageError`` for bad arguments.
    """
    if out is None:
        out = sys.stdout
    if count is not None and (isinstance(count, bool) or not isinstance(count, int) or count < 1):
        raise UsageError(f"--count must be a whole number >= 1, not {count!r}")
    if duration_s is not None and not duration_s > 0:
        raise UsageError(f"--duration must be > 0 s, not {duration_s!r}")
    if rate_hz is not None and not (rate_hz > 0 and math.isfinite(rate_hz)):
        raise UsageError(f"--rate-hz must be > 0, not {rate_hz!r}")
    address = format_address(host, port)
    watch: _Watch | None = None
    sock: socket.socket | None = None
    try:
        sock = _connect(host, port, timeout_s)
        started = time.monotonic()
        watch = _Watch(address, out, started)
        deadline = None if duration_s is None else started + duration_s
        reader = LineReader()
        try:
            sock.sendall((_auth_command(token) if token else b"") + _watch_command(rate_hz))
        except OSError:
            pass  # the server went away at once: what it sent is still read below, then EOF
        watch.tick(started)
        while True:
            now = time.monotonic()
            if deadline is not None and now >= deadline:
                watch.finish(now)
                return EXIT_OK
            wait = _POLL_S if deadline is None else max(0.001, min(_POLL_S, deadline - now))
            sock.settimeout(wait)
            try:
                data = sock.recv(_RECV_BYTES)
            except TimeoutError:
                data = None
            except OSError as exc:
                reason = exc.strerror or str(exc) or type(exc).__name__
                watch.finish(time.monotonic(), f"fog-driver watch: lost the connection to {address}: {reason} "
                             f"({watch.state['angles']:,} ANGLE received)")  # fmt: skip
                return EXIT_CONNECTION_CLOSED
            now = time.monotonic()
            if data == b"":
                watch.finish(now, f"fog-driver watch: {address} closed the connection "
                             f"({watch.state['angles']:,} ANGLE received)")  # fmt: skip
                return EXIT_CONNECTION_CLOSED
            if data:
                oversized_before = reader.oversized
                for line in reader.feed(data):
                    if not line.strip():
                        continue  # an empty line (a keep-alive) is not an error
                    obj = parse_line(line)
                    if obj is None:
                        watch.malformed()
                        continue
                    watch.handle(obj, now)
                    if count is not None and watch.state["angles"] >= count:
                        watch.finish(now)
                        return EXIT_OK
                if reader.oversized != oversized_before:
                    watch.state["oversized"] = reader.oversized
            watch.tick(now)
    except KeyboardInterrupt:
        if watch is not None:
            try:
                watch.finish(time.monotonic())
            except (OSError, ValueError, KeyboardInterrupt):
                pass
        return EXIT_OK
    finally:
        if watch is not None:
            watch.restore()
        if sock is not None:
            sock.close()


def watch_command(address: str | None, *, rate_hz: float | None = 10.0, count: int | None = None,
                  duration_s: float | None = None) -> int:  # fmt: skip
    """``fog-driver watch [HOST:PORT]``: parse the address and run the watch on stdout (the token, if the daemon
    has one, from the environment variable ``FOG_DRIVER_TOKEN``)."""
    host, port = parse_address(address)
    token = os.environ.get(TOKEN_ENV) or None
    return run_watch(host, port, rate_hz=rate_hz, count=count, duration_s=duration_s, token=token)

