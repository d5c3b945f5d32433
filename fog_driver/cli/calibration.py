"""``fog-driver fit``, ``compensate`` and ``evaluate``: fit a drift model, apply it to a capture, report on it."""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from pathlib import Path

from .. import __version__
from ..client.display import Progress
from ..compensation.adapt import AdaptConfig
from ..compensation.fitting.choice import SE_MULTIPLE
from ..compensation.fitting.fit import (
    FITTERS,
    KIND_HELP,
    FitConfig,
    WeakFitError,
    bias_step_warning,
)
from ..compensation.fitting.quality import format_checks
from ..compensation.fitting.report import WORSE_MARKER
from ..compensation.pipeline import Compensator
from ..dwells import read_table_log
from ..errors import FogDriverError, InputFileError, OutputFileError, UsageError
from ..extras import require_extra
from ..files.bounded import file_sha256
from ..files.kinds import ROW_COLUMNS
from ..files.outputs import check_outputs, refuse_captures, write_error
from ..files.stamps import utc_now_iso
from ..files.typed_mapping import dataclass_from_mapping
from ..files.yamlio import MAX_YAML_BYTES, read_yaml
from ..formats.registry import FORMATS
from ..modelfiles import load_model, not_a_state_file, save_model
from ..offline.chamber import capture_program_warnings
from ..offline.compensate import (
    capture_facts,
    check_model,
    compensate_capture,
    csv_sidecar_path,
    write_csv_provenance,
)
from ..offline.fit import fit_model_file
from ..offline.replay import REPLAYED, control_events, unreplayed
from ..offline.rows import compensated_rows, format_row
from ..offline.table import check_table_log_used, table_summary_lines
from ..report import positioning
from ..report.coverage import format_coverage
from ..report.evaluate import (
    evaluate,
    format_bias_instability,
    model_label,
    report_file_names,
    series_names,
    write_report,
)
from ..samples.captures import _capture_size, read_provenance
from ..sim.capture import check_truth_matches, read_truth
from .argtypes import finite_float, period_s, scale_arcsec_per_count, time_window

#: What ``fog-driver fit`` fits without ``--kind``: the project's best model (docs/explanation/accuracy.md).
DEFAULT_FIT_KIND = "wesn"


def _print_fit_report(report) -> None:
    """The fit's table, its noise-floor line, and a warning (with the fit's other warnings, on stdout: stderr
    keeps the one-line error of a refused fit) for each model row that leaves more drift than no compensation
    (marked in the table)."""
    print(report.format())
    note = report.floor_note()
    if note:
        print(f"note: {note}")
    for line in report.lines():  # noise_1min_dph, and the model choice with its margin
        print(line)
    before = report.rows[0]
    for what, fit_value, validate_value in report.rows[1:]:
        for col in report.worse().get(what, []):
            value, base = (fit_value, before[1]) if col == "fit" else (validate_value, before[2])
            where = "its fit data" if col == "fit" else "the validation data"
            print(
                f"warning: {what.removeprefix('after, ')} is {WORSE_MARKER} on {where}: {value:.4f} deg/h "
                f"against {base:.4f} deg/h before compensation"
            )


