"""How an operator's view of the daemon shows its numbers: ``fog-driver watch``, ``fog-driver ctl`` and the web view
(``fog_driver.daemon.web.view``) format angles, rates and temperatures here, so they always agree.

Standard library only (this is part of the client library).  Angles: ``format_arcsec`` (0.01") and ``format_dms``
(deg, min, sec to 0.01"), rounded half away from zero on the value's shortest decimal form.  Other values:
``show`` (``-`` when absent, a number in a format spec, text made printable) for the terminal views, ``fixed``
(``-`` unless a finite number) for the web page.  ``banners``: what the operator must see first (LINK DOWN, NO DATA,
the bias), the same lines on the terminal and on the page.  ``drift_sigma``: the drift's 1-sigma as both show it
(the since-bias form once a bias was captured).  ``model_in_use`` and ``model_text``: the model the daemon runs,
as every view names it.  ``Progress``: one status line rewritten on a terminal.
"""

from __future__ import annotations

import json
import math
import sys
import time
from collections.abc import Mapping
from decimal import ROUND_HALF_UP, Decimal
from typing import Any, TextIO, TypeGuard

from .address import DEFAULT_HOST, DEFAULT_PORT, format_address
from .messages import since_bias_sigma_dph

#: The thermometers in the order every view lists them (``watch``, the web view); any other follows, sorted.
TEMPERATURE_ORDER = ("top", "bottom", "housing")

__all__ = [
    "BAND_SIGMAS",
    "DEFAULT_BIAS_S",
    "DEGREE",
    "MISSING",
    "NO_DATA_S",
    "TEMPERATURE_ORDER",
    "Progress",
    "banners",
    "drift_sigma",
    "finite_number",
    "fixed",
    "format_arcsec",
    "format_dms",
    "is_number",
    "mapping",
    "model_in_use",
    "model_text",
    "show",
    "terminal_safe",
]

#: No ANGLE for this long (s, host time) is the ``NO DATA`` banner.
NO_DATA_S = 3.0
#: ``b``'s (and ``fog-driver ctl bias``'s) ``?BIAS`` seconds.
DEFAULT_BIAS_S = 60

MISSING = "-"
DEGREE = "\u00b0"
#: The web view's band around the drift estimate: +- this many sigma (95 % of a normal error).
BAND_SIGMAS = 1.96


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


def format_dms(arcsec: float, *, degree: str = DEGREE) -> str:
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


def is_number(value: Any) -> TypeGuard[int | float]:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def show(value: Any, spec: str = "") -> str:
    """A value for the view: ``-`` when absent (or null), a number in ``spec``, other values as text."""
    if value is None:
        return MISSING
    if is_number(value):
        if isinstance(value, float) and not math.isfinite(value):
            return str(value)
        try:
            return format(value, spec)
        except OverflowError:  # an integer beyond float's range, in a float format
            return str(_unrounded(value))
    if isinstance(value, bool):
        return "true" if value else "false"
    text = value if isinstance(value, str) else json.dumps(value, separators=(",", ":"), default=str)
    return terminal_safe(text if len(text) <= 60 else text[:57] + "...")


def terminal_safe(text: str) -> str:
    """No control characters from the server reach the terminal (no newlines, no escape sequences)."""
    return text if text.isprintable() else "".join(ch if ch.isprintable() else "?" for ch in text)


def mapping(value: Any) -> Mapping[str, Any]:
    """``value`` when it is a mapping, else an empty one (a server's object may hold anything)."""
    return value if isinstance(value, Mapping) else {}


def finite_number(value: Any) -> float | None:
    """``value`` as a float when it is a finite number (not a bool), else None."""
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        value = float(value)
        return value if math.isfinite(value) else None
    return None


def fixed(value: Any, digits: int) -> str:
    """A finite number to ``digits`` decimals (``f"{value:.{digits}f}"``), else ``-`` (the web page's rule)."""
    number = finite_number(value)
    return "-" if number is None else f"{number:.{digits}f}"


def drift_sigma(angle: Mapping[str, Any], status: Mapping[str, Any]) -> tuple[float | None, bool]:
    """``(sigma_dph, since_bias)``: the drift's 1-sigma as the operator's views show it, from an ANGLE object and
    the last STATUS.  Before a bias is captured, the sample's ``drift_sigma_dph``, sigma(t): the error of the
    estimate's 1-min mean about its mean over the run (that mean is the bias).  Once STATUS says a ``?BIAS``
    capture completed (``bias_captured``) with ``bias_sigma_dph`` = sigma(t_b), the error since then
    (``since_bias`` True)::

        sqrt(sigma(t)**2 + sigma(t_b)**2)

    ``sigma_dph`` is None when the sample has none (no estimate, a daemon before protocol 1.1), and when a bias
    was captured without one (its share of the error is unknown: no figure rather than one too small)."""
    sigma = finite_number(angle.get("drift_sigma_dph"))
    if sigma is None or status.get("bias_captured") is not True:
        return sigma, False
    return since_bias_sigma_dph(sigma, status.get("bias_sigma_dph")), True


