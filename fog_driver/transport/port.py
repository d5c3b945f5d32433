"""Opening ports and reading them through unplugs: ``open_port`` and ``PortReader``.

Everything that looks like a port goes through ``serial.serial_for_url``: device
paths (``/dev/ttyUSB0``, a pty slave), pyserial URLs (``loop://``,
``socket://host:port``) and ours (``replay://capture.bin?rate=1000``).  So the
rest of the driver never special-cases a replay.

``PortReader`` is the session layer of gpsd's model: it owns the port's life,
hands out raw byte chunks, and when the port disappears (a USB adapter pulled
out, a replay with ``unplug=1`` at its end) it closes it, reports the loss, waits
with exponential backoff and opens it again.  Every state change is reported to
an ``on_state`` callback as a ``PortEvent`` and logged with structlog.

A network port (``socket://``, ``rfc2217://``) can die without a word: a cable pulled between the host and
the device server, a server losing power, a NAT forgetting the flow leave the connection open and silent.
``PortReader`` turns TCP keepalive on for it and takes a silence of ``silence_s`` on a connection that has
delivered bytes as its loss (an instrument streams without pause: at 1 Hz at the slowest the driver reads).
"""

from __future__ import annotations

import contextlib
import errno
import math
import os
import select
import socket
import stat
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Literal

import serial
import structlog

try:  # POSIX only; pyserial's POSIX ports let termios.error escape from flushes
    import termios

    from serial.serialposix import Serial as _PosixSerial

    _TERMIOS_ERRORS: tuple[type[BaseException], ...] = (termios.error,)
except ImportError:  # pragma: no cover - non-POSIX
    _TERMIOS_ERRORS = ()
    _PosixSerial = None

__all__ = [
    "DEFAULT_BAUDRATE",
    "DEFAULT_SILENCE_S",
    "PortError",
    "PortEvent",
    "PortReader",
    "PortSetupError",
    "PortState",
    "open_port",
]

log = structlog.get_logger("fog_driver.transport")

DEFAULT_BAUDRATE = 460800
#: The most one read takes: chunks stay small (bounded memory and latency downstream) even when a
#: port has megabytes waiting, as an unpaced ``replay://`` does.
MAX_READ_BYTES = 64 * 1024

#: What a port that vanished or cannot be opened raises.  ``serial.SerialException``
#: is an ``OSError``; ``termios.error`` is not.
PORT_ERRORS: tuple[type[BaseException], ...] = (OSError, *_TERMIOS_ERRORS)

PortState = Literal["opening", "open", "lost", "retry_wait", "closed"]

#: How long a network port that has delivered bytes may then give none before its connection is taken as lost
#: (s).  Five frame periods of the slowest instrument the driver reads: protocol v1 sends an IDENTITY frame a
#: second whatever its SAMPLE rate, and a KVH or STDBIN device's ``rate_hz`` is at least 1 Hz (KVH's ``=DR``
#: goes no lower); 1 kHz is the usual rate.
DEFAULT_SILENCE_S = 5.0
#: TCP keepalive on a network port: the first probe after this much idle time (s), then one every
#: ``KEEPALIVE_INTERVAL_S``; ``KEEPALIVE_PROBES`` unanswered ones end the connection (about 11 s of a dead
#: peer in all, which ``TCP_USER_TIMEOUT`` also bounds for bytes sent and not acknowledged).  It covers what
#: the silence rule cannot: a connection that has delivered nothing yet (the device server up, the
#: instrument off), and the server's side of the connection, freed sooner when the daemon's end goes.
KEEPALIVE_IDLE_S = 5
KEEPALIVE_INTERVAL_S = 2
KEEPALIVE_PROBES = 3


def network_socket(port: serial.SerialBase) -> socket.socket | None:
    """The TCP connection under a network port (pyserial's ``socket://`` and ``rfc2217://`` keep it in
    ``_socket``; it has no public accessor), or None for any other port (a tty, ``loop://``, ``replay://``)."""
    sock = getattr(port, "_socket", None)
    return sock if isinstance(sock, socket.socket) and sock.type == socket.SOCK_STREAM else None


