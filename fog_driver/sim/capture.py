"""Simulate a whole run to files: the capture, its provenance sidecar and the truth file.

The truth file ``<name>.truth.csv`` has one row per device second (the frames
``k`` with ``k // rate_hz`` equal to the row's ``second``: exactly the blocks a
driver averages over), written by construction from the simulator's physics,
never by decoding.  Rates are means over the second in deg/h (angle per
device second; 1 deg/h = 1 arcsec/s); temperatures are means of the true node
temperatures; ``angle_deg`` is the turntable angle at the end of the second.

Columns: ``second, t_device_s, t_true_s, n_frames, input_dph, earth_dph,
scale_factor_error_dph, constant_bias_dph, drift_dph, drift_bias_temp_dph,
drift_shupe_dph, drift_gradient_dph, drift_hysteresis_dph, bias_instability_dph,
rrw_dph, arw_dph, measured_dph, air_c, housing_c, top_c, bottom_c, fiber_c,
angle_deg``.  ``drift_dph`` is the temperature drift D (the four ``drift_*``
terms); ``measured_dph`` is what the counts say (quantization included).  The
noise a compensator cannot remove is ``bias_instability + rrw + arw`` plus
quantization (``measured - everything else``).
"""

from __future__ import annotations

import contextlib
import filecmp
import math
import threading
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import __version__
from ..dwells import ANGLE_END_COLUMN, TABLE_LOG_COLUMNS
from ..errors import FogDriverError, InputFileError, OutputFileError, UsageError, read_error
from ..files.bounded import open_regular
from ..files.kinds import TRUTH_HEADER
from ..files.outputs import check_outputs, write_error
from ..files.stamps import utc_now_iso
from ..lab.profiles import profile_to_doc
from ..samples.captures import CaptureWriter, read_provenance, sidecar_path, write_provenance
from .instrument import COMPONENTS, FAMILY_COMPONENT, STDBIN_TEMPERATURE_CHANNELS, STDBIN_VERSION, FrameBlock, Simulator

TRUTH_COLUMNS = (
    "second",
    "t_device_s",
    "t_true_s",
    "n_frames",
    "input_dph",
    "earth_dph",
    "scale_factor_error_dph",
    "constant_bias_dph",
    "drift_dph",
    "drift_bias_temp_dph",
    "drift_shupe_dph",
    "drift_gradient_dph",
    "drift_hysteresis_dph",
    "bias_instability_dph",
    "rrw_dph",
    "arw_dph",
    "measured_dph",
    "air_c",
    "housing_c",
    "top_c",
    "bottom_c",
    "fiber_c",
    "angle_deg",
)
_DRIFT_PARTS = ("drift_bias_temp", "drift_shupe", "drift_gradient", "drift_hysteresis")
#: Seconds of frames computed at once when writing files (any value gives the same bytes).
BATCH_SECONDS = 10


def truth_path(capture_path: str | Path) -> Path:
    """``run.bin`` -> ``run.truth.csv``."""
    return Path(capture_path).with_suffix(".truth.csv")


def table_log_path(capture_path: str | Path) -> Path:
    """``run.bin`` -> ``run.table.csv``: the table log of a simulated run with positioning dwells."""
    return Path(capture_path).with_suffix(".table.csv")


def device_stops(sim: Simulator) -> list[dict]:
    """The motion's dwells in device time (s from the first sample: the instrument's clock runs
    ``clock_ppm`` fast), with the table's true angles; ``angle_end_deg`` where a creep turned it."""
    ppm = 1.0 + sim.config.clock_ppm * 1e-6
    out = []
    for stop in sim.profile.motion.dwells():
        entry = {
            "t_start_s": round(stop.t_start_s * ppm, 6),
            "t_end_s": round(stop.t_end_s * ppm, 6),
            "angle_deg": float(stop.angle_deg),
        }
        if stop.angle_end_deg is not None:
            entry["angle_end_deg"] = float(stop.angle_end_deg)
        out.append(entry)
    return out


def write_table_log(path: Path, stops: list[dict], capture_name: str) -> None:
    """The table log: one dwell per row, ``t_start_s,t_end_s,angle_deg`` (the format ``evaluate --reference``
    reads: ``fog_driver.dwells.read_table_log``) and ``angle_end_deg`` when a creep turned the table within a
    dwell; angles cumulative, degrees, at full precision (``repr``)."""
    columns = [*TABLE_LOG_COLUMNS] + ([ANGLE_END_COLUMN] if any(ANGLE_END_COLUMN in s for s in stops) else [])
    lines = [f"# table log of {capture_name}: the simulated table's true angles (device time)", ",".join(columns)]
    for stop in stops:
        lines.append(",".join(repr(float(stop.get(c, stop["angle_deg"]))) for c in columns))
    path.write_text("\n".join(lines) + "\n", encoding="ascii")


