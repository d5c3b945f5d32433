"""``fog-driver ctl``: one control command to a running daemon (``fog-driver run``), like gpsd's ``gpsctl``.

``fog-driver ctl [HOST:PORT] [--token-file FILE] [--json] COMMAND [ARGS]`` (or ``--connect HOST:PORT``, as
``watch`` takes the address: a first word that is not a command is the daemon's address) with COMMAND one of:

=====================  =========================================================================
``zero``               ``?ZERO``: the published angles start again from 0 here
``bias [SECONDS]``     ``?BIAS`` (60 s by default, 1..86400): acknowledged at once, then the
                       result event is waited for (SECONDS of device data plus the daemon's margin,
                       and 5 s more); on a terminal a progress line shows on stderr
``adapt on|off``       ``?ADAPT``: adapt the model's weights online (``--reference-dph``, 0 at rest)
``table ANGLE``        ``?TABLE``: the table has stood at ANGLE degrees for the last ``--dwell`` seconds
                       (default 12, the least), from ``--angle-start`` when it moved within the dwell
``reload``             ``?RELOAD``: load the model file again (unchanged: nothing happens)
``status``             ``?STATUS``: one line of the daemon's state, then the model in use (its
                       file, kind, fit date and serial) and ``sha256: HEX`` of its file
``save``               ``?SAVE``: save the adaptation state to the configured file
=====================  =========================================================================

It is built on the client library (``fog_driver.client.Client``, without reconnecting); the token comes
from ``FOG_DRIVER_TOKEN`` or ``--token-file`` and ``?AUTH`` is sent first.  Output: one human-readable line per
answer on stdout (``status``: three, with the model's), or with ``--json`` the daemon's own lines (the reply,
and for ``bias`` the result event).
Exit statuses (sysexits), each failure one line on stderr: 0 done; 64 the daemon does not know the
command (an older daemon), or bad arguments (a first word that is neither a command nor followed by one, an
address that is not HOST:PORT, the address given twice: checked after argparse, whose grammar cannot say
``[HOST:PORT] COMMAND``, so one line and 64 like every other bad argument of ctl, not argparse's 2); 65 the
daemon refused the command or the bias capture failed; 69 the daemon cannot be reached or the connection was
lost; 77 the token was refused or is needed.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Mapping
from typing import Any, TextIO

from ..client import Bias, BiasFailed, Client, CommandRefused, Message, NoReply, Status, Unauthorized, UnknownCommand
from ..client.display import DEFAULT_BIAS_S, Progress, mapping, model_text
from ..client.protocol import (
    MAX_BIAS_S,
    MAX_REFERENCE_DPH,
    MIN_TABLE_DWELL_S,
    REPLY_TIMEOUT_S,
    answer_as,
    printable,
    table_args,
)
from ..client.wire import TOKEN_ENV, parse_address, read_token
from ..errors import FogDriverError, UsageError

__all__ = ["COMMANDS", "ctl_command", "parse_request", "run_ctl", "split_words"]

#: ``fog-driver ctl`` commands -> the protocol's command names.
COMMANDS = {
    "zero": "ZERO",
    "bias": "BIAS",
    "adapt": "ADAPT",
    "table": "TABLE",
    "reload": "RELOAD",
    "status": "STATUS",
    "save": "SAVE",
}
#: Seconds the result of a ``bias`` is waited for beyond the daemon's own deadline (``timeout_s`` of its reply).
BIAS_WAIT_MARGIN_S = 5.0
#: How long a reply is waited for by default: the client library's (the daemon answers every control command
#: within 30 s).
DEFAULT_TIMEOUT_S = REPLY_TIMEOUT_S


def split_words(words: list[str], address: str | None = None) -> tuple[str | None, str, list[str]]:
    """``[HOST:PORT] COMMAND [ARG ...]`` -> ``(address, command, args)``: a first word that is a command is the
    command (and ``address``, from ``--connect``, the address), any other the daemon's address, followed by the
    command.  ``UsageError`` (one line naming the commands) for a first word that is neither a command nor an
    address followed by one, for a malformed address, and for an address given twice."""
    names = ", ".join(COMMANDS)
    if not words:
        raise UsageError(f"no command: one of {names}")
    first, rest = words[0], words[1:]
    if first in COMMANDS:
        return address, first, rest
    if not rest:
        raise UsageError(f"{first!r} is not a command ({names}), and no command follows it")
    if rest[0] not in COMMANDS:
        raise UsageError(f"neither {first!r} nor {rest[0]!r} is a command ({names})")
    try:
        parse_address(first)
    except UsageError as exc:
        raise UsageError(f"{exc} (and not a command: {names})") from None
    if address is not None:
        raise UsageError(f"the daemon's address given twice: {first!r} and --connect {address}")
    return first, rest[0], rest[1:]


def parse_request(
    command: str,
    words: list[str],
    *,
    reference_dph: float | None = None,
    dwell_s: float | None = None,
    angle_start_deg: float | None = None,
) -> tuple[str, dict | None]:
    """``ctl``'s COMMAND and ARGS -> ``(protocol name, argument object or None)``; ``UsageError`` when bad."""
    name = COMMANDS.get(command)
    if name is None:
        raise UsageError(f"unknown command {command!r}: one of {', '.join(COMMANDS)}")
    if reference_dph is not None and name != "ADAPT":
        raise UsageError("--reference-dph goes with `adapt on` only")
    if (dwell_s is not None or angle_start_deg is not None) and name != "TABLE":
        raise UsageError("--dwell and --angle-start go with `table` only")
    if name == "TABLE":
        if len(words) != 1:
            raise UsageError("table takes one argument: the table's angle in degrees")
        try:
            angle = float(words[0])
        except ValueError:
            raise UsageError(f"table ANGLE: not a number: {words[0]!r}") from None
        try:
            return name, table_args(angle, MIN_TABLE_DWELL_S if dwell_s is None else dwell_s, angle_start_deg)
        except ValueError as exc:
            raise UsageError(f"table: {exc}") from None
    if name == "BIAS":
        if len(words) > 1:
            raise UsageError("bias takes at most one argument: the seconds of data (default 60)")
        if not words:
            return name, {"seconds": DEFAULT_BIAS_S}
        try:
            seconds = float(words[0])
        except ValueError:
            raise UsageError(f"bias SECONDS: not a number: {words[0]!r}") from None
        if not 1 <= seconds <= MAX_BIAS_S:
            raise UsageError(f"bias SECONDS must be between 1 and {MAX_BIAS_S}, not {words[0]}")
        return name, {"seconds": int(seconds) if seconds.is_integer() else seconds}
    if name == "ADAPT":
        if len(words) != 1 or words[0] not in ("on", "off"):
            raise UsageError("adapt takes one argument: on or off")
        if words[0] == "off":
            if reference_dph is not None:
                raise UsageError("--reference-dph goes with `adapt on` only")
            return name, {"enable": False}
        reference = 0.0 if reference_dph is None else reference_dph
        if not (math.isfinite(reference) and abs(reference) <= MAX_REFERENCE_DPH):
            raise UsageError(f"--reference-dph must be a number within +-{MAX_REFERENCE_DPH:g} deg/h")
        return name, {"enable": True, "reference_dph": reference}
    if words:
        raise UsageError(f"{command} takes no arguments")
    return name, None


