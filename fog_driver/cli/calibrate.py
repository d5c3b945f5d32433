"""``fog-driver calibrate``: a whole calibration in one command: the gyro recorded as ``record`` records it, the
chamber driven through the program by the host (``fog_driver.lab.runner``), its log ``RUN.chamber.csv`` beside
the capture, and (``--fit``) the drift model fitted at the end as ``fog-driver fit`` fits it.

Needs the ``lab`` extra (one line with the pip command, exit 64); ``--help`` does not.  The checks before the
chamber or the port is touched: ``--out`` (64), the profile (65), ``--resume``'s log (65), the outputs (73 if
the capture, its sidecar, the chamber log or the model exist without ``--force``), the URL (64).  Then the
controller is locked and connected (69), the program's range checked (65, nothing written), the port opened
(69: a port another program holds, a daemon, is refused: ``transport.port.open_port`` opens it exclusively),
and the program starts at the first gyro frame.  The sidecar names the chamber log (``chamber_log``, relative
to the capture), the program (``program``: its name and ``program_sha256``) and the controller (``chamber``);
an interrupted run (SIGINT, SIGTERM) ends with the on-stop action, the capture and the log flushed, the
sidecar's ``status: interrupted``, and exit 130; no fit then.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from pathlib import Path
from typing import Any

from ..client.display import Progress
from ..errors import UsageError
from ..extras import require_extra
from ..files.outputs import check_outputs
from ..lab.chamberlog import ChamberLogWriter, LogHeader, program_sha256
from ..lab.lock import ControllerLock
from ..lab.runner import RunOptions, SystemClock, check_range, run_program
from ..samples.captures import read_provenance, sidecar_path, write_provenance
from ..samples.record import record
from ..signals import stop_on_signals
from .argtypes import baud, positive_float
from .captures import FORMAT_NAMES, _record_wire, load_config
from .lab import EXIT_INTERRUPTED, add_program_options, load_program, open_chamber, resume_from

#: The chamber log beside the capture ``RUN.bin``: ``RUN.chamber.csv``.
CHAMBER_LOG_SUFFIX = ".chamber.csv"
_NO_READING = -32768  # a thermometer's raw value when it has no reading


def chamber_log_path(capture: str | Path) -> Path:
    """``RUN.bin`` -> ``RUN.chamber.csv``, beside it."""
    return Path(capture).with_suffix(CHAMBER_LOG_SUFFIX)


class FrameFeed:
    """The gyro as the runner sees it (``lab.runner.GyroFeed``): the device time of the last sample frame and the
    host seconds since it; and its three temperatures (degC, None: no reading) for the progress line.

    Fed by ``record``'s ``on_event`` in the recording's thread; read by the runner's.  The device clock is a u32
    of microseconds: unwrapped here (one wrap a 71.6 min)."""

    def __init__(self, monotonic: Any = time.monotonic) -> None:
        self._monotonic = monotonic
        self._lock = threading.Lock()
        self._last_t_us: int | None = None
        self._wraps = 0
        self._device_t_s: float | None = None
        self._host_s: float | None = None
        self.temperatures_c: tuple[float | None, float | None, float | None] = (None, None, None)
        self.first_frame = threading.Event()

    def on_event(self, event: Any) -> None:
        t_us = getattr(event, "t_us", None)
        if t_us is None:
            return
        raw = (event.t_top_raw, event.t_bottom_raw, event.t_housing_raw)
        with self._lock:
            if self._last_t_us is not None and t_us < self._last_t_us:
                self._wraps += 1
            self._last_t_us = t_us
            self._device_t_s = (t_us + self._wraps * 2**32) / 1e6
            self._host_s = self._monotonic()
            self.temperatures_c = tuple(None if r == _NO_READING else r / 256.0 for r in raw)  # type: ignore[assignment]
        self.first_frame.set()

    def device_t_s(self) -> float | None:
        with self._lock:
            return self._device_t_s

    def seconds_since_frame(self) -> float | None:
        with self._lock:
            return None if self._host_s is None else self._monotonic() - self._host_s


def _progress_text(row: Any, feed: FrameFeed, duration_s: float) -> str:
    """The progress line: the program's time, its segment, the set point, the air, the gyro's temperatures, the
    time left."""

    def c(value: float | None) -> str:
        return "-" if value is None else f"{value:.2f}"

    temps = "/".join(c(t) for t in feed.temperatures_c)
    t = "settling" if row.t_s is None else f"{row.t_s:7.1f} s"
    left = "" if row.t_s is None else f"  {max(duration_s - row.t_s, 0.0):.0f} s left"
    return (
        f"{row.state} {t}  segment {'-' if row.segment is None else row.segment}  set point {c(row.setpoint_c)}  "
        f"air {c(row.air_c)} degC  gyro top/bottom/housing {temps} degC{left}"
    )


class _RecordingThread(threading.Thread):
    """``samples.record.record`` in a thread; its result or its error kept for the caller."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(name="calibrate-record", daemon=True)
        self.kwargs = kwargs
        self.result: Any = None
        self.error: BaseException | None = None
        self.done = threading.Event()

    def run(self) -> None:
        try:
            self.result = record(**self.kwargs)
        except BaseException as exc:  # raised again in the caller's thread
            self.error = exc
        finally:
            self.done.set()


