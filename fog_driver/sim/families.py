"""Physics families the development population never had: drift mechanisms drawn per instrument on top of it.

``draw_instrument(K, family=NAME)`` (``fog_driver.sim.population``) is instrument K of the population plus one
family's term, drawn per instrument from its own streams (keyed ``"<family>:<parameter>"`` and K, like every
population parameter).  The term is computed on the slow grid (step ``dt`` = 1 s, index k) from the TRUE
temperatures (``thermal.py``: Th housing, Tt/Tb ring top/bottom, Tf fiber, Tm mount, Tc the coil's boundary;
rates from the model), with explicit state, and added to the truth's ``drift_dph`` and to the gyro's output;
the truth file keeps its columns (``drift_dph`` minus its four ``drift_*`` parts is the family's term).  The
fit never sees any of it: nothing outside the simulator imports this module.

The ranges are ours, chosen so each term is the size of the drift the development family has (a 1-min drift
RMS of 0.05-0.2 deg/h raw), not a small correction; "log" is log-uniform, "+-" a random sign.

``memory`` -- thermal hysteresis as a play (backlash) operator, and a very slow thermal memory::

    p(k) = min(Tf(k) + w/2, max(Tf(k) - w/2, p(k-1))),  p(-1) = Tf(0)      play operator of width w
    m(k) = m(k-1) + (1 - exp(-dt/tau_M)) (Tf(k) - m(k-1)),  m(-1) = Tf(0)  first-order memory
    D_F  = (B_P / (w/2)) (p - Tf) + k_M (Tf - m)

  w 3..15 degC, B_P (the play term's largest size) +-log 0.05..0.2 deg/h, tau_M log 3..12 h (beyond the
  fit's history features), k_M +-log 0.002..0.01 deg/h/degC.  The bias depends on where the temperature came
  from: a coil's potting and the fiber's coating hold stress that is released only past a threshold
  (backlash) or over hours.  Mechanism: Lefevre, "The Fiber-Optic Gyroscope", Artech House, 2nd ed. 2014
  (thermal and stress-induced nonreciprocity); the play operator is the elementary hysteresis operator of
  Preisach-type models.

``layered`` -- a multi-layer coil with radial diffusion and a temperature-dependent Shupe coefficient::

    T_0 = Tb (the coil's hub, on the base plate), T_(N+1) = Th (its outer face, in the case)
    T_i(k) = T_i(k-1) + r (T_(i-1) - 2 T_i + T_(i+1)),  r = (dt/s) (N+1)^2 / tau_D,  s sub-steps, r <= 0.4
    D_F = k0 (1 + beta (mean_i T_i - 20)) 60 sum_i w_i (T_i(k) - T_i(k-1)) / dt

  (the explicit finite-difference form of dT/dt = (L^2/tau_D) d2T/dx2 across the winding's thickness L,
  the boundaries held over each step; a winding thin against its radius, so planar).  N 6..16 layers,
  tau_D log 600..3600 s, w_i each -1..1 normalized to sum |w_i| = 1 (a quadrupole winding's residual
  asymmetry layer by layer, of both signs), k0 +-log 0.1..0.5 deg/h per degC/min, beta +-log 0.005..0.02
  per degC (dn/dT and the expansion change with temperature).  Shupe, "Thermally induced nonreciprocity
  in the fiber-optic interferometer", Appl. Opt. 19(5), 1980; Mohr, "Thermooptically induced bias drift in
  fiber optical Sagnac interferometers", J. Lightwave Technol. 14(1), 1996 (the bias as a position-weighted
  integral of the temperature rate along the fiber).

``stress`` -- thermal stress of the mount and the potting, and a warm-up transient::

    dT(k) = Tm(k) - Th(k)
    S(k)  = exp(-dt/tau_C) S(k-1) + (dT(k) - dT(k-1)),  S(-1) = 0, dT(-1) = dT(0)   stress with creep
    D_F   = k_S S + k_Q (Tc - Tf)^2
    q_w(t) = Q_w (1 - exp(-t / tau_w))   more heat in the housing (degC of its steady rise), through the network

  tau_C log 1..6 h (the stress of a held difference relaxes to 0), k_S +-log 0.005..0.025 deg/h/degC,
  k_Q +-log 0.0005..0.003 deg/h/degC^2 (elasto-optic: birefringence goes with the stress squared), Q_w 1..4
  degC, tau_w log 10..40 min (the electronics' dissipation rising after power-on, at every run's start).
  The warm-up changes the true temperatures (the thermometers see it): it is physics the fit can see, the
  other two terms are stress it must infer.  Mechanism: Lefevre 2014 (thermal stress, elasto-optic effect).

``correlated`` -- a correlated bias instability that no temperature explains::

    b(k) = phi b(k-1) + sigma sqrt(1 - phi^2) sqrt(1 + g |60 dTf/dt(k)|) w(k),  phi = exp(-dt/tau),
    b(-1) = sigma w(-1),  w ~ N(0, 1);   D_F = b

  tau log 10..60 min, sigma log 0.01..0.04 deg/h, g log 1..4 min/degC (thermally excited polarization noise:
  at a held fiber rate r the stationary variance is sigma^2 (1 + g |r|)).  A first-order Gauss-Markov bias,
  the correlated bias term of IEEE Std 952-1997's FOG error model; it is in the truth's drift, not its noise,
  so a sigma that claims to cover the drift must cover it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from .draws import Draws, Range

__all__ = ["FAMILIES", "FAMILY_RANGES", "FamilyPhysics", "FamilyTerm", "draw_family"]

FAMILIES = ("memory", "layered", "stress", "correlated")
#: The largest diffusion number per sub-step of the layered coil's explicit scheme (stable below 1/2).
MAX_DIFFUSION_NUMBER = 0.4

FAMILY_RANGES: dict[str, dict[str, Range]] = {
    "memory": {
        "play_width_c": Range(3.0, 15.0),
        "play_bias_dph": Range(0.05, 0.2, log=True, signed=True),
        "memory_tau_s": Range(10800.0, 43200.0, log=True),
        "memory_dph_per_c": Range(0.002, 0.01, log=True, signed=True),
    },
    "layered": {
        "layers": Range(6, 16),  # an integer
        "diffusion_tau_s": Range(600.0, 3600.0, log=True),
        "layer_weight": Range(-1.0, 1.0),  # each layer
        "shupe_dph_per_c_per_min": Range(0.1, 0.5, log=True, signed=True),
        "shupe_beta_per_c": Range(0.005, 0.02, log=True, signed=True),
    },
    "stress": {
        "creep_tau_s": Range(3600.0, 21600.0, log=True),
        "stress_dph_per_c": Range(0.005, 0.025, log=True, signed=True),
        "radial_quadratic_dph_per_c2": Range(0.0005, 0.003, log=True, signed=True),
        "warmup_heating_c": Range(1.0, 4.0),
        "warmup_tau_s": Range(600.0, 2400.0, log=True),
    },
    "correlated": {
        "tau_s": Range(600.0, 3600.0, log=True),
        "sigma_dph": Range(0.01, 0.04, log=True),
        "rate_gain_min_per_c": Range(1.0, 4.0, log=True),
    },
}


@dataclass(frozen=True)
class FamilyPhysics:
    """One family's drawn parameters (``FAMILY_RANGES[name]``'s names; ``layer_weights``: the layered coil's)."""

    name: str
    params: dict[str, float] = field(default_factory=dict)
    layer_weights: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        if self.name not in FAMILIES:
            raise ValueError(f"family: one of {', '.join(FAMILIES)}, not {self.name!r}")
        wanted = set(FAMILY_RANGES[self.name]) - {"layers", "layer_weight"}
        if set(self.params) != wanted:
            raise ValueError(f"family {self.name}: parameters {', '.join(sorted(wanted))}, got {sorted(self.params)}")
        object.__setattr__(self, "params", {k: float(v) for k, v in self.params.items()})
        object.__setattr__(self, "layer_weights", tuple(float(v) for v in self.layer_weights))
        if (self.name == "layered") != bool(self.layer_weights) or len(self.layer_weights) > 64:
            raise ValueError("layer_weights: one per layer for the layered family (at most 64), none for the others")
        for name in ("play_width_c", "memory_tau_s", "diffusion_tau_s", "creep_tau_s", "warmup_tau_s", "tau_s"):
            if name in self.params and not self.params[name] > 0:
                raise ValueError(f"family {self.name}: {name} must be > 0")

    def __hash__(self) -> int:
        return hash((self.name, tuple(sorted(self.params.items())), self.layer_weights))


