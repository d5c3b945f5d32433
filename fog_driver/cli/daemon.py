"""``fog-driver run``: the daemon, on the configured port or the embedded simulator."""

from __future__ import annotations

import argparse
import dataclasses
import os
import signal
import sys
import threading

import structlog

from .. import __version__
from ..console import configure_logging
from ..daemon.config import DriverConfig, load_config
from ..daemon.service import ConfigError, Service
from ..errors import FogDriverError, InternalError
from ..formats.registry import FORMATS
from ..signals import SignalDispatcher
from ..sim.instrument import Simulator
from ..sim.profiles import load_profile
from ..sim.serve import serve_pty
from ..tools.watch import format_address

FORMAT_NAMES = list(FORMATS)


def cmd_run(args: argparse.Namespace) -> int:
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
        "--format",
        choices=["auto", *FORMAT_NAMES],
        metavar="FORMAT",
        help=f"the instrument's frame format (overrides 'format'; {', '.join(['auto', *FORMAT_NAMES])}); "
        "a format other than fog-v1 needs 'device' settings in the config",
    )
    p.set_defaults(func=cmd_run)
