"""One state contract for every streaming stage: ``get_state()`` and ``set_state(state)``.

Each stage runs N inputs once uninterrupted; a second copy runs the first k, its state is taken, and a FRESH
stage restored from it runs the rest: the continuation (and the final state) is the uninterrupted run's, bit for
bit (NaN-aware), for k = 0, the end and points between.  The stage that was saved carries on identically too
(saving changes nothing, and the restored stage shares nothing with it).  Where the daemon persists a state
(the adaptation document, ``adapt_state``) it goes through YAML and JSON on the way.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from fog_driver.compensation.adapt import OnlineReadout
from fog_driver.compensation.adapt_config import AdaptConfig, StaticDetector
from fog_driver.compensation.aflp import AflpFilter, AflpParams
from fog_driver.compensation.blocks import BlockAverager
from fog_driver.compensation.features import FeatureExtractor
from fog_driver.compensation.fitting.data import FitConfig
from fog_driver.compensation.model import MODEL_KINDS, ModelFile
from fog_driver.compensation.pipeline import CompensatedColumns, Compensator
from fog_driver.compensation.readout import AdaptiveLaw, AdaptiveLawParams
from fog_driver.compensation.reservoir import WaveletReservoir
from fog_driver.compensation.table import CHAIN_KEY, SHAPE_CANDIDATES, TableLaw, learned_part
from fog_driver.compensation.table import law as table_law_module
from fog_driver.compensation.uncertainty import DriftUncertainty
from fog_driver.daemon.config import DEFAULT_MODEL
from fog_driver.dwells import Dwell
from fog_driver.errors import InputFileError
from fog_driver.flags import FLAG_SCALE_FACTOR
from fog_driver.modelfiles import load_model
from fog_driver.offline.fit import fit_model_file
from fog_driver.protocol import decode_file
from fog_driver.samples.stream import SampleBlock, SampleStream

DATA = Path(__file__).resolve().parents[1] / "data"
FRAME_S = 0.1  # the fixtures' frame period
#: adapting settings short enough for the fixtures' 300 s: the bias captured, the law learning, windows closing
ADAPT = AdaptConfig(warmup_s=5.0, bias_capture_s=10.0, static_window_s=5.0, compare_window_s=20.0)


def same(a: Any, b: Any) -> bool:
    """Exact equality of plain values, arrays and states, NaN equal to NaN."""
    if hasattr(a, "to_dict") and not isinstance(a, dict):
        return type(a) is type(b) and same(a.to_dict(), b.to_dict())
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        a, b = np.asarray(a), np.asarray(b)
        if a.shape != b.shape or a.dtype != b.dtype:
            return False
        return bool(np.array_equal(a, b, equal_nan=a.dtype.kind == "f"))
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return isinstance(b, (list, tuple)) and len(a) == len(b) and all(same(x, y) for x, y in zip(a, b))
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    return type(a) is type(b) and a == b


def cuts(n: int) -> list[int]:
    """Where to save: the start, the end, and points between (one of them odd)."""
    return sorted({0, 1, n // 3, (2 * n) // 3 + 1, n - 1, n})


def check_contract(
    make: Callable[[], Any],
    feed: Callable[[Any, Any], Any],
    inputs: Sequence[Any],
    k: int,
    save: Callable[[Any], Any] = lambda s: s.get_state(),
    restore: Callable[[Any, Any], None] = lambda s, state: s.set_state(state),
) -> None:
    """The contract (module docstring) for one stage, saved after ``k`` of ``inputs``."""
    whole = make()
    expected = [feed(whole, x) for x in inputs]
    first = make()
    for x in inputs[:k]:
        feed(first, x)
    state = save(first)
    fresh = make()
    restore(fresh, state)
    assert same([feed(fresh, x) for x in inputs[k:]], expected[k:]), "the restored stage's continuation"
    assert same([feed(first, x) for x in inputs[k:]], expected[k:]), "the saved stage's continuation"
    assert same(save(fresh), save(whole)) and same(save(first), save(whole)), "the final state"


def through_text(state: Any) -> Any:
    """A state through YAML and JSON text, as the daemon writes and a client reads it."""
    return json.loads(json.dumps(yaml.safe_load(yaml.safe_dump(state))))


# -- the inputs ----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def faulty_samples() -> SampleBlock:
    """Frames with thermometer faults and gaps."""
    return SampleStream().run(decode_file(DATA / "sim-faults.bin"))


@pytest.fixture(scope="module")
def samples() -> SampleBlock:
    return SampleStream().run(decode_file(DATA / "sim-short.bin"))


@pytest.fixture(scope="module")
def default_model() -> ModelFile:
    """The shipped model: a WESN with candidate structures and a coil."""
    return load_model(DEFAULT_MODEL)


@pytest.fixture(scope="module")
def block_temps(faulty_samples) -> list[tuple[float, ...]]:
    blocks = BlockAverager(FRAME_S, 1.0).run(faulty_samples)
    return [blocks.block(i).temps_c for i in range(len(blocks))]


def model_inputs(model_file: ModelFile, temps: list[tuple[float, ...]]) -> tuple[list[np.ndarray], list[Any]]:
    """The standardized and the raw inputs of the blocks whose inputs are valid, as the pipeline makes them."""
    features = FeatureExtractor(model_file.features, substitution=model_file.substitution)
    z, raw = [], []
    for t in temps:
        u, _ = features.step(t)
        if not any(v != v for v in u):
            raw.append(list(u))
            z.append(model_file.normalizer.transform(u))
    return z, raw


# -- the stages ----------------------------------------------------------------------------------


def test_aflp_filter_continues_exactly_from_any_sample():
    r = np.random.default_rng(1).normal(0.0, 1.0, 300).cumsum()
    r[[40, 41, 200]] = np.nan
    for k in cuts(len(r)):
        check_contract(lambda: AflpFilter(AflpParams(order=6)), lambda f, x: f.step(x), list(r), k)


def test_feature_extractor_continues_exactly_from_any_block(default_model, block_temps):
    def make() -> FeatureExtractor:
        return FeatureExtractor(default_model.features, substitution=default_model.substitution)

    for k in cuts(len(block_temps)):
        check_contract(make, lambda e, t: e.step(t), block_temps, k)


def test_block_averager_continues_exactly_from_any_frame(faulty_samples):
    frames = [faulty_samples.sample(i) for i in range(len(faulty_samples))]
    for k in cuts(len(frames)):
        check_contract(lambda: BlockAverager(FRAME_S, 1.0), lambda a, s: a.step(s), frames, k)


@pytest.mark.parametrize("kind", sorted(MODEL_KINDS))
def test_each_model_continues_exactly_from_any_block(kind, block_temps):
    model_file, _ = fit_model_file(
        [DATA / "sim-short.bin"], kind=kind, config=FitConfig(warmup_s=30.0), accept_weak=True
    )
    z, _ = model_inputs(model_file, block_temps)

    def make() -> Any:
        model = MODEL_KINDS[kind].from_dict(model_file.model.to_dict())
        model.start(z[0])
        return model

    def feed(model: Any, zi: np.ndarray) -> tuple[float, float]:
        y = model.step(zi)
        model.feed_back(y + 0.01)  # the estimate used differs from the model's own (adapting)
        return y, float(model.regressors_step(zi) @ model.weights)

    for k in cuts(len(z)):
        check_contract(make, feed, z, k)


def test_reservoir_continues_exactly_from_any_sample(default_model):
    params = default_model.model.reservoir.params
    u = np.random.default_rng(2).normal(0.0, 1.0, (200, params.n_inputs))
    for k in cuts(len(u)):
        check_contract(lambda: WaveletReservoir(params), lambda r, ui: r.step(ui).copy(), list(u), k)


def test_adaptive_law_continues_exactly_from_any_sample():
    rng = np.random.default_rng(3)
    x = rng.normal(0.0, 1.0, (300, 5))
    d = x @ rng.normal(0.0, 1.0, 5) + rng.normal(0.0, 0.1, 300)
    d[17] = np.nan
    rows = list(zip(x, d.tolist(), (rng.random(300) < 0.7).tolist()))
    params = AdaptiveLawParams(filter_time_s=2.0, memory_time_s=50.0, sigma=0.01)

    def feed(law: AdaptiveLaw, row: tuple[np.ndarray, float, bool]) -> float:
        xi, di, learn = row
        y = law.predict(xi)
        law.learn(xi, di) if learn else law.track(xi, di)
        return y

    for k in cuts(len(rows)):
        check_contract(lambda: AdaptiveLaw(params, 5), feed, rows, k)


def test_online_readout_continues_exactly_from_any_block_and_through_text():
    rng = np.random.default_rng(4)
    w0, b0 = np.array([0.5, -0.2, 0.1]), 0.3
    f = rng.normal(0.0, 1.0, (400, 3))
    measured = f @ (w0 + 0.05) + b0 + 7.0 + rng.normal(0.0, 0.05, 400)  # a bias to capture, a drift to learn
    rows = list(zip(f, measured.tolist(), (rng.random(400) < 0.9).tolist()))
    rows[250] = (f[250], 1e6, True)  # the gate refuses a move

    def feed(readout: OnlineReadout, row: tuple[np.ndarray, float, bool]) -> tuple[float, int]:
        return readout.step(row[0], row[1], 0.0, row[2])

    for k in cuts(len(rows)):
        check_contract(lambda: OnlineReadout(w0, b0, ADAPT, 1.0), feed, rows, k)
        check_contract(
            lambda: OnlineReadout(w0, b0, ADAPT, 1.0),
            feed,
            rows,
            k,
            save=lambda r: through_text(r.get_state()),
        )
    readout = OnlineReadout(w0, b0, ADAPT, 1.0)
    for row in rows:
        feed(readout, row)
    assert readout.updates and readout.rejected and readout.compare_windows  # every part of the state was used


def test_static_detector_continues_exactly_from_any_block():
    rates = np.random.default_rng(5).normal(0.0, 5.0, 200)
    rates[[60, 61, 130]] = [200.0, np.nan, -90.0]
    for k in cuts(len(rates)):
        check_contract(lambda: StaticDetector(30.0, 7), lambda s, r: s.step(r), rates.tolist(), k)


def test_uncertainty_continues_exactly_from_any_block(default_model, block_temps):
    z, raw = model_inputs(default_model, block_temps)
    rows = list(zip(z, raw, np.linspace(-0.5, 0.5, len(z)).tolist()))

    def make() -> DriftUncertainty:
        u = DriftUncertainty(default_model.sigma_spec, default_model.candidate_models(), default_model.domain)
        u.start(z[0])
        return u

    for k in cuts(len(rows)):
        check_contract(make, lambda u, row: u.step(*row), rows, k)


# -- the table law -------------------------------------------------------------------------------

#: dwells of the table standing still at 0 deg in the fixture's 300 s
DWELLS = [Dwell(t, t + 25.0, 0.0) for t in (10.0, 45.0, 80.0, 115.0, 150.0, 185.0, 220.0, 255.0)]


def table_calls(
    model_file: ModelFile, samples: SampleBlock, dwells: list[Dwell]
) -> tuple[list[tuple[str, tuple]], dict]:
    """Every call the pipeline makes to its table law over ``samples`` with ``dwells``, and the law's settings."""
    comp = Compensator(model_file, FRAME_S, adapt=ADAPT, table=True)
    law = comp.table
    assert law is not None
    calls: list[tuple[str, tuple]] = []
    for name in ("estimate", "block", "observe"):
        method = getattr(law, name)

        def recording(*args: Any, _method: Callable = method, _name: str = name) -> Any:
            calls.append((_name, tuple(np.array(a) if isinstance(a, np.ndarray) else a for a in args)))
            return _method(*args)

        setattr(law, name, recording)
    comp.add_dwells(dwells)
    comp.run(samples)
    settings = dict(
        frozen_weights=law.w0,
        frozen_intercept=law.b0,
        block_s=law.block_s,
        config=law.config,
        fit_residual_dph=model_file.fit_residual_dph,
        coil=law.coil,
        shape=law.shape,
        n_shape=law.n_features if law.shape == SHAPE_CANDIDATES else None,
    )
    return calls, settings


