"""Positioning accuracy: the paper's Table 1, computed from a capture and its reference stops.

The paper's experiment: at each chamber temperature the turntable turns in 36-degree steps, 10
steps, dwelling between them; the instrument's measured angle of each step is compared with the
table's.  Table 1 gives, per temperature, the mean and standard deviation (arcsec) of that
positioning error, uncompensated and compensated.

Reference stops
    Dwells (``fog_driver.dwells.Dwell(t_start_s, t_end_s, angle_deg)``): the table is still from ``t_start_s``
    to ``t_end_s`` (device time, seconds from the capture's first sample) at the cumulative angle ``angle_deg``;
    with ``angle_end_deg`` it moved within the dwell (a creep), linearly to that angle, and the dwell's
    reference is the mean over its trimmed window (``dwell_reference_deg``).
    They come from the simulator's sidecar (``positioning_stops``) or from a station's table log
    (``fog_driver.dwells.read_table_log``, whose docstring gives the format).  ``load_stops`` picks one.

Sequences (``group_sequences``)
    Consecutive stops belong to one sequence while one dwell's end and the next one's start are less
    than ``gap_s`` (120 s) apart; a sequence needs at least 2 stops (1 move).

Errors (``positioning_errors``)
    The measured angle at a dwell is the mean of the angle over the dwell, ``dwell_trim_s`` (5 s)
    cut from both ends so the table's settling is excluded; the error of a move is the measured
    change between consecutive dwells minus the reference change, in arcsec.  A dwell with no
    sample in its trimmed window (a gap in the capture) gives NaN for its two moves; they are left
    out of the statistics (``n_moves`` counts the finite ones).

Bias (``positioning_table``)
    A gyro measures the Earth rate and its constant and turn-on bias too (together ~10 deg/h in the
    simulator, 10 arcsec/s: ~650 arcsec over one 64-s step), which no drift model removes (models
    are fitted to the drift relative to each run's own mean, see ``compensation/adapt.py``).  As an
    operator zeroes the instrument at rest before the test (the daemon's ``?BIAS``), the table
    removes, from every method's angle, the mean rate over a bias window at rest, the same window
    for every method: ``bias_window_s=(t0, t1)``, or by default the first ``BIAS_WINDOW_S`` (300 s)
    of the capture after every compensator's start-up (the first 1-s point without the
    ``uncompensated`` flag), ending before the first stop (the table is assumed still until then);
    when that leaves under ``MIN_BIAS_WINDOW_S`` (30 s), the first stop's trimmed dwell is used.
    ``remove_bias=False`` keeps everything (errors then carry the Earth rate).  The raw errors so
    measure the uncompensated temperature drift since the bias window; the compensated ones what
    the model leaves of it.

Statistics and improvement
    Per sequence and method: mean and sample standard deviation (ddof 1; NaN for one move) of the
    move errors.  The label is the mean housing temperature over the sequence (the top thermometer
    when housing readings are missing), rounded to whole degrees ("-40 degC"), or the given
    ``plateau_temps_c`` (one per sequence, in order), or "sequence N" without temperatures.  The
    housing runs warmer than the chamber air (in the simulator ~2.4 degC at 25 degC: "27 degC");
    pass the chamber set points as ``plateau_temps_c`` to label rows as the paper does.
    ``improvement(rows, method)`` = 1 - mean_i |mean error_i| compensated / mean_i |mean error_i|
    raw, in percent (the paper's overall "precision improvement").  The paper's per-temperature
    figure (``improvement_per_row``) is 1 - |mean error comp| / |mean error raw| at one temperature:
    its -40 degC row, 0.168 -> 0.097 arcsec, gives 1 - 0.097 / 0.168 = 42.3 %; the paper prints
    42.1 %, which is the same definition on unrounded means (e.g. 0.1675 -> 0.0970).

``report_for(capture, model_file, summary, ...)`` is the section ``fog-driver evaluate`` asks for.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..compensation.dwell import DWELL_TRIM_S, reference_deg, trimmed_window
from ..compensation.model import ModelFile
from ..dwells import ANGLE_END_COLUMN, TABLE_LOG_COLUMNS, Dwell, check_dwell_order, read_table_log, table_angle_deg
from ..errors import InputFileError, UsageError
from ..flags import FLAG_UNCOMPENSATED
from ..modelfiles import load_model
from ..offline.compensate import compensate_capture
from ..samples.captures import find_sidecar, read_provenance
from ..samples.sources import CaptureReader, wire_settings_for

__all__ = [
    "BIAS_WINDOW_S",
    "DEFAULT_GAP_S",
    "MIN_BIAS_WINDOW_S",
    "NO_SEQUENCES",
    "RAW",
    "Row",
    "format_table",
    "group_sequences",
    "improvement",
    "improvement_per_row",
    "load_stops",
    "positioning_errors",
    "positioning_table",
    "report_for",
    "stops_from_sidecar",
    "summary_dict",
]

RAW = "uncompensated"
DEFAULT_GAP_S = 120.0
DEFAULT_TRIM_S = DWELL_TRIM_S
BIAS_WINDOW_S = 300.0
MIN_BIAS_WINDOW_S = 30.0
NO_SEQUENCES = "no positioning sequences in this capture: the table is skipped"
ARCSEC_PER_DEG = 3600.0

# --- reference stops ---------------------------------------------------------------------------


def _sidecar_number(entry: dict, name: str, where: str) -> float:
    v = entry[name]
    if name.startswith("angle"):  # the bound ?TABLE applies
        try:
            return table_angle_deg(v, name)
        except ValueError as exc:
            raise InputFileError(f"{where}: {exc}") from None
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise InputFileError(f"{where}: {name} must be a finite number, got {v!r}")
    return float(v)


def stops_from_sidecar(capture: str | Path) -> list[Dwell]:
    """The ``positioning_stops`` of the capture's provenance sidecar; [] without a sidecar or stops."""
    provenance = read_provenance(capture) or {}
    entries = provenance.get("positioning_stops") or []
    where = f"{find_sidecar(capture)}: positioning_stops"
    if not isinstance(entries, list):
        raise InputFileError(f"{where}: expected a list of stops")
    stops: list[Dwell] = []
    for i, entry in enumerate(entries):
        if not isinstance(entry, dict) or any(c not in entry for c in TABLE_LOG_COLUMNS):
            raise InputFileError(f"{where}[{i}]: expected a mapping with {', '.join(TABLE_LOG_COLUMNS)}")
        start, end, angle = (_sidecar_number(entry, c, f"{where}[{i}]") for c in TABLE_LOG_COLUMNS)
        check_dwell_order(stops, start, end, f"{where}[{i}]")
        has_end = entry.get(ANGLE_END_COLUMN) is not None  # optional
        stops.append(
            Dwell(start, end, angle, _sidecar_number(entry, ANGLE_END_COLUMN, f"{where}[{i}]") if has_end else None)
        )
    return stops


