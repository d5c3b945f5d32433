"""The daemon's read-only chamber: polled beside the capture, logged, in STATUS; a lost link never stops it."""

from __future__ import annotations

import datetime as _dt
import threading

import pytest

from fog_driver.daemon.chamber import RECONNECT_MAX_S, ChamberPoller, chamber_log_path
from fog_driver.daemon.config import ChamberConfig, DriverConfig, load_config
from fog_driver.errors import InputFileError
from fog_driver.lab.chamberlog import read_chamber_log
from fog_driver.lab.controllers.base import ControllerProtocolError, ControllerUnreachable


class FakeChamber:
    """A controller whose air and set point the test sets; ``down`` makes every call fail as a lost link."""

    url = "sim://"

    def __init__(self) -> None:
        self.air_c = 21.5
        self.setpoint_c = 20.0
        self.down: Exception | None = None
        self.connects = 0
        self.writes: list[float] = []

    def connect(self) -> None:
        if self.down is not None:
            raise self.down
        self.connects += 1

    def close(self) -> None:
        pass

    def read_air_c(self) -> float:
        if self.down is not None:
            raise self.down
        return self.air_c

    def read_setpoint_c(self) -> float:
        if self.down is not None:
            raise self.down
        return self.setpoint_c

    def write_setpoint_c(self, setpoint_c: float) -> None:
        self.writes.append(setpoint_c)


class Clock:
    def __init__(self) -> None:
        self.t = 100.0
        self.utc = _dt.datetime(2026, 12, 7, 17, 0, tzinfo=_dt.UTC)

    def monotonic(self) -> float:
        return self.t

    def utc_now(self) -> _dt.datetime:
        return self.utc + _dt.timedelta(seconds=self.t - 100.0)


def _poller(tmp_path, chamber, clock, capture="fog-0001.bin", device_t_s=12.5, poll_s=5.0):
    where = {"capture": None if capture is None else str(tmp_path / capture)}
    poller = ChamberPoller(
        ChamberConfig(url="sim://", poll_s=poll_s),
        chamber,
        capture_path=lambda: where["capture"],
        device_t_s=lambda: device_t_s,
        clock=clock.monotonic,
        utc_now=clock.utc_now,
    )
    return poller, where


def test_the_daemon_logs_the_chamber_beside_its_capture_and_says_it_in_status(tmp_path):
    chamber, clock = FakeChamber(), Clock()
    poller, where = _poller(tmp_path, chamber, clock)
    for air_c in (21.5, 22.0, 22.75):
        chamber.air_c = air_c
        poller.poll_once()
        clock.t += 5.0
    poller.close_log()
    log = read_chamber_log(tmp_path / "fog-0001.chamber.csv")
    assert [r.air_c for r in log.rows] == [21.5, 22.0, 22.75]
    assert {r.setpoint_c for r in log.rows} == {20.0} and {r.state for r in log.rows} == {"running"}
    assert {r.device_t_s for r in log.rows} == {12.5}
    assert {r.t_s for r in log.rows} == {None} and {r.program_c for r in log.rows} == {None}
    assert log.rows[1].t_utc == "2026-12-07T17:00:05.000Z"
    assert log.header.controller_url == "sim://" and log.header.run_id == "fog-0001"
    snapshot = poller.snapshot()
    assert snapshot["air_c"] == 22.75 and snapshot["setpoint_c"] == 20.0 and snapshot["state"] == "running"
    assert snapshot["link_up"] is True and snapshot["age_s"] == 5.0 and snapshot["utc"] == log.rows[2].t_utc
    assert chamber.writes == []  # read-only: never a write


def test_a_lost_chamber_link_is_logged_and_retried_with_backoff_and_comes_back(tmp_path):
    chamber, clock = FakeChamber(), Clock()
    poller, _ = _poller(tmp_path, chamber, clock)
    poller.poll_once()
    chamber.down = ControllerUnreachable("sim://: connection reset")
    connects_before = chamber.connects
    attempts_at = []
    for _ in range(12):  # 60 s of 5-s polls while the link is down
        clock.t += 5.0
        before = poller.failures
        reading = poller.poll_once()
        assert reading.state == "link_lost"
        if poller.failures > before:
            attempts_at.append(clock.t)
    gaps = [b - a for a, b in zip(attempts_at, attempts_at[1:])]
    assert gaps == sorted(gaps) and gaps[0] == 5.0 and gaps[-1] > 5.0  # backoff: the gaps grow
    snapshot = poller.snapshot()
    assert snapshot["state"] == "link_lost" and snapshot["link_up"] is False
    assert snapshot["air_c"] == 21.5 and snapshot["age_s"] == 60.0  # the last good read, and how old
    chamber.down = None
    for _ in range(int(RECONNECT_MAX_S / 5) + 1):  # back within the longest backoff
        clock.t += 5.0
        if poller.poll_once().state == "running":
            break
    assert poller.snapshot()["link_up"] is True and chamber.connects == connects_before + 1
    poller.close_log()
    rows = read_chamber_log(tmp_path / "fog-0001.chamber.csv").rows
    lost = [r for r in rows if r.state == "link_lost"]
    assert len(lost) >= 12 and all(r.air_c is None and r.setpoint_c is None for r in lost)
    assert rows[0].state == "running" and rows[-1].state == "running"