def truth_rows(block: FrameBlock, rate_hz: int, scale_arcsec_per_count: float) -> np.ndarray:
    """Per-device-second truth of a block that starts on a second boundary, shape (seconds, columns)."""
    n = len(block.seq)
    second = (block.k0 + np.arange(n)) // rate_hz
    starts = np.flatnonzero(np.r_[True, second[1:] != second[:-1]]) if n else np.zeros(0, np.int64)
    count = np.diff(np.r_[starts, n])
    duration_s = count / rate_hz  # device seconds covered

    def rate(arcsec: np.ndarray) -> np.ndarray:
        return np.add.reduceat(arcsec, starts) / duration_s

    def mean(values: np.ndarray) -> np.ndarray:
        return np.add.reduceat(values, starts) / count

    c = block.components_arcsec
    columns = {
        "second": second[starts],
        "t_device_s": second[starts].astype(np.float64),
        "t_true_s": block.t_true_s[starts],
        "n_frames": count,
        **{
            f"{name}_dph" if name != "scale_factor_error" else "scale_factor_error_dph": rate(c[name])
            for name in COMPONENTS
            if name != "input"
        },
        "input_dph": rate(c["input"]),
        "drift_dph": rate(sum(c[name] for name in (*_DRIFT_PARTS, FAMILY_COMPONENT) if name in c)),
        "measured_dph": rate(block.dtheta_counts * scale_arcsec_per_count),
        **{
            f"{name}": mean(block.truth_temps_c[name])
            for name in ("air_c", "housing_c", "top_c", "bottom_c", "fiber_c")
        },
        "angle_deg": block.angle_deg[np.r_[starts[1:] - 1, n - 1]] if n else np.zeros(0),
    }
    return np.column_stack([columns[name] for name in TRUTH_COLUMNS]) if n else np.zeros((0, len(TRUTH_COLUMNS)))


def write_truth_header(f) -> None:
    f.write(TRUTH_HEADER + "\n")
    f.write(",".join(TRUTH_COLUMNS) + "\n")


def write_truth_rows(f, rows: np.ndarray) -> None:
    fmt = ["%d", "%.0f", "%.6f", "%d"] + ["%.9g"] * (len(TRUTH_COLUMNS) - 4)
    np.savetxt(f, rows, fmt=fmt, delimiter=",")


def read_truth(path: str | Path) -> dict[str, np.ndarray]:
    """The truth file as named columns (plain numbers; no pickle, no code); a missing, unreadable or
    malformed file, or one that is not a regular file (``bounded.open_regular``), is a one-line
    ``InputFileError``.  Read as it streams (one row a device second: no size limit)."""
    try:
        with open_regular(path, "truth file") as f, warnings.catch_warnings():  # (numpy's warning of no rows:
            warnings.simplefilter("ignore", UserWarning)  # the one line below says it)
            data = np.loadtxt(f, delimiter=",", comments="#", skiprows=2, ndmin=2)
    except OSError as exc:
        raise read_error(path, "truth file", exc) from None
    except ValueError as exc:
        raise InputFileError(f"{path}: not a truth file ({' '.join(str(exc).split())})") from None
    if data.shape[1] != len(TRUTH_COLUMNS) or not len(data) or not np.array_equal(data[:, 0], np.arange(len(data))):
        raise InputFileError(
            f"{path}: not a truth file (expected {len(TRUTH_COLUMNS)} columns and one row per device second from 0)"
        )
    return {name: data[:, i] for i, name in enumerate(TRUTH_COLUMNS)}