#: ``DWELLS`` with wrong angles: the fifth and sixth dwell lie by 18 arcsec (two intervals rejected in a row: the
#: chain starts again from the sixth); or the fifth by 18 arcsec, the sixth by 9 (learned, and blamed by its
#: neighbours two dwells later: undone, ``table.judge``)
LYING_DWELLS = {
    "two lies in a row": [*DWELLS[:4], Dwell(150.0, 175.0, 0.005), Dwell(185.0, 210.0, 0.005), *DWELLS[6:]],
    "a lie blamed later": [*DWELLS[:4], Dwell(150.0, 175.0, 0.005), Dwell(185.0, 210.0, 0.0025), *DWELLS[6:]],
}
DWELLS_WITH_A_LIE = LYING_DWELLS["two lies in a row"]
#: device times to save at (s): inside the first dwell (before the chain's anchor), between the first two (the
#: anchor held, the bias captured next), inside the third (the bias captured, learning), between the first lie
#: and the next dwell (the interval rejected held for the judge, a guard flag pending), inside that dwell, and
#: just after it and the next (the intervals the judge may still undo held)
CHAIN_TIMES_S = (20.0, 40.0, 95.0, 175.2, 180.0, 190.0, 210.3, 215.0)


@pytest.mark.parametrize("lies", sorted(LYING_DWELLS))
def test_table_law_restored_continues_exactly_inside_and_between_dwells(default_model, samples, lies):
    """The table law's state is what it learned and its chain (the ring of blocks, the anchor, the bias capture,
    the intervals the judge may undo, the outcomes): a fresh law restored from it, through text, continues as
    the uninterrupted one, call for call, to the same final state, saved anywhere: inside a dwell, between two
    dwells of a chain, while an interval rejected waits for the judge."""
    calls, settings = table_calls(default_model, samples, LYING_DWELLS[lies])
    rw = settings.pop("frozen_weights"), settings.pop("frozen_intercept"), settings.pop("block_s")

    def make() -> TableLaw:
        return TableLaw(*rw, **settings)

    def feed(law: TableLaw, call: tuple[str, tuple]) -> Any:
        name, args = call
        return getattr(law, name)(*args)

    def at(t_s: float) -> int:
        """The call before which to save: the first call of the first block that ends after ``t_s``."""
        starts = [i for i, (name, _) in enumerate(calls) if name == "estimate"]
        blocks = [args[0] for name, args in calls if name == "block"]
        return next(i for i, index in zip(starts, blocks) if (index + 1) * rw[2] > t_s)

    chains = []
    for k in sorted({*cuts(len(calls)), *(at(t) for t in CHAIN_TIMES_S), at(95.0) + 1}):
        check_contract(make, feed, calls, k, save=lambda law: through_text(law.get_state()))
        chains.append(make_and_feed(make, calls[:k]).get_state()["chain"])
    held = [c for c in chains if c["anchor"] is not None]
    assert any(c["bias"]["bias_dph"] is None for c in held)  # saved while the bias was captured
    assert any(c["bias"]["bias_dph"] is not None and c["window"]["middles"] for c in held)  # and while learning
    assert any(c["doubted"] is not None and c["learned"] is not None for c in chains)  # and before the judge
    assert any(c["rejections_in_row"] and c["flag_pending"] for c in chains)  # and just after a rejection
    statuses = [str(o.status) for o in make_and_feed(make, calls).outcomes]
    assert statuses.count("learned") >= 3 and statuses.count("rejected") >= 2


