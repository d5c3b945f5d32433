"""The headless daemon's life cycle: start, reload, stop; the rooms it owns.

The rooms: ``acquisition.py`` (the hot loop: port -> decoder -> compensator -> publish, and the pipeline state),
``commands.py`` (the control commands, a table), ``status.py`` (VERSION, DEVICE, STATUS and the numbers
``/metrics`` reads), ``hub.py`` with ``connection.py`` (the NDJSON clients), ``rawlog.py`` (the raw capture)
with ``modelstore.py`` (the models kept beside it), ``web/`` (the web view and metrics; both listeners stand on
``listener.py``), ``udp.py``, ``sdnotify.py``; ``limits.py`` holds their limits.  This
module builds them, starts and stops them, and applies reloads (the model file, SIGHUP's config).

Threads and who owns what:

* the acquisition thread reads the port (``PortReader``: reconnects within ``backoff_max_s`` of the port
  coming back), hands every byte to the raw capture (``CaptureSink.put``: O(1), never a wait for the disk),
  decodes, compensates sample by sample and hands each chunk's ANGLE objects to the hub in one call; it
  never waits on a client, on the disk or on logging;
* the capture thread writes, rotates and fsyncs the raw capture (``rawlog.CaptureSink``); a disk that fails
  degrades the capture (STATUS and DEVICE say ``failed``; retried with backoff), never the publishing;
* the hub's thread serves clients (``hub.py``), and runs control commands in its worker threads;
* the main thread publishes STATUS, logs a one-line summary every ``status_every_s`` and pings the systemd
  watchdog (at half ``WATCHDOG_USEC``, only while the acquisition, the hub and the port reader make progress);
  the signal dispatcher's thread handles signals (``fog_driver.signals``).

The lock (``Service.lock``) guards only the in-memory pipeline: decoder, stream, compensator, angle offsets.
It is held per chunk by the acquisition thread and briefly by control commands; nothing slow runs under it.
A model reload parses and builds the new compensator outside it, then swaps it in (``reload_model``);
``?SAVE`` takes a snapshot under it and writes the file outside it.

Angles: ``angle_arcsec`` is the compensated angle integrated from the frames, less the offsets ``?ZERO`` and
``?BIAS`` introduce (``acquisition.py`` says how).

Live == offline.  The published ``angle_arcsec`` equals ``fog-driver compensate`` (``offline.compensate``)
on the daemon's raw capture (its files concatenated in name order), bit for bit, when the offline run is given
the daemon's settings: ``--scale-override`` for ``scale_override_arcsec_per_count``, ``--force-model`` for
``force_model``, and with an ``adapt_state`` the state file as it was at the start with ``--adapt-state``
(``--adapt-reference`` for ``adapt_reference_dph``).  The control events that change what is published
(``?TABLE``, ``?ADAPT``, ``?ZERO``, ``?BIAS``, a model reload) are noted in the capture's sidecar (``events``,
with the byte of the file and the sample they took effect at) and replayed there by ``compensate``
(``offline.replay``); a copy of each model used is kept beside the captures (``models/<sha256>.yaml``).  (ANGLE's
``utc``, the host's clock when the sample was read, is the one key that cannot be reproduced offline; see
``stamp_utc``.)  The sidecar also records the model (path, SHA-256), the scale settings, the adaptation state's
SHA-256 and the instrument.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import errno
import hashlib
import os
import threading
import time
from pathlib import Path
from typing import Any

import structlog

from .. import __version__
from ..compensation.adapt import AdaptConfig
from ..compensation.binding import InstrumentCompensation, ModelMismatchError, check_channels
from ..compensation.model import ModelFile
from ..compensation.pipeline import CompensatedSample, Compensator
from ..dwells import Dwell
from ..errors import FogDriverError, OutputFileError, TemporaryFailure, UsageError
from ..extras import require_extra
from ..files.bounded import NotARegularFile, file_sha256
from ..files.yamlio import MAX_YAML_BYTES
from ..modelfiles import (
    adaptation_restorer,
    model_bytes,
    not_a_state_file,
    read_model,
    read_state_doc,
    write_state_doc,
)
from ..protocol import IdentityFrame
from ..samples.sources import make_source
from ..transport import PortEvent, PortReader
from ..transport.setup import make_on_open
from . import status
from .acquisition import Acquisition, stamp_utc
from .chamber import ChamberPoller, open_daemon_controller
from .commands import run_command
from .config import DEFAULT_HTTP_PORT, DriverConfig, format_address, parse_host_port, token_warnings
from .errors import ConfigError
from .hub import Hub
from .limits import CLIENT_SNDBUF_BYTES, JOIN_TIMEOUT_S, PORT_BACKOFF_MAX_S, READER_STALL_S
from .rawlog import CaptureSink, RotatingCapture
from .sdnotify import Notifier
from .status import PROTO_MAJOR, PROTO_MINOR
from .udp import UdpPublisher
from .web.metrics import LatencyHistogram

log = structlog.get_logger("fog_driver.daemon")


def _file_sha256(path: str | Path) -> str | None:
    """A model's or a state file's SHA-256, or None when it cannot be read (``bounded.file_sha256``: not a regular
    file, or larger than ``MAX_YAML_BYTES``)."""
    try:
        return file_sha256(path, "file", MAX_YAML_BYTES)
    except FogDriverError:
        return None


class Service:
    """One instrument: its port, its model, its clients."""

    #: Settings that need a restart; every other one applies on SIGHUP (``reload_config``).
    RESTART_KEYS = (
        "port",
        "baud",
        "listen",
        "udp",
        "udp_version",
        "http",
        "http_history_min",
        "http_hosts",
        "http_trusted_proxies",
        "http_secure_cookies",
        "open_stream",
        "capture_dir",
        "capture_rotate_mb",
        "capture_rotate_s",
        "capture_keep_days",
        "capture_max_gb",
        "scale_arcsec_per_count",
        "scale_override_arcsec_per_count",
        "format",
        "axis",
        "device",
        "publish_axes",
        "chamber",
    )

    def __init__(self, config: DriverConfig, *, port: str, model_file: ModelFile | None = None) -> None:
        self.config = config
        self.port_url = port
        try:
            self.model_file, self.model_bytes = (
                (model_file, model_bytes(model_file)) if model_file is not None else read_model(config.model_path)
            )
        except FogDriverError as exc:
            raise ConfigError(str(exc)) from None
        #: the SHA-256 of the model's bytes (of its file, or of the text ``save_model`` writes for an object)
        self.model_sha256 = hashlib.sha256(self.model_bytes).hexdigest()
        self.model_path: str | None = None if model_file is not None else str(config.model_path)  #: None: an object
        #: STATUS's and VERSION's ``model_file`` (path, SHA-256, kind, fit date, serial), one object replaced whole
        #: by a reload, so no reader sees one model's path with another's digest
        self.model_fields = status.model_file_fields(self.model_file, self.model_path, self.model_sha256)
        for line in self.model_file.warnings(str(config.model_path)):
            log.warning("model_warning", message=line)
        for line in token_warnings(config.token):
            log.warning("token_too_short", message=line)
        self.lock = threading.Lock()  # the in-memory pipeline only
        self._reload_lock = threading.Lock()  # one reload at a time, never held with ``lock`` while parsing
        self.stop = threading.Event()
        self.started_monotonic = time.monotonic()
        #: the ``adapt_state`` path whose stale state could not be set aside: the state is in memory only
        #: (restored from nothing, never saved there), said once at start (``adapt_state_in_memory``)
        self.adapt_state_in_memory: str | None = None
        self.adapt_state_sha256 = self._check_adapt_state(self.model_file)
        self.source = make_source(config)
        if config.format != "auto":
            self._check_channels(self.model_file, config.wire_settings(), f"the model {config.model_path}")
        self.binding = self._new_binding(self.model_file)
        self.acquisition = Acquisition(self)  # the pipeline's state and the hot loop
        self.port_state = "closed"
        self.last_event: dict | None = None
        self._adapt_touched = config.adapt_reference_dph is not None  # save the state at exit only if adapted
        self.reloads = 0
        self.hub = None
        self.capture = None
        self.udp = None
        self.web = None
        self.latency = LatencyHistogram()  # frame-to-publish, for /metrics
        self.notifier = None
        self.reader: PortReader | None = None
        self.chamber: ChamberPoller | None = None  #: the read-only chamber (the config's ``chamber:``)
        self._acquisition: threading.Thread | None = None
        self.failure: BaseException | None = None
        #: the save at exit that failed (``shutdown``): ``run_until_stopped`` then ends in it (exit 73)
        self.adapt_state_not_saved: OutputFileError | None = None
        self._save_failures_logged: set[str] = set()
        self.cpu = status.CpuMeter()

    @property
    def compensator(self) -> Compensator | None:
        return self.binding.compensator

    @property
    def identity(self) -> IdentityFrame | None:
        """The instrument's IDENTITY in use (None until the first plausible one)."""
        return self.acquisition.identity

    @property
    def samples_before_identity(self) -> list:
        """Samples kept while no IDENTITY has arrived (compensated once one does)."""
        return self.acquisition.samples_before_identity

    @property
    def bias_dph(self) -> float:
        """The bias removed from the published rate (deg/h): 0 until a ``?BIAS`` capture completes."""
        return self.acquisition.offsets.bias_dph

    @staticmethod
    def _check_channels(model_file: ModelFile, wire, model_name: str = "the model") -> None:
        """A model fitted on other temperature channels than the instrument's format carries cannot run: exit 78."""
        try:
            check_channels(model_file, wire, model_name, "the instrument")
        except ModelMismatchError as exc:
            raise ConfigError(str(exc)) from None

    def _new_binding(self, model_file: ModelFile) -> InstrumentCompensation:
        return InstrumentCompensation(
            model_file,
            force=self.config.force_model,
            model_name=f"the model {self.config.model_path}",
            hint="set force_model: true in the config (fog-driver run --force-model) to apply it anyway",
            adapt=AdaptConfig(),
            reference_rate_dph=self.config.adapt_reference_dph,
            restore_adaptation=None if self.adapt_state_in_memory else adaptation_restorer(self.config.adapt_state),
            table_dwells=[],  # the table law records from the start, for the first ?TABLE
        )

    def _check_adapt_state(self, model_file: ModelFile) -> str | None:
        """The configured adaptation state, checked against the model before anything runs, so it can never stop
        the daemon after it said it was ready.  Returns the usable state's SHA-256.

        A path naming a file that is not an adaptation state (``modelfiles.not_a_state_file``: a model, a
        capture, a sidecar, a config...) is a ``ConfigError`` (exit 78), and nothing is renamed.  A state file
        saved for another model (a re-fit) or corrupt is set aside (renamed ``.stale-<UTC>``) with a warning;
        one that cannot be set aside (a read-only directory) is let be: the daemon runs with its state in
        memory, starting at rest, never saving it there, and says so once (``adapt_state_in_memory``)."""
        path = self.config.adapt_state
        if not path:
            return None
        self._refuse_a_foreign_state_path(path)
        if not Path(path).exists():
            return None
        try:
            probe = Compensator(model_file, 0.01, adapt=AdaptConfig(), table=True)
            probe.restore_adaptation(read_state_doc(path), str(path))
        except NotARegularFile as exc:  # (a FIFO, /dev/zero, a directory: never read, nor set aside)
            raise ConfigError(str(exc)) from None
        except FogDriverError as exc:
            stamp = _dt.datetime.now(_dt.UTC).strftime("%Y%m%dT%H%M%SZ")
            aside = Path(f"{path}.stale-{stamp}")
            try:
                os.replace(path, aside)
            except OSError as move:
                self.adapt_state_in_memory = str(path)
                log.warning(
                    "adapt_state_in_memory",
                    path=str(path),
                    reason=f"unusable adaptation state ({exc}) that cannot be set aside ({move.strerror or move}): "
                    "the state is kept in memory, starting at rest, and not saved there (?SAVE and the save at "
                    "exit are off until a restart)",
                )
                return None
            log.warning("adapt_state_set_aside", reason=str(exc), moved_to=str(aside))
            return None
        return _file_sha256(path)

    def save_adapt_state(self, doc: dict, *, log_failure: bool = True) -> None:
        """Write the adaptation state ``doc`` (a snapshot) to ``adapt_state`` (``modelfiles.write_state_doc``:
        atomically, never over a file that is not an adaptation state), outside the lock.  An
        ``OutputFileError`` when it cannot be written, or when the state is in memory only
        (``adapt_state_in_memory``); with ``log_failure`` (``?SAVE``: else only the client would see its ERROR) each
        distinct failure is logged once (``adapt_state_not_saved``)."""
        path = str(self.config.adapt_state)
        try:
            if path == self.adapt_state_in_memory:
                raise OutputFileError(
                    f"{path}: not saved: the adaptation state is in memory only (the unusable state there could "
                    "not be set aside at start)"
                )
            write_state_doc(path, doc)
        except OutputFileError as exc:
            if log_failure and str(exc) not in self._save_failures_logged:
                self._save_failures_logged.add(str(exc))
                log.error("adapt_state_not_saved", reason=str(exc))
            raise

    @staticmethod
    def _refuse_a_foreign_state_path(path: str) -> None:
        """An ``adapt_state`` that names a file of another kind (``modelfiles.not_a_state_file``): exit 78."""
        kind = not_a_state_file(path)
        if kind is not None and kind.startswith("not a regular file"):  # the words every reader gives
            raise ConfigError(f"{path}: {kind}: an adaptation state file must be one")
        if kind is not None:
            raise ConfigError(
                f"{path}: adapt_state is {kind}, not an adaptation state; refusing to read, set aside or replace it"
            )

    # -- objects clients see -------------------------------------------------------------------

    def version_object(self) -> dict:
        return status.version_object(self)

    def device_object(self) -> dict | None:
        return status.device_object(self)

    def status_object(self, *, mark_cpu: bool = True) -> dict:
        """STATUS now (``status.status_object``; call under ``lock``)."""
        return status.status_object(self, mark_cpu=mark_cpu)

    def angle_object(self, c: CompensatedSample) -> dict:
        return self.acquisition.angle_object(c)

    def note(self, event: str, **fields: Any) -> None:
        """An event for the capture's sidecar, in order with the bytes (call under ``lock``), with ``seq``: the
        last sample compensated before it took effect (``offline.replay`` finds it there)."""
        if self.capture is not None:
            seq = self.acquisition.last_seq
            self.capture.note({"event": event, **fields, **({"seq": seq} if seq is not None else {})})

    # -- acquisition ---------------------------------------------------------------------------

    def _on_port_state(self, event: PortEvent) -> None:
        self.port_state = event.state
        self.acquisition.port_changed(event.state, event.url, time.monotonic())
        if event.state in ("open", "lost"):
            self.publish(self.device_object())

    def _on_capture_status(self, status: str) -> None:
        self.publish(self.device_object())

    def publish(self, obj: dict | None) -> None:
        """An object for every authorized client and the web view (non-blocking, any thread)."""
        if obj is None:
            return
        if self.hub is not None:
            self.hub.publish(obj)
        if self.web is not None:
            self.web.publish(obj)

    def process(self, chunk: bytes) -> list[dict]:
        """Bytes from the port -> ANGLE objects (``Acquisition.process``; also used by tests)."""
        return self.acquisition.process(chunk)

    def publish_event(self, obj: dict) -> None:
        """An event for every authorized client (non-blocking), and kept as ``last_event`` (tests, STATUS-less
        services); never raises into the acquisition."""
        self.last_event = obj
        if self.hub is not None or self.web is not None:
            try:
                self.publish(obj)
            except Exception:  # noqa: BLE001 - an event nobody can take must never stop the acquisition
                log.exception("event_not_published", event=obj.get("class"))

    # -- control (called from the hub's worker threads) ----------------------------------------

    def control(self, name: str, args: dict, client_id: int) -> dict:
        """A control command (``commands.COMMANDS``): its answer, an ERROR for an unknown one."""
        return run_command(self, name, args)

    def set_reference(self, reference: float | None) -> None:
        """Adapt against ``reference`` (None: frozen, which also ends adapting from table angles) from the next
        block (under ``lock``)."""
        if reference is None and self.compensator.table_engaged:
            self.compensator.stop_table()
            self.note("adapt", reference_dph=None)
            return
        if reference == self.compensator.reference_rate_dph:
            return
        self.compensator.reference_rate_dph = reference
        self.binding.reference_rate_dph = reference
        self._adapt_touched = self._adapt_touched or reference is not None
        self.note("adapt", reference_dph=reference)

    def table_dwell(self, angle_deg: float, dwell_s: float, angle_start_deg: float | None) -> Dwell:
        """A live dwell into the table law (``Compensator.table_dwell``; ``ValueError`` when refused), noted in
        the capture's sidecar (under ``lock``)."""
        if self.compensator.reference_rate_dph is not None:
            raise ValueError('adapting against a reference rate (?ADAPT): ?ADAPT={"enable":false} first')
        dwell = self.compensator.table_dwell(angle_deg, dwell_s, angle_start_deg)
        self._adapt_touched = True  # the state (what the table law learned) is saved at exit
        self.note("table", angle_deg=angle_deg, dwell_s=dwell_s, angle_start_deg=angle_start_deg)
        return dwell

    # -- reloads ---------------------------------------------------------------------------------

    def reload_from_file(self, config: DriverConfig) -> dict:
        """Read ``config``'s model file (outside the lock) and use it, unless it is byte for byte the one in
        use; all or nothing: an unreadable model, or one fitted for another instrument than the one on the
        port, changes nothing (``FogDriverError``)."""
        with self._reload_lock:
            path = config.model_path
            digest = _file_sha256(path)
            if digest is not None and digest == self.model_sha256 and path == self.config.model_path:
                return {
                    "class": "RELOAD",
                    "model": self.model_file.kind,
                    "created_utc": self.model_file.created_utc,
                    "changed": False,
                }
            model_file, data = read_model(path)
            self._swap_model(model_file, data, config.force_model, str(path))
            for line in model_file.warnings(str(path)):
                log.warning("model_warning", message=line)
            log.info("model_reloaded", model=str(path), **self.model_fields)
            return {"class": "RELOAD", "model": model_file.kind, "created_utc": model_file.created_utc, "changed": True}

    def reload_model(self, model_file: ModelFile) -> None:
        """Compensate with ``model_file`` from the next block on (see ``_swap_model``)."""
        with self._reload_lock:
            self._swap_model(model_file, model_bytes(model_file), self.config.force_model, None)

    def _swap_model(self, model_file: ModelFile, data: bytes, force: bool, path: str | None) -> None:
        """Build the compensator for ``model_file`` (read from ``data``) outside the lock, then swap it in
        (``InstrumentCompensation.swap_model``: what carries on).  A model fitted for another instrument than the
        one on the port is refused (unless ``force``).  With a capture, the reload is noted in its sidecar with
        the model's SHA-256, and a copy of the model is kept beside it, so that ``compensate`` replays it."""
        identity = self.binding.identity
        if identity is not None:
            self.binding.check(identity, model_file, force=force, model_name="the new model")
        if self.source.wire is not None:
            self._check_channels(model_file, self.source.wire, "the new model")
        new = self.binding.compensator_for(model_file, 1.0 / identity.rate_hz) if identity is not None else None
        digest = hashlib.sha256(data).hexdigest()
        with self.lock:  # O(state): the pipeline state is copied, nothing is parsed
            self.binding.swap_model(model_file, new)
            self.binding.force = force
            self.model_file, self.model_bytes, self.model_sha256, self.model_path = model_file, data, digest, path
            self.model_fields = status.model_file_fields(model_file, path, digest)
            self.reloads += 1
            self.note("model", kind=model_file.kind, created_utc=model_file.created_utc, sha256=digest)
            if self.capture is not None:
                self.capture.keep_model(digest, data)
                self.capture.update_provenance({"model": self._model_provenance()}, current_file=False)
        if self.web is not None:  # the page's VERSION names the new model too (STATUS does from its next one)
            self.web.publish(self.version_object())

    def reload_config(self, config: DriverConfig) -> dict:
        """SIGHUP: apply every setting that can change live, all or nothing, and say which need a restart.

        The model file is read first (if it cannot be used, nothing changes); then the token, the client
        backlog, the status period, the adaptation reference (only when the file's value changed: a client's
        ``?ADAPT`` is not undone by an unrelated edit), ``adapt_state`` and ``force_model`` apply.  The keys
        of ``RESTART_KEYS`` that changed are kept as they are and reported (``restart_needed``)."""
        restart = [k for k in self.RESTART_KEYS if getattr(config, k) != getattr(self.config, k)]
        new = dataclasses.replace(config, **{k: getattr(self.config, k) for k in self.RESTART_KEYS})
        if new.token != self.config.token:  # ValueError (e.g. no token beyond loopback): nothing changed
            for listener in (self.hub, self.web):
                if listener is not None:
                    listener.check_token(new.token)
        if new.adapt_state and new.adapt_state != self.config.adapt_state:
            self._refuse_a_foreign_state_path(new.adapt_state)  # ConfigError: nothing changed
        result = self.reload_from_file(new)  # FogDriverError: nothing changed
        old = self.config
        self.config = new
        if self.hub is not None:
            if new.token != old.token:
                self.hub.set_token(new.token)
            self.hub.set_max_backlog_s(new.max_client_backlog_s)
        if self.web is not None:
            if new.token != old.token:
                self.web.set_token(new.token)
            self.web.max_backlog_s = new.max_client_backlog_s
        if self.reader is not None:
            self.reader.silence_s = new.port_silence_s  # read at the reader's next read
        with self.lock:
            self.binding.force = new.force_model
            if new.adapt_reference_dph != old.adapt_reference_dph and self.compensator is not None:
                self.set_reference(new.adapt_reference_dph)
        applied = [
            f.name
            for f in dataclasses.fields(DriverConfig)
            if f.name not in self.RESTART_KEYS and getattr(new, f.name) != getattr(old, f.name)
        ]
        if restart:
            log.warning("config_needs_restart", keys=restart)
        log.info("config_reloaded", applied=applied, restart_needed=restart)
        return {**result, "applied": applied, "restart_needed": restart}

    # -- life cycle ----------------------------------------------------------------------------

    def start(self) -> tuple[str, int]:
        """Listen, open the raw capture, start acquiring; returns the listening address."""
        if self.config.http is not None:  # first: its errors come before anything else listens or logs
            self._start_web(self._make_web())
        try:
            address = self._start_after_web()
        except BaseException:
            if self.web is not None:
                self.web.stop()
                self.web = None
            raise
        log.info("model_in_use", **self.model_fields)  # a reload logs model_reloaded
        return address

    def _start_after_web(self) -> tuple[str, int]:
        host, port = parse_host_port(self.config.listen)
        try:
            self.hub = Hub(
                host,
                port,
                version=self.version_object,
                device=self.device_object,
                control=self.control,
                token=self.config.token,
                open_stream=self.config.open_stream,
                max_backlog_s=self.config.max_client_backlog_s,
                sndbuf_bytes=CLIENT_SNDBUF_BYTES,
                latency=self.latency,
            )
        except ValueError as exc:
            raise ConfigError(f"listen {self.config.listen}: {exc}") from None
        try:
            address = self.hub.start()
        except OSError as exc:  # in use, or not on this host yet (the network coming up): may clear by itself
            error = TemporaryFailure if exc.errno in (errno.EADDRINUSE, errno.EADDRNOTAVAIL) else ConfigError
            hint = (
                " (another fog-driver run? give this one another address: --listen or 'listen' in its config)"
                if exc.errno == errno.EADDRINUSE
                else ""
            )
            raise error(f"cannot listen on {self.config.listen}: {exc.strerror or exc}{hint}") from None
        try:
            capture = RotatingCapture(
                self.config.capture_dir,
                max_bytes=int(self.config.capture_rotate_mb * 2**20),
                max_age_s=self.config.capture_rotate_s,
                provenance=self._provenance(),
                keep_days=self.config.capture_keep_days,
                max_total_bytes=None if self.config.capture_max_gb is None else int(self.config.capture_max_gb * 1e9),
            )
            self.capture = CaptureSink(capture, on_status=self._on_capture_status)
            self.capture.keep_model(self.model_sha256, self.model_bytes)  # the model the capture starts with
            if self.config.udp:
                self.udp = UdpPublisher(*parse_host_port(self.config.udp), version=self.config.udp_version)
            self.chamber = self._make_chamber()
        except BaseException:  # a start that fails leaves nothing listening or running behind it
            if self.capture is not None:
                self.capture.close()
                self.capture = None
            self.hub.stop()
            raise
        setup = self.config.device.device_setup()
        on_open = None if setup is None else make_on_open(setup, on_result=self.acquisition.on_device_setup)
        self.reader = PortReader(
            self.port_url,
            baudrate=self.config.baud,
            backoff_max_s=PORT_BACKOFF_MAX_S,
            on_state=self._on_port_state,
            on_open=on_open,
            silence_s=self.config.port_silence_s,
        )
        if self.web is not None:
            self.web.view.control_address = format_address(*address)  # the bias banner's ctl command
            log.info("web_listening", address=format_address(*self.web.address), token=self.web.need_token)
        self._acquisition = threading.Thread(target=self.acquisition.run, name="acquisition", daemon=True)
        self._acquisition.start()
        if self.chamber is not None:
            self.chamber.start()
        return address

    def _make_chamber(self) -> ChamberPoller | None:
        """The read-only chamber poller of the ``chamber:`` section, not started (None: no section).  A URL its
        driver refuses is a ``ConfigError`` (exit 78); a missing extra (``lab``) a ``UsageError`` (exit 64)."""
        config = self.config.chamber
        if config is None:
            return None
        try:
            controller = open_daemon_controller(config, lambda line: log.warning("chamber_notice", message=line))
        except UsageError as exc:
            if "pip install" in str(exc):
                raise
            raise ConfigError(f"chamber: url: {exc}") from None
        except FogDriverError as exc:
            raise ConfigError(f"chamber: url: {exc}") from None
        capture = self.capture
        return ChamberPoller(
            config,
            controller,
            capture_path=lambda: None if capture is None else capture.status_fields().get("path"),
            device_t_s=lambda: self.acquisition.last_t_s,
        )

    def _make_web(self):
        """The web view and /metrics on ``http``, not started (UsageError, exit 64 as for every command: the
        web extra is missing; ConfigError: no token beyond loopback, a bad address)."""
        what = f"the web view and /metrics (http {self.config.http})"
        require_extra("web", what)
        from .web.server import WebUnavailable, WebView  # optional extra: web (aiohttp, plotly, prometheus-client)

        try:
            host, port = parse_host_port(self.config.http, default_port=DEFAULT_HTTP_PORT)
            return WebView(
                host,
                port,
                token=self.config.token,
                read_status=self.metrics_state,
                latency=self.latency,
                max_backlog_s=self.config.max_client_backlog_s,
                history_min=self.config.http_history_min,
                open_stream=self.config.open_stream,
                http_hosts=self.config.http_hosts,
                trusted_proxies=self.config.http_trusted_proxies,
                secure_cookies=self.config.http_secure_cookies,
            )
        except WebUnavailable as exc:  # (a module found by require_extra but not by the web view's own check)
            raise UsageError(f"{what}: {exc}") from None
        except ValueError as exc:
            raise ConfigError(f"http {self.config.http}: {exc}") from None

    def _start_web(self, web) -> None:
        """Start the web view (TemporaryFailure: its address is in use or not there yet); ``self.web`` from then on."""
        try:
            web.start()
        except OSError as exc:
            error = TemporaryFailure if exc.errno in (errno.EADDRINUSE, errno.EADDRNOTAVAIL) else ConfigError
            raise error(f"cannot listen on {self.config.http} (http): {exc.strerror or exc}") from None
        web.publish(self.version_object())
        web.publish(self.device_object())
        self.web = web

    def metrics_state(self) -> dict[str, Any]:
        """What ``/metrics`` reads at each scrape (``status.metrics_state``; any thread)."""
        return status.metrics_state(self)

    def _provenance(self) -> dict[str, Any]:
        """What a capture's sidecar records so the published output can be reproduced from it."""
        c = self.config
        return {
            "source": "fog-driver run",
            "port": self.port_url,
            "baud": c.baud,
            "fog_driver_version": __version__,
            "pid": os.getpid(),
            "model": self._model_provenance(),
            **(self.source.wire.sidecar_fields() if self.source.wire is not None else {}),
            "settings": {
                "scale_arcsec_per_count": c.scale_arcsec_per_count,
                "scale_override_arcsec_per_count": c.scale_override_arcsec_per_count,
                "force_model": c.force_model,
                "adapt_reference_dph": c.adapt_reference_dph,
                "adapt_state": c.adapt_state,
                "adapt_state_sha256": self.adapt_state_sha256,
            },
        }

    def _model_provenance(self) -> dict[str, Any]:
        """The model in use, as a capture's sidecar records it (a copy is kept beside the captures)."""
        return {
            "path": self.model_path,
            "sha256": self.model_sha256,
            "kind": self.model_file.kind,
            "created_utc": self.model_file.created_utc,
            "instrument_serial": self.model_file.instrument_serial,
        }

    def _making_progress(self) -> bool:
        """Whether the watchdog may be pinged: the acquisition and hub threads live and the port reader's loop
        comes round (a quiet port still does, at its read timeout)."""
        if self._acquisition is None or not self._acquisition.is_alive():
            return False
        if self.hub is not None and not self.hub.running:
            return False
        reader = self.reader
        return reader is None or time.monotonic() - reader.last_activity_monotonic < READER_STALL_S

    def run_until_stopped(self, on_status=None) -> int:
        """The main loop: STATUS and a log summary every ``status_every_s`` (read afresh each time, so a SIGHUP
        applies it), the watchdog at its own cadence, until ``stop``."""
        self.notifier = Notifier.from_environment()
        self.notifier.ready(status=f"listening on {self.config.listen}")
        next_status = time.monotonic() + self.config.status_every_s
        try:
            while True:
                tick = self.notifier.loop_wait_s(self.config.status_every_s)
                if self.stop.wait(max(0.0, min(tick, next_status - time.monotonic()))):
                    break
                now = time.monotonic()
                if self._making_progress():
                    self.notifier.maybe_watchdog(now)
                if now < next_status:
                    continue
                next_status = now + self.config.status_every_s
                with self.lock:
                    status = self.status_object()
                self.publish(status)
                # the model is logged when the daemon starts (model_in_use) and reloads it, not every second
                log.info("status", **{k: v for k, v in status.items() if k not in ("class", "model_file")})
                self.notifier.status(
                    f"{status['port_state']}, {status['frames']} frames, "
                    f"{status.get('clients', 0)} clients, capture {status.get('capture_state')}"
                )
                if on_status:
                    on_status(status)
        finally:
            self.shutdown()
        if self.adapt_state_not_saved is not None:
            if self.failure is None:
                raise self.adapt_state_not_saved  # exit 73, on one line: the state this run adapted is lost
            log.error("adapt_state_not_saved", reason=str(self.adapt_state_not_saved))
        if isinstance(self.failure, FogDriverError):
            raise self.failure  # the CLI prints it on one line, with its exit status
        return 0 if self.failure is None else 1

    def shutdown(self) -> None:
        """Stop acquiring, save the adaptation (only if it ran, and not when it is in memory only), close the
        capture and the hub (SIGTERM ends here, exit 0; a state that cannot be saved is kept in
        ``adapt_state_not_saved``, and the run ends in it: exit 73).  Each wait is bounded: ``JOIN_TIMEOUT_S``
        for the acquisition and for the capture."""
        self.stop.set()
        with self.lock:
            if self.acquisition.bias_capture is not None:  # its result would come after the clients are gone
                self.acquisition.bias_capture.timer.cancel()
        if self.notifier is not None:
            self.notifier.stopping()
        if self._acquisition is not None:
            self._acquisition.join(timeout=JOIN_TIMEOUT_S)
        doc = None
        with self.lock:
            path = self.config.adapt_state
            if self.compensator is not None and path and path != self.adapt_state_in_memory and self._adapt_touched:
                doc = self.compensator.adaptation_document()
        if doc is not None:
            try:
                self.save_adapt_state(doc, log_failure=False)  # the run ends in it (``run_until_stopped``)
            except OutputFileError as exc:
                self.adapt_state_not_saved = exc
        if self.chamber is not None:
            self.chamber.close(JOIN_TIMEOUT_S)
        if self.capture is not None and not self.capture.close(JOIN_TIMEOUT_S):
            log.error("capture_not_closed", reason=f"the capture thread did not finish within {JOIN_TIMEOUT_S} s")
        if self.hub is not None:
            self.hub.stop()
        if self.web is not None:
            self.web.stop()
        if self.udp is not None:
            self.udp.close()


__all__ = ["PROTO_MAJOR", "PROTO_MINOR", "ConfigError", "Service", "stamp_utc"]