def cmd_fit(args: argparse.Namespace) -> int:
    out = Path(args.out)
    profile_files = [p for p in args.profile if Path(p).is_file()]
    check_outputs(
        [out], force=args.force, inputs=[*args.captures, *args.validate, *filter(None, [args.config]), *profile_files]
    )
    if args.kind == "pso-svr":
        require_extra("svr", "fitting a pso-svr model")
    config = FitConfig()
    if args.config:
        config = dataclass_from_mapping(FitConfig, read_yaml(args.config, "fit config") or {}, args.config)
    kind = args.kind or DEFAULT_FIT_KIND
    default = (
        f" (the default kind: the polynomial is saved instead only if it does better on the fit's own "
        f"validation split by more than {SE_MULTIPLE:g} standard errors; --kind chooses)"
        if args.kind is None
        else ""
    )
    print(f"fitting a {kind} model{default}", flush=True)
    chamber_warnings = capture_program_warnings(args.captures)  # did each capture's chamber run its program?
    for line in chamber_warnings:
        print(f"warning: {line}", flush=True)
    progress = Progress()
    try:
        model_file, report = fit_model_file(
            args.captures,
            kind=kind,
            config=config,
            validate_paths=args.validate,
            fall_back=args.kind is None,
            accept_weak=args.accept_weak_fit,
            progress=progress.show,
            wire_format=args.format,
            profiles=args.profile,
        )
    except WeakFitError as exc:
        progress.clear()
        _print_fit_report(exc.report)
        print(exc.quality.format())
        for check in exc.quality.failed:
            print(f"error: {check.message}")
        raise InputFileError(
            f"{exc}; {out} not written (--accept-weak-fit writes it anyway, and the model file records that)"
        ) from None
    finally:
        progress.clear()
    if chamber_warnings:
        model_file.provenance["chamber_warnings"] = chamber_warnings
    save_model(out, model_file)
    provenance = model_file.provenance
    fitted = provenance["captures"]
    print(
        f"fitted a {model_file.kind} model for {model_file.instrument_serial} on {len(fitted)} capture(s) "
        f"({sum(c['static_blocks'] for c in fitted):,} static blocks of {sum(c['blocks'] for c in fitted):,}) "
        f"-> {out}"
    )
    moving = sum(c.get("moving_blocks", 0) for c in fitted)
    if moving:
        print(
            f"note: {moving:,} blocks of table motion were found and not fitted (with {config.motion_margin_s:g} s "
            f"on each side)"
        )
    selection = provenance.get("selection")
    if selection and model_file.kind == kind:
        _print_structure(selection)
    _print_fit_report(report)
    _print_quality(provenance["fit_quality"], len(model_file.temperature_channels))
    print(
        f"the model's input box and estimate bound (+-{model_file.domain.estimate_limit_dph:.3g} deg/h) are in "
        f"the file: outside them its estimate is flagged extrapolating"
    )
    return 0


def _print_structure(selection: dict) -> None:
    """The structure the fit chose from the data (the model file's ``provenance.selection``), its limits and
    warnings."""
    history = (
        (
            f"history neurons {', '.join(f'{v:g}' for v in selection['history_s'])} s at "
            f"{selection['history_penalty']:g}x the penalty"
        )
        if selection["history_s"]
        else "no history neurons"
    )
    order = selection.get("coil_order", 1)
    stages = f" in {order} stages" if order > 1 else ""
    print(
        f"structure chosen from the data: coil lag {selection['coil_lag_s']:g} s{stages}, ridge penalty "
        f"{selection['ridge_alpha']:g}, {history}"
        f"{'' if selection['state_powers'] else ', linear in the coil temperature'}"
    )
    lags = selection.get("lags_explaining_equally_s")
    if lags:
        coils = selection.get("coils_explaining_equally") or []
        print(
            f"coil lags explaining the data within the noise of the best: {min(lags):g} to {max(lags):g} s "
            f"(a factor {max(lags) / min(lags):.2f}; {len(coils) or len(lags)} structures, "
            f"the spread of up to 6 of them goes into drift_sigma_dph)"
        )
    for note in selection.get("limits", []):
        print(f"note: {note}")
    for key in ("warning", "warning_validation"):
        if key in selection:
            print(f"warning: {selection[key]}")


def _print_quality(quality: dict, temperature_channels: int) -> None:
    """The fit's checks (the model file's ``provenance.fit_quality``), the model's condition for information,
    the weaknesses accepted, and the bias step test."""
    print(format_checks(quality))
    if "model_condition" in quality:  # for information: a model's own basis may be collinear by design
        print(f"{'model regressors, condition':34s} {quality['model_condition']:10.4g}  (information, not a check)")
    for message in quality.get("weak", []):
        print(f"warning: weak fit accepted (--accept-weak-fit): {message}")
    if "bias_step" in quality:
        step = quality["bias_step"]
        print(
            f"{'bias step test (largest step)':34s} {step['step_dph']:+10.4f} deg/h at minute {step['minute']} of "
            f"{step['capture']}, {100 * step['share']:.0f} % of the temperature terms' residual"
        )
        warning = bias_step_warning(step, temperature_channels)
        if warning:
            print(f"warning: {warning}")


_FLAGS = ROW_COLUMNS.index("flags")  # a compensate row's flags


