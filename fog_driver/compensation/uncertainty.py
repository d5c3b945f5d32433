"""The drift estimate's uncertainty, ``drift_sigma_dph``: the 1-sigma of the error of the estimate as a
1-min mean, about the error's mean over the run (that mean is the bias, which a zero window removes).

**Calibrated by the fit on its own data** (``calibration``: ``SigmaCalibration``, made by
``fitting.sigma_calibration`` from contiguous stretches of the fit run the model was refitted without)::

    sigma^2 = k^2 (c_0 + c_s s^2 + c_r rdot^2 + c_c (1 - p)^2 + c_w p^2 + c_d d^2) + (k_b d R)^2

    s       the candidates' spread (below); rdot the ring temperature's rate, degC/min (the inputs' own,
            unclamped); p = clip((T_ring - T_lo) / (T_hi - T_lo), 0, 1) where the ring temperature sits in
            the fit data's range T_lo..T_hi (1 - p: towards the cold end, p: towards the warm end); d the
            distance from the fit box (below: in the calibration, from the box of the data it was refitted on)
    c_j     >= 0: c_0 = c_b r^2 and c_s = c_b, the model's validation residual r and the candidates'
            spread in the model's own proportion, sized by the held-out stretches; c_r, c_c, c_w the
            weights of the features the held-out stretches showed to predict the error's size (a feature
            that did not gets 0); c_d 0 (files may carry one); k the scale that makes the band cover 95 %
            of the held-out minutes with the box term beside it; (k_b d R)^2 today's box term below, kept as
            a floor: how far an estimate may err outside everything the fit saw is more than a few held-out
            stretches can show

**Today's rule without a calibration** (a model file made before it, or a fit whose data were too few to
calibrate on, ``calibration.method: none``, which uses ``FALLBACK_SCALE`` on the first two parts):
three parts, each scaled by a factor set on simulated instruments (``SPREAD_SCALE``, ``RESIDUAL_SCALE``,
``BOX_SCALE``; the model file keeps the factors it was made with)::

    sigma^2 = (k_s s)^2 + (k_r r)^2 + (k_b d R)^2

    s = sqrt(mean_c (D_c - D_hat)^2)     the spread of the candidate structures about the estimate: the
                                         coils that explain the fit data within the noise of the chosen one
                                         (``fitting.wesn.tied_coils``), each run on the same inputs; they
                                         agree where the data decided and part where it did not (ramps
                                         faster than the fit's)
    r                                    the model's error on data it was not fitted on: the validation
                                         residual in 1-min means with the white noise taken out,
                                         sqrt(max(v^2 - n^2, 0)) (``fitting.fit``)
    d = max_k max(0, lo_k - u_k, u_k - hi_k) / (hi_k - lo_k)
                                         the distance of the temperatures from the fit box, in spans of it
    R                                    the range of the fit target's 1-min means (the drift the fit saw)

While adapting, an estimate of the adapted weights takes its sigma from the law's own innovation
statistics instead (``adapt.OnlineReadout.adapted_sigma_dph``), with the box term beside it.

A model file without candidates (a polynomial, an older file) has ``sigma_kind: residual``: s = 0, the
other two parts only, and a warning when it loads.  The candidates step once a block, on the inputs the
model sees (clamped to the box), from rest at the same first input: ``step`` and ``run`` of the
compensator see the same values, and so does a capture replayed offline.  The compensator's ``run``
collects their steps during its block loop and takes them afterwards in runs of blocks (``defer``,
``resolve``: each candidate's ``run``, bit-identical to its steps), so offline compensation pays the
per-call overhead once per run of blocks rather than once per block and candidate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .domain import ESTIMATE_LIMIT_FACTOR, InputDomain
from .features import channels_of

#: The calibrated factors (module docstring): one common factor on the spread and the residual, the box's 1
#: (``benchmarks/calibrate_sigma.py``; docs/decisions/2026-12-07-uncertainty-factors.md).  A model file keeps
#: the factors it was made with.
SPREAD_SCALE = 0.85
RESIDUAL_SCALE = 0.85
BOX_SCALE = 1.0

SIGMA_KINDS = ("candidates", "residual")

#: The features a calibrated sigma weighs, in this order (module docstring): each enters squared.
SIGMA_FEATURES = ("constant", "spread", "rate", "cold", "warm", "box")
#: ``calibration.method``: calibrated on held-out stretches, or not (too few: the fall-back rule).
CALIBRATION_METHODS = ("held-out-stretches", "none")
#: The fall-back's factor on the spread and the residual when a fit could not calibrate its sigma: the
#: population's rule without its 0.85 shrink, wider than it (conservative).
FALLBACK_SCALE = 1.0


@dataclass(frozen=True)
class SigmaCalibration:
    """The model file's ``uncertainty.calibration``: how the fit calibrated ``drift_sigma_dph`` on its own
    held-out stretches (module docstring), or why it could not (``method: none``, ``reason``)."""

    method: str
    weights: tuple[float, ...] = (0.0,) * len(SIGMA_FEATURES)  #: c_j, in the order of ``SIGMA_FEATURES``
    scale: float = 1.0  #: k
    ring_low_c: float = 0.0  #: T_lo
    ring_high_c: float = 0.0  #: T_hi
    stretches: int = 0  #: held-out stretches it was calibrated on
    stretch_min: float = 0.0
    reason: str = ""  #: with ``method: none``: why

    def __post_init__(self) -> None:
        if self.method not in CALIBRATION_METHODS:
            raise ValueError(f"uncertainty.calibration: method must be one of {', '.join(CALIBRATION_METHODS)}")
        values = (*self.weights, self.scale, self.ring_low_c, self.ring_high_c, self.stretch_min)
        if len(self.weights) != len(SIGMA_FEATURES) or not all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in values
        ):
            raise ValueError(
                f"uncertainty.calibration: {len(SIGMA_FEATURES)} finite weights, a finite scale and ring range"
            )
        if min(self.weights) < 0 or self.scale < 0 or self.ring_high_c < self.ring_low_c:
            raise ValueError("uncertainty.calibration: weights and scale must be >= 0, ring_c low <= high")
        if self.method == "held-out-stretches" and not self.weights[0] > 0:
            raise ValueError("uncertainty.calibration: a calibrated sigma needs a constant weight > 0")
        object.__setattr__(self, "weights", tuple(float(v) for v in self.weights))

    @property
    def calibrated(self) -> bool:
        return self.method == "held-out-stretches"

    def to_dict(self) -> dict[str, Any]:
        if not self.calibrated:
            return {"method": self.method, "reason": self.reason}
        return {
            "method": self.method,
            "weights": {name: float(w) for name, w in zip(SIGMA_FEATURES, self.weights)},
            "scale": float(self.scale),
            "ring_c": [float(self.ring_low_c), float(self.ring_high_c)],
            "stretches": int(self.stretches),
            "stretch_min": float(self.stretch_min),
        }

    @classmethod
    def from_dict(cls, doc: Any) -> SigmaCalibration:
        if not isinstance(doc, dict):
            raise ValueError("uncertainty.calibration must be a mapping")
        method = doc.get("method")
        if method == "none":
            unknown = set(doc) - {"method", "reason"}
            if unknown:
                raise ValueError(f"uncertainty.calibration: unknown keys {', '.join(sorted(map(str, unknown)))}")
            return cls("none", reason=str(doc.get("reason", "")))
        known = {"method", "weights", "scale", "ring_c", "stretches", "stretch_min"}
        unknown = set(doc) - known
        if unknown:
            raise ValueError(f"uncertainty.calibration: unknown keys {', '.join(sorted(map(str, unknown)))}")
        weights, ring = doc.get("weights"), doc.get("ring_c")
        if not isinstance(weights, dict) or set(weights) - set(SIGMA_FEATURES):
            raise ValueError(f"uncertainty.calibration.weights: a mapping of {', '.join(SIGMA_FEATURES)}")
        if not isinstance(ring, list) or len(ring) != 2:
            raise ValueError("uncertainty.calibration.ring_c: [low, high]")
        stretches = doc.get("stretches", 0)
        if isinstance(stretches, bool) or not isinstance(stretches, int) or stretches < 0:
            raise ValueError("uncertainty.calibration.stretches: an integer >= 0")
        return cls(
            str(method),
            tuple(weights.get(name, 0.0) for name in SIGMA_FEATURES),
            doc.get("scale", 1.0),
            ring[0],
            ring[1],
            stretches,
            doc.get("stretch_min", 0.0),
        )

    def features(self, spread_sq: Any, ring_c: Any, ring_rate_c_per_min: Any, box: Any) -> np.ndarray:
        """The squared features (``SIGMA_FEATURES``, last axis) of rows of (s^2, T_ring, rdot, d): what the
        weights multiply; the fit's calibration and ``sigma_of`` use the same numbers."""
        p = _position(ring_c, self.ring_low_c, self.ring_high_c)
        rate = np.asarray(ring_rate_c_per_min, dtype=np.float64)
        d = np.asarray(box, dtype=np.float64) + 0.0 * p
        q = 1.0 - p
        return np.stack(
            [np.ones_like(p), np.asarray(spread_sq, dtype=np.float64) + 0.0 * p, rate * rate, q * q, p * p, d * d],
            axis=-1,
        )


