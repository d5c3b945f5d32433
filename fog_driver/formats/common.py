"""What every format's decoder produces: samples of up to three axes, and counters kept the same way.

A format decoder turns bytes into ``ImuSample`` events (and format-specific events such as a built-in-test
reply); the sample stream later reduces an ``ImuSample`` to the instrument's one angle axis.  Units ride in
the names: angle increments in arcsec, rates in deg/h (1 arcsec/s is exactly 1 deg/h), temperatures in degC.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

from ..protocol.sequence import Unwrapper, count_seq_step

AXES = ("x", "y", "z")


@dataclass(frozen=True)
class ImuSample:
    """One sample of a format's stream, in common units.

    ``seq`` is the format's sequence counter unwrapped (monotonic across wraps; None where the format has
    none).  ``t_s`` is device time in s when the format carries it, else None and ``host_time`` True (the
    stream then times samples by their arrival).  ``dtheta_arcsec`` is the angle increment over the sample
    per axis (x, y, z; NaN for an axis the device does not send): from a delta-angle output directly, or
    ``rate x period`` for a rate output (``from_rate`` True).  ``rate_dph`` is the mean rate over the sample
    (``dtheta_arcsec / period_s``, or the rate as sent).  ``temps_c`` maps the format's named temperature
    channels to degC (NaN: invalid this sample).  ``flags`` holds common flags (``SAMPLE_FLAGS``) that apply;
    ``status`` the raw status bits as sent, kept, not interpreted further.
    """

    seq: int | None
    t_s: float | None
    dtheta_arcsec: tuple[float, float, float]
    rate_dph: tuple[float, float, float]
    temps_c: dict[str, float]
    flags: frozenset[str] = frozenset()
    status: int = 0
    from_rate: bool = False
    host_time: bool = False
    extra: dict[str, float] = field(default_factory=dict)  #: e.g. accelerations (m/s^2), heading/roll/pitch (deg)
    offset: int = 0  #: byte offset of the frame in the stream the decoder was fed


@dataclass
class FormatCounters:
    """Counters every format keeps, named as protocol v1's (a format may add its own in a subclass).

    Byte accounting holds at every moment: ``bytes_in == bytes_in_frames + bytes_discarded + pending``.
    """

    bytes_in: int = 0  #: bytes fed
    bytes_in_frames: int = 0  #: bytes inside checksum-valid frames (any kind)
    bytes_discarded: int = 0  #: bytes dropped while hunting for a header
    sample_frames: int = 0  #: frames that gave an ``ImuSample``
    other_frames: int = 0  #: checksum-valid frames of another kind (a built-in-test reply, a block skipped)
    crc_errors: int = 0  #: header positions whose complete frame failed the checksum
    length_errors: int = 0  #: header positions whose length field cannot be right
    truncated_frames: int = 0  #: header positions cut off by the end of the stream
    resyncs: int = 0  #: valid frames preceded by discarded bytes
    seq_gaps: int = 0  #: samples whose sequence is not the previous + 1
    missing_frames: int = 0  #: samples the gaps skipped over
    seq_repeats: int = 0  #: samples repeating the previous sequence number

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


class SeqUnwrapper:
    """Unwraps a counter that wraps at ``modulus`` (``protocol.sequence.Unwrapper``) and counts gaps and
    repeats into ``counters``."""

    def __init__(self, modulus: int, counters: FormatCounters) -> None:
        self.counters = counters
        self.unwrapper = Unwrapper(modulus)

    def step(self, raw: int) -> int:
        """The unwrapped sequence of the next frame whose counter reads ``raw``: ``(raw - previous) mod m``
        is 1 normally, 0 for a repeat, k > 1 when k - 1 frames are missing."""
        u = self.unwrapper
        d = u.step(raw)
        if d != 1:  # (tested here: the call only on a gap, a repeat or the first frame)
            count_seq_step(self.counters, d)
        return u.value