def make_and_feed(make: Callable[[], TableLaw], calls: list[tuple[str, tuple]]) -> TableLaw:
    law = make()
    for name, args in calls:
        getattr(law, name)(*args)
    return law


# -- the pipeline --------------------------------------------------------------------------------


def columns_of(out: CompensatedColumns) -> list[np.ndarray]:
    return [getattr(out, f) for f in CompensatedColumns.__dataclass_fields__]


def slice_block(s: SampleBlock, lo: int, hi: int) -> SampleBlock:
    return SampleBlock(*(getattr(s, f)[lo:hi] for f in SampleBlock.__dataclass_fields__))


def check_pipeline(make: Callable[[], Compensator], samples: SampleBlock, k: int, adapting: bool) -> None:
    """The pipeline's contract: ``get_state`` at frame ``k`` (through text, as a file keeps it) and ``set_state``
    into a fresh compensator carry the run on exactly: the open block, the model, the angles, and when adapting
    the readout and the static detector; the adaptation document then matches the uninterrupted run's too."""
    n = len(samples)
    whole = make()
    expected = whole.run(samples)
    first = make()
    first.run(slice_block(samples, 0, k))
    state = through_text(first.get_state())
    fresh = make()
    fresh.set_state(state)
    rest = fresh.run(slice_block(samples, k, n))
    for got, want in zip(columns_of(rest), columns_of(expected)):
        assert same(got, want[k:])
    assert same(fresh.get_state(), whole.get_state())
    if adapting:
        assert same(fresh.adaptation_document(), whole.adaptation_document())


