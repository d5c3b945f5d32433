"""The daemon's read-only chamber (the config's ``chamber:`` section): the air and the set point read every
``poll_s``, logged beside the capture, in STATUS, ``/metrics`` and the web view.

A thread of its own (``chamber``) opens the controller (``lab.controllers.registry.open_controller``, ``sim://``
through the simulator's opener, imported when first needed) and, every ``poll_s``, reads the air and the set
point.  It never writes to the chamber: the daemon watches a chamber someone else drives (``chamber run``, the
front panel).  It shares nothing with the acquisition but two reads of plain attributes (the capture file's
path, the device time of the last sample), so a chamber that is slow, lost or answers garbage never stops or
slows the gyro's acquisition:

- a read that fails (``ControllerUnreachable``, a ``ControllerProtocolError``, any one-line ``FogDriverError``)
  is a row ``link_lost``; the controller is closed and reconnected with backoff: the next attempt after
  ``poll_s``, doubling up to ``RECONNECT_MAX_S``; while waiting, one ``link_lost`` row per poll keeps the log's
  cadence.  The loss and the return are logged once each (``chamber_link_lost``, ``chamber_link_back``);
- the log: ``<capture stem>.chamber.csv`` beside the capture file being written (``fog_driver.lab.chamberlog``),
  a new one when the capture rotates, so each capture file has its chamber log beside it (``evaluate`` and
  ``fit`` find it there).  Its rows: ``t_s``, ``program_c`` and ``segment`` empty (the daemon runs no program),
  ``device_t_s`` the device time of the last sample published, state ``running`` for a read, ``link_lost`` for
  a failed one.  Before the capture has a file (no byte yet) nothing is logged; a log that cannot be written is
  logged once and retried with the next capture file (the readings still reach STATUS);
- ``snapshot()``: the last reading for STATUS (``chamber``: ``air_c``, ``setpoint_c``, ``state``, ``url``,
  ``age_s`` since the last good read, ``utc`` of it, ``link_up``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime as _dt
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import structlog

from ..errors import FogDriverError
from ..lab.chamberlog import ChamberLogWriter, LogHeader, LogRow, format_utc
from ..lab.controllers.base import ChamberController
from ..offline.chamber import chamber_log_beside as chamber_log_path
from ..offline.chamber import open_lab_controller
from .config import ChamberConfig

log = structlog.get_logger("fog_driver.daemon")

#: The longest wait between two reconnection attempts (s).
RECONNECT_MAX_S = 60.0


def open_daemon_controller(config: ChamberConfig, on_notice: Callable[[str], None]) -> ChamberController:
    """The configured controller, not connected (``UsageError``: an unknown option, the ``lab`` extra missing)."""
    return open_lab_controller(config.url, overrides=dict(config.overrides), on_notice=on_notice)


@dataclass(frozen=True)
class ChamberReading:
    """One poll: its readings (None when the read failed), its state and time, and the last good read's values
    and times (those of this poll when it is good; None: never a good one)."""

    air_c: float | None
    setpoint_c: float | None
    state: str  # running | link_lost
    utc: str
    good_air_c: float | None = None
    good_setpoint_c: float | None = None
    good_monotonic_s: float | None = None
    good_utc: str | None = None


class ChamberPoller:
    """Polls a chamber controller read-only (the module docstring).  ``capture_path()``: the capture file being
    written (None: none yet); ``device_t_s()``: the device time of the last sample (None: none yet).  ``clock``,
    ``utc_now`` and ``wait`` are injectable (tests): ``wait(timeout_s)`` returns True when the poller is to stop."""

    def __init__(
        self,
        config: ChamberConfig,
        controller: ChamberController,
        *,
        capture_path: Callable[[], str | None],
        device_t_s: Callable[[], float | None],
        clock: Callable[[], float] = time.monotonic,
        utc_now: Callable[[], _dt.datetime] = lambda: _dt.datetime.now(_dt.UTC),
        stop: threading.Event | None = None,
    ) -> None:
        self.config = config
        self.controller = controller
        self.capture_path = capture_path
        self.device_t_s = device_t_s
        self.clock = clock
        self.utc_now = utc_now
        self.stop = stop or threading.Event()
        self.connected = False
        self.reading: ChamberReading | None = None
        self.reads = 0
        self.failures = 0
        self._retry_at = 0.0
        self._retry_s = config.poll_s
        self._log: ChamberLogWriter | None = None
        self._log_for: str | None = None  # the capture file the log is beside
        self._log_refused: set[str] = set()
        self._thread: threading.Thread | None = None

    # -- one poll -------------------------------------------------------------------------------

    def _read(self) -> tuple[float, float]:
        if not self.connected:
            self.controller.connect()
            self.connected = True
        return self.controller.read_air_c(), self.controller.read_setpoint_c()

    def poll_once(self) -> ChamberReading:
        """Read the air and the set point (or note the link lost), log the row, keep the reading."""
        now = self.clock()
        utc = format_utc(self.utc_now())
        previous = self.reading
        air_c = setpoint_c = None
        if self.connected or now >= self._retry_at:
            try:
                air_c, setpoint_c = self._read()
            except FogDriverError as exc:
                self._lost(now, str(exc), was_up=previous is None or previous.state == "running")
        if air_c is not None and setpoint_c is not None:
            if previous is not None and previous.state == "link_lost":
                log.info("chamber_link_back", url=self.config.url)
            self._retry_s = self.config.poll_s
            self.reads += 1
            reading = ChamberReading(air_c, setpoint_c, "running", utc, air_c, setpoint_c, now, utc)
        elif previous is not None:
            reading = dataclasses.replace(previous, air_c=None, setpoint_c=None, state="link_lost", utc=utc)
        else:
            reading = ChamberReading(None, None, "link_lost", utc)
        self.reading = reading
        self._write_row(reading)
        return reading

    def _lost(self, now: float, reason: str, *, was_up: bool) -> None:
        self.failures += 1
        if was_up:
            log.warning("chamber_link_lost", url=self.config.url, reason=reason, retry_s=self._retry_s)
        with contextlib.suppress(Exception):  # a controller that cannot even close is lost anyway
            self.controller.close()
        self.connected = False
        self._retry_at = now + self._retry_s
        self._retry_s = min(self._retry_s * 2.0, max(RECONNECT_MAX_S, self.config.poll_s))

    # -- the log beside the capture -------------------------------------------------------------

    def _writer(self) -> ChamberLogWriter | None:
        capture = self.capture_path()
        if capture is None:
            return None
        if capture == self._log_for:
            return self._log
        self.close_log()
        self._log_for = capture
        path = chamber_log_path(capture)
        header = LogHeader("", "", self.config.url, Path(capture).stem, None)
        try:
            self._log = ChamberLogWriter(path, header)
        except FogDriverError as exc:
            if str(path) not in self._log_refused:
                self._log_refused.add(str(path))
                log.error("chamber_log_not_written", path=str(path), reason=str(exc))
        return self._log

    def _write_row(self, reading: ChamberReading) -> None:
        writer = self._writer()
        if writer is None:
            return
        row = LogRow(reading.utc, None, self.device_t_s(), reading.setpoint_c, reading.air_c, reading.state, None, None)
        try:
            writer.write(row)
        except FogDriverError as exc:
            log.error("chamber_log_not_written", path=str(writer.path), reason=str(exc))
            self._log = None  # the next capture file gets a new one

    def close_log(self) -> None:
        if self._log is not None:
            try:
                self._log.close()
            except FogDriverError as exc:
                log.error("chamber_log_not_written", path=str(self._log.path), reason=str(exc))
            self._log = None

    # -- what STATUS says -----------------------------------------------------------------------

    def snapshot(self) -> dict[str, Any]:
        """STATUS's ``chamber`` object (before the first poll: the URL and state ``starting``)."""
        reading = self.reading
        if reading is None:
            return {"url": self.config.url, "state": "starting", "link_up": False}
        out: dict[str, Any] = {"url": self.config.url, "state": reading.state, "link_up": reading.state == "running"}
        if reading.good_monotonic_s is not None:  # the last good read's, kept while the link is lost
            out["air_c"] = reading.good_air_c
            out["setpoint_c"] = reading.good_setpoint_c
            out["age_s"] = round(max(0.0, self.clock() - reading.good_monotonic_s), 3)
            out["utc"] = reading.good_utc
        return out

    # -- the thread -----------------------------------------------------------------------------

    def run(self) -> None:
        """Poll every ``poll_s`` until ``stop``: the next poll is due ``poll_s`` after the last was due, or at once
        when a poll took longer than that (a controller's timeout): no burst of polls to catch up."""
        due = self.clock()
        try:
            while not self.stop.is_set():
                try:
                    self.poll_once()
                except Exception:  # noqa: BLE001 - a bug here must never reach the acquisition: logged, polling goes on
                    log.exception("chamber_poll_failed", url=self.config.url)
                due = max(due + self.config.poll_s, self.clock())  # a slow poll delays the next, never a burst
                if self.stop.wait(max(0.0, due - self.clock())):
                    break
        finally:
            self.close_log()
            with contextlib.suppress(Exception):
                self.controller.close()

    def start(self) -> None:
        self._thread = threading.Thread(target=self.run, name="chamber", daemon=True)
        self._thread.start()

    def close(self, timeout_s: float) -> None:
        self.stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
