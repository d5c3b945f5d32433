"""The headless daemon: acquisition -> compensation -> publishing, with control and an always-on raw capture.

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

Angles: ``angle_arcsec`` is the compensated angle integrated from the frames
(``Compensator.angle_comp_arcsec``) less the offsets ``?ZERO`` and ``?BIAS``
introduce.  Frames lost while the port was away carry no increment: the angle continues from the last frame
received and the first frame after the gap is flagged ``gap``.

Live == offline.  The published ``angle_arcsec`` equals ``fog-driver compensate`` (``apply.compensate_capture``)
on the daemon's raw capture (its files concatenated in name order), bit for bit, when the offline run is given
the daemon's settings: ``--scale-override`` for ``scale_override_arcsec_per_count``, ``--force`` for
``force_model``, and with an ``adapt_state`` the state file as it was at the start with ``--adapt-state``
(``--adapt-reference`` for ``adapt_reference_dph``), and when during the capture no ``?ZERO`` or ``?BIAS``
offset was taken, no ``?ADAPT`` changed the reference and no different model was loaded.  (ANGLE's ``utc``, the
host's clock when the sample was read, is the one key that cannot be reproduced offline; see ``stamp_utc``.)  Each of
those is recorded in the capture's sidecar (``events``, with the byte of the file it took effect at), as are the
model (path, SHA-256), the scale settings, the adaptation state's SHA-256 and the instrument.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import errno
import hashlib
import math
import os
import resource
import threading
import time
from pathlib import Path
from typing import Any

import structlog

from .. import __version__
from ..compensation.adapt import AdaptConfig
from ..compensation.binding import InstrumentCompensation, ModelMismatchError, check_channels
from ..compensation.model import ModelFile
from ..compensation.pipeline import (
    FLAG_NAMES,
    CompensatedSample,
    Compensator,
    flag_names,
)
from ..errors import FogDriverError, TemporaryFailure
from ..modelfiles import adaptation_restorer, load_model, read_state_doc, write_state_doc
from ..protocol import IdentityFrame
from ..samples.sources import make_source
from ..samples.stream import identity_is_plausible
from ..transport import PortError, PortEvent, PortReader
from ..transport.setup import make_on_open
from .config import DriverConfig, parse_host_port
from .limits import (
    BIAS_ANSWER_MARGIN_S,
    CLIENT_SNDBUF_BYTES,
    DEFAULT_BIAS_S,
    JOIN_TIMEOUT_S,
    MAX_ADAPT_REFERENCE_DPH,
    MAX_BIAS_S,
    MAX_SAMPLES_BEFORE_IDENTITY,
    MIN_BIAS_S,
    PORT_BACKOFF_MAX_S,
    READER_STALL_S,
)
from .web.metrics import LatencyHistogram

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


def _file_sha256(path: str | Path) -> str | None:
    """A file's SHA-256, or None when it cannot be read."""
    try:
        return hashlib.sha256(Path(path).read_bytes()).hexdigest()
    except OSError:
        return None


class ConfigError(FogDriverError):
    """A bad configuration or model: exit 78 (EX_CONFIG), so systemd does not restart in a loop."""

    exit_status = 78