@pytest.mark.parametrize("kind", ["polynomial", "wesn"])
def test_frozen_pipeline_continues_exactly_from_any_frame(kind, faulty_samples):
    model_file, _ = fit_model_file(
        [DATA / "sim-short.bin"], kind=kind, config=FitConfig(warmup_s=30.0), accept_weak=True
    )
    for k in cuts(len(faulty_samples)):
        check_pipeline(lambda: Compensator(model_file, FRAME_S), faulty_samples, k, adapting=False)


def test_rate_adapting_pipeline_continues_exactly_from_any_frame(default_model, samples):
    def make() -> Compensator:
        return Compensator(default_model, FRAME_S, adapt=ADAPT, reference_rate_dph=0.0)

    assert make().run(samples).flags.any()
    for k in cuts(len(samples)):
        check_pipeline(make, samples, k, adapting=True)


def test_table_adapting_pipeline_continues_exactly_from_any_frame_before_a_dwell(default_model, samples):
    """Adapting from table angles, the law recording every block and no dwell given yet: the pipeline's state,
    the readout's and what the law learned carry the run on exactly."""

    def make() -> Compensator:
        return Compensator(dataclasses.replace(default_model), FRAME_S, adapt=ADAPT, table=True)

    for k in cuts(len(samples)):
        check_pipeline(make, samples, k, adapting=True)


