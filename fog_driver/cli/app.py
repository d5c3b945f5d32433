"""The ``fog-driver`` command line: thin subcommands that parse, call the library, and print.

Errors the user can act on are printed as one line on stderr with a non-zero
exit status (see ``fog_driver.errors``); they never show a traceback.  Any other
exception is a bug: one line ``fog-driver: error: internal error: <type>: <message>``,
exit 70 (EX_SOFTWARE), and its traceback in the log on stderr.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import sys
import threading
from collections.abc import Sequence
from pathlib import Path

import structlog

from .. import __version__
from ..console import LOG_FORMATS, Progress, configure_logging
from ..errors import FogDriverError, InputFileError, InternalError, OutputFileError, UsageError
from ..files.outputs import check_outputs, write_error
from ..samples.captures import format_summary, inspect_capture
from ..signals import SignalDispatcher, stop_on_signals

EXIT_PROBLEMS = 1  # inspect --strict found problems


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be > 0: {text!r}")
    return value


def _baud(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer baud rate: {text!r}") from None
    if not 50 <= value <= 12_000_000:
        raise argparse.ArgumentTypeError(f"baud rate out of range: {value}")
    return value


def cmd_inspect(args: argparse.Namespace) -> int:
    from ..samples.sources import PROTOCOL_V1, capture_format

    other, doc = PROTOCOL_V1, {}
    if args.format != PROTOCOL_V1 and os.path.isfile(args.capture) and os.access(args.capture, os.R_OK):
        other, doc = capture_format(args.capture, args.format)  # (an unreadable file: inspect's own words below)
    if other != PROTOCOL_V1:  # without a sidecar too: inspect is how one finds out what a capture holds
        from ..formats.summary import format_format_summary, summarize_format

        settings = doc.get("wire_settings") if doc.get("wire_format") == other else None
        settings = settings if isinstance(settings, dict) else {}
        try:
            found = summarize_format(args.capture, other, settings if isinstance(settings, dict) else {})
        except (TypeError, ValueError) as exc:  # wire_settings the decoder cannot take
            raise InputFileError(f"{args.capture}: its sidecar's wire_settings do not fit {other}: {exc}") from None
        print(json.dumps(found.as_json_dict()) if args.json else format_format_summary(found))
        return EXIT_PROBLEMS if args.strict and found.problems() else 0
    progress = Progress()
    try:
        summary = inspect_capture(args.capture, progress=progress.bytes_done)
    finally:
        progress.clear()
    if args.json:
        print(json.dumps(summary.as_json_dict(), sort_keys=False))
    else:
        print(format_summary(summary))
    if args.strict and summary.problems:
        return EXIT_PROBLEMS
    return 0


def _record_wire(config_path: str | None, fmt: str | None):
    """What ``record [--config FILE] [--format NAME]`` says the port sends, and the device's setup commands
    (None, None: protocol v1, no setup)."""
    from ..daemon.config import DriverConfig, load_config

    if config_path is None and fmt in (None, "fog-v1"):
        return None, None
    config = load_config(config_path) if config_path else DriverConfig()
    name = fmt or config.format
    if name == "auto":
        raise UsageError(
            f"{config_path}: format auto: record needs the format the port sends (--format, or format: in the config)"
        )
    try:
        wire = config.wire_settings(name)
    except ValueError as exc:
        raise UsageError(
            f"record --format {name}: {exc} (--config FILE with a device: section: see configs/kvh-dsp1750.yaml)"
        ) from None
    return wire, config.device.device_setup()


def cmd_record(args: argparse.Namespace) -> int:
    from ..samples.record import record  # imports the transport (pyserial) only when needed

    if not args.out.endswith(".bin"):
        raise UsageError(f"--out {args.out!r}: a capture file name must end in .bin")
    wire, setup = _record_wire(args.config, args.format)
    progress = Progress()
    stop = threading.Event()

    def on_progress(p) -> None:
        c = p.counters
        target = (
            f" / {args.duration:g} s ({max(args.duration - p.elapsed_s, 0.0):.0f} s left)" if args.duration else " s"
        )
        progress.show(
            f"recording {p.elapsed_s:7.1f}{target}  {p.bytes_written:,} bytes  {c.sample_frames:,} frames  "
            f"{c.crc_errors} CRC errors  {c.missing_frames} missing  port {p.port_state}"
        )

    waiting_said = False

    def on_state(event) -> None:
        # The transport logs every state change (warnings on stderr by default); keep the
        # progress line from running into those log lines.
        nonlocal waiting_said
        progress.clear()
        if args.wait and event.state == "retry_wait" and not waiting_said:  # said once; -v shows each try
            waiting_said = True
            now = event.detail.removeprefix(f"cannot open {args.port}: ")
            print(f"waiting for {args.port} to appear (now: {now}); Ctrl-C to stop", file=sys.stderr, flush=True)

    try:
        with stop_on_signals(stop):
            result = record(
                args.port,
                args.out,
                baudrate=args.baud,
                duration_s=args.duration,
                reconnect=not args.no_reconnect,
                stop=stop,
                on_progress=on_progress,
                on_state=on_state,
                notes=args.notes,
                overwrite=args.force,
                wait=args.wait,
                wire=wire,
                setup=setup,
            )
    finally:
        progress.clear()
    c = result.counters
    print(
        f"recorded {result.bytes_written:,} bytes in {result.elapsed_s:.1f} s to {result.path} "
        f"({c.sample_frames:,} sample frames, {c.crc_errors} CRC errors, {c.missing_frames} missing); "
        f"provenance in {result.sidecar}"
    )
    return 0


def _rate_hz(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer rate: {text!r}") from None
    if not 1 <= value <= 0xFFFF:
        raise argparse.ArgumentTypeError(f"rate must be 1..65535 Hz (a u16 on the wire): {value}")
    return value


def _seed(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer seed: {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"seed must be >= 0: {value}")
    return value


def _instrument_seed(text: str) -> int:
    from ..sim.population import MAX_INSTRUMENT_SEED

    value = _seed(text)
    if value > MAX_INSTRUMENT_SEED:
        raise argparse.ArgumentTypeError(f"instrument seed must be 0..{MAX_INSTRUMENT_SEED}: {value}")
    return value


def _simulator(args: argparse.Namespace):
    from ..sim.faults import parse_fault_spec
    from ..sim.instrument import Simulator, load_instrument_config
    from ..sim.population import draw_instrument
    from ..sim.profiles import load_profile

    profile = load_profile(args.profile)
    config = load_instrument_config(args.instrument)
    if args.instrument_seed is not None:
        config = draw_instrument(args.instrument_seed, config)
    faults = parse_fault_spec(args.faults)
    return Simulator(
        profile, config, rate_hz=args.rate_hz, seed=args.seed, faults=faults, wire_format=args.format
    ), faults


def cmd_simulate(args: argparse.Namespace) -> int:
    if (args.out is None) == (args.serve is None):
        raise UsageError("give exactly one of --out CAPTURE.bin (write a capture) or --serve pty|DEVICE (stream live)")
    sim, faults = _simulator(args)
    if args.serve is not None:
        from ..sim.serve import serve_cli

        return serve_cli(sim, args)
    from ..sim.capture import simulate_to_file

    if not args.out.endswith(".bin"):
        raise UsageError(f"--out {args.out!r}: a capture file name must end in .bin")
    progress = Progress()
    try:
        result = simulate_to_file(
            sim,
            args.out,
            duration_s=args.duration,
            overwrite=args.force,
            progress=lambda done, total: progress.show(f"simulating {100.0 * done / total:5.1f} % ({done:,} frames)"),
            faults_text=faults.describe(),
        )
    finally:
        progress.clear()
    print(
        f"simulated {sim.profile.name} at {sim.rate_hz} Hz, seed {sim.seed}: {result.frames:,} frames, "
        f"{result.bytes:,} bytes -> {result.capture} (+ {result.sidecar.name}, {result.truth.name})"
    )
    return 0


#: What ``fog-driver fit`` fits without ``--kind``: the project's best model (README, "Accuracy").
DEFAULT_FIT_KIND = "wesn"


def _print_fit_report(report) -> None:
    """The fit's table, its noise-floor line, and a warning (with the fit's other warnings, on stdout: stderr
    keeps the one-line error of a refused fit) for each model row that leaves more drift than no compensation
    (marked in the table)."""
    from ..compensation.fitting.report import WORSE_MARKER

    print(report.format())
    note = report.floor_note()
    if note:
        print(f"note: {note}")
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
    from ..compensation.fitting.quality import format_checks
    from ..files.yamlio import dataclass_from_mapping, read_yaml
    from ..modelfiles import save_model
    from ..offline.fit import FitConfig, WeakFitError, fit_model_file

    out = Path(args.out)
    check_outputs([out], force=args.force, inputs=[*args.captures, *args.validate, *filter(None, [args.config])])
    if args.kind == "pso-svr":
        from ..extras import require_extra

        require_extra("svr", "fitting a pso-svr model")
    config = FitConfig()
    if args.config:
        config = dataclass_from_mapping(FitConfig, read_yaml(args.config, "fit config") or {}, args.config)
    kind = args.kind or DEFAULT_FIT_KIND
    default = (
        " (the default kind: the polynomial is saved instead if the wesn does worse on its own validation "
        "split; --kind chooses)"
        if args.kind is None
        else ""
    )
    print(f"fitting a {kind} model{default}", flush=True)
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
        for note in selection.get("limits", []):
            print(f"note: {note}")
        for key in ("warning", "warning_validation"):
            if key in selection:
                print(f"warning: {selection[key]}")
    if "fell_back" in provenance:
        print(f"note: {provenance['fell_back']}")
    _print_fit_report(report)
    quality = provenance["fit_quality"]
    print(format_checks(quality))
    if "model_condition" in quality:  # for information: a model's own basis may be collinear by design
        print(f"{'model regressors, condition':34s} {quality['model_condition']:10.4g}  (information, not a check)")
    for message in quality.get("weak", []):
        print(f"warning: weak fit accepted (--accept-weak-fit): {message}")
    if "bias_step" in quality:
        from ..compensation.fitting.fit import bias_step_warning

        step = quality["bias_step"]
        print(
            f"{'bias step test (largest step)':34s} {step['step_dph']:+10.4f} deg/h at minute {step['minute']} of "
            f"{step['capture']}, {100 * step['share']:.0f} % of the temperature terms' residual"
        )
        warning = bias_step_warning(step, len(model_file.temperature_channels))
        if warning:
            print(f"warning: {warning}")
    print(
        f"the model's input box and estimate bound (+-{model_file.domain.estimate_limit_dph:.3g} deg/h) are in "
        f"the file: outside them its estimate is flagged extrapolating"
    )
    return 0


def cmd_compensate(args: argparse.Namespace) -> int:
    from ..modelfiles import load_model
    from ..offline.compensate import compensate_capture
    from ..offline.rows import ROW_COLUMNS, compensated_rows, format_row
    from ..samples.captures import _capture_size

    out = Path(args.out)
    inputs = [args.capture, args.model]
    check_outputs([out], force=args.force, inputs=inputs)
    if args.adapt_state is not None:
        _check_adapt_state(Path(args.adapt_state), save=args.adapt_reference is not None, inputs=inputs + [out])
    model_file = load_model(args.model)
    size = _capture_size(Path(args.capture))
    adapt = None
    if args.adapt_reference is not None or args.adapt_state is not None:
        from ..compensation.adapt import AdaptConfig

        adapt = AdaptConfig()
    if args.adapt_state is not None and args.adapt_reference is None and not Path(args.adapt_state).exists():
        raise InputFileError(
            f"{args.adapt_state}: no such adaptation state (without --adapt-reference it is only read)"
        )
    for line in model_file.warnings(args.model):
        print(f"warning: {line}")
    progress = Progress()
    written = 0
    extrapolating_s, last_t_s = 0.0, 0.0
    try:
        with out.open("w", encoding="ascii") as f:
            f.write(",".join(ROW_COLUMNS) + "\n")
            chunks = compensate_capture(
                args.capture,
                model_file,
                force=args.force,
                model_name=args.model,
                adapt=adapt,
                reference_rate_dph=args.adapt_reference,
                adapt_state=args.adapt_state,
                save_adapt_state=args.adapt_reference is not None,
                scale_override_arcsec_per_count=args.scale_override,
                wire_format=args.format,
                progress=lambda done: progress.show(f"compensating {100.0 * done / size:5.1f} %"),
            )
            for row in compensated_rows(chunks, args.every):
                f.write(format_row(row) + "\n")
                written += 1
                extrapolating_s += row[0] - last_t_s if "extrapolating" in row[-1].split("|") else 0.0
                last_t_s = row[0]
    except (FogDriverError, OSError) as exc:
        out.unlink(missing_ok=True)
        if isinstance(exc, FogDriverError):
            raise
        raise write_error(out, "the compensated CSV", exc) from None
    finally:
        progress.clear()
    print(
        f"compensated {args.capture} with {args.model} ({model_file.kind}): {written:,} rows every "
        f"{args.every:g} s -> {out}"
    )
    if extrapolating_s > 0:
        print(
            f"warning: the model extrapolated for {extrapolating_s / 60:.1f} of {last_t_s / 60:.1f} min (rows flagged "
            f"extrapolating): the capture's inputs left the range it was fitted on, or its estimate was clipped"
        )
    return 0


def _check_adapt_state(path: Path, *, save: bool, inputs: list) -> None:
    """``compensate --adapt-state``: read when it exists, and (``save``) replaced at the end, so an existing
    file must be an adaptation state (by its content), and its directory must exist."""
    from ..files.outputs import describe

    if path.exists() and not path.is_dir() and (kind := describe(path)) != "an adaptation state":
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
    from ..extras import require_extra
    from ..modelfiles import load_model
    from ..report import positioning
    from ..report.evaluate import evaluate, format_bias_instability, model_label, series_names, write_report
    from ..sim.capture import check_truth_matches, read_truth

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
    stops = positioning.read_reference_csv(args.reference) if args.reference else None
    label = model_label(args.model, model_file)
    compare = {}
    for path in args.compare:
        other = load_model(path)
        name = model_label(path, other)
        while name in compare or name in (label, "raw", "compensated"):
            name += "'"
        compare[name] = other
    progress = Progress()
    progress.show("evaluating...", force=True)
    try:
        summary, series, allans = evaluate(
            Path(args.capture),
            model_file,
            truth=truth,
            force=args.force,
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
            force=args.force,
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
        if summary["extrapolating_seconds"]:
            print(
                f"warning: the model extrapolated for {summary['extrapolating_seconds'] / 60:.1f} of "
                f"{summary['seconds'] / 60:.1f} min (inputs outside its fit range, or its estimate clipped)"
            )
    return 0


def _time_window(text: str) -> tuple[float, float]:
    """``START:END`` in seconds, 0 <= START < END, both finite."""
    start, sep, end = text.partition(":")
    try:
        window = (float(start), float(end))
    except ValueError:
        window = None
    if not sep or window is None or not all(math.isfinite(x) for x in window) or not 0 <= window[0] < window[1]:
        raise argparse.ArgumentTypeError(f"expected START:END in seconds with 0 <= START < END: {text!r}")
    return window


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1: {text!r}")
    return value


def cmd_watch(args: argparse.Namespace) -> int:
    from ..tools.watch import watch_command

    previous = signal.signal(signal.SIGTERM, signal.default_int_handler)  # SIGTERM ends it as Ctrl-C does
    try:
        return watch_command(
            args.connect or args.address,
            rate_hz=args.rate_hz,
            count=args.count,
            duration_s=args.duration,
            json_lines=args.json,
            token_file=args.token_file,
        )
    finally:
        signal.signal(signal.SIGTERM, previous)


def cmd_ctl(args: argparse.Namespace) -> int:
    from ..tools.ctl import ctl_command

    return ctl_command(
        args.ctl_command,
        args.ctl_args,
        address=args.connect,
        token_file=args.token_file,
        json_out=args.json,
        reference_dph=args.reference_dph,
        timeout_s=args.timeout,
    )


def cmd_run(args: argparse.Namespace) -> int:
    import dataclasses

    from ..daemon.config import DriverConfig, load_config
    from ..daemon.service import ConfigError, Service
    from ..tools.watch import format_address

    # A service logs JSON lines to journald or a pipe (per-second summaries); at a terminal it is quiet.
    configure_logging(args.verbose, args.log_format, service=True)
    _never_world_writable()

    def read_config() -> DriverConfig:
        config = load_config(args.config) if args.config else DriverConfig()
        overrides = {
            k: getattr(args, k)
            for k in ("port", "model", "listen", "http", "capture_dir", "format")
            if getattr(args, k)
        }
        return dataclasses.replace(config, **overrides)

    try:
        config = read_config()
    except (FogDriverError, ValueError) as exc:
        raise ConfigError(str(exc)) from None
    stop = threading.Event()
    simulator = None
    port = config.port
    if args.simulate or (port is None and _stdin_is_a_terminal()):
        simulator, port = _start_embedded_simulator(stop)
    elif port is None:  # under systemd, or piped: a production daemon never falls back to a simulator
        where = f" in {args.config}" if args.config else ""
        raise ConfigError(
            f"no instrument port: set 'port'{where} or give --port PORT_OR_URL "
            "(--simulate runs the built-in simulated instrument)"
        )
    try:
        service = Service(config, port=port)
        service.stop = stop
        host, listen_port = service.start()  # a listen address in use: TemporaryFailure, exit 75 (restarted)
    except BaseException:
        if simulator is not None:  # a failed start leaves no simulator behind (nor a link: it has none)
            stop.set()
            simulator.join(timeout=10)
        raise

    def on_signal(signum: int) -> None:
        """In the signal dispatcher's thread: a reload never runs inside a handler, nor twice at once."""
        if signum == signal.SIGHUP:  # reload the config file and the model, without stopping
            try:
                service.reload_config(read_config())
            except (FogDriverError, ValueError) as exc:  # keep running with what is in use
                structlog.get_logger("fog_driver.daemon").error("config_reload_failed", reason=str(exc))
            return
        stop.set()

    try:
        with SignalDispatcher((signal.SIGINT, signal.SIGTERM, signal.SIGHUP), on_signal):
            # The readiness line comes after the handlers: a signal sent on seeing it is handled.
            address = format_address(host, listen_port)  # an IPv6 address in brackets: [::1]:2948
            web = "" if service.web is None else f"; web view on http://{format_address(*service.web.address)}/"
            print(
                f"fog-driver {__version__}: {port} -> listening on {address}{web}; raw capture in "
                f"{config.capture_dir}/; connect with: fog-driver watch {address}  (Ctrl-C to stop)",
                flush=True,
            )
            status = service.run_until_stopped()
    finally:
        if simulator is not None:
            simulator.join(timeout=10)
    if status != 0 and service.failure is not None and not isinstance(service.failure, FogDriverError):
        raise InternalError.from_exception(service.failure)  # the acquisition thread logged its traceback
    return status