def _number(obj: Mapping[str, Any], key: str, spec: str) -> str:
    value = obj.get(key)
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return format(value, spec)
    return "-"


def _word(obj: Mapping[str, Any], key: str) -> str:
    value = obj.get(key)
    return printable(value if isinstance(value, str) else "-" if value is None else str(value))


def describe(reply: dict) -> str:
    """The human-readable text of a daemon's answer (or BIAS event): one line, but for STATUS's model lines."""
    cls = reply.get("class")
    if cls == "ZERO":
        return "zeroed: the published angle starts again from 0 here"
    if cls == "BIAS":
        state = reply.get("state")
        if state == "started":
            return (
                f"bias capture started: {_number(reply, 'seconds', 'g')} s of data; keep the table still "
                f"(result within {_number(reply, 'timeout_s', 'g')} s)"
            )
        if state == "done":
            sigma = ""  # a daemon since protocol 1.1 with a drift sigma: the since-bias form's sigma(t_b)
            if reply.get("bias_sigma_dph") is not None:
                sigma = f" (the drift's 1-sigma then {_number(reply, 'bias_sigma_dph', '.4f')} deg/h)"
            return (
                f"bias captured: {_number(reply, 'bias_dph', '.4f')} deg/h over {_number(reply, 'seconds', '.1f')} s"
                f"{sigma}; removed from rate_dph and angle_arcsec from now on"
            )
        return f"bias capture failed: {_word(reply, 'reason')}"
    if cls == "ADAPT":
        if reply.get("enable"):
            return (
                f"adaptation on: the weights adapt while the table is static "
                f"(reference {_number(reply, 'reference_dph', 'g')} deg/h)"
            )
        return "adaptation off: the weights are frozen"
    if cls == "TABLE":
        return (
            f"table angle {_number(reply, 'angle_deg', 'g')} deg taken for the dwell "
            f"{_number(reply, 't_start_s', '.1f')}..{_number(reply, 't_end_s', '.1f')} s of device time "
            f"(its verdict: fog-driver ctl status)"
        )
    if cls == "RELOAD":
        if reply.get("changed"):
            return f"reloaded the model: {_word(reply, 'model')} (created {_word(reply, 'created_utc')})"
        return f"model unchanged ({_word(reply, 'model')}, created {_word(reply, 'created_utc')}): nothing reloaded"
    if cls == "SAVE":
        return f"adaptation state saved to {_word(reply, 'path')}"
    if cls == "STATUS":
        bias = "captured" if reply.get("bias_captured") else "not captured"
        if reply.get("bias_capture_target_s") is not None:
            bias = (
                f"capturing {_number(reply, 'bias_capture_s', '.1f')} / "
                f"{_number(reply, 'bias_capture_target_s', 'g')} s"
            )
        line = (
            f"port {_word(reply, 'port_state')}, {_number(reply, 'frames', ',')} frames, "
            f"{_number(reply, 'published', ',')} published, bias {_number(reply, 'bias_dph', '.4f')} deg/h ({bias}), "
            f"adapting {'yes' if reply.get('adapting') else 'no'}, {_number(reply, 'clients', 'd')} clients, "
            f"capture {_word(reply, 'capture_state')}, uptime {_number(reply, 'uptime_s', '.0f')} s"
        )
        return "\n".join([line, *_model_lines(reply)])
    return _word(reply, "class")


