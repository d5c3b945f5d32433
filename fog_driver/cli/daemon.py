"""``fog-driver run``: the daemon, on the configured port or the embedded simulator."""

from __future__ import annotations

import argparse
import dataclasses
import errno
import os
import signal
import sys
import threading

import structlog

from .. import __version__
from ..console import configure_logging
from ..daemon.config import DriverConfig, load_config
from ..daemon.service import ConfigError, Service
from ..errors import DeviceError, FogDriverError, InternalError
from ..extras import require_extra
from ..formats.registry import FORMATS
from ..lab.profiles import load_profile
from ..signals import SignalDispatcher, deferred_hangups
from ..sim.instrument import Simulator
from ..sim.serve import serve_pty
from ..tools.watch import format_address
from ..transport.port import not_a_serial_device, open_error_text

FORMAT_NAMES = list(FORMATS)


def cmd_run(args: argparse.Namespace) -> int:
    # A service logs JSON lines to journald or a pipe (per-second summaries); at a terminal it is quiet.
    configure_logging(args.verbose, args.log_format, service=True)
    _never_world_writable()

    def read_config() -> DriverConfig:
        config = load_config(args.config) if args.config else DriverConfig()
        overrides = {
            k: getattr(args, k)
            for k in ("port", "model", "listen", "http", "capture_dir", "format", "force_model")
            if getattr(args, k)
        }
        return dataclasses.replace(config, **overrides)

    try:
        config = read_config()
    except (FogDriverError, ValueError) as exc:
        raise ConfigError(str(exc)) from None
    if config.http:  # before any work (the simulator, the model): as every command checks its extras
        # exit 64, as every command's missing extra (the unit's RestartPreventExitStatus= has it: a restart
        # cannot install it)
        require_extra("web", f"the web view and /metrics (http {config.http})")
    stop = threading.Event()
    simulator = None
    port = config.port
    interactive = _at_a_terminal()
    if args.simulate or (port is None and interactive):
        simulator, port = _start_embedded_simulator(stop)
    elif port is None:  # under systemd, or piped: a production daemon never falls back to a simulator
        where = f" in {args.config}" if args.config else ""
        raise ConfigError(
            f"no instrument port: set 'port'{where} or give --port PORT_OR_URL "
            "(--simulate runs the built-in simulated instrument)"
        )
    elif interactive:
        _check_port(port, wait=args.wait)
    try:
        service = Service(config, port=port)
        service.stop = stop
        host, listen_port = service.start()  # a listen address in use: TemporaryFailure, exit 75 (restarted)
    except BaseException:
        if simulator is not None:  # a failed start leaves no simulator behind (nor a link: it has none)
            stop.set()
            simulator.join(timeout=10)
        raise

    log = structlog.get_logger("fog_driver.daemon")
    stopping_said = [False]

    def on_signal(signum: int) -> None:
        """In the signal dispatcher's thread: a reload never runs inside a handler, nor twice at once.  Once
        stopping, every signal is left to the stop under way (said once): a second Ctrl-C must not cut it short."""
        if stop.is_set():
            if not stopping_said[0]:
                stopping_said[0] = True
                log.info("already_stopping", signal=signal.Signals(signum).name, detail="the stop under way completes")
            return
        if signum == signal.SIGHUP:  # reload the config file and the model, without stopping
            try:
                service.reload_config(read_config())
            except (FogDriverError, ValueError) as exc:  # keep running with what is in use
                log.error("config_reload_failed", reason=str(exc))
            return
        stop.set()

    # The fog-driver command (``defer_hangups`` ran): the process ends with this function, and from the stop on
    # no signal may end it halfway; in-process (a test) the handlers are given back.
    whole_process = deferred_hangups() is not None
    try:
        with SignalDispatcher(
            (signal.SIGINT, signal.SIGTERM, signal.SIGHUP), on_signal, ignore_after=whole_process
        ) as dispatcher:
            hangups = deferred_hangups()
            if hangups:  # SIGHUPs while starting: one reload now that it runs (the files may have changed since)
                log.info("sighup_during_start", count=hangups, detail="reloading once, now that the daemon runs")
                dispatcher.deliver(signal.SIGHUP)
            # The readiness line comes after the handlers: a signal sent on seeing it is handled.
            print(_readiness_line(service, port, host, listen_port), flush=True)
            status = service.run_until_stopped()
    finally:
        if simulator is not None:
            simulator.join(timeout=10)
    if status != 0 and service.failure is not None and not isinstance(service.failure, FogDriverError):
        raise InternalError.from_exception(service.failure)  # the acquisition thread logged its traceback
    return status