def _wait_for_frames(feed: FrameFeed, recording: _RecordingThread, stop: threading.Event) -> None:
    """Until the first sample frame, the recording's end (its error raised here), or a stop."""
    while not (feed.first_frame.wait(0.1) or recording.done.is_set() or stop.is_set()):
        pass
    if recording.error is not None:
        raise recording.error


def cmd_calibrate(args: argparse.Namespace) -> int:
    require_extra("lab", "fog-driver calibrate")
    if not args.out.endswith(".bin"):
        raise UsageError(f"--out {args.out!r}: a capture file name must end in .bin")
    out = Path(args.out)
    log_path = chamber_log_path(out)
    profile, program = load_program(args.profile)
    resume_t_s, run_id = resume_from(args.resume, log_path, program, "--out")
    outputs = [out, sidecar_path(out), log_path, *([Path(args.fit)] if args.fit else [])]
    check_outputs(outputs, force=args.force, captures=[out])
    config = load_config(args.config) if args.config else None
    wire, setup = _record_wire(args.config, config, args.format)
    controller = open_chamber(args.chamber, args.chamber_config)
    options = RunOptions(step_s=args.step_s, on_stop=args.on_stop, pause_after_s=args.pause_after_s)
    sha = program_sha256(program)
    feed = FrameFeed()
    progress = Progress()
    stop, stop_recording = threading.Event(), threading.Event()
    with ControllerLock(controller.address):
        controller.connect()
        try:
            check_range(program, controller.read_range_c(), options.on_stop)  # before the port: nothing recorded
            recording = _RecordingThread(
                url=args.port,
                out_path=out,
                baudrate=args.baud,
                stop=stop_recording,
                on_state=lambda _event: progress.clear(),
                notes=args.notes,
                overwrite=args.force,
                wire=wire,
                setup=setup,
                on_event=feed.on_event,
                extra_fields={
                    "source": "calibrate",
                    "chamber_log": log_path.name,
                    "program": {"name": profile.name, "program_sha256": sha},
                    "chamber": args.chamber,
                    "run_id": run_id,
                    **({"resumed_from": args.resume} if args.resume else {}),
                },
            )
            with stop_on_signals(stop):
                recording.start()
                try:
                    _wait_for_frames(feed, recording, stop)
                    header = LogHeader(profile.name, sha, args.chamber, run_id, args.resume)
                    log = ChamberLogWriter(log_path, header, force=args.force)
                    print(
                        f"calibrate: {profile.name} ({program.duration_s:g} s) on {args.chamber}, gyro {args.port} "
                        f"-> {out}, log {log_path}"
                        f"{f', resumed at {resume_t_s:g} s' if resume_t_s is not None else ''}; Ctrl-C to stop",
                        file=sys.stderr,
                        flush=True,
                    )
                    try:
                        result = run_program(
                            controller,
                            program,
                            log,
                            options=options,
                            clock=SystemClock(),
                            stop=stop,
                            gyro=feed,
                            resume_t_s=resume_t_s,
                            on_row=lambda row: progress.show(_progress_text(row, feed, program.duration_s)),
                        )
                    finally:
                        log.close()
                finally:
                    progress.clear()
                    stop_recording.set()
                    recording.join()
        finally:
            controller.close()
    if recording.error is not None:
        raise recording.error
    recorded = recording.result
    if result.status == "interrupted":
        fields = read_provenance(out) or {}
        write_provenance(out, {**fields, "status": "interrupted"})
    c = recorded.counters
    print(
        f"calibrate {result.status} at {result.program_t_s:g} s of {program.duration_s:g} s: {result.rows} chamber "
        f"rows -> {log_path}; {recorded.bytes_written:,} bytes ({c.sample_frames:,} sample frames, "
        f"{c.missing_frames} missing) -> {out}"
    )
    if result.status == "interrupted":
        if args.fit:
            print(f"no fit: the run was interrupted (resume it with --resume {log_path})", file=sys.stderr)
        return EXIT_INTERRUPTED
    if args.fit:
        return _fit(out, args)
    return 0


