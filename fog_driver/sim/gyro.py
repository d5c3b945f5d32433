"""FOG error model in physical units: what the gyro adds to the true input rate.

Output rate, deg/h (1 deg/h = 1 arcsec/s)::

    w_out = (w_in + W_E sin(lat)) (1 + s(Tf))          true input (turntable + Earth), scale-factor error
          + B0 + B_on                                  constant bias, turn-on bias (new every run)
          + D(t)                                       temperature drift (below)
          + b_BI(t) + b_RRW(t) + n_ARW(t)              bias instability, rate random walk, angle random walk

    D = P(Tf - Tref)                                   bias vs fiber temperature (cubic, nonlinear)
      + k_S dTf/dt                                     Shupe term, deg/h per degC/min of fiber rate
      + k_G (Tt - Tb) + k_R (Tc - Tf)                  axial gradient across the ring; radial, coil boundary to fiber
      + k_H (Tf - Th)                                  thermal history: Th is Tf lagged by tau_H (hysteresis)

    s(Tf) = (s0 + s1 (Tf - Tref) + s2 (Tf - Tref)^2) * 1e-6   scale-factor error

Default values and why (a navigation-grade FOG in an arcsecond angle
instrument; each is a configuration key in ``configs/sim/instrument.yaml``):

* ``arw_deg_per_sqrt_h = 0.003``: ARW N gives a 1-s rate standard deviation of
  ``N * 60`` deg/h = 0.18 deg/h, the paper's measured 0.176 deg/h.
* ``bias_instability_dph = 0.005`` with 300 s correlation: a first-order
  Gauss-Markov process with that standard deviation has its Allan-deviation
  floor near 0.6 x 0.005 deg/h (typical of 0.003-0.01 deg/h navigation-grade
  coils).
* ``rrw_dph_per_sqrt_h = 0.0003``: a slow rate random walk, ~0.001 deg/h over
  the 7-hour run.
* Bias vs temperature ``(0.004, 1.5e-4, -2e-6)`` deg/h per degC^1..3 about 20 degC:
  about 1 deg/h of curved variation over -40..+58 degC of fiber temperature,
  the order of an uncompensated FOG's full-range bias change.
* Shupe ``0.15`` deg/h per degC/min: a quadrupole-wound coil of a few hundred
  metres (the paper's 1 degC/min ramps then give ~0.1 deg/h, clearly above the
  1-min noise of ~0.025 deg/h, as their Fig. 5 suggests).
* Gradient ``0.08`` deg/h per degC of top-bottom difference (axial); radial ``0`` per degC of the
  coil's boundary above its fiber (``thermal.py``: Tc - Tf, a ramp's rate times the coil's lag).
* Thermal history ``0.003`` deg/h per degC with a 1 h lag: the part of the
  drift that depends on where the temperature came from, not just where it is.
* Scale factor ``0.05`` ppm/degC and no offset (``scale_factor_ppm`` 0): a calibrated,
  temperature-compensated scale factor; with much more, the paper's sub-arcsecond positioning errors
  over 36-degree moves (0.05-0.86 arcsec) would be impossible.  The population's instruments are not
  calibrated so well (``population.py``: an offset of 5 to 50 ppm, a slope of 0.1 to 1 ppm/degC): a
  36-degree move then reads 0.6 to 6.5 arcsec off, what adapting from the table's angles must tell
  from drift.
* Constant bias ``0.5`` deg/h and turn-on bias ``0.05`` deg/h (1 sigma, drawn
  per run); Earth rate 15.041 deg/h x sin(latitude), latitude 40 deg by default.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Sidereal Earth rate, deg/h.
EARTH_RATE_DPH = 15.041067
#: ARW in deg/sqrt(h) -> angle noise in arcsec per sqrt(s): N deg/sqrt(h) = N * 3600 / 60 arcsec/sqrt(s).
ARCSEC_PER_SQRT_S_PER_DEG_PER_SQRT_H = 60.0


@dataclass(frozen=True)
class GyroParams:
    reference_temp_c: float = 20.0
    bias_temp_coeffs_dph: tuple[float, ...] = (0.004, 1.5e-4, -2.0e-6)
    shupe_dph_per_c_per_min: float = 0.15
    gradient_dph_per_c: float = 0.08
    radial_gradient_dph_per_c: float = 0.0
    hysteresis_dph_per_c: float = 0.003
    hysteresis_tau_s: float = 3600.0
    arw_deg_per_sqrt_h: float = 0.003
    bias_instability_dph: float = 0.005
    bias_instability_tau_s: float = 300.0
    rrw_dph_per_sqrt_h: float = 0.0003
    scale_factor_ppm: float = 0.0
    scale_factor_ppm_per_c: float = 0.05
    scale_factor_ppm_per_c2: float = 0.0
    constant_bias_dph: float = 0.5
    turn_on_bias_sigma_dph: float = 0.05
    latitude_deg: float = 40.0

    def __post_init__(self) -> None:
        for name in ("hysteresis_tau_s", "bias_instability_tau_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0")
        for name in ("arw_deg_per_sqrt_h", "bias_instability_dph", "rrw_dph_per_sqrt_h", "turn_on_bias_sigma_dph"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0")

    @property
    def earth_rate_dph(self) -> float:
        """The Earth-rate component along a vertical sensitive axis."""
        return EARTH_RATE_DPH * math.sin(math.radians(self.latitude_deg))

    @property
    def arw_rate_std_1s_dph(self) -> float:
        """Standard deviation of 1-s mean rates from ARW alone: ``N * 60`` deg/h."""
        return self.arw_deg_per_sqrt_h * ARCSEC_PER_SQRT_S_PER_DEG_PER_SQRT_H

    def bias_vs_temperature_dph(self, fiber_c: np.ndarray) -> np.ndarray:
        """``P(Tf - Tref) = sum_k c_k (Tf - Tref)^k``, k = 1..len(coeffs)."""
        dt = np.asarray(fiber_c) - self.reference_temp_c
        out = np.zeros_like(dt, dtype=np.float64)
        for k, coeff in enumerate(self.bias_temp_coeffs_dph, start=1):
            out += coeff * dt**k
        return out

    def scale_factor_error(self, fiber_c: np.ndarray) -> np.ndarray:
        """Relative scale-factor error ``s(Tf) = (s0 + s1 dT + s2 dT^2) 1e-6`` (dimensionless), dT = Tf - Tref."""
        dt = np.asarray(fiber_c) - self.reference_temp_c
        return (
            self.scale_factor_ppm + self.scale_factor_ppm_per_c * dt + self.scale_factor_ppm_per_c2 * dt * dt
        ) * 1e-6


@dataclass
class DriftTerms:
    """The temperature drift's parts on the slow grid, deg/h."""

    bias_vs_temperature: np.ndarray
    shupe: np.ndarray
    gradient: np.ndarray
    hysteresis: np.ndarray

    @property
    def total(self) -> np.ndarray:
        return self.bias_vs_temperature + self.shupe + self.gradient + self.hysteresis


