"""The bias capture: everything constant (the Earth rate, the turn-on bias), captured at each switch-on.

The bias is the T_eff-weighted mean of the intervals' rates ``r / T_eff`` (``estimate``: r before any bias)
over the first intervals spanning ``capture_s``::

    bias = sum r / sum T_eff

An interval whose rate is farther than ``TABLE_SIGMAS`` sigmas from the capture's mean so far is rejected,
with ``sigma^2 = R / T_eff^2 + var(rates so far) + prior_dph^2 + (1e-6 SF_PRIOR_PPM m / T_eff)^2`` (its own
noise, the capture's spread, the drift's spread allowed for, and the scale factor, not yet known, times the
move m).  ``capture_s = 0``: no capture, the bias is 0.  ``BiasCapture.get_state`` is the capture in progress as
plain values (exact), ``set_state`` its inverse.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .estimate import ARCSEC_PER_DEG, SF_PRIOR_PPM, TABLE_SIGMAS

__all__ = ["BiasCapture"]


class BiasCapture:
    """The capture of one run (module docstring); ``bias_dph`` None until it is complete."""

    def __init__(self, capture_s: float) -> None:
        self.capture_s = capture_s
        self.bias_dph: float | None = None if capture_s > 0 else 0.0
        self.sum_arcsec = 0.0
        self.time_s = 0.0
        #: each interval's (rate, T_eff) taken so far
        self.rates: list[tuple[float, float]] = []

    def so_far(self) -> tuple[float, float] | None:
        """The bias and its between-interval variance: the captured one (variance 0), else the capture's so far;
        None before its first interval."""
        if self.bias_dph is not None:
            return self.bias_dph, 0.0
        if self.time_s > 0:
            spread = [q for q, _ in self.rates]
            return self.sum_arcsec / self.time_s, float(np.var(spread)) if len(spread) >= 2 else 0.0
        return None

    def disagreement(
        self, r: float, t_eff: float, r_var: float, move_deg: float, prior_dph: float
    ) -> tuple[float, float] | None:
        """The interval's rate less the capture's mean so far and its sigma (deg/h) when it is farther than
        ``TABLE_SIGMAS`` sigmas from it (module docstring); None when it agrees, or is the first."""
        so_far = self.so_far()
        if so_far is None:
            return None
        mean, between = so_far
        rate = r / t_eff
        sf = 1e-6 * SF_PRIOR_PPM * move_deg * ARCSEC_PER_DEG / t_eff  # the scale factor, not yet known
        sigma = math.sqrt(r_var / t_eff**2 + between + prior_dph**2 + sf * sf)
        if abs(rate - mean) > TABLE_SIGMAS * sigma:
            return rate - mean, sigma
        return None

    def add(self, r: float, t_eff: float) -> None:
        """An interval taken: into the sums, the bias once they span ``capture_s``."""
        self.rates.append((r / t_eff, t_eff))
        self.sum_arcsec += r
        self.time_s += t_eff
        if self.time_s >= self.capture_s:
            self.bias_dph = self.sum_arcsec / self.time_s

    def get_state(self) -> dict[str, Any]:
        """The capture as plain values (exact): the bias (None while captured), the sums and the intervals'
        (rate, T_eff) so far."""
        return {
            "bias_dph": None if self.bias_dph is None else float(self.bias_dph),
            "sum_arcsec": float(self.sum_arcsec),
            "time_s": float(self.time_s),
            "rates": [[float(q), float(t)] for q, t in self.rates],
        }

    def set_state(self, state: dict[str, Any]) -> None:
        """Inverse of ``get_state``; ``ValueError`` (nothing changed) for values that are not numbers."""
        bias = None if state["bias_dph"] is None else float(state["bias_dph"])
        rates = [(float(q), float(t)) for q, t in state["rates"]]
        self.sum_arcsec, self.time_s = float(state["sum_arcsec"]), float(state["time_s"])
        self.bias_dph, self.rates = bias, rates
