"""The frame formats fog_driver knows, by name, and a sniffer that tells them apart from a stream's bytes.

Every entry names a streaming decoder (``feed(bytes) -> events``, ``close()``, ``counters``).  Adding a
format is one module and one line in ``FORMATS``.  ``sniff`` is gpsd's idea: feed the first bytes to
every format's decoder and take the format whose checksums verify on the most frames; each decoder hunts
with a 1-byte resync, so garbage before the first frame (a port opened mid-frame) costs nothing.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from ..protocol import FrameDecoder
from .ixblue import StdbinDecoder
from .kvh import KvhDecoder

#: Bytes ``sniff`` looks at by default: at 1 kHz, about 2 s of protocol v1 or KVH, a few STDBIN telegrams.
SNIFF_BYTES = 64 * 1024
#: Fewer checksum-valid frames than this in the bytes looked at is no verdict (a 32-bit CRC passes by chance
#: once in 4e9 positions; two in a row by chance, never in practice).
MIN_FRAMES = 2


@dataclass(frozen=True)
class FrameFormat:
    """One entry of the registry: its name, what it is, and how to make its decoder."""

    name: str
    description: str
    #: ``make_decoder(**settings)``: a streaming decoder, set as the device was (``decoder_settings``' keys)
    make_decoder: Callable[..., Any]
    #: the decoder's counters -> how many checksum-valid frames it has found
    valid_frames: Callable[[Any], int]
    #: the format's temperature channels, in the order they fill a sample's three temperature places
    temperature_channels: tuple[str, ...] = ()
    #: the device settings its decoder takes (keys of a capture sidecar's ``wire_settings``)
    decoder_settings: tuple[str, ...] = ()

    def decoder(self, settings: Mapping[str, Any] | None = None) -> Any:
        """A decoder set as the device was: the keys of ``settings`` that this format's decoder takes (the others,
        such as the axis or the serial number, are not the decoder's); a key absent or None keeps its default."""
        settings = settings or {}
        return self.make_decoder(**{k: settings[k] for k in self.decoder_settings if settings.get(k) is not None})


def _fog_v1() -> Any:
    return FrameDecoder()


def _kvh(fmt: str) -> Callable[..., Any]:
    def make(**settings: Any) -> Any:
        return KvhDecoder(format=fmt, **settings)

    return make


def _ixblue(**settings: Any) -> Any:
    return StdbinDecoder(**settings)


_KVH_SETTINGS = ("rot_format", "rot_units", "temp_units", "rate_hz")


def _v1_frames(counters: Any) -> int:
    return int(counters.sample_frames + counters.identity_frames + counters.unknown_frames)


def _format_frames(counters: Any) -> int:
    return int(counters.sample_frames + counters.other_frames)


FORMATS: dict[str, FrameFormat] = {
    f.name: f
    for f in (
        FrameFormat(
            "fog-v1",
            "fog_driver's own protocol v1 (firmware_protocol/PROTOCOL.md)",
            _fog_v1,
            _v1_frames,
            ("top", "bottom", "housing"),
        ),
        FrameFormat(
            "kvh-a",
            "KVH (EMCORE) DSP-1750/1760/1775 normal mode, Format A",
            _kvh("a"),
            _format_frames,
            ("sensor",),
            _KVH_SETTINGS,
        ),
        FrameFormat(
            "kvh-b",
            "KVH (EMCORE) DSP-1750/1760/1775 normal mode, Format B",
            _kvh("b"),
            _format_frames,
            ("sensor",),
            _KVH_SETTINGS,
        ),
        FrameFormat(
            "kvh-c",
            "KVH (EMCORE) DSP-1750/1760/1775 normal mode, Format C",
            _kvh("c"),
            _format_frames,
            ("sensor",),
            _KVH_SETTINGS,
        ),
        FrameFormat(
            "ixblue-stdbin",
            "iXblue (Exail) STDBIN v2..v5 (Phins, Octans, ...)",
            _ixblue,
            _format_frames,
            ("fog", "accelerometer", "board"),
            ("rate_hz",),
        ),
    )
}


@dataclass(frozen=True)
class Sniffed:
    """What ``sniff`` saw: the format (None: no verdict), and the valid frames of every format."""

    name: str | None
    frames: dict[str, int]
    bytes_looked_at: int

    def describe(self) -> str:
        """One line for a person: ``kvh-a (57 valid frames in the first 2,052 bytes)``."""
        where = f"in the first {self.bytes_looked_at:,} bytes"
        if self.name is not None:
            return f"{self.name} ({self.frames[self.name]:,} valid frames {where})"
        seen = ", ".join(f"{name} {n:,}" for name, n in self.frames.items() if n)
        return f"no known format {where}" + (f" (valid frames: {seen}, too few to tell)" if seen else "")


def sniff(data: bytes | bytearray | memoryview, limit: int = SNIFF_BYTES) -> Sniffed:
    """The format of a stream from its first ``limit`` bytes: the one whose checksums verify on the most
    frames, at least ``MIN_FRAMES`` of them (or the only frame of a stream shorter than two frames)."""
    head = bytes(data[:limit])
    frames = {}
    for name, fmt in FORMATS.items():
        decoder = fmt.make_decoder()
        decoder.feed(head)
        frames[name] = fmt.valid_frames(decoder.counters)
    best = max(frames, key=lambda name: frames[name])
    count = frames[best]
    tied = sum(1 for n in frames.values() if n == count)
    enough = count >= MIN_FRAMES or (count == 1 and len(head) < limit)
    return Sniffed(best if enough and tied == 1 else None, frames, len(head))


def sniff_file(path: str, limit: int = SNIFF_BYTES) -> Sniffed:
    """``sniff`` of a file's first ``limit`` bytes (OSError when it cannot be read)."""
    with open(path, "rb") as f:
        return sniff(f.read(limit), limit)