def enable_keepalive(sock: socket.socket) -> None:
    """Turn TCP keepalive on with the ``KEEPALIVE_*`` timing, each option where the platform has it (Linux has
    them all; macOS names the idle time ``TCP_KEEPALIVE``; elsewhere the system's own, slow, timing)."""
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE, 1)
    idle_name = "TCP_KEEPIDLE" if hasattr(socket, "TCP_KEEPIDLE") else "TCP_KEEPALIVE"
    dead_ms = (KEEPALIVE_IDLE_S + KEEPALIVE_INTERVAL_S * KEEPALIVE_PROBES) * 1000
    for name, value in (
        (idle_name, KEEPALIVE_IDLE_S),
        ("TCP_KEEPINTVL", KEEPALIVE_INTERVAL_S),
        ("TCP_KEEPCNT", KEEPALIVE_PROBES),
        ("TCP_USER_TIMEOUT", dead_ms),
    ):
        option = getattr(socket, name, None)
        if option is not None:
            with contextlib.suppress(OSError):  # an option the running kernel lacks: the others still help
                sock.setsockopt(socket.IPPROTO_TCP, option, value)


def silence_text(silence_s: float) -> str:
    """The reason of a loss by silence, as ``lost`` and ``retry_wait`` report it."""
    return f"no bytes for {silence_s:g} s: the connection is taken as lost"


def check_silence_s(silence_s: float | None, name: str = "silence_s") -> None:
    """ValueError (naming the setting ``name``) unless ``silence_s`` is None (no silence rule) or a finite number
    of seconds > 0."""
    if silence_s is not None and (
        isinstance(silence_s, bool) or not isinstance(silence_s, int | float) or not 0 < silence_s < math.inf
    ):
        raise ValueError(f"{name} must be a number of seconds > 0 (or null: never), got {silence_s!r}")


def read_available(port: serial.SerialBase, limit: int = MAX_READ_BYTES) -> bytes:
    """Every byte the port holds, up to ``limit`` (at most ``MAX_READ_BYTES``), after waiting up to the port's
    timeout for the first (``b""`` at the timeout).

    A POSIX serial device (a tty, a pty, a USB adapter) is read directly: one ``select`` on its descriptor
    and pyserial's cancel pipe, then one ``read(2)`` of whatever the kernel has.  That is two system calls
    per lump of bytes where ``port.read(port.in_waiting or 1)`` makes six (pyserial reads a woken port one
    byte at a time, then asks how many more are waiting).  Its errors are pyserial's: a failing ``read(2)``
    raises ``SerialException("read failed: ...")``, and a descriptor that is readable but gives no bytes (a
    USB adapter unplugged) raises pyserial's "device reports readiness to read but returned no data".
    Any other port (``replay://``, ``loop://``, ``socket://``) is read through pyserial's ``read``, the
    first byte and then the rest of its lump in one chunk.
    """
    fd = getattr(port, "fd", None)
    if (
        _PosixSerial is not None
        and isinstance(port, _PosixSerial)
        and isinstance(fd, int)
        and port.pipe_abort_read_r is not None
    ):
        cancel = port.pipe_abort_read_r
        try:
            ready = select.select([fd, cancel], [], [], port.timeout)[0]
            if cancel in ready:
                os.read(cancel, 1000)
                return b""
            if not ready:
                return b""
            data = os.read(fd, limit)
        except BlockingIOError:  # EAGAIN and its kin: nothing after all (EINTR is retried by Python)
            return b""
        except OSError as exc:
            raise serial.SerialException(f"read failed: {exc}") from exc
        if not data:
            raise serial.SerialException(
                "device reports readiness to read but returned no data "
                "(device disconnected or multiple access on port?)"
            )
        return data
    waiting = port.in_waiting
    data = port.read(min(waiting or 1, limit))
    if not waiting and data and limit > len(data):  # woken by a first byte: the rest of its lump with it
        try:
            waiting = port.in_waiting
            if waiting:
                data += port.read(min(waiting, limit - len(data)))
        except PORT_ERRORS:
            pass  # the byte read is returned; the next read meets the error and reports it
    return data


class PortError(Exception):
    """A port could not be used and the reader was told not to retry (or retrying cannot help)."""


class PortSetupError(Exception):
    """What an ``on_open`` hook raises when the device does not accept its setup: the open failed.

    A ``raw`` attribute (``bytes``), when present, holds what the port delivered during the attempt.
    """


@dataclass(frozen=True, slots=True)
class PortEvent:
    """One change of a ``PortReader``'s port state.

    ``attempt`` numbers the open attempts since the last open that delivered
    data (1 for the first); ``retry_in_s`` is set only for ``retry_wait``.
    """

    state: PortState
    url: str
    detail: str = ""  #: error text for "lost" and "retry_wait", and for "closed" when not stopped
    attempt: int = 0
    retry_in_s: float | None = None


