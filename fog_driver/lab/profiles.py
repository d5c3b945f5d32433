"""Chamber temperature profiles and turntable motion plans: what one chamber run does to the instrument.

A ``SimProfile`` is the chamber's air temperature over time (``ChamberProfile.air_temp_c(t_s)``) and
the turntable's rotation about the instrument's sensitive axis (``MotionPlan.rate_dps(t_s)``,
``MotionPlan.angle_deg(t_s)``).  Both are exact closed forms, vectorized over numpy arrays with one
``np.searchsorted`` over the segment boundaries (the simulator evaluates millions of frame times at
once).  Times are seconds from the start of the run.  The chamber program is in ``fog_driver.lab.program``, the
motion plan in ``fog_driver.lab.motion``; this module holds the whole profile, the built-in ones and the profile
files.

Built-in profiles (``load_profile("paper")``, ``load_profile("paper-validation")``, ``load_profile("calibration")``):

- ``paper``: the paper's 440-minute chamber experiment.  20 degC, 30 min warm-up; +1 degC/min to
  25, 30, ..., 55 degC with 15 min at each; back to 20 degC at 2 degC/min (the paper only says
  "quickly"; 2 degC/min is a realistic chamber cooling rate) and 12.5 min at 20 degC, which makes
  the total exactly 440 min; then -1 degC/min to 15, 10, ..., -40 degC with 15 min at each.
  Static table.  ``configs/profiles/paper.yaml`` is the same profile in the file format.
- ``paper-validation``: the paper's validation experiment.  20 degC, 30 min warm-up; down to -40 degC
  at 1 degC/min, then up through -30, -20, -10, 0, 10, 20, 25, 30, 40, 55 degC at 1 degC/min (one
  cool-down, then always warming, so the chamber never overshoots back and forth); 75 min at each
  temperature: 60 min to settle, then the 10 x 36 deg positioning sequence (697.9 s), and 202 s of
  margin before the next ramp.  1010 min in total.
- ``calibration``: the program ``fog-driver plan`` writes with its default options (the paper's -40..55 degC
  and 440 min, ramps up to 3 degC/min; ``fog_driver.lab.plan``), from which the drift model's time scales
  can be identified in one run.  Static table.  ``configs/profiles/calibration.yaml`` is the same profile.

YAML profile files (read with ``yaml.safe_load``; unknown keys are errors; indices in messages and
``at_plateau`` count from 0, as ``plateaus()`` does)::

    name: fast-ramps                  # optional, default the file's stem
    start_c: 20
    segments:
      - hold: {duration_min: 10}      # or duration_s, exactly one
      - ramp: {rate_c_per_min: 2.0, target_c: 40}
      - step: {target_c: 30}
      - sinusoid: {amplitude_c: 5, period_min: 30, duration_min: 60}
    motion:                           # optional, default static; a mapping or a list of them
      kind: positioning               # static | constant_rate | positioning | creep
      at_plateau: 1                   # or start_s; settle_s (default 600) after the plateau starts
      moves: 10                       # step_deg 36, dwell_s 60, max_rate_dps 20, accel_dps2 10
      step_deg: [36, -72, 10]         # or a list of steps, taken in turn (both signs, several sizes)
    # a creep (rate_dph, start_s, stop_s: all required) is an item of the list that may overlap the others:
    #   - {kind: creep, rate_dph: 0.2, start_s: 3600, stop_s: 7200}
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from ..errors import InputFileError
from ..files.typed_mapping import unknown_key
from ..files.yamlio import MAX_YAML_BYTES, read_yaml
from .checks import check_number
from .motion import ConstantRate, Creep, MotionItem, MotionPlan, Positioning, positioning_at_plateau
from .plan import design_program
from .program import KIND_OF, SEGMENT_KINDS, ChamberProfile, Hold, Ramp, Segment, Sinusoid, Step

__all__ = [
    "BUILTIN_PROFILES",
    "MAX_PROFILE_BYTES",
    "MAX_PROFILE_S",
    "MAX_SEGMENTS",
    "SimProfile",
    "calibration_profile",
    "dump_profile",
    "load_profile",
    "paper_profile",
    "paper_validation_profile",
    "parse_profile",
    "profile_to_doc",
]

MAX_PROFILE_BYTES = MAX_YAML_BYTES
MAX_SEGMENTS = 10_000
#: A run longer than this (the chamber program or the motion) is refused: 31 days of frames would fill a disk
#: long before, and a typo (a hold of 1e300 s) must not start a run that never ends.
MAX_PROFILE_S = 31 * 86400.0


# --- the whole profile -------------------------------------------------------------------------


@dataclass(frozen=True)
class SimProfile:
    """A chamber run: the air temperature program, the turntable motion, and where it came from."""

    name: str
    chamber: ChamberProfile
    motion: MotionPlan
    source: str

    @property
    def duration_s(self) -> float:
        """The longer of the chamber program and the motion plan."""
        return max(self.chamber.duration_s, self.motion.duration_s)


def _paper_chamber() -> ChamberProfile:
    segs: list[Segment] = [Hold(30 * 60.0)]
    for temp_c in range(25, 56, 5):
        segs += [Ramp(1.0, temp_c), Hold(15 * 60.0)]
    segs += [Ramp(2.0, 20.0), Hold(12.5 * 60.0)]  # "quickly" back to 20 degC: 17.5 + 12.5 = 30 min
    for temp_c in range(15, -41, -5):
        segs += [Ramp(1.0, temp_c), Hold(15 * 60.0)]
    return ChamberProfile("paper", 20.0, tuple(segs))


PAPER_VALIDATION_TEMPS_C = (-40, -30, -20, -10, 0, 10, 20, 25, 30, 40, 55)
VALIDATION_SETTLE_S = 3600.0
VALIDATION_HOLD_S = 75 * 60.0


def paper_profile() -> SimProfile:
    """The paper's 440-minute chamber experiment, static table (see the module docstring)."""
    return SimProfile("paper", _paper_chamber(), MotionPlan.static(), "built-in")