def _readiness_line(service: Service, port: str, host: str, listen_port: int) -> str:
    """The line that says the daemon is ready: the port, where clients connect, the model in use (its file and the
    instrument serial it was fitted for), the raw capture, and the two commands that connect to it; it ends
    ``(Ctrl-C to stop)`` (what a script waiting for it looks for)."""
    address = format_address(host, listen_port)  # an IPv6 address in brackets: [::1]:2948
    web = "" if service.web is None else f"; web view on http://{format_address(*service.web.address)}/"
    model = service.model_fields
    return (
        f"fog-driver {__version__}: {port} -> listening on {address}{web}; model {model.get('path', '-')} "
        f"(fitted for {model.get('serial', '-')}); raw capture in {service.config.capture_dir}/; "
        f"connect with: fog-driver watch {address} or fog-driver ctl {address} status  (Ctrl-C to stop)"
    )


def _never_world_writable() -> None:
    """Add 'others may not write' to the umask the daemon was given (even 0): no capture, sidecar or state
    file it creates is world-writable.  (The systemd unit sets ``UMask=0027``: group-readable only.)
    Call it before any thread starts: the umask is the whole process's."""
    os.umask(os.umask(0o022) | 0o002)


def _at_a_terminal() -> bool:
    """True when a person runs the command at a terminal: stdin is a TTY and systemd did not start it (no
    ``NOTIFY_SOCKET``).  Under systemd, cron or a pipe the daemon waits for its port and never serves the
    simulated instrument in place of a real one."""
    return sys.stdin is not None and sys.stdin.isatty() and not os.environ.get("NOTIFY_SOCKET")


def _check_port(port: str, *, wait: bool) -> None:
    """At a terminal: a device path that does not exist (a typo, an unplugged adapter) or cannot be opened is a
    one-line ``DeviceError`` at once (exit 69, as ``record``), unless ``wait``: then a line says the daemon
    waits for it.  A path that is there but is no serial device (``/dev/null``, a regular file, a directory:
    ``not_a_serial_device``; a pty is one) is a ``DeviceError`` at once even with ``wait``: waiting cannot make
    it one.  A URL (``socket://``, ``rfc2217://``) is the transport's to judge."""
    if "://" in port:
        return
    unusable = not_a_serial_device(port)
    if unusable is not None:
        raise DeviceError(unusable)
    if os.path.exists(port):
        if os.access(port, os.R_OK | os.W_OK):
            return
        problem = open_error_text(port, PermissionError(errno.EACCES, os.strerror(errno.EACCES)))
    else:
        problem = open_error_text(port, FileNotFoundError(errno.ENOENT, os.strerror(errno.ENOENT)))
    if not wait:
        raise DeviceError(f"{problem} (--wait waits for it)")
    print(f"waiting for {port} (now: {problem.removeprefix(f'cannot open {port}: ')}); Ctrl-C to stop", file=sys.stderr)


def _start_embedded_simulator(stop: threading.Event) -> tuple[threading.Thread, str]:
    """The demonstration instrument: the simulator on a pty in this process (the paper profile)."""
    sim = Simulator(load_profile("paper"), rate_hz=100, seed=0)
    ready = threading.Event()
    where: dict[str, str] = {}

    def on_ready(server) -> None:
        where["path"] = server.slave_path
        ready.set()

    def serve() -> None:
        try:
            # a demonstration does not warn about its own simulator's stalls (logged at info: -v)
            serve_pty(sim, link=None, stop=stop, on_ready=on_ready, warn_behind=False)
        finally:
            ready.set()

    thread = threading.Thread(target=serve, name="simulator", daemon=True)
    thread.start()
    ready.wait(30)
    if "path" not in where:
        raise FogDriverError("the embedded simulator did not start")
    return thread, where["path"]


def add_run(p: argparse.ArgumentParser) -> None:
    """``fog-driver run``: its arguments and its function."""
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
        "--wait",
        action="store_true",
        help="at a terminal, wait for a port that is not there yet (default: an error at once, exit 69; a path "
        "that is there but no serial device, such as /dev/null, is one even with --wait); "
        "under systemd, or without a terminal, the daemon always waits for its port",
    )
    p.add_argument(
        "--force-model",
        action="store_true",
        help="apply the model even when it was fitted for another instrument serial (sets force_model)",
    )
    p.add_argument(
        "--format",
        choices=["auto", *FORMAT_NAMES],
        metavar="FORMAT",
        help=f"the instrument's frame format (overrides 'format'; {', '.join(['auto', *FORMAT_NAMES])}); "
        "a format other than fog-v1 needs 'device' settings in the config",
    )
    p.set_defaults(func=cmd_run)