def open_port(
    url_or_path: str, *, baudrate: int = DEFAULT_BAUDRATE, timeout_s: float | None = 0.05
) -> serial.SerialBase:
    """Open a device path or a pyserial URL (``replay://`` included) with a read timeout.

    A device path (no ``scheme://``) is opened exclusively (pyserial's ``exclusive``: an flock on POSIX), so a
    port a running daemon or recorder holds is refused, not shared (two readers would each get half the bytes).

    Raises ``serial.SerialException`` when the port cannot be opened (or is held) and
    ``ValueError`` for a URL scheme nobody handles or bad settings.
    """
    if "://" in url_or_path:
        return serial.serial_for_url(url_or_path, baudrate=baudrate, timeout=timeout_s)
    try:
        return serial.serial_for_url(url_or_path, baudrate=baudrate, timeout=timeout_s, exclusive=True)
    except serial.SerialException as exc:
        if "exclusively lock" in str(exc):
            raise serial.SerialException(f"{url_or_path} is held by another program (a running daemon?)") from None
        raise


class PortReader:
    """Read a port as a stream of byte chunks, reopening it with backoff when it is lost.

    ``chunks(stop)`` yields non-empty ``bytes`` exactly as the port delivered
    them and returns when ``stop`` is set (within one read timeout).  With
    ``reconnect=False`` it also returns at the first loss, and raises
    ``PortError`` if the very first open fails.  ``chunks(stop, read_on=f)``
    reads on after ``stop`` while the port is open: each read takes at most
    ``f()`` bytes, until ``f()`` is 0, the port is lost, or ``read_on_s`` pass
    (a recorder that ends on a frame boundary asks for one byte at a time while
    its decoder holds part of a frame).

    Backoff: the first wait after a loss or a failed open is
    ``backoff_initial_s``; each further failure doubles it up to
    ``backoff_max_s``; it starts over once an open port has delivered data
    (a port that opens but dies before giving a byte keeps backing off, so a
    flapping device cannot make a tight loop).

    A URL that no handler understands, or invalid settings (``ValueError`` from
    pyserial), raises ``PortError`` at once even with ``reconnect=True``:
    retrying cannot fix a configuration error.

    ``first_open`` is what a failed open does before the port has ever opened:
    ``"retry"`` (a service waiting for its device: retry with backoff, each
    failure logged as a warning), ``"fail"`` (a typo in a device name is not
    waited for: ``PortError`` at once, even with ``reconnect=True``; reconnecting
    is for a port that worked), or ``"wait"`` (retry, logging at info level: the
    caller has told the user once that it waits for the device).

    Counters: ``bytes_read``, ``opens`` (successful opens), ``losses`` (open
    ports lost), ``open_failures``.  They are plain ints written by the reading
    thread; reading them from another thread is fine for monitoring.
    ``last_activity_monotonic`` is when the reading loop last came round (a read
    returned, with data or at its timeout, or a state changed): a watchdog tells a
    quiet port from a stuck reader by it.

    ``on_open`` (optional) is called with the port right after every successful
    open (the first and each reopen after a loss), before any read: a device setup
    (``fog_driver.transport.setup.make_on_open``).  The bytes it returns (what the
    port delivered meanwhile) are yielded first, as one chunk.  If it raises
    ``PortSetupError`` or a port error, the open failed: the port is closed, the
    failure is reported and counted like a failed open (``retry_wait``, or
    ``PortError`` under ``reconnect=False`` or ``first_open="fail"`` before any
    open succeeded), and the bytes of the exception's ``raw`` attribute are yielded
    before the report.  The ``"open"`` state is reported after ``on_open`` returns.

    A network port (``socket://``, ``rfc2217://``: ``network_socket``) gets TCP keepalive (``enable_keepalive``)
    right after it opens, before ``on_open``, and the silence rule: once the connection has delivered a byte,
    ``silence_s`` without one is its loss (reason ``silence_text``), counted, reported and reopened as any
    other; a connection that has delivered nothing yet is left to keepalive.  ``silence_s=None``: no silence
    rule.  A local port (a tty) never gets it: its silence is the instrument's (switched off, its cable out of
    the adapter), which reopening the tty cannot end, and the kernel already reports an unplugged adapter.
    ``silence_s`` is read at each read, so it may be changed while the reader runs (a config reload).
    """

    def __init__(
        self,
        url: str,
        *,
        baudrate: int = DEFAULT_BAUDRATE,
        read_timeout_s: float = 0.05,
        backoff_initial_s: float = 0.1,
        backoff_max_s: float = 2.0,
        reconnect: bool = True,
        on_state: Callable[[PortEvent], None] | None = None,
        first_open: Literal["retry", "fail", "wait"] = "retry",
        on_open: Callable[[serial.SerialBase], bytes] | None = None,
        silence_s: float | None = DEFAULT_SILENCE_S,
    ) -> None:
        if read_timeout_s <= 0:
            raise ValueError(f"read_timeout_s must be > 0 so a stop is seen between reads, got {read_timeout_s}")
        if not 0 < backoff_initial_s <= backoff_max_s:
            raise ValueError(f"need 0 < backoff_initial_s <= backoff_max_s, got {backoff_initial_s}, {backoff_max_s}")
        self.url = url
        self.baudrate = baudrate
        self.read_timeout_s = read_timeout_s
        self.backoff_initial_s = backoff_initial_s
        self.backoff_max_s = backoff_max_s
        self.reconnect = reconnect
        self.on_state = on_state
        if first_open not in ("retry", "fail", "wait"):
            raise ValueError(f"first_open must be 'retry', 'fail' or 'wait', got {first_open!r}")
        self.first_open = first_open
        self.on_open = on_open
        check_silence_s(silence_s)
        self.silence_s = silence_s
        self.bytes_read = 0
        self.opens = 0
        self.losses = 0
        self.open_failures = 0
        self.state: PortState = "closed"
        self.last_activity_monotonic = time.monotonic()

    def _report(self, state: PortState, *, detail: str = "", attempt: int = 0, retry_in_s: float | None = None) -> None:
        """Record, log and publish one state change."""
        self.state = state
        self.last_activity_monotonic = time.monotonic()
        # The callback first, so a terminal display can clear its status line before the log line.
        if self.on_state is not None:
            self.on_state(PortEvent(state, self.url, detail, attempt, retry_in_s))
        waiting = self.first_open == "wait" and not self.opens
        level = log.warning if state in ("lost", "retry_wait") and not waiting else log.info
        level("port_state", state=state, url=self.url, detail=detail, attempt=attempt, retry_in_s=retry_in_s)

    def chunks(
        self, stop: threading.Event, *, read_on: Callable[[], int] | None = None, read_on_s: float = 1.0
    ) -> Iterator[bytes]:
        """Yield byte chunks from the port until ``stop`` is set, then, with ``read_on``, while ``read_on()``
        wants more (see the class docstring)."""
        attempt = 0
        delay_s = self.backoff_initial_s
        detail = ""
        try:
            while not stop.is_set():
                attempt += 1
                delivered = False
                self._report("opening", attempt=attempt)
                port: serial.SerialBase | None = None
                sock: socket.socket | None = None  # the network port's connection (None: a tty, a replay)
                setup_bytes = b""
                try:
                    port = open_port(self.url, baudrate=self.baudrate, timeout_s=self.read_timeout_s)
                except ValueError as exc:
                    detail = f"cannot open {self.url}: {exc}"
                    raise PortError(detail) from exc
                except PORT_ERRORS as exc:
                    self.open_failures += 1
                    detail = open_error_text(self.url, exc)
                    if not self.reconnect or (self.first_open == "fail" and not self.opens):
                        raise PortError(detail) from exc
                else:
                    sock = network_socket(port)
                    if sock is not None:
                        with contextlib.suppress(OSError):  # a socket that died already: the first read says so
                            enable_keepalive(sock)
                    if self.on_open is not None:
                        try:
                            setup_bytes = self.on_open(port)
                        except (PortSetupError, *PORT_ERRORS) as exc:  # the device refused: the open failed
                            _close_quietly(port)
                            port = None
                            self.open_failures += 1
                            detail = f"setup of {self.url} failed: {' '.join(str(exc).split()) or type(exc).__name__}"
                            raw = getattr(exc, "raw", b"")
                            if isinstance(raw, bytes | bytearray) and raw:  # what the port said is still data
                                self.bytes_read += len(raw)
                                yield bytes(raw)
                            if not self.reconnect or (self.first_open == "fail" and not self.opens):
                                raise PortError(detail) from exc
                        except BaseException:
                            _close_quietly(port)
                            raise
                if port is not None:
                    self.opens += 1
                    self._report("open", attempt=attempt)
                    try:
                        if setup_bytes:  # inside the try: the port is closed even if the consumer stops here
                            self.bytes_read += len(setup_bytes)
                            delivered = True
                            yield bytes(setup_bytes)
                        read_on_until: float | None = None  # set at the stop, with read_on
                        last_byte_s = time.monotonic()  # (the silence rule counts from the last byte)
                        while True:
                            limit = MAX_READ_BYTES
                            if stop.is_set():
                                if read_on is None:
                                    detail = ""
                                    return  # stopped while open
                                now = time.monotonic()
                                read_on_until = now + read_on_s if read_on_until is None else read_on_until
                                wanted = read_on()
                                if wanted <= 0 or now >= read_on_until:
                                    detail = ""
                                    return  # stopped while open, and the consumer has what it wanted
                                limit = min(wanted, MAX_READ_BYTES)
                            try:
                                data = read_available(port, limit)
                            except PORT_ERRORS as exc:
                                detail = str(exc) or type(exc).__name__
                                break
                            now = self.last_activity_monotonic = time.monotonic()
                            if data:
                                last_byte_s = now
                                self.bytes_read += len(data)
                                delivered = True
                                yield data
                            elif delivered and sock is not None:
                                silence_s = self.silence_s  # (once: a reload may change it meanwhile)
                                if silence_s is not None and now - last_byte_s >= silence_s:
                                    detail = silence_text(silence_s)
                                    break
                    finally:
                        _close_quietly(port)
                    if stop.is_set():  # the far end closed as we were stopping (a demo's simulator): no loss
                        return
                    self.losses += 1
                    self._report("lost", detail=detail, attempt=attempt)
                    if not self.reconnect:
                        return
                if delivered:  # the port worked: back off from the start again
                    delay_s = self.backoff_initial_s
                self._report("retry_wait", detail=detail, attempt=attempt, retry_in_s=delay_s)
                if stop.wait(delay_s):
                    return
                if delivered:
                    attempt = 0
                delay_s = min(delay_s * 2.0, self.backoff_max_s)
        finally:
            self._report("closed", detail="" if stop.is_set() else detail)


