"""``inspect`` for a capture of another instrument's format: what its frames hold, axis by axis.

The summary a calibration engineer needs before trusting such a capture: how many frames decoded, what the
decoder threw away (bytes discarded, checksum errors, resyncs, sequence gaps), how long it lasts, each gyro
axis's mean rate and its spread, each temperature channel's range, and how many samples carried each flag.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..errors import InputFileError
from .common import AXES, ImuSample
from .registry import FORMATS

_BLOCK = 1 << 20


@dataclass
class _Channel:
    n: int = 0
    total: float = 0.0
    total_sq: float = 0.0
    low: float = math.inf
    high: float = -math.inf

    def add(self, value: float) -> None:
        if math.isnan(value):
            return
        self.n += 1
        self.total += value
        self.total_sq += value * value
        self.low = min(self.low, value)
        self.high = max(self.high, value)

    def mean(self) -> float:
        return self.total / self.n if self.n else math.nan

    def std(self) -> float:
        if self.n < 2:
            return math.nan
        return math.sqrt(max(0.0, (self.total_sq - self.total * self.total / self.n) / (self.n - 1)))


@dataclass
class FormatSummary:
    """What ``summarize_format`` found in a capture of format ``name``."""

    path: str
    name: str
    settings: dict[str, Any]
    counters: dict[str, int]
    samples: int = 0
    first_seq: int | None = None
    last_seq: int | None = None
    first_t_s: float | None = None
    last_t_s: float | None = None
    rate_dph: dict[str, _Channel] = field(default_factory=lambda: {a: _Channel() for a in AXES})
    temps_c: dict[str, _Channel] = field(default_factory=dict)
    flags: Counter[str] = field(default_factory=Counter)

    def add(self, sample: ImuSample) -> None:
        self.samples += 1
        if sample.seq is not None:
            self.first_seq = sample.seq if self.first_seq is None else self.first_seq
            self.last_seq = sample.seq
        if sample.t_s is not None:
            self.first_t_s = sample.t_s if self.first_t_s is None else self.first_t_s
            self.last_t_s = sample.t_s
        for axis, rate in zip(AXES, sample.rate_dph):
            self.rate_dph[axis].add(rate)
        for channel, value in sample.temps_c.items():
            self.temps_c.setdefault(channel, _Channel()).add(value)
        self.flags.update(sample.flags)

    def problems(self) -> list[str]:
        c = self.counters
        found = []
        for key, what in (
            ("crc_errors", "checksum errors"),
            ("bytes_discarded", "bytes discarded"),
            ("missing_frames", "frames missing (sequence gaps)"),
            ("truncated_frames", "frames cut off"),
        ):
            if c.get(key):
                found.append(f"{c[key]:,} {what}")
        for channel, ch in self.temps_c.items():  # PLAUSIBLE_TEMP_C: a thermometer's range
            if ch.n and (ch.low < -55.0 or ch.high > 125.0):
                found.append(
                    f"temperature {channel} reads {ch.low:.2f} .. {ch.high:.2f} degC, outside -55 .. 125 "
                    "(the device's temperature units? temp_units in wire_settings)"
                )
        return found

    def as_json_dict(self) -> dict[str, Any]:
        def channel(ch: _Channel) -> dict[str, Any]:
            finite = ch.n > 0
            return {
                "n": ch.n,
                "mean": ch.mean() if finite else None,
                "std": ch.std() if ch.n > 1 else None,
                "min": ch.low if finite else None,
                "max": ch.high if finite else None,
            }

        return {
            "path": self.path,
            "format": self.name,
            "settings": self.settings,
            "counters": self.counters,
            "samples": self.samples,
            "seq": [self.first_seq, self.last_seq],
            "t_s": [self.first_t_s, self.last_t_s],
            "rate_dph": {a: channel(ch) for a, ch in self.rate_dph.items()},
            "temps_c": {k: channel(ch) for k, ch in self.temps_c.items()},
            "flags": dict(self.flags),
            "problems": self.problems(),
        }


def summarize_format(path: str | Path, name: str, settings: dict[str, Any] | None = None) -> FormatSummary:
    """Decode a whole capture of format ``name`` and summarize it (an ``InputFileError`` when unreadable)."""
    decoder = FORMATS[name].decoder(settings)
    summary = FormatSummary(str(path), name, dict(settings or {}), {})
    try:
        with open(path, "rb") as f:
            for block in iter(lambda: f.read(_BLOCK), b""):
                for event in decoder.feed(block):
                    if isinstance(event, ImuSample):
                        summary.add(event)
    except OSError as exc:
        raise InputFileError(f"{path}: cannot read: {exc.strerror or exc}") from None
    for event in decoder.close():
        if isinstance(event, ImuSample):
            summary.add(event)
    summary.counters = decoder.counters.as_dict()
    return summary


def format_format_summary(s: FormatSummary, use: str = "") -> str:
    """The text ``inspect`` prints for another format's capture; ``use``, what the other commands do with it,
    ends the verdict."""
    c = s.counters
    settings = ", ".join(f"{k} {v}" for k, v in s.settings.items())
    lines = [
        f"capture       {s.path}",
        f"format        {s.name}: {FORMATS[s.name].description}",
        f"settings      {settings or 'the decoder defaults (no wire_settings in a sidecar)'}",
        f"frames        {c.get('sample_frames', 0):,} samples, {c.get('other_frames', 0):,} other; "
        f"{c.get('bytes_in_frames', 0):,} of {c.get('bytes_in', 0):,} bytes in frames",
        f"integrity     {c.get('crc_errors', 0):,} checksum errors, {c.get('bytes_discarded', 0):,} bytes discarded, "
        f"{c.get('resyncs', 0):,} resyncs, {c.get('truncated_frames', 0):,} cut off",
    ]
    if s.first_seq is not None:
        lines.append(
            f"sequence      {s.first_seq:,} .. {s.last_seq:,} (unwrapped); {c.get('seq_gaps', 0):,} gaps, "
            f"{c.get('missing_frames', 0):,} missing, {c.get('seq_repeats', 0):,} repeated"
        )
    if s.first_t_s is not None and s.last_t_s is not None:
        lines.append(f"device time   {s.first_t_s:.3f} .. {s.last_t_s:.3f} s ({s.last_t_s - s.first_t_s:,.1f} s)")
    for axis, ch in s.rate_dph.items():
        if ch.n:
            lines.append(
                f"{'rate ' + axis:13s} mean {ch.mean():.4f} deg/h, std {ch.std():.4f} deg/h over {ch.n:,} samples"
            )
    for channel, ch in s.temps_c.items():
        if ch.n:
            lines.append(f"{'temp ' + channel:13s} {ch.low:.2f} .. {ch.high:.2f} degC ({ch.n:,} readings)")
    if s.flags:
        lines.append("flags         " + ", ".join(f"{k} {v:,}" for k, v in sorted(s.flags.items())))
    problems = s.problems()
    lines.append(f"verdict       {'clean' if not problems else '; '.join(problems)}" + (f"; {use}" if use else ""))
    return "\n".join(lines)