def cmd_compensate(args: argparse.Namespace) -> int:
    out = Path(args.out)
    sidecar = csv_sidecar_path(out)
    inputs = [args.capture, args.model]
    check_outputs([out, sidecar], force=args.force, inputs=inputs)
    if args.adapt_state is not None:
        _check_adapt_state(
            Path(args.adapt_state),
            save=args.adapt_reference is not None or args.table_log is not None,
            inputs=inputs + [out, sidecar],
        )
    if args.table_log is not None and args.adapt_reference is not None:
        raise UsageError(
            "--table-log and --adapt-reference are two signals to adapt from: give one (--table-log learns from "
            "the table's angles, --adapt-reference from a declared rate)"
        )
    dwells = None if args.table_log is None else read_table_log(args.table_log)
    sidecar_doc = read_provenance(args.capture)
    events = control_events(sidecar_doc, args.capture)  # a daemon capture: the operator's commands, replayed
    if dwells is not None and any(e.kind == "table" for e in events):
        raise UsageError(
            f"{args.capture}: its sidecar holds the daemon's ?TABLE dwells, which are replayed; --table-log would "
            f"give the table's angles twice"
        )
    model_file = load_model(args.model)
    size = _capture_size(Path(args.capture))
    adapt = None
    if args.adapt_reference is not None or args.adapt_state is not None or dwells is not None or events:
        adapt = AdaptConfig()
    adapting = args.adapt_reference is not None or args.table_log is not None  # the state is saved at the end
    if args.adapt_state is not None and not adapting and not Path(args.adapt_state).exists():
        raise InputFileError(
            f"{args.adapt_state}: no such adaptation state (without --adapt-reference or --table-log it is only read)"
        )
    checked = check_model(
        model_file, args.capture, model_name=args.model, force_model=args.force_model, wire_format=args.format
    )
    if checked.warning:
        print(f"warning: {checked.warning}", file=sys.stderr)
    for line in model_file.warnings(args.model):
        print(f"warning: {line}")
    provenance = _compensate_provenance(args, model_file, checked.capture_serial)  # the state file before it is saved
    capture_sha = hashlib.sha256()
    progress = Progress()
    written = 0
    extrapolating_s, last_t_s = 0.0, 0.0
    done: list[Compensator] = []
    try:
        with out.open("w", encoding="ascii") as f:
            f.write(",".join(ROW_COLUMNS) + "\n")
            chunks = compensate_capture(
                args.capture,
                model_file,
                force_model=args.force_model,
                model_name=args.model,
                adapt=adapt,
                reference_rate_dph=args.adapt_reference,
                adapt_state=args.adapt_state,
                save_adapt_state=adapting,
                scale_override_arcsec_per_count=args.scale_override,
                wire_format=args.format,
                progress=lambda done: progress.show(f"compensating {100.0 * done / size:5.1f} %"),
                on_block=capture_sha.update,
                table_dwells=dwells,
                on_done=done.append,
                events=list(events),
            )
            for row in compensated_rows(chunks, args.every):
                f.write(format_row(row) + "\n")
                written += 1
                extrapolating_s += row[0] - last_t_s if "extrapolating" in row[_FLAGS].split("|") else 0.0
                last_t_s = row[0]
        provenance["capture"]["sha256"] = capture_sha.hexdigest()
        provenance.update(rows=written, extrapolating_s=round(float(extrapolating_s), 3))
        if args.table_log is not None:
            table = check_table_log_used(done[0], args.table_log, args.capture)
            provenance["table"] = table.summary()  # plain values
        if checked.warning:
            provenance["warnings"] = [checked.warning]
        write_csv_provenance(out, provenance)
    except (FogDriverError, OSError) as exc:
        out.unlink(missing_ok=True)
        sidecar.unlink(missing_ok=True)  # never a sidecar describing a CSV that is not there
        if isinstance(exc, FogDriverError):
            raise
        raise write_error(out, "the compensated CSV", exc) from None
    finally:
        progress.clear()
    print(
        f"compensated {args.capture} with {args.model} ({model_file.kind}): {written:,} rows every "
        f"{args.every:g} s -> {out} (provenance in {sidecar.name})"
    )
    if events:
        kinds = ", ".join(
            f"{sum(e.kind == k for e in events)} {k}" for k in REPLAYED if any(e.kind == k for e in events)
        )
        print(f"replayed the daemon's control events where they took effect: {kinds}")
    for missing in unreplayed(sidecar_doc, args.capture):
        print(f"warning: the capture's sidecar has {missing}: these rows are not what the daemon published after them")
    if args.table_log is not None or any(e.kind == "table" for e in events):
        for line in table_summary_lines(done[0]):
            print(line)
    if extrapolating_s > 0:
        print(
            f"warning: the model extrapolated for {extrapolating_s / 60:.1f} of {last_t_s / 60:.1f} min (rows flagged "
            f"extrapolating): the capture's inputs left the range it was fitted on, or its estimate was clipped"
        )
    return 0