def _position(ring_c: Any, low_c: float, high_c: float) -> np.ndarray:
    """p of the module docstring: where the ring temperature sits in the fit's range, clipped to 0..1 (0.5 for a
    range of width 0)."""
    t = np.asarray(ring_c, dtype=np.float64)
    span = high_c - low_c
    if not span > 0:
        return np.full(t.shape, 0.5)
    return np.clip((t - low_c) / span, 0.0, 1.0)


def _calibrated_variance(w: Any, spread_sq: Any, rate: Any, p: Any, d: Any) -> Any:
    """The calibrated part ``c_0 + c_s s^2 + c_r rdot^2 + c_c (1 - p)^2 + c_w p^2 + c_d d^2`` (module
    docstring), of numbers (``step``) or of arrays (``resolve``) alike: one order of operations, so the two
    agree bit for bit."""
    q = 1.0 - p
    return w[0] + w[1] * spread_sq + w[2] * (rate * rate) + w[3] * (q * q) + w[4] * (p * p) + w[5] * (d * d)


def ring_reading(u: Any) -> tuple[float, float]:
    """(T_ring, rdot) of one raw input row: the mean of the first two channels' temperatures and rates (one
    channel: its own), as ``features.ring_of``."""
    n = channels_of(len(u))
    if n == 1:
        return float(u[0]), float(u[1])
    return 0.5 * (float(u[0]) + float(u[1])), 0.5 * (float(u[n]) + float(u[n + 1]))


