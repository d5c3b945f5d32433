"""The hot loop: port -> decoder -> compensator -> publish, and the pipeline state it owns.

``Acquisition.run`` is the acquisition thread's body: it reads the port (``PortReader.chunks``), hands every
byte to the raw capture (``CaptureSink.put``: O(1), never a wait for the disk), decodes, compensates sample by
sample (``process``) and hands each chunk's ANGLE objects to the hub and the web view in one call each; it never
waits on a client, on the disk or on logging.  ``process`` runs under the service's ``lock``, which guards the
in-memory pipeline only (decoder, stream, compensator, angle offsets).

Angles: ``angle_arcsec`` is the compensated angle integrated from the frames (``Compensator.angle_comp_arcsec``)
less the offsets ``?ZERO`` and ``?BIAS`` introduce:
``angle_arcsec = angle_comp_arcsec - zero_comp_arcsec - bias_angle_arcsec``, with ``bias_angle_arcsec`` the
integral of ``bias_dph`` over the frame periods since the bias was set, and ``rate_dph = dtheta_comp_arcsec /
period_s - bias_dph`` (arcsec/s is deg/h).  Frames lost while the port was away carry no increment: the angle
continues from the last frame received and the first frame after the gap is flagged ``gap``.

The service is this room's owner: the acquisition reads its public names only (``config``, ``lock``,
``source``, ``binding``, ``model_file``, ``capture``, ``udp``, ``hub``, ``web``, ``reader``, ``stop``) and
calls ``process`` (its entry point for each chunk, which is ``Acquisition.process``), ``publish``,
``publish_event``, ``note`` and ``device_object``.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass
from typing import Any

import structlog

from ..compensation.binding import ModelMismatchError, check_channels
from ..compensation.offsets import PublishOffsets
from ..compensation.pipeline import CompensatedSample
from ..errors import FogDriverError
from ..flags import FLAG_NAMES, flag_names
from ..protocol import IdentityFrame
from ..samples.stream import identity_is_plausible
from ..transport import PortError
from .errors import ConfigError
from .limits import MAX_SAMPLES_BEFORE_IDENTITY
from .status import identity_fields

__all__ = ["Acquisition", "BiasCapture", "PortOutage", "stamp_utc"]

log = structlog.get_logger("fog_driver.daemon")


@dataclass(eq=False)
class BiasCapture:
    """A ``?BIAS`` capture running: the compensated increments of ``target_s`` seconds of device time, summed.

    The bias it measures is ``bias_dph = sum_arcsec / seconds`` (the mean compensated rate; arcsec/s is deg/h).
    The drift estimate's error during the capture went into it: its 1-sigma is ``sigma_dph``, the mean of the
    ``drift_sigma_dph`` of the samples that had one, ``sigma_sum_dph / sigma_samples`` (NaN when none had)."""

    capture_id: int
    target_s: float
    sum_arcsec: float = 0.0
    seconds: float = 0.0
    timer: threading.Timer | None = None
    sigma_sum_dph: float = 0.0
    sigma_samples: int = 0

    def add(self, dtheta_comp_arcsec: float, period_s: float, drift_sigma_dph: float = math.nan) -> bool:
        """One sample's increment (and its drift estimate's sigma); True once ``target_s`` seconds are in."""
        self.sum_arcsec += dtheta_comp_arcsec
        self.seconds += period_s
        if math.isfinite(drift_sigma_dph):
            self.sigma_sum_dph += drift_sigma_dph
            self.sigma_samples += 1
        return self.seconds >= self.target_s

    @property
    def sigma_dph(self) -> float:
        return self.sigma_sum_dph / self.sigma_samples if self.sigma_samples else math.nan


class Acquisition:
    """The pipeline state between the port and the clients, and the thread that moves samples through it."""

    def __init__(self, service: Any) -> None:  # the owning ``service.Service``
        self.service = service
        self.identity: IdentityFrame | None = None
        self.samples_before_identity: list = []
        self.samples_dropped_before_identity = 0
        self.samples_published = 0
        #: the sequence number of the last sample compensated (the sidecar's events say where they took effect)
        self.last_seq: int | None = None
        self.last_t_s: float | None = None
        self.flagged = dict.fromkeys(FLAG_NAMES.values(), 0)  # published samples per flag, since start
        self.offsets = PublishOffsets()  #: what ?ZERO and ?BIAS do to the published angles (a replay does the same)
        self.bias_capture: BiasCapture | None = None
        self.bias_captures = 0  # ?BIAS captures started (each one's capture_id)
        self.bias_captured = False  # a ?BIAS capture completed: bias_dph is a measured bias, not the default 0
        self.bias_sigma_dph = math.nan  # the drift estimate's sigma during that capture (sigma(t_b)); NaN: none
        self.setup_bytes_left = 0  # bytes read during a device setup, still to be skipped by the decoder
        self._format_problem_said = False
        self.outage: PortOutage | None = None  #: the port lost, not yet delivering samples again

    # -- the thread ------------------------------------------------------------------------------------------

    def run(self) -> None:
        """The acquisition thread: chunks from the port until ``stop``; a failure stops the service (its exit
        status in ``service.failure``)."""
        service = self.service
        try:
            for chunk in service.reader.chunks(service.stop):
                read_s = time.monotonic()
                angles = service.process(chunk)  # the service's entry point (= self.process), where tests hook in
                hub, web = service.hub, service.web
                if angles and (hub is not None or web is not None):
                    stamp_utc(angles, time.time_ns())
                    if hub is not None:
                        hub.publish_angles(angles, read_s)
                    if web is not None:
                        web.publish_angles(angles)
        except (ModelMismatchError, PortError) as exc:  # refused at the first IDENTITY; a URL no handler takes
            self._stopped(ConfigError(str(exc)))
        except FogDriverError as exc:
            self._stopped(exc)
        except Exception as exc:  # a bug: log it with its traceback, and stop cleanly
            log.exception("acquisition_crashed", reason=str(exc))
            service.failure = exc
            service.stop.set()

    def _stopped(self, failure: FogDriverError) -> None:
        log.error("acquisition_stopped", reason=str(failure))
        self.service.failure = failure
        self.service.stop.set()

    # -- the port's outages ------------------------------------------------------------------------------------

    def port_changed(self, state: str, url: str, now_s: float) -> None:
        """A port state (the acquisition thread, from the reader): an outage starts at the first "lost" and its
        length is taken at the next "open" (``PortOutage``); ``now_s``: monotonic seconds."""
        if state == "lost" and self.outage is None:
            self.outage = PortOutage(url, now_s)
        elif state == "open" and self.outage is not None and self.outage.open_s is None:
            self.outage.open_s = now_s

    def _outage_over(self, sample: Any) -> None:
        """The first sample decoded after a reopen: ``port_recovered`` with the outage's length and the frames it
        cost (the sample's ``missing_before``: the sequence gap across the outage).  A warning, as the loss was:
        a person at a terminal reads it after the retries."""
        outage = self.outage
        if outage is None or outage.open_s is None:
            return
        self.outage = None
        log.warning(
            "port_recovered",
            url=outage.url,
            down_s=round(outage.open_s - outage.lost_s, 1),
            frames_missing=int(getattr(sample, "missing_before", 0)),
        )

    # -- bytes -> ANGLE objects --------------------------------------------------------------------------------

    def process(self, chunk: bytes) -> list[dict]:
        """Bytes from the port -> ANGLE objects (the acquisition thread; also used by tests)."""
        service = self.service
        angles: list[dict] = []
        with service.lock:
            if service.capture is not None:
                service.capture.put(chunk)
            if self.setup_bytes_left:  # the setup's bytes: the PortReader yields them as the first chunk
                skipped = min(len(chunk), self.setup_bytes_left)
                self.setup_bytes_left -= skipped
                chunk = chunk[skipped:]
            try:
                items = service.source.feed(chunk)
            except ValueError as exc:  # format auto found a format the config has no device settings for
                raise ConfigError(f"format auto: {exc}") from None
            if service.source.format_problem is not None and not self._format_problem_said:
                self._format_problem_said = True
                log.warning("format_problem", format=service.config.format, problem=service.source.format_problem)
            for sample in items:
                if isinstance(sample, IdentityFrame):
                    self._on_identity(angles, sample)
                    continue
                if self.outage is not None:
                    self._outage_over(sample)
                if not service.binding.bound:  # frame period unknown until the first IDENTITY
                    self.samples_before_identity.append(sample)
                    if len(self.samples_before_identity) > MAX_SAMPLES_BEFORE_IDENTITY:
                        del self.samples_before_identity[0]
                        self.samples_dropped_before_identity += 1
                    continue
                angles.append(self._compensate(sample))
        return angles

    def on_device_setup(self, result: Any) -> None:
        """The setup commands were sent on an open (the reader's thread, before the bytes read meanwhile are
        yielded): logged, and noted in the capture's sidecar in order with the bytes.  The device re-initialises
        its output for about ``settle_s`` after it; its status byte marks the frames it says are invalid."""
        sent = [command.decode("ascii", "replace").strip() for command in result.sent]
        log.info("device_setup", sent=sent, replies=list(result.replies), settle_s=result.settle_s)
        with self.service.lock:
            # The bytes read during the setup (frames the device sent under its old settings, and its replies)
            # are captured but not decoded; the note says where they are, and offline readers skip them too.
            self.service.note(
                "device_setup", sent=sent, replies=list(result.replies), bytes_not_decoded=len(result.raw)
            )
            self.setup_bytes_left = len(result.raw)

    def _on_identity(self, angles: list[dict], identity: IdentityFrame) -> None:
        """An IDENTITY in the stream, in order with the samples around it (an implausible one is counted by the
        stream and changes nothing)."""
        if not identity_is_plausible(identity) or identity == self.identity:
            return
        service = self.service
        config, capture, binding = service.config, service.capture, service.binding
        changed = self.identity is None or self.identity[1:] != identity[1:]
        detected = self.identity is None and config.format == "auto"  # the format is known from now on
        self.identity = identity
        if detected:
            check_channels(
                service.model_file, service.source.wire, f"the model {config.model_path}", "the instrument"
            )  # ModelMismatchError: exit 78, as below
            log.info("format_detected", format=service.source.wire.format)
            if capture is not None:
                capture.update_provenance(service.source.wire.sidecar_fields())
        if binding.changes_binding(identity):
            first = not binding.bound
            binding.bind(identity)  # ModelMismatchError: the acquisition stops with exit 78
            fields = identity_fields(identity)
            if capture is not None:
                capture.update_provenance({"instrument": fields})
            if first:
                pending, self.samples_before_identity = self.samples_before_identity, []
                angles.extend(self._compensate(s) for s in pending)
            else:
                service.note("instrument_changed", **fields)
                log.warning("instrument_changed", **fields)
        if changed:
            service.publish(service.device_object())

    def _compensate(self, sample: Any) -> dict:
        service = self.service
        c = service.binding.step(sample)
        self.last_seq = c.seq
        self.last_t_s = c.t_s  # the device time of the last sample (the chamber log's device_t_s)
        period = service.compensator.frame_period_s
        capture = self.bias_capture
        if capture is not None and capture.add(c.dtheta_comp_arcsec, period, c.drift_sigma_dph):
            self._finish_bias(capture)
        self.offsets.advance(period)
        obj = self.angle_object(c)
        axes = getattr(sample, "axes_rate_dph", None)  # publish_axes, a three-axis format
        if axes is not None:
            obj["axes_rate_raw_dph"] = {a: r for a, r in zip("xyz", axes) if math.isfinite(r)}
        if service.udp is not None:
            service.udp.send(obj)
        self.samples_published += 1
        for name in obj["flags"]:  # the names angle_object already made
            self.flagged[name] += 1
        return obj

    def angle_object(self, c: CompensatedSample) -> dict:
        """The ANGLE object of one compensated sample (see the module docstring for the offsets)."""
        period = self.service.compensator.frame_period_s
        offsets = self.offsets
        rate_comp = offsets.rate_dph(c.dtheta_comp_arcsec, period)
        temps = {name: t for name, t in zip(self.service.source.temperature_channels, c.temps_c) if t == t}
        obj = {
            "class": "ANGLE",
            "seq": c.seq,
            "t_s": c.t_s,
            "angle_arcsec": offsets.angle_arcsec(c.angle_comp_arcsec),
            "angle_raw_arcsec": offsets.angle_raw_arcsec(c.angle_raw_arcsec),
            "rate_dph": rate_comp,
            "rate_raw_dph": c.dtheta_arcsec / period,
        }
        if math.isfinite(c.drift_dph):  # NaN while there is no estimate (flagged uncompensated): omitted
            obj["drift_dph"] = c.drift_dph
        if math.isfinite(c.drift_sigma_dph):  # NaN while there is no estimate: omitted, as an absent thermometer
            obj["drift_sigma_dph"] = c.drift_sigma_dph
        obj["temps_c"] = temps
        obj["flags"] = flag_names(c.flags)
        return obj

    def _finish_bias(self, capture: BiasCapture) -> None:
        """A ``?BIAS`` capture is complete: apply it and publish its result (under ``lock``, in the acquisition
        thread; nobody waits on it, so a client that hung up meanwhile changes nothing)."""
        capture.timer.cancel()
        self.offsets.bias_dph = bias_dph = capture.sum_arcsec / capture.seconds
        self.bias_sigma_dph = capture.sigma_dph
        self.bias_captured = True
        self.bias_capture = None
        sigma = {"bias_sigma_dph": self.bias_sigma_dph} if math.isfinite(self.bias_sigma_dph) else {}
        self.service.note("bias", bias_dph=bias_dph, seconds=capture.seconds, **sigma)
        log.info("bias_applied", capture_id=capture.capture_id, bias_dph=bias_dph, seconds=capture.seconds, **sigma)
        self.service.publish_event(
            {
                "class": "BIAS",
                "state": "done",
                "capture_id": capture.capture_id,
                "bias_dph": bias_dph,
                "seconds": capture.seconds,
                **sigma,
            }
        )


@dataclass(eq=False)
class PortOutage:
    """The port ``url`` lost at ``lost_s`` (monotonic s), open again at ``open_s`` (None: not yet)."""

    url: str
    lost_s: float
    open_s: float | None = None


def stamp_utc(angles: list[dict], now_ns: int) -> None:
    """Give each ANGLE object ``utc``: the host's UTC clock when the daemon read the bytes that completed the
    sample (``now_ns``, from ``time.time_ns()``), ISO 8601 to the millisecond (``2026-12-02T14:56:26.123Z``).

    Host time, beside the device's ``t_s``: a station logging ANGLE lines can line them up with other
    instruments.  It is added after ``Acquisition.process``, so the pipeline's output stays a function of the
    port's bytes alone (``compensate`` of the capture gives it exactly); live and offline ANGLE objects differ
    by this key only.  One chunk's samples share one stamp (a chunk is what one read returned)."""
    seconds, ns = divmod(now_ns, 1_000_000_000)
    stamp = time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(seconds)) + f".{ns // 1_000_000:03d}Z"
    for obj in angles:
        obj["utc"] = stamp