def paper_validation_profile() -> SimProfile:
    """The paper's validation run: 11 temperatures, 60 min settle + 10 x 36 deg positioning at each."""
    segs: list[Segment] = [Hold(30 * 60.0)]
    for temp_c in PAPER_VALIDATION_TEMPS_C:
        segs += [Ramp(1.0, temp_c), Hold(VALIDATION_HOLD_S)]
    chamber = ChamberProfile("paper-validation", 20.0, tuple(segs))
    motion = MotionPlan(
        tuple(
            positioning_at_plateau(chamber, k, VALIDATION_SETTLE_S) for k in range(1, len(PAPER_VALIDATION_TEMPS_C) + 1)
        )
    )
    return SimProfile("paper-validation", chamber, motion, "built-in")


def calibration_profile() -> SimProfile:
    """The default calibration program: ``fog-driver plan`` with its default options (``fog_driver.lab.plan``)."""
    return SimProfile("calibration", design_program().chamber, MotionPlan.static(), "built-in")


BUILTIN_PROFILES = {
    "paper": paper_profile,
    "paper-validation": paper_validation_profile,
    "calibration": calibration_profile,
}


# --- YAML ----------------------------------------------------------------------------------------

_SEGMENT_KEYS = {
    "hold": ({"duration_min", "duration_s"}, set()),
    "ramp": ({"rate_c_per_min", "target_c"}, {"rate_c_per_min", "target_c"}),
    "step": ({"target_c"}, {"target_c"}),
    "sinusoid": ({"amplitude_c", "period_min", "period_s", "duration_min", "duration_s"}, {"amplitude_c"}),
}
_MOTION_KEYS = {
    "static": (set(), set()),
    "constant_rate": ({"rate_dps", "start_s", "stop_s"}, {"rate_dps"}),
    "creep": ({"rate_dph", "start_s", "stop_s"}, {"rate_dph", "start_s", "stop_s"}),
    "positioning": (
        {"start_s", "at_plateau", "settle_s", "moves", "step_deg", "dwell_s", "max_rate_dps", "accel_dps2"},
        set(),
    ),
}


class _Bad(Exception):
    """A problem at a place in the document; becomes ``InputFileError(f"{file}: {where}: {message}")``."""


def _at(where: str) -> str:
    return f"{where}: " if where else ""


def _check_keys(doc: Any, where: str, known: set[str], required: set[str]) -> dict:
    if not isinstance(doc, dict):
        got = "nothing" if doc is None else f"a {type(doc).__name__}"
        raise _Bad(f"{_at(where)}expected a mapping" + ("" if where else " with start_c and segments") + f", got {got}")
    for key in doc:
        if key not in known:
            raise _Bad(f"{_at(where)}{unknown_key(key, known)}")
    for key in sorted(required):
        if key not in doc:
            raise _Bad(f"{_at(where)}missing {key}")
    return doc


def _field(where: str, name: str, value: Any, **checks: bool) -> float:
    try:
        return check_number(name, value, **checks)
    except ValueError as exc:
        raise _Bad(f"{_at(where)}{exc}") from None


def _seconds(doc: dict, where: str, stem: str) -> float:
    given = [k for k in (f"{stem}_min", f"{stem}_s") if k in doc]
    if len(given) != 1:
        raise _Bad(f"{where}: give exactly one of {stem}_min and {stem}_s" + (", not both" if given else ""))
    key = given[0]
    value = _field(where, key, doc[key], positive=True)
    return value * 60.0 if key.endswith("_min") else value


