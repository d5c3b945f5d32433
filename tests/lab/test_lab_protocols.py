"""Every driver against the simulated lab's server of its protocol: the client codecs (``lab/controllers/codecs``)
and the servers (``sim/chamber_serve``) were written apart, each from the manual, so a disagreement fails here.

The chamber runs on a clock the test moves (no sleeps): the air is checked against the chamber's own dynamics."""

from __future__ import annotations

import pytest

from fog_driver.lab.controllers.base import ChamberController
from fog_driver.offline.chamber import open_lab_controller
from fog_driver.sim.chamber import ChamberParams, SimChamber
from fog_driver.sim.chamber_serve import serve_chamber

#: scheme -> the options its client needs (Thermotron has no range read: the URL gives it)
SCHEMES = {
    "espec": "",
    "thermotron": "?range=-70:180",
    "simserv": "",
    "watlow-f4t": "",
}


class Clock:
    def __init__(self) -> None:
        self.t_s = 0.0

    def __call__(self) -> float:
        return self.t_s


def _open(server_url: str, scheme: str, notices: list[str]) -> ChamberController:
    return open_lab_controller(server_url + SCHEMES[scheme], on_notice=notices.append, timeout_s=2.0)


@pytest.mark.parametrize("scheme", sorted(SCHEMES))
def test_each_driver_reads_writes_and_stops_its_protocols_simulated_chamber(scheme: str) -> None:
    clock = Clock()
    chamber = SimChamber(clock, ChamberParams(start_c=20.0, rate_c_per_min=6.0, tau_s=30.0))
    notices: list[str] = []
    with serve_chamber(f"{scheme}://127.0.0.1:0", chamber) as server:
        controller = _open(server.url, scheme, notices)
        controller.connect()
        try:
            limits = controller.read_range_c()
            assert (limits.low_c, limits.high_c) == (-70.0, 180.0)
            assert controller.read_air_c() == pytest.approx(20.0, abs=0.05)
            controller.write_setpoint_c(32.5)
            assert chamber.setpoint_c() == pytest.approx(32.5, abs=1e-4)
            assert controller.read_setpoint_c() == pytest.approx(32.5, abs=controller.resolution_c / 2 + 1e-9)
            clock.t_s = 600.0  # long past the 2-min ramp and its 30-s lag
            assert controller.read_air_c() == pytest.approx(chamber.air_c(), abs=0.05)
            assert controller.read_air_c() == pytest.approx(32.5, abs=0.1)
            assert controller.read_status().state in ("constant", "program", "unknown")
            controller.safe_stop()
            # (a read after it: the server answers in order, and a Thermotron's STOP answers nothing)
            state = controller.read_status().state
            assert state == ("unknown" if scheme == "simserv" else "standby")  # SIMSERV has no state read
            assert chamber.mode == "standby"
        finally:
            controller.close()


@pytest.mark.parametrize("scheme", sorted(SCHEMES))
def test_each_driver_converts_a_chamber_that_speaks_degf(scheme: str) -> None:
    clock = Clock()
    chamber = SimChamber(clock, ChamberParams(start_c=25.0, unit="F"))
    notices: list[str] = []
    with serve_chamber(f"{scheme}://127.0.0.1:0", chamber) as server:
        url = server.url + SCHEMES[scheme]
        if scheme != "watlow-f4t":  # the F4T says its unit; the ASCII protocols are told
            url += ("&" if "?" in url else "?") + "unit=F"
        controller = open_lab_controller(url, on_notice=notices.append)
        controller.connect()
        try:
            assert controller.read_air_c() == pytest.approx(25.0, abs=0.06)
            controller.write_setpoint_c(40.0)
            assert chamber.setpoint_c() == pytest.approx(40.0, abs=0.03)
        finally:
            controller.close()
