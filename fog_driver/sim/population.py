"""A population of simulated instruments: physics drawn per instrument from physically plausible ranges.

A compensation model earns trust on coils whose thermal behaviour nobody wrote down, so it is judged
on many instruments, not on the one ``configs/sim/instrument.yaml`` describes.  ``draw_instrument(K)``
(``fog-driver simulate --instrument-seed K``) gives instrument K: the same K gives the same instrument,
on every machine (uniform draws and decimal arithmetic only), and every parameter is drawn from its own
stream (keyed by its name), so adding a parameter later changes no other.  The noise (ARW, bias
instability, rate random walk), the scale factor's curvature, the clock and the Earth rate come from the
base configuration; the serial is ``FOG-POP-K``.

The ranges and why (``RANGES``; "log" is log-uniform, "+-" a random sign on the magnitude):

Thermal network (``thermal.py``; time constants in s):

* ``tau_housing_s`` log 240..900: an aluminium case of 1-3 kg in forced chamber air (4-15 min).
* ``tau_top_s`` log 180..480, ``tau_bottom_s`` log 240..600: the ring's surfaces follow the
  housing through the mounting and the air gap; the bottom sits on the thicker base plate.
* ``tau_ring_s`` log 240..900: top <-> bottom conduction through the ring (4-15 min).  Together
  these keep the top-bottom gradient of a 2 degC/min ramp at a few degC, as measured on real rings.
* ``tau_mount_s`` log 1200..3600, ``tau_bottom_mount_s`` log 300..1800: the turntable's top plate
  is a large mass (20-60 min) and the base plate's contact to it varies with the clamping.
* ``self_heating_c`` 1..6, ``top_heating_c`` 0..0.6: 2-10 W of electronics in the case at 0.5-1 K/W,
  and part of it above the ring (a small static top-bottom gradient).
* coil stages: 1, 2 or 3 first-order lags in series from the coil's boundary to its fiber, each
  log 120..1500 s (2 to 25 min): potting, the coil former and the winding's layers are a
  distributed thermal mass; one lag is the simplest coil, three a thick, potted one.  The last
  stage is ``tau_fiber_s``, the others ``coil_inner_lags_s``.
* coil coupling: raw weights top 0.2..1, bottom 0.2..1, housing 0..0.4, normalized to sum 1: how
  the coil sits between the ring's top and bottom, and whether it touches the housing wall.

FOG drift (``gyro.py``; deg/h):

* bias curve: the bias against fiber temperature is ``A (a1 u + a2 u^2 + a3 u^3 + a4 u^4)``,
  ``u = (Tf - 20) / 50``, shape ``a_k`` 0..1 with random signs, its excursion over -40..60 degC
  (``A``) log 0.3..2: source wavelength, polarizer and coil stress each bend the curve; smooth,
  but not the cubic a polynomial baseline assumes.
* ``shupe_dph_per_c_per_min`` +-log 0.03..0.3 (per degC/min of the fiber's own rate): the residual
  of a quadrupole winding, 10x between a good and a poor coil; its sign depends on which half of
  the winding is the warmer.
* ``gradient_dph_per_c`` +-log 0.01..0.1 (axial, ring top - bottom): thermally induced stress
  across the coil (the default instrument's 0.08 is near the top).
* ``radial_gradient_dph_per_c`` +-log 0.002..0.02 (coil boundary - fiber): the Shupe effect of a
  gradient through the winding.  A ramp of r degC/min across a coil lag of tau minutes makes
  about r tau degC of it, so this is 0.02-0.3 deg/h per degC/min for a 10-minute coil: the same
  order as the Shupe term, as it should be.
* ``hysteresis_dph_per_c`` +-log 0.0005..0.005 with ``hysteresis_tau_s`` log 600..10800: the bias
  depends on where the temperature came from (stress relaxation in the potting, 10 min to 3 h).

Scale factor (``gyro.py``: ``s(Tf) = (s0 + s1 (Tf - 20)) 1e-6``):

* ``scale_factor_ppm`` (s0) +- 5..50: the residual of a factory calibration, of either sign; a
  36-degree move reads 0.6 to 6.5 arcsec off.
* ``scale_factor_ppm_per_c`` (s1) 0.1..1: the source's wavelength drifts with temperature
  (a few ppm/degC uncompensated) and a compensated instrument keeps a fraction of it.
  Added after the drift ranges, each from its own stream: no other instrument parameter changed.
  At rest they act on the Earth rate alone: a constant of at most 50 ppm of 9.7 deg/h (0.0005
  deg/h, taken by the bias) and at most 0.001 deg/h across -40..55 degC.

Together these give a 1-min drift RMS of the order of the default instrument's, no term dominating
(``benchmarks/bench_population.py``; docs/decisions/2026-12-07-population-ranges.md).

Thermometers (``instrument.ThermometerParams``):

* ``sensor_lags_s`` each log 5..90: a sensor glued on a pad reads within seconds, one in a boss
  or under a cover lags by a minute or more.
* ``offsets_c`` each -0.3..0.3: a calibration error fixed for the instrument (a class-B PT100
  is +-0.3 degC at 0 degC); the per-run part (``offset_sigma_c``) is 0.01.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .draws import Draws, Range
from .families import draw_family
from .gyro import GyroParams
from .instrument import InstrumentConfig, ThermometerParams

__all__ = ["RANGES", "Range", "SERIAL_FORMAT", "draw_instrument"]

#: Serial of instrument K (at most 16 characters: the IDENTITY frame's field).
SERIAL_FORMAT = "FOG-POP-{:05d}"
MAX_INSTRUMENT_SEED = 99_999
#: Fiber temperatures over which the bias curve's excursion is measured, degC.
BIAS_CURVE_SPAN_C = (-40.0, 60.0)
BIAS_CURVE_SCALE_C = 50.0
PER_RUN_OFFSET_SIGMA_C = 0.01


RANGES: dict[str, Range] = {
    "tau_housing_s": Range(240.0, 900.0, log=True),
    "tau_top_s": Range(180.0, 480.0, log=True),
    "tau_bottom_s": Range(240.0, 600.0, log=True),
    "tau_ring_s": Range(240.0, 900.0, log=True),
    "tau_mount_s": Range(1200.0, 3600.0, log=True),
    "tau_bottom_mount_s": Range(300.0, 1800.0, log=True),
    "self_heating_c": Range(1.0, 6.0),
    "top_heating_c": Range(0.0, 0.6),
    "coil_stages": Range(1, 3),  # an integer
    "coil_lag_s": Range(120.0, 1500.0, log=True),  # each stage
    "coil_weight_top": Range(0.2, 1.0),
    "coil_weight_bottom": Range(0.2, 1.0),
    "coil_weight_housing": Range(0.0, 0.4),
    "bias_curve_excursion_dph": Range(0.3, 2.0, log=True),
    "bias_curve_shape": Range(0.0, 1.0, signed=True),  # each of a1..a4
    "shupe_dph_per_c_per_min": Range(0.03, 0.3, log=True, signed=True),
    "gradient_dph_per_c": Range(0.01, 0.1, log=True, signed=True),
    "radial_gradient_dph_per_c": Range(0.002, 0.02, log=True, signed=True),
    "hysteresis_dph_per_c": Range(0.0005, 0.005, log=True, signed=True),
    "hysteresis_tau_s": Range(600.0, 10800.0, log=True),
    "scale_factor_ppm": Range(5.0, 50.0, signed=True),
    "scale_factor_ppm_per_c": Range(0.1, 1.0),
    "sensor_lag_s": Range(5.0, 90.0, log=True),  # each sensor
    "sensor_offset_c": Range(-0.3, 0.3),  # each sensor
}


def _bias_coefficients(excursion_dph: float, shape: list[float], reference_c: float) -> tuple[float, ...]:
    """Coefficients ``c_k`` of ``sum_k c_k (Tf - Tref)^k`` for the curve ``A sum_k a_k u^k``, ``u = (Tf - 20) / 50``,
    with ``A`` making its excursion over ``BIAS_CURVE_SPAN_C`` equal to ``excursion_dph`` (Tref must be 20)."""
    if reference_c != 20.0:
        raise ValueError("the population's bias curve is about a reference temperature of 20 degC")
    u = (np.linspace(*BIAS_CURVE_SPAN_C, 1001) - 20.0) / BIAS_CURVE_SCALE_C
    curve = sum(a * u ** (k + 1) for k, a in enumerate(shape))
    amplitude = excursion_dph / float(curve.max() - curve.min())
    return tuple(amplitude * a / BIAS_CURVE_SCALE_C ** (k + 1) for k, a in enumerate(shape))


def draw_instrument(seed: int, base: InstrumentConfig | None = None, family: str | None = None) -> InstrumentConfig:
    """Instrument ``seed`` of the population: ``base`` (default: the defaults) with its physics drawn
    from ``RANGES`` (see the module docstring) and the serial ``FOG-POP-<seed>``; with a ``family``
    (``fog_driver.sim.families.FAMILIES``), the same instrument plus that family's physics, drawn for ``seed``
    (the serial stays ``FOG-POP-<seed>``; the configuration's ``family`` records it)."""
    if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed <= MAX_INSTRUMENT_SEED:
        raise ValueError(f"instrument seed must be an integer 0..{MAX_INSTRUMENT_SEED}, got {seed!r}")
    base = base or InstrumentConfig()
    d = Draws(seed, RANGES)
    stages = 1 + min(2, int(d.uniforms("coil_stages", 1)[0] * 3))
    lags = d.values("coil_lag_s", stages)
    weights = [d.value("coil_weight_top"), d.value("coil_weight_bottom"), d.value("coil_weight_housing")]
    total = sum(weights)
    thermal = dataclasses.replace(
        base.thermal,
        **{
            name: d.value(name)
            for name in (
                "tau_housing_s",
                "tau_top_s",
                "tau_bottom_s",
                "tau_ring_s",
                "tau_mount_s",
                "tau_bottom_mount_s",
                "self_heating_c",
                "top_heating_c",
            )
        },
        tau_fiber_s=lags[-1],
        coil_inner_lags_s=tuple(lags[:-1]),
        coil_coupling=tuple(w / total for w in weights),
    )
    gyro: GyroParams = dataclasses.replace(
        base.gyro,
        reference_temp_c=20.0,
        bias_temp_coeffs_dph=_bias_coefficients(
            d.value("bias_curve_excursion_dph"), d.values("bias_curve_shape", 4), 20.0
        ),
        **{
            name: d.value(name)
            for name in (
                "shupe_dph_per_c_per_min",
                "gradient_dph_per_c",
                "radial_gradient_dph_per_c",
                "hysteresis_dph_per_c",
                "hysteresis_tau_s",
                "scale_factor_ppm",
                "scale_factor_ppm_per_c",
            )
        },
    )
    thermometers: ThermometerParams = dataclasses.replace(
        base.thermometers,
        sensor_lags_s=tuple(d.values("sensor_lag_s", 3)),
        offsets_c=tuple(d.values("sensor_offset_c", 3)),
        offset_sigma_c=PER_RUN_OFFSET_SIGMA_C,
    )
    return dataclasses.replace(
        base,
        serial=SERIAL_FORMAT.format(seed),
        thermal=thermal,
        gyro=gyro,
        thermometers=thermometers,
        population_seed=seed,
        family=None if family is None else draw_family(family, seed),
    )