def model_in_use(status: Mapping[str, Any], version: Mapping[str, Any]) -> Mapping[str, Any]:
    """The model the daemon runs (``model_file``: path, sha256, kind, created_utc, serial): STATUS's, which a
    reload changes from the next one on, else VERSION's (the greeting), else empty (a daemon before protocol
    1.2, or one with a token before ``?AUTH``)."""
    return mapping(mapping(status).get("model_file")) or mapping(mapping(version).get("model_file"))


def model_text(model_file: Mapping[str, Any]) -> str:
    """The model in one line, as ``watch``, ``ctl status`` and the web page name it: ``PATH (KIND, fitted
    CREATED_UTC, for SERIAL)``, the path whole (made printable, never shortened); ``-`` when unknown.  The
    SHA-256 is each view's to show (``ctl status`` prints it whole on a line of its own)."""
    model_file = mapping(model_file)
    if not model_file:
        return MISSING
    path = model_file.get("path")
    details = [show(model_file.get("kind"))]
    if model_file.get("created_utc") is not None:
        details.append(f"fitted {show(model_file.get('created_utc'))}")
    if model_file.get("serial") is not None:
        details.append(f"for {show(model_file.get('serial'))}")
    where = terminal_safe(path) if isinstance(path, str) else "(not from a file)"
    return f"{where} ({', '.join(details)})"


def _bias_hint(state: Mapping[str, Any]) -> str:
    """How to capture the bias from here: the key (when keys work) and the ``ctl`` command for this daemon."""
    address = state.get("address")
    connect = "" if address in (None, format_address(DEFAULT_HOST, DEFAULT_PORT)) else f" --connect {address}"
    command = f"`fog-driver ctl{connect} bias {DEFAULT_BIAS_S}`"
    return f"press b (or {command})" if state.get("keys") else f"run {command}"


def banners(state: Mapping[str, Any]) -> list[str]:
    """What the operator must see first, most urgent first: LINK DOWN, NO DATA for N s, the bias.

    ``LINK DOWN`` when DEVICE says ``deactivated`` (or STATUS's ``port_state`` is not ``open``); ``NO DATA
    for N s`` when no ANGLE came for ``NO_DATA_S`` (``angle_age_s``, or ``elapsed_s`` before the first one);
    the bias banner while STATUS says ``bias_captured: false`` (a daemon that does not say gets none), or a
    running capture's progress (``bias_capture_s`` of ``bias_capture_target_s``).
    """
    lines = []
    device, status = mapping(state.get("device")), mapping(state.get("status"))
    port_state = status.get("port_state")
    if device.get("state") == "deactivated" or (port_state is not None and port_state != "open"):
        lines.append("*** LINK DOWN: the daemon's instrument port is closed; no samples, the angle holds ***")
    age = state.get("angle_age_s") if state.get("angle") else state.get("elapsed_s")
    if is_number(age) and age >= NO_DATA_S and mapping(state.get("watch")).get("enable", True) is not False:
        lines.append(f"*** NO DATA for {age:.0f} s ***")
    if is_number(status.get("bias_capture_target_s")):
        lines.append(
            f"capturing the bias: {show(status.get('bias_capture_s'), '.1f')} / "
            f"{show(status.get('bias_capture_target_s'), 'g')} s of data; keep the table still"
        )
    elif status.get("bias_captured") is False:
        lines.append(f"bias not removed: at rest the angle climbs with Earth rate + bias; {_bias_hint(state)}")
    return lines


class Progress:
    """Rewrites one status line on a terminal (``\\r``); silent when the stream is not a tty (piped, CI)."""

    def __init__(self, stream: TextIO | None = None, min_interval_s: float = 0.2) -> None:
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = bool(getattr(self.stream, "isatty", lambda: False)())
        self.min_interval_s = min_interval_s
        self._last_shown = 0.0
        self._width = 0

    def show(self, text: str, force: bool = False) -> None:
        if not self.enabled:
            return
        now = time.monotonic()
        if not force and now - self._last_shown < self.min_interval_s:
            return
        self._last_shown = now
        pad = max(0, self._width - len(text))
        self.stream.write("\r" + text + " " * pad)
        self.stream.flush()
        self._width = len(text)

    def clear(self) -> None:
        if self.enabled and self._width:
            self.stream.write("\r" + " " * self._width + "\r")
            self.stream.flush()
            self._width = 0

    def bytes_done(self, done: int, total: int) -> None:
        pct = 100.0 * done / total if total else 100.0
        self.show(f"decoding {done / 1e6:.1f} / {total / 1e6:.1f} MB ({pct:.0f} %)")