def _file_sha256(path: str | Path) -> str:
    """The SHA-256 of a whole (small) file: a model, an adaptation state, a table log (a regular file of at most
    ``MAX_YAML_BYTES``, the largest of their limits; else a one-line error)."""
    return file_sha256(path, "file", MAX_YAML_BYTES)


def _compensate_provenance(args: argparse.Namespace, model_file, capture_serial: str | None) -> dict:
    """The CSV's provenance sidecar, as known before the run (the capture's SHA-256 and the rows come after):
    the capture, the model (path, SHA-256, serial), and the settings, named as the daemon's sidecar names them
    so that the daemon's run and this one can be compared key by key."""
    state = args.adapt_state
    return {
        "written_utc": utc_now_iso(),
        "fog_driver_version": __version__,
        "capture": {"path": str(args.capture), "sha256": None, "instrument_serial": capture_serial},
        "model": {
            "path": str(args.model),
            "sha256": _file_sha256(args.model),
            "kind": model_file.kind,
            "created_utc": model_file.created_utc,
            "instrument_serial": model_file.instrument_serial,
        },
        "settings": {
            "every_s": args.every,
            "format": args.format,
            "scale_override_arcsec_per_count": args.scale_override,
            "force_model": args.force_model,
            "adapt_reference_dph": args.adapt_reference,
            "adapt_state": state,
            "adapt_state_sha256": _file_sha256(state) if state is not None and Path(state).is_file() else None,
            "table_log": args.table_log,
            "table_log_sha256": _file_sha256(args.table_log) if args.table_log is not None else None,
        },
    }


def _check_adapt_state(path: Path, *, save: bool, inputs: list) -> None:
    """``compensate --adapt-state``: read when it exists, and (``save``) replaced at the end, so an existing
    file must be an adaptation state (by its content: ``modelfiles.not_a_state_file``, as the daemon's
    ``adapt_state``), and its directory must exist."""
    if save:
        refuse_captures([path])  # a capture is never replaced, whatever it is called
    if (kind := not_a_state_file(path)) not in (None, "a directory"):
        raise OutputFileError(
            f"{path}: --adapt-state exists and is {kind}, not an adaptation state; refusing to read or replace it"
        )
    if save:
        check_outputs([path], force=True, inputs=inputs)
    elif path.is_dir():
        raise InputFileError(f"{path}: is a directory, not an adaptation state")


def _read(value: float | None, fmt: str) -> str:
    """A read point for printing: the number, or "not reached"."""
    return "not reached" if value is None else format(value, fmt)