def _never_world_writable() -> None:
    """Add 'others may not write' to the umask the daemon was given (even 0): no capture, sidecar or state
    file it creates is world-writable.  (The systemd unit sets ``UMask=0027``: group-readable only.)
    Call it before any thread starts: the umask is the whole process's."""
    os.umask(os.umask(0o022) | 0o002)


def _stdin_is_a_terminal() -> bool:
    """True when a person runs the command at a terminal (not under systemd, cron or a pipe)."""
    return sys.stdin is not None and sys.stdin.isatty()


def _start_embedded_simulator(stop: threading.Event) -> tuple[threading.Thread, str]:
    """The demonstration instrument: the simulator on a pty in this process (the paper profile)."""
    from ..sim.instrument import Simulator
    from ..sim.profiles import load_profile
    from ..sim.serve import serve_pty

    sim = Simulator(load_profile("paper"), rate_hz=100, seed=0)
    ready = threading.Event()
    where: dict[str, str] = {}

    def on_ready(server) -> None:
        where["path"] = server.slave_path
        ready.set()

    def serve() -> None:
        try:
            serve_pty(sim, link=None, stop=stop, on_ready=on_ready)
        finally:
            ready.set()

    thread = threading.Thread(target=serve, name="simulator", daemon=True)
    thread.start()
    ready.wait(30)
    if "path" not in where:
        raise FogDriverError("the embedded simulator did not start")
    return thread, where["path"]