def drift_terms(
    params: GyroParams,
    fiber_c: np.ndarray,
    fiber_rate_c_per_s: np.ndarray,
    top_c: np.ndarray,
    bottom_c: np.ndarray,
    history_c: np.ndarray,
    boundary_c: np.ndarray | None = None,
) -> DriftTerms:
    """``D`` split into its terms (see the module docstring), from true (not measured) temperatures;
    the gradient term holds the axial and the radial part (``boundary_c``: the coil's boundary Tc)."""
    gradient = params.gradient_dph_per_c * (np.asarray(top_c) - np.asarray(bottom_c))
    if params.radial_gradient_dph_per_c:
        gradient = gradient + params.radial_gradient_dph_per_c * (np.asarray(boundary_c) - np.asarray(fiber_c))
    return DriftTerms(
        bias_vs_temperature=params.bias_vs_temperature_dph(fiber_c),
        shupe=params.shupe_dph_per_c_per_min * 60.0 * np.asarray(fiber_rate_c_per_s),
        gradient=gradient,
        hysteresis=params.hysteresis_dph_per_c * (np.asarray(fiber_c) - np.asarray(history_c)),
    )


class SlowNoise:
    """Bias instability (first-order Gauss-Markov) and rate random walk on a fixed grid, with explicit state.

    ``b(k+1) = phi b(k) + sigma sqrt(1 - phi^2) w``, ``phi = exp(-dt/tau)``, sigma = bias instability;
    ``r(k+1) = r(k) + K sqrt(dt / 3600 s) w``, K = rate random walk in deg/h/sqrt(h).
    """

    def __init__(self, params: GyroParams, dt_s: float, rng: np.random.Generator) -> None:
        self.rng = rng
        self.phi = math.exp(-dt_s / params.bias_instability_tau_s)
        self.bi_sigma = params.bias_instability_dph
        self.bi_drive = params.bias_instability_dph * math.sqrt(1.0 - self.phi**2)
        self.rrw_step = params.rrw_dph_per_sqrt_h * math.sqrt(dt_s / 3600.0)
        self.bi = self.bi_sigma * float(rng.standard_normal())  # stationary start
        self.rrw = 0.0

    def run(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """The next ``n`` grid values of (bias instability, rate random walk), deg/h."""
        w = self.rng.standard_normal((2, n))
        bi = np.empty(n)
        x = self.bi
        phi, drive = self.phi, self.bi_drive
        for k, wk in enumerate(w[0].tolist()):
            x = phi * x + drive * wk
            bi[k] = x
        self.bi = x
        rrw = self.rrw + np.cumsum(self.rrw_step * w[1])
        if n:
            self.rrw = float(rrw[-1])
        return bi, rrw
