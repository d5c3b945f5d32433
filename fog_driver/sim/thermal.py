"""Thermal model of the instrument: chamber air -> housing and mount -> fiber ring top and bottom -> fiber.

A lumped, linear network of first-order links (temperatures in degC, time
constants in s)::

    dTh/dt = (Tair + q_h - Th) / tau_h                                  housing, self-heated by q_h
    dTt/dt = (Th + q_t - Tt) / tau_t + (Tb - Tt) / tau_r                ring top (electronics above it: q_t)
    dTb/dt = (Th - Tb) / tau_b + (Tm - Tb) / tau_mb + (Tt - Tb) / tau_r  ring bottom, on the base plate
    Tc     = c_t Tt + c_b Tb + c_h Th                                  the coil's boundary (coupling weights, sum 1)
    dC1/dt = (Tc - C1) / tau_1,  dC2/dt = (C1 - C2) / tau_2, ...       the coil's internal lags (none by default)
    dTf/dt = (Cn - Tf) / tau_f           (Cn = Tc without inner lags)   the fiber itself (not measured)
    dTm/dt = (Tair - Tm) / tau_m                                        the turntable mount (not measured)

The top and bottom of the ring follow the housing with different time
constants, and the bottom also follows the turntable it is bolted to, a large
thermal mass that lags the air by tens of minutes; so a ramp produces a real
top-bottom gradient that lives on after the ramp, not just in proportion to
the rate of change (which would make the gradient and Shupe terms impossible
to tell apart).  The fiber, wound between top and bottom, lags both
thermometers.  At power-on (``cold_start``) every node
starts at the air temperature and the self-heating warms the instrument over
the first half hour, as in the paper's 30-minute warm-up.  The mount starts at the air temperature.

The coil.  By default its boundary is the ring mean (``coil_coupling`` (0.5, 0.5, 0)) and one lag of
``tau_fiber_s`` separates it from the fiber; a real coil's potting, former and layers make a
distributed thermal mass, which ``coil_inner_lags_s`` approximates by more first-order stages in
series (outermost first), and a coil in contact with the housing wall couples to it too
(``coil_coupling[2]``).  ``fog_driver.sim.population`` draws both per instrument.

Discretisation: exact for an input held over each step (zero-order hold at
the step's mid-point air temperature), ``x(k+1) = Phi x(k) + Gamma u(k)`` with
``Phi = expm(A dt)``, ``Gamma = int_0^dt expm(A s) ds B``, on a fixed grid of
``dt_s`` (1 s by default; the smallest time constant is minutes).

Defaults (chosen to be plausible for a navigation-grade FOG angle instrument
of about 15 cm diameter in a thermal chamber, and stated so a reader can
disagree): the housing follows the air with 8 min (aluminium case, forced
chamber air); the ring top and bottom follow the housing with 5 and 7 min
(the bottom sits on a thicker base plate), and exchange heat through the
ring with 10 min; the bottom exchanges with the mount with 10 min, and the
mount (a turntable top plate) follows the air with 40 min; the fiber lags the
ring surfaces by 4 min (potting); 3 degC
of self-heating in the housing and 0.3 degC from the electronics above the
ring, so there is a small static gradient.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

NODES = ("housing", "top", "bottom", "fiber", "mount")  #: then the coil's inner stages C1..Cn, if any


@dataclass(frozen=True)
class ThermalParams:
    tau_housing_s: float = 480.0
    tau_top_s: float = 300.0
    tau_bottom_s: float = 420.0
    tau_ring_s: float = 600.0
    tau_fiber_s: float = 240.0
    tau_mount_s: float = 2400.0
    tau_bottom_mount_s: float = 600.0
    self_heating_c: float = 3.0
    top_heating_c: float = 0.3
    cold_start: bool = True
    coil_coupling: tuple[float, ...] = (0.5, 0.5, 0.0)  #: weights of ring top, ring bottom, housing; sum 1
    coil_inner_lags_s: tuple[float, ...] = ()  #: the coil's inner stages before tau_fiber_s, outermost first

    def __post_init__(self) -> None:
        for name in (
            "tau_housing_s",
            "tau_top_s",
            "tau_bottom_s",
            "tau_ring_s",
            "tau_fiber_s",
            "tau_mount_s",
            "tau_bottom_mount_s",
        ):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0")
        w = tuple(float(v) for v in self.coil_coupling)
        if len(w) != 3 or min(w) < 0 or abs(sum(w) - 1.0) > 1e-9:
            raise ValueError(f"coil_coupling: three weights >= 0 (top, bottom, housing) summing to 1, got {w}")
        lags = tuple(float(v) for v in self.coil_inner_lags_s)
        if len(lags) > 8 or not all(v > 0 for v in lags):
            raise ValueError(f"coil_inner_lags_s: up to 8 time constants > 0, got {lags}")
        object.__setattr__(self, "coil_coupling", w)
        object.__setattr__(self, "coil_inner_lags_s", lags)

    def system(self) -> tuple[Matrix, list[float], list[float]]:
        """``dx/dt = A x + B u + c`` with x = [Th, Tt, Tb, Tf, Tm, C1..Cn] and u = Tair."""
        h, t, b, r, f = self.tau_housing_s, self.tau_top_s, self.tau_bottom_s, self.tau_ring_s, self.tau_fiber_s
        m, mb = self.tau_mount_s, self.tau_bottom_mount_s
        inner = self.coil_inner_lags_s
        n = 5 + len(inner)
        ct, cb, ch = self.coil_coupling
        boundary = [ch, ct, cb, 0.0, 0.0] + [0.0] * len(inner)  # Tc as a row over the state
        a = [
            [-1 / h, 0.0, 0.0, 0.0, 0.0],
            [1 / t, -1 / t - 1 / r, 1 / r, 0.0, 0.0],
            [1 / b, 1 / r, -1 / b - 1 / r - 1 / mb, 0.0, 1 / mb],
            [0.0, 0.0, 0.0, -1 / f, 0.0],
            [0.0, 0.0, 0.0, 0.0, -1 / m],
        ]
        a = [row + [0.0] * len(inner) for row in a]
        # What drives each coil stage: the boundary Tc, then the stage before it; the fiber is driven by the last.
        drivers = [boundary] + [[float(j == 5 + i) for j in range(n)] for i in range(len(inner))]
        for i, tau in enumerate(inner):
            a.append([d / tau for d in drivers[i]])
            a[-1][5 + i] -= 1 / tau
        a[3] = [d / f for d in drivers[-1]]
        a[3][3] -= 1 / f
        bu = [1 / h, 0.0, 0.0, 0.0, 1 / m] + [0.0] * len(inner)
        c = [self.self_heating_c / h, self.top_heating_c / t, 0.0, 0.0, 0.0] + [0.0] * len(inner)
        return a, bu, c

    def boundary_c(self, nodes: np.ndarray) -> np.ndarray:
        """The coil's boundary temperature Tc for node rows (n, 5 + inner) in the state's order."""
        ct, cb, ch = self.coil_coupling
        tc = ct * nodes[:, 1] + cb * nodes[:, 2]
        return tc + ch * nodes[:, 0] if ch else tc

    def fiber_rate_c_per_s(self, nodes: np.ndarray) -> np.ndarray:
        """dTf/dt from the model: (driver - Tf) / tau_f, the driver being Tc or the last inner stage."""
        driver = nodes[:, 4 + len(self.coil_inner_lags_s)] if self.coil_inner_lags_s else self.boundary_c(nodes)
        return (driver - nodes[:, 3]) / self.tau_fiber_s

    def equilibrium(self, air_c: float) -> np.ndarray:
        """The powered instrument's steady state at a constant air temperature: ``A x + B u + c = 0``."""
        a, bu, c = self.system()
        return np.array(_solve(a, [-(bi * air_c + ci) for bi, ci in zip(bu, c)]))


