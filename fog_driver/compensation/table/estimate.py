"""The law: an interval between two dwells as an observation, the sums it adds to, and the estimate.

The observation.  Between dwells a and b (their sums under the kernel K, ``window``), with A the table's angles
at the windows' mean times (arcsec) and dA = A_b - A_a, its whole turns taken from the gyro's own move::

    r = theta - dA - F - bias T_eff
      = x . dw + T_eff db + 1e-6 dA s0 + 1e-6 dA (T_int - SF_REF_C) s1 + e

the drift the frozen model missed, as weights dw on the shape regressors and a level db, and the scale factor
error ``s(T) = s0 + s1 (T - SF_REF_C)`` ppm times the move.  ``phi`` is the row of r's regressors
(``Layout``: dw, db, s0, s1).  Its noise, ``R = N^2 B (L_a / 3 + G + L_b / 3) + (MODEL_NOISE_SHARE sigma_D
T_eff)^2``: the gyro's white noise under the kernel (L the windows' lengths, G the time between them, N^2 the
block rates' white noise variance, ``noise_var_dph2``) and the frozen model's share (sigma_D its fit residual).

The sums (the paper's ``dH/dt = -l H + X X^T``, ``dI/dt = -l I + X D`` with the intervals as impulses weighted
by their inverse noise)::

    H = k k^T o H + phi phi^T / R        I = k o I + phi r / R

with ``k = sqrt(beta)`` on the drift's rows (``beta = exp(-dt / TABLE_MEMORY_S)``) and 1 on the scale
factor's.  Each prior scale s_D of ``PRIOR_SCALES`` (in runaway bounds) gives an estimate ``delta_k = P_k I``,
``P_k = (H + L0(s_D))^-1``; the scale 0 learns the level and the scale factor alone (``dw = 0``).  The prior
L0 (``prior``): on the correction's variation ``n C / s_D^2`` (C the regressors' covariance over the blocks
seen, ``gram``), on its mean level ``m . dw + db`` the runaway bound, on the scale factor ``SF_PRIOR_PPM`` and
``SF_SLOPE_PRIOR_PPM_PER_C``.

The evidence.  Before an interval is learned, each scale predicts it, ``N(phi . delta_k, c (R + phi P_k
phi^T))``, and ``E_k = beta E_k + log p_k(r)``.  The estimate in use is the mixture's mean, ``delta = sum_k
w_k delta_k``, ``w_k ~ exp(E_k)`` with prior odds ``exp(FROZEN_LOG_ODDS)`` for the frozen shape, and P the
mixture's covariance ``sum_k w_k (P_k + (delta_k - delta)(delta_k - delta)^T)``: the weights move smoothly,
so the drift has no steps, and a model that is right keeps its shape (a wider prior predicts the intervals no
better and pays for its spread).  ``c`` (``calibration``) is
the running mean of the squared normalized innovations ``z^2 = e^2 / (R + phi P phi^T)``, each capped at
``CALIBRATION_CAP``, over ``CALIBRATION_INTERVALS`` with a prior of ``CALIBRATION_PRIOR`` intervals at 1.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np

from ..adapt import RUNAWAY_FIT_RESIDUALS
from .window import Anchor, Columns

__all__ = ["ARCSEC_PER_DEG", "SF_REF_C", "TABLE_SIGMAS", "Layout", "MixtureLaw", "Prediction"]

ARCSEC_PER_DEG = 3600.0
TURN_ARCSEC = 360.0 * ARCSEC_PER_DEG
#: The rejection threshold, in sigmas of the interval's innovation.
TABLE_SIGMAS = 3.0
#: A move farther than this from every whole turn of the gyro's own is ambiguous: refused.
AMBIGUOUS_DEG = 90.0
#: The scale factor's reference temperature: s(T) = s0 + s1 (T - SF_REF_C).
SF_REF_C = 25.0
SF_PRIOR_PPM = 100.0
SF_SLOPE_PRIOR_PPM_PER_C = 2.0
#: The memory of the law's sums and of the evidence (the exponential forgetting of old intervals), 24 h
#: (``benchmarks/bench_table.py``; docs/decisions/2026-12-07-table-law-prior.md).
TABLE_MEMORY_S = 24 * 3600.0
#: The drift prior's scales the law weighs (s_D, in runaway bounds); 0 is the frozen shape (the level and the
#: scale factor learned), weighed by their evidence rather than one scale for all (``benchmarks/bench_table.py``;
#: docs/decisions/2026-12-07-table-law-prior.md).
PRIOR_SCALES = (0.0, 0.025, 0.05, 0.1, 0.2)
#: The frozen shape's prior log odds against each of the others (e^3: a prior weight of 0.83 among five):
#: the evidence must earn a departure (``benchmarks/bench_table.py``; docs/decisions/2026-12-07-table-law-prior.md).
FROZEN_LOG_ODDS = 3.0
#: The share of the frozen model's drift sigma counted as the interval's noise.
MODEL_NOISE_SHARE = 0.5
#: The innovation calibration's memory (intervals), its prior weight (intervals at 1), and the cap on
#: one interval's squared normalized innovation (a liar must not widen the threshold much).
CALIBRATION_INTERVALS = 20.0
CALIBRATION_PRIOR = 4.0
CALIBRATION_CAP = 16.0
#: The gram of the regressors: its memory.
GRAM_MEMORY_S = TABLE_MEMORY_S
#: The law's shape regressors g: the candidate structures' departures from the frozen drift (a model file
#: with candidates), or the model's own regressors (without).
SHAPE_CANDIDATES = "candidates"
SHAPE_REGRESSORS = "regressors"
SHAPES = (SHAPE_CANDIDATES, SHAPE_REGRESSORS)


class Layout:
    """The law's vector (``phi``, ``delta``, the rows of H and P): the shape weights dw (``n_shape``), the
    level db, the scale factor s0 and its slope s1."""

    def __init__(self, n_shape: int) -> None:
        self.n_shape = n_shape
        self.shape = slice(0, n_shape)
        self.level, self.sf0, self.sf1 = n_shape, n_shape + 1, n_shape + 2
        self.size = n_shape + 3
        #: the rows that forget: the drift's (dw and db)
        self.drift = slice(0, n_shape + 1)
        #: the level and the scale factor: all the frozen shape learns
        self.own = slice(n_shape, n_shape + 3)

    def row(self, x: np.ndarray, t_eff_s: float, move_arcsec: float, t_int_c: float) -> np.ndarray:
        """``phi``: the shape regressors' sums x, T_eff, ``1e-6 m`` and ``1e-6 m (T_int - SF_REF_C)``."""
        phi = np.empty(self.size)
        phi[self.shape] = x
        phi[self.level] = t_eff_s
        phi[self.sf0] = 1e-6 * move_arcsec
        phi[self.sf1] = 1e-6 * move_arcsec * (t_int_c - SF_REF_C)
        return phi


