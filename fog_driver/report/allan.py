"""Allan deviation of a rate series, its confidence intervals and its IEEE 952 read points.

allantools does the computing.  For a rate series in deg/h, one value every ``dt_s``::

    sigma(tau)   overlapping Allan deviation, deg/h, at octave taus (allantools.oadev, data_type "freq")

Confidence interval at every tau (as Stable32 and allantools' ``confidence_interval_noiseID`` do)
    1. the noise type alpha (frequency-noise exponent: 2 white PM, 1 flicker PM, 0 white FM (ARW),
       -1 flicker FM (bias instability), -2 random-walk FM (RRW)) by the lag-1 autocorrelation
       (``allantools.autocorr_noise_id``, Riley & Greenhall 2004), on the series averaged over tau.
       Made robust two ways: it is run only where the averaged series has at least
       ``NOISE_ID_MIN_POINTS`` (100) points (the lag-1 autocorrelation's standard error is about
       1/sqrt(n): at 30 points, the allantools minimum, white noise of 10 h read as flicker PM at
       tau = 1024 s and got a 10x too narrow interval), longer taus keep the last identified alpha;
       and alpha never rises with tau (a gyro's noise only reddens with tau: Q, N, B, K, R in
       IEEE 952's order), so a chance identification cannot narrow a long tau's interval;
    2. the equivalent degrees of freedom of the overlapping estimator for that alpha,
       ``allantools.edf_greenhall(alpha, d=2, m, N, overlapping=True)`` (Greenhall & Riley 2004);
    3. the chi-squared interval (NIST SP 1065 eq. 45), ``allantools.confidence_interval(sigma, edf,
       ci=0.683)``: ``sigma^2 edf / chi2(0.84, edf) <= sigma_true^2 <= sigma^2 edf / chi2(0.16, edf)``.

Trusted taus
    tau <= T / ``TRUST_FRACTION`` (10), T the length of the record.  At tau = T/10 the overlapping
    estimator of white FM still has about 13 degrees of freedom (a 68 % interval of about +-20 %);
    beyond it, with fewer than 10 independent intervals, a flicker or random-walk noise leaves fewer
    than 5 and the interval spans a factor 2.  Longer taus are computed, tabulated and drawn
    (hollow, dashed) but never read.

Read points (IEEE Std 952-1997, Annex C; sigma(tau) of the rate in deg/h, tau in s)::

    region            sigma(tau)                 slope    read at            reported as
    quantization Q    sqrt(3) Q / tau            -1       tau = sqrt(3) s    Q = sigma(sqrt 3) [deg/h s = arcsec]
    angle RW  N       N / sqrt(tau)              -1/2     tau = 1 s          N = sigma(1) / 60   deg/sqrt(h)
    bias inst. B      sqrt(2 ln 2 / pi) B        0        the minimum        B = sigma_min / 0.6643   deg/h
    rate RW   K       K sqrt(tau / 3)            +1/2     tau = 3 s          K = 60 sigma(3)     deg/h/sqrt(h)
    rate ramp R       R tau / sqrt(2)            +1       tau = sqrt(2) s    R = 3600 sigma(sqrt 2)  deg/h/h

Q, N, K and R are read on a line of the region's slope fitted (in log-log, the slope fixed, the
intercept weighted by each point's degrees of freedom) through the longest run of at least
``MIN_REGION_POINTS`` (3) consecutive trusted taus that shows that slope: the run's own least-squares
slope within ``SLOPE_TOLERANCE`` (0.2) of it and every point within ``REGION_SIGMAS`` (3) standard
errors of the line (the standard error of ln sigma is 1 / sqrt(2 edf)).  Where no run shows the slope,
the reading is None ("not reached").  Two regions may share a corner tau, no more: of two that
overlap further (a curve whose scatter fits two slopes, e.g. a thermal drift between +1/2 and +1),
the one over fewer octaves is dropped, as not shown.  B is the minimum of sigma over the trusted taus; when that
minimum is at the last trusted tau the curve is still falling there, and B is only an upper bound
("minimum not reached"; ``bias_instability_bound`` is "upper bound", else "floor").
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import UsageError
from ..extras import missing_message

TRUST_FRACTION = 10.0
NOISE_ID_MIN_POINTS = 100
CONFIDENCE = 0.683
MIN_REGION_POINTS = 3
SLOPE_TOLERANCE = 0.2
REGION_SIGMAS = 3.0
#: sqrt(2 ln 2 / pi): the flicker floor of the Allan deviation over the bias instability B
FLICKER_FLOOR = math.sqrt(2.0 * math.log(2.0) / math.pi)

#: the slope of each read point's region, log sigma over log tau
SLOPES = {"quantization": -1.0, "arw": -0.5, "rrw": 0.5, "rate_ramp": 1.0}
#: the ADEV table's columns (summary.json and allan-<series>.csv)
TABLE_COLUMNS = ("tau_s", "adev_dph", "lo_dph", "hi_dph", "n_pairs", "edf", "alpha", "trusted")


def _allantools():
    try:
        import allantools  # optional extra: report
    except ImportError:
        raise UsageError(missing_message("report", "Allan deviation", ["allantools"])) from None
    return allantools


@dataclass
class AllanResult:
    """The ADEV curve with its 68.3 % confidence interval, and the IEEE 952 read points (module docstring).

    A read point is None where the curve shows no region of its slope within the trusted taus."""

    tau_s: np.ndarray
    sigma_dph: np.ndarray
    lo_dph: np.ndarray  #: the interval's lower end
    hi_dph: np.ndarray  #: the interval's upper end
    n_pairs: np.ndarray  #: the number of overlapping differences averaged
    edf: np.ndarray  #: equivalent degrees of freedom
    alpha: np.ndarray  #: the noise type the interval assumes
    trusted: np.ndarray  #: bool: tau <= record / TRUST_FRACTION
    record_s: float
    arw_deg_per_rt_h: float | None
    bias_instability_dph: float
    bias_instability_tau_s: float
    bias_instability_bound: str  #: "floor", or "upper bound" (the curve still falls at the last trusted tau)
    rrw_dph_per_rt_h: float | None
    rate_ramp_dph_per_h: float | None
    quantization_arcsec: float | None
    #: per read point (``SLOPES``' names), the fitted line's (first tau, last tau) in s ...
    regions: dict[str, tuple[float, float]]
    #: ... and its intercept: ln sigma = intercept + slope ln tau
    intercepts: dict[str, float]

    def line_dph(self, name: str, tau_s: np.ndarray) -> np.ndarray:
        """The fitted line of read point ``name`` at ``tau_s``, deg/h."""
        return np.exp(self.intercepts[name] + SLOPES[name] * np.log(tau_s))

    @property
    def trusted_limit_s(self) -> float:
        return self.record_s / TRUST_FRACTION

    @property
    def minimum_reached(self) -> bool:
        return self.bias_instability_bound == "floor"

    def read_points(self) -> dict:
        """The read points as summary.json keeps them (units in the names; None: not reached)."""
        return {
            "arw_deg_per_rt_h": self.arw_deg_per_rt_h,
            "bias_instability_dph": self.bias_instability_dph,
            "bias_instability_tau_s": self.bias_instability_tau_s,
            "bias_instability_bound": self.bias_instability_bound,
            "rrw_dph_per_rt_h": self.rrw_dph_per_rt_h,
            "rate_ramp_dph_per_h": self.rate_ramp_dph_per_h,
            "quantization_arcsec": self.quantization_arcsec,
            "trusted_tau_max_s": self.trusted_limit_s,
            "regions_s": {k: list(v) for k, v in self.regions.items()},
        }

    def table(self) -> list[dict]:
        """The full ADEV table, one dict per tau (``TABLE_COLUMNS``)."""
        return [
            {
                "tau_s": float(t),
                "adev_dph": float(s),
                "lo_dph": float(lo),
                "hi_dph": float(hi),
                "n_pairs": int(n),
                "edf": float(e),
                "alpha": int(a),
                "trusted": bool(ok),
            }
            for t, s, lo, hi, n, e, a, ok in zip(
                self.tau_s, self.sigma_dph, self.lo_dph, self.hi_dph, self.n_pairs, self.edf, self.alpha, self.trusted
            )
        ]


def allan(rate_dph: np.ndarray, dt_s: float = 1.0) -> AllanResult:
    """Overlapping Allan deviation at octave taus, its confidence intervals and read points (module docstring)."""
    at = _allantools()
    rate = np.asarray(rate_dph, dtype=np.float64)
    if len(rate) < 16 or not np.all(np.isfinite(rate)):
        raise ValueError("the Allan deviation needs at least 16 finite samples")
    tau, sigma, _, n_pairs = at.oadev(rate, rate=1.0 / dt_s, data_type="freq", taus="octave")
    tau = np.asarray(tau, dtype=np.float64)
    sigma = np.asarray(sigma, dtype=np.float64)
    m = np.rint(tau / dt_s).astype(int)
    alpha = np.zeros(len(tau), dtype=int)
    last = 2  # the whitest type, until identified
    for k, mk in enumerate(m):
        if len(rate) // mk >= NOISE_ID_MIN_POINTS:
            found = int(np.clip(at.autocorr_noise_id(rate, int(mk), data_type="freq", dmin=0, dmax=2)[0], -2, 2))
            last = min(last, found)
        alpha[k] = last
    edf = np.array([_edf(at, int(a), int(mk), len(rate) + 1) for a, mk in zip(alpha, m)], dtype=np.float64)
    bounds = np.array([at.confidence_interval(s, e, ci=CONFIDENCE) for s, e in zip(sigma, edf)])
    record_s = len(rate) * dt_s
    trusted = tau <= record_s / TRUST_FRACTION
    if not trusted.any():
        trusted[0] = True
    t_idx = np.flatnonzero(trusted)
    i_min = int(t_idx[np.argmin(sigma[t_idx])])
    bound = "upper bound" if i_min == t_idx[-1] and len(t_idx) > 1 else "floor"
    regions: dict[str, tuple[float, float]] = {}
    intercepts: dict[str, float] = {}

    def read(name: str, at_tau_s: float) -> float | None:
        slope = SLOPES[name]
        line = slope_region(tau[t_idx], sigma[t_idx], edf[t_idx], slope)
        if line is None:
            return None
        intercept, first, stop = line
        regions[name] = (float(tau[t_idx][first]), float(tau[t_idx][stop - 1]))
        intercepts[name] = intercept
        return float(math.exp(intercept + slope * math.log(at_tau_s)))

    readings = {
        "arw": read("arw", 1.0),
        "quantization": read("quantization", math.sqrt(3.0)),
        "rrw": read("rrw", 3.0),
        "rate_ramp": read("rate_ramp", math.sqrt(2.0)),
    }
    # one region per stretch of the curve: of two regions sharing more than a corner, the shorter is dropped
    by_length = sorted(regions, key=lambda k: (-np.log2(regions[k][1] / regions[k][0]), list(SLOPES).index(k)))
    kept: list[str] = []
    for name in by_length:
        t0, t1 = regions[name]
        if any(min(t1, regions[o][1]) > max(t0, regions[o][0]) for o in kept):
            del regions[name], intercepts[name]
            readings[name] = None
        else:
            kept.append(name)
    arw, q, rrw, ramp = (readings[k] for k in ("arw", "quantization", "rrw", "rate_ramp"))
    return AllanResult(
        tau,
        sigma,
        bounds[:, 0],
        bounds[:, 1],
        np.asarray(n_pairs, dtype=np.int64),
        edf,
        alpha,
        trusted,
        record_s,
        arw_deg_per_rt_h=None if arw is None else arw / 60.0,
        bias_instability_dph=float(sigma[i_min] / FLICKER_FLOOR),
        bias_instability_tau_s=float(tau[i_min]),
        bias_instability_bound=bound,
        rrw_dph_per_rt_h=None if rrw is None else 60.0 * rrw,
        rate_ramp_dph_per_h=None if ramp is None else 3600.0 * ramp,
        quantization_arcsec=q,  # sigma(sqrt 3) in deg/h times 1 s = arcsec
        regions=regions,
        intercepts=intercepts,
    )


def _edf(at, alpha: int, m: int, n_phase: int) -> float:
    """Greenhall's EDF of the overlapping ADEV; where it has no case (white PM with fewer than 3 strides
    of data), the next redder alpha's (fewer degrees of freedom: a wider, safe interval)."""
    for a in range(alpha, -3, -1):
        try:
            return float(at.edf_greenhall(alpha=a, d=2, m=m, N=n_phase, overlapping=True, modified=False))
        except NotImplementedError:
            continue
    return 1.0