Matrix = list[list[float]]


def _matmul(a: Matrix, b: Matrix) -> Matrix:
    return [[sum(a[i][k] * b[k][j] for k in range(len(b))) for j in range(len(b[0]))] for i in range(len(a))]


def expm(m: Matrix) -> Matrix:
    """Matrix exponential by scaling and squaring with a Taylor series, in plain floats.

    Plain Python arithmetic rather than BLAS: the same bits on every machine, so a
    seed gives the same capture everywhere (BLAS kernels round differently per CPU).
    """
    n = len(m)
    norm = max(sum(abs(v) for v in row) for row in m)
    squarings = 0
    while norm / 2**squarings > 0.5:
        squarings += 1
    scaled = [[v / 2**squarings for v in row] for row in m]
    result = [[float(i == j) for j in range(n)] for i in range(n)]
    term = [row[:] for row in result]
    for k in range(1, 20):
        term = [[v / k for v in row] for row in _matmul(term, scaled)]
        result = [[r + t for r, t in zip(rr, tr)] for rr, tr in zip(result, term)]
    for _ in range(squarings):
        result = _matmul(result, result)
    return result


def _solve(a: Matrix, b: list[float]) -> list[float]:
    """Gaussian elimination with partial pivoting, plain floats (small systems)."""
    n = len(a)
    m = [row[:] + [rhs] for row, rhs in zip(a, b)]
    for col in range(n):
        pivot = max(range(col, n), key=lambda r: abs(m[r][col]))
        m[col], m[pivot] = m[pivot], m[col]
        for r in range(col + 1, n):
            f = m[r][col] / m[col][col]
            m[r] = [x - f * y for x, y in zip(m[r], m[col])]
    x = [0.0] * n
    for r in range(n - 1, -1, -1):
        x[r] = (m[r][n] - sum(m[r][c] * x[c] for c in range(r + 1, n))) / m[r][r]
    return x


