"""Where the pipeline's drift estimate comes from: one protocol (``EstimateSource``), three implementations.

Once a block the pipeline (``pipeline.Compensator``) tells the source the block has closed and which reference
rate is in force (``begin_block``, inputs valid or not), asks it for the estimate from the block's standardized
inputs when they are valid (``estimate``: the estimate, its flags, its sigma), feeds the estimate it used back to
the model when the source says so (``feeds_back``), and ends the block (``end_block``: what the source keeps of
it; the flags it adds to the estimate).

* ``FrozenSource``: the model file's weights, ``model.step(z)``; nothing learned.
* ``RateSource``: the online readout (``adapt.OnlineReadout``) from the stored weights over the model's
  regressors, learning on blocks where a reference rate is given and the gyro's static detector says the table
  is static, after ``warmup_s``, on clean blocks (no gap, no thermometer fault, fresh inputs, settled after a
  gap); the adapted weights' sigma while their estimate is in use.
* ``TableSource``: the table law (``table.TableLaw``) beside a rate path: the law records every block and gives
  the estimate once engaged (a dwell was given) and no reference rate is set (the two signals exclude each
  other); until then the rate path does, as before.  Dwells wait until their blocks have closed.  Its state
  (``TableSource.get_state``) is the law's, whole (``TableLaw.get_state``), the dwells waiting, whether it is
  engaged, the scale factor held and the last ring temperature.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple, Protocol

import numpy as np

from ..dwells import Dwell
from ..flags import FLAG_SCALE_FACTOR
from .adapt import OnlineReadout
from .adapt_config import AdaptConfig, StaticDetector
from .blocks import ModelBlock
from .model import DriftModel
from .table import SHAPE_CANDIDATES, SHAPE_REGRESSORS, TableLaw
from .table.state import dwell_from, dwell_state
from .uncertainty import DriftUncertainty


class BlockInputs(NamedTuple):
    """A closed block's valid inputs: the standardized ones ``z`` (the model's), the raw ones ``u`` (clamped to
    the fit box: the sigma's box term), and whether the block is clean (no gap, no thermometer fault, fresh
    inputs, past a gap's settling)."""

    block: ModelBlock
    z: np.ndarray
    u: Any
    clean: bool


class BlockEstimate(NamedTuple):
    estimate_dph: float
    flags: int  #: ``FLAG_ADAPTING`` / ``FLAG_GUARD`` of the estimate
    sigma_dph: float


class EstimateSource(Protocol):
    """What the pipeline asks of the estimating stage, once a block (module docstring)."""

    #: the estimate used is fed back to the model (``DriftModel.feed_back``)
    feeds_back: bool
    #: the candidates' sigmas are needed within the block (the pipeline's ``run`` may not defer them)
    needs_sigmas_in_block: bool
    #: the angle is corrected by the scale factor (``scale_ppm``, held with the estimate)
    corrects_scale: bool

    @property
    def scale_ppm(self) -> float: ...

    @property
    def rate_path(self) -> RateSource | None:
        """The rate path (the online readout and its static detector), if this source has one."""
        ...

    @property
    def table_path(self) -> TableSource | None:
        """The table path (the table law and its dwells), if this source has one."""
        ...

    def begin_block(self, block: ModelBlock, reference_rate_dph: float | None) -> None: ...

    def estimate(self, inputs: BlockInputs) -> BlockEstimate: ...

    def end_block(self, block: ModelBlock, clean: bool) -> int: ...


class FrozenSource:
    """The model file's weights: ``model.step(z)`` and the candidates' sigma; nothing learned."""

    feeds_back = False
    needs_sigmas_in_block = False
    corrects_scale = False
    scale_ppm = 0.0
    rate_path: RateSource | None = None
    table_path: TableSource | None = None

    def __init__(self, model: DriftModel, uncertainty: DriftUncertainty) -> None:
        self.model = model
        self.uncertainty = uncertainty

    def begin_block(self, block: ModelBlock, reference_rate_dph: float | None) -> None:
        """Nothing to watch."""

    def estimate(self, inputs: BlockInputs) -> BlockEstimate:
        estimate = self.model.step(inputs.z)
        return BlockEstimate(estimate, 0, self.uncertainty.step(inputs.z, inputs.u, estimate))

    def end_block(self, block: ModelBlock, clean: bool) -> int:
        return 0


class RateSource:
    """The online readout over the model's regressors (``adapt.OnlineReadout``), gated by the static detector
    and the reference rate (module docstring)."""

    feeds_back = True
    needs_sigmas_in_block = False
    corrects_scale = False
    scale_ppm = 0.0
    table_path: TableSource | None = None

    def __init__(
        self,
        model: DriftModel,
        uncertainty: DriftUncertainty,
        adapt: AdaptConfig,
        block_s: float,
        fit_residual_dph: float | None,
    ) -> None:
        self.model = model
        self.uncertainty = uncertainty
        self.online = OnlineReadout(model.weights, model.intercept, adapt, block_s, fit_residual_dph=fit_residual_dph)
        self.static_detector = StaticDetector.from_config(adapt, block_s)
        self._static = False  # the static detector's verdict on this block
        self._reference: float | None = None  # the reference rate in force for this block

    @property
    def rate_path(self) -> RateSource:
        return self

    def begin_block(self, block: ModelBlock, reference_rate_dph: float | None) -> None:
        """The static detector sees every block's rate."""
        self._static = self.static_detector.step(block.rate_dph)
        self._reference = reference_rate_dph

    def estimate(self, inputs: BlockInputs) -> BlockEstimate:
        f = self.model.regressors_step(inputs.z)
        estimate, flags = self.online_estimate(f, inputs)
        return BlockEstimate(estimate, flags, self.sigma(inputs, estimate, None))

    def online_estimate(self, f: np.ndarray, inputs: BlockInputs) -> tuple[float, int]:
        """The readout's estimate from the model's regressor row ``f``, learning when the block is gated: static,
        clean and past the warm-up (with a reference, the readout's own condition)."""
        block = inputs.block
        gate = self._static and inputs.clean and block.t_end_s > self.online.config.warmup_s
        return self.online.step(f, block.rate_dph, self._reference, gate)

    def candidates_sigma(self, inputs: BlockInputs, estimate: float, drifts: list[float] | None) -> float:
        """The candidates' sigma about ``estimate``: stepped here, or from their ``drifts`` already stepped."""
        if drifts is None:
            return self.uncertainty.step(inputs.z, inputs.u, estimate)
        return self.uncertainty.sigma_of(drifts, inputs.u, estimate)

    def sigma(self, inputs: BlockInputs, estimate: float, drifts: list[float] | None) -> float:
        """``candidates_sigma``, or the adapted weights' while their estimate is the one in use."""
        sigma = self.candidates_sigma(inputs, estimate, drifts)
        if self.online.used_adapted:
            return self.uncertainty.adapted(self.online.adapted_sigma_dph, inputs.u)
        return sigma

    def end_block(self, block: ModelBlock, clean: bool) -> int:
        return 0

    def get_state(self) -> dict[str, Any]:
        """The rate path's state: the readout's (``OnlineReadout.get_state``) and the static detector's, as plain
        YAML-safe values (exact); the rest is each block's own."""
        return {"online": self.online.get_state(), "detector": self.static_detector.get_state()}

    def set_state(self, state: dict[str, Any]) -> None:
        """Inverse of ``get_state``; ``ValueError`` (nothing changed) for missing or unknown keys or bad values."""
        if not isinstance(state, dict) or set(state) != {"online", "detector"}:
            raise ValueError("rate path state needs exactly the keys ['detector', 'online']")
        online_before = self.online.get_state()
        detector = StaticDetector(self.static_detector.threshold_dph, self.static_detector.window_blocks)
        try:
            detector.set_state(state["detector"])
            self.online.set_state(state["online"])
        except (KeyError, TypeError, ValueError) as exc:
            self.online.set_state(online_before)
            raise ValueError(f"rate path state: {exc}") from None
        self.static_detector = detector

    def carry_on(self, old: RateSource) -> None:
        """Continue ``old``'s adaptation (a reloaded model, the same one): its readout's state and its detector."""
        self.online.set_state(old.online.get_state())
        self.static_detector = old.static_detector


class TableSource:
    """The table law beside a rate path (module docstring): the law records every block; engaged and without a
    reference rate it gives the estimate, and the scale factor it learned corrects the angle."""

    feeds_back = True
    needs_sigmas_in_block = True  # the candidates' drifts are the law's shape regressors
    corrects_scale = True

    def __init__(
        self, rate: RateSource, fit_residual_dph: float | None, frame_period_s: float, n_channels: int
    ) -> None:
        """Beside the rate path ``rate`` (its model, its candidates, its settings and block length)."""
        self.rate = rate
        self.model = model = rate.model
        self.uncertainty = rate.uncertainty
        adapt, block_s = rate.online.config, rate.online.sample_time_s
        n_candidates = len(self.uncertainty.candidates)
        #: its shape regressors: the candidate structures' departures, else the model's own regressors
        self.table = TableLaw(
            model.weights,
            model.intercept,
            block_s,
            adapt,
            fit_residual_dph=fit_residual_dph,
            coil=model.coil_lag(),
            shape=SHAPE_CANDIDATES if n_candidates else SHAPE_REGRESSORS,
            n_shape=n_candidates or None,
        )
        self.block_s = float(block_s)
        self.frame_period_s = float(frame_period_s)
        self.n_channels = n_channels
        #: the law gives the estimate once engaged (a dwell was given) and no reference rate is set
        self.engaged = False
        #: the dwells waiting for their blocks to close
        self.dwells: list[Dwell] = []
        self._scale_ppm = 0.0  # the scale factor held with the estimate
        self._t_ring_c = math.nan  # the last finite ring temperature
        self._leads = False
        self._f: np.ndarray | None = None  # this block's regressor row, frozen drift and shape regressors
        self._y_frozen = math.nan
        self._g: np.ndarray | None = None
        self._drifts: list[float] | None = None

    @property
    def scale_ppm(self) -> float:
        return self._scale_ppm

    @property
    def rate_path(self) -> RateSource:
        return self.rate

    @property
    def table_path(self) -> TableSource:
        return self

    def begin_block(self, block: ModelBlock, reference_rate_dph: float | None) -> None:
        self.rate.begin_block(block, reference_rate_dph)
        self._leads = self.engaged and reference_rate_dph is None
        self._f, self._y_frozen, self._g, self._drifts = None, math.nan, None, None

    def estimate(self, inputs: BlockInputs) -> BlockEstimate:
        z = inputs.z
        drifts = self.uncertainty.advance(z) if self.table.shape == SHAPE_CANDIDATES else None
        self._drifts = drifts
        self._f = f = self.model.regressors_step(z)
        if not self._leads:  # the rate path's estimate, as before a dwell was given
            estimate, flags = self.rate.online_estimate(f, inputs)
            return BlockEstimate(estimate, flags, self.rate.sigma(inputs, estimate, drifts))
        self._y_frozen, self._g = self._table_inputs(f, drifts)
        _, estimate, flags = self.table.estimate(self._y_frozen, self._g)
        return BlockEstimate(estimate, flags, self.rate.candidates_sigma(inputs, estimate, drifts))

    def _table_inputs(self, f: np.ndarray, drifts: list[float] | None) -> tuple[float, np.ndarray]:
        """The table law's inputs from the model's regressors ``f``: the frozen drift, bit for bit the model's
        (``D_hat = f . w0 + b0``, the rate path's ``frozen_estimate``), and the shape regressors: the candidates'
        departures from it, ``D_c - D_hat``, or ``f`` itself."""
        y_frozen = self.rate.online.frozen_estimate(f)
        return y_frozen, f if drifts is None else np.asarray(drifts, dtype=np.float64) - y_frozen

    def end_block(self, block: ModelBlock, clean: bool) -> int:
        """The block into the table law (its inputs: none when the block's were not valid), then the dwells whose
        blocks have all closed; the scale factor held with the estimate (``FLAG_SCALE_FACTOR`` while applied)."""
        table = self.table
        y_frozen, g = self._y_frozen, self._g
        if g is None and self._f is not None:
            y_frozen, g = self._table_inputs(self._f, self._drifts)
        temps = block.temps_c
        ring = 0.5 * (temps[0] + temps[1]) if self.n_channels >= 2 else temps[0]
        if math.isfinite(ring):
            self._t_ring_c = ring
        else:
            ring, clean = self._t_ring_c, False
        warming_up = clean and not block.t_end_s > table.config.warmup_s  # not learned from, for the warm-up alone
        clean = clean and not warming_up
        frames_s = block.n_samples * self.frame_period_s
        table.block(block.index, y_frozen, g, block.rate_dph, frames_s, ring, clean, warming_up)
        end_s = (block.index + 1) * self.block_s
        while self.dwells and self.dwells[0].t_end_s <= end_s + 1e-9:
            table.observe(self.dwells.pop(0))
        # the scale factor corrects the angle while adapting from table angles (not after ?ADAPT off)
        self._scale_ppm = table.scale_ppm_at(table.coil_temperature_c) if self._leads else 0.0
        return FLAG_SCALE_FACTOR if self._scale_ppm else 0

    def get_state(self) -> dict[str, Any]:
        """Everything the table path continues from, as plain YAML-safe values (exact): the law's state (its
        chain too), whether it is engaged, the dwells waiting, the scale factor held and the last finite ring
        temperature (what a block leaves for the next; the rest is the block's own)."""
        return {
            "law": self.table.get_state(),
            "engaged": self.engaged,
            "dwells": [dwell_state(d) for d in self.dwells],
            "scale_ppm": float(self._scale_ppm),
            "t_ring_c": float(self._t_ring_c),
        }

    def set_state(self, state: dict[str, Any]) -> None:
        """Inverse of ``get_state``; ``ValueError`` (nothing changed) for missing or unknown keys or bad values."""
        keys = {"law", "engaged", "dwells", "scale_ppm", "t_ring_c"}
        if not isinstance(state, dict) or set(state) != keys:
            raise ValueError(f"table path state needs exactly the keys {sorted(keys)}")
        try:
            dwells = [dwell_from(d) for d in state["dwells"]]
            scale_ppm, t_ring_c = float(state["scale_ppm"]), float(state["t_ring_c"])
        except (TypeError, ValueError) as exc:
            raise ValueError(f"table path state: not dwells and numbers: {exc}") from None
        if not isinstance(state["engaged"], bool):
            raise ValueError("table path state: engaged must be true or false")
        self.table.set_state(state["law"])
        self.engaged, self.dwells, self._scale_ppm, self._t_ring_c = state["engaged"], dwells, scale_ppm, t_ring_c

    def carry_on(self, old: TableSource, same_model: bool) -> None:
        """Continue ``old``'s adapting from table angles (a reloaded model): engaged as it was; with the same
        model the same law, its chain, the dwells waiting and the scale factor held (another model: a new law)."""
        self.engaged = old.engaged
        if same_model:
            self.table, self.dwells = old.table, old.dwells
            self._scale_ppm, self._t_ring_c = old._scale_ppm, old._t_ring_c
