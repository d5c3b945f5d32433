"""Device setup: a list of ASCII commands sent to the instrument each time its port opens.

``DeviceSetup`` holds the commands (validated when it is built, so a typo in a configuration file is a
one-line error at load time and never garbage on the wire) and how to send them; ``run_setup`` sends
them on an open pyserial port and returns a ``SetupResult``; ``make_on_open`` turns a setup into the
``on_open`` hook of ``PortReader``, which runs it after every open (the first and each reopen after an
unplug).

KVH DSP-1750 / DSP-1760 / 1775 command protocol, as implemented here:

* Every command starts with ``=`` (set / act) or ``?`` (query), parameters are comma-separated, input is
  case-insensitive, and a command ends with CR, LF or both; only characters 0x20..0x7E are used.  We send
  CR LF (``b"\\r\\n"``), which every variant accepts.
* Normal mode streams binary frames and ignores every command except a few (``=CONFIG,1``, ``?BIT``...);
  ``=CONFIG,1`` enters configuration mode, where the binary output stops and every command is answered;
  ``=CONFIG,0`` goes back to normal mode and the binary output restarts.
* Reply: a command is answered by itself without the ``=`` prefix, in upper case (``=TEMPUNITS,C_100`` ->
  ``TEMPUNITS,C_100``); a query by its text without the ``?`` followed by the answer (``?DR`` ->
  ``DR,1000``); the device does not echo the characters it receives.  An unknown command in configuration
  mode is answered ``INVALID,`` followed by the text received; a bad parameter to a known command gets a
  usage prompt (its exact first word was not visible in the source read: such a reply is not the expected
  one, so the wait ends at the deadline and the error quotes the last line the device sent).

Sources:

* KVH 1775 IMU technical manual (56-0298 Rev. B), section 7 "Commands and Queries" (terminators,
  prefixes, reply = command without ``=``, ``INVALID,`` in configuration mode), section 4.2 (0x20..0x7E,
  "a carriage return, a line feed, or both are all valid end of command delimiters"), section 3.3
  (configuration mode stops the binary output), section 8.3 (``=BAUD``: the reply comes at the new baud
  rate): https://www.easymanua.ls/kvh-industries/1775-imu/manual?p=57 (and ``?p=45``, ``?p=43``,
  ``?p=63``).
* A DSP-1750 driver of the PeRL lab (``program_imu``: writes ``=CONFIG,1\\r\\n``, reads until
  ``CONFIG,1``; ``=DR,<n>\\r\\n`` until ``DR,``; ``=rotfmt,RATE\\r\\n`` until ``ROTFMT,RATE``; then
  ``=CONFIG,0\\r\\n``; an LCM publisher of ``senlcm_kvh1750_t`` whose repository the public code index
  did not name); Paradigm Hyperloop's ``imu_config/imu_config.c`` (github.com/ParadigmHyperloop/hyperloop:
  ``CONFIG_CMD "=config,1\\r\\n"``, ``CONFIG_RES "CONFIG,1"``, read with a select() timeout); the ROS ``kvh_driver``
  (``kvh_driver/src/helpers/kvh_imu.cpp`` in github.com/jtukpah/wildfire_hyperdrive_ssrr_2024: ``=config,1\\n`` /
  ``=config,0\\n``, LF only, which the manual also allows); an OpenDLV-derived P1775 configuration script
  (``=CONFIG,1``, ``=CONFIG,0``, each ``\\r\\n``-terminated).  Those drivers either read without a deadline or sleep a
  fixed 200 ms between commands; here each reply is waited for with a monotonic deadline instead.

Frames right after ``=CONFIG,0``: the output restarts, and a change of data rate or filter re-initializes
the output filters (manual, table 8-4), so the first frames after a setup are start-up data.  No
published settling time was found; ``settle_s`` (default 1 s, configurable) is how long after the end of
the setup (``SetupResult.finished_monotonic``) the caller treats frames as start-up.  This module only
reports it; what to do with those frames is the caller's decision.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Literal

import serial
import structlog

from .port import PORT_ERRORS, PortSetupError

__all__ = [
    "DEFAULT_REPLY_TIMEOUT_S",
    "DEFAULT_SETTLE_S",
    "KVH_TERMINATOR",
    "MAX_COMMAND_LEN",
    "DeviceSetup",
    "DeviceSetupError",
    "InvalidSetupCommand",
    "SetupResult",
    "make_on_open",
    "run_setup",
    "validate_command",
]

log = structlog.get_logger("fog_driver.transport.setup")

#: CR LF: the manual accepts CR, LF or both; CR LF is what the drivers cited above send.
KVH_TERMINATOR = b"\r\n"
#: How long one command waits for its reply.  The manual's typical answer time for ``?bit`` is 100 ms.
DEFAULT_REPLY_TIMEOUT_S = 1.0
#: How long after the setup the frames are start-up data (no published figure; see the module docstring).
DEFAULT_SETTLE_S = 1.0
#: The longest command accepted (the longest documented KVH command, ``=AXES`` with nine floats, is
#: under 120 characters).
MAX_COMMAND_LEN = 128
#: The most bytes kept while looking for a reply line (a runaway stream cannot grow the line buffer).
_MAX_LINE_BUFFER = 4096
#: Read timeout used during the setup when the port's own is None (blocking) or longer.
_POLL_S = 0.05

#: Commands the setup manages itself or that would break the session: refused in the list.
_RESERVED = {
    "CONFIG": "config mode is entered and left by the setup itself",
    "BAUD": "the port's baud rate would not follow the device's; change the port setting instead",
}


class InvalidSetupCommand(ValueError):
    """A setup command that must not be sent (a configuration error, found when the setup is built)."""


class DeviceSetupError(PortSetupError):
    """The device did not answer a setup command as expected (one line, naming the command).

    ``raw`` holds every byte read from the port during the setup up to the failure.
    """

    def __init__(self, message: str, raw: bytes = b"") -> None:
        super().__init__(message)
        self.raw = raw


def validate_command(command: object) -> str:
    """Return ``command`` if it is a command that may be sent, else raise ``InvalidSetupCommand``.

    A command is a ``str`` of printable ASCII (0x20..0x7E, manual section 4.2) without spaces, at most
    ``MAX_COMMAND_LEN`` characters, starting with ``=`` or ``?`` and followed by a keyword; CR and LF
    (the terminators) are refused, as are ``=CONFIG`` and ``=BAUD`` (see ``_RESERVED``).
    """
    if not isinstance(command, str):
        raise InvalidSetupCommand(f"setup command {command!r}: not a string")
    shown = repr(command) if len(command) <= MAX_COMMAND_LEN else repr(command[:MAX_COMMAND_LEN]) + "..."
    if not command:
        raise InvalidSetupCommand("setup command '': empty")
    if len(command) > MAX_COMMAND_LEN:
        raise InvalidSetupCommand(f"setup command {shown}: longer than {MAX_COMMAND_LEN} characters")
    bad = next((c for c in command if not "\x21" <= c <= "\x7e"), None)
    if bad is not None:
        what = "a line break" if bad in "\r\n" else "a space" if bad == " " else f"character {bad!r}"
        raise InvalidSetupCommand(f"setup command {shown}: contains {what} (only printable ASCII, no spaces)")
    if command[0] not in "=?":
        raise InvalidSetupCommand(f"setup command {shown}: must start with '=' (set) or '?' (query)")
    keyword = command[1:].split(",", 1)[0].upper()
    if not keyword:
        raise InvalidSetupCommand(f"setup command {shown}: no keyword after {command[0]!r}")
    if command[0] == "=" and keyword in _RESERVED:
        raise InvalidSetupCommand(f"setup command {shown}: not allowed ({_RESERVED[keyword]})")
    return command


@dataclass(frozen=True, slots=True)
class DeviceSetup:
    """Commands sent on every open, and how: validated on construction (``InvalidSetupCommand``).

    ``commands`` are sent in order inside configuration mode (``=CONFIG,1`` before, ``=CONFIG,0``
    after); an empty list sends nothing at all.  ``reply_timeout_s`` bounds the wait for each reply;
    ``settle_s`` is how long after the setup the frames are start-up data.
    """

    commands: tuple[str, ...] = ()
    protocol: Literal["kvh"] = "kvh"
    reply_timeout_s: float = DEFAULT_REPLY_TIMEOUT_S
    settle_s: float = DEFAULT_SETTLE_S
    terminator: bytes = KVH_TERMINATOR

    def __post_init__(self) -> None:
        if isinstance(self.commands, str):  # a lone string would be split into characters
            raise InvalidSetupCommand("setup commands: a list of commands, not a single string")
        object.__setattr__(self, "commands", tuple(validate_command(c) for c in self.commands))
        if self.protocol != "kvh":
            raise InvalidSetupCommand(f"setup protocol {self.protocol!r}: only 'kvh' is known")
        if not (_is_number(self.reply_timeout_s) and 0 < self.reply_timeout_s <= 60):
            raise InvalidSetupCommand(f"setup reply_timeout_s {self.reply_timeout_s!r}: need 0 < s <= 60")
        if not (_is_number(self.settle_s) and 0 <= self.settle_s <= 600):
            raise InvalidSetupCommand(f"setup settle_s {self.settle_s!r}: need 0 <= s <= 600")
        if self.terminator not in (b"\r", b"\n", b"\r\n"):
            raise InvalidSetupCommand(f"setup terminator {self.terminator!r}: must be CR, LF or CR LF")

    @classmethod
    def from_mapping(cls, mapping: dict[str, object] | None) -> DeviceSetup:
        """Build from a configuration mapping (``commands``, ``reply_timeout_s``, ``settle_s``).

        Unknown keys and wrong types are ``InvalidSetupCommand`` errors with one line each.
        """
        if mapping is None:
            return cls()
        if not isinstance(mapping, dict):
            raise InvalidSetupCommand(f"setup: expected a mapping, got {type(mapping).__name__}")
        known = {"commands", "protocol", "reply_timeout_s", "settle_s"}
        unknown = sorted(set(mapping) - known)
        if unknown:
            raise InvalidSetupCommand(f"setup: unknown key(s) {', '.join(map(str, unknown))}")
        commands = mapping.get("commands", ())
        if commands is None:
            commands = ()
        if not isinstance(commands, list | tuple):
            raise InvalidSetupCommand(f"setup commands: expected a list, got {type(commands).__name__}")
        kwargs: dict[str, object] = {k: mapping[k] for k in ("protocol", "reply_timeout_s", "settle_s") if k in mapping}
        return cls(tuple(commands), **kwargs)  # type: ignore[arg-type]

    def wire(self) -> list[tuple[str, bytes, str]]:
        """The exchanges of a setup, in order: (command, bytes sent, reply expected); empty if no commands."""
        if not self.commands:
            return []
        sequence = ["=CONFIG,1", *self.commands, "=CONFIG,0"]
        return [(c, c.encode("ascii") + self.terminator, expected_reply(c)) for c in sequence]


@dataclass(frozen=True, slots=True)
class SetupResult:
    """What one setup run produced.

    ``raw``: every byte read from the port during the setup, in order (binary frames sent before the
    device entered configuration mode, reply lines, whatever followed ``CONFIG,0`` in the same read):
    the caller puts them in the raw capture.  ``replies``: the reply line of each exchange (``CONFIG,1``
    first, ``CONFIG,0`` last).  ``finished_monotonic``: ``time.monotonic()`` when ``CONFIG,0`` was
    read; frames until ``settle_until_monotonic`` are start-up data.
    """

    raw: bytes
    replies: tuple[str, ...]
    settle_s: float
    finished_monotonic: float
    sent: tuple[bytes, ...] = field(default=())

    @property
    def settle_until_monotonic(self) -> float:
        """The monotonic time before which frames are start-up data."""
        return self.finished_monotonic + self.settle_s


def _is_number(value: object) -> bool:
    """A real number, not a bool (``True`` is an ``int`` to Python, and a typo in a config file)."""
    return isinstance(value, int | float) and not isinstance(value, bool)


def expected_reply(command: str) -> str:
    """The start of the reply line to ``command``: its text without the prefix, upper case."""
    return command[1:].upper()


def _printable_tail(line: bytes) -> str:
    """The last run of printable ASCII in ``line``: a reply that followed binary frames without a break."""
    end = len(line)
    start = end
    while start > 0 and 0x20 <= line[start - 1] <= 0x7E:
        start -= 1
    return line[start:end].decode("ascii")


def _reply_matches(command: str, tail: str) -> bool:
    """Whether the text ``tail`` is the reply to ``command`` (set: exactly the echo; query: echo + answer)."""
    expected = expected_reply(command)
    if command[0] == "=":
        return tail.upper().endswith(expected)
    upper = tail.upper()
    return upper.endswith(expected) or (expected + ",") in upper


class _LineReader:
    """Reads a port until a reply line or a deadline, keeping every byte read."""

    def __init__(self, port: serial.SerialBase, on_bytes: Callable[[bytes], None] | None) -> None:
        self.port = port
        self.on_bytes = on_bytes
        self.raw = bytearray()
        self._partial = bytearray()
        self.last_line = ""

    def _lines(self, data: bytes) -> Iterable[bytes]:
        self._partial += data
        while True:
            cuts = [c for c in (self._partial.find(b"\r"), self._partial.find(b"\n")) if c >= 0]
            if not cuts:
                break
            cut = min(cuts)
            line = bytes(self._partial[:cut])
            del self._partial[: cut + 1]
            if line:
                yield line
        if len(self._partial) > _MAX_LINE_BUFFER:  # binary stream without a break: keep only the tail
            del self._partial[:-_MAX_LINE_BUFFER]

    def wait_reply(self, command: str, timeout_s: float) -> str:
        """Read until the reply to ``command``; ``DeviceSetupError`` on ``INVALID`` or at the deadline."""
        deadline = time.monotonic() + timeout_s
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                if self.last_line:
                    last = f" (last line: {self.last_line[:60]!r})"
                else:
                    last = f" ({len(self.raw)} bytes, no text line)" if self.raw else " (nothing received)"
                raise DeviceSetupError(
                    f"no reply {expected_reply(command)!r} from the device to {command!r} within {timeout_s:g} s{last}",
                    bytes(self.raw),
                )
            data = self.port.read(max(1, min(self.port.in_waiting, 65536)))
            if not data:
                continue
            self.raw += data
            if self.on_bytes is not None:
                self.on_bytes(data)
            for line in self._lines(data):
                tail = _printable_tail(line)
                if not tail:
                    continue
                self.last_line = tail
                if "INVALID," in tail.upper():  # before the match: the refusal quotes the command
                    raise DeviceSetupError(f"the device refused {command!r}: {tail[:80]!r}", bytes(self.raw))
                if _reply_matches(command, tail):
                    return tail


def run_setup(
    port: serial.SerialBase, setup: DeviceSetup, *, on_bytes: Callable[[bytes], None] | None = None
) -> SetupResult:
    """Send ``setup``'s commands on the open ``port`` inside KVH configuration mode, waiting for each reply.

    Sends ``=CONFIG,1``, each command, ``=CONFIG,0``, each followed by ``setup.terminator``, and after
    each reads the port until its reply line arrives or ``setup.reply_timeout_s`` (monotonic) passes;
    nothing is sent without its predecessor's reply.  Every byte read is kept (returned in
    ``SetupResult.raw``, and passed to ``on_bytes`` as it arrives).  With no commands, nothing is sent
    or read.  Raises ``DeviceSetupError`` (one line, naming the command; ``.raw`` has the bytes read) if a
    reply does not come in time or the device refuses a command, after sending ``=CONFIG,0`` (not
    waited for) so the device is not left silent in configuration mode; ``OSError``/``serial.SerialException`` if the
    port fails.
    """
    exchanges = setup.wire()
    if not exchanges:
        return SetupResult(b"", (), setup.settle_s, time.monotonic())
    saved_timeout = port.timeout
    if saved_timeout is None or saved_timeout > _POLL_S:
        port.timeout = _POLL_S  # each read returns within _POLL_S so the deadline is kept
    reader = _LineReader(port, on_bytes)
    replies: list[str] = []
    sent: list[bytes] = []
    try:
        for command, wire, _ in exchanges:
            port.write(wire)
            port.flush()
            sent.append(wire)
            try:
                replies.append(reader.wait_reply(command, setup.reply_timeout_s))
            except DeviceSetupError:
                if command != "=CONFIG,0":  # maybe in config mode (a reply may be lost): do not leave it mute
                    try:
                        port.write(b"=CONFIG,0" + setup.terminator)
                        port.flush()
                    except PORT_ERRORS:  # the port is going anyway; the setup error is the news
                        pass
                raise
            log.debug("device_setup_reply", command=command, reply=replies[-1])
    finally:
        if port.timeout != saved_timeout:
            port.timeout = saved_timeout
    finished = time.monotonic()
    log.info("device_setup_done", commands=len(setup.commands), bytes_read=len(reader.raw), settle_s=setup.settle_s)
    return SetupResult(bytes(reader.raw), tuple(replies), setup.settle_s, finished, tuple(sent))


def make_on_open(
    setup: DeviceSetup, *, on_result: Callable[[SetupResult], None] | None = None
) -> Callable[[serial.SerialBase], bytes]:
    """A ``PortReader`` ``on_open`` hook running ``setup`` on each open: returns the bytes read.

    ``on_result`` receives each ``SetupResult`` (for ``settle_s`` and ``finished_monotonic``) before the
    bytes are yielded.
    """

    def on_open(port: serial.SerialBase) -> bytes:
        result = run_setup(port, setup)
        if on_result is not None:
            on_result(result)
        return result.raw

    return on_open