def check_stops_within(stops: Sequence[Dwell], span_s: float, where: str | Path, capture: str | Path) -> None:
    """A one-line ``InputFileError`` when reference stops lie outside the capture's device time (``span_s``
    seconds from its first sample): the reference of another capture, or times not counted from its start."""
    outside = [s for s in stops if s.t_end_s > span_s + 1.0]
    if outside:
        raise InputFileError(
            f"{where}: {len(outside)} of {len(stops)} reference stops end after the capture does "
            f"(the last at {stops[-1].t_end_s:,.1f} s; {capture} holds {span_s:,.1f} s of device "
            f"time from its first sample): the reference of another capture?"
        )


def load_stops(capture: str | Path, reference_csv: str | Path | None = None) -> list[Dwell]:
    """The station's reference CSV when given, else the simulator sidecar's stops (maybe [])."""
    return read_table_log(reference_csv) if reference_csv is not None else stops_from_sidecar(capture)


def group_sequences(stops: Sequence[Dwell], gap_s: float = DEFAULT_GAP_S) -> list[list[Dwell]]:
    """Split time-ordered stops into sequences: a new one where a dwell starts ``gap_s`` or more after the last ended.

    Sequences of a single stop (no move) are dropped.
    """
    groups: list[list[Dwell]] = []
    for stop in stops:
        if groups and stop.t_start_s - groups[-1][-1].t_end_s < gap_s:
            groups[-1].append(stop)
        else:
            groups.append([stop])
    return [g for g in groups if len(g) >= 2]