class Prediction(NamedTuple):
    """One interval as an observation of the law (``MixtureLaw.predict``)."""

    phi: np.ndarray
    r_arcsec: float
    r_var: float
    t_eff_s: float
    move_deg: float
    off_deg: float
    degraded: bool
    warming_up: bool  # degraded by the warm-up alone (``AdaptConfig.warmup_s``)


class MixtureLaw:
    """The sums H and I, the evidence of each prior scale, the estimate delta and its covariance P (module
    docstring), with what they are weighed by: the regressors' gram, the block rates' white noise and the
    innovation calibration."""

    #: what learning an interval changes (``snapshot``)
    LEARNED = ("h", "i", "delta", "cov", "evidence", "calibration_sum", "calibration_n", "last_update_s")

    def __init__(self, n_shape: int, block_s: float, runaway_dph: float) -> None:
        self.layout = Layout(n_shape)
        self.block_s = float(block_s)
        self.runaway_dph = runaway_dph
        #: the frozen model's error scale over an interval: its fit residual (1-min RMS), as the runaway bound has it
        self.model_sigma_dph = runaway_dph / RUNAWAY_FIT_RESIDUALS
        self._gram_a = 1.0 - math.exp(-self.block_s / GRAM_MEMORY_S)
        self.reset()
        self.gram = np.zeros((n_shape + 1, n_shape + 1))
        self.gram_weight = 0.0
        self.noise_var_dph2 = math.nan  # the block rates' white noise variance (deg/h)^2
        self.noise_dwells = 0
        self.calibration_sum = 0.0
        self.calibration_n = 0.0
        self.last_update_s: float | None = None

    def reset(self) -> None:
        """The estimate back to the frozen weights, the sums and the evidence cleared."""
        n = self.layout.size
        self.h = np.zeros((n, n))
        self.i = np.zeros(n)
        self.delta = np.zeros(n)
        self.cov = np.zeros((n, n))
        #: each prior scale's cumulative log predictive likelihood of the intervals (forgetting as H does)
        self.evidence = np.zeros(len(PRIOR_SCALES))

    def snapshot(self) -> dict[str, Any]:
        """Copies of what learning an interval changes (``LEARNED``), to return to (``restore``)."""
        return {k: _copied(getattr(self, k)) for k in self.LEARNED}

    def restore(self, snapshot: dict[str, Any]) -> None:
        for k in self.LEARNED:
            setattr(self, k, _copied(snapshot[k]))  # a copy: a snapshot kept for a later undo stays as it was

    # -- what the intervals are weighed by -------------------------------------------------------

    def add_to_gram(self, g: np.ndarray) -> None:
        """A clean block's shape regressors into their gram (with a 1, for the mean), for the prior."""
        row = np.append(g, 1.0)
        self.gram_weight += self._gram_a * (1.0 - self.gram_weight)
        self.gram += self._gram_a * (np.outer(row, row) - self.gram)

    def add_noise(self, var_dph2: float) -> None:
        """A dwell's white noise variance of a block rate into the running mean, over ``CALIBRATION_INTERVALS``."""
        self.noise_dwells += 1
        old = 0.0 if math.isnan(self.noise_var_dph2) else self.noise_var_dph2
        self.noise_var_dph2 = old + (var_dph2 - old) / min(self.noise_dwells, CALIBRATION_INTERVALS)

    def calibration(self) -> float:
        """``c``, the running mean of the squared normalized innovations (module docstring)."""
        return (CALIBRATION_PRIOR + self.calibration_sum) / (CALIBRATION_PRIOR + self.calibration_n)

    def calibrate(self, z2: float) -> None:
        """One interval's squared normalized innovation into ``c``."""
        keep = 1.0 - 1.0 / CALIBRATION_INTERVALS
        self.calibration_sum = keep * self.calibration_sum + min(z2, CALIBRATION_CAP)
        self.calibration_n = keep * self.calibration_n + 1.0

    # -- an interval -----------------------------------------------------------------------------

    def predict(self, a: Anchor, bb: Anchor, columns: Columns, bias_dph: float | None) -> Prediction:
        """The interval from anchor ``a`` to ``bb`` as an observation (module docstring): its regressors ``phi``,
        the angle error left after the frozen drift and the bias (once captured), ``r = theta - m - F - bias
        T_eff`` in arcsec (m the table's move, its whole turns the gyro's), and its variance ``R``; no state
        changes."""
        lay = self.layout
        b = self.block_s
        d = columns.between(a.summary, bb.summary)
        t_eff = d.time_s
        x = d.shape
        t_int = d.temperature_c_s / t_eff
        theta = d.angle_arcsec
        move = bb.angle_arcsec - a.angle_arcsec
        predicted = d.frozen_arcsec
        bias = 0.0 if bias_dph is None else bias_dph
        adapted = float(np.dot(x, self.delta[lay.shape]) + t_eff * self.delta[lay.level])
        gyro_move = theta - bias * t_eff - predicted - adapted
        turns = round((gyro_move - move) / TURN_ARCSEC)
        move += turns * TURN_ARCSEC
        la, lb = a.window_blocks * b, bb.window_blocks * b
        gap = (bb.first_block - a.end_block) * b
        k2 = la / 3.0 + gap + lb / 3.0
        noise = self.noise_var_dph2 * b if math.isfinite(self.noise_var_dph2) else 0.0
        model = MODEL_NOISE_SHARE * self.model_sigma_dph * t_eff
        return Prediction(
            phi=lay.row(x, t_eff, move, t_int),
            r_arcsec=theta - move - predicted - bias * t_eff,
            r_var=noise * k2 + model * model,
            t_eff_s=t_eff,
            move_deg=move / ARCSEC_PER_DEG,
            off_deg=(gyro_move - move) / ARCSEC_PER_DEG,
            degraded=bool(d.degraded_blocks > 0.5),
            warming_up=bool(d.degraded_blocks - d.warmup_blocks < 0.5),
        )

    def innovation(self, p: Prediction) -> tuple[float, float]:
        """The interval's innovation against the estimate in use, ``e = r - phi . delta``, and its variance before
        the calibration, ``R + phi P phi^T``."""
        return p.r_arcsec - float(np.dot(p.phi, self.delta)), p.r_var + float(p.phi @ self.cov @ p.phi)

    def scale_factor_part(self, phi: np.ndarray) -> float:
        """The estimate's scale factor part of an interval, ``phi_s0 s0 + phi_s1 s1`` (arcsec)."""
        lay = self.layout
        part: float = phi[lay.sf0] * self.delta[lay.sf0] + phi[lay.sf1] * self.delta[lay.sf1]
        return part

    def learn(
        self, p: Prediction, candidates: list[tuple[np.ndarray, np.ndarray]], calibration: float, t_now_s: float
    ) -> None:
        """Interval ``p`` into the evidence (each scale's prediction of r from ``candidates``, made before
        learning it) and the sums, at device time ``t_now_s``; then the estimate anew.  ``LinAlgError``: the
        equations became singular."""
        lay = self.layout
        phi, r, r_var = p.phi, p.r_arcsec, p.r_var
        beta = 1.0 if self.last_update_s is None else math.exp(-max(t_now_s - self.last_update_s, 0.0) / TABLE_MEMORY_S)
        self.last_update_s = t_now_s
        weight = 1.0 / max(r_var, 1e-30)
        forget = np.ones(lay.size)  # the drift forgets, the scale factor (a constant of the coil) does not
        forget[lay.drift] = math.sqrt(beta)
        for k, (delta_k, cov_k) in enumerate(candidates):  # each scale's prediction of r, before learning it
            e_k = r - float(np.dot(phi, delta_k))
            v = (r_var + float(phi @ cov_k @ phi)) * calibration
            self.evidence[k] = beta * self.evidence[k] - 0.5 * (math.log(max(v, 1e-30)) + e_k * e_k / max(v, 1e-30))
        self.h *= np.outer(forget, forget)
        self.h += weight * np.outer(phi, phi)
        self.i *= forget
        self.i += (weight * r) * phi
        self.blend(self.candidates())

    def new_level(self) -> None:
        """The level db out of the sums, marginalized: with l its index, ``H <- H - H[:, l] H[l, :] / H[l, l]``,
        ``I <- I - H[:, l] I[l] / H[l, l]`` (row and column l then 0), so what the intervals said of the shape
        and the scale factor, whatever the level was, stays, and the level is learned afresh; then the estimate
        anew.  ``LinAlgError``: the equations became singular."""
        lvl = self.layout.level
        h_ll = float(self.h[lvl, lvl])
        if not h_ll > 0:
            return
        col = self.h[:, lvl].copy()
        self.i -= col * (self.i[lvl] / h_ll)
        self.h -= np.outer(col, col) / h_ll
        self.h[lvl, :] = 0.0
        self.h[:, lvl] = 0.0
        self.i[lvl] = 0.0
        self.blend(self.candidates())

    # -- the estimate ----------------------------------------------------------------------------

    def candidates(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """Each prior scale's estimate and covariance, ``(H + L0(s_D)) delta = I``; the scale 0 learns the level
        and the scale factor alone (the drift's shape stays the frozen one's: ``dw = 0``)."""
        lay = self.layout
        out = []
        for scale in PRIOR_SCALES:
            delta = np.zeros(lay.size)
            cov = np.zeros((lay.size, lay.size))
            if scale > 0:
                cov[:] = np.linalg.inv(self.h + self.prior(scale * self.runaway_dph))
                delta[:] = cov @ self.i
            else:
                own = lay.own  # L0's block of the level and the scale factor (dw = 0)
                cov[own, own] = np.linalg.inv(self.h[own, own] + self.prior(self.runaway_dph)[own, own])
                delta[own] = cov[own, own] @ self.i[own]
            out.append((delta, cov))
        return out

    def weights(self) -> np.ndarray:
        """The prior scales' posterior weights: their evidence, with the frozen drift's prior odds."""
        log_w = self.evidence.copy()
        log_w[[k for k, scale in enumerate(PRIOR_SCALES) if scale == 0]] += FROZEN_LOG_ODDS
        w = np.exp(log_w - log_w.max())
        return np.asarray(w / w.sum())

    def blend(self, candidates: list[tuple[np.ndarray, np.ndarray]]) -> None:
        """The estimate in use: the candidates' mean under their weights, and its covariance (the mixture's)."""
        w = self.weights()
        self.delta = sum(wk * d for wk, (d, _) in zip(w, candidates))
        self.cov = sum(wk * (c + np.outer(d - self.delta, d - self.delta)) for wk, (d, c) in zip(w, candidates))

    def prior(self, prior_dph: float) -> np.ndarray:
        """L0: the correction's variation over the blocks seen (``dw`` through the regressors' covariance C)
        within ``s_D``, its mean level (``m . dw + db``, m the regressors' mean) within the runaway bound (the
        table's angles see the level: only the runaway bound limits it), the scale factor within its priors."""
        lay = self.layout
        f_n = lay.n_shape
        out = np.zeros((lay.size, lay.size))
        if self.gram_weight > 0:
            g = self.gram / self.gram_weight
            mean = g[f_n, :f_n]
            cov = g[:f_n, :f_n] - np.outer(mean, mean)
        else:
            mean, cov = np.zeros(f_n), np.eye(f_n)
        ridge = 1e-6 * float(np.trace(cov)) / max(f_n, 1) + 1e-12
        level = 1.0 / self.runaway_dph**2
        out[lay.shape, lay.shape] = f_n * (cov + ridge * np.eye(f_n)) / prior_dph**2 + level * np.outer(mean, mean)
        out[lay.shape, lay.level] = out[lay.level, lay.shape] = level * mean
        out[lay.level, lay.level] = level
        out[lay.sf0, lay.sf0] = 1.0 / SF_PRIOR_PPM**2
        out[lay.sf1, lay.sf1] = 1.0 / SF_SLOPE_PRIOR_PPM_PER_C**2
        return out

    @property
    def frozen_weight(self) -> float:
        """The frozen drift's weight among the prior scales (1 before any interval is learned)."""
        if not self.h.any():
            return 1.0
        return float(sum(w for w, scale in zip(self.weights(), PRIOR_SCALES) if scale == 0))

    @property
    def scale_factor_ppm(self) -> tuple[float, float]:
        """The learned (s0 ppm, s1 ppm/degC)."""
        return float(self.delta[self.layout.sf0]), float(self.delta[self.layout.sf1])


def _copied(value: Any) -> Any:
    """An array copied (the law updates its arrays in place), anything else as it is."""
    return np.copy(value) if isinstance(value, np.ndarray) else value
