"""How an operator's view of the daemon shows its numbers: ``fog-driver watch``, ``fog-driver ctl`` and the web view
(``fog_driver.daemon.web.view``) format angles, rates and temperatures here, so they always agree.

Standard library only (this is part of the client library).  Angles: ``format_arcsec`` (0.01") and ``format_dms``
(deg, min, sec to 0.01"), rounded half away from zero on the value's shortest decimal form.  Other values:
``show`` (``-`` when absent, a number in a format spec, text made printable) for the terminal views, ``fixed``
(``-`` unless a finite number) for the web page.  ``banners``: what the operator must see first (LINK DOWN, NO DATA,
the bias), the same lines on the terminal and on the page.  ``drift_sigma``: the drift's 1-sigma as both show it
(the since-bias form once a bias was captured).  ``model_in_use`` and ``model_text``: the model the daemon runs,
as every view names it.  ``RateAverage``: the rate's mean over the last second of device time, which both show.
``format_duration``: a duration as ``21 min 4 s``.  ``Progress``: one status line rewritten on a terminal.
"""

from __future__ import annotations

import json
import math
import sys
import time
from collections import deque
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
    "RATE_AVERAGE_S",
    "TEMPERATURE_ORDER",
    "Progress",
    "RateAverage",
    "banners",
    "drift_sigma",
    "finite_number",
    "fixed",
    "format_arcsec",
    "format_dms",
    "format_duration",
    "is_number",
    "link_down",
    "mapping",
    "model_in_use",
    "model_text",
    "no_samples_reason",
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
#: The rate shown is averaged over this much device time (s): ``watch`` and the web view.
RATE_AVERAGE_S = 1.0


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


class RateAverage:
    """The compensated rate's mean over the last ``RATE_AVERAGE_S`` of device time: the mean of *every* frame's
    ``rate_dph`` in it, from ANGLE objects in the order they come, all of them (the web view) or one per
    ``1/rate_hz`` of a decimated ``?WATCH`` (``fog-driver watch``).  One sample's ``rate_dph`` is quantized to
    one count per frame period (1 deg/h steps at 100 Hz); the mean is not.

    Two ANGLE objects ``a``, ``b`` in a row bound a segment of ``n = b.seq - a.seq`` frames; its mean rate is
    ``b.rate_dph`` when ``n == 1`` (adjacent frames: the frame's own rate, which no ``?ZERO`` can disturb), else
    the angle's difference over the device time, ``(b.angle_arcsec - a.angle_arcsec) / (b.t_s - a.t_s)``
    (1 arcsec/s = 1 deg/h: every frame between them counted, the decimated ones too).  The mean is over the
    segments ending in the last ``RATE_AVERAGE_S`` of device time, weighted by their frames::

        rate_dph = sum(rate_k * n_k) / sum(n_k)        span_s = t_last - t_start of the first segment

    The average starts again (no segment across) where the angle is not the sum of the frames' rates: device
    time or ``seq`` going back (the instrument restarted, another one plugged in); frames lost between two
    objects, seen as ``b`` flagged ``gap`` where ``a`` was not (the first frame after a gap is flagged, and its
    successors while the estimate settles: those are averaged as any others), or a step of more than
    ``RATE_AVERAGE_S`` to a ``gap`` sample (a second gap while settling); and ``reset`` (``watch`` calls it at its
    own ``?ZERO``).  A shorter second gap while the first settles, or another client's ``?ZERO`` between two
    decimated objects, is not seen: the mean is off for one second.  Objects without a finite ``t_s`` or an
    integer ``seq`` are ignored."""

    def __init__(self) -> None:
        self._segments: deque[tuple[float, float, int, float]] = deque()  # (t_start, t_end, frames, rate x frames)
        self._last: tuple[float, int, float | None, bool] | None = None  # (t_s, seq, angle_arcsec, flagged gap)

    def reset(self) -> None:
        """Start again from the next ANGLE object."""
        self._segments.clear()
        self._last = None

    def add(self, angle: Mapping[str, Any]) -> None:
        t_s, seq = finite_number(angle.get("t_s")), angle.get("seq")
        if t_s is None or not isinstance(seq, int) or isinstance(seq, bool):
            return
        arcsec = finite_number(angle.get("angle_arcsec"))
        flags = angle.get("flags")
        gap = isinstance(flags, list) and "gap" in flags
        previous, self._last = self._last, (t_s, seq, arcsec, gap)
        if previous is None:
            return
        t_before, seq_before, arcsec_before, gap_before = previous
        dt_s, frames = t_s - t_before, seq - seq_before
        rate_dph = finite_number(angle.get("rate_dph")) if frames == 1 else None
        if rate_dph is None and arcsec is not None and arcsec_before is not None and dt_s > 0:
            rate_dph = (arcsec - arcsec_before) / dt_s
        lost = gap and (not gap_before or dt_s > RATE_AVERAGE_S)
        if dt_s <= 0 or frames <= 0 or lost or rate_dph is None:
            self._segments.clear()
            return
        self._segments.append((t_before, t_s, frames, rate_dph * frames))
        while self._segments[0][1] <= t_s - RATE_AVERAGE_S:
            self._segments.popleft()

    def mean(self) -> tuple[float, float] | None:
        """``(rate_dph, span_s)``, or None before a segment (fewer than two objects since the start or a break)."""
        if not self._segments:
            return None
        frames = sum(segment[2] for segment in self._segments)
        total = math.fsum(segment[3] for segment in self._segments)
        return total / frames, self._segments[-1][1] - self._segments[0][0]