def _format_option(p: argparse.ArgumentParser) -> None:
    from ..formats.registry import FORMATS

    p.add_argument(
        "--format",
        default="auto",
        choices=["auto", *FORMATS],
        metavar="FORMAT",
        help=f"the capture's frame format: {', '.join(['auto', *FORMATS])} (default auto: the sidecar's, "
        f"else sniffed from the first bytes); a format the bytes contradict is an error",
    )


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="fog-driver",
        description="Fiber-optic-gyro instrument driver and temperature-drift compensator.",
    )
    parser.add_argument("--version", action="version", version=f"fog-driver {__version__}")
    # The logging options, before or after the command: `fog-driver -v run` and `fog-driver run -v`.
    logging_options = argparse.ArgumentParser(add_help=False)
    for where, default in ((parser, {"verbose": 0, "log_format": "auto"}), (logging_options, None)):
        where.add_argument(
            "-v",
            "--verbose",
            action="count",
            default=default["verbose"] if default else argparse.SUPPRESS,
            help="more log output on stderr (-v info, -vv debug)",
        )
        where.add_argument(
            "--log-format",
            choices=LOG_FORMATS,
            default=default["log_format"] if default else argparse.SUPPRESS,
            help="log lines for a person (human) or a machine (json); auto: human on a terminal, "
            "json elsewhere (journald, pipes)",
        )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    def add_parser(name: str, **kw) -> argparse.ArgumentParser:
        return sub.add_parser(name, parents=[logging_options], **kw)

    from ..formats.registry import FORMATS

    FORMAT_NAMES = list(FORMATS)
    p = add_parser("inspect", help="check a capture file and summarize what it holds")
    p.add_argument("capture", metavar="CAPTURE.bin")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of the text report")
    p.add_argument("--strict", action="store_true", help=f"exit {EXIT_PROBLEMS} when the capture is not clean")
    p.add_argument(
        "--format",
        default="auto",
        choices=["auto", *FORMAT_NAMES],
        help="the capture's frame format (default auto: sniffed from its first 64 kB)",
    )
    p.set_defaults(func=cmd_inspect)

    p = add_parser("record", help="record a port's raw bytes to a capture file with a provenance sidecar")
    p.add_argument("port", metavar="PORT_OR_URL", help="device path (/dev/ttyUSB0) or pyserial URL (replay://x.bin)")
    p.add_argument("--out", required=True, metavar="CAPTURE.bin")
    p.add_argument("--duration", type=_positive_float, metavar="S", help="stop after S seconds (host clock)")
    p.add_argument("--baud", type=_baud, default=460800, metavar="B", help="baud rate (default 460800)")
    p.add_argument("--no-reconnect", action="store_true", help="stop when the port is lost instead of reconnecting")
    p.add_argument(
        "--wait",
        action="store_true",
        help="wait for a port that is not there yet (default: a port that does not open is an error at "
        "once; a port lost after it worked is always reopened, unless --no-reconnect)",
    )
    p.add_argument("--notes", help="free text stored in the provenance sidecar")
    p.add_argument("--force", action="store_true", help="overwrite an existing capture file")
    p.add_argument(
        "--config",
        metavar="FILE",
        help="a daemon config whose format, axis and device settings (rate, units, setup commands) "
        "say what the port sends: recorded in the sidecar (default: fog-v1)",
    )
    p.add_argument(
        "--format",
        choices=FORMAT_NAMES,
        metavar="FORMAT",
        help=f"the frame format the port sends ({', '.join(FORMAT_NAMES)}; default: the config's, "
        "else fog-v1); another than fog-v1 needs --config with its device settings",
    )
    p.set_defaults(func=cmd_record)

    from ..sim.instrument import WIRE_FORMATS

    p = add_parser("simulate", help="simulate the instrument: write a capture with its truth, or serve it live")
    p.add_argument(
        "--profile",
        default="paper",
        metavar="NAME_OR_YAML",
        help="a profile's name: built-in (paper, paper-validation) or a file's stem in configs/profiles/ "
        "(fast-ramps, positioning, ...); or a profile YAML file's path (default: paper)",
    )
    p.add_argument("--out", metavar="CAPTURE.bin", help="write the capture, its sidecar and CAPTURE.truth.csv")
    p.add_argument("--serve", metavar="pty|DEVICE", help="stream in real time on a new pty, or to a serial device")
    p.add_argument("--rate-hz", type=_rate_hz, default=100, metavar="R", help="SAMPLE frame rate (default 100)")
    p.add_argument("--seed", type=_seed, default=0, metavar="N", help="random seed (same seed, same bytes)")
    p.add_argument(
        "--format",
        default="fog-v1",
        choices=WIRE_FORMATS,
        help="the frames to send: fog-v1 (the instrument's own protocol, default), a KVH DSP-1750 "
        "normal-mode format (delta angles in rad, temperature in 0.01 degC) or ixblue-stdbin "
        "(STDBIN v5 telegrams: rotation rate in deg/s, attitude, the three thermometers in degC)",
    )
    p.add_argument(
        "--faults",
        default="none",
        metavar="SPEC",
        help="e.g. drop=1e-3,flip=1e-5,garbage=0.1,thermo=0.05:2,disconnect=60:2 (see README)",
    )
    p.add_argument(
        "--instrument", metavar="CONFIG.yaml", help="instrument model (default: configs/sim/instrument.yaml values)"
    )
    p.add_argument(
        "--instrument-seed",
        type=_instrument_seed,
        metavar="K",
        help="instrument K of the simulated population: its physics drawn from documented ranges",
    )
    p.add_argument("--duration", type=_positive_float, metavar="S", help="stop after S device seconds")
    p.add_argument("--force", action="store_true", help="overwrite an existing capture")
    p.add_argument(
        "--link", metavar="PATH", help="--serve pty: the stable symlink to the pty (default /tmp/fog-driver-sim.tty)"
    )
    p.add_argument(
        "--speed",
        type=_positive_float,
        default=1.0,
        metavar="X",
        help="--serve: run X times faster than real time (quick hardware-in-the-loop tests)",
    )
    p.add_argument("--baud", type=_baud, default=460800, metavar="B", help="--serve DEVICE: baud rate (default 460800)")
    p.set_defaults(func=cmd_simulate)

    from ..compensation.fitting.fit import FITTERS, KIND_HELP

    kinds = (
        [DEFAULT_FIT_KIND]
        + [k for k in KIND_HELP if k != DEFAULT_FIT_KIND]
        + [k for k in FITTERS if k not in KIND_HELP]
    )
    p = add_parser(
        "fit",
        help="fit a drift model to static chamber captures",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="model kinds (--kind):\n" + "\n".join(f"  {k:11s} {KIND_HELP.get(k, '')}" for k in kinds),
    )
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
    p.add_argument("--force", action="store_true", help="overwrite an existing model file")
    p.add_argument(
        "--accept-weak-fit",
        action="store_true",
        help="write the model even when its data fail the fit's checks (too short, too little "
        "temperature range, ...); the model file records it",
    )
    _format_option(p)
    p.set_defaults(func=cmd_fit)

    p = add_parser("compensate", help="apply a drift model to a capture; write a CSV row per period")
    p.add_argument("capture", metavar="CAPTURE.bin")
    p.add_argument("--model", required=True, metavar="MODEL.yaml")
    p.add_argument("--out", required=True, metavar="OUT.csv")
    p.add_argument("--every", type=_positive_float, default=1.0, metavar="SECONDS", help="row period (default 1 s)")
    p.add_argument(
        "--force", action="store_true", help="apply a model fitted for another instrument; overwrite OUT.csv"
    )
    p.add_argument(
        "--adapt-reference",
        type=float,
        metavar="DPH",
        help="adapt the weights online, against this known input rate while the table is static "
        "(deg/h; 0 for a table at rest: Earth rate and bias are captured first)",
    )
    p.add_argument(
        "--adapt-state",
        metavar="STATE.yaml",
        help="restore the adaptation state from here (with --adapt-reference: if it exists, and save it "
        "at the end; without: its adapted weights give the estimate, as in a daemon that restored it)",
    )
    p.add_argument(
        "--scale-override",
        type=_positive_float,
        metavar="ARCSEC_PER_COUNT",
        help="use this scale factor whatever the IDENTITY frames say (the daemon's scale_override_arcsec_per_count)",
    )
    _format_option(p)
    p.set_defaults(func=cmd_compensate)

    p = add_parser("run", help="the headless daemon: live compensation, publishing, control, raw capture")
    p.add_argument("--config", metavar="FILE", help="settings (configs/default.yaml lists them); flags override")
    instrument = p.add_mutually_exclusive_group()
    instrument.add_argument(
        "--port", metavar="PORT_OR_URL", help="the instrument's device path or URL (overrides 'port')"
    )
    instrument.add_argument(
        "--simulate",
        action="store_true",
        help="serve the built-in simulated instrument (a demonstration) instead of a port; the "
        "default on a terminal when no port is configured",
    )
    p.add_argument(
        "--model", metavar="MODEL.yaml", help="drift model (default: the shipped fog_driver/data/models/default.yaml)"
    )
    p.add_argument("--listen", metavar="HOST:PORT", help="where clients connect (default 127.0.0.1:2948)")
    p.add_argument(
        "--http",
        metavar="HOST:PORT",
        help="serve the web view and /metrics here (overrides 'http'; needs the web extra; e.g. 127.0.0.1:8948)",
    )
    p.add_argument("--capture-dir", dest="capture_dir", metavar="DIR", help="raw capture directory")
    p.add_argument(
        "--format",
        choices=["auto", *FORMAT_NAMES],
        metavar="FORMAT",
        help=f"the instrument's frame format (overrides 'format'; {', '.join(['auto', *FORMAT_NAMES])}); "
        "a format other than fog-v1 needs 'device' settings in the config",
    )
    p.set_defaults(func=cmd_run)

    p = add_parser("watch", help="live view of a running daemon (fog-driver run): angle, rate, temperatures, counters")
    p.add_argument(
        "address",
        nargs="?",
        metavar="HOST:PORT",
        help="the daemon's client address (default 127.0.0.1:2948; also HOST, :PORT, [IPV6]:PORT)",
    )
    p.add_argument(
        "--rate-hz",
        type=_positive_float,
        default=10.0,
        metavar="R",
        help="ANGLE updates a second to ask the daemon for (default 10)",
    )
    p.add_argument("--count", type=_positive_int, metavar="N", help="stop after N ANGLE updates")
    p.add_argument("--duration", type=_positive_float, metavar="S", help="stop after S seconds")
    p.add_argument("--connect", metavar="HOST:PORT", help="the daemon's client address (as the positional HOST:PORT)")
    p.add_argument(
        "--json",
        action="store_true",
        help="print the daemon's NDJSON lines unchanged, one per line, flushed (like gpspipe -w)",
    )
    p.add_argument(
        "--token-file",
        metavar="FILE",
        help="read the daemon's client token from FILE's first line (default: $FOG_DRIVER_TOKEN)",
    )
    p.set_defaults(func=cmd_watch)

    p = add_parser(
        "ctl",
        help="send one control command to a running daemon: zero, bias, adapt, reload, status, save",
        description="zero | bias [SECONDS] | adapt on|off | reload | status | save.  Exit 0 done; "
        "64 unknown to the daemon; 65 refused or the bias capture failed; 69 unreachable "
        "or the connection lost; 77 the token refused or needed.",
    )
    p.add_argument(
        "ctl_command",
        metavar="COMMAND",
        choices=["zero", "bias", "adapt", "reload", "status", "save"],
        help="zero, bias, adapt, reload, status or save",
    )
    p.add_argument("ctl_args", nargs="*", metavar="ARG", help="bias: SECONDS (default 60, 1..86400); adapt: on or off")
    p.add_argument(
        "--connect",
        metavar="HOST:PORT",
        help="the daemon's client address (default 127.0.0.1:2948; also HOST, :PORT, [IPV6]:PORT)",
    )
    p.add_argument(
        "--token-file",
        metavar="FILE",
        help="read the daemon's client token from FILE's first line (default: $FOG_DRIVER_TOKEN)",
    )
    p.add_argument(
        "--json", action="store_true", help="print the daemon's answer (and bias's result event) as JSON lines"
    )
    p.add_argument(
        "--reference-dph",
        type=float,
        metavar="DPH",
        help="adapt on: the known input rate while static (deg/h; default 0, a table at rest)",
    )
    p.add_argument(
        "--timeout",
        type=_positive_float,
        default=35.0,
        metavar="S",
        help="how long to wait for the answer (default 35 s; bias waits for its result besides)",
    )
    p.set_defaults(func=cmd_ctl)

    p = add_parser("evaluate", help="a report: Allan deviation, drift before and after, positioning accuracy, plots")
    p.add_argument("capture", metavar="CAPTURE.bin")
    p.add_argument("--model", required=True, metavar="MODEL.yaml")
    p.add_argument("--out", required=True, metavar="DIR", help="the report folder (report.md, summary.json, PNGs)")
    p.add_argument("--truth", metavar="TRUTH.csv", help="a simulator truth file: score against the true drift")
    p.add_argument("--reference", metavar="STOPS.csv", help="reference positioning stops (see the README)")
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
        type=_time_window,
        metavar="START:END",
        help="zero every method over this device-time window, seconds from the first sample "
        "(default: the first 300 s of compensated output)",
    )
    p.add_argument("--json", action="store_true", help="also print summary.json on stdout")
    p.add_argument("--force", action="store_true", help="overwrite the report folder; a model for another instrument")
    _format_option(p)
    p.set_defaults(func=cmd_evaluate)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    configure_logging(args.verbose, args.log_format)
    try:
        return args.func(args)
    except FogDriverError as exc:
        print(f"fog-driver: error: {exc}", file=sys.stderr)
        return exc.exit_status
    except KeyboardInterrupt:
        print("fog-driver: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        # The reader of our output went away (e.g. `| head`); nothing more to say.
        sys.stderr.close()
        return 0
    except Exception as exc:  # a bug: the traceback goes to the log, one line to the user, exit 70
        structlog.get_logger("fog_driver").exception("internal_error", command=args.command)
        error = InternalError.from_exception(exc)
        print(f"fog-driver: error: {error}", file=sys.stderr)
        return error.exit_status


if __name__ == "__main__":
    sys.exit(main())
