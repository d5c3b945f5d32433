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

Thermometer faults (a NaN block mean: no valid reading in the block; or an implausible one) are
detected per block and per sensor, and degrade the inputs gracefully:

- **plausible**: a reading is accepted when it lies in ``blocks.PLAUSIBLE_TEMP_C`` (a saturated 127.99 degC
  is not; the block averager has left such samples out already), with all three in that range lies
  within ``max_spread_c`` of their median (cross-sensor), and moves less than ``max_rate_c_per_s * Ts``
  from the sensor's value of the block before (a faulted one: from its own previous reading, or from
  its substitute);
- **substituted**: a faulted sensor is predicted from the healthy ones (``Substitution``): from both
  partners when both are healthy, else from one (T1: T2, T3; T2: T1, T3; T3: T1, T2)::

      T_k = sum_j a_kj T_j + sum_j b_kj dT_j/dt + c_k        c_k: T_k - prediction, tracked while healthy

  (``c_k`` smoothed with ``rate_tau_fast_s``, so the substitute continues from the last reading).  The
  coefficients are fitted on the model's own fit data (``fit_substitution``: the thermal coupling
  between the sensors, whose gradients change during a ramp); without them (``Substitution.offsets``)
  a sensor is its partner plus their last offset.  Its rate and gradients keep tracking the ramp; the
  block is flagged ``FLAG_SUBSTITUTED``;
- **stuck**: a reading that has not moved by ``stuck_tol_c`` since every healthy partner moved by more than
  ``stuck_partner_c`` is stuck (a frozen converter or bus returning its last value: in range, no jump,
  near the others, so the checks above pass it).  From that block on it is faulted and substituted; its
  offsets are those it had when it last moved (the ones tracked since followed the stuck value), its
  rate smoothers are re-seated on the substitute's ramp (``value - L_k rate``: the rate continues
  without a step), and the next ``RECOVERY_TAUS * rate_tau_slow_s`` are flagged ``FLAG_RECOVERING``
  (the model ran on the stuck value until it was caught).  It is taken back only once its reading
  moves again, then as any faulted sensor.  A healthy sensor's reading moves with its partners (a
  coupling of 1/200 would be needed to stay within 0.01 degC while they move 2 degC), and with none
  moving nothing is decided: a stuck sensor is caught once its partners have moved ``stuck_partner_c``
  (a minute into a 2 degC/min ramp), and the estimates until then used it;
- **frozen**: with no healthy partner (all three faulted) the last value and the rate smoothers are
  held; after ``hold_s`` the block is flagged ``FLAG_INPUT_STALE`` (the compensator then holds
  its estimate);
- **recovery**: a faulted sensor is accepted again at once when its reading agrees with the value
  in use (within the step limit), else after ``recover_s`` of plausible, self-consistent readings;
  then both rate smoothers are shifted by the step (no rate spike from it), and when it had to wait
  the next ``RECOVERY_TAUS * rate_tau_slow_s`` are flagged ``FLAG_RECOVERING`` (the model
  settles to the corrected temperature).

Before any valid value of a sensor (and with no partner to substitute from), its inputs are NaN
and the block is flagged ``FLAG_INPUT_STALE``.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from ..flags import FLAG_INPUT_STALE, FLAG_RECOVERING, FLAG_SUBSTITUTED
from . import numerics
from .blocks import plausible_temp
from .fitting.ridge import standardized_ridge

#: Protocol v1's thermometers, in the order they fill a sample's three temperature places.
V1_CHANNELS = ("top", "bottom", "housing")


def input_names(channels: tuple[str, ...] = V1_CHANNELS) -> tuple[str, ...]:
    """The inputs made from a format's temperature channels (one to three, in their places' order)::

        u = [T_1 .. T_n, dT_1/dt .. dT_n/dt, T_1 - T_2 .. T_1 - T_n]

    three channels (protocol v1, STDBIN): the 8 inputs above; one channel (KVH): ``[T, dT/dt]``."""
    if not 1 <= len(channels) <= 3:
        raise ValueError(f"a model needs 1 to 3 temperature channels, not {len(channels)}")
    return (
        tuple(f"t_{c}_c" for c in channels)
        + tuple(f"rate_{c}_c_per_min" for c in channels)
        + tuple(f"grad_{channels[0]}_{c}_c" for c in channels[1:])
    )