def cmd_evaluate(args: argparse.Namespace) -> int:
    require_extra("report", "evaluate's report (Allan deviation, plots)")
    out = Path(args.out)
    check_outputs(directories=[out], force=args.force)
    model_file = load_model(args.model)
    for line in model_file.warnings(args.model):
        print(f"warning: {line}", file=sys.stderr if args.json else sys.stdout)  # --json: stdout is the summary
    truth = None
    if args.truth:
        truth = read_truth(args.truth)
        check_truth_matches(truth, args.truth, args.capture)
    stops = read_table_log(args.reference) if args.reference else None
    label = model_label(args.model, model_file)
    compare = {}
    for path in args.compare:
        other = load_model(path)
        name = model_label(path, other)
        while name in compare or name in (label, "raw", "compensated"):
            name += "'"
        compare[name] = other
    if out.is_dir():  # --force: the report's files replace files of those names, never a capture
        refuse_captures(out / name for name in report_file_names(list(compare)))
    capture_serial = None
    facts = capture_facts(args.capture, args.format)  # read once for every model
    for path, model in [(args.model, model_file), *zip(args.compare, compare.values())]:
        checked = check_model(model, args.capture, model_name=path, force_model=args.force_model, facts=facts)
        capture_serial = checked.capture_serial
        if checked.warning:
            print(f"warning: {checked.warning}", file=sys.stderr)
    progress = Progress()
    progress.show("evaluating...", force=True)
    try:
        summary, series, allans = evaluate(
            Path(args.capture),
            model_file,
            truth=truth,
            force_model=args.force_model,
            capture_serial=capture_serial,
            label=label,
            compare=compare,
            progress=progress.show,
            wire_format=args.format,
        )
        span_s = float(series.t_s[-1])
        if truth is not None:
            check_truth_matches(truth, args.truth, args.capture, span_s=span_s)
        if stops is not None:
            positioning.check_stops_within(stops, span_s, args.reference, args.capture)
        progress.show("evaluating: positioning table", force=True)
        positioning_md = positioning.report_for(
            args.capture,
            model_file,
            summary,
            reference=args.reference,
            compare=compare,
            zero_window_s=args.zero_window,
            force_model=args.force_model,
            label=label,
            wire_format=args.format,
        )
        progress.show("evaluating: writing the report", force=True)
        try:
            report = write_report(out, summary, series, allans, positioning_md)
        except OSError as exc:
            raise write_error(out, "the report", exc) from None
    finally:
        progress.clear()
    for warning in summary["warnings"]:
        print(f"warning: {warning}", file=sys.stderr)
    if args.json:
        print(json.dumps(summary))
    else:
        print(f"report: {report}  (summary.json, allan-*.csv and PNG plots beside it)")
        for name in series_names(summary)[1:]:
            a, b = summary["raw"], summary[name]
            print(
                f"{summary['model']['label'] if name == 'compensated' else name}: "
                f"ARW {_read(a['arw_deg_per_rt_h'], '.5f')} -> "
                f"{_read(b['arw_deg_per_rt_h'], '.5f')} deg/sqrt(h); bias instability "
                f"{format_bias_instability(a)} -> {format_bias_instability(b)}; 1-min drift RMS "
                f"{a['drift_rms_1min_dph']:.4f} -> {b['drift_rms_1min_dph']:.4f} deg/h"
            )
        if "truth" in summary:
            print(format_coverage(summary["truth"]["sigma"]))
        if summary["extrapolating_seconds"]:
            print(
                f"warning: the model extrapolated for {summary['extrapolating_seconds'] / 60:.1f} of "
                f"{summary['seconds'] / 60:.1f} min (inputs outside its fit range, or its estimate clipped)"
            )
    return 0


def _format_option(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--format",
        default="auto",
        choices=["auto", *FORMATS],
        metavar="FORMAT",
        help=f"the capture's frame format: {', '.join(['auto', *FORMATS])} (default auto: the sidecar's, "
        f"else sniffed from the first bytes); a format the bytes contradict is an error",
    )


def _force_model_option(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--force-model",
        action="store_true",
        help="apply a model fitted for another instrument serial than the capture's (the daemon's force_model): "
        "warned on stderr and recorded in the outputs",
    )