class ThermalModel:
    """Steps the thermal network along a fixed time grid, with explicit state.

    ``run(air_c_mid)`` advances one step per entry of ``air_c_mid`` (the air
    temperature at each step's mid-point) and returns the node temperatures
    at the END of each step, shape (n, 5) in ``NODES`` order.
    """

    def __init__(self, params: ThermalParams, dt_s: float, initial_air_c: float, housing_heat: bool = False) -> None:
        """``housing_heat``: ``run`` also takes an extra heat in the housing (degC of its steady rise, like
        ``self_heating_c``) per step (a physics family's warm-up); its Gamma column is computed apart, so
        Phi and the other columns are the same bits with or without it."""
        self.params = params
        self.dt_s = float(dt_s)
        a, bu, c = params.system()
        # expm of the augmented [[A, B, c], [0, 0, 0]] dt gives Phi and, in its last two columns,
        # Gamma = int_0^dt expm(A s) ds [B, c]: the held input and the heat sources over one step.
        n = len(a)
        augmented = [row + [bi, ci] for row, bi, ci in zip(a, bu, c)] + [[0.0] * (n + 2), [0.0] * (n + 2)]
        e = expm([[v * dt_s for v in row] for row in augmented])
        self._phi = [row[:n] for row in e[:n]]
        self._gamma_u = [row[n] for row in e[:n]]
        self._gamma_c = [row[n + 1] for row in e[:n]]
        self._gamma_heat: list[float] | None = None
        if housing_heat:
            heat = [[*row, float(i == 0) / params.tau_housing_s] for i, row in enumerate(a)] + [[0.0] * (n + 1)]
            self._gamma_heat = [row[n] for row in expm([[v * dt_s for v in row] for row in heat])[:n]]
        if params.cold_start:
            self.state = np.full(n, float(initial_air_c))
        else:
            self.state = params.equilibrium(initial_air_c)

    def run(self, air_c_mid: np.ndarray, heat_c_mid: np.ndarray | None = None) -> np.ndarray:
        """``heat_c_mid``: the extra housing heat per step (only with ``housing_heat``)."""
        out = np.empty((len(air_c_mid), len(self.state)))
        x = self.state.tolist()
        rows = [(phi_row, gu, gc) for phi_row, gu, gc in zip(self._phi, self._gamma_u, self._gamma_c)]
        if heat_c_mid is not None:
            if self._gamma_heat is None:
                raise ValueError("this thermal model was built without housing_heat")
            gh = self._gamma_heat
            air = np.asarray(air_c_mid, dtype=np.float64).tolist()
            for k, (u, q) in enumerate(zip(air, np.asarray(heat_c_mid, dtype=np.float64).tolist())):
                x = [sum(p * v for p, v in zip(r[0], x)) + r[1] * u + r[2] + g * q for r, g in zip(rows, gh)]
                out[k] = x
            self.state = np.array(x)
            return out
        for k, u in enumerate(np.asarray(air_c_mid, dtype=np.float64).tolist()):
            # Plain floats: a 5x5 step is faster (and the same on every machine) outside numpy.
            x = [sum(p * v for p, v in zip(phi_row, x)) + gu * u + gc for phi_row, gu, gc in rows]
            out[k] = x
        self.state = np.array(x)
        return out