def format_duration(seconds: Any) -> str:
    """A duration as a person reads it, to the second: ``4 s``, ``21 min 4 s``, ``3 h 07 min``, ``2 d 5 h``;
    ``-`` unless a finite number >= 0."""
    value = finite_number(seconds)
    if value is None or value < 0:
        return MISSING
    whole = int(value)
    days, rest = divmod(whole, 86400)
    hours, rest = divmod(rest, 3600)
    minutes, secs = divmod(rest, 60)
    if days:
        return f"{days} d {hours} h"
    if hours:
        return f"{hours} h {minutes:02d} min"
    if minutes:
        return f"{minutes} min {secs} s"
    return f"{secs} s"


def _bias_hint(state: Mapping[str, Any]) -> str:
    """How to capture the bias from here: the key (when keys work) and the ``ctl`` command for this daemon."""
    address = state.get("address")
    at = "" if address in (None, format_address(DEFAULT_HOST, DEFAULT_PORT)) else f" {address}"
    command = f"`fog-driver ctl{at} bias {DEFAULT_BIAS_S}`"
    return f"press b (or {command})" if state.get("keys") else f"run {command}"


def link_down(state: Mapping[str, Any]) -> bool:
    """DEVICE says ``deactivated``, or STATUS's ``port_state`` is there and not ``open``."""
    port_state = mapping(state.get("status")).get("port_state")
    return mapping(state.get("device")).get("state") == "deactivated" or port_state not in (None, "open")


def no_samples_reason(state: Mapping[str, Any]) -> str | None:
    """Why no sample comes, from what the daemon said last (the same keys as ``banners``; ``watch_refused``: the
    message of an ``ERROR`` to ``?WATCH``): ``?WATCH refused, MESSAGE``; ``link down`` (DEVICE ``deactivated``
    or STATUS ``port_state`` not ``open``); ``port open, no samples from the instrument`` (DEVICE
    ``activated`` or STATUS ``port_state`` ``open``); None when the daemon said neither (no DEVICE, no STATUS:
    a daemon that withholds them before ``?AUTH``)."""
    refused = state.get("watch_refused")
    if refused is not None:
        return f"?WATCH refused, {show(refused)}"
    if link_down(state):
        return "link down"
    if mapping(state.get("device")).get("state") == "activated" or mapping(state.get("status")).get("port_state"):
        return "port open, no samples from the instrument"
    return None


def banners(state: Mapping[str, Any]) -> list[str]:
    """What the operator must see first, most urgent first: LINK DOWN, NO DATA for N s, the bias.

    ``LINK DOWN`` when DEVICE says ``deactivated`` (or STATUS's ``port_state`` is not ``open``); ``NO DATA
    for N s (REASON)`` when no ANGLE came for ``NO_DATA_S`` (``angle_age_s``, or ``elapsed_s`` before the first
    one), with ``no_samples_reason`` when there is one;
    the bias banner while STATUS says ``bias_captured: false`` (a daemon that does not say gets none), or a
    running capture's progress (``bias_capture_s`` of ``bias_capture_target_s``).
    """
    lines = []
    status = mapping(state.get("status"))
    if link_down(state):
        lines.append("*** LINK DOWN: the daemon's instrument port is closed; no samples, the angle holds ***")
    age = state.get("angle_age_s") if state.get("angle") else state.get("elapsed_s")
    if is_number(age) and age >= NO_DATA_S and mapping(state.get("watch")).get("enable", True) is not False:
        reason = no_samples_reason(state)
        lines.append(f"*** NO DATA for {age:.0f} s{f' ({reason})' if reason else ''} ***")
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