def _fit(capture: Path, args: argparse.Namespace) -> int:
    """``fog-driver fit CAPTURE --out MODEL --profile PROFILE [--format F] --force``: the same code, the same
    arguments' defaults (the outputs were checked before the run: ``--force`` here only lets it write)."""
    from .calibration import cmd_fit  # start-up time: the fit's modules only with --fit
    from .parser import build_parser  # start-up time: the parser imports this module

    argv = ["fit", str(capture), "--out", args.fit, "--profile", args.profile, "--force"]
    if args.format:
        argv += ["--format", args.format]
    return int(cmd_fit(build_parser(["fit"]).parse_args(argv)))


def add_calibrate(p: argparse.ArgumentParser) -> None:
    """``fog-driver calibrate``: its arguments and its function (``--help`` imports nothing of the lab extra)."""
    p.add_argument("port", metavar="PORT_OR_URL", help="the gyro's port: a device path or a pyserial URL")
    p.add_argument("--chamber", required=True, metavar="URL", help="the controller, e.g. espec://HOST, sim://")
    p.add_argument("--profile", required=True, metavar="PROFILE", help="a profile file (as plan writes) or a name")
    p.add_argument(
        "--out", required=True, metavar="RUN.bin", help="the capture; its chamber log is RUN.chamber.csv beside it"
    )
    p.add_argument("--fit", metavar="MODEL.yaml", help="fit a drift model to the capture at the end (as fit does)")
    p.add_argument("--force", action="store_true", help="overwrite the capture, its sidecar, the log and the model")
    p.add_argument(
        "--pause-after-s",
        type=positive_float,
        default=10.0,
        metavar="S",
        help="hold the program while the gyro sends no frame for more than S seconds (default 10)",
    )
    add_program_options(p, resume_help="go on from an interrupted run's chamber log, into a new --out")
    p.add_argument("--baud", type=baud, default=460800, metavar="B", help="the gyro's baud rate (default 460800)")
    p.add_argument("--config", metavar="FILE", help="a daemon config saying what the port sends (as record --config)")
    p.add_argument(
        "--format", choices=FORMAT_NAMES, metavar="FORMAT", help="the frame format the port sends (as record --format)"
    )
    p.add_argument("--notes", help="free text stored in the provenance sidecar")
    p.set_defaults(func=cmd_calibrate)
