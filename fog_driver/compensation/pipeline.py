"""The streaming compensation pipeline: samples in, compensated samples out, with explicit state.

    samples --(BlockAverager, model rate)--> blocks --(FeatureExtractor, Standardizer)--> z
            --(drift model)--> drift estimate D_hat (deg/h), held until the next block closes

Every frame of block j is compensated with the estimate made from blocks
before j (causal, held)::

    dtheta_comp = dtheta - D_hat * frame_period_s        (1 deg/h = 1 arcsec/s)
    angle_raw   = sum of dtheta,  angle_comp = sum of dtheta_comp         (from the frames, never host time)

Until the model gives an estimate there is none: D_hat is NaN (``drift_dph`` and ``drift_sigma_dph`` absent),
the frame is flagged ``FLAG_UNCOMPENSATED`` and compensated by nothing, ``dtheta_comp = dtheta`` (the
compensated angle integrates the raw rate; no NaN reaches an angle).  That is so in the first block of a run,
while a thermometer has never read valid, while the inputs are stale before any estimate, and from the frame
after a gap longer than ``MAX_GAP_S`` (the pipeline restarts at rest) until the first block after it closes.
Inputs outside the model file's fit box (``domain``) are clamped to it and an estimate beyond its bound is
clipped, both flagged ``FLAG_EXTRAPOLATING``.  A non-finite estimate keeps the last good one and flags the
frame ``guard`` (``uncompensated`` when there is none); a NaN is never fed back to the model.
``step(sample)`` and ``run(samples)`` share the block-level code and give
bit-identical results for any split of a capture (tested).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, NamedTuple, cast

import numpy as np

from ..dwells import Dwell, table_angle_deg
from ..errors import InputFileError
from ..flags import (
    FLAG_EXTRAPOLATING,
    FLAG_GAP,
    FLAG_GUARD,
    FLAG_INPUT_STALE,
    FLAG_THERMOMETER_FAULT,
    FLAG_UNCOMPENSATED,
)
from ..protocol import STATUS_THERMOMETER_FAULT
from ..samples.stream import Sample, SampleBlock
from .adapt import OnlineReadout
from .adapt_config import AdaptConfig, StaticDetector
from .blocks import PLAUSIBLE_TEMP_C, BlockAverager, ModelBlock
from .dwell import MIN_LIVE_DWELL_S, out_of_order
from .estimate_sources import BlockInputs, EstimateSource, FrozenSource, RateSource, TableSource
from .features import DEGRADED_FLAGS, FeatureExtractor
from .model import ModelFile
from .table import CHAIN_KEY, TableLaw, TableOutcome
from .uncertainty import DriftUncertainty

#: A link gap longer than this restarts the pipeline at rest (the model's memory of before is stale);
#: a shorter one is stepped through block by block.
MAX_GAP_S = 6 * 3600.0
#: After a gap the estimates are flagged ``gap`` for this many slow rate-smoother time constants.
SETTLE_TAUS = 3.0


def restarts_at_rest(missing_blocks, block_s: float):
    """Whether ``missing_blocks`` blocks missing (a link gap; a scalar or an array, element-wise) restart the
    pipeline at rest: longer than ``MAX_GAP_S``."""
    return missing_blocks * block_s > MAX_GAP_S


def stale_estimate(estimate_block, frame_block, block_s: float):
    """Whether a frame's held estimate is from before a gap that restarts the pipeline (``restarts_at_rest``):
    the blocks from the estimate's to the frame's are all missing (scalars or arrays, element-wise).  Such a
    frame has no estimate (``Compensator.step``/``run``: NaN, ``uncompensated``)."""
    return (estimate_block >= 0) & restarts_at_rest(frame_block - estimate_block, block_s)


def frame_flags(estimate_flags, estimate_block, frame_block, missing_before, status, temps_c, stale=False):
    """The flags of a frame, the one rule of ``Compensator.step`` (scalars) and ``Compensator.run`` (arrays,
    element-wise)::

        flags = the flags of the estimate it is compensated with (uncompensated when ``stale``:
                ``stale_estimate``)
              | gap                if frames were lost just before it (missing_before > 0), or its estimate is
                                   from before a gap (0 <= estimate_block < frame_block)
              | thermometer_fault  if its status says so, or a reading of ``temps_c`` (its format's channels,
                                   a scalar or a column each) is NaN or outside ``PLAUSIBLE_TEMP_C``
    """
    low, high = PLAUSIBLE_TEMP_C
    estimate_flags = estimate_flags * (stale == 0) + FLAG_UNCOMPENSATED * stale  # stale: no estimate's flags
    gap = (missing_before > 0) | ((estimate_block >= 0) & (frame_block > estimate_block))
    fault = (status & STATUS_THERMOMETER_FAULT) != 0
    for t in temps_c:
        fault = fault | (t < low) | (t > high) | (t != t)  # not plausible: outside, or NaN
    return estimate_flags | FLAG_GAP * gap | FLAG_THERMOMETER_FAULT * fault


class CompensatedSample(NamedTuple):
    seq: int
    t_s: float
    dtheta_arcsec: float
    #: the drift estimate applied (deg/h); NaN while there is none (flagged ``uncompensated``: module docstring)
    drift_dph: float
    dtheta_comp_arcsec: float
    angle_raw_arcsec: float
    angle_comp_arcsec: float
    temps_c: tuple[float, ...]
    flags: int
    #: the 1-sigma of the drift estimate's error as a 1-min mean, about its mean over the run (deg/h);
    #: NaN while there is no estimate (``uncertainty``)
    drift_sigma_dph: float = math.nan


@dataclass
class CompensatedColumns:
    seq: np.ndarray
    t_s: np.ndarray
    dtheta_arcsec: np.ndarray
    drift_dph: np.ndarray
    dtheta_comp_arcsec: np.ndarray
    angle_raw_arcsec: np.ndarray
    angle_comp_arcsec: np.ndarray
    temps_c: np.ndarray  #: (n, 3)
    flags: np.ndarray
    drift_sigma_dph: np.ndarray | None = None  #: as ``CompensatedSample.drift_sigma_dph``; None: all NaN

    def __post_init__(self) -> None:
        if self.drift_sigma_dph is None:
            self.drift_sigma_dph = np.full(len(self.seq), math.nan)

    def __len__(self) -> int:
        return len(self.seq)

    def sample(self, i: int) -> CompensatedSample:
        return CompensatedSample(
            int(self.seq[i]),
            float(self.t_s[i]),
            float(self.dtheta_arcsec[i]),
            float(self.drift_dph[i]),
            float(self.dtheta_comp_arcsec[i]),
            float(self.angle_raw_arcsec[i]),
            float(self.angle_comp_arcsec[i]),
            tuple(float(v) for v in self.temps_c[i]),
            int(self.flags[i]),
            float(cast(np.ndarray, self.drift_sigma_dph)[i]),
        )


class Compensator:
    """A model file applied to a sample stream, the estimate from one source (``estimate_sources``): the frozen
    weights; adapting online (``adapt``: the rate path, learning where ``reference_rate_dph`` is given, the table's
    known rate, 0 at rest); or adapting from table angles too (``table``: the table law beside the rate path).
    Frames carry ``FLAG_ADAPTING`` / ``FLAG_GUARD`` / ``FLAG_SCALE_FACTOR`` from the estimate.
    """

    def __init__(
        self,
        model_file: ModelFile,
        frame_period_s: float,
        adapt: AdaptConfig | None = None,
        reference_rate_dph: float | None = None,
        table: bool = False,
    ) -> None:
        self.model_file = model_file
        self.model = model_file.model
        self.frame_period_s = float(frame_period_s)
        self.n_channels = len(model_file.temperature_channels)
        self.averager = BlockAverager(frame_period_s, model_file.model_rate_hz, self.n_channels)
        self.features = FeatureExtractor(
            model_file.features, substitution=model_file.substitution, n_channels=self.n_channels
        )
        self._normalizer = model_file.normalizer
        self.domain = model_file.domain
        self._block_s = 1.0 / model_file.model_rate_hz
        self._settle_blocks = int(math.ceil(SETTLE_TAUS * model_file.features.rate_tau_slow_s / self._block_s))
        self._last_index: int | None = None  # the last block seen (a gap: blocks missing after it)
        self._last_temps: tuple[float, ...] = (
            math.nan,
            math.nan,
            math.nan,
        )  # its temperatures (a gap is interpolated from them)
        self._settle_until = -1  # estimates up to this block are flagged gap (the smoothers catch up)
        self.estimate_dph = math.nan  #: the held estimate; NaN: none yet (module docstring)
        self.sigma_dph = math.nan  #: the held estimate's drift_sigma_dph
        self.estimate_flags = FLAG_UNCOMPENSATED
        self._estimate_block = -1  # the block index the estimate applies from
        self.angle_raw_arcsec = 0.0
        self.angle_comp_arcsec = 0.0
        self.blocks_seen = 0
        self._started = False
        self.model.reset()
        self.uncertainty = DriftUncertainty(model_file.sigma_spec, model_file.candidate_models(), self.domain)
        if table and adapt is None:  # adapting from table angles is adapting: its settings, and the rate path's
            adapt = AdaptConfig()
        self.adapt = adapt
        self.reference_rate_dph = None if reference_rate_dph is None else float(reference_rate_dph)
        #: where the estimate comes from: the frozen weights, the rate path, or the table law beside it
        self.source: EstimateSource
        if adapt is None:
            self.source = FrozenSource(self.model, self.uncertainty)
        else:
            rate = RateSource(self.model, self.uncertainty, adapt, self._block_s, model_file.fit_residual_dph)
            if table:
                self.source = TableSource(rate, model_file.fit_residual_dph, self.frame_period_s, self.n_channels)
            else:
                self.source = rate

    @property
    def online(self) -> OnlineReadout | None:
        """The online readout when adapting (the rate path's), else None."""
        rate = self.source.rate_path
        return None if rate is None else rate.online

    @property
    def static_detector(self) -> StaticDetector | None:
        rate = self.source.rate_path
        return None if rate is None else rate.static_detector

    @property
    def table(self) -> TableLaw | None:
        """The table law when adapting from table angles, else None."""
        path = self.source.table_path
        return None if path is None else path.table

    @property
    def table_engaged(self) -> bool:
        """The table law records every block; it gives the estimate once engaged (a dwell was given) and no
        reference rate is set (the two signals exclude each other)."""
        path = self.source.table_path
        return path is not None and path.engaged

    @property
    def scale_ppm(self) -> float:
        """The scale factor (ppm) held with the estimate (adapting from table angles; else 0)."""
        return self.source.scale_ppm

    # -- block level: shared by step and run ---------------------------------------------------

    def _on_block(self, block: ModelBlock) -> None:
        """A block has closed: update the held estimate, which applies from the next block on.

        Blocks missing before it (a link gap) are stepped first, their temperatures interpolated linearly
        between the blocks on either side (the features, the model and the law advance by the elapsed time;
        nothing is learned: no rate), up to ``MAX_GAP_S``; after a longer gap the pipeline restarts at
        rest.  Either way the estimates of the next ``SETTLE_TAUS`` slow rate-smoother time constants are
        flagged ``gap``: the smoothers are catching up with what the gap hid."""
        if self._last_index is not None and block.index > self._last_index + 1:
            missing = block.index - self._last_index - 1
            if restarts_at_rest(missing, self._block_s):
                self.features.reset()
                self.model.reset()
                self.uncertainty.reset()
                self._started = False
                self.estimate_dph, self.sigma_dph, self.estimate_flags = math.nan, math.nan, FLAG_UNCOMPENSATED
            else:  # the temperatures interpolated linearly across the gap (exact for a ramp)
                before, now = self._last_temps, block.temps_c
                for i, index in enumerate(range(self._last_index + 1, block.index)):
                    w = (i + 1) / (missing + 1)
                    temps = tuple(a + w * (b - a) for a, b in zip(before, now))  # NaN where either is NaN
                    self._process(ModelBlock(index, math.nan, 0, math.nan, temps, FLAG_GAP))
            self._settle_until = block.index + self._settle_blocks
        self._last_index = block.index
        self._last_temps = tuple(float(v) for v in block.temps_c)
        self._process(block)
        if block.index <= self._settle_until:
            self.estimate_flags |= FLAG_GAP

    def _process(self, block: ModelBlock) -> None:
        u: Any  # the inputs: a list, an array once clamped
        u, flags = self.features.step(block.temps_c)
        flags |= block.flags & (FLAG_GAP | FLAG_THERMOMETER_FAULT)
        self.blocks_seen += 1
        source = self.source
        source.begin_block(block, self.reference_rate_dph)
        clean = not flags & (FLAG_GAP | FLAG_THERMOMETER_FAULT | DEGRADED_FLAGS) and block.index > self._settle_until
        if any(v != v for v in u):  # a thermometer never read valid yet: nothing to model, no estimate
            self.estimate_dph, self.sigma_dph = math.nan, math.nan
            self.estimate_flags = FLAG_UNCOMPENSATED | flags
        else:
            extrapolating = 0
            raw = u
            if self.domain is not None:
                u, outside = self.domain.clamp(u)
                extrapolating = FLAG_EXTRAPOLATING if outside else 0
            z = self._normalizer.transform(u)
            if not self._started:  # the model starts at rest at its first valid input, as when fitted
                self.model.start(z)
                self.uncertainty.start(z)
                self._started = True
            estimate, adapt_flags, sigma = source.estimate(BlockInputs(block, z, raw, clean))
            if self.domain is not None:
                estimate, clipped = self.domain.bound(estimate)
                extrapolating |= FLAG_EXTRAPOLATING if clipped else 0
            held = flags & FLAG_INPUT_STALE  # inputs frozen beyond hold_s: the estimate is held
            if held:
                estimate, sigma = self.estimate_dph, self.sigma_dph
            if source.feeds_back and math.isfinite(estimate):
                self.model.feed_back(estimate)  # the estimate actually used (the WESN's output feedback), never NaN
            if math.isfinite(estimate):
                self.estimate_dph = estimate
                self.sigma_dph = sigma
                self.estimate_flags = (flags & DEGRADED_FLAGS) | adapt_flags | extrapolating
            elif math.isfinite(self.estimate_dph):  # the last good estimate is kept
                self.estimate_flags = FLAG_GUARD | (flags & DEGRADED_FLAGS)
            else:  # none to keep: no estimate yet
                self.estimate_dph, self.sigma_dph = math.nan, math.nan
                self.estimate_flags = FLAG_UNCOMPENSATED | (flags & DEGRADED_FLAGS)
        self.estimate_flags |= source.end_block(block, clean)
        self._estimate_block = block.index + 1

    # -- table angles ----------------------------------------------------------------------------

    def _table_path(self) -> TableSource:
        """The table path; ``ValueError`` unless this compensator adapts from table angles."""
        path = self.source.table_path
        if path is None:
            raise ValueError("this compensator does not adapt from table angles")
        return path

    def add_dwells(self, dwells: list[Dwell]) -> None:
        """Dwells (device time from the first sample) for the table law, taken as their blocks close; the table
        law gives the estimate from now on."""
        path = self._table_path()
        if self.reference_rate_dph is not None:
            raise ValueError("adapting against a reference rate: table angles are the other signal")
        path.dwells.extend(dwells)
        path.engaged = True

    @property
    def device_time_s(self) -> float | None:
        """The device time at the end of the latest frame, s from the first (None: no frame yet)."""
        return self.averager.device_time_s

    def table_dwell(self, angle_deg: float, dwell_s: float, angle_start_deg: float | None = None) -> Dwell:
        """A live dwell: the table has stood at ``angle_deg`` for the last ``dwell_s`` seconds (from
        ``angle_start_deg`` when it moved within the dwell).  Checked here (``ValueError``, one line: nothing
        changed) for what can be told at once: an angle that is not a table angle (``dwell.table_angle_deg``: the
        bound ``?TABLE`` and a table log apply), no frame yet, a dwell shorter than ``MIN_LIVE_DWELL_S``, longer
        than the time since the chain's last break (a gap, a restart, ``?ZERO``), or starting before the
        previous dwell ended; what the gyro says of it is the law's verdict once its blocks have closed."""
        path = self._table_path()
        angle_deg = table_angle_deg(angle_deg, "angle_deg")
        if angle_start_deg is not None:
            angle_start_deg = table_angle_deg(angle_start_deg, "angle_start_deg")
        now = self.device_time_s
        if now is None:
            raise ValueError("no samples yet: no dwell to hold the angle against")
        if not dwell_s >= MIN_LIVE_DWELL_S:
            raise ValueError(f"a dwell must last at least {MIN_LIVE_DWELL_S:g} s, got {dwell_s:g}")
        start = now - dwell_s
        since = path.table.chain_start_s
        if since is None or start < since - 1e-9:
            held = 0.0 if since is None else now - since
            raise ValueError(
                f"the dwell ({dwell_s:g} s) reaches back past a break in the data (a gap, a restart, a zero): "
                f"{held:.1f} s since"
            )
        order = out_of_order(start, path.dwells[-1].t_end_s if path.dwells else path.table.last_dwell_end_s)
        if order is not None:
            raise ValueError(order)
        if angle_start_deg is None:
            dwell = Dwell(start, now, angle_deg)
        else:
            dwell = Dwell(start, now, angle_start_deg, angle_deg)
        self.add_dwells([dwell])
        return dwell

    def stop_table(self) -> None:
        """Adapting from table angles ends: the estimate is the rate path's again (frozen without a reference);
        dwells not yet taken are dropped, the law keeps recording (and its weights) for a later ``?TABLE``."""
        path = self.source.table_path
        if path is not None:
            path.engaged = False
            path.dwells.clear()

    def break_table_chain(self) -> None:
        """No interval is learned across this point (``?ZERO``, an identity change)."""
        if self.table is not None:
            self.table.break_chain()

    @property
    def pending_dwells(self) -> list[Dwell]:
        """Dwells given whose blocks have not all closed yet."""
        path = self.source.table_path
        return [] if path is None else list(path.dwells)

    @property
    def table_outcomes(self) -> list[TableOutcome]:
        return [] if self.table is None else list(self.table.outcomes)

    # -- adaptation state ----------------------------------------------------------------------

    def get_state(self) -> dict:
        """Everything the pipeline continues from: the open block, the feature smoothers and held values, the
        model's memory (reservoir), the held estimate, the two angles (``angles``: raw and compensated, arcsec),
        when adapting the rate path's state under ``readout`` (``RateSource.get_state``: the readout and the
        static detector), and when adapting from table angles the table path's under ``table``
        (``TableSource.get_state``: the law, its chain, the dwells waiting).  Plain YAML-safe values, exact.
        The adaptation document keeps the first part only (``adaptation_document``)."""
        state = self._own_state()
        state["angles"] = [float(self.angle_raw_arcsec), float(self.angle_comp_arcsec)]
        rate = self.source.rate_path
        if rate is not None:
            state["readout"] = rate.get_state()
        path = self.source.table_path
        if path is not None:
            state["table"] = path.get_state()
        return state

    def _own_state(self) -> dict:
        """``get_state`` less the angles, the readout and the table path: the part the adaptation document keeps
        and a reload carries on (``continue_from``), built without the parts they would drop."""
        return {
            "averager": self.averager.get_state(),
            "features": self.features.get_state(),
            "model": self.model.get_state(),
            "started": self._started,
            "blocks_seen": self.blocks_seen,
            "estimate_dph": self.estimate_dph,
            "estimate_flags": self.estimate_flags,
            "estimate_block": self._estimate_block,
            "last_index": self._last_index,
            "last_temps": list(self._last_temps),
            "settle_until": self._settle_until,
            "sigma_dph": self.sigma_dph,
            "uncertainty": self.uncertainty.get_state(),
        }

    def set_state(self, state: dict) -> None:
        """Inverse of ``get_state`` (``ValueError``, nothing changed, when it does not fit this model and frame
        rate); a state without ``angles``, ``readout`` or ``table`` leaves that part as it is (the adaptation
        document's pipeline has none of them)."""
        keys = {
            "averager",
            "features",
            "model",
            "started",
            "blocks_seen",
            "estimate_dph",
            "estimate_flags",
            "estimate_block",
            "last_index",
            "last_temps",
            "settle_until",
        }
        optional = {"sigma_dph", "uncertainty", "angles"}  # the first two absent in states saved before the sigma
        rate, path = self.source.rate_path, self.source.table_path
        if rate is not None:
            optional.add("readout")
        if path is not None:
            optional.add("table")
        if not isinstance(state, dict) or not keys <= set(state) <= keys | optional:
            raise ValueError(f"pipeline state needs exactly the keys {sorted(keys)} (and {sorted(optional)})")
        try:  # the scalars first, and every part on fresh objects: nothing changes when a part is bad
            scalars = (
                bool(state["started"]),
                int(state["blocks_seen"]),
                float(state["estimate_dph"]),
                int(state["estimate_flags"]),
                int(state["estimate_block"]),
                None if state["last_index"] is None else int(state["last_index"]),
                tuple(float(v) for v in state["last_temps"]),
                int(state["settle_until"]),
                float(state.get("sigma_dph", math.nan)),
            )
            angles = tuple(float(v) for v in state["angles"]) if "angles" in state else None
        except (TypeError, ValueError) as exc:
            raise ValueError(f"pipeline state: not numbers: {exc}") from None
        if angles is not None and len(angles) != 2:
            raise ValueError("pipeline state: angles needs 2 values (raw, compensated)")
        if len(scalars[6]) != 3:
            raise ValueError("pipeline state: last_temps needs 3 values")
        averager = BlockAverager(self.averager.frame_period_s, self.averager.model_rate_hz, self.n_channels)
        averager.set_state(state["averager"])
        features = FeatureExtractor(
            self.features.params, substitution=self.features.substitution, n_channels=self.n_channels
        )
        try:
            features.set_state(state["features"])
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"pipeline state: bad feature state: {exc}") from None
        before = self.model.get_state()
        try:
            self.model.set_state(state["model"])
        except (KeyError, TypeError, ValueError) as exc:
            self.model.set_state(before)
            raise ValueError(f"pipeline state: bad model state: {exc}") from None
        if {k: len(v) if isinstance(v, list) else None for k, v in self.model.get_state().items()} != {
            k: len(v) if isinstance(v, list) else None for k, v in before.items()
        }:
            self.model.set_state(before)
            raise ValueError("pipeline state: the model state is for another model")
        uncertainty_before = self.uncertainty.get_state()
        if "uncertainty" in state:
            try:
                self.uncertainty.set_state(state["uncertainty"])
            except (KeyError, TypeError, ValueError) as exc:
                self.model.set_state(before)
                raise ValueError(f"pipeline state: bad uncertainty state: {exc}") from None
        table_before = path.get_state() if path is not None and "table" in state else None
        if path is not None and table_before is not None:
            try:
                path.set_state(state["table"])
            except ValueError as exc:
                self.model.set_state(before)
                self.uncertainty.set_state(uncertainty_before)
                raise ValueError(f"pipeline state: bad table path state: {exc}") from None
        if rate is not None and "readout" in state:
            try:
                rate.set_state(state["readout"])
            except ValueError as exc:
                self.model.set_state(before)
                self.uncertainty.set_state(uncertainty_before)
                if path is not None and table_before is not None:
                    path.set_state(table_before)
                raise ValueError(f"pipeline state: bad readout state: {exc}") from None
        self.averager = averager
        self.features = features
        (
            self._started,
            self.blocks_seen,
            self.estimate_dph,
            self.estimate_flags,
            self._estimate_block,
            self._last_index,
            self._last_temps,
            self._settle_until,
            self.sigma_dph,
        ) = scalars
        if angles is not None:
            self.angle_raw_arcsec, self.angle_comp_arcsec = angles

    def continue_from(self, old: Compensator, *, same_model: bool) -> None:
        """Carry on from ``old`` (a model reloaded mid-run): with the same inputs (features, block length
        and frame period) the open block, the smoothers, the gap bookkeeping and the held estimate (the
        substitutes' offsets where the new model predicts a sensor the same way; the others are tracked
        afresh); with the same model (``same_model``) also its memory and its adaptation.  A different model
        starts at rest at the next block's inputs, as at switch-on.  The angles are the caller's to carry."""
        same_grid = (self.averager.block_us, self.averager.frame_period_s) == (
            old.averager.block_us,
            old.averager.frame_period_s,
        )
        if self.features.params != old.features.params or not same_grid:
            return
        # the table path and the rate path carry on below (``carry_on``); the angles are the caller's to carry
        state = old._own_state()
        state["features"] = self.features.adopt_state(state["features"], old.features.substitution)
        if not same_model:
            state["model"], state["started"] = self.model.get_state(), False
            state["uncertainty"] = self.uncertainty.get_state()
        self.set_state(state)
        rate, old_rate = self.source.rate_path, old.source.rate_path
        if same_model and old_rate is not None and rate is not None:
            rate.carry_on(old_rate)
        path, old_path = self.source.table_path, old.source.table_path
        if old_path is not None and path is not None:  # adapting from table angles carries on
            path.carry_on(old_path, same_model)

    def adaptation_document(self) -> dict:
        """The adaptation state: the readout, the static detector, and the pipeline's state, so that a restart
        of the same run continues exactly (``modelfiles.save_adaptation`` writes it), as a snapshot of plain
        values (to take under a lock and write outside it); only when adapting."""
        online = self.check_adapting()
        # the pipeline's own part: the angles are the caller's, the readout is the document's own (beside it), and
        # the table law's chain is not the document's
        doc = online.state_document(detector=self.static_detector, pipeline=self._own_state())
        if self.table is not None and (self.table_engaged or self.table.accepted):
            doc["table"] = self.table.learned_state()  # what it learned from the table's angles (a new run restores it)
        return doc

    def check_adapting(self) -> OnlineReadout:
        """The online readout; ``ValueError`` unless this compensator adapts (has an adapt config)."""
        if self.online is None:
            raise ValueError("this compensator is not adapting (no adapt config)")
        return self.online

    def restore_adaptation(self, doc: dict, where: str, *, new_run: bool = True) -> None:
        """Restore ``adaptation_document``'s document (read from ``where``; ``InputFileError`` when it does not
        fit this model).  With ``new_run`` (a new switch-on: a new turn-on bias, a new device clock) the bias
        is captured again and only the readout is kept (the adapted W); without, the same run continues: the
        pipeline's state (open block, smoothers, reservoir, held estimate) is restored too, and the output
        continues exactly as if uninterrupted, but for the table law, whose chain the document does not keep
        (``table.learned_part``): it starts a new one (a document with a chain in it is refused; the pipeline's
        ``get_state`` holds the chain)."""
        online = self.check_adapting()
        for part, key in (("table", CHAIN_KEY), ("pipeline", "table")):  # a document's table law starts a new chain
            if isinstance(doc.get(part), dict) and key in doc[part]:
                raise InputFileError(f"{where}: corrupt adaptation state: {part} has no {key!r} in a document")
        if self.table is not None and "table" in doc:  # checked first: a refusal changes nothing
            try:
                self.table.set_state(doc["table"])
            except ValueError as exc:
                raise InputFileError(f"{where}: corrupt adaptation state: {exc}") from None
        if not new_run and "pipeline" in doc:  # checked before anything changes
            saved = self.get_state()
            try:
                self.set_state(doc["pipeline"])
            except ValueError as exc:
                raise InputFileError(f"{where}: corrupt adaptation state: {exc}") from None
            try:
                online.load_state_doc(doc, where, detector=self.static_detector)
            except InputFileError:
                self.set_state(saved)
                raise
        else:
            online.load_state_doc(doc, where, detector=self.static_detector)
        if new_run:
            online.begin_run()

    # -- frame level ---------------------------------------------------------------------------

    def step(self, sample: Sample) -> CompensatedSample:
        for block in self.averager.step(sample):
            self._on_block(block)
        frame_block = self.averager.open_block
        stale = stale_estimate(self._estimate_block, frame_block, self._block_s)
        drift, sigma = (math.nan, math.nan) if stale else (self.estimate_dph, self.sigma_dph)
        if drift == drift:
            dtheta_comp = sample.dtheta_arcsec - drift * self.frame_period_s
            if self.source.corrects_scale:
                dtheta_comp -= (1e-6 * self.scale_ppm) * sample.dtheta_arcsec
        else:  # no estimate: nothing subtracted
            dtheta_comp = sample.dtheta_arcsec
        self.angle_raw_arcsec += sample.dtheta_arcsec
        self.angle_comp_arcsec += dtheta_comp
        temps = (sample.t_top_c, sample.t_bottom_c, sample.t_housing_c)
        flags = frame_flags(
            self.estimate_flags,
            self._estimate_block,
            frame_block,
            sample.missing_before,
            sample.status,
            temps[: self.n_channels],
            stale,
        )
        return CompensatedSample(
            sample.seq,
            sample.t_s,
            sample.dtheta_arcsec,
            drift,
            dtheta_comp,
            self.angle_raw_arcsec,
            self.angle_comp_arcsec,
            temps,
            flags,
            sigma,
        )

    def run(self, samples: SampleBlock) -> CompensatedColumns:
        """Vector form of ``step`` over many samples: per-frame work vectorized, blocks in order."""
        n = len(samples)
        held_before = (self.estimate_dph, self.estimate_flags, self._estimate_block, self.sigma_dph, self.scale_ppm)
        blocks = self.averager.run(samples)
        # The estimate each closed block leaves behind, in order; the candidate structures' steps are
        # taken after the loop, in runs (``DriftUncertainty.defer``), and their sigmas put in place; not with
        # a table law (its shape regressors need them in the block).
        after = []
        if not self.source.needs_sigmas_in_block:
            self.uncertainty.defer()
        try:
            for i in range(len(blocks)):
                self._on_block(blocks.block(i))
                after.append(
                    (self.estimate_dph, self.estimate_flags, self._estimate_block, self.sigma_dph, self.scale_ppm)
                )
        finally:
            try:
                resolved = self.uncertainty.resolve()
            except BaseException:
                self.sigma_dph = math.nan if self.sigma_dph < 0 else self.sigma_dph  # never a placeholder held
                raise
            after = [(*a[:3], _resolved(a[3], resolved), a[4]) for a in after]
            self.sigma_dph = _resolved(self.sigma_dph, resolved)
        # Which estimate each frame sees: the latest from a block with a smaller index.
        frame_block = self.averager.blocks_of(
            samples.t_s
        )  # the grid is set: a block has closed, or these samples set it
        which = np.searchsorted(blocks.index, frame_block, side="left") - 1  # -1: the estimate held before
        estimates = np.array([held_before[0]] + [a[0] for a in after])
        est_flags = np.array([held_before[1]] + [a[1] for a in after], dtype=np.int64)
        est_blocks = np.array([held_before[2]] + [a[2] for a in after], dtype=np.int64)
        sigmas = np.array([held_before[3]] + [a[3] for a in after], dtype=float)
        stale = stale_estimate(est_blocks[which + 1], frame_block, self._block_s)
        drift = np.where(stale, math.nan, estimates[which + 1])
        dtheta = samples.dtheta_arcsec
        dtheta_comp = dtheta - drift * self.frame_period_s
        if self.source.corrects_scale:
            scales = np.array([held_before[4]] + [a[4] for a in after], dtype=float)
            dtheta_comp = dtheta_comp - (1e-6 * scales[which + 1]) * dtheta
        dtheta_comp = np.where(np.isnan(drift), dtheta, dtheta_comp)  # no estimate: nothing subtracted
        angle_raw = np.cumsum(np.r_[self.angle_raw_arcsec, dtheta])[1:]
        angle_comp = np.cumsum(np.r_[self.angle_comp_arcsec, dtheta_comp])[1:]
        if n:
            self.angle_raw_arcsec = float(angle_raw[-1])
            self.angle_comp_arcsec = float(angle_comp[-1])
        columns = (samples.t_top_c, samples.t_bottom_c, samples.t_housing_c)
        temps = np.column_stack(columns)
        flags = frame_flags(
            est_flags[which + 1],
            est_blocks[which + 1],
            frame_block,
            samples.missing_before,
            samples.status,
            columns[: self.n_channels],
            stale,
        )
        sigma = np.where(stale, math.nan, sigmas[which + 1])
        return CompensatedColumns(
            samples.seq, samples.t_s, dtheta, drift, dtheta_comp, angle_raw, angle_comp, temps, flags, sigma
        )


def _resolved(sigma: float, resolved: np.ndarray) -> float:
    """A sigma of ``DriftUncertainty.step`` while deferring: placeholder ``-k`` is ``resolved[k - 1]``."""
    return float(resolved[int(-sigma) - 1]) if sigma < 0 else sigma