#: The candidate structures a fit keeps beside the chosen one (``fitting.wesn.spread_candidates``: at most this
#: many of the tied coils, spread over their lags); a model file with more is refused (``UncertaintySpec``).
MAX_CANDIDATES = 6


@dataclass(frozen=True)
class UncertaintySpec:
    """The model file's ``uncertainty`` section: how ``drift_sigma_dph`` is made (module docstring)."""

    sigma_kind: str  #: "candidates" or "residual"
    residual_dph: float  #: r
    target_range_dph: float  #: R
    spread_scale: float = SPREAD_SCALE
    residual_scale: float = RESIDUAL_SCALE
    box_scale: float = BOX_SCALE
    #: the candidate structures, as model dicts of the model's own kind
    candidates: tuple[dict[str, Any], ...] = field(default=(), compare=False)
    #: the fit's own calibration (module docstring); None in files made before it: today's rule, warned
    calibration: SigmaCalibration | None = None

    def __post_init__(self) -> None:
        if self.sigma_kind not in SIGMA_KINDS:
            raise ValueError(f"uncertainty: sigma_kind must be one of {', '.join(SIGMA_KINDS)}")
        for name in ("residual_dph", "target_range_dph", "spread_scale", "residual_scale", "box_scale"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not (math.isfinite(v) and v >= 0):
                raise ValueError(f"uncertainty: {name} must be a finite number >= 0, got {v!r}")
        if self.sigma_kind == "residual" and self.candidates:
            raise ValueError("uncertainty: a 'residual' sigma has no candidates")
        if len(self.candidates) > MAX_CANDIDATES:
            raise ValueError(
                f"uncertainty.candidates: {len(self.candidates)} candidates; a fit writes at most {MAX_CANDIDATES}"
            )

    def to_dict(self) -> dict[str, Any]:
        return {
            "sigma_kind": self.sigma_kind,
            "residual_dph": float(self.residual_dph),
            "target_range_dph": float(self.target_range_dph),
            "spread_scale": float(self.spread_scale),
            "residual_scale": float(self.residual_scale),
            "box_scale": float(self.box_scale),
            **({"candidates": list(self.candidates)} if self.candidates else {}),
            **({"calibration": self.calibration.to_dict()} if self.calibration is not None else {}),
        }

    @classmethod
    def from_dict(cls, doc: Any) -> UncertaintySpec:
        if not isinstance(doc, dict):
            raise ValueError("uncertainty must be a mapping")
        known = {
            "sigma_kind",
            "residual_dph",
            "target_range_dph",
            "spread_scale",
            "residual_scale",
            "box_scale",
            "candidates",
            "calibration",
        }
        unknown = set(doc) - known
        if unknown:
            raise ValueError(f"uncertainty: unknown keys {', '.join(sorted(map(str, unknown)))}")
        candidates = doc.get("candidates", [])
        if not isinstance(candidates, list) or not all(isinstance(c, dict) for c in candidates):
            raise ValueError("uncertainty: candidates must be a list of models")
        try:
            return cls(
                str(doc["sigma_kind"]),
                doc["residual_dph"],
                doc["target_range_dph"],
                doc.get("spread_scale", SPREAD_SCALE),
                doc.get("residual_scale", RESIDUAL_SCALE),
                doc.get("box_scale", BOX_SCALE),
                tuple(candidates),
                SigmaCalibration.from_dict(doc["calibration"]) if "calibration" in doc else None,
            )
        except KeyError as exc:
            raise ValueError(f"uncertainty: missing {exc}") from None

    @classmethod
    def residual_only(cls, residual_dph: float | None, domain: InputDomain | None) -> UncertaintySpec:
        """The fall-back for a model file without an ``uncertainty`` section: its fit residual as r
        (0 when it has none), no candidates."""
        r = residual_dph if residual_dph is not None and math.isfinite(residual_dph) else 0.0
        return cls("residual", max(float(r), 0.0), target_range_of(domain))


def target_range_of(domain: InputDomain | None) -> float:
    """R: the range of the fit target's 1-min means, from the estimate's bound (``domain``); 0 without one."""
    return 0.0 if domain is None else domain.estimate_limit_dph / ESTIMATE_LIMIT_FACTOR


def box_distance(domain: InputDomain | None, u: Any) -> float:
    """d: how far the temperatures of the input row ``u`` (raw units) lie outside the fit box, in spans of
    it (0 inside; NaN inputs count as inside)."""
    if domain is None:
        return 0.0
    n = channels_of(len(domain.names))
    d = 0.0
    for k in range(n):
        lo, hi, v = domain.low[k], domain.high[k], float(u[k])
        span = hi - lo
        if span > 0 and v == v:
            d = max(d, (lo - v) / span, (v - hi) / span)
    return d


class DriftUncertainty:
    """``drift_sigma_dph`` of each model block (module docstring), with the candidates' explicit state.

    ``candidates``: the candidate models (``DriftModel``), built by the caller from the spec's dicts."""

    def __init__(self, spec: UncertaintySpec, candidates: list[Any], domain: InputDomain | None) -> None:
        self.spec = spec
        self.candidates = candidates
        self.domain = domain
        self._fixed_sq = (spec.residual_scale * spec.residual_dph) ** 2
        self._box = spec.box_scale * spec.target_range_dph
        calibration = spec.calibration
        #: the calibrated rule's numbers (module docstring), or None: today's rule
        self._calibration = calibration if calibration is not None and calibration.calibrated else None
        self._k2 = 0.0 if self._calibration is None else self._calibration.scale**2
        self._deferred: list[list[Any]] | None = None  # between defer() and resolve(): the candidates' work
        self._placeholders = 0  # placeholders handed out since defer()

    def reset(self) -> None:
        if self._deferred is not None and self.candidates:
            self._deferred.append(["reset"])
            return
        for c in self.candidates:
            c.reset()

    def start(self, z: np.ndarray) -> None:
        if self._deferred is not None and self.candidates:
            self._deferred.append(["start", np.array(z, dtype=np.float64)])
            return
        for c in self.candidates:
            c.start(z)

    def step(self, z: np.ndarray, u: Any, estimate_dph: float) -> float:
        """The sigma of ``estimate_dph``, the model's output on the standardized inputs ``z`` (as the model
        saw them) whose raw row, before clamping, is ``u``.  Finite whenever the estimate is.

        Between ``defer`` and ``resolve`` it returns a placeholder instead (a negative number, which no
        sigma is), resolved to the sigma by ``resolve``."""
        if self._deferred is not None and self.candidates:
            d = box_distance(self.domain, u)
            box = self._box * d
            last = self._deferred[-1] if self._deferred else None
            if last is None or last[0] != "step":
                last = ["step", [], [], [], self._placeholders, []]
                self._deferred.append(last)
            last[1].append(np.array(z, dtype=np.float64))
            last[2].append(estimate_dph)
            last[3].append(box)
            last[5].append((*ring_reading(u), d) if self._calibration is not None else (0.0, 0.0, 0.0))
            self._placeholders += 1
            return -float(self._placeholders)
        return self.sigma_of(self.advance(z), u, estimate_dph)

    def advance(self, z: np.ndarray) -> list[float]:
        """Step every candidate one block on ``z`` and return their drifts ``D_c`` (deg/h): the first half of
        ``step``, for a caller that needs them before its estimate (the table law's shape regressors); not
        while deferring."""
        if self._deferred is not None and self.candidates:
            raise RuntimeError("the candidates are deferred: their drifts come with resolve()")
        return [c.step(z) for c in self.candidates]

    def sigma_of(self, drifts_dph: list[float], u: Any, estimate_dph: float) -> float:
        """The second half of ``step``: the sigma of ``estimate_dph`` from the candidates' drifts of this block
        (``advance``) and the raw inputs ``u``."""
        distance = box_distance(self.domain, u)
        box = self._box * distance
        spread_sq = 0.0
        if drifts_dph:
            total = 0.0
            for d in drifts_dph:
                dev = d - estimate_dph
                total += dev * dev
            spread_sq = total / len(drifts_dph)
        cal = self._calibration
        if cal is not None:
            ring_c, rate = ring_reading(u)
            span = cal.ring_high_c - cal.ring_low_c
            p = min(max((ring_c - cal.ring_low_c) / span, 0.0), 1.0) if span > 0 else 0.5
            v = _calibrated_variance(cal.weights, spread_sq, rate, p, distance)
            sigma = math.sqrt(self._k2 * v + box * box)
            return sigma if math.isfinite(sigma) else math.sqrt(self._k2 * cal.weights[0] + box * box)
        sigma = math.sqrt((self.spec.spread_scale**2) * spread_sq + self._fixed_sq + box * box)
        return sigma if math.isfinite(sigma) else math.sqrt(self._fixed_sq + box * box)

    def defer(self) -> None:
        """Collect the candidates' steps instead of taking them one block at a time, for ``resolve`` to take
        in runs (``WesnModel.run``, bit-identical to its steps): the compensator's ``run`` over many blocks.
        ``step`` returns placeholders meanwhile."""
        self._deferred = []
        self._placeholders = 0

    def resolve(self) -> np.ndarray:
        """Take the collected work in order, each run of steps as one ``run`` of every candidate, and end
        deferring; returns the sigmas, placeholder ``-k`` at index ``k - 1``.  The arithmetic is ``step``'s,
        element by element, so the sigmas and the candidates' states are those of the steps."""
        work, self._deferred = self._deferred or [], None
        sigmas = np.empty(self._placeholders if work else 0)
        for item in work:
            if item[0] == "reset":
                for c in self.candidates:
                    c.reset()
            elif item[0] == "start":
                for c in self.candidates:
                    c.start(item[1])
            else:
                _, z, estimates, boxes, first, rings = item
                z, estimate, box = np.array(z), np.array(estimates), np.array(boxes)
                total = np.zeros(len(z))
                for c in self.candidates:
                    dev = c.run(z) - estimate
                    total = total + dev * dev
                spread_sq = total / len(self.candidates)
                cal = self._calibration
                with np.errstate(invalid="ignore", over="ignore"):
                    if cal is not None:
                        ring = np.array(rings, dtype=np.float64).reshape(-1, 3)
                        p = _position(ring[:, 0], cal.ring_low_c, cal.ring_high_c)
                        v = _calibrated_variance(cal.weights, spread_sq, ring[:, 1], p, ring[:, 2])
                        sigma = np.sqrt(self._k2 * v + box * box)
                        fixed = self._k2 * cal.weights[0] + box * box
                    else:
                        sigma = np.sqrt((self.spec.spread_scale**2) * spread_sq + self._fixed_sq + box * box)
                        fixed = self._fixed_sq + box * box
                sigma = np.where(np.isfinite(sigma), sigma, np.sqrt(fixed))
                sigmas[first : first + len(z)] = sigma
        return sigmas

    def adapted(self, adapted_sigma_dph: float, u: Any) -> float:
        """The sigma of an adapted estimate (``adapt.OnlineReadout.adapted_sigma_dph``, from the law's own
        innovation statistics) with the box term: ``sqrt(sigma_a^2 + (k_b d R)^2)``."""
        box = self._box * box_distance(self.domain, u)
        return math.sqrt(adapted_sigma_dph * adapted_sigma_dph + box * box)

    def get_state(self) -> list[dict]:
        return [c.get_state() for c in self.candidates]

    def set_state(self, state: Any) -> None:
        if not isinstance(state, list) or len(state) != len(self.candidates):
            raise ValueError(f"uncertainty state needs {len(self.candidates)} candidate states")
        before = self.get_state()
        try:
            for c, s in zip(self.candidates, state):
                c.set_state(s)
        except (KeyError, TypeError, ValueError):
            for c, s in zip(self.candidates, before):
                c.set_state(s)
            raise