def _parse_segment(item: Any, where: str) -> Segment:
    if not isinstance(item, dict) or len(item) != 1:
        raise _Bad(f"{where}: expected a one-key mapping like {{hold: {{duration_min: 10}}}}")
    ((kind, body),) = item.items()
    if kind not in SEGMENT_KINDS:
        raise _Bad(f"{where}: unknown segment kind {kind!r} (known: {', '.join(SEGMENT_KINDS)})")
    where = f"{where} ({kind})"
    known, required = _SEGMENT_KEYS[kind]
    body = _check_keys(body, where, known, required)
    if kind == "hold":
        return Hold(_seconds(body, where, "duration"))
    if kind == "ramp":
        return Ramp(
            _field(where, "rate_c_per_min", body["rate_c_per_min"], positive=True),
            _field(where, "target_c", body["target_c"]),
        )
    if kind == "step":
        return Step(_field(where, "target_c", body["target_c"]))
    return Sinusoid(
        _field(where, "amplitude_c", body["amplitude_c"], nonnegative=True),
        _seconds(body, where, "period"),
        _seconds(body, where, "duration"),
    )


def _parse_motion_item(doc: Any, where: str, chamber: ChamberProfile) -> MotionItem | None:
    if not isinstance(doc, dict):
        raise _Bad(f"{where}: expected a mapping with a kind (static, constant_rate, positioning, creep)")
    if "kind" not in doc:
        raise _Bad(f"{where}: missing kind (static, constant_rate, positioning, creep)")
    kind = doc["kind"]
    if kind not in _MOTION_KEYS:
        raise _Bad(f"{where}: unknown motion kind {kind!r} (known: {', '.join(_MOTION_KEYS)})")
    where = f"{where} ({kind})"
    known, required = _MOTION_KEYS[kind]
    body = {k: v for k, v in _check_keys(doc, where, known | {"kind"}, required).items() if k != "kind"}
    try:
        if kind == "static":
            return None
        if kind == "constant_rate":
            return ConstantRate(**body)
        if kind == "creep":
            return Creep(**body)
        if ("start_s" in body) == ("at_plateau" in body):
            raise _Bad(f"{where}: give exactly one of start_s and at_plateau")
        if "start_s" in body:
            if "settle_s" in body:
                raise _Bad(f"{where}: settle_s goes with at_plateau, not with start_s")
            return Positioning(**body)
        return positioning_at_plateau(chamber, body.pop("at_plateau"), body.pop("settle_s", 600.0), **body)
    except ValueError as exc:
        raise _Bad(f"{where}: {exc}") from None


def parse_profile(doc: Any, where: str = "profile", default_name: str = "profile") -> SimProfile:
    """Validate a parsed YAML document into a ``SimProfile``; every problem is a one-line ``InputFileError``."""
    try:
        doc = _check_keys(doc, "", {"name", "start_c", "segments", "motion"}, {"start_c", "segments"})
        name = doc.get("name", default_name)
        if not isinstance(name, str) or not name.strip() or "\n" in name:
            raise _Bad(f"name must be a one-line string, got {name!r}")
        start_c = _field("", "start_c", doc["start_c"])
        items = doc["segments"]
        if not isinstance(items, list) or not items:
            raise _Bad("segments must be a non-empty list")
        if len(items) > MAX_SEGMENTS:
            raise _Bad(f"segments: {len(items)} segments, more than the limit of {MAX_SEGMENTS}")
        segments = tuple(_parse_segment(item, f"segments[{i}]") for i, item in enumerate(items))
        chamber = ChamberProfile(name, start_c, segments)
        motion_doc = doc.get("motion")
        if motion_doc is None:
            motion = MotionPlan.static()
        else:
            entries = motion_doc if isinstance(motion_doc, list) else [motion_doc]
            wheres = [f"motion[{i}]" for i in range(len(entries))] if isinstance(motion_doc, list) else ["motion"]
            parsed = [_parse_motion_item(e, w, chamber) for e, w in zip(entries, wheres)]
            try:
                motion = MotionPlan(tuple(p for p in parsed if p is not None))
            except ValueError as exc:
                raise _Bad(f"motion: {exc}") from None
        for part, seconds in (("the chamber program", chamber.duration_s), ("the motion", motion.duration_s)):
            if seconds > MAX_PROFILE_S:
                raise _Bad(
                    f"{part} lasts {seconds / 86400:.3g} days, more than the limit of {MAX_PROFILE_S / 86400:g} days"
                )
    except _Bad as exc:
        raise InputFileError(f"{where}: {exc}") from None
    return SimProfile(name, chamber, motion, where)


PROFILE_FOLDER = Path("configs") / "profiles"


