"""The drift estimate's uncertainty, ``drift_sigma_dph``: the 1-sigma of the error of the estimate as a
1-min mean, about the error's mean over the run (that mean is the bias, which a zero window removes).

Built from what the fit knows, in three parts, each scaled by a factor calibrated on simulated
instruments (``SPREAD_SCALE``, ``RESIDUAL_SCALE``, ``BOX_SCALE``; the model file keeps the factors it was
made with)::

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
            box = self._box * box_distance(self.domain, u)
            last = self._deferred[-1] if self._deferred else None
            if last is None or last[0] != "step":
                last = ["step", [], [], [], self._placeholders]
                self._deferred.append(last)
            last[1].append(np.array(z, dtype=np.float64))
            last[2].append(estimate_dph)
            last[3].append(box)
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
        box = self._box * box_distance(self.domain, u)
        spread_sq = 0.0
        if drifts_dph:
            total = 0.0
            for d in drifts_dph:
                dev = d - estimate_dph
                total += dev * dev
            spread_sq = total / len(drifts_dph)
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
                _, z, estimates, boxes, first = item
                z, estimate, box = np.array(z), np.array(estimates), np.array(boxes)
                total = np.zeros(len(z))
                for c in self.candidates:
                    dev = c.run(z) - estimate
                    total = total + dev * dev
                spread_sq = total / len(self.candidates)
                fixed = self._fixed_sq + box * box
                with np.errstate(invalid="ignore", over="ignore"):
                    sigma = np.sqrt((self.spec.spread_scale**2) * spread_sq + self._fixed_sq + box * box)
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