#: What a failed open means to a user, by errno (other errors: the system's own text).
_OPEN_REASONS = {
    errno.ENOENT: "no such device",
    errno.ENODEV: "no such device",
    errno.ENXIO: "no such device",
    errno.EACCES: "permission denied (is the user in the dialout group?)",
    errno.EBUSY: "device busy (another program has it open?)",
    errno.EISDIR: "is a directory, not a device",
    errno.ENOTDIR: "a part of the path is not a directory",
}


def open_error_text(url: str, exc: BaseException) -> str:
    """One short line for a failed open: "cannot open /dev/ttyUSB0: no such device" (pyserial's own text
    repeats the path and the errno twice)."""
    code = getattr(exc, "errno", None)
    if isinstance(code, int) and code:
        reason = _OPEN_REASONS.get(code) or os.strerror(code).lower()
    else:
        reason = " ".join(str(exc).split()) or type(exc).__name__
    return f"cannot open {url}: {reason}"


def not_a_serial_device(path: str) -> str | None:
    """Why the existing ``path`` can never be a serial port, as one line ("cannot open /dev/null: a character
    device that is not a terminal, not a serial device"), or None: it is a terminal device (a serial port, a
    USB adapter, a pty), or it does not exist or cannot be opened now (``open_error_text``'s to say; waiting
    may help with those, never with this).

    A character device is opened (read-write, non-blocking, not as the controlling terminal) and closed
    again to ask whether it is a terminal (``isatty``: what pyserial's ``tcgetattr`` needs)."""
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return None
    if stat.S_ISCHR(mode):
        try:
            fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK | os.O_CLOEXEC)
        except OSError:
            return None
        try:
            if os.isatty(fd):
                return None
        finally:
            os.close(fd)
        kind = "a character device that is not a terminal"
    elif stat.S_ISREG(mode):
        kind = "a regular file"
    elif stat.S_ISDIR(mode):
        kind = "a directory"
    else:
        kind = "not a device"
    return f"cannot open {path}: {kind}, not a serial device"


def _close_quietly(port: serial.SerialBase) -> None:
    """Close a port that may already be dead; errors on the way out carry no news."""
    with contextlib.suppress(*PORT_ERRORS):
        port.close()