class Service:
    """One instrument: its port, its model, its clients."""

    #: Settings that need a restart; every other one applies on SIGHUP (``reload_config``).
    RESTART_KEYS = (
        "port",
        "baud",
        "listen",
        "udp",
        "http",
        "http_history_min",
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
    )

    def __init__(self, config: DriverConfig, *, port: str, model_file: ModelFile | None = None) -> None:
        self.config = config
        self.port_url = port
        try:
            self.model_file = model_file or load_model(config.model_path)
        except FogDriverError as exc:
            raise ConfigError(str(exc)) from None
        self.model_sha256 = None if model_file is not None else _file_sha256(config.model_path)
        for line in self.model_file.warnings(str(config.model_path)):
            log.warning("model_warning", message=line)
        self.lock = threading.Lock()  # the in-memory pipeline only
        self._reload_lock = threading.Lock()  # one reload at a time, never held with ``lock`` while parsing
        self.stop = threading.Event()
        self.started_monotonic = time.monotonic()
        self.adapt_state_sha256 = self._check_adapt_state(self.model_file)
        self.source = make_source(config)
        self._format_problem_said = False
        self._setup_bytes_left = 0  # bytes read during a device setup, still to be skipped by the decoder
        if config.format != "auto":
            self._check_channels(self.model_file, config.wire_settings(), f"the model {config.model_path}")
        self.binding = self._new_binding(self.model_file)
        self.identity: IdentityFrame | None = None
        self.port_state = "closed"
        self.samples_published = 0
        self.flagged = dict.fromkeys(FLAG_NAMES.values(), 0)  # published samples per flag, since start
        self.samples_before_identity: list = []
        self.samples_dropped_before_identity = 0
        self.zero_raw_arcsec = 0.0
        self.zero_comp_arcsec = 0.0
        self.bias_dph = 0.0
        self.bias_angle_arcsec = 0.0
        self._bias_capture: dict[str, Any] | None = None
        self._bias_captures = 0  # ?BIAS captures started (each one's capture_id)
        self.bias_captured = False  # a ?BIAS capture completed: bias_dph is a measured bias, not the default 0
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
        self._acquisition: threading.Thread | None = None
        self.failure: BaseException | None = None
        self._cpu_mark = (time.monotonic(), time.process_time())

    @property
    def compensator(self) -> Compensator | None:
        return self.binding.compensator

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
            hint="set force_model: true in the config to apply it anyway",
            adapt=AdaptConfig(),
            reference_rate_dph=self.config.adapt_reference_dph,
            restore_adaptation=adaptation_restorer(self.config.adapt_state),
        )

    def _check_adapt_state(self, model_file: ModelFile) -> str | None:
        """The configured adaptation state, checked against the model before anything runs: a state saved for
        another model (a re-fit) or a corrupt one is set aside (renamed ``.stale-<UTC>``) with a warning, so
        it can never stop the daemon after it said it was ready.  Returns the usable state's SHA-256."""
        path = self.config.adapt_state
        if not path or not Path(path).exists():
            return None
        try:
            probe = Compensator(model_file, 0.01, adapt=AdaptConfig())
            probe.online.load_state_doc(read_state_doc(path), str(path), detector=probe.static_detector)
        except FogDriverError as exc:
            stamp = _dt.datetime.now(_dt.UTC).strftime("%Y%m%dT%H%M%SZ")
            aside = Path(f"{path}.stale-{stamp}")
            try:
                os.replace(path, aside)
            except OSError as move:
                raise ConfigError(
                    f"{path}: unusable adaptation state ({exc}) that cannot be set aside: {move.strerror or move}"
                ) from None
            log.warning("adapt_state_set_aside", reason=str(exc), moved_to=str(aside))
            return None
        return _file_sha256(path)

    # -- objects clients see -------------------------------------------------------------------

    def version_object(self) -> dict:
        obj: dict[str, Any] = {
            "class": "VERSION",
            "release": __version__,
            "proto_major": PROTO_MAJOR,
            "proto_minor": PROTO_MINOR,
            "model": self.model_file.kind,
        }
        if self.identity is not None:
            obj["instrument"] = self._identity_fields()
        return obj

    def _identity_fields(self) -> dict:
        i = self.identity
        return {
            "serial": i.serial,
            "firmware": i.firmware_version,
            "rate_hz": i.rate_hz,
            "scale_arcsec_per_count": i.scale_arcsec_per_count,
        }

    def device_object(self) -> dict | None:
        obj: dict[str, Any] = {
            "class": "DEVICE",
            "path": self.port_url,
            "state": "activated" if self.port_state == "open" else "deactivated",
        }
        if self.source.wire is not None:
            obj["format"] = self.source.wire.format
        if self.identity is not None:
            obj.update(self._identity_fields())
        if self.capture is not None:
            obj["capture"] = self.capture.state
        return obj

    def status_object(self, *, mark_cpu: bool = True) -> dict:
        """STATUS now; ``mark_cpu``: the CPU share is over the time since the last marked call (the periodic
        STATUS marks it; a client's ``?STATUS`` does not, so it cannot skew the periodic figure)."""
        now = time.monotonic()
        cpu = time.process_time()
        wall_mark, cpu_mark = self._cpu_mark
        if mark_cpu:
            self._cpu_mark = (now, cpu)
        c = self.source.counters
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
            "identities_rejected": self.source.identities_rejected,
            "instrument_changes": self.binding.rebuilds,
            "published": self.samples_published,
            "flagged": dict(self.flagged),
            "cpu_percent": round(100.0 * (cpu - cpu_mark) / max(now - wall_mark, 1e-9), 2),
            "rss_mb": _current_rss_mb(),
            "bias_dph": self.bias_dph,
            "bias_captured": self.bias_captured,
            "adapting": bool(self.compensator and self.compensator.reference_rate_dph is not None),
            "reloads": self.reloads,
        }
        if self._bias_capture is not None:  # a ?BIAS capture running: how far it is, in seconds of device time
            obj["bias_capture_s"] = self._bias_capture["seconds"]
            obj["bias_capture_target_s"] = self._bias_capture["target_s"]
        if self.samples_dropped_before_identity:
            obj["samples_dropped_before_identity"] = self.samples_dropped_before_identity
        if self.source.format_problem is not None:
            obj["format_problem"] = self.source.format_problem
        if self.source.increments_rejected:  # another format's float words that were NaN or no gyro's
            obj["increments_rejected"] = self.source.increments_rejected
        online = self.compensator.online if self.compensator is not None else None
        if online is not None:  # is the published drift the adapted weights' (the comparison guard's verdict)?
            obj["adapted_in_use"] = online.adapted_in_use
        if self.hub is not None:
            obj["clients"] = self.hub.clients
            obj["dropped_clients"] = self.hub.dropped_clients
        if self.web is not None:
            obj["web_clients"] = len(self.web.browsers)
            obj["web_dropped_clients"] = self.web.dropped_browsers
        if self.capture is not None:
            capture = self.capture.status()
            obj["capture_state"] = capture["state"]
            obj["capture_bytes"] = capture["bytes"]
            obj["capture_bytes_lost"] = capture["bytes_lost"]
            if "path" in capture:
                obj["capture"] = capture["path"]
            if "last_error" in capture:
                obj["capture_error"] = capture["last_error"]
        if self.udp is not None:
            obj.update(self.udp.status_fields())
        return obj

    def angle_object(self, c: CompensatedSample) -> dict:
        period = self.compensator.frame_period_s
        rate_comp = c.dtheta_comp_arcsec / period - self.bias_dph
        temps = {name: t for name, t in zip(self.source.temperature_channels, c.temps_c) if t == t}
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

    def _note(self, event: str, **fields: Any) -> None:
        """An event for the capture's sidecar, in order with the bytes (call under ``lock``)."""
        if self.capture is not None:
            self.capture.note({"event": event, **fields})

    # -- acquisition ---------------------------------------------------------------------------

    def _on_port_state(self, event: PortEvent) -> None:
        self.port_state = event.state
        if event.state in ("open", "lost"):
            self._publish(self.device_object())

    def _on_device_setup(self, result) -> None:
        """The setup commands were sent on an open (the reader's thread, before the bytes read meanwhile are
        yielded): logged, and noted in the capture's sidecar in order with the bytes.  The device re-initialises
        its output for about ``settle_s`` after it; its status byte marks the frames it says are invalid."""
        sent = [command.decode("ascii", "replace").strip() for command in result.sent]
        log.info("device_setup", sent=sent, replies=list(result.replies), settle_s=result.settle_s)
        with self.lock:
            # The bytes read during the setup (frames the device sent under its old settings, and its replies)
            # are captured but not decoded; the note says where they are, and offline readers skip them too.
            self._note("device_setup", sent=sent, replies=list(result.replies), bytes_not_decoded=len(result.raw))
            self._setup_bytes_left = len(result.raw)

    def _on_capture_state(self, state: str) -> None:
        self._publish(self.device_object())

    def _publish(self, obj: dict | None) -> None:
        """An object for every authorized client and the web view (non-blocking, any thread)."""
        if obj is None:
            return
        if self.hub is not None:
            self.hub.publish(obj)
        if self.web is not None:
            self.web.publish(obj)

    def process(self, chunk: bytes) -> list[dict]:
        """Bytes from the port -> ANGLE objects (the acquisition thread; also used by tests)."""
        angles: list[dict] = []
        with self.lock:
            if self.capture is not None:
                self.capture.put(chunk)
            if self._setup_bytes_left:  # the setup's bytes: the PortReader yields them as the first chunk
                skipped = min(len(chunk), self._setup_bytes_left)
                self._setup_bytes_left -= skipped
                chunk = chunk[skipped:]
            try:
                items = self.source.feed(chunk)
            except ValueError as exc:  # format auto found a format the config has no device settings for
                raise ConfigError(f"format auto: {exc}") from None
            if self.source.format_problem is not None and not self._format_problem_said:
                self._format_problem_said = True
                log.warning("format_problem", format=self.config.format, problem=self.source.format_problem)
            for sample in items:
                if isinstance(sample, IdentityFrame):
                    self._on_identity(angles, sample)
                    continue
                if not self.binding.bound:  # frame period unknown until the first IDENTITY
                    self.samples_before_identity.append(sample)
                    if len(self.samples_before_identity) > MAX_SAMPLES_BEFORE_IDENTITY:
                        del self.samples_before_identity[0]
                        self.samples_dropped_before_identity += 1
                    continue
                angles.append(self._compensate(sample))
        return angles

    def _on_identity(self, angles: list[dict], identity: IdentityFrame) -> None:
        """An IDENTITY in the stream, in order with the samples around it (an implausible one is counted by the
        stream and changes nothing)."""
        if not identity_is_plausible(identity) or identity == self.identity:
            return
        changed = self.identity is None or self.identity[1:] != identity[1:]
        detected = self.identity is None and self.config.format == "auto"  # the format is known from now on
        self.identity = identity
        if detected:
            check_channels(
                self.model_file, self.source.wire, f"the model {self.config.model_path}", "the instrument"
            )  # ModelMismatchError: exit 78, as below
            log.info("format_detected", format=self.source.wire.format)
            if self.capture is not None:
                self.capture.update_provenance(self.source.wire.sidecar_fields())
        if self.binding.changes_binding(identity):
            first = not self.binding.bound
            self.binding.bind(identity)  # ModelMismatchError: the acquisition stops with exit 78
            fields = self._identity_fields()
            if self.capture is not None:
                self.capture.update_provenance({"instrument": fields})
            if first:
                pending, self.samples_before_identity = self.samples_before_identity, []
                angles.extend(self._compensate(s) for s in pending)
            else:
                self._note("instrument_changed", **fields)
                log.warning("instrument_changed", **fields)
        if changed:
            self._publish(self.device_object())

    def _compensate(self, sample) -> dict:
        c = self.binding.step(sample)
        period = self.compensator.frame_period_s
        if self._bias_capture is not None:
            capture = self._bias_capture
            capture["sum_arcsec"] += c.dtheta_comp_arcsec
            capture["seconds"] += period
            if capture["seconds"] >= capture["target_s"]:
                self._finish_bias(capture)
        self.bias_angle_arcsec += self.bias_dph * period
        obj = self.angle_object(c)
        axes = getattr(sample, "axes_rate_dph", None)  # publish_axes, a three-axis format
        if axes is not None:
            obj["axes_rate_raw_dph"] = {a: r for a, r in zip("xyz", axes) if math.isfinite(r)}
        if self.udp is not None:
            self.udp.send(obj)
        self.samples_published += 1
        for name in obj["flags"]:  # the names angle_object already made
            self.flagged[name] += 1
        return obj

    def _finish_bias(self, capture: dict) -> None:
        """A ``?BIAS`` capture is complete: apply it and publish its result (under ``lock``, in the acquisition
        thread; nobody waits on it, so a client that hung up meanwhile changes nothing)."""
        capture["timer"].cancel()
        self.bias_dph = capture["sum_arcsec"] / capture["seconds"]
        self.bias_captured = True
        self._bias_capture = None
        self._note("bias", bias_dph=self.bias_dph, seconds=capture["seconds"])
        log.info("bias_applied", capture_id=capture["capture_id"], bias_dph=self.bias_dph, seconds=capture["seconds"])
        self._publish_event(
            {
                "class": "BIAS",
                "state": "done",
                "capture_id": capture["capture_id"],
                "bias_dph": self.bias_dph,
                "seconds": capture["seconds"],
            }
        )

    def _publish_event(self, obj: dict) -> None:
        """An event for every authorized client (non-blocking), and kept as ``last_event`` (tests, STATUS-less
        services); never raises into the acquisition."""
        self.last_event = obj
        if self.hub is not None or self.web is not None:
            try:
                self._publish(obj)
            except Exception:  # noqa: BLE001 - an event nobody can take must never stop the acquisition
                log.exception("event_not_published", event=obj.get("class"))

    def _acquire(self) -> None:
        try:
            for chunk in self.reader.chunks(self.stop):
                read_s = time.monotonic()
                angles = self.process(chunk)
                if angles and (self.hub is not None or self.web is not None):
                    stamp_utc(angles, time.time_ns())
                    if self.hub is not None:
                        self.hub.publish_angles(angles, read_s)
                    if self.web is not None:
                        self.web.publish_angles(angles)
        except ModelMismatchError as exc:  # refused at the first IDENTITY: a configuration problem
            log.error("acquisition_stopped", reason=str(exc))
            self.failure = ConfigError(str(exc))
            self.stop.set()
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

    # -- control (called from the hub's worker threads) ----------------------------------------

    def control(self, name: str, args: dict, client_id: int) -> dict:
        handler = getattr(self, f"_cmd_{name.lower()}", None)
        if handler is None:
            return {"class": "ERROR", "message": f"unknown command ?{name}", "command": name}
        return handler(args)

    def _cmd_status(self, args: dict) -> dict:
        with self.lock:
            return self.status_object(mark_cpu=False)

    def _cmd_zero(self, args: dict) -> dict:
        """Zero the published angles here (the raw capture and the model are untouched)."""
        with self.lock:
            if self.compensator is None:
                return {"class": "ERROR", "message": "no samples yet: nothing to zero"}
            self.zero_raw_arcsec = self.compensator.angle_raw_arcsec
            self.zero_comp_arcsec = self.compensator.angle_comp_arcsec - self.bias_angle_arcsec
            self._note("zero")
        return {"class": "ZERO", "zeroed": True}

    def _cmd_bias(self, args: dict) -> dict:
        """Capture the residual bias over N seconds (device time) of static data, then remove it.

        Answered at once (``BIAS`` ``state: started`` with the capture's ``capture_id``); the result is an event
        published later to every authorized client (the one that asked included, if it is still there):
        ``BIAS`` ``state: done`` with ``bias_dph``, or ``state: failed`` with ``reason`` when the N seconds of
        data did not arrive within N + ``BIAS_ANSWER_MARGIN_S`` seconds of host time (the port went away): the
        capture is then abandoned and the bias in use is kept.  One capture at a time."""
        seconds = args.get("seconds", DEFAULT_BIAS_S)
        if (
            isinstance(seconds, bool)
            or not isinstance(seconds, (int, float))
            or not MIN_BIAS_S <= seconds <= MAX_BIAS_S
        ):
            return {"class": "ERROR", "message": f'?BIAS needs "seconds" between {MIN_BIAS_S} and {MAX_BIAS_S}'}
        timeout_s = float(seconds) + BIAS_ANSWER_MARGIN_S
        with self.lock:
            if self._bias_capture is not None:
                return {"class": "ERROR", "message": "a bias capture is already running"}
            self._bias_captures += 1
            capture = {"capture_id": self._bias_captures, "target_s": float(seconds), "sum_arcsec": 0.0, "seconds": 0.0}
            timer = threading.Timer(timeout_s, self._bias_timed_out, args=(capture,))
            timer.daemon = True
            capture["timer"] = timer
            self._bias_capture = capture
            timer.start()
        log.info("bias_started", capture_id=capture["capture_id"], seconds=float(seconds))
        return {
            "class": "BIAS",
            "state": "started",
            "capture_id": capture["capture_id"],
            "seconds": float(seconds),
            "timeout_s": timeout_s,
        }

    def _bias_timed_out(self, capture: dict) -> None:
        """The timer of a ``?BIAS`` capture: abandon it if it is still the one running (its own thread)."""
        with self.lock:
            if self._bias_capture is not capture:
                return  # completed (or replaced) meanwhile
            self._bias_capture = None
            event = {
                "class": "BIAS",
                "state": "failed",
                "capture_id": capture["capture_id"],
                "seconds": capture["target_s"],
                "seconds_captured": capture["seconds"],
                "reason": f"only {capture['seconds']:.1f} of {capture['target_s']:g} s of data arrived within "
                f"{capture['target_s'] + BIAS_ANSWER_MARGIN_S:g} s (is the instrument sending?); "
                f"the bias in use is kept",
            }
            log.warning("bias_failed", capture_id=capture["capture_id"], reason=event["reason"])
            self._publish_event(event)

    def _cmd_adapt(self, args: dict) -> dict:
        enable = args.get("enable")
        if not isinstance(enable, bool):
            return {"class": "ERROR", "message": '?ADAPT needs "enable": true or false'}
        reference = args.get("reference_dph", 0.0)
        if isinstance(reference, bool) or not isinstance(reference, (int, float)) or not math.isfinite(reference):
            return {"class": "ERROR", "message": '"reference_dph" must be a number (deg/h, 0 at rest)'}
        if abs(reference) > MAX_ADAPT_REFERENCE_DPH:
            return {"class": "ERROR", "message": '"reference_dph" must be within +-1e7 deg/h'}
        with self.lock:
            if self.compensator is None:
                return {"class": "ERROR", "message": "no samples yet: nothing to adapt"}
            self._set_reference(float(reference) if enable else None)
        return {"class": "ADAPT", "enable": enable, **({"reference_dph": float(reference)} if enable else {})}

    def _set_reference(self, reference: float | None) -> None:
        """Adapt against ``reference`` (None: frozen) from the next block (under ``lock``)."""
        if reference == self.compensator.reference_rate_dph:
            return
        self.compensator.reference_rate_dph = reference
        self.binding.reference_rate_dph = reference
        self._adapt_touched = self._adapt_touched or reference is not None
        self._note("adapt", reference_dph=reference)

    def _cmd_save(self, args: dict) -> dict:
        path = self.config.adapt_state
        if not path:
            return {"class": "ERROR", "message": "no adapt_state file configured"}
        with self.lock:
            if self.compensator is None:
                return {"class": "ERROR", "message": "no samples yet: nothing to save"}
            doc = self.compensator.adaptation_document()  # a snapshot; written outside the lock
        try:
            write_state_doc(path, doc)
        except FogDriverError as exc:
            return {"class": "ERROR", "message": str(exc)}
        return {"class": "SAVE", "path": str(path)}

    def _cmd_reload(self, args: dict) -> dict:
        """Load the model file again; the angles carry on from where they are."""
        try:
            return self.reload_from_file(self.config)
        except FogDriverError as exc:  # keep running with the model in use
            log.error("model_reload_failed", reason=str(exc))
            return {"class": "ERROR", "message": str(exc)}

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
            model_file = load_model(path)
            self._swap_model(model_file, digest, config.force_model)
            for line in model_file.warnings(str(path)):
                log.warning("model_warning", message=line)
            log.info("model_reloaded", model=str(path), kind=model_file.kind, created_utc=model_file.created_utc)
            return {"class": "RELOAD", "model": model_file.kind, "created_utc": model_file.created_utc, "changed": True}

    def reload_model(self, model_file: ModelFile) -> None:
        """Compensate with ``model_file`` from the next block on (see ``_swap_model``)."""
        with self._reload_lock:
            self._swap_model(model_file, None, self.config.force_model)

    def _swap_model(self, model_file: ModelFile, digest: str | None, force: bool) -> None:
        """Build the compensator for ``model_file`` outside the lock, then swap it in: the angles, the open
        block and the feature smoothers carry on; the same model also keeps its memory (reservoir) and its
        adaptation; a different model starts at rest at the current inputs (as at switch-on) and adapts afresh.
        A model fitted for another instrument than the one on the port is refused (unless ``force``)."""
        identity = self.binding.identity
        if identity is not None:
            self.binding.check(identity, model_file, force=force, model_name="the new model")
        if self.source.wire is not None:
            self._check_channels(model_file, self.source.wire, "the new model")
        new = None
        if identity is not None:
            new = Compensator(model_file, 1.0 / identity.rate_hz, adapt=AdaptConfig())
        with self.lock:  # O(state): the pipeline state is copied, nothing is parsed
            old = self.compensator
            if old is not None and (new is None or new.frame_period_s != old.frame_period_s):
                new = Compensator(model_file, old.frame_period_s, adapt=AdaptConfig())  # the rate changed meanwhile
            if old is not None:
                new.reference_rate_dph = old.reference_rate_dph
                new.angle_raw_arcsec, new.angle_comp_arcsec = old.angle_raw_arcsec, old.angle_comp_arcsec
                new.continue_from(old, same_model=_same_model(old.model_file, model_file))
                self.binding.replace_model(model_file, new)
            else:
                self.binding.model_file = model_file
            self.binding.force = force
            self.model_file = model_file
            self.model_sha256 = digest
            self.reloads += 1
            self._note("model", kind=model_file.kind, created_utc=model_file.created_utc, sha256=digest)

    def reload_config(self, config: DriverConfig) -> dict:
        """SIGHUP: apply every setting that can change live, all or nothing, and say which need a restart.

        The model file is read first (if it cannot be used, nothing changes); then the token, the client
        backlog, the status period, the adaptation reference (only when the file's value changed: a client's
        ``?ADAPT`` is not undone by an unrelated edit), ``adapt_state`` and ``force_model`` apply.  The keys
        of ``RESTART_KEYS`` that changed are kept as they are and reported (``restart_needed``)."""
        restart = [k for k in self.RESTART_KEYS if getattr(config, k) != getattr(self.config, k)]
        new = dataclasses.replace(config, **{k: getattr(self.config, k) for k in self.RESTART_KEYS})
        if self.hub is not None and new.token != self.config.token:
            self.hub.check_token(new.token)  # ValueError (e.g. no token beyond loopback): nothing changed
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
        with self.lock:
            self.binding.force = new.force_model
            if new.adapt_reference_dph != old.adapt_reference_dph and self.compensator is not None:
                self._set_reference(new.adapt_reference_dph)
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
            return self._start_after_web()
        except BaseException:
            if self.web is not None:
                self.web.stop()
                self.web = None
            raise

    def _start_after_web(self) -> tuple[str, int]:
        from .hub import Hub
        from .rawlog import CaptureSink, RotatingCapture

        host, port = parse_host_port(self.config.listen)
        try:
            self.hub = Hub(
                host,
                port,
                version=self.version_object,
                device=self.device_object,
                control=self.control,
                token=self.config.token,
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
            self.capture = CaptureSink(capture, on_state=self._on_capture_state)
            if self.config.udp:
                from .udp import UdpPublisher

                self.udp = UdpPublisher(*parse_host_port(self.config.udp))
        except BaseException:  # a start that fails leaves nothing listening or running behind it
            if self.capture is not None:
                self.capture.close()
                self.capture = None
            self.hub.stop()
            raise
        setup = self.config.device.device_setup()
        on_open = None if setup is None else make_on_open(setup, on_result=self._on_device_setup)
        self.reader = PortReader(
            self.port_url,
            baudrate=self.config.baud,
            backoff_max_s=PORT_BACKOFF_MAX_S,
            on_state=self._on_port_state,
            on_open=on_open,
        )
        if self.web is not None:
            from .config import format_address

            self.web.view.control_address = format_address(*address)  # the bias banner's ctl command
            log.info("web_listening", address=format_address(*self.web.address), token=self.web.need_token)
        self._acquisition = threading.Thread(target=self._acquire, name="acquisition", daemon=True)
        self._acquisition.start()
        return address

    def _make_web(self):
        """The web view and /metrics on ``http``, not started (ConfigError: the extra is missing, no token
        beyond loopback)."""
        from .config import DEFAULT_HTTP_PORT
        from .web.server import WebUnavailable, WebView

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
            )
        except (ValueError, WebUnavailable) as exc:
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
        """What ``/metrics`` reads at each scrape (``metrics.DaemonCollector``): STATUS, DEVICE, VERSION and
        the counters STATUS does not carry (any thread)."""
        with self.lock:
            out: dict[str, Any] = {
                "status": self.status_object(mark_cpu=False),
                "device": self.device_object(),
                "version": self.version_object(),
            }
        reader = self.reader
        if reader is not None:
            out["reconnects"] = max(0, reader.opens - 1)
        if self.capture is not None:
            out["capture_failures"] = self.capture.status()["failures"]
        out["model_age_s"] = _age_s(self.model_file.created_utc)
        return out

    def _provenance(self) -> dict[str, Any]:
        """What a capture's sidecar records so the published output can be reproduced from it."""
        c = self.config
        return {
            "source": "fog-driver run",
            "port": self.port_url,
            "baud": c.baud,
            "fog_driver_version": __version__,
            "pid": os.getpid(),
            "model": {
                "path": str(c.model_path),
                "sha256": self.model_sha256,
                "kind": self.model_file.kind,
                "created_utc": self.model_file.created_utc,
                "instrument_serial": self.model_file.instrument_serial,
            },
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
        from .sdnotify import Notifier

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
                self._publish(status)
                log.info("status", **{k: v for k, v in status.items() if k != "class"})
                self.notifier.status(
                    f"{status['port_state']}, {status['frames']} frames, "
                    f"{status.get('clients', 0)} clients, capture {status.get('capture_state')}"
                )
                if on_status:
                    on_status(status)
        finally:
            self.shutdown()
        if isinstance(self.failure, FogDriverError):
            raise self.failure  # the CLI prints it on one line, with its exit status
        return 0 if self.failure is None else 1

    def shutdown(self) -> None:
        """Stop acquiring, save the adaptation (only if it ran), close the capture and the hub (SIGTERM ends
        here, exit 0).  Each wait is bounded: ``JOIN_TIMEOUT_S`` for the acquisition and for the capture."""
        self.stop.set()
        with self.lock:
            if self._bias_capture is not None:  # its result would come after the clients are gone
                self._bias_capture["timer"].cancel()
        if self.notifier is not None:
            self.notifier.stopping()
        if self._acquisition is not None:
            self._acquisition.join(timeout=JOIN_TIMEOUT_S)
        doc = None
        with self.lock:
            if self.compensator is not None and self.config.adapt_state and self._adapt_touched:
                doc = self.compensator.adaptation_document()
        if doc is not None:
            try:
                write_state_doc(self.config.adapt_state, doc)
            except FogDriverError as exc:
                log.error("adapt_state_not_saved", reason=str(exc))
        if self.capture is not None and not self.capture.close(JOIN_TIMEOUT_S):
            log.error("capture_not_closed", reason=f"the capture thread did not finish within {JOIN_TIMEOUT_S} s")
        if self.hub is not None:
            self.hub.stop()
        if self.web is not None:
            self.web.stop()
        if self.udp is not None:
            self.udp.close()


def stamp_utc(angles: list[dict], now_ns: int) -> None:
    """Give each ANGLE object ``utc``: the host's UTC clock when the daemon read the bytes that completed the
    sample (``now_ns``, from ``time.time_ns()``), ISO 8601 to the millisecond (``2026-12-02T14:56:26.123Z``).

    Host time, beside the device's ``t_s``: a station logging ANGLE lines can line them up with other
    instruments.  It is added after ``Service.process``, so the pipeline's output stays a function of the
    port's bytes alone (``compensate`` of the capture gives it exactly); live and offline ANGLE objects differ
    by this key only.  One chunk's samples share one stamp (a chunk is what one read returned)."""
    seconds, ns = divmod(now_ns, 1_000_000_000)
    stamp = time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(seconds)) + f".{ns // 1_000_000:03d}Z"
    for obj in angles:
        obj["utc"] = stamp


def _age_s(created_utc: str) -> float | None:
    """Seconds since an ISO 8601 UTC time (a model's ``created_utc``), or None when it is not one."""
    try:
        created = _dt.datetime.fromisoformat(created_utc.replace("Z", "+00:00"))
    except (ValueError, AttributeError):
        return None
    if created.tzinfo is None:
        created = created.replace(tzinfo=_dt.UTC)
    return (_dt.datetime.now(_dt.UTC) - created).total_seconds()


def _same_model(a: ModelFile, b: ModelFile) -> bool:
    """The same drift model (kind, normalization and every matrix): its memory and adaptation carry over."""
    return (
        a.kind == b.kind and a.normalizer.to_dict() == b.normalizer.to_dict() and a.model.to_dict() == b.model.to_dict()
    )


__all__ = ["ConfigError", "Service", "stamp_utc"]
