"""The simulated chamber's dynamics against their closed forms, on a fake clock; ``sim://`` options."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fog_driver.errors import UsageError
from fog_driver.lab.controllers.base import ChamberController, ControllerRefused
from fog_driver.lab.controllers.url import parse_controller_url
from fog_driver.sim.chamber import ChamberParams, SimChamber, open_sim_controller


class FakeClock:
    def __init__(self) -> None:
        self.t_s = 0.0

    def __call__(self) -> float:
        return self.t_s


def test_a_step_without_a_rate_limit_follows_one_minus_exp_of_t_over_tau() -> None:
    clock = FakeClock()
    chamber = SimChamber(clock, ChamberParams(start_c=20.0, rate_c_per_min=0.0, tau_s=60.0))
    chamber.write_setpoint_c(50.0)
    clock.t_s = 400.0
    t = np.linspace(0.0, 400.0, 41)
    expected = 20.0 + 30.0 * (1.0 - np.exp(-t / 60.0))
    np.testing.assert_allclose(chamber.air_c_at(t), expected, rtol=0, atol=1e-9)
    assert chamber.air_c() == pytest.approx(expected[-1], abs=1e-9)


def test_a_rate_limited_ramp_without_lag_has_the_rate_as_its_slope_and_stops_at_the_set_point() -> None:
    clock = FakeClock()
    chamber = SimChamber(clock, ChamberParams(start_c=20.0, rate_c_per_min=3.0, tau_s=0.0))
    clock.t_s = 10.0
    chamber.write_setpoint_c(-10.0)  # 30 degC down at 3 degC/min: 600 s
    clock.t_s = 2000.0
    t = np.array([10.0, 110.0, 310.0, 610.0, 1000.0])
    expected = np.array([20.0, 20.0 - 5.0, 20.0 - 15.0, -10.0, -10.0])
    np.testing.assert_allclose(chamber.air_c_at(t), expected, atol=1e-9)


def test_a_lagged_ramp_trails_the_command_by_rate_times_tau() -> None:
    clock = FakeClock()
    rate_c_per_s, tau_s = 6.0 / 60.0, 30.0
    chamber = SimChamber(clock, ChamberParams(start_c=0.0, rate_c_per_min=6.0, tau_s=tau_s, low_c=-10, high_c=200))
    chamber.write_setpoint_c(100.0)
    clock.t_s = 600.0
    t = np.array([100.0, 300.0, 500.0])
    # closed form of dA/dt = (s t - A)/tau from A(0) = 0: A = s (t - tau) + s tau exp(-t/tau)
    expected = rate_c_per_s * (t - tau_s) + rate_c_per_s * tau_s * np.exp(-t / tau_s)
    np.testing.assert_allclose(chamber.air_c_at(t), expected, atol=1e-9)


def test_a_time_beyond_the_present_holds_the_present_air() -> None:
    clock = FakeClock()
    chamber = SimChamber(clock, ChamberParams(rate_c_per_min=0.0, tau_s=60.0))
    chamber.write_setpoint_c(30.0)
    clock.t_s = 60.0
    now = chamber.air_c()
    np.testing.assert_allclose(chamber.air_c_at(np.array([61.0, 70.0])), [now, now])


def test_rewriting_the_set_point_midway_continues_from_the_air_reached() -> None:
    clock = FakeClock()
    chamber = SimChamber(clock, ChamberParams(start_c=20.0, rate_c_per_min=0.0, tau_s=50.0))
    chamber.write_setpoint_c(40.0)
    clock.t_s = 50.0
    a1 = 40.0 - 20.0 * math.exp(-1.0)
    chamber.write_setpoint_c(20.0)
    clock.t_s = 100.0
    assert chamber.air_c() == pytest.approx(20.0 + (a1 - 20.0) * math.exp(-1.0), abs=1e-9)


def test_standby_lets_the_air_return_to_the_start_temperature_and_local_refuses_writes() -> None:
    clock = FakeClock()
    chamber = SimChamber(clock, ChamberParams(start_c=20.0, rate_c_per_min=0.0, tau_s=0.0))
    chamber.write_setpoint_c(60.0)
    clock.t_s = 1.0
    assert chamber.air_c() == 60.0
    chamber.set_mode("standby")
    clock.t_s = 2.0
    assert chamber.air_c() == 20.0
    assert chamber.status().state == "standby"
    chamber.set_mode("local")
    with pytest.raises(ControllerRefused):
        chamber.write_setpoint_c(30.0)


def test_a_set_point_outside_the_range_is_refused() -> None:
    chamber = SimChamber(FakeClock(), ChamberParams(low_c=-40.0, high_c=120.0))
    with pytest.raises(ValueError):
        chamber.write_setpoint_c(130.0)
    assert chamber.range_c().high_c == 120.0


def test_a_sim_url_opens_a_chamber_controller_with_its_options() -> None:
    url = parse_controller_url("sim://?speed=1000&start_c=25&rate_c_per_min=0&tau_s=0&low_c=-10&high_c=90")
    controller = open_sim_controller(url, overrides={}, on_notice=print, timeout_s=1.0)
    assert isinstance(controller, ChamberController)
    controller.connect()
    assert controller.read_range_c().low_c == -10.0
    assert controller.read_setpoint_c() == 25.0
    controller.write_setpoint_c(30.004)
    assert controller.read_setpoint_c() == pytest.approx(30.0)
    with pytest.raises(ControllerRefused):
        controller.write_setpoint_c(95.0)
    controller.safe_stop()
    assert controller.read_status().state == "standby"


@pytest.mark.parametrize("text", ["sim://?sped=2", "sim://?tau_s=-1", "sim://?speed=0", "sim://?low_c=x"])
def test_a_sim_url_with_an_unknown_or_bad_option_is_a_usage_error(text: str) -> None:
    with pytest.raises(UsageError):
        open_sim_controller(parse_controller_url(text), overrides={}, on_notice=print, timeout_s=1.0)
