"""The command line's argument types: each turns one option's text into its value, or says in one line why not
(``argparse.ArgumentTypeError``)."""

from __future__ import annotations

import argparse
import math

from ..client.protocol import MAX_WATCH_RATE_HZ


def finite_float(text: str) -> float:
    """Any number but NaN and the infinities (which Python's ``float`` takes)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number: {text!r}")
    return value


def positive_float(text: str) -> float:
    """A finite number > 0 (a duration, a rate, a scale: infinity is none of them)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not value > 0 or not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be > 0 and finite: {text!r}")
    return value


#: The longest ``ctl --timeout``: a day (beyond every answer and bias capture; 1e10 s overflowed ``select``).
MAX_REPLY_TIMEOUT_S = 86400.0


def reply_timeout_s(text: str) -> float:
    """How long to wait for a daemon's answer: a finite number of seconds, > 0 and at most ``MAX_REPLY_TIMEOUT_S``."""
    value = positive_float(text)
    if value > MAX_REPLY_TIMEOUT_S:
        raise argparse.ArgumentTypeError(f"an answer is waited for at most {MAX_REPLY_TIMEOUT_S:g} s (a day): {text!r}")
    return value


def watch_rate_hz(text: str) -> float:
    """``watch --rate-hz``: ANGLE updates a second, > 0 and at most ``MAX_WATCH_RATE_HZ`` (what a daemon takes)."""
    value = positive_float(text)
    if value > MAX_WATCH_RATE_HZ:
        raise argparse.ArgumentTypeError(f"a daemon sends at most {MAX_WATCH_RATE_HZ} ANGLE updates a second: {text!r}")
    return value


F32_TINY = 2.0**-126  #: the smallest normal float32 ...
F32_MAX = (2.0 - 2.0**-23) * 2.0**127  #: ... and the largest


def scale_arcsec_per_count(text: str) -> float:
    """A scale factor as an IDENTITY frame carries it: a float32, ``F32_TINY`` to ``F32_MAX`` arcsec per count
    (a larger number is infinite as a float32, a smaller one 0 or subnormal)."""
    value = positive_float(text)
    if not F32_TINY <= value <= F32_MAX:
        raise argparse.ArgumentTypeError(
            f"a scale factor is a float32, {F32_TINY:.4g} to {F32_MAX:.4g} arcsec per count: {text!r}"
        )
    return value


MIN_PERIOD_S = 1e-6  #: rows are cut in whole microseconds of device time
MAX_PERIOD_S = 1e9  #: longer than any capture (31 years)


def period_s(text: str) -> float:
    """A row period in seconds, ``MIN_PERIOD_S`` to ``MAX_PERIOD_S``."""
    value = positive_float(text)
    if not MIN_PERIOD_S <= value <= MAX_PERIOD_S:
        raise argparse.ArgumentTypeError(
            f"a period must be {MIN_PERIOD_S:g} s (rows are cut in whole microseconds) to {MAX_PERIOD_S:g} s: {text!r}"
        )
    return value


def baud(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer baud rate: {text!r}") from None
    if not 50 <= value <= 12_000_000:
        raise argparse.ArgumentTypeError(f"baud rate out of range: {value}")
    return value


def rate_hz(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer rate: {text!r}") from None
    if not 1 <= value <= 0xFFFF:
        raise argparse.ArgumentTypeError(f"rate must be 1..65535 Hz (a u16 on the wire): {value}")
    return value


def seed(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer seed: {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"seed must be >= 0: {value}")
    return value


def time_window(text: str) -> tuple[float, float]:
    """``START:END`` in seconds, 0 <= START < END, both finite."""
    start, sep, end = text.partition(":")
    try:
        window = (float(start), float(end))
    except ValueError:
        window = None
    if not sep or window is None or not all(math.isfinite(x) for x in window) or not 0 <= window[0] < window[1]:
        raise argparse.ArgumentTypeError(f"expected START:END in seconds with 0 <= START < END: {text!r}")
    return window


def positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1: {text!r}")
    return value
