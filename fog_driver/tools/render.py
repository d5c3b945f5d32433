"""``fog-driver watch``'s view, pure: a state mapping in, the lines shown out (``render`` for the terminal block,
``compact_line`` for a log line a second).  The numbers are formatted by ``fog_driver.client.display``, as the web
view formats them."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from ..client.display import (
    DEFAULT_BIAS_S,
    DEGREE,
    MISSING,
    TEMPERATURE_ORDER,
    banners,
    drift_sigma,
    finite_number,
    format_arcsec,
    format_dms,
    is_number,
    mapping,
    model_in_use,
    model_text,
    show,
    terminal_safe,
)

__all__ = ["compact_line", "device_text", "identity_text", "model_line", "render", "server_text"]


def _angle_text(value: Any, degree: str) -> str:
    if value is None:
        return MISSING
    if is_number(value):
        return f'{format_arcsec(value)}" ({format_dms(value, degree=degree)})'
    return show(value)


def _hz(value: Any) -> str:
    return f"{show(value, 'g')} Hz" if value is not None else MISSING


def identity_text(version: Mapping[str, Any]) -> str:
    inst = mapping(version.get("instrument"))
    if not inst:
        return MISSING
    parts = [f"serial {show(inst.get('serial'))}"]
    if inst.get("firmware") is not None:
        parts.append(f"firmware {show(inst.get('firmware'))}")
    if inst.get("rate_hz") is not None:
        parts.append(_hz(inst.get("rate_hz")))
    return ", ".join(parts)


def device_text(device: Mapping[str, Any]) -> str:
    if not device:
        return MISSING
    parts = [show(device.get("path")) if device.get("path") is not None else "(no path)"]
    parts.append(show(device.get("state")))
    if device.get("serial") is not None:
        parts.append(f"serial {show(device.get('serial'))}")
    if device.get("rate_hz") is not None:
        parts.append(_hz(device.get("rate_hz")))
    return ", ".join(parts)


#: The hex digits of the model file's SHA-256 ``watch`` shows (``fog-driver ctl status`` prints them all).
MODEL_SHA256_DIGITS = 12


def model_line(model_file: Mapping[str, Any]) -> str:
    """The model in use (``display.model_text``) and the first ``MODEL_SHA256_DIGITS`` of its SHA-256."""
    text = model_text(model_file)
    sha256 = mapping(model_file).get("sha256")
    if isinstance(sha256, str):
        text += f"  sha256 {terminal_safe(sha256[:MODEL_SHA256_DIGITS])}"
    return text


def server_text(version: Mapping[str, Any]) -> str:
    if not version:
        return "waiting for VERSION"
    text = f"server {show(version.get('release'))}"
    major, minor = version.get("proto_major"), version.get("proto_minor")
    if major is not None:
        text += f", protocol {show(major)}.{show(minor) if minor is not None else 0}"
        if major != 1:
            text += " (this client speaks 1.x)"
    return text


def _temps(temps: Mapping[str, Any], sep: str) -> str:
    if not temps:
        return MISSING
    names = [*TEMPERATURE_ORDER] + sorted(k for k in temps if k not in TEMPERATURE_ORDER)
    return sep.join(f"{name} {show(temps.get(name), '.2f')}" for name in names) + " degC"


def _flags(flags: Any) -> str:
    if flags is None:
        return MISSING
    if isinstance(flags, list):
        return ", ".join(show(f) for f in flags) if flags else "none"
    return show(flags)


def _status_items(status: Mapping[str, Any]) -> list[str]:
    items = []
    for key in sorted(k for k in status if isinstance(k, str) and k != "class"):
        value = status[key]
        if isinstance(value, (str, int, float)):  # scalars only (bool is an int)
            items.append(f"{terminal_safe(key)}={show(value, 'g' if isinstance(value, float) else '')}")
    return items


#: The terminal block's labels take this many columns; a wrapped line goes on under the text after them.
_LABEL_COLUMNS = 12


def _wrap(label: str, items: list[str], width: int) -> list[str]:
    """``label  a  b  c`` wrapped at ``width``, continuation lines indented under the first item."""
    indent = " " * _LABEL_COLUMNS
    lines, current = [], f"{label:<{_LABEL_COLUMNS}}"
    for item in items:
        candidate = current + ("  " if current.strip() != label else "") + item
        if len(candidate) > width and current.strip() != label:
            lines.append(current)
            current = indent + item
        else:
            current = candidate
    lines.append(current)
    return lines


def _fold(line: str, width: int) -> list[str]:
    """A line longer than ``width`` cut into lines that fit, each after the first indented under the label's
    text: between two items (a double space) where one fits, else at a space, else where it must be.  Nothing
    is lost at the terminal's edge."""
    indent = " " * _LABEL_COLUMNS if width > 2 * _LABEL_COLUMNS else ""
    lines: list[str] = []
    rest = line
    while len(rest) > width:
        start = len(indent) + 1  # past the label (or the indent): its padding is no place to cut
        window = rest[: width + 1]
        cut = window.rfind("  ", start)
        if cut < start:
            cut = window.rfind(" ", start)
        if cut < start:
            cut = width
        lines.append(rest[:cut].rstrip())
        rest = indent + rest[cut:].lstrip()
    return [*lines, rest]