def input_columns(n_channels: int) -> list[int]:
    """Where ``input_names`` of ``n_channels`` channels sit in the three-channel vector of 8."""
    return list(range(n_channels)) + [3 + k for k in range(n_channels)] + [5 + k for k in range(1, n_channels)]


def channels_of(n_inputs: int) -> int:
    """How many temperature channels an input vector of ``n_inputs`` comes from (8: 3, 5: 2, 2: 1)."""
    for n in (3, 2, 1):
        if n_inputs == 3 * n - 1:
            return n
    raise ValueError(f"{n_inputs} inputs come from no number of temperature channels (8, 5 or 2 inputs)")


def ring_of(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The ring's temperature and rate from rows of inputs (raw or standardized): the mean of the first two
    channels (protocol v1: the fiber ring's top and bottom), or the one channel a one-channel format has."""
    u = np.asarray(u)
    n = channels_of(u.shape[-1])
    if n == 1:
        return u[..., 0], u[..., 1]
    return 0.5 * (u[..., 0] + u[..., 1]), 0.5 * (u[..., n] + u[..., n + 1])


INPUT_NAMES = input_names()
N_INPUTS = len(INPUT_NAMES)
#: The flags of a degraded input (frozen, substituted, or settling after a fault): carried by the estimate,
#: never fitted or learned from.
DEGRADED_FLAGS = FLAG_INPUT_STALE | FLAG_SUBSTITUTED | FLAG_RECOVERING
#: The recovery flag lasts this many slow rate-smoother time constants.
RECOVERY_TAUS = 3.0
#: Substitution partner sets per sensor, in order of preference: both others, then the ring's other half first.
PARTNER_SETS = (((1, 2), (1,), (2,)), ((0, 2), (0,), (2,)), ((0, 1), (0,), (1,)))
SENSOR_NAMES = INPUT_NAMES[:3]


@dataclass(frozen=True)
class Substitution:
    """How a faulted thermometer is predicted from healthy ones: per sensor k and partner set S
    (``PARTNER_SETS[k]``), the coefficients ``[a_j for j in S] + [b_j for j in S]`` of
    ``T_k = sum a_j T_j + sum b_j dT_j/dt + c_k`` (degC, degC/min), or None (not used)."""

    coefficients: tuple[tuple[tuple[float, ...] | None, ...], ...]

    @classmethod
    def offsets(cls) -> Substitution:
        """No fitted coupling: a sensor is its partner plus their last offset."""
        return cls(tuple((None, (1.0, 0.0), (1.0, 0.0)) for _ in range(3)))

    def to_dict(self) -> dict:
        return {
            SENSOR_NAMES[k]: {
                "+".join(SENSOR_NAMES[j] for j in partners): None if c is None else list(c)
                for partners, c in zip(PARTNER_SETS[k], self.coefficients[k])
            }
            for k in range(3)
        }

    @classmethod
    def from_dict(cls, doc: dict) -> Substitution:
        if not isinstance(doc, dict) or set(doc) != set(SENSOR_NAMES):
            raise ValueError(f"substitution needs the keys {', '.join(SENSOR_NAMES)}")
        rows = []
        for k, name in enumerate(SENSOR_NAMES):
            entry = doc[name]
            keys = ["+".join(SENSOR_NAMES[j] for j in partners) for partners in PARTNER_SETS[k]]
            if not isinstance(entry, dict) or set(entry) != set(keys):
                raise ValueError(f"substitution of {name} needs the keys {', '.join(keys)}")
            row = []
            for key, partners in zip(keys, PARTNER_SETS[k]):
                c = entry[key]
                if c is not None:
                    c = tuple(float(v) for v in c)
                    if len(c) != 2 * len(partners) or not all(math.isfinite(v) for v in c):
                        raise ValueError(f"substitution of {name} from {key}: {2 * len(partners)} finite numbers")
                row.append(c)
            rows.append(tuple(row))
        return cls(tuple(rows))


#: The coupling fit's ridge penalty per row, on standardized columns: only enough to keep a column that
#: never moved (a run without ramps: rates near 0) from taking an absurd weight.
RIDGE_ALPHA = 1e-6


def fit_substitution(
    inputs: list[np.ndarray], usable: list[np.ndarray], block_s: float, chunk_s: float = 1200.0
) -> Substitution:
    """Fit ``Substitution`` on captures' inputs (rows of the 8 inputs; ``usable``: all three measured).

    Per sensor and partner set, least squares of T_k on the partners' temperatures and rates with one
    intercept per capture (the intercept is ``c_k``, tracked in operation).  A fitted row is kept only
    where it beats the plain offset (a single partner, coefficients 1, 0) on interleaved held-out chunks
    of ``chunk_s``: the RMS of the residual within each held-out chunk, its chunk mean removed (what a
    substitute drifts off over a fault of that length).  A pair is kept only where it beats the better
    single.  Returns ``Substitution.offsets()`` where the data are too few (under 4 chunks)."""
    if any(u.shape[1] != N_INPUTS for u in inputs):  # fewer than three channels: none to predict from
        return Substitution.offsets()
    chunk = max(1, int(round(chunk_s / block_s)))
    rows = [(u[m], np.arange(len(u))[m] // chunk, i) for i, (u, m) in enumerate(zip(inputs, usable))]
    u = np.vstack([r[0] for r in rows]) if rows else np.empty((0, N_INPUTS))
    if len(u) < 4 * chunk:
        return Substitution.offsets()
    chunk_id = np.concatenate([r[1] + 100_000 * r[2] for r in rows])
    capture = np.concatenate([np.full(len(r[0]), r[2]) for r in rows])
    held_out = np.concatenate([r[1] % 2 == 1 for r in rows])

    def design(partners: tuple[int, ...]) -> np.ndarray:
        return u[:, [*partners, *(3 + j for j in partners)]]

    def solve(x: np.ndarray, y: np.ndarray, mask: np.ndarray) -> np.ndarray:
        return standardized_ridge(x[mask], y[mask], RIDGE_ALPHA, groups=capture[mask])[0]

    def held_out_rms(x: np.ndarray, y: np.ndarray, coef: np.ndarray) -> float:
        residual = (y - x @ coef)[held_out]
        _, chunk_of = np.unique(chunk_id[held_out], return_inverse=True)
        residual -= (np.bincount(chunk_of, weights=residual) / np.bincount(chunk_of))[chunk_of]
        return float(np.sqrt(np.mean(residual**2)))

    result = []
    for k in range(3):
        y = u[:, k]
        chosen: list[tuple[float, ...] | None] = []
        scores = []
        for partners in PARTNER_SETS[k]:
            x = design(partners)
            score = held_out_rms(x, y, solve(x, y, ~held_out))
            coef = tuple(float(v) for v in solve(x, y, np.ones(len(y), dtype=bool)))
            if len(partners) == 1:
                plain_score = held_out_rms(x, y, np.array([1.0, 0.0]))
                if not score < plain_score:
                    coef, score = (1.0, 0.0), plain_score
            chosen.append(coef)
            scores.append(score)
        if not scores[0] < min(scores[1:]):
            chosen[0] = None
        result.append(tuple(chosen))
    return Substitution(tuple(result))


@dataclass(frozen=True)
class FeatureParams:
    sample_time_s: float = 1.0
    rate_tau_fast_s: float = 30.0
    rate_tau_slow_s: float = 90.0
    hold_s: float = 30.0
    max_rate_c_per_s: float = 0.5
    max_spread_c: float = 50.0
    recover_s: float = 10.0
    stuck_tol_c: float = 0.01
    stuck_partner_c: float = 2.0

    def __post_init__(self) -> None:
        if not 0 < self.rate_tau_fast_s < self.rate_tau_slow_s:
            raise ValueError("need 0 < rate_tau_fast_s < rate_tau_slow_s")
        if not self.sample_time_s > 0 or self.hold_s < 0:
            raise ValueError("sample_time_s must be > 0 and hold_s >= 0")
        if not (self.max_rate_c_per_s > 0 and self.max_spread_c > 0 and self.recover_s >= 0):
            raise ValueError("max_rate_c_per_s and max_spread_c must be > 0 and recover_s >= 0")
        if not (0 <= self.stuck_tol_c < self.stuck_partner_c):
            raise ValueError("need 0 <= stuck_tol_c < stuck_partner_c")


class FeatureExtractor:
    """Block temperatures -> the inputs (``input_names`` of the first ``n_channels`` temperature places; 8 for
    three), with explicit state (smoothers, last valid values)."""

    def __init__(
        self,
        params: FeatureParams | None = None,
        state: dict | None = None,
        substitution: Substitution | None = None,
        n_channels: int = 3,
    ) -> None:
        if n_channels not in (1, 2, 3):
            raise ValueError(f"n_channels must be 1, 2 or 3, not {n_channels!r}")
        self.n_channels = n_channels
        #: the temperature places in use (a format with fewer channels leaves the others out entirely: they
        #: are never faulted, substituted or flagged, and never a partner)
        self._present = [k < n_channels for k in range(3)]
        self._columns = input_columns(n_channels)
        self.params = params or FeatureParams()
        self.substitution = substitution or Substitution.offsets()
        p = self.params
        # Correctly rounded exponentials: the same coefficients on every machine (the C library's are not).
        self._a1 = 1.0 - numerics.exp_correctly_rounded(-p.sample_time_s / p.rate_tau_fast_s)
        self._a2 = 1.0 - numerics.exp_correctly_rounded(-p.sample_time_s / p.rate_tau_slow_s)
        # A discrete EMA lags a ramp of slope r by r * lag, lag = Ts / (exp(Ts / tau) - 1) (-> tau as Ts -> 0).
        lag_fast = p.sample_time_s / numerics.expm1_correctly_rounded(p.sample_time_s / p.rate_tau_fast_s)
        lag_slow = p.sample_time_s / numerics.expm1_correctly_rounded(p.sample_time_s / p.rate_tau_slow_s)
        self._lag_fast_s, self._lag_slow_s = lag_fast, lag_slow
        self._denominator_min = (lag_slow - lag_fast) / 60.0
        self.reset()
        if state is not None:
            self.set_state(state)

    def reset(self) -> None:
        self._last = [math.nan] * 3  # the value in use per sensor (a reading, a substitute, or frozen)
        self._stale_s = [0.0] * 3  # how long each sensor's value has been frozen
        self._m1 = [math.nan] * 3
        self._m2 = [math.nan] * 3
        self._faulted = [False] * 3
        self._raw_prev = [math.nan] * 3  # a faulted sensor's previous in-range reading
        self._good_s = [0.0] * 3  # how long a faulted sensor has read plausibly
        self._offset = [math.nan] * 9  # per sensor and partner set: smoothed T_k - prediction while all healthy
        self._recovering_s = 0.0
        self._anchor = [math.nan] * 9  # per sensor k: the three values in use when k's reading last moved
        self._anchor_offset = [math.nan] * 9  # per sensor k: its three offsets then
        self._stuck_at = [math.nan] * 3  # a sensor caught stuck: the reading it is stuck at

    def get_state(self) -> dict:
        return {
            "last": list(self._last),
            "stale_s": list(self._stale_s),
            "m1": list(self._m1),
            "m2": list(self._m2),
            "faulted": list(self._faulted),
            "raw_prev": list(self._raw_prev),
            "good_s": list(self._good_s),
            "offset": list(self._offset),
            "recovering_s": self._recovering_s,
            "anchor": list(self._anchor),
            "anchor_offset": list(self._anchor_offset),
            "stuck_at": list(self._stuck_at),
        }

    def set_state(self, state: dict) -> None:
        """Inverse of ``get_state``; a state saved before fault handling (no ``faulted`` ...) means healthy, one
        saved before the stuck check (no ``anchor`` ...) starts it afresh."""
        values: dict[str, list[Any]] = {k: [float(v) for v in state[k]] for k in ("last", "stale_s", "m1", "m2")}
        values["faulted"] = [bool(v) for v in state.get("faulted", [False] * 3)]
        for k, default in (("raw_prev", math.nan), ("good_s", 0.0)):
            values[k] = [float(v) for v in state.get(k, [default] * 3)]
        offset = [float(v) for v in state.get("offset", [math.nan] * 9)]
        anchor = [float(v) for v in state.get("anchor", [math.nan] * 9)]
        anchor_offset = [float(v) for v in state.get("anchor_offset", [math.nan] * 9)]
        stuck_at = [float(v) for v in state.get("stuck_at", [math.nan] * 3)]
        if (
            any(len(v) != 3 for v in values.values())
            or len(stuck_at) != 3
            or {len(offset), len(anchor), len(anchor_offset)} != {9}
        ):
            raise ValueError("feature state: 3 values per sensor (9 offsets and anchors)")
        values["offset"] = offset
        recovering_s = float(state.get("recovering_s", 0.0))
        self._last, self._stale_s, self._m1, self._m2 = values["last"], values["stale_s"], values["m1"], values["m2"]
        self._faulted, self._raw_prev, self._good_s = values["faulted"], values["raw_prev"], values["good_s"]
        self._offset, self._recovering_s = values["offset"], recovering_s
        self._anchor, self._anchor_offset, self._stuck_at = anchor, anchor_offset, stuck_at

    def step(self, temps_c: tuple[float, ...] | np.ndarray) -> tuple[list[float], int]:
        """The input vector for one block and its flags (``FLAG_SUBSTITUTED``, ``FLAG_RECOVERING``,
        ``FLAG_INPUT_STALE``, or 0)."""
        p = self.params
        ts = p.sample_time_s
        step_limit = p.max_rate_c_per_s * ts
        raw = [float(temps_c[k]) for k in range(3)]
        # 1. Plausible readings: in range and, with three in range, within max_spread_c of their median
        #    (``level``); and no jump (``ok``): against the value in use, a faulted sensor against its previous
        #    reading (or, in step 3, against its predicted value).
        level = [plausible_temp(v) for v in raw]  # NaN: False
        if all(level):
            median = sorted(raw)[1]
            level = [abs(v - median) <= p.max_spread_c for v in raw]
        ok = [False] * 3
        for k in range(3):
            if level[k]:
                ref = self._raw_prev[k] if self._faulted[k] else self._last[k]
                ok[k] = not abs(raw[k] - ref) > step_limit  # no reference (NaN): accepted
        # 2. Healthy sensors with a plausible reading use it; a healthy one without becomes faulted.
        flags = 0
        healthy = [False] * 3
        t = [math.nan] * 3
        rates = [math.nan] * 3
        for k in range(3):
            if self._faulted[k] or not self._present[k]:
                continue
            if ok[k]:
                healthy[k] = True
                t[k], rates[k] = self._smooth(k, raw[k])
            else:
                self._faulted[k] = True  # step 3 handles it from this block on
        caught = self._check_stuck(raw, healthy, t)
        # 3. Faulted ones: the value in use is predicted from healthy partners, else frozen (value and rate
        #    held).  A plausible reading that agrees with it, or after recover_s of plausible readings, is
        #    accepted again: the smoothers shift by the step, so it causes no rate spike.
        for k in range(3):
            if healthy[k] or not self._present[k]:
                continue
            value = raw[k]
            (in_use, rate_in_use), substituted = self._substitute(k, healthy, t, rates), True
            if in_use != in_use:
                in_use, substituted = self._last[k], False
            ok[k] = ok[k] or level[k] and abs(value - in_use) <= step_limit
            if self._stuck_at[k] == self._stuck_at[k]:  # caught stuck: usable again only once it moves
                if abs(value - self._stuck_at[k]) <= p.stuck_tol_c:
                    ok[k] = False
                else:
                    self._stuck_at[k] = math.nan
            self._good_s[k] = self._good_s[k] + ts if ok[k] else 0.0  # consecutive plausible readings
            self._raw_prev[k] = value if plausible_temp(value) else math.nan
            if ok[k]:
                agrees = in_use != in_use or abs(value - in_use) <= step_limit
                if agrees or self._good_s[k] >= p.recover_s:
                    self._faulted[k] = False
                    if self._m1[k] == self._m1[k] and in_use == in_use:
                        self._m1[k] += value - in_use
                        self._m2[k] += value - in_use
                    if not agrees:
                        self._recovering_s = RECOVERY_TAUS * p.rate_tau_slow_s
                    t[k], rates[k] = self._smooth(k, value)
                    healthy[k] = True
                    continue
            if substituted:
                flags |= FLAG_SUBSTITUTED
                t[k], rates[k] = self._reseat(k, in_use, rate_in_use) if caught[k] else self._smooth(k, in_use)
                continue
            self._stale_s[k] += ts
            if self._stale_s[k] > p.hold_s or in_use != in_use:
                flags |= FLAG_INPUT_STALE
            if in_use == in_use:
                t[k] = in_use
                rates[k] = (self._m1[k] - self._m2[k]) / self._denominator_min
        # 4. The offsets of each prediction while the sensor and its partners are all healthy.
        for k in range(3):
            if not healthy[k]:
                continue
            for s_index, (partners, coef) in enumerate(zip(PARTNER_SETS[k], self.substitution.coefficients[k])):
                if coef is None or not all(healthy[j] for j in partners):
                    continue
                difference = t[k] - self._predict(partners, coef, t, rates)
                i = 3 * k + s_index
                self._offset[i] = (
                    difference
                    if self._offset[i] != self._offset[i]
                    else (self._offset[i] + self._a1 * (difference - self._offset[i]))
                )
        if self._recovering_s > 0:
            flags |= FLAG_RECOVERING
            self._recovering_s = max(0.0, self._recovering_s - ts)
        full = [t[0], t[1], t[2], rates[0], rates[1], rates[2], t[0] - t[1], t[0] - t[2]]
        return (full if self.n_channels == 3 else [full[i] for i in self._columns]), flags

    def adopt_state(self, state: dict, substitution: Substitution) -> dict:
        """``state`` of an extractor that predicted sensors by ``substitution``, for this one: the offsets of
        the predictions this one makes differently are dropped (tracked afresh while the sensor is healthy)."""
        offset = list(state.get("offset", [math.nan] * 9))
        anchor_offset = list(state.get("anchor_offset", [math.nan] * 9))
        for k in range(3):
            for s_index in range(3):
                if substitution.coefficients[k][s_index] != self.substitution.coefficients[k][s_index]:
                    offset[3 * k + s_index] = anchor_offset[3 * k + s_index] = math.nan
        return {**state, "offset": offset, "anchor_offset": anchor_offset}

    def _substitute(self, k: int, healthy: list[bool], t: list[float], rates: list[float]) -> tuple[float, float]:
        """Sensor k predicted from the first partner set that is all healthy, and the rate that prediction
        ramps at (``sum a_j dT_j/dt``); NaN, NaN: none, or no offset yet."""
        for s_index, (partners, coef) in enumerate(zip(PARTNER_SETS[k], self.substitution.coefficients[k])):
            offset = self._offset[3 * k + s_index]
            if coef is not None and offset == offset and all(healthy[j] for j in partners):
                rate = sum(coef[i] * rates[j] for i, j in enumerate(partners))
                return self._predict(partners, coef, t, rates) + offset, rate
        return math.nan, math.nan

    def _check_stuck(self, raw: list[float], healthy: list[bool], t: list[float]) -> list[bool]:
        """Which healthy sensors are caught stuck in this block (see the module docstring); those are made
        faulted (``healthy`` updated), their offsets put back to those they had when they last moved."""
        p = self.params
        caught = [False] * 3
        for k in range(3):
            if not healthy[k]:
                continue
            anchor = self._anchor[3 * k : 3 * k + 3]
            if not abs(raw[k] - anchor[k]) <= p.stuck_tol_c:  # it moved (or has no anchor yet): anchor here
                self._anchor[3 * k : 3 * k + 3] = [t[j] if healthy[j] else math.nan for j in range(3)]
                self._anchor_offset[3 * k : 3 * k + 3] = self._offset[3 * k : 3 * k + 3]
                continue
            moved = []
            for j in range(3):
                if j != k and healthy[j]:
                    if anchor[j] != anchor[j]:  # a partner healthy again: counted from here
                        self._anchor[3 * k + j] = t[j]
                    moved.append(abs(t[j] - anchor[j]))
            if moved and min(moved) > p.stuck_partner_c:
                caught[k], healthy[k], self._faulted[k] = True, False, True
                self._stuck_at[k], self._raw_prev[k], self._good_s[k] = raw[k], raw[k], 0.0
                self._offset[3 * k : 3 * k + 3] = self._anchor_offset[3 * k : 3 * k + 3]
                self._anchor[3 * k : 3 * k + 3] = [math.nan] * 3
                self._recovering_s = RECOVERY_TAUS * p.rate_tau_slow_s
        return caught

    def _reseat(self, k: int, value: float, rate_c_per_min: float) -> tuple[float, float]:
        """Sensor k's smoothers put where they would be on a ramp through ``value`` at ``rate_c_per_min``
        (``m_i = value - L_i rate``): the rate it returns is that ramp's, with no step."""
        self._stale_s[k] = 0.0
        self._last[k] = value
        slope_c_per_s = rate_c_per_min / 60.0
        self._m1[k] = value - self._lag_fast_s * slope_c_per_s
        self._m2[k] = value - self._lag_slow_s * slope_c_per_s
        return value, (self._m1[k] - self._m2[k]) / self._denominator_min

    def _smooth(self, k: int, value: float) -> tuple[float, float]:
        """Sensor k's value through its two smoothers: (value, rate in degC/min)."""
        self._stale_s[k] = 0.0
        self._last[k] = value
        if self._m1[k] != self._m1[k]:
            self._m1[k] = self._m2[k] = value
        self._m1[k] += self._a1 * (value - self._m1[k])
        self._m2[k] += self._a2 * (value - self._m2[k])
        return value, (self._m1[k] - self._m2[k]) / self._denominator_min

    @staticmethod
    def _predict(partners: tuple[int, ...], coef: tuple[float, ...], t: list[float], rates: list[float]) -> float:
        """``sum a_j T_j + sum b_j dT_j/dt`` over the partners (no offset)."""
        n = len(partners)
        return sum(coef[i] * t[j] + coef[n + i] * rates[j] for i, j in enumerate(partners))

    def run(self, temps_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``step`` over blocks: (n, inputs) inputs and (n,) flags, bit-identical."""
        out = np.empty((len(temps_c), len(self._columns)))
        flags = np.zeros(len(temps_c), dtype=np.int64)
        for i, row in enumerate(np.asarray(temps_c, dtype=np.float64).tolist()):
            out[i], flags[i] = self.step(row)
        return out, flags


def params_to_dict(params: FeatureParams) -> dict:
    return asdict(params)
