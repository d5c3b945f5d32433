"""Allan deviation of a rate series and its IEEE 952 read points (allantools does the computing).

For a rate series in deg/h sampled every ``dt_s``::

    sigma(tau)  overlapping Allan deviation, deg/h        (allantools.oadev, data_type "freq")
    ARW         = sigma(tau = 1 s) * sqrt(1 s / 3600 s)    deg/sqrt(h)   (slope -1/2 line read at tau = 1 s)
    BI          = min over tau of sigma / 0.664           deg/h         (the flicker floor), over tau up to a
                                                                        tenth of the record (longer taus rest on
                                                                        too few intervals to read)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import UsageError
from ..extras import missing_message



def _allantools():
    try:
        import allantools
    except ImportError:
        raise UsageError(missing_message("report", "Allan deviation", ["allantools"])) from None
    return allantools


@dataclass
class AllanResult:
    tau_s: np.ndarray
    sigma_dph: np.ndarray
    arw_deg_sqrt_h: float
    bias_instability_dph: float
    bias_instability_tau_s: float


def allan(rate_dph: np.ndarray, dt_s: float = 1.0) -> AllanResult:
    """Overlapping Allan deviation at octave-spaced tau and the IEEE 952 read points."""
    rate = np.asarray(rate_dph, dtype=np.float64)
    if len(rate) < 16 or not np.all(np.isfinite(rate)):
        raise ValueError("the Allan deviation needs at least 16 finite samples")
    tau, sigma, _, _ = _allantools().oadev(rate, rate=1.0 / dt_s, data_type="freq", taus="octave")
    tau = np.asarray(tau, dtype=np.float64)
    sigma = np.asarray(sigma, dtype=np.float64)
    at_1s = float(np.interp(0.0, np.log(tau), np.log(sigma))) if tau[0] > 1.0 else None
    sigma_1s = float(np.exp(at_1s)) if at_1s is not None else float(sigma[np.argmin(np.abs(tau - 1.0))])
    readable = np.flatnonzero(tau <= len(rate) * dt_s / 10.0)
    candidates = readable if len(readable) else np.arange(len(tau))
    i = int(candidates[np.argmin(sigma[candidates])])
    return AllanResult(tau, sigma, sigma_1s / 60.0, float(sigma[i] / 0.664), float(tau[i]))
