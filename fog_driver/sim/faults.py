"""Fault injection for simulated instruments and links.

A fault spec is a comma-separated list of ``name=value`` items, e.g.::

    drop=1e-3,flip=1e-5,garbage=0.2,thermo=0.05:2,disconnect=120:3+300:0.5

| item | meaning |
|---|---|
| ``drop=P`` | each SAMPLE frame is lost on the link with probability P (a seq gap) |
| ``flip=P`` | each byte on the link has one bit flipped with probability P (a CRC error) |
| ``garbage=R`` | R bursts per second of 1-64 random bytes (sync bytes included) between frames |
| ``thermo=R[:S]`` | R thermometer faults per second, each one sensor reading -32768 for S seconds (default 1) with status bit 2 |
| ``disconnect=T:S[+T:S...]`` | the link is cut at device time T s for S s: bytes in between are lost, mid-frame |

``none`` or an empty string means no faults.  Faults draw on their own random
stream, so the same seed gives the same faults, and adding faults never
changes the instrument's physics.
"""  # noqa: E501 - a Markdown table row cannot be wrapped

from __future__ import annotations

from dataclasses import dataclass, field

from ..errors import UsageError
from ..lab.profiles import MAX_PROFILE_S

#: The longest a thermometer fault may last: no simulated run lasts longer.
MAX_THERMO_FAULT_S = MAX_PROFILE_S


@dataclass(frozen=True)
class FaultSpec:
    drop_prob: float = 0.0
    flip_prob_per_byte: float = 0.0
    garbage_bursts_per_s: float = 0.0
    thermo_faults_per_s: float = 0.0
    thermo_fault_s: float = 1.0
    disconnects: tuple[tuple[float, float], ...] = field(default_factory=tuple)  #: (start s, duration s), device time

    @property
    def any(self) -> bool:
        return bool(
            self.drop_prob
            or self.flip_prob_per_byte
            or self.garbage_bursts_per_s
            or self.thermo_faults_per_s
            or self.disconnects
        )

    def describe(self) -> str:
        """The spec in its own syntax (for provenance)."""
        items = []
        if self.drop_prob:
            items.append(f"drop={self.drop_prob:g}")
        if self.flip_prob_per_byte:
            items.append(f"flip={self.flip_prob_per_byte:g}")
        if self.garbage_bursts_per_s:
            items.append(f"garbage={self.garbage_bursts_per_s:g}")
        if self.thermo_faults_per_s:
            items.append(f"thermo={self.thermo_faults_per_s:g}:{self.thermo_fault_s:g}")
        if self.disconnects:
            items.append("disconnect=" + "+".join(f"{t:g}:{d:g}" for t, d in self.disconnects))
        return ",".join(items) or "none"


def _number(text: str, item: str, *, probability: bool = False) -> float:
    try:
        value = float(text)
    except ValueError:
        raise UsageError(f"fault spec item {item!r}: {text!r} is not a number") from None
    if not (value >= 0 and value == value and value != float("inf")):
        raise UsageError(f"fault spec item {item!r}: {text!r} must be a finite number >= 0")
    if probability and value > 1:
        raise UsageError(f"fault spec item {item!r}: a probability must be <= 1, got {text}")
    return value


def parse_fault_spec(text: str | None) -> FaultSpec:
    """Parse ``drop=...,flip=...`` (see the module docstring); a bad spec is a one-line ``UsageError``."""
    if text is None or text.strip() in ("", "none"):
        return FaultSpec()
    if len(text) > 4096:
        raise UsageError("fault spec longer than 4096 characters")
    values: dict = {}
    for item in text.split(","):
        item = item.strip()
        name, sep, value = item.partition("=")
        if not sep or not value:
            raise UsageError(f"fault spec item {item!r}: expected name=value (drop, flip, garbage, thermo, disconnect)")
        if name in values:
            raise UsageError(f"fault spec item {name!r} given twice")
        if name == "drop":
            values[name] = {"drop_prob": _number(value, item, probability=True)}
        elif name == "flip":
            values[name] = {"flip_prob_per_byte": _number(value, item, probability=True)}
        elif name == "garbage":
            values[name] = {"garbage_bursts_per_s": _number(value, item)}
        elif name == "thermo":
            rate, _, seconds = value.partition(":")
            entry = {"thermo_faults_per_s": _number(rate, item)}
            if seconds:
                entry["thermo_fault_s"] = _number(seconds, item)
                if not 0 < entry["thermo_fault_s"] <= MAX_THERMO_FAULT_S:
                    raise UsageError(
                        f"fault spec item {item!r}: a fault lasts > 0 s and at most {MAX_THERMO_FAULT_S / 86400:g} days"
                    )
            values[name] = entry
        elif name == "disconnect":
            cuts = []
            for cut in value.split("+"):
                start, colon, duration = cut.partition(":")
                if not colon:
                    raise UsageError(f"fault spec item {item!r}: expected disconnect=START_S:DURATION_S[+...]")
                cuts.append((_number(start, item), _number(duration, item)))
            cuts.sort()
            for (t0, d0), (t1, _) in zip(cuts, cuts[1:]):
                if t0 + d0 > t1:
                    raise UsageError(f"fault spec item {item!r}: disconnects overlap")
            values[name] = {"disconnects": tuple(cuts)}
        else:
            raise UsageError(
                f"fault spec item {item!r}: unknown fault {name!r} (drop, flip, garbage, thermo, disconnect)"
            )
    merged: dict = {}
    for entry in values.values():
        merged.update(entry)
    return FaultSpec(**merged)