@pytest.mark.parametrize(
    ("lies", "scale_factor"),
    [("two lies in a row", False), ("a lie blamed later", False), ("a lie blamed later", True)],
)
def test_table_adapting_pipeline_engaged_continues_exactly_inside_and_between_dwells(
    default_model, samples, lies, scale_factor, monkeypatch
):
    """Adapting from table angles with dwells given (some of them lies): restored into a fresh pipeline (the
    readout through the adaptation document, the pipeline's state with its table path: the law, its chain, the
    dwells still waiting, the scale factor held), through text, the run carries on as the uninterrupted one bit
    for bit, saved inside a dwell, between two dwells of a chain and anywhere else.  ``scale_factor``: the scale
    factor corrects the angle from the first interval learned (the fixture's table never turns: its threshold
    raised)."""
    if scale_factor:
        monkeypatch.setattr(table_law_module, "SF_APPLY_SIGMA_PPM", 1e9)
    n = len(samples)

    def make() -> Compensator:
        c = Compensator(default_model, FRAME_S, adapt=ADAPT, table=True)
        c.add_dwells(LYING_DWELLS[lies])
        return c

    whole = make()
    expected = whole.run(samples)
    for k in sorted({*cuts(n), *(int(round(t / FRAME_S)) for t in CHAIN_TIMES_S)}):
        first = make()
        first.run(slice_block(samples, 0, k))
        doc, state = through_text(first.adaptation_document()), through_text(first.get_state())
        fresh = Compensator(default_model, FRAME_S, adapt=ADAPT, table=True)
        fresh.restore_adaptation(doc, "the document", new_run=False)  # the readout (the law's learning as a new run)
        fresh.set_state(state)  # then the pipeline and the table path whole
        fresh.angle_raw_arcsec, fresh.angle_comp_arcsec = first.angle_raw_arcsec, first.angle_comp_arcsec
        rest = fresh.run(slice_block(samples, k, n))
        for got, want in zip(columns_of(rest), columns_of(expected)):
            assert same(got, want[k:])
        assert same(fresh.get_state(), whole.get_state())
        assert same(fresh.adaptation_document(), whole.adaptation_document())
    statuses = [str(o.status) for o in whole.table_outcomes]
    assert statuses.count("learned") >= 3 and statuses.count("rejected") >= 2  # it learned, and rejected the lies
    assert (expected.flags & FLAG_SCALE_FACTOR).any() == scale_factor


