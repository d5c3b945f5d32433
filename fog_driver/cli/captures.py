"""``fog-driver inspect``, ``record`` and ``simulate``: the commands that read, write or make capture files."""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import threading

from ..client.display import Progress
from ..daemon.config import DriverConfig, load_config
from ..errors import InputFileError, UsageError
from ..extras import require_extra
from ..formats.registry import FORMATS
from ..formats.summary import format_format_summary, summarize_format
from ..lab.profiles import MAX_PROFILE_S, load_profile
from ..samples.captures import format_summary, inspect_capture
from ..samples.record import record
from ..samples.sources import PROTOCOL_V1, capture_format, wire_settings_for
from ..signals import stop_on_signals
from ..sim.capture import simulate_to_file
from ..sim.families import FAMILIES
from ..sim.faults import parse_fault_spec
from ..sim.instrument import WIRE_FORMATS, Simulator, load_instrument_config
from ..sim.population import MAX_INSTRUMENT_SEED, draw_instrument
from ..sim.serve import serve_cli
from ..transport import DEFAULT_SILENCE_S
from .argtypes import baud, positive_float, rate_hz, seed

EXIT_PROBLEMS = 1  # inspect --strict found problems
EXIT_INTERRUPTED = 130  # stopped by Ctrl-C (SIGINT) or SIGTERM, as the shell reports a SIGINT
FORMAT_NAMES = list(FORMATS)


#: The commands that read a capture of any frame format (``FORMATS``), each the same way: ``--format``
#: (``calibration._format_option``) and ``samples.sources.wire_settings_for`` (the device's settings from the capture's
#: sidecar).  ``inspect`` says so of a capture of another format than protocol v1 (``capture_use``).
CAPTURE_READERS = ("fit", "compensate", "evaluate")


def capture_use(path: str, fmt: str) -> str:
    """What ``CAPTURE_READERS`` do with the capture ``path`` of format ``fmt`` (not protocol v1), in words: they
    read it, a model applying to captures of its temperature channels; or why they cannot yet
    (``wire_settings_for``'s reason: no sidecar with the device's settings)."""
    commands = f"{', '.join(CAPTURE_READERS[:-1])} and {CAPTURE_READERS[-1]}"
    try:
        wire_settings_for(path, fmt)
    except InputFileError as exc:
        reason = str(exc).removeprefix(f"{path}: ")
        return f"{commands} read {fmt} captures, but not this one as it is: {reason}"
    channels = ", ".join(FORMATS[fmt].temperature_channels)
    return (
        f"{commands} read it (a model applies to captures of the temperature channels it was fitted on; "
        f"{fmt} has {channels})"
    )


def cmd_inspect(args: argparse.Namespace) -> int:
    other, doc = PROTOCOL_V1, {}
    if args.format != PROTOCOL_V1 and os.path.isfile(args.capture) and os.access(args.capture, os.R_OK):
        other, doc = capture_format(args.capture, args.format)  # (an unreadable file: inspect's own words below)
    if other != PROTOCOL_V1:  # without a sidecar too: inspect is how one finds out what a capture holds
        settings = doc.get("wire_settings") if doc.get("wire_format") == other else None
        settings = settings if isinstance(settings, dict) else {}
        try:
            found = summarize_format(args.capture, other, settings if isinstance(settings, dict) else {})
        except (TypeError, ValueError) as exc:  # wire_settings the decoder cannot take
            raise InputFileError(f"{args.capture}: its sidecar's wire_settings do not fit {other}: {exc}") from None
        print(
            json.dumps(found.as_json_dict())
            if args.json
            else format_format_summary(found, capture_use(args.capture, other))
        )
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


def _record_wire(config_path: str | None, config: DriverConfig | None, fmt: str | None):
    """What ``record [--config FILE] [--format NAME]`` says the port sends, and the device's setup commands
    (None, None: protocol v1, no setup); ``config``: the file's, read."""
    if config is None and fmt in (None, "fog-v1"):
        return None, None
    config = config or DriverConfig()
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