def _model_lines(status: Mapping[str, Any]) -> list[str]:
    """STATUS's model in use (protocol 1.2): ``model PATH (KIND, fitted ..., for SERIAL)`` and ``sha256: HEX``;
    none from an older daemon."""
    model_file = mapping(status.get("model_file"))
    if not model_file:
        return []
    return [f"model {model_text(model_file)}", f"sha256: {_word(model_file, 'sha256')}"]


def _refused(name: str, exc: CommandRefused) -> FogDriverError:
    """The library's typed refusal, in ctl's words (a missing token names the environment variable and flag)."""
    if isinstance(exc, Unauthorized):
        if name == "AUTH":
            return Unauthorized(f"the daemon refused the token: {_word({'m': exc.message}, 'm')}")
        return Unauthorized(f"the daemon needs a token for ?{name}: set {TOKEN_ENV} or give --token-file")
    if isinstance(exc, UnknownCommand):
        return UsageError(str(exc))
    return exc


def run_ctl(
    host: str,
    port: int,
    name: str,
    args: dict | None,
    *,
    token: str | None = None,
    json_out: bool = False,
    out: TextIO | None = None,
    progress_stream: TextIO | None = None,
    timeout_s: float = DEFAULT_TIMEOUT_S,
) -> int:
    """Send one command (``name``, ``args``) to the daemon at ``host:port`` and print its answer; for ``BIAS``
    wait for the capture's result too.  Returns 0; raises ``FogDriverError`` (one line, its exit status)."""
    out = sys.stdout if out is None else out
    client = Client(
        (host, port), token=token, timeout_s=min(timeout_s, 5.0), reconnect=False, reply_timeout_s=timeout_s
    )
    try:
        try:
            client.connect()  # ConnectError (69) at once; Unauthorized (77) for a refused token
        except CommandRefused as exc:
            raise _refused("AUTH", exc) from None
        try:
            reply = client.command(name, args)
        except CommandRefused as exc:
            raise _refused(name, exc) from None
        _show(out, json_out, reply)
        if name == "BIAS":
            _wait_for_bias(
                client,
                answer_as(Bias, reply),
                out,
                json_out,
                progress_stream if progress_stream is not None else sys.stderr,
            )
        return 0
    finally:
        client.close()


def _show(out: TextIO, json_out: bool, message: Message) -> None:
    out.write((message.line.decode("utf-8") if json_out else describe(dict(message.raw))) + "\n")
    out.flush()


def _wait_for_bias(client: Client, started: Bias, out: TextIO, json_out: bool, progress_stream: TextIO) -> None:
    """The result of the capture ``started`` acknowledged: its ``done`` event (printed), or a failure."""
    wait_s = started.timeout_s
    if wait_s is None or not 0 < wait_s <= MAX_BIAS_S + 3600:
        wait_s = (started.seconds or DEFAULT_BIAS_S) + 30.0
    deadline = time.monotonic() + wait_s + BIAS_WAIT_MARGIN_S
    progress = Progress(progress_stream)
    try:
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise NoReply(f"no result of the bias capture from {client.address} within the time allowed")
            message = client.poll(remaining)
            if (
                isinstance(message, Bias)
                and message.state in ("done", "failed")
                and message.capture_id == started.capture_id
            ):
                result = message
                break
            if isinstance(message, Status) and message.raw.get("bias_capture_target_s") is not None:
                progress.show(
                    f"bias: {_number(message.raw, 'bias_capture_s', '.1f')} / "
                    f"{_number(message.raw, 'bias_capture_target_s', 'g')} s of data (keep the table still)"
                )
    finally:
        progress.clear()
    _show(out, json_out, result)
    if result.state != "done":
        raise BiasFailed(describe(dict(result.raw)), message=result.reason or "", command="BIAS")


def ctl_command(
    words: list[str],
    *,
    address: str | None = None,
    token_file: str | None = None,
    json_out: bool = False,
    reference_dph: float | None = None,
    timeout_s: float = DEFAULT_TIMEOUT_S,
    dwell_s: float | None = None,
    angle_start_deg: float | None = None,
) -> int:
    """``fog-driver ctl [HOST:PORT] COMMAND [ARG ...]`` (``words``; ``address``: ``--connect``): split the words
    (``split_words``), parse the command and the address, read the token, run it on stdout."""
    address, command, arguments = split_words(words, address)
    name, args = parse_request(
        command, arguments, reference_dph=reference_dph, dwell_s=dwell_s, angle_start_deg=angle_start_deg
    )
    host, port = parse_address(address)
    token = read_token(token_file)
    return run_ctl(host, port, name, args, token=token, json_out=json_out, timeout_s=timeout_s)