def test_a_chamber_answering_garbage_is_a_lost_link_not_a_stopped_daemon(tmp_path):
    chamber, clock = FakeChamber(), Clock()
    poller, _ = _poller(tmp_path, chamber, clock)
    chamber.down = ControllerProtocolError("sim://: garbage reply b'\\xff'")
    assert poller.poll_once().state == "link_lost"
    assert poller.snapshot() == {"url": "sim://", "state": "link_lost", "link_up": False}


def test_a_rotated_capture_gets_its_own_chamber_log_and_none_before_the_first_file(tmp_path):
    chamber, clock = FakeChamber(), Clock()
    poller, where = _poller(tmp_path, chamber, clock, capture=None)
    poller.poll_once()  # no capture file yet: STATUS has it, no log
    assert poller.snapshot()["air_c"] == 21.5 and not list(tmp_path.iterdir())
    where["capture"] = str(tmp_path / "fog-0001.bin")
    poller.poll_once()
    where["capture"] = str(tmp_path / "fog-0002.bin")
    poller.poll_once()
    poller.poll_once()
    poller.close_log()
    assert len(read_chamber_log(tmp_path / "fog-0001.chamber.csv").rows) == 1
    assert len(read_chamber_log(tmp_path / "fog-0002.chamber.csv").rows) == 2
    assert chamber_log_path("/x/fog-0002.bin").name == "fog-0002.chamber.csv"


def test_the_poller_thread_polls_until_stopped_and_closes_its_log(tmp_path):
    chamber = FakeChamber()
    stop = threading.Event()
    polled = threading.Event()

    class Reading(FakeChamber):
        def read_setpoint_c(self) -> float:
            polled.set()
            return 20.0

    chamber = Reading()
    poller = ChamberPoller(
        ChamberConfig(url="sim://", poll_s=0.5),
        chamber,
        capture_path=lambda: str(tmp_path / "fog-0001.bin"),
        device_t_s=lambda: None,
        stop=stop,
    )
    poller.start()
    assert polled.wait(10)
    poller.close(10)
    assert not poller._thread.is_alive()
    assert read_chamber_log(tmp_path / "fog-0001.chamber.csv").rows[0].air_c == 21.5


def test_a_chamber_section_reads_its_url_poll_and_overrides(tmp_path):
    path = tmp_path / "fog.yaml"
    path.write_text(
        "chamber:\n  url: watlow-f4t://10.0.0.5?unit=1\n  poll_s: 2\n"
        "  overrides: {word_order: high, air_register: 2820}\n"
    )
    chamber = load_config(path).chamber
    assert chamber == ChamberConfig("watlow-f4t://10.0.0.5?unit=1", 2.0, {"word_order": "high", "air_register": 2820})
    path.write_text("chamber:\n  url: sim://\n")
    assert load_config(path).chamber.poll_s == 5.0
    assert DriverConfig().chamber is None


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ("chamber:\n  url: sim://\n  pol_s: 2\n", "chamber: unknown key 'pol_s' (did you mean 'poll_s'?)"),
        ("chamber:\n  poll_s: 2\n", "chamber: url: the chamber controller's URL is needed"),
        ("chamber:\n  url: sim://\n  poll_s: 0\n", "chamber: poll_s must be in [0.5, 3600] s, got 0"),
        ("chamber:\n  url: sim://\n  poll_s: fast\n", "chamber.poll_s: expected a finite number, got 'fast'"),
        ("chamber:\n  url: modbus://x\n", "unknown scheme 'modbus'"),
        ("chamber:\n  url: sim://\n  overrides: {a: [1, 2]}\n", "chamber.overrides: expected a mapping of names"),
        ("chamber: sim://\n", "chamber: expected a mapping"),
    ],
)
def test_a_bad_chamber_section_is_one_line(tmp_path, text, needle):
    path = tmp_path / "fog.yaml"
    path.write_text(text)
    with pytest.raises(InputFileError) as err:
        load_config(path)
    assert needle in str(err.value) and "\n" not in str(err.value)


def test_run_with_a_bad_chamber_section_exits_78(tmp_path):
    from cli_run import assert_one_line_error, run_cli

    path = tmp_path / "fog.yaml"
    path.write_text("chamber:\n  url: sim://\n  colour: red\n")
    proc = run_cli("run", "--config", str(path), "--port", "/dev/null")
    assert_one_line_error(proc, 78, "unknown key 'colour'")


