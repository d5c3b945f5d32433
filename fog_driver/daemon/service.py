"""The headless daemon: acquisition -> compensation -> publishing, with control and an always-on raw capture.

Threads and who owns what:

* the acquisition thread reads the port (``PortReader``: reconnects within
  ``backoff_max_s`` of the port coming back), appends every byte to the raw
  capture, decodes, compensates sample by sample and hands each chunk's ANGLE
  objects to the hub in one call; it never waits on a client, on disk beyond
  its own append, or on logging;
* the hub's thread serves clients (``hub.py``);
* the main thread publishes STATUS, logs a one-line summary and pings the
  systemd watchdog every ``status_every_s``, and handles signals.

The pipeline state (decoder, stream, compensator, angle offsets) is touched
under one lock: by the acquisition thread per chunk, and by control commands.

Angles: ``angle_arcsec`` is the compensated angle integrated from the frames
(``Compensator.angle_comp_arcsec``) less the offsets ``?ZERO`` and ``?BIAS``
introduce; without them it equals ``fog-driver compensate`` on the daemon's
own raw capture, bit for bit (tested).  Frames lost while the port was away
carry no increment: the angle continues from the last frame received and the
first frame after the gap is flagged ``gap``.
"""

from __future__ import annotations

import dataclasses
import math
import resource
import threading
import time
from concurrent.futures import Future
from pathlib import Path
from typing import Any

import structlog

from .. import __version__
from ..compensation.adapt import AdaptConfig
from ..compensation.compensator import FLAG_NAMES, CompensatedSample, Compensator, flag_names
from ..compensation.model import ModelFile, load_model
from ..config import DriverConfig, parse_host_port
from ..errors import FogDriverError
from ..protocol import FrameDecoder, IdentityFrame
from ..transport import PortError, PortEvent, PortReader

log = structlog.get_logger("fog_driver.daemon")

PROTO_MAJOR = 1
PROTO_MINOR = 0


def _current_rss_mb() -> float:
    """The resident set size now (VmRSS; Linux), else the peak (``ru_maxrss``)."""
    try:
        with open("/proc/self/status", encoding="ascii") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return round(int(line.split()[1]) / 1024.0, 1)
    except OSError:
        pass
    return round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, 1)


class ConfigError(FogDriverError):
    """A bad configuration or model: exit 78 (EX_CONFIG), so systemd does not restart in a loop."""

    exit_status = 78