def add_fit(p: argparse.ArgumentParser) -> None:
    """``fog-driver fit``: its arguments, the model kinds below them, and its function."""
    kinds = (
        [DEFAULT_FIT_KIND]
        + [k for k in KIND_HELP if k != DEFAULT_FIT_KIND]
        + [k for k in FITTERS if k not in KIND_HELP]
    )
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.epilog = "model kinds (--kind):\n" + "\n".join(f"  {k:11s} {KIND_HELP.get(k, '')}" for k in kinds)
    p.add_argument("captures", nargs="+", metavar="CAPTURE.bin")
    p.add_argument("--out", required=True, metavar="MODEL.yaml")
    p.add_argument(
        "--kind",
        default=None,
        choices=kinds,
        metavar="KIND",
        help=f"{', '.join(kinds)} (below; default: {DEFAULT_FIT_KIND}, or the polynomial when the "
        f"{DEFAULT_FIT_KIND} does worse on the fit's own validation split)",
    )
    p.add_argument("--config", metavar="CONFIG.yaml", help="fit settings (see configs/fit.yaml)")
    p.add_argument(
        "--validate",
        action="append",
        default=[],
        metavar="CAPTURE.bin",
        help="a held-out capture to report on (repeatable)",
    )
    p.add_argument(
        "--profile",
        action="append",
        default=[],
        metavar="NAME_OR_YAML",
        help="the chamber program the fit captures ran, for captures whose sidecar records none (a recording made "
        "by hand): a built-in profile's name or a profile file, as simulate --profile takes; once for every "
        "capture, or once per capture in order.  The fit judges what it leaves unidentified",
    )
    p.add_argument("--force", action="store_true", help="overwrite an existing model file")
    p.add_argument(
        "--accept-weak-fit",
        action="store_true",
        help="write the model even when its data fail the fit's checks (too short, too little "
        "temperature range, ...); the model file records it",
    )
    _format_option(p)
    p.set_defaults(func=cmd_fit)


def add_compensate(p: argparse.ArgumentParser) -> None:
    """``fog-driver compensate``: its arguments and its function."""
    p.add_argument("capture", metavar="CAPTURE.bin")
    p.add_argument("--model", required=True, metavar="MODEL.yaml")
    p.add_argument("--out", required=True, metavar="OUT.csv")
    p.add_argument("--every", type=period_s, default=1.0, metavar="SECONDS", help="row period (default 1 s)")
    p.add_argument("--force", action="store_true", help="overwrite OUT.csv and its sidecar OUT.csv.yaml")
    _force_model_option(p)
    p.add_argument(
        "--adapt-reference",
        type=finite_float,
        metavar="DPH",
        help="adapt the weights online, against this known input rate while the table is static "
        "(deg/h; 0 for a table at rest: Earth rate and bias are captured first)",
    )
    p.add_argument(
        "--table-log",
        metavar="STOPS.csv",
        help="adapt the weights online from the table's angles at its dwells (the stops CSV evaluate reads: "
        "t_start_s,t_end_s,angle_deg[,angle_end_deg]); learns the scale factor too.  Not with --adapt-reference",
    )
    p.add_argument(
        "--adapt-state",
        metavar="STATE.yaml",
        help="restore the adaptation state from here (with --adapt-reference: if it exists, and save it "
        "at the end; without: its adapted weights give the estimate, as in a daemon that restored it)",
    )
    p.add_argument(
        "--scale-override",
        type=scale_arcsec_per_count,
        metavar="ARCSEC_PER_COUNT",
        help="use this scale factor whatever the IDENTITY frames say (the daemon's scale_override_arcsec_per_count)",
    )
    _format_option(p)
    p.set_defaults(func=cmd_compensate)


def add_evaluate(p: argparse.ArgumentParser) -> None:
    """``fog-driver evaluate``: its arguments and its function."""
    p.add_argument("capture", metavar="CAPTURE.bin")
    p.add_argument("--model", required=True, metavar="MODEL.yaml")
    p.add_argument("--out", required=True, metavar="DIR", help="the report folder (report.md, summary.json, PNGs)")
    p.add_argument("--truth", metavar="TRUTH.csv", help="a simulator truth file: score against the true drift")
    p.add_argument(
        "--reference", metavar="STOPS.csv", help="reference positioning stops (see the docs: reference/commands)"
    )
    p.add_argument(
        "--compare",
        action="append",
        default=[],
        metavar="MODEL.yaml",
        help="another model to evaluate beside MODEL: its drift RMS, Allan curve and positioning column, "
        "labelled by file stem and kind (repeatable)",
    )
    p.add_argument(
        "--zero-window",
        type=time_window,
        metavar="START:END",
        help="zero every method over this device-time window, seconds from the first sample "
        "(default: the first 300 s of compensated output)",
    )
    p.add_argument("--json", action="store_true", help="also print summary.json on stdout")
    p.add_argument("--force", action="store_true", help="write into a report folder that is not empty")
    _force_model_option(p)
    _format_option(p)
    p.set_defaults(func=cmd_evaluate)