def test_status_metrics_and_the_web_view_show_the_chamber(tmp_path, monkeypatch):
    from prometheus_client import CollectorRegistry, generate_latest
    from prometheus_client.parser import text_string_to_metric_families

    import fog_driver.daemon.service as service_module
    from fog_driver.daemon.service import Service
    from fog_driver.daemon.web.metrics import DaemonCollector, LatencyHistogram
    from fog_driver.daemon.web.view import ViewState

    chamber, clock = FakeChamber(), Clock()
    monkeypatch.setattr(service_module, "open_daemon_controller", lambda config, on_notice: chamber)
    service = Service(DriverConfig(chamber=ChamberConfig("sim://", 5.0)), port="unused")
    poller = service._make_chamber()
    poller.clock, poller.utc_now = clock.monotonic, clock.utc_now
    service.chamber = poller
    poller.poll_once()
    clock.t += 2.5
    with service.lock:
        status = service.status_object()
    assert status["chamber"] == {
        "url": "sim://",
        "state": "running",
        "link_up": True,
        "air_c": 21.5,
        "setpoint_c": 20.0,
        "age_s": 2.5,
        "utc": "2026-12-07T17:00:00.000Z",
    }
    registry = CollectorRegistry(auto_describe=False)
    registry.register(DaemonCollector(service.metrics_state, LatencyHistogram()))
    samples = {
        s.name: s.value for f in text_string_to_metric_families(generate_latest(registry).decode()) for s in f.samples
    }
    assert samples["fog_driver_chamber_up"] == 1.0 and samples["fog_driver_chamber_air_celsius"] == 21.5
    assert samples["fog_driver_chamber_setpoint_celsius"] == 20.0
    assert samples["fog_driver_chamber_reading_age_seconds"] == 2.5
    view = ViewState()
    view.add_object({"class": "STATUS", **status}, 0.0)
    assert view.text(None)["status_chamber"] == "air 21.50 degC, set point 20.00 degC (link up, 2.5 s ago)"
    chamber.down = ControllerUnreachable("gone")
    poller.poll_once()
    with service.lock:
        status = service.status_object()
    view.add_object({"class": "STATUS", **status}, 1.0)
    assert view.text(None)["status_chamber"].endswith("(link lost, 2.5 s ago)")


def test_a_chamber_url_its_driver_refuses_stops_the_start_with_exit_78(monkeypatch):
    import fog_driver.daemon.service as service_module
    from fog_driver.daemon.service import ConfigError, Service
    from fog_driver.errors import UsageError

    def refuse(config, on_notice):
        raise UsageError("controller URL sim://?speed=x: bad speed='x'")

    monkeypatch.setattr(service_module, "open_daemon_controller", refuse)
    service = Service(DriverConfig(chamber=ChamberConfig("sim://?speed=x", 5.0)), port="unused")
    with pytest.raises(ConfigError, match="chamber: url: controller URL sim://") as err:
        service._make_chamber()
    assert err.value.exit_status == 78


def test_a_running_daemon_logs_its_chamber_beside_the_capture_file_it_writes(tmp_path, monkeypatch):
    from pathlib import Path

    import fog_driver.daemon.service as service_module
    from fog_driver.daemon.service import Service

    data = (Path(__file__).resolve().parents[1] / "data" / "sim-short.bin").read_bytes()
    polled = threading.Event()

    class Signalling(FakeChamber):
        def read_setpoint_c(self) -> float:
            polled.set()
            return super().read_setpoint_c()

    chamber = Signalling()
    monkeypatch.setattr(service_module, "open_daemon_controller", lambda config, on_notice: chamber)
    config = DriverConfig(
        listen="127.0.0.1:0", capture_dir=str(tmp_path / "captures"), chamber=ChamberConfig("sim://", 0.5)
    )
    service = Service(config, port=str(tmp_path / "no-such-tty"))  # the acquisition waits for the port
    try:
        service.start()
        angles = service.process(data)  # the pipeline, as the acquisition thread runs it
        service.capture.put(data)  # and the capture, as the port's reader feeds it
        logs: list = []
        for _ in range(40):  # each poll signals; the first after the capture's file exists writes a row
            assert polled.wait(10)
            polled.clear()
            logs = list((tmp_path / "captures").glob("*.chamber.csv"))
            rows = read_chamber_log(logs[0]).rows if logs else []
            if rows and rows[-1].device_t_s == angles[-1]["t_s"]:  # the capture's writer has caught up
                break
        with service.lock:
            status = service.status_object()
        assert status["chamber"]["air_c"] == 21.5 and status["chamber"]["link_up"] is True
        capture = Path(service.capture.status_fields()["path"])
    finally:
        service.stop.set()
        service.shutdown()
    (log,) = logs
    assert log == chamber_log_path(capture) and capture.exists()
    rows = read_chamber_log(log).rows
    # a row holds the device time the daemon had reached at its poll: never ahead of the data, the last the end
    assert rows and rows[-1].device_t_s == angles[-1]["t_s"]
    assert all(r.device_t_s <= angles[-1]["t_s"] for r in rows)
    assert chamber.writes == []