def check_truth_matches(
    truth: dict[str, np.ndarray], truth_file: str | Path, capture: str | Path, span_s: float | None = None
) -> None:
    """A one-line ``InputFileError`` when ``truth`` (read from ``truth_file``) is not the truth of ``capture``:
    the capture's sidecar names another truth file that is there (and differs), or the truth's seconds differ from the
    capture's (the sidecar's frames and rate, or ``span_s``, the capture's device time from its first sample)."""
    rows = len(truth["second"])
    provenance = read_provenance(capture) or {}
    named = provenance.get("truth_file")
    own = Path(capture).parent / named if isinstance(named, str) else None
    if own is not None and own.is_file() and not filecmp.cmp(own, truth_file, shallow=False):
        raise InputFileError(f"{truth_file}: not the truth of {capture}: its sidecar names {own} (give that one)")
    frames, rate_hz = provenance.get("frames"), provenance.get("rate_hz")
    if isinstance(frames, int) and isinstance(rate_hz, int) and rate_hz > 0:
        expected = -(-frames // rate_hz)
        if rows != expected:
            raise InputFileError(
                f"{truth_file}: {rows:,} s of truth, but {capture} holds {expected:,} s ({frames:,} "
                f"frames at {rate_hz} Hz, says its sidecar): the truth of another capture"
            )
    if span_s is not None and abs(rows - math.ceil(span_s - 1e-6)) > 1:
        raise InputFileError(
            f"{truth_file}: {rows:,} s of truth, but {capture} holds {span_s:,.0f} s of device time: "
            f"the truth of another capture"
        )


def truth_noise_dph(truth: dict[str, np.ndarray]) -> np.ndarray:
    """What no compensator can remove, per second: measured - (input + earth + scale-factor error +
    constant bias + drift) = bias instability + RRW + ARW + quantization."""
    known = sum(truth[f"{c}_dph"] for c in ("input", "earth", "scale_factor_error", "constant_bias", "drift"))
    return truth["measured_dph"] - known


@dataclass
class SimulationResult:
    capture: Path
    sidecar: Path
    truth: Path
    frames: int
    bytes: int
    sha256: str
    interrupted: bool = False  #: stopped before the end (``stop``): the sidecar says ``status: interrupted``
    table_log: Path | None = None  #: the table log (``write_table_log``), when the motion has dwells


def simulate_to_file(
    sim: Simulator,
    out_path: str | Path,
    *,
    duration_s: float | None = None,
    overwrite: bool = False,
    progress: Callable[[int, int], None] | None = None,
    profile_source: str = "",
    faults_text: str = "none",
    stop: threading.Event | None = None,
) -> SimulationResult:
    """Run ``sim`` over its profile (or ``duration_s`` device seconds) into capture, sidecar and truth.

    All three are checked first (``check_outputs``: none exists unless ``overwrite``); a failed write (disk
    full) is an ``OutputFileError`` and removes the capture and truth file this run started.  The sidecar says
    ``status: complete``; a run stopped before its end keeps what it wrote, described as the daemon describes
    a capture its recorder did not close (``status: interrupted``, ``end_reason``, the frames, bytes and
    SHA-256 written): ``stop`` set (checked between batches of ``BATCH_SECONDS``: the capture and the truth
    hold the same seconds, the result's ``interrupted`` is True), or a ``KeyboardInterrupt`` (re-raised once
    the sidecar is written)."""
    out_path = Path(out_path)
    total = sim.total_frames() if duration_s is None else int(round(duration_s * sim.rate_hz))
    batch = BATCH_SECONDS * sim.rate_hz
    truth_file = truth_path(out_path)
    stops = device_stops(sim)
    table_file = table_log_path(out_path) if stops else None
    check_outputs(
        [out_path, sidecar_path(out_path), truth_file, *([table_file] if table_file else [])],
        force=overwrite,
        captures=[out_path],
    )
    writer = CaptureWriter(out_path, overwrite=overwrite)  # fails before creating anything
    written = 0  # frames in the capture
    try:
        with writer, truth_file.open("w", encoding="ascii") as tf:
            write_truth_header(tf)
            for block, data in sim.batches(batch, total):
                writer.write(data)
                written = sim.next_frame
                write_truth_rows(tf, truth_rows(block, sim.rate_hz, sim.config.scale_f32))
                if progress:
                    progress(sim.next_frame, total)
                if stop is not None and stop.is_set() and written < total:
                    break
    except (OSError, OutputFileError, UsageError) as exc:  # UsageError: what the profile asks overflows a frame
        _remove(out_path, truth_file, *([table_file] if table_file else []))  # (an older run's log with --force)
        raise exc if isinstance(exc, FogDriverError) else write_error(truth_file, "truth file", exc) from None
    except KeyboardInterrupt:
        with contextlib.suppress(OSError, OutputFileError):
            if table_file is not None:
                write_table_log(table_file, _held(stops, written, sim), out_path.name)
            _write_sidecar(sim, out_path, truth_file, total, writer, written, profile_source, faults_text, stops)
        raise
    if table_file is not None:
        try:
            write_table_log(table_file, _held(stops, written, sim), out_path.name)
        except OSError as exc:
            _remove(out_path, truth_file, table_file)
            raise write_error(table_file, "table log", exc) from None
    try:
        sidecar = _write_sidecar(sim, out_path, truth_file, total, writer, written, profile_source, faults_text, stops)
    except OutputFileError:
        _remove(out_path, truth_file, *([table_file] if table_file else []))
        raise
    return SimulationResult(
        out_path,
        sidecar,
        truth_file,
        written,
        writer.bytes_written,
        writer.sha256,
        interrupted=written < total,
        table_log=table_file,
    )


def _held(stops: list[dict], frames: int, sim: Simulator) -> list[dict]:
    """The dwells that end within the ``frames`` written (an interrupted run logs the dwells it holds)."""
    return [s for s in stops if s["t_end_s"] <= frames / sim.rate_hz]


def _remove(*paths: Path) -> None:
    """Remove the files of a run that failed half-way (running it again makes them)."""
    for path in paths:
        path.unlink(missing_ok=True)


def _write_sidecar(
    sim: Simulator,
    out_path: Path,
    truth_file: Path,
    total: int,
    writer: CaptureWriter,
    written: int,
    profile_source: str,
    faults_text: str,
    stops: list[dict],
) -> Path:
    """The capture's provenance sidecar: ``status: complete`` once all ``total`` frames are written, else
    ``interrupted`` with the ``written`` frames (``simulate_to_file``); ``bytes`` and ``sha256`` are the
    ``writer``'s: exactly what is on disk; ``stops``: ``device_stops(sim)``; ``program``: the profile run, in
    the profile-file format (``profiles.profile_to_doc``: ``name``, ``start_c``, ``segments``, ``motion``),
    from the capture's first frame, whatever part of it the capture holds."""
    ending: dict = {"status": "complete"}
    if written < total:
        ending = {
            "status": "interrupted",
            "end_reason": f"stopped after {written:,} of {total:,} frames ({written / sim.rate_hz:g} s of "
            f"{total / sim.rate_hz:g} s)",
            "frames_planned": total,
        }
    return write_provenance(
        out_path,
        {
            "source": "simulate",
            **ending,
            "generated_utc": utc_now_iso(),
            "fog_driver_version": __version__,
            "profile": sim.profile.name,
            "profile_source": profile_source or sim.profile.source,
            "program": profile_to_doc(sim.profile),  # the whole program, as a profile file: fit judges it
            "seed": sim.seed,
            "rate_hz": sim.rate_hz,
            "faults": faults_text,
            "frames": written,
            "bytes": writer.bytes_written,
            "sha256": writer.sha256,
            "truth_file": truth_file.name,
            **({"table_log": table_log_path(out_path).name} if stops else {}),
            "instrument": {
                "serial": sim.config.serial,
                "firmware": f"{sim.config.firmware >> 8}.{sim.config.firmware & 0xFF}",
                "rate_hz": sim.rate_hz,
                "scale_arcsec_per_count": sim.config.scale_f32,
            },
            "run": {
                "seq0": sim.seq0,
                "t_us0": sim.t_us0,
                "turn_on_bias_dph": sim.turn_on_bias_dph,
                "thermometer_offsets_c": [float(v) for v in sim.thermometer_offsets_c],
            },
            "positioning_stops": stops,  # device time, s from the first sample
            "model": sim.config.as_dict(),
            **_wire_format(sim),
        },
    )


def _wire_format(sim: Simulator) -> dict:
    """The frame format and the device settings it was sent with, for a format other than protocol v1 (whose
    frames say everything themselves; a sidecar without ``wire_format`` is protocol v1).  KVH: the decoder's
    settings and the thermometer its temperature is; STDBIN: ``rate_hz``, ``version`` and
    ``temperature_channels`` (each Temperatures-block channel -> the simulated thermometer it carries)."""
    if sim.wire_format == "fog-v1":
        return {}
    if sim.wire_format == "ixblue-stdbin":
        return {
            "wire_format": sim.wire_format,
            "wire_settings": {
                "rate_hz": sim.rate_hz,
                "version": STDBIN_VERSION,
                "temperature_channels": dict(STDBIN_TEMPERATURE_CHANNELS),
            },
        }
    return {
        "wire_format": sim.wire_format,
        "wire_settings": {
            "rot_format": "delta",
            "rot_units": "rad",
            "temp_units": "c_100",
            "rate_hz": sim.rate_hz,
            "temperature_channel": "housing",
        },
    }