def _received(state: Mapping[str, Any]) -> str:
    parts = [f"{show(state.get('angle_rate_hz'), '.1f')} ANGLE/s", f"{show(state.get('angles', 0), ',')} ANGLE"]
    for key, name in (("malformed", "malformed"), ("oversized", "oversized"), ("unknown", "unknown class")):
        if state.get(key):
            parts.append(f"{show(state.get(key), ',')} {name}")
    policy = mapping(state.get("watch"))
    if policy:
        if policy.get("enable") is False:
            parts.append("(WATCH disabled)")
        else:
            rate = policy.get("rate_hz")
            parts.append(f"(WATCH {show(rate, 'g')} Hz)" if rate is not None else "(WATCH every sample)")
    return "  ".join(parts)


def _rate_text(state: Mapping[str, Any], angle: Mapping[str, Any]) -> str:
    """The rate: the mean over the last second of device time (0.01 deg/h), else the one sample's (0.1)."""
    mean, span = state.get("rate_mean_dph"), state.get("rate_span_s")
    if is_number(mean) and is_number(span):
        return f"{show(mean, '.2f')} deg/h (mean over {show(span, '.1f')} s)"
    return f"{show(angle.get('rate_dph'), '.1f')} deg/h (one sample)"


def _drift_text(angle: Mapping[str, Any], status: Mapping[str, Any]) -> str:
    """The drift estimate and, when the sample has one, its 1-sigma (``display.drift_sigma``: since the bias
    once one was captured, and labelled so); ``- (no estimate yet)`` while the sample has none (``drift_dph``
    absent: flagged uncompensated)."""
    if finite_number(angle.get("drift_dph")) is None:
        return f"{show(None)} (no estimate yet)"
    text = f"{show(angle.get('drift_dph'), '.4f')} deg/h"
    if finite_number(angle.get("drift_sigma_dph")) is None:
        return text
    sigma, since_bias = drift_sigma(angle, status)
    if since_bias and sigma is None:
        return text + " +- - (1-sigma since the bias: unknown, the bias was captured without one)"
    if since_bias:
        return text + f" +- {show(sigma, '.4f')} (1-sigma since the bias)"
    return text + f" +- {show(sigma, '.4f')} (1-sigma)"