def test_the_adaptation_document_keeps_what_the_table_law_learned_and_a_chain_in_it_is_refused(default_model, samples):
    """The state file is what the law learned, as before (``learned_part``: no chain, no table path in the
    pipeline's part); reading it is a new run, and a document carrying a chain anyway is refused, nothing
    changed."""

    def make() -> Compensator:
        return Compensator(default_model, FRAME_S, adapt=ADAPT, table=True)

    saved = make()
    saved.add_dwells(DWELLS_WITH_A_LIE)
    saved.run(slice_block(samples, 0, int(round(180.0 / FRAME_S))))
    doc, state = through_text(saved.adaptation_document()), through_text(saved.get_state())
    assert CHAIN_KEY not in doc["table"] and not {"table", "angles", "readout"} & set(doc["pipeline"])
    assert same(doc["table"], learned_part(state["table"]["law"]))
    assert state["table"]["law"][CHAIN_KEY]["anchor"] is not None and state["table"]["dwells"]
    restored = make()
    restored.restore_adaptation(doc, "state.yaml", new_run=False)
    assert restored.table is not None and restored.table.accepted == saved.table.accepted
    assert restored.table.anchor is None and restored.table.bias_dph is None  # a new chain, the bias captured again
    for part, extra in (
        ("table", {CHAIN_KEY: state["table"]["law"][CHAIN_KEY]}),
        ("pipeline", {"table": state["table"]}),
    ):
        refused = make()
        before = refused.get_state()
        with pytest.raises(InputFileError, match="corrupt adaptation state"):
            refused.restore_adaptation({**doc, part: {**doc[part], **extra}}, "state.yaml", new_run=False)
        assert same(refused.get_state(), before)


def test_a_table_law_state_with_a_broken_chain_is_refused_and_changes_nothing(default_model, samples):
    comp = Compensator(default_model, FRAME_S, adapt=ADAPT, table=True)
    comp.add_dwells(DWELLS_WITH_A_LIE)
    comp.run(slice_block(samples, 0, int(round(180.0 / FRAME_S))))
    assert comp.table is not None
    state = through_text(comp.table.get_state())
    chain = state[CHAIN_KEY]
    broken = [
        {**chain, "anchor": len(chain["anchors"])},  # no such anchor
        {**chain, "window": {**chain["window"], "rates": chain["window"]["rates"][1:]}},  # rows without rates
        {**chain, "coil_c": [*chain["coil_c"], 20.0]},  # another coil's
        {k: v for k, v in chain.items() if k != "doubted"},  # a field missing
        {**chain, "outcomes": {**chain["outcomes"], "recent": [["x"]]}},  # not an outcome
    ]
    for bad in broken:
        law = comp.table
        before = law.get_state()
        with pytest.raises(ValueError, match="table law state"):
            law.set_state({**state, CHAIN_KEY: bad})
        assert same(law.get_state(), before)
    comp.table.set_state(state)  # and the state itself is taken
    assert same(comp.table.get_state(), state)