def profile_folders() -> list[Path]:
    """Where profile names are looked up, in order: ``configs/profiles/`` in the current directory, then
    in the source tree this package runs from (a clone's editable install; absent from a wheel's)."""
    candidates = [Path.cwd() / PROFILE_FOLDER, Path(__file__).resolve().parents[2] / PROFILE_FOLDER]
    folders: list[Path] = []
    for folder in candidates:
        if folder.is_dir() and all(folder.resolve() != f.resolve() for f in folders):
            folders.append(folder)
    return folders


def profile_names() -> list[str]:
    """Every name ``load_profile`` accepts: the built-in profiles, then the profile files' stems."""
    names = list(BUILTIN_PROFILES)
    for folder in profile_folders():
        names += [f.stem for f in sorted(folder.glob("*.yaml")) if f.stem not in names]
    return names


def load_profile(name_or_path: str | Path) -> SimProfile:
    """A profile by name or a YAML profile file, validated.

    A name is a built-in profile (``paper``, ``paper-validation``, ``calibration``) or the stem of a file in
    ``configs/profiles/`` (see :func:`profile_folders`): ``fast-ramps`` is ``configs/profiles/fast-ramps.yaml``.
    Anything with a ``/`` or a ``.yaml`` suffix is a path.
    """
    if isinstance(name_or_path, str) and name_or_path in BUILTIN_PROFILES:
        return BUILTIN_PROFILES[name_or_path]()
    path = Path(name_or_path)
    if (
        isinstance(name_or_path, str)
        and "/" not in name_or_path
        and path.suffix not in (".yaml", ".yml")
        and not path.is_file()
    ):
        for folder in profile_folders():
            if (folder / f"{name_or_path}.yaml").is_file():
                path = folder / f"{name_or_path}.yaml"
                break
        else:
            raise InputFileError(
                f"{name_or_path}: no such profile (profiles: {', '.join(profile_names())}; "
                "or give the path of a profile YAML file)"
            )
    doc = read_yaml(path, "profile file", hint=f" (profiles: {', '.join(profile_names())})")
    return parse_profile(doc, str(path), default_name=path.stem)


def _plain(x: float) -> float | int:
    return int(x) if float(x).is_integer() and abs(x) < 2**53 else float(x)


def _time_entry(stem: str, seconds: float) -> dict[str, float | int]:
    minutes = seconds / 60.0
    return {f"{stem}_min": _plain(minutes)} if minutes * 60.0 == seconds else {f"{stem}_s": _plain(seconds)}


def profile_to_doc(profile: SimProfile) -> dict[str, Any]:
    """The YAML document for ``profile`` (``parse_profile`` of it gives an equal chamber and motion)."""
    segments: list[dict[str, Any]] = []
    for seg in profile.chamber.segments:
        if isinstance(seg, Hold):
            body: dict[str, Any] = _time_entry("duration", seg.duration_s)
        elif isinstance(seg, Ramp):
            body = {"rate_c_per_min": _plain(seg.rate_c_per_min), "target_c": _plain(seg.target_c)}
        elif isinstance(seg, Step):
            body = {"target_c": _plain(seg.target_c)}
        else:
            body = {
                "amplitude_c": _plain(seg.amplitude_c),
                **_time_entry("period", seg.period_s),
                **_time_entry("duration", seg.duration_s),
            }
        segments.append({KIND_OF[type(seg)]: body})
    doc: dict[str, Any] = {"name": profile.name, "start_c": _plain(profile.chamber.start_c), "segments": segments}
    items = []
    for item in profile.motion.items:
        if isinstance(item, Creep):
            entry: dict[str, Any] = {
                "kind": "creep",
                "rate_dph": _plain(item.rate_dph),
                "start_s": _plain(item.start_s),
                "stop_s": _plain(item.stop_s),
            }
        elif isinstance(item, ConstantRate):
            entry = {
                "kind": "constant_rate",
                "rate_dps": _plain(item.rate_dps),
                "start_s": _plain(item.start_s),
            }
            if item.stop_s is not None:
                entry["stop_s"] = _plain(item.stop_s)
        else:
            entry = {
                "kind": "positioning",
                "start_s": _plain(item.start_s),
                "moves": item.moves,
                "step_deg": [_plain(v) for v in item.step_deg]
                if isinstance(item.step_deg, tuple)
                else _plain(item.step_deg),
                "dwell_s": _plain(item.dwell_s),
                "max_rate_dps": _plain(item.max_rate_dps),
                "accel_dps2": _plain(item.accel_dps2),
            }
        items.append(entry)
    if items:
        doc["motion"] = items[0] if len(items) == 1 else items
    return doc


def dump_profile(profile: SimProfile) -> str:
    """``profile`` as YAML text in the profile-file format (positioning sequences with their resolved ``start_s``)."""
    return yaml.safe_dump(profile_to_doc(profile), sort_keys=False, default_flow_style=None)