class Service:
    """One instrument: its port, its model, its clients."""

    def __init__(self, config: DriverConfig, *, port: str, model_file: ModelFile | None = None) -> None:
        self.config = config
        self.port_url = port
        try:
            self.model_file = model_file or load_model(config.model_path)
        except FogDriverError as exc:
            raise ConfigError(str(exc)) from None
        for line in self.model_file.warnings(str(config.model_path)):
            log.warning("model_warning", message=line)
        self.lock = threading.Lock()
        self.stop = threading.Event()
        self.started_monotonic = time.monotonic()
        self._reset_pipeline()
        self.identity: IdentityFrame | None = None
        self.port_state = "closed"
        self.samples_published = 0
        self.flagged = dict.fromkeys(FLAG_NAMES.values(), 0)  # published samples per flag, since start
        self.samples_before_identity: list = []
        self.zero_raw_arcsec = 0.0
        self.zero_comp_arcsec = 0.0
        self.bias_dph = 0.0
        self.bias_angle_arcsec = 0.0
        self._bias_capture: dict[str, Any] | None = None
        self.hub = None
        self.rawlog = None
        self.udp = None
        self.notifier = None
        self._acquisition: threading.Thread | None = None
        self.failure: BaseException | None = None
        self._cpu_mark = (time.monotonic(), time.process_time())

    def _reset_pipeline(self) -> None:
        self.decoder = FrameDecoder()
        self.stream = self.config.sample_stream()
        self.compensator: Compensator | None = None

    # -- objects clients see -------------------------------------------------------------------

    def version_object(self) -> dict:
        obj: dict[str, Any] = {"class": "VERSION", "release": __version__, "proto_major": PROTO_MAJOR,
                               "proto_minor": PROTO_MINOR, "model": self.model_file.kind}  # fmt: skip
        if self.identity is not None:
            obj["instrument"] = self._identity_fields()
        return obj

    def _identity_fields(self) -> dict:
        i = self.identity
        return {"serial": i.serial, "firmware": i.firmware_version, "rate_hz": i.rate_hz,
                "scale_arcsec_per_count": i.scale_arcsec_per_count}  # fmt: skip

    def device_object(self) -> dict | None:
        obj: dict[str, Any] = {"class": "DEVICE", "path": self.port_url,
                               "state": "activated" if self.port_state == "open" else "deactivated"}  # fmt: skip
        if self.identity is not None:
            obj.update(self._identity_fields())
        return obj

    def status_object(self) -> dict:
        now = time.monotonic()
        cpu = time.process_time()
        wall_mark, cpu_mark = self._cpu_mark
        self._cpu_mark = (now, cpu)
        c = self.decoder.counters
        obj: dict[str, Any] = {
            "class": "STATUS",
            "uptime_s": round(now - self.started_monotonic, 3),
            "port_state": self.port_state,
            "bytes_in": c.bytes_in,
            "frames": c.sample_frames,
            "crc_errors": c.crc_errors,
            "bytes_discarded": c.bytes_discarded,
            "seq_gaps": c.seq_gaps,
            "missing_frames": c.missing_frames,
            "published": self.samples_published,
            "flagged": dict(self.flagged),
            "cpu_percent": round(100.0 * (cpu - cpu_mark) / max(now - wall_mark, 1e-9), 2),
            "rss_mb": _current_rss_mb(),
            "bias_dph": self.bias_dph,
            "adapting": bool(self.compensator and self.compensator.reference_rate_dph is not None),
        }
        online = self.compensator.online if self.compensator is not None else None
        if online is not None:  # is the published drift the adapted weights' (the comparison guard's verdict)?
            obj["adapted_in_use"] = online.adapted_in_use
        if self.hub is not None:
            obj["clients"] = self.hub.clients
            obj["dropped_clients"] = self.hub.dropped_clients
        if self.rawlog is not None and self.rawlog.current_path is not None:
            obj["capture"] = str(self.rawlog.current_path)
        return obj

    def angle_object(self, c: CompensatedSample) -> dict:
        period = self.compensator.frame_period_s
        rate_comp = c.dtheta_comp_arcsec / period - self.bias_dph
        temps = {name: t for name, t in zip(("top", "bottom", "housing"), c.temps_c) if t == t}
        return {
            "class": "ANGLE",
            "seq": c.seq,
            "t_s": c.t_s,
            "angle_arcsec": c.angle_comp_arcsec - self.zero_comp_arcsec - self.bias_angle_arcsec,
            "angle_raw_arcsec": c.angle_raw_arcsec - self.zero_raw_arcsec,
            "rate_dph": rate_comp,
            "rate_raw_dph": c.dtheta_arcsec / period,
            "drift_dph": c.drift_dph,
            "temps_c": temps,
            "flags": flag_names(c.flags),
        }

    # -- acquisition ---------------------------------------------------------------------------

    def _on_port_state(self, event: PortEvent) -> None:
        self.port_state = event.state
        if event.state in ("open", "lost") and self.hub is not None:
            self.hub.publish(self.device_object())

    def _new_compensator(self) -> Compensator:
        compensator = Compensator(self.model_file, 1.0 / self.identity.rate_hz, adapt=AdaptConfig(),
                                  reference_rate_dph=self.config.adapt_reference_dph)  # fmt: skip
        if self.config.adapt_state and Path(self.config.adapt_state).exists():
            compensator.load_adaptation(self.config.adapt_state)
        return compensator

    def process(self, chunk: bytes) -> list[dict]:
        """Bytes from the port -> ANGLE objects (the acquisition thread; also used by tests)."""
        angles: list[dict] = []
        with self.lock:
            for event in self.decoder.feed(chunk):
                sample = self.stream.step(event)
                if isinstance(event, IdentityFrame):
                    changed = self.identity is None or self.identity[1:] != event[1:]
                    self.identity = event
                    if changed and self.hub is not None:
                        self.hub.publish(self.device_object())
                if sample is None:
                    continue
                if self.compensator is None:
                    if self.identity is None:  # frame period unknown until the first IDENTITY
                        self.samples_before_identity.append(sample)
                        continue
                    self.compensator = self._new_compensator()
                    pending, self.samples_before_identity = self.samples_before_identity, []
                    for earlier in pending:
                        angles.append(self._compensate(earlier))
                angles.append(self._compensate(sample))
        return angles

    def _compensate(self, sample) -> dict:
        c = self.compensator.step(sample)
        period = self.compensator.frame_period_s
        if self._bias_capture is not None:
            capture = self._bias_capture
            capture["sum_arcsec"] += c.dtheta_comp_arcsec
            capture["seconds"] += period
            if capture["seconds"] >= capture["target_s"]:
                self.bias_dph = capture["sum_arcsec"] / capture["seconds"]
                self._bias_capture = None
                capture["future"].set_result({"class": "BIAS", "bias_dph": self.bias_dph,
                                              "seconds": capture["seconds"]})  # fmt: skip
        self.bias_angle_arcsec += self.bias_dph * period
        obj = self.angle_object(c)
        if self.udp is not None:
            self.udp.send(obj)
        self.samples_published += 1
        for name in obj["flags"]:  # the names angle_object already made
            self.flagged[name] += 1
        return obj

    def _acquire(self) -> None:
        baud = self.config.baud
        reader = PortReader(self.port_url, baudrate=baud, backoff_max_s=1.0, on_state=self._on_port_state)
        try:
            for chunk in reader.chunks(self.stop):
                if self.rawlog is not None:
                    with self.lock:  # the status loop polls (flushes, rotates) the capture too
                        self.rawlog.write(chunk)
                angles = self.process(chunk)
                if angles and self.hub is not None:
                    self.hub.publish_angles(angles)
        except PortError as exc:  # a URL no handler understands, bad settings: retrying cannot help
            log.error("acquisition_stopped", reason=str(exc))
            self.failure = ConfigError(str(exc))
            self.stop.set()
        except FogDriverError as exc:
            log.error("acquisition_stopped", reason=str(exc))
            self.failure = exc
            self.stop.set()
        except Exception as exc:  # a bug: log it with its traceback, and stop cleanly
            log.exception("acquisition_crashed", reason=str(exc))
            self.failure = exc
            self.stop.set()

    # -- control (called from the hub's thread) -------------------------------------------------

    def control(self, name: str, args: dict, client_id: int) -> dict | Future:
        handler = getattr(self, f"_cmd_{name.lower()}", None)
        if handler is None:
            return {"class": "ERROR", "message": f"unknown command ?{name}"}
        with self.lock:
            return handler(args)

    def _cmd_status(self, args: dict) -> dict:
        return self.status_object()

    def _cmd_zero(self, args: dict) -> dict:
        """Zero the published angles here (the raw capture and the model are untouched)."""
        if self.compensator is None:
            return {"class": "ERROR", "message": "no samples yet: nothing to zero"}
        self.zero_raw_arcsec = self.compensator.angle_raw_arcsec
        self.zero_comp_arcsec = self.compensator.angle_comp_arcsec - self.bias_angle_arcsec
        return {"class": "ZERO", "zeroed": True}

    def _cmd_bias(self, args: dict) -> dict | Future:
        """Capture the residual bias over N seconds (device time) of static data, then remove it."""
        seconds = args.get("seconds", 60)
        if isinstance(seconds, bool) or not isinstance(seconds, (int, float)) or not 1 <= seconds <= 86400:
            return {"class": "ERROR", "message": "?BIAS needs \"seconds\" between 1 and 86400"}
        if self._bias_capture is not None:
            return {"class": "ERROR", "message": "a bias capture is already running"}
        future: Future = Future()
        self._bias_capture = {"target_s": float(seconds), "sum_arcsec": 0.0, "seconds": 0.0, "future": future}
        return future

    def _cmd_adapt(self, args: dict) -> dict:
        if self.compensator is None:
            return {"class": "ERROR", "message": "no samples yet: nothing to adapt"}
        enable = args.get("enable")
        if not isinstance(enable, bool):
            return {"class": "ERROR", "message": "?ADAPT needs \"enable\": true or false"}
        reference = args.get("reference_dph", 0.0)
        if isinstance(reference, bool) or not isinstance(reference, (int, float)) or not math.isfinite(reference):
            return {"class": "ERROR", "message": "\"reference_dph\" must be a number (deg/h, 0 at rest)"}
        self.compensator.reference_rate_dph = float(reference) if enable else None
        return {"class": "ADAPT", "enable": enable, **({"reference_dph": float(reference)} if enable else {})}

    def _cmd_save(self, args: dict) -> dict:
        path = self.config.adapt_state
        if not path:
            return {"class": "ERROR", "message": "no adapt_state file configured"}
        if self.compensator is None:
            return {"class": "ERROR", "message": "no samples yet: nothing to save"}
        try:
            self.compensator.save_adaptation(path)
        except FogDriverError as exc:
            return {"class": "ERROR", "message": str(exc)}
        return {"class": "SAVE", "path": str(path)}

    def _cmd_reload(self, args: dict) -> dict:
        """Load the model file again; the angles carry on from where they are."""
        try:
            model_file = load_model(self.config.model_path)
        except FogDriverError as exc:  # keep running with the model in use
            log.error("model_reload_failed", reason=str(exc))
            return {"class": "ERROR", "message": str(exc)}
        self.reload_model(model_file)
        for line in model_file.warnings(str(self.config.model_path)):
            log.warning("model_warning", message=line)
        log.info("model_reloaded", model=str(self.config.model_path), kind=model_file.kind,
                 created_utc=model_file.created_utc)  # fmt: skip
        return {"class": "RELOAD", "model": model_file.kind, "created_utc": model_file.created_utc}

    #: Settings a SIGHUP can change in a running daemon; the others need a restart.
    RESTART_KEYS = ("port", "baud", "listen", "udp", "capture_dir", "capture_rotate_mb", "capture_rotate_s")

    def reload_config(self, config: DriverConfig) -> dict:
        """SIGHUP: take the new settings that can change live, then reload the model file."""
        with self.lock:
            ignored = [k for k in self.RESTART_KEYS if getattr(config, k) != getattr(self.config, k)]
            self.config = dataclasses.replace(config, **{k: getattr(self.config, k) for k in self.RESTART_KEYS})
            if self.hub is not None:
                self.hub.max_backlog_s = self.config.max_client_backlog_s
            if self.compensator is not None:
                self.compensator.reference_rate_dph = self.config.adapt_reference_dph
            result = self._cmd_reload({})
        if ignored:
            log.warning("config_needs_restart", keys=ignored)
        log.info("config_reloaded", restart_needed=ignored)
        return result

    def reload_model(self, model_file: ModelFile) -> None:
        """Compensate with ``model_file`` from the next block on, without a restart of the pipeline: the
        angles, the open block and the feature smoothers carry on; the same model reloaded also keeps its
        memory (reservoir) and its adaptation; a different model starts at rest at the current inputs (as
        at switch-on), and its adaptation from its saved state, if any."""
        old = self.compensator
        self.model_file = model_file
        if old is not None:
            new = self._new_compensator()
            new.angle_raw_arcsec, new.angle_comp_arcsec = old.angle_raw_arcsec, old.angle_comp_arcsec
            new.continue_from(old, same_model=_same_model(old.model_file, model_file))
            self.compensator = new

    # -- life cycle ----------------------------------------------------------------------------

    def start(self) -> tuple[str, int]:
        """Listen, open the raw capture, start acquiring; returns the listening address."""
        from .hub import Hub
        from .rawlog import RotatingCapture

        host, port = parse_host_port(self.config.listen)
        try:
            self.hub = Hub(host, port, version=self.version_object, device=self.device_object,
                           control=self.control, token=self.config.token,
                           max_backlog_s=self.config.max_client_backlog_s,
                           sndbuf_bytes=256 * 1024)  # a non-reading client is noticed in seconds, not megabytes  # fmt: skip
        except ValueError as exc:
            raise ConfigError(f"listen {self.config.listen}: {exc}") from None
        try:
            address = self.hub.start()
        except OSError as exc:
            raise ConfigError(f"cannot listen on {self.config.listen}: {exc.strerror or exc}") from None
        self.rawlog = RotatingCapture(
            self.config.capture_dir,
            max_bytes=int(self.config.capture_rotate_mb * 2**20),
            max_age_s=self.config.capture_rotate_s,
            provenance={"source": "fog-driver run", "port": self.port_url, "baud": self.config.baud,
                        "fog_driver_version": __version__},  # fmt: skip
        )
        if self.config.udp:
            from .udp import UdpPublisher

            self.udp = UdpPublisher(*parse_host_port(self.config.udp))
        self._acquisition = threading.Thread(target=self._acquire, name="acquisition", daemon=True)
        self._acquisition.start()
        return address

    def run_until_stopped(self, on_status=None) -> int:
        """The main loop: STATUS and a log summary every ``status_every_s``, until ``stop``."""
        from .sdnotify import Notifier

        self.notifier = Notifier.from_environment()
        self.notifier.ready(status=f"listening on {self.config.listen}")
        every = self.config.status_every_s
        try:
            while not self.stop.wait(every):
                with self.lock:
                    if self.rawlog is not None:
                        self.rawlog.poll()  # a quiet port still flushes, and rotates by age
                    status = self.status_object()
                self.hub.publish(status)
                log.info("status", **{k: v for k, v in status.items() if k != "class"})
                self.notifier.status(f"{status['port_state']}, {status['frames']} frames, "
                                     f"{status.get('clients', 0)} clients")  # fmt: skip
                if self._acquisition is not None and self._acquisition.is_alive():
                    self.notifier.maybe_watchdog(time.monotonic())  # only while acquisition lives
                if on_status:
                    on_status(status)
        finally:
            self.shutdown()
        if isinstance(self.failure, FogDriverError):
            raise self.failure  # the CLI prints it on one line, with its exit status
        return 0 if self.failure is None else 1

    def shutdown(self) -> None:
        """Flush and close everything (SIGTERM ends here, exit 0)."""
        self.stop.set()
        if self.notifier is not None:
            self.notifier.stopping()
        if self._acquisition is not None:
            self._acquisition.join(timeout=10)
        with self.lock:
            if self.compensator is not None and self.config.adapt_state:
                try:
                    self.compensator.save_adaptation(self.config.adapt_state)
                except FogDriverError as exc:
                    log.error("adapt_state_not_saved", reason=str(exc))
        if self.rawlog is not None:
            with self.lock:  # after the acquisition thread has ended (or given up on after 10 s)
                self.rawlog.close()
        if self.hub is not None:
            self.hub.stop()


def _same_model(a: ModelFile, b: ModelFile) -> bool:
    """The same drift model (kind, normalization and every matrix): its memory and adaptation carry over."""
    return a.kind == b.kind and a.normalizer.to_dict() == b.normalizer.to_dict() and a.model.to_dict() == b.model.to_dict()