def draw_family(name: str, seed: int) -> FamilyPhysics:
    """Family ``name``'s parameters for instrument ``seed``, each from the stream ``"<name>:<parameter>"``."""
    if name not in FAMILIES:
        raise ValueError(f"family: one of {', '.join(FAMILIES)}, not {name!r}")
    ranges: Mapping[str, Range] = {f"{name}:{k}": r for k, r in FAMILY_RANGES[name].items()}
    d = Draws(seed, ranges)
    params = {k: d.value(f"{name}:{k}") for k in FAMILY_RANGES[name] if k not in ("layers", "layer_weight")}
    weights: tuple[float, ...] = ()
    if name == "layered":
        raw = d.values("layered:layer_weight", d.integer("layered:layers"))
        total = sum(abs(w) for w in raw)
        weights = tuple(w / total for w in raw)
    return FamilyPhysics(name, params, weights)


def play(x: np.ndarray, width: float, start: float) -> np.ndarray:
    """The play (backlash) operator of ``width`` on the series ``x``, from the output ``start``."""
    out = np.empty(len(x))
    p, half = start, 0.5 * width
    for k, v in enumerate(np.asarray(x, dtype=np.float64).tolist()):
        p = min(v + half, max(v - half, p))
        out[k] = p
    return out


class FamilyTerm:
    """A family's drift term on the slow grid, with explicit state: ``run`` on consecutive rows gives the same
    values however the rows are split into calls.

    ``run(nodes, fiber_rate_c_per_s, boundary_c)``: node rows (housing, top, bottom, fiber, mount, ...) at the
    end of each grid step, the fiber's rate and the coil's boundary; returns D_F (deg/h) per row.
    ``heat_c(t_mid_s)``: the extra housing heat at the steps' mid-points (the stress family's warm-up), else None.
    """

    def __init__(self, physics: FamilyPhysics, dt_s: float, rng: np.random.Generator | None = None) -> None:
        self.physics = physics
        self.p = physics.params
        self.dt_s = float(dt_s)
        self.rng = rng
        self._state: list[float] | None = None  # set from the first row
        if physics.name == "correlated" and rng is None:
            raise ValueError("the correlated family needs a random generator")

    def heat_c(self, t_mid_s: np.ndarray) -> np.ndarray | None:
        if self.physics.name != "stress":
            return None
        return self.p["warmup_heating_c"] * -np.expm1(-np.asarray(t_mid_s, dtype=np.float64) / self.p["warmup_tau_s"])

    def run(self, nodes: np.ndarray, fiber_rate_c_per_s: np.ndarray, boundary_c: np.ndarray) -> np.ndarray:
        n = len(nodes)
        if not n:
            return np.zeros(0)
        return getattr(self, f"_{self.physics.name}")(
            np.asarray(nodes, dtype=np.float64), np.asarray(fiber_rate_c_per_s), np.asarray(boundary_c)
        )

    def _memory(self, nodes: np.ndarray, rate: np.ndarray, boundary: np.ndarray) -> np.ndarray:
        p, fiber = self.p, nodes[:, 3]
        if self._state is None:
            self._state = [float(fiber[0]), float(fiber[0])]
        width = p["play_width_c"]
        played = play(fiber, width, self._state[0])
        a = 1.0 - math.exp(-self.dt_s / p["memory_tau_s"])
        memory = np.empty(len(fiber))
        m = self._state[1]
        for k, v in enumerate(fiber.tolist()):
            m = m + a * (v - m)
            memory[k] = m
        self._state = [float(played[-1]), m]
        return p["play_bias_dph"] / (0.5 * width) * (played - fiber) + p["memory_dph_per_c"] * (fiber - memory)

    def layer_profile(self, inner_c: float, outer_c: float) -> list[float]:
        """The steady state between the faces: linear across the winding."""
        n = len(self.physics.layer_weights)
        return [inner_c + (outer_c - inner_c) * (i + 1) / (n + 1) for i in range(n)]

    def diffuse(self, layers: list[float], inner_c: float, outer_c: float) -> list[float]:
        """One grid step of the layers' explicit scheme, the faces held at ``inner_c`` and ``outer_c``."""
        n = len(layers)
        r_step = self.dt_s * (n + 1) ** 2 / self.p["diffusion_tau_s"]
        substeps = max(1, math.ceil(r_step / MAX_DIFFUSION_NUMBER))
        r = r_step / substeps
        t = layers
        for _ in range(substeps):
            ext = [inner_c, *t, outer_c]
            t = [ext[i] + r * (ext[i - 1] - 2.0 * ext[i] + ext[i + 1]) for i in range(1, n + 1)]
        return t

    def _layered(self, nodes: np.ndarray, rate: np.ndarray, boundary: np.ndarray) -> np.ndarray:
        p, w = self.p, self.physics.layer_weights
        inner, outer = nodes[:, 2].tolist(), nodes[:, 0].tolist()
        if self._state is None:
            self._state = self.layer_profile(inner[0], outer[0])
        out = np.empty(len(inner))
        t = self._state
        for k in range(len(inner)):
            new = self.diffuse(t, inner[k], outer[k])
            weighted_rate = sum(wi * (a - b) for wi, a, b in zip(w, new, t)) / self.dt_s  # degC/s
            mean = sum(new) / len(new)
            out[k] = p["shupe_dph_per_c_per_min"] * (1.0 + p["shupe_beta_per_c"] * (mean - 20.0)) * 60.0 * weighted_rate
            t = new
        self._state = t
        return out

    def _stress(self, nodes: np.ndarray, rate: np.ndarray, boundary: np.ndarray) -> np.ndarray:
        p = self.p
        diff = (nodes[:, 4] - nodes[:, 0]).tolist()
        if self._state is None:
            self._state = [0.0, diff[0]]
        phi = math.exp(-self.dt_s / p["creep_tau_s"])
        stress = np.empty(len(diff))
        s, last = self._state
        for k, v in enumerate(diff):
            s = phi * s + (v - last)
            last = v
            stress[k] = s
        self._state = [s, last]
        radial = boundary - nodes[:, 3]
        return p["stress_dph_per_c"] * stress + p["radial_quadratic_dph_per_c2"] * radial * radial

    def _correlated(self, nodes: np.ndarray, rate: np.ndarray, boundary: np.ndarray) -> np.ndarray:
        p = self.p
        assert self.rng is not None
        if self._state is None:
            self._state = [p["sigma_dph"] * float(self.rng.standard_normal())]  # stationary start
        phi = math.exp(-self.dt_s / p["tau_s"])
        drive = p["sigma_dph"] * math.sqrt(1.0 - phi * phi)
        gain = p["rate_gain_min_per_c"] * 60.0
        w = self.rng.standard_normal(len(nodes)).tolist()
        out = np.empty(len(w))
        b = self._state[0]
        for k, (wk, rk) in enumerate(zip(w, np.abs(rate).tolist())):
            b = phi * b + drive * math.sqrt(1.0 + gain * rk) * wk
            out[k] = b
        self._state = [b]
        return out