def render(state: Mapping[str, Any], *, width: int = 80, degree: str = DEGREE, height: int | None = None) -> list[str]:
    """The live view's lines (no ANSI, no newlines) from a state mapping; every key may be absent.  Every line
    fits in ``width`` columns (the terminal's; 80 by default): a longer one is folded at spaces (``_fold``).
    With ``height`` (the terminal's lines), a block that would not fit loses the end of its STATUS counters (the
    last line kept says how many more there are), never the lines after them: the error, the last key's outcome,
    the keys.

    Keys read: ``address`` (text), ``elapsed_s``, ``version``/``device``/``angle``/``status``
    (the latest protocol object of that class; the model in use is STATUS's, else VERSION's), ``error`` (the last
    ERROR message),
    ``watch`` (the server's WATCH answer), ``angles`` (ANGLE objects received), ``angle_rate_hz``, ``angle_age_s``
    (seconds since the last ANGLE), ``rate_mean_dph`` and ``rate_span_s`` (the averaged rate and the device time it
    spans), ``keys`` (keys work: their line is shown), ``action`` (the last key's outcome), ``malformed``,
    ``oversized``, ``unknown``.
    """
    version, device = mapping(state.get("version")), mapping(state.get("device"))
    angle, status = mapping(state.get("angle")), mapping(state.get("status"))
    head = f"fog-driver watch {show(state.get('address'))}  |  {server_text(version)}"
    if state.get("elapsed_s") is not None:
        head += f"  |  {show(state.get('elapsed_s'), '.1f')} s"
    lines = [head, *banners(state)]
    lines += [
        f"{'instrument':<12}{identity_text(version)}",
        f"{'model':<12}{model_line(model_in_use(status, version))}",
        f"{'device':<12}{device_text(device)}",
    ]
    if not angle:
        lines.append(f"{'angle':<12}{MISSING} (waiting for ANGLE)")
    else:
        lines.append(
            f"{'angle':<12}{_angle_text(angle.get('angle_arcsec'), degree)}"
            f"    raw {_angle_text(angle.get('angle_raw_arcsec'), degree)}"
        )
        lines.append(f"{'rate':<12}{_rate_text(state, angle)}")
        lines.append(f"{'drift':<12}{_drift_text(angle, status)}")
        lines.append(f"{'temps':<12}{_temps(mapping(angle.get('temps_c')), '  ')}")
        lines.append(f"{'flags':<12}{_flags(angle.get('flags'))}")
        sample = f"seq {show(angle.get('seq'))}  t {show(angle.get('t_s'), '.3f')} s"
        if angle.get("utc") is not None:
            sample += f"  utc {show(angle.get('utc'))}"
        if state.get("angle_age_s") is not None:
            sample += f"  (received {show(state.get('angle_age_s'), '.1f')} s ago)"
        lines.append(f"{'sample':<12}{sample}")
    lines.append(f"{'received':<12}{_received(state)}")
    items = _status_items(status)
    counters = _wrap("status", items, width) if items else [f"{'status':<12}{MISSING}"]
    after = []
    if state.get("error") is not None:
        after.append(f"{'error':<12}{show(state.get('error'))}")
    if state.get("action") is not None:
        after.append(f"{'last key':<12}{terminal_safe(str(state.get('action')))}")
    if state.get("keys"):
        after.append(f"{'keys':<12}q quit   z zero the angle   b capture the bias ({DEFAULT_BIAS_S} s, table still)")
    before, after = _folded(lines, width), _folded(after, width)
    counters = _folded(counters, width)
    if height is not None and len(before) + len(counters) + len(after) > height:
        room = max(1, height - len(before) - len(after))
        hidden = len(counters) - room + 1
        label = "status" if room == 1 else ""
        counters = [*counters[: room - 1], f"{label:<12}... {hidden} more line(s) of counters (a taller terminal)"]
    return before + counters + after


def _folded(lines: list[str], width: int) -> list[str]:
    return [folded for line in lines for folded in _fold(line, width)]


def compact_line(state: Mapping[str, Any], *, degree: str = DEGREE) -> str:
    """One line of the latest state, for logs (the non-terminal view prints one a second)."""
    angle, status = mapping(state.get("angle")), mapping(state.get("status"))
    parts = [f"[{show(state.get('elapsed_s'), '7.1f')} s]"]
    parts += [
        line.strip("* ").split(":")[0] if line.startswith("***") else line.split(";")[0] for line in banners(state)
    ]
    if not angle:
        parts.append("waiting for ANGLE")
    else:
        parts += [
            f"seq {show(angle.get('seq'))}",
            f"t {show(angle.get('t_s'), '.3f')} s",
            f"angle {_angle_text(angle.get('angle_arcsec'), degree)}",
            f"raw {_angle_text(angle.get('angle_raw_arcsec'), degree)}",
            f"rate {_rate_text(state, angle)}",
            f"drift {_drift_text(angle, status)}",
            f"temps {_temps(mapping(angle.get('temps_c')), ' ')}",
            f"flags {_flags(angle.get('flags')).replace(', ', ',')}",
        ]
    parts.append(_received(state))
    items = _status_items(status)
    if items:
        parts.append("status " + " ".join(items))
    return parts[0] + " " + " | ".join(parts[1:])