def silence_seconds(text: str) -> float:
    """``record --silence-s``: seconds >= 0 (0: no silence rule), finite."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number of seconds: {text!r}") from None
    if not 0 <= value < math.inf:
        raise argparse.ArgumentTypeError(f"must be a number of seconds >= 0 (0: never): {text!r}")
    return value


def cmd_record(args: argparse.Namespace) -> int:
    if not args.out.endswith(".bin"):
        raise UsageError(f"--out {args.out!r}: a capture file name must end in .bin")
    config = load_config(args.config) if args.config else None
    wire, setup = _record_wire(args.config, config, args.format)
    if args.silence_s is not None:  # the option over the config's port_silence_s; 0: never
        silence_s = args.silence_s or None
    else:
        silence_s = config.port_silence_s if config is not None else DEFAULT_SILENCE_S
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
                silence_s=silence_s,
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


def _instrument_seed(text: str) -> int:
    value = seed(text)
    if value > MAX_INSTRUMENT_SEED:
        raise argparse.ArgumentTypeError(f"instrument seed must be 0..{MAX_INSTRUMENT_SEED}: {value}")
    return value


def _simulator(args: argparse.Namespace):
    profile = load_profile(args.profile)
    config = load_instrument_config(args.instrument)
    if args.family is not None and args.instrument_seed is None:
        raise UsageError("--family adds a physics family to a population instrument: give --instrument-seed K too")
    if args.instrument_seed is not None:
        config = draw_instrument(args.instrument_seed, config, family=args.family)
    faults = parse_fault_spec(args.faults)
    return Simulator(
        profile, config, rate_hz=args.rate_hz, seed=args.seed, faults=faults, wire_format=args.format
    ), faults


def cmd_simulate(args: argparse.Namespace) -> int:
    if (args.out is None) == (args.serve is None):
        raise UsageError("give exactly one of --out CAPTURE.bin (write a capture) or --serve pty|DEVICE (stream live)")
    if args.duration is not None and args.duration > MAX_PROFILE_S:  # as a profile that long is refused
        raise UsageError(
            f"--duration {args.duration:g} s: more than the {MAX_PROFILE_S / 86400:g} days a simulated run may last"
        )
    if args.chamber_serve is not None and args.serve is None:
        raise UsageError("--chamber-serve applies to --serve only (a live stream whose air the chamber drives)")
    if args.chamber_serve is not None and args.chamber_serve.lower().startswith("watlow-f4t"):
        require_extra("lab", "simulate --chamber-serve watlow-f4t://")  # the F4T is served by pymodbus
    sim, faults = _simulator(args)
    if args.serve is not None:
        return serve_cli(sim, args)
    if not args.out.endswith(".bin"):
        raise UsageError(f"--out {args.out!r}: a capture file name must end in .bin")
    progress = Progress()
    stop = threading.Event()
    try:
        with stop_on_signals(stop):  # Ctrl-C or SIGTERM: the run ends at the next batch, described as interrupted
            result = simulate_to_file(
                sim,
                args.out,
                duration_s=args.duration,
                overwrite=args.force,
                progress=lambda done, total: progress.show(
                    f"simulating {100.0 * done / total:5.1f} % ({done:,} frames)"
                ),
                faults_text=faults.describe(),
                stop=stop,
            )
    finally:
        progress.clear()
    if result.interrupted:  # the interrupted line only: the success line would say the run completed
        print(
            f"fog-driver: interrupted: {result.capture} holds the first {result.frames / sim.rate_hz:g} s "
            f"(status: interrupted in {result.sidecar.name})",
            file=sys.stderr,
        )
        return EXIT_INTERRUPTED
    print(
        f"simulated {sim.profile.name} at {sim.rate_hz} Hz, seed {sim.seed}: {result.frames:,} frames, "
        f"{result.bytes:,} bytes -> {result.capture} (+ {result.sidecar.name}, {result.truth.name}"
        f"{', ' + result.table_log.name if result.table_log else ''})"
    )
    return 0


def add_inspect(p: argparse.ArgumentParser) -> None:
    """``fog-driver inspect``: its arguments and its function."""
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


def add_record(p: argparse.ArgumentParser) -> None:
    """``fog-driver record``: its arguments and its function."""
    p.add_argument("port", metavar="PORT_OR_URL", help="device path (/dev/ttyUSB0) or pyserial URL (replay://x.bin)")
    p.add_argument("--out", required=True, metavar="CAPTURE.bin")
    p.add_argument("--duration", type=positive_float, metavar="S", help="stop after S seconds (host clock)")
    p.add_argument("--baud", type=baud, default=460800, metavar="B", help="baud rate (default 460800)")
    p.add_argument("--no-reconnect", action="store_true", help="stop when the port is lost instead of reconnecting")
    p.add_argument(
        "--wait",
        action="store_true",
        help="wait for a port that is not there yet (default: a port that does not open is an error at "
        "once; a port lost after it worked is always reopened, unless --no-reconnect)",
    )
    p.add_argument(
        "--silence-s",
        type=silence_seconds,
        metavar="S",
        help="a network port (socket://, rfc2217://) that sends no byte for S seconds after it has sent some "
        "is taken as lost (and reopened, unless --no-reconnect); 0: never (default: the config's port_silence_s, "
        f"else {DEFAULT_SILENCE_S:g})",
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


def add_simulate(p: argparse.ArgumentParser) -> None:
    """``fog-driver simulate``: its arguments and its function."""
    p.add_argument(
        "--profile",
        default="paper",
        metavar="NAME_OR_YAML",
        help="a profile's name: built-in (paper, paper-validation, calibration) or a file's stem in configs/profiles/ "
        "(fast-ramps, positioning, ...); or a profile YAML file's path (default: paper)",
    )
    p.add_argument(
        "--out",
        metavar="CAPTURE.bin",
        help="write the capture, its sidecar, CAPTURE.truth.csv and, when the profile has positioning dwells, "
        "CAPTURE.table.csv (the table log)",
    )
    p.add_argument("--serve", metavar="pty|DEVICE", help="stream in real time on a new pty, or to a serial device")
    p.add_argument("--rate-hz", type=rate_hz, default=100, metavar="R", help="SAMPLE frame rate (default 100)")
    p.add_argument("--seed", type=seed, default=0, metavar="N", help="random seed (same seed, same bytes)")
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
        help="e.g. drop=1e-3,flip=1e-5,garbage=0.1,thermo=0.05:2,disconnect=60:2 (see the docs: reference/commands)",
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
    p.add_argument(
        "--family",
        choices=FAMILIES,
        help="with --instrument-seed: add this physics family, which the population never had",
    )
    p.add_argument("--duration", type=positive_float, metavar="S", help="stop after S device seconds")
    p.add_argument("--force", action="store_true", help="overwrite an existing capture")
    p.add_argument(
        "--link", metavar="PATH", help="--serve pty: the stable symlink to the pty (default /tmp/fog-driver-sim.tty)"
    )
    p.add_argument(
        "--speed",
        type=positive_float,
        default=1.0,
        metavar="X",
        help="--serve: run X times faster than real time (quick hardware-in-the-loop tests)",
    )
    p.add_argument("--baud", type=baud, default=460800, metavar="B", help="--serve DEVICE: baud rate (default 460800)")
    p.add_argument(
        "--chamber-serve",
        metavar="URL",
        help="--serve: also serve a simulated chamber on URL's protocol (espec://, thermotron://, simserv://, "
        "watlow-f4t://HOST:PORT; port 0 picks a free one, printed as 'serving the chamber on URL'); the instrument's "
        "air is that chamber's (its set point reached through a rate limit and a lag: URL options rate_c_per_min "
        "(default 3), tau_s (60), start_c (the profile's start), low_c, high_c (-70, 180), unit (C|F)); its clock "
        "is the device time (--speed)",
    )
    p.set_defaults(func=cmd_simulate)
