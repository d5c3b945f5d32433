"""Files in, files out: fitting a drift model to capture files (``fog-driver fit``).

``load_capture`` decodes a capture block by block and reduces it to the model rate
(``compensation.fitting.data.capture_data`` makes it the fit's data); ``run_program`` finds the chamber
program its run followed (its sidecar's ``program``, or ``fit --profile``) and judges it
(``compensation.fitting.program``); ``fit_model_file`` reads the captures and fits
(``compensation.fitting.fit.fit_model``).  Saving the model file is ``modelfiles``'.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from ..compensation.blocks import BlockAverager, BlockColumns
from ..compensation.fitting.data import CaptureData, FitConfig, capture_data
from ..compensation.fitting.fit import WeakFitError, check_kind, fit_model
from ..compensation.fitting.program import RunProgram
from ..compensation.fitting.report import FitReport
from ..compensation.model import ModelFile
from ..errors import InputFileError, UsageError
from ..lab.plan import (
    DESIGN,
    MIN_FAST_RATE_C_PER_MIN,
    WARMUP_FRACTION,
    WARMUP_MIN,
    ChamberLimits,
    design_program,
    identifiability_gaps,
)
from ..lab.profiles import load_profile, parse_profile
from ..lab.program import ChamberProfile, Hold, Ramp, Sinusoid
from ..samples.captures import find_sidecar, read_provenance, what_it_is
from ..samples.sources import CaptureReader, wire_settings_for

__all__ = [
    "FitConfig",
    "WeakFitError",
    "fit_model_file",
    "judge_program",
    "load_capture",
    "run_program",
]  # the fit at its edge


def load_capture(
    path: str | Path,
    config: FitConfig,
    progress: Callable[[int, int], None] | None = None,
    *,
    purpose: str = "to fit",
    warmup_setting: str = "warmup_s in the fit config, fit --config FILE",
    wire_format: str = "auto",
) -> CaptureData:
    """Decode a capture block by block and reduce it to the model rate; ``progress(bytes read, file size)``
    after every block read.  No static, valid block is an ``InputFileError`` saying why
    (``fitting.data.no_static_reason``; ``purpose`` and ``warmup_setting`` word it).  ``wire_format``: ``--format``
    (``sources.wire_settings_for``: auto reads the sidecar, else sniffs)."""
    path = Path(path)
    sha = hashlib.sha256()
    wire = wire_settings_for(path, wire_format)
    reader = CaptureReader(path, wire)
    n_channels = len(wire.temperature_channels)
    averager: BlockAverager | None = None
    parts = []
    on_block: Callable[[bytes], None] = sha.update
    if progress is not None:
        size = path.stat().st_size if path.is_file() else 0
        done = [0]

        def on_block(block: bytes) -> None:
            sha.update(block)
            done[0] += len(block)
            progress(done[0], size)

    for part in reader.parts(on_block=on_block):
        samples = part.samples
        if averager is None:
            if reader.identity is None:
                if not len(samples):
                    continue
                raise InputFileError(f"{path}: no IDENTITY frame before the first sample: frame rate unknown")
            averager = BlockAverager(1.0 / reader.identity.rate_hz, config.model_rate_hz, n_channels)
        parts.append(averager.run(samples))
    if averager is None:
        raise InputFileError(f"{path}: no SAMPLE frames to fit{what_it_is(path)}")
    parts.append(BlockColumns.from_blocks(averager.flush()))
    blocks = BlockColumns(*(np.concatenate([getattr(p, f) for p in parts]) for f in BlockColumns.__dataclass_fields__))
    identity = reader.identity
    return capture_data(
        path,
        sha.hexdigest(),
        identity.serial if identity else None,
        averager.frame_period_s,
        blocks,
        config,
        wire.temperature_channels,
        wire.format,
        purpose=purpose,
        warmup_setting=warmup_setting,
    )


#: The sidecar key of the chamber program a run followed: a profile file's document (``lab.profiles``).
PROGRAM_KEY = "program"


def run_program(path: str | Path, held_s: float, profile: str | None = None) -> RunProgram | None:
    """The chamber program the run in capture ``path`` followed, judged over the ``held_s`` seconds of it the
    capture holds; None when it is not known.

    The program is the sidecar's ``program`` (a profile file's document: what ``simulate`` ran), else
    ``profile`` (``fit --profile``: a built-in profile's name or a profile file, as ``simulate --profile``
    takes).  Both, and different, is a ``UsageError``; a ``program`` that is no profile an ``InputFileError``.
    Judged (``judge_program``): ``lab.plan.identifiability_gaps`` of its first ``held_s`` seconds, whether it
    is ``fog-driver plan``'s own program for its limits (``_planned``), and a fastest ramp half its own for a
    program with slower ramps, when that is still fast enough for the rate terms (``MIN_FAST_RATE_C_PER_MIN``)."""
    path = Path(path)
    recorded = (read_provenance(path) or {}).get(PROGRAM_KEY)
    chamber, source = None, ""
    if recorded is not None:
        sidecar = find_sidecar(path)
        chamber = parse_profile(recorded, f"{sidecar}: {PROGRAM_KEY}").chamber
        source = f"{path.name}'s sidecar"
    if profile is not None:
        given = load_profile(profile).chamber
        if chamber is not None and not _same_program(chamber, given):
            raise UsageError(
                f"{path}: its sidecar records the program it ran ({chamber.name}, {chamber.duration_s / 60:g} min), "
                f"not --profile {profile}: give --profile only for captures whose sidecar records none"
            )
        if chamber is None:
            chamber, source = given, f"--profile {profile}"
    return None if chamber is None else judge_program(chamber, held_s, source)


def judge_program(chamber: ChamberProfile, held_s: float, source: str) -> RunProgram:
    """``chamber`` judged over its first ``held_s`` seconds (``run_program``); ``source``: where it was learned."""
    part = chamber.until(held_s)
    fastest = max((s.segment.rate_c_per_min for s in part.spans() if isinstance(s.segment, Ramp)), default=0.0)
    judged = RunProgram(
        name=chamber.name,
        source=source,
        held_min=part.duration_s / 60.0,
        program_min=chamber.duration_s / 60.0,
        gaps=identifiability_gaps(part),
        slower_max_rate_c_per_min=fastest / 2.0 if fastest / 2.0 >= MIN_FAST_RATE_C_PER_MIN else None,
    )
    return judged if judged.cut else dataclasses.replace(judged, planned=_planned(chamber))


def _same_program(a: ChamberProfile, b: ChamberProfile) -> bool:
    """Whether two chamber programs are the same (their start and segments, to rounding; not their names)."""
    if len(a.segments) != len(b.segments) or not math.isclose(a.start_c, b.start_c, abs_tol=1e-9):
        return False
    for x, y in zip(a.segments, b.segments):
        if type(x) is not type(y):
            return False
        if not all(math.isclose(u, v, rel_tol=1e-9, abs_tol=1e-9) for u, v in zip(vars(x).values(), vars(y).values())):
            return False
    return True


def _planned(chamber: ChamberProfile) -> bool:
    """Whether ``chamber`` is the program ``fog-driver plan`` writes for its own limits: its extremes, its
    fastest ramp and its length (``lab.plan.design_program``); only a program that starts as plan's do, with
    its warm-up hold (``WARMUP_MIN``, at most ``WARMUP_FRACTION`` of the run), is designed again to compare."""
    minutes = chamber.duration_s / 60.0
    first = chamber.segments[0] if chamber.segments else None
    warmup_s = 60.0 * min(WARMUP_MIN, WARMUP_FRACTION * minutes)
    if not isinstance(first, Hold) or not math.isclose(first.duration_s, warmup_s, rel_tol=1e-9):
        return False
    spans = chamber.spans()
    temps = [t for s in spans for t in (s.start_c, s.end_c)]
    temps += [s.start_c + k * s.segment.amplitude_c for s in spans if isinstance(s.segment, Sinusoid) for k in (-1, 1)]
    rates = [s.segment.rate_c_per_min for s in spans if isinstance(s.segment, Ramp)]
    try:
        limits = ChamberLimits(
            min(temps, default=0.0), max(temps, default=0.0), max(rates, default=0.0), chamber.duration_s / 60.0
        )
    except ValueError:  # limits no chamber has (no ramp, no span): no program plan writes
        return False
    return _same_program(chamber, design_program(limits, DESIGN).chamber)


def fit_model_file(
    paths: Sequence[str | Path],
    *,
    kind: str,
    config: FitConfig,
    validate_paths: Sequence[str | Path] = (),
    fall_back: bool = False,
    accept_weak: bool = False,
    progress: Callable[[str], None] | None = None,
    wire_format: str = "auto",
    profiles: Sequence[str] = (),
) -> tuple[ModelFile, FitReport]:
    """Fit ``kind`` (and the polynomial baseline beside it) to capture files; return the model file and the
    report (``compensation.fitting.fit.fit_model``: the comparisons, the checks, ``WeakFitError``).

    ``progress(text)`` hears every phase and how far it is ("decoding paper.bin 40 %", then the fit's).
    ``wire_format``: ``--format`` (the captures' frame format; auto: each capture's sidecar, else sniffed);
    every capture must have the same temperature channels, which the model file records.  ``profiles``:
    ``fit --profile``, the chamber program the fit captures ran (``run_program``): none, one for every
    capture, or one per capture in order."""
    check_kind(kind)
    if len(profiles) > 1 and len(profiles) != len(paths):
        raise UsageError(
            f"--profile given {len(profiles)} times for {len(paths)} fit captures: give it once (every capture ran "
            f"that program) or once per capture, in order"
        )
    say = progress or (lambda text: None)

    def decoding(p: str | Path) -> Callable[[int, int], None] | None:
        name = Path(p).name
        return (
            None if progress is None else lambda done, total: say(f"decoding {name} {100 * done / max(total, 1):.0f} %")
        )

    for profile in dict.fromkeys(profiles):  # a profile that is not one: refused before any capture is decoded
        load_profile(profile)
    captures = [load_capture(p, config, decoding(p), wire_format=wire_format) for p in paths]
    given = list(profiles) * len(paths) if len(profiles) == 1 else list(profiles) or [None] * len(paths)
    for capture, profile in zip(captures, given):
        capture.program = run_program(capture.path, len(capture.blocks) / config.model_rate_hz, profile)
    validate = [load_capture(p, config, decoding(p), wire_format=wire_format) for p in validate_paths]
    return fit_model(
        captures, validate, kind=kind, config=config, fall_back=fall_back, accept_weak=accept_weak, progress=progress
    )
