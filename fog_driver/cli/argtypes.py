"""The command line's argument types: each turns one option's text into its value, or says in one line why not
(``argparse.ArgumentTypeError``)."""

from __future__ import annotations

import argparse
import math


def positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be > 0: {text!r}")
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