# --- dwell means ---------------------------------------------------------------------------------


def _windows(stops: Sequence[Dwell], trim_s: float) -> np.ndarray:
    """(n, 2) trimmed dwell windows (``dwell.trimmed_window``: the table law's too); a dwell not longer than
    2 trims is a ``ValueError``."""
    return np.array([trimmed_window(s.t_start_s, s.t_end_s, trim_s) for s in stops], dtype=np.float64).reshape(-1, 2)


class _DwellSums:
    """Per-dwell sums of angle and time over its trimmed window, fed in time-ordered chunks."""

    def __init__(self, windows: np.ndarray) -> None:
        self.windows = windows
        self.sum_a = np.zeros(len(windows))
        self.sum_t = np.zeros(len(windows))
        self.n = np.zeros(len(windows), dtype=np.int64)

    def add(self, t_s: np.ndarray, angle: np.ndarray) -> None:
        if not len(t_s):
            return
        lo = np.searchsorted(t_s, self.windows[:, 0], side="left")
        hi = np.searchsorted(t_s, self.windows[:, 1], side="right")
        for k in np.flatnonzero(hi > lo):
            self.sum_a[k] += angle[lo[k] : hi[k]].sum()
            self.sum_t[k] += t_s[lo[k] : hi[k]].sum()
            self.n[k] += hi[k] - lo[k]

    def means(self, bias_arcsec_per_s: float = 0.0) -> np.ndarray:
        """Mean angle per dwell with ``bias * t`` removed (NaN for an empty dwell)."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return (self.sum_a - bias_arcsec_per_s * self.sum_t) / self.n


def dwell_reference_deg(stop: Dwell) -> float:
    """The table's mean angle over the dwell's trimmed window (``dwell.reference_deg``, as the table law holds
    it): ``angle_deg``, or with ``angle_end_deg`` the mean of the two."""
    return reference_deg(stop.angle_deg, stop.angle_end_deg)


def _move_errors(means: np.ndarray, stops: Sequence[Dwell]) -> np.ndarray:
    reference = np.array([dwell_reference_deg(s) for s in stops], dtype=np.float64) * ARCSEC_PER_DEG
    return np.diff(means) - np.diff(reference)


def positioning_errors(
    t_s: np.ndarray,
    angle_arcsec: np.ndarray,
    stops: Sequence[Dwell],
    *,
    dwell_trim_s: float = DEFAULT_TRIM_S,
    bias_arcsec_per_s: float = 0.0,
) -> np.ndarray:
    """Error of each move between consecutive ``stops``, arcsec: measured change - reference change.

    ``t_s`` is device time from the first sample (ascending), ``angle_arcsec`` the angle there; the
    measured angle at a dwell is its mean over [t_start + trim, t_end - trim], with
    ``bias_arcsec_per_s * t`` removed first.  NaN for moves next to a dwell with no samples.
    """
    t = np.asarray(t_s, dtype=np.float64)
    a = np.asarray(angle_arcsec, dtype=np.float64)
    if t.shape != a.shape or t.ndim != 1:
        raise ValueError(f"t_s and angle_arcsec must be 1-d and the same length, got {t.shape} and {a.shape}")
    if len(stops) < 2:
        return np.zeros(0)
    sums = _DwellSums(_windows(stops, dwell_trim_s))
    sums.add(t, a)
    return _move_errors(sums.means(bias_arcsec_per_s), stops)


# --- the table -----------------------------------------------------------------------------------


@dataclass
class Row:
    """One sequence (one temperature): its label, the number of moves, and {method: (mean, std)} in arcsec."""

    label: str
    n_moves: int
    stats: dict[str, tuple[float, float]]
    temp_c: float | None = None  #: mean housing (else top) temperature over the sequence
    t_start_s: float = 0.0
    t_end_s: float = 0.0
    errors: dict[str, np.ndarray] = field(default_factory=dict)  #: per move, arcsec (NaN: no data)
    bias_dph: dict[str, float] = field(default_factory=dict)  #: the rate removed per method (1 deg/h = 1 arcsec/s)
    bias_window_s: tuple[float, float] | None = None


@dataclass
class _Pass:
    """What one decoding pass over the capture keeps: dwell sums, 1-s points, temperature sums."""

    sums: _DwellSums
    t_points: list[np.ndarray] = field(default_factory=list)
    a_points: list[np.ndarray] = field(default_factory=list)
    ready_s: float | None = None


def _columns(
    capture: Path,
    model_file: ModelFile | None,
    force_model: bool,
    name: str,
    wire_format: str = "auto",
    options: Mapping[str, Any] | None = None,
) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """(t_s absolute, raw angle, method's angle, temps (n, 3), uncompensated mask) per chunk."""
    if model_file is not None:
        for _, c in compensate_capture(
            capture,
            model_file,
            force_model=force_model,
            model_name=f"model {name!r}",
            wire_format=wire_format,
            **(options or {}),
        ):
            yield c.t_s, c.angle_raw_arcsec, c.angle_comp_arcsec, c.temps_c, (c.flags & FLAG_UNCOMPENSATED) != 0
        return
    angle = 0.0
    for part in CaptureReader(capture, wire_settings_for(capture, wire_format)).parts():
        s = part.samples
        if not len(s):
            continue
        a = angle + np.cumsum(s.dtheta_arcsec)
        angle = float(a[-1])
        temps = np.column_stack([s.t_top_c, s.t_bottom_c, s.t_housing_c])
        yield s.t_s, a, a, temps, np.zeros(len(s), dtype=bool)


def _seq_temps(t: np.ndarray, temps: np.ndarray, spans: np.ndarray, acc: np.ndarray) -> None:
    """Add nan-sums and counts of housing and top temperature within each sequence span to ``acc`` (k, 4)."""
    lo = np.searchsorted(t, spans[:, 0], side="left")
    hi = np.searchsorted(t, spans[:, 1], side="right")
    for k in np.flatnonzero(hi > lo):
        for j, col in enumerate((2, 0)):  # housing, then top
            v = temps[lo[k] : hi[k], col]
            ok = ~np.isnan(v)
            acc[k, 2 * j] += v[ok].sum()
            acc[k, 2 * j + 1] += ok.sum()


def _second_points(t: np.ndarray, a: np.ndarray, last_second: int) -> tuple[np.ndarray, np.ndarray, int]:
    """The first sample of every new whole device second (and the chunk's last sample)."""
    sec = np.floor(t + 1e-9).astype(np.int64)
    new = np.flatnonzero(np.r_[sec[0] != last_second, sec[1:] != sec[:-1]])
    idx = np.unique(np.r_[new, len(t) - 1])
    return t[idx], a[idx], int(sec[-1])


def _rate(t: np.ndarray, a: np.ndarray, window: tuple[float, float]) -> float:
    """Mean rate (arcsec/s) over ``window`` from the 1-s points: (a(end) - a(start)) / (t(end) - t(start))."""
    i0 = int(np.searchsorted(t, window[0], side="left"))
    i1 = int(np.searchsorted(t, window[1], side="right")) - 1
    if i1 <= i0 or i0 >= len(t):
        raise UsageError(f"the bias window {window[0]:g}..{window[1]:g} s holds no samples of the capture")
    return float((a[i1] - a[i0]) / (t[i1] - t[i0]))


def _label(temp_c: float | None, index: int) -> str:
    if temp_c is None:
        return f"sequence {index + 1}"
    return f"{round(temp_c) + 0:d} degC"


def _stats(errors: np.ndarray) -> tuple[float, float]:
    e = errors[np.isfinite(errors)]
    mean = float(e.mean()) if len(e) else math.nan
    std = float(e.std(ddof=1)) if len(e) > 1 else math.nan
    return mean, std


def _read_passes(
    capture: Path,
    model_files: Mapping[str, ModelFile],
    windows: np.ndarray,
    spans: np.ndarray,
    temp_acc: np.ndarray,
    force_model: bool,
    wire_format: str,
    options: Mapping[str, Mapping[str, Any]],
) -> dict[str, _Pass]:
    """One pass over ``capture`` per model (the first also reads the raw angle and adds the sequences'
    temperatures to ``temp_acc``): each method's dwell sums, its points once a second, and when it is ready."""
    passes: dict[str, _Pass] = {}
    methods = [(name, mf) for name, mf in model_files.items()] or [(None, None)]
    for i, (name, mf) in enumerate(methods):
        first = i == 0
        targets = {name: _Pass(_DwellSums(windows))} if name is not None else {}
        if first:
            targets[RAW] = _Pass(_DwellSums(windows), ready_s=0.0)
        t0: float | None = None
        last_second = {key: -1 for key in targets}
        extra = options.get(name or "", {})
        for t_abs, raw, comp, temps, uncomp in _columns(capture, mf, force_model, name or "", wire_format, extra):
            if t0 is None:
                t0 = float(t_abs[0])
            t = t_abs - t0
            for key, p in targets.items():
                a = raw if key == RAW else comp
                p.sums.add(t, a)
                tp, ap, last_second[key] = _second_points(t, a, last_second[key])
                p.t_points.append(tp)
                p.a_points.append(ap)
                if p.ready_s is None and not uncomp.all():
                    p.ready_s = float(np.ceil(t[int(np.argmin(uncomp))]))
            if first:
                _seq_temps(t, temps, spans, temp_acc)
        passes.update(targets)
    return passes


def _bias(
    passes: dict[str, _Pass],
    points: dict[str, tuple[np.ndarray, np.ndarray]],
    remove_bias: bool,
    bias_window_s: tuple[float, float] | None,
    capture: Path,
    flat: list[Dwell],
    stops: Sequence[Dwell],
    windows: np.ndarray,
) -> tuple[tuple[float, float] | None, dict[str, float]]:
    """The window the bias is read over and each method's bias rate on it (the module docstring): 0 without
    ``remove_bias``."""
    window: tuple[float, float] | None = None
    bias = {k: 0.0 for k in passes}
    if remove_bias:
        if bias_window_s is not None:
            window = (float(bias_window_s[0]), float(bias_window_s[1]))
            if not window[1] > window[0]:
                raise UsageError(f"bias window {window[0]:g}..{window[1]:g} s: the end must be after the start")
        else:
            never = [k for k, p in passes.items() if p.ready_s is None]
            if never:
                raise UsageError(f"model {never[0]!r} never produced a compensated sample on {capture}")
            start = max(p.ready_s for p in passes.values())  # type: ignore[type-var]
            end = min(start + BIAS_WINDOW_S, flat[0].t_start_s, stops[0].t_start_s)
            window = (start, end)
            if end - start < MIN_BIAS_WINDOW_S:
                window = (float(windows[0, 0]), float(windows[0, 1]))
        bias = {k: _rate(*points[k], window) for k in passes}
    return window, bias


def positioning_table(
    capture: str | Path,
    model_files: Mapping[str, ModelFile],
    stops: Sequence[Dwell],
    *,
    plateau_temps_c: Sequence[float] | None = None,
    dwell_trim_s: float = DEFAULT_TRIM_S,
    gap_s: float = DEFAULT_GAP_S,
    remove_bias: bool = True,
    bias_window_s: tuple[float, float] | None = None,
    force_model: bool = False,
    wire_format: str = "auto",
    options: Mapping[str, Mapping[str, Any]] | None = None,
) -> list[Row]:
    """The paper's Table 1 for ``capture``: one ``Row`` per positioning sequence ([] when there is none).

    ``"uncompensated"`` uses the raw angle; each named model its compensated angle
    (``compensate_capture(capture, model, force_model=force_model, **options[name])``, one pass per model;
    bounded memory): ``options`` gives a method more of ``compensate_capture``'s keywords, such as adapting
    from a table log (``adapt=AdaptConfig(), table_dwells=...``), so one model can be two methods.
    Bias handling, labels and statistics: the module docstring.  ``format_table([])`` says the
    table is skipped (``NO_SEQUENCES``).
    """
    capture = Path(capture)
    sequences = group_sequences(stops, gap_s)
    if not sequences:
        return []
    if plateau_temps_c is not None and len(plateau_temps_c) != len(sequences):
        raise UsageError(f"{len(plateau_temps_c)} plateau temperatures for {len(sequences)} positioning sequences")
    for name in model_files:
        if name == RAW:
            raise UsageError(f"{RAW!r} is the raw column's name, not a model's")
    flat = [s for seq in sequences for s in seq]
    windows = _windows(flat, dwell_trim_s)
    spans = np.array([(seq[0].t_start_s, seq[-1].t_end_s) for seq in sequences])
    temp_acc = np.zeros((len(sequences), 4))

    passes = _read_passes(capture, model_files, windows, spans, temp_acc, force_model, wire_format, options or {})

    points = {k: (np.concatenate(p.t_points), np.concatenate(p.a_points)) for k, p in passes.items()}
    window, bias = _bias(passes, points, remove_bias, bias_window_s, capture, flat, stops, windows)

    order = [RAW] + [k for k in model_files]
    rows: list[Row] = []
    offset = 0
    for i, seq in enumerate(sequences):
        n = len(seq)
        errors = {k: _move_errors(passes[k].sums.means(bias[k])[offset : offset + n], seq) for k in order}
        offset += n
        house_sum, house_n, top_sum, top_n = temp_acc[i]
        temp_c = house_sum / house_n if house_n else (top_sum / top_n if top_n else None)
        label = f"{plateau_temps_c[i]:g} degC" if plateau_temps_c is not None else _label(temp_c, i)
        finite = np.isfinite(errors[RAW])
        for k in order:
            finite &= np.isfinite(errors[k])
        rows.append(
            Row(
                label,
                int(finite.sum()),
                {k: _stats(errors[k]) for k in order},
                None if temp_c is None else float(temp_c),
                seq[0].t_start_s,
                seq[-1].t_end_s,
                errors,
                {k: float(bias[k]) for k in order},
                window,
            )
        )
    return rows


def _num(x: float) -> str:
    return f"{x:.3f}" if math.isfinite(x) else "n/a"


def format_table(rows: Sequence[Row], methods: Sequence[str] | None = None) -> str:
    """A Markdown table like the paper's Table 1 (arcsec); ``NO_SEQUENCES`` when ``rows`` is empty."""
    if not rows:
        return NO_SEQUENCES
    methods = list(methods) if methods is not None else [m for m in rows[0].stats if m != RAW]
    head = ["Temperature", "moves", f"{RAW} mean", f"{RAW} std"]
    for m in methods:
        head += [f"{m} mean", f"{m} std"]
    lines = ["| " + " | ".join(head) + " |", "|" + "|".join(["---"] + ["---:"] * (len(head) - 1)) + "|"]
    for r in rows:
        cells = [r.label, str(r.n_moves)]
        for m in [RAW, *methods]:
            mean, std = r.stats[m]
            cells += [_num(mean), _num(std)]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def improvement_per_row(rows: Sequence[Row], method: str) -> list[float]:
    """The paper's per-temperature figure, percent: 1 - |mean error| compensated / |mean error| raw."""
    out = []
    for r in rows:
        raw, comp = abs(r.stats[RAW][0]), abs(r.stats[method][0])
        out.append(100.0 * (1.0 - comp / raw) if raw > 0 and math.isfinite(raw) and math.isfinite(comp) else math.nan)
    return out


def improvement(rows: Sequence[Row], method: str) -> float:
    """The paper's overall "precision improvement", percent: 1 - mean |mean error| comp / mean |mean error| raw."""
    pairs = [(abs(r.stats[RAW][0]), abs(r.stats[method][0])) for r in rows]
    pairs = [(a, b) for a, b in pairs if math.isfinite(a) and math.isfinite(b)]
    if not pairs:
        return math.nan
    raw = sum(a for a, _ in pairs) / len(pairs)
    comp = sum(b for _, b in pairs) / len(pairs)
    return 100.0 * (1.0 - comp / raw) if raw > 0 else math.nan


def summary_dict(rows: Sequence[Row]) -> list[dict[str, Any]]:
    """Rows as plain JSON-ready dicts (label, moves, temp_c, {method: {mean, std}}; NaN as None)."""

    def clean(x: float) -> float | None:
        return float(x) if math.isfinite(x) else None

    return [
        {
            "label": r.label,
            "moves": r.n_moves,
            "temp_c": r.temp_c,
            "methods": {m: {"mean_arcsec": clean(a), "std_arcsec": clean(b)} for m, (a, b) in r.stats.items()},
            "bias_dph": r.bias_dph,
            "bias_window_s": list(r.bias_window_s) if r.bias_window_s else None,
        }
        for r in rows
    ]


def report_for(
    capture: str | Path,
    model_file: ModelFile,
    summary: dict[str, Any],
    *,
    reference: str | Path | None = None,
    compare: Sequence[str | Path] | Mapping[str, ModelFile] = (),
    zero_window_s: tuple[float, float] | None = None,
    force_model: bool = False,
    wire_format: str = "auto",
    label: str | None = None,
) -> str | None:
    """The positioning section of ``fog-driver evaluate``.

    Stops from ``reference`` (a reference CSV), else the sidecar's; ``compare``: more models, by label, or
    model files, labelled by their file stem and kind ("m-default (polynomial)"); ``label``: the main
    model's (default: its kind); ``zero_window_s``: the bias window (None for the default).  Adds
    ``summary["positioning"]`` and returns the Markdown table with the improvement figures, or None (the
    table is skipped) when the capture has no sequence.
    """
    capture = Path(capture)
    stops = load_stops(capture, reference)
    models: dict[str, ModelFile] = {label or model_file.kind: model_file}
    others = compare.items() if isinstance(compare, Mapping) else ((None, p) for p in compare)
    for name, other in others:
        if name is None:
            other_file = load_model(other)
            name = f"{Path(other).stem} ({other_file.kind})"
        else:
            other_file = other
        while name in models or name == RAW:
            name += "'"
        models[name] = other_file
    rows = positioning_table(
        capture, models, stops, force_model=force_model, bias_window_s=zero_window_s, wire_format=wire_format
    )
    if not rows:
        summary["positioning"] = None
        return None
    summary["positioning"] = {
        "rows": summary_dict(rows),
        "improvement_percent": {m: (v if math.isfinite(v := improvement(rows, m)) else None) for m in models},
    }
    lines = [format_table(rows), ""]
    for m in models:
        per_row = ", ".join(f"{r.label} {p:.1f} %" for r, p in zip(rows, improvement_per_row(rows, m)))
        lines.append(
            f"- {m}: precision improvement {improvement(rows, m):.1f} % over all temperatures "
            f"(per temperature: {per_row})"
        )
    window = rows[0].bias_window_s
    if window is not None:
        lines.append(
            f"- errors in arcsec; every method's mean rate over {window[0]:g}..{window[1]:g} s "
            f"(the bias: Earth rate, constant and turn-on bias) removed first"
        )
    return "\n".join(lines)