def slope_region(tau: np.ndarray, sigma: np.ndarray, edf: np.ndarray, slope: float) -> tuple[float, int, int] | None:
    """The longest run ``[first, stop)`` of at least ``MIN_REGION_POINTS`` consecutive points that shows
    ``slope`` (module docstring) and the intercept of its line, ``ln sigma = intercept + slope ln tau``;
    None when there is none.  Ties: the run at the shorter taus."""
    x, y = np.log(tau), np.log(sigma)
    se = 1.0 / np.sqrt(2.0 * np.maximum(edf, 1.0))  # standard error of ln sigma
    w = 1.0 / se**2
    best = None
    n = len(x)
    for first in range(n):
        for stop in range(first + MIN_REGION_POINTS, n + 1):
            xs, ys, ws, ss = x[first:stop], y[first:stop], w[first:stop], se[first:stop]
            free = np.polyfit(xs, ys, 1)[0]
            if abs(free - slope) > SLOPE_TOLERANCE:
                continue
            intercept = float(np.sum(ws * (ys - slope * xs)) / np.sum(ws))
            if np.any(np.abs(ys - intercept - slope * xs) > REGION_SIGMAS * ss):
                continue
            if best is None or stop - first > best[2] - best[1]:
                best = (intercept, first, stop)
    return best


def write_csv(path: Path, result: AllanResult) -> Path:
    """The ADEV table as CSV (``TABLE_COLUMNS``; trusted as 1/0); ``read_csv`` reads it back."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(TABLE_COLUMNS)
    for row in result.table():
        writer.writerow([repr(row[c]) if isinstance(row[c], float) else int(row[c]) for c in TABLE_COLUMNS])
    path.write_text(buf.getvalue(), encoding="ascii")
    return path


def read_csv(path: Path) -> list[dict]:
    """The rows ``write_csv`` wrote, as ``AllanResult.table`` gives them."""
    with path.open(encoding="ascii", newline="") as f:
        rows = list(csv.DictReader(f))
    out = []
    for r in rows:
        out.append(
            {
                "tau_s": float(r["tau_s"]),
                "adev_dph": float(r["adev_dph"]),
                "lo_dph": float(r["lo_dph"]),
                "hi_dph": float(r["hi_dph"]),
                "n_pairs": int(r["n_pairs"]),
                "edf": float(r["edf"]),
                "alpha": int(r["alpha"]),
                "trusted": r["trusted"] == "1",
            }
        )
    return out
