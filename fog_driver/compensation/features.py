"""The drift model's input vector, per model block: temperatures, their rates, two gradients.

    u = [T1, T2, T3, dT1/dt, dT2/dt, dT3/dt, T1 - T2, T1 - T3]     degC, degC/min

T1, T2, T3 are the ring top, ring bottom and housing block means.  Rates come
from a causal smoother, never from differences of 1/256 degC readings (those
are noise): two exponential moving averages with time constants tau1 < tau2
lag a ramp of slope r by r L1 and r L2, so::

    m_k(n) = m_k(n-1) + (1 - exp(-Ts / tau_k)) (T(n) - m_k(n-1))
    L_k    = Ts / (exp(Ts / tau_k) - 1)                    (the discrete lag; -> tau_k as Ts -> 0)
    dT/dt  = (m1 - m2) / (L2 - L1)                         exact for a ramp, smoothed for noise

Inputs are standardized with ``readout.Standardizer`` (statistics stored from the fit data).
A NaN block mean (a thermometer fault) is replaced by the last valid value
for up to ``hold_s``; beyond that the block is flagged ``FLAG_INPUT_STALE``
and the last valid value is still used (the output is never NaN).  Before
any valid value at all, inputs are NaN and the block is flagged.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from . import numerics

INPUT_NAMES = ("t_top_c", "t_bottom_c", "t_housing_c", "rate_top_c_per_min", "rate_bottom_c_per_min",
               "rate_housing_c_per_min", "grad_top_bottom_c", "grad_top_housing_c")  # fmt: skip
N_INPUTS = len(INPUT_NAMES)
#: Set when a thermometer has been invalid for longer than ``hold_s`` (or was never valid).
FLAG_INPUT_STALE = 1 << 2


@dataclass(frozen=True)
class FeatureParams:
    sample_time_s: float = 1.0
    rate_tau_fast_s: float = 30.0
    rate_tau_slow_s: float = 90.0
    hold_s: float = 30.0

    def __post_init__(self) -> None:
        if not 0 < self.rate_tau_fast_s < self.rate_tau_slow_s:
            raise ValueError("need 0 < rate_tau_fast_s < rate_tau_slow_s")
        if not self.sample_time_s > 0 or self.hold_s < 0:
            raise ValueError("sample_time_s must be > 0 and hold_s >= 0")


class FeatureExtractor:
    """Block temperatures -> the 8 inputs, with explicit state (smoothers, last valid values)."""

    def __init__(self, params: FeatureParams | None = None, state: dict | None = None) -> None:
        self.params = params or FeatureParams()
        p = self.params
        # Correctly rounded exponentials: the same coefficients on every machine (the C library's are not).
        self._a1 = 1.0 - numerics.exp_correctly_rounded(-p.sample_time_s / p.rate_tau_fast_s)
        self._a2 = 1.0 - numerics.exp_correctly_rounded(-p.sample_time_s / p.rate_tau_slow_s)
        # A discrete EMA lags a ramp of slope r by r * lag, lag = Ts / (exp(Ts / tau) - 1) (-> tau as Ts -> 0).
        lag_fast = p.sample_time_s / numerics.expm1_correctly_rounded(p.sample_time_s / p.rate_tau_fast_s)
        lag_slow = p.sample_time_s / numerics.expm1_correctly_rounded(p.sample_time_s / p.rate_tau_slow_s)
        self._denominator_min = (lag_slow - lag_fast) / 60.0
        self.reset()
        if state is not None:
            self.set_state(state)

    def reset(self) -> None:
        self._last = [math.nan] * 3  # last valid temperature per sensor
        self._stale_s = [0.0] * 3  # how long each sensor has been invalid
        self._m1 = [math.nan] * 3
        self._m2 = [math.nan] * 3

    def get_state(self) -> dict:
        return {"last": list(self._last), "stale_s": list(self._stale_s), "m1": list(self._m1), "m2": list(self._m2)}

    def set_state(self, state: dict) -> None:
        self._last = [float(v) for v in state["last"]]
        self._stale_s = [float(v) for v in state["stale_s"]]
        self._m1 = [float(v) for v in state["m1"]]
        self._m2 = [float(v) for v in state["m2"]]

    def step(self, temps_c: tuple[float, float, float] | np.ndarray) -> tuple[list[float], int]:
        """The input vector for one block and its flags (``FLAG_INPUT_STALE`` or 0)."""
        p = self.params
        flags = 0
        t = [0.0, 0.0, 0.0]
        rates = [0.0, 0.0, 0.0]
        for k in range(3):
            value = float(temps_c[k])
            if value == value:
                self._last[k] = value
                self._stale_s[k] = 0.0
            else:
                self._stale_s[k] += p.sample_time_s
                value = self._last[k]
                if self._stale_s[k] > p.hold_s or value != value:
                    flags |= FLAG_INPUT_STALE
            if value != value:  # never a valid reading yet
                t[k] = math.nan
                rates[k] = math.nan
                continue
            if self._m1[k] != self._m1[k]:
                self._m1[k] = self._m2[k] = value
            self._m1[k] += self._a1 * (value - self._m1[k])
            self._m2[k] += self._a2 * (value - self._m2[k])
            t[k] = value
            rates[k] = (self._m1[k] - self._m2[k]) / self._denominator_min
        return [t[0], t[1], t[2], rates[0], rates[1], rates[2], t[0] - t[1], t[0] - t[2]], flags

    def run(self, temps_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``step`` over blocks: (n, 8) inputs and (n,) flags, bit-identical."""
        out = np.empty((len(temps_c), N_INPUTS))
        flags = np.zeros(len(temps_c), dtype=np.int64)
        for i, row in enumerate(np.asarray(temps_c, dtype=np.float64).tolist()):
            out[i], flags[i] = self.step(row)
        return out, flags


def params_to_dict(params: FeatureParams) -> dict:
    return asdict(params)
