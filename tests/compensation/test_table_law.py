"""Adapting from the table's angles (``compensation.table``): the law against the simulator's truth, its
safety (a lie, a late angle, motion, order, wrapped and ambiguous angles, gaps), step == run, and the CLI."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from fog_driver.cli.app import main
from fog_driver.compensation.dwell import angle_at_deg, blocks_within, reference_deg, trimmed_window
from fog_driver.compensation.pipeline import Compensator
from fog_driver.compensation.table import SF_REF_C, TableLaw, TableOutcome, learned_part
from fog_driver.daemon.config import DEFAULT_MODEL
from fog_driver.dwells import Dwell, read_table_log
from fog_driver.flags import FLAG_ADAPTING, FLAG_GUARD, FLAG_SCALE_FACTOR
from fog_driver.lab.profiles import parse_profile
from fog_driver.modelfiles import load_model
from fog_driver.protocol import decode_file
from fog_driver.samples.stream import SampleBlock, SampleStream
from fog_driver.sim.capture import read_truth, simulate_to_file, truth_noise_dph
from fog_driver.sim.instrument import InstrumentConfig, Simulator
from fog_driver.sim.tablelog import late, lie

S0_PPM, S1_PPM_PER_C = 40.0, 0.5
RATE_HZ = 5
PROFILE = {
    "name": "table-law-test",
    "start_c": 20,
    "segments": [
        {"hold": {"duration_min": 20}},
        {"ramp": {"rate_c_per_min": 1, "target_c": 40}},
        {"hold": {"duration_min": 30}},
        {"ramp": {"rate_c_per_min": 1, "target_c": 5}},
        {"hold": {"duration_min": 30}},
    ],
    "motion": {
        "kind": "positioning",
        "start_s": 300,
        "moves": 58,
        "step_deg": [36, 90, -36, 180, -90, 10, -180, -10],
        "dwell_s": 120,
    },
}


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A 135-min run of an instrument with a 40-ppm, 0.5-ppm/degC scale-factor error, the table dwelling 120 s
    between moves of both signs and several sizes; its samples, table log and truth."""
    out = tmp_path_factory.mktemp("table") / "run.bin"
    base = InstrumentConfig()
    config = dataclasses.replace(
        base,
        gyro=dataclasses.replace(base.gyro, scale_factor_ppm=S0_PPM, scale_factor_ppm_per_c=S1_PPM_PER_C),
    )
    samples, dwells, truth = simulate_run(config, 11, out)
    return samples, dwells, truth, config, out


def simulate_run(config: InstrumentConfig, seed: int, out: Path) -> tuple[SampleBlock, list[Dwell], dict]:
    """``PROFILE`` simulated for ``config`` into ``out``: its samples, table log (as dwells) and truth."""
    simulate_to_file(Simulator(parse_profile(PROFILE), config, rate_hz=RATE_HZ, seed=seed), out)
    samples = SampleStream().run(decode_file(out))
    dwells = read_table_log(out.with_suffix(".table.csv"))
    return samples, dwells, read_truth(out.with_suffix(".truth.csv"))


def rate_and_gradient_drift_scaled(config: InstrumentConfig, factor: float) -> InstrumentConfig:
    """``config`` with its temperature-rate (Shupe) and gradient drifts ``factor`` times: the model made for the
    default instrument is off for it."""
    gyro = config.gyro
    return dataclasses.replace(
        config,
        gyro=dataclasses.replace(
            gyro,
            shupe_dph_per_c_per_min=factor * gyro.shupe_dph_per_c_per_min,
            gradient_dph_per_c=factor * gyro.gradient_dph_per_c,
        ),
    )


def first(samples: SampleBlock, dwells: list[Dwell], seconds: float) -> tuple[SampleBlock, list[Dwell]]:
    """The run's first ``seconds`` and the dwells that end within them."""
    n = int(np.searchsorted(samples.t_s - samples.t_s[0], seconds))
    return samples.take(slice(0, n)), [d for d in dwells if d.t_end_s < seconds]


def compensate(samples: SampleBlock, dwells: list[Dwell], model_file=None) -> tuple[Compensator, object]:
    comp = Compensator(model_file or load_model(DEFAULT_MODEL), 1.0 / RATE_HZ, table=True)
    comp.add_dwells(dwells)
    return comp, comp.run(samples)


def without_candidates():
    """The default model file without its candidate structures (as a polynomial or an older file has none)."""
    return dataclasses.replace(load_model(DEFAULT_MODEL), uncertainty=None)


def test_the_lying_and_late_logs_against_the_simulators_truth(run):
    """``sim.tablelog``: one dwell off the simulator's true angle by exactly the lie (start and end angles under a
    creep alike), one ending late; the rest of the log the truth, untouched."""
    *_, out = run
    truth = read_table_log(out.with_suffix(".table.csv"))
    lied = lie(truth, 7, 0.01)
    assert [d.angle_deg - t.angle_deg for d, t in zip(lied, truth)] == [0.0] * 7 + [
        lied[7].angle_deg - truth[7].angle_deg
    ] + [0.0] * (len(truth) - 8)
    assert lied[7].angle_deg - truth[7].angle_deg == pytest.approx(0.01, abs=1e-12)
    crept = lie([Dwell(0.0, 60.0, 36.0, 36.001)], 0, -0.5)[0]
    assert (crept.angle_deg, crept.angle_end_deg) == (35.5, pytest.approx(35.501))
    delayed = late(truth, 3, 2.0)
    assert delayed[3].t_end_s == truth[3].t_end_s + 2.0 and delayed[3].angle_deg == truth[3].angle_deg
    assert delayed[:3] == truth[:3] and delayed[4:] == truth[4:]
    with pytest.raises(ValueError, match="dwell 99"):
        lie(truth[:5], 99, 0.01)
    with pytest.raises(ValueError, match="finite"):
        late(truth, 0, math.nan)


def test_the_shared_dwell_definition():
    assert trimmed_window(10.0, 40.0) == (15.0, 35.0)
    with pytest.raises(ValueError, match="not longer than twice"):
        trimmed_window(10.0, 20.0)
    assert blocks_within(15.0, 35.0, 1.0) == (15, 35)
    assert blocks_within(15.2, 34.9, 1.0) == (16, 34)  # whole blocks only
    assert reference_deg(36.0, None) == 36.0
    assert reference_deg(36.0, 36.1) == pytest.approx(36.05)


def test_the_scale_factor_is_found_against_the_simulators_truth(run):
    """Within 5 ppm of the truth at every temperature of the run's plateaus (the coil's true temperature),
    and applied to the angle (flagged) once known."""
    samples, dwells, truth, config, _ = run
    comp, cols = compensate(samples, dwells)
    law = comp.table
    s0, s1 = law.scale_factor_ppm
    for lo, hi in ((900, 1200), (2700, 3000), (6300, 8100)):  # the plateaus at 20, 40 and 5 degC, settled
        fiber = truth["fiber_c"][lo:hi]
        true_ppm = float(np.mean(config.gyro.scale_factor_error(fiber))) * 1e6
        found = s0 + s1 * (float(np.mean(fiber)) - SF_REF_C)
        assert abs(found - true_ppm) < 5.0, (lo, found, true_ppm)
    assert law.scale_factor_applied
    assert cols.flags[-1] & FLAG_SCALE_FACTOR
    counts = {s: sum(o.status == s for o in law.outcomes) for s in ("learned", "rejected", "refused")}
    assert counts["rejected"] == counts["refused"] == 0, law.outcomes
    assert counts["learned"] >= len(dwells) - 4
    # the angle: over a move, the compensated angle takes away s(T) times it (beside the drift), s the truth's
    k = max(range(len(dwells) - 10, len(dwells) - 1), key=lambda i: abs(dwells[i + 1].angle_deg - dwells[i].angle_deg))
    a, b = dwells[k], dwells[k + 1]  # a 180-degree move near the end
    t = cols.t_s - cols.t_s[0]
    sel = (t > a.t_end_s) & (t < b.t_start_s)
    taken = float(np.sum(cols.dtheta_arcsec[sel] - cols.drift_dph[sel] / RATE_HZ - cols.dtheta_comp_arcsec[sel]))
    move = (b.angle_deg - a.angle_deg) * 3600.0
    true_ppm = float(np.mean(config.gyro.scale_factor_error(truth["fiber_c"][int(a.t_end_s) : int(b.t_start_s)])))
    assert abs(true_ppm * move) > 10.0  # a move the scale factor shows in
    assert taken == pytest.approx(true_ppm * move, abs=5e-6 * abs(move))


def drift_error_dph(cols, truth: dict, dwells: list[Dwell], skip_s: float = 1800.0) -> float:
    """The drift estimate's error against the truth as the benchmark scores it: 1-min means of the true drift
    and the gyro's own noise (the floor no estimate goes below) less the estimate, their mean removed, over
    the minutes after ``skip_s`` that hold no table move."""
    t = cols.t_s - cols.t_s[0]
    second = np.floor(t).astype(np.int64)
    n = min(int(second[-1]) + 1, len(truth["drift_dph"]))
    keep = second < n
    estimate = np.bincount(second[keep], weights=cols.drift_dph[keep], minlength=n) / np.maximum(
        np.bincount(second[keep], minlength=n), 1
    )
    moving = np.zeros(n, dtype=bool)
    for a, b in zip(dwells, dwells[1:]):
        moving[int(a.t_end_s) : int(math.ceil(b.t_start_s))] = True
    m = n // 60
    measured = truth["drift_dph"][: m * 60] + truth_noise_dph(truth)[: m * 60]
    error = (measured - estimate[: m * 60]).reshape(m, 60).mean(axis=1)
    scored = ~moving[: m * 60].reshape(m, 60).any(axis=1) & (np.arange(m) * 60 >= skip_s)
    e = error[scored]
    return float(np.sqrt(np.mean((e - e.mean()) ** 2)))


def test_a_right_model_keeps_its_shape_a_wrong_one_is_corrected(run, tmp_path):
    """The weighing of the prior scales, against the simulator's truth: on the instrument the default model
    was made for, the frozen shape keeps most of the weight and the error stays the frozen one's (within 2 %);
    on one whose temperature-rate (Shupe) and gradient drifts are 1.3 times the model's, the weight moves to the
    adapted shapes and the error falls by more than half."""
    samples, dwells, truth, config, _ = run
    frozen = Compensator(load_model(DEFAULT_MODEL), 1.0 / RATE_HZ).run(samples)
    comp, cols = compensate(samples, dwells)
    assert comp.table.frozen_weight > 0.5
    assert drift_error_dph(cols, truth, dwells) <= 1.02 * drift_error_dph(frozen, truth, dwells)

    off = rate_and_gradient_drift_scaled(config, 1.3)
    off_samples, off_dwells, off_truth = simulate_run(off, 12, tmp_path / "off.bin")
    off_frozen = Compensator(load_model(DEFAULT_MODEL), 1.0 / RATE_HZ).run(off_samples)
    off_comp, off_cols = compensate(off_samples, off_dwells)
    assert off_comp.table.frozen_weight < 0.5
    assert drift_error_dph(off_cols, off_truth, off_dwells) < 0.6 * drift_error_dph(off_frozen, off_truth, off_dwells)


def test_a_model_far_off_is_held_at_the_runaway_bound_not_reset(run, tmp_path):
    """An instrument whose temperature-rate and gradient drifts are twice the model's: the correction it needs
    passes the runaway bound.  The drift published stays within the bound of the frozen one, held there and
    flagged ``guard``; the law is not reset, and the error still falls against the truth."""
    samples, dwells, truth, config, _ = run
    far = rate_and_gradient_drift_scaled(config, 2.0)
    far_samples, far_dwells, far_truth = simulate_run(far, 13, tmp_path / "far.bin")
    frozen = Compensator(load_model(DEFAULT_MODEL), 1.0 / RATE_HZ).run(far_samples)
    comp, cols = compensate(far_samples, far_dwells)
    law = comp.table
    assert law.clamped_blocks > 0 and law.guards == 0
    change = cols.drift_dph - frozen.drift_dph
    assert np.nanmax(np.abs(change)) <= law.runaway_dph * (1 + 1e-12)
    held = np.abs(np.abs(change) - law.runaway_dph) < 1e-9
    assert held.any() and (cols.flags[held] & FLAG_GUARD).all()
    assert law.summary()["clamped_blocks"] == law.clamped_blocks
    assert drift_error_dph(cols, far_truth, far_dwells) < 0.8 * drift_error_dph(frozen, far_truth, far_dwells)


def test_the_comparison_guard_publishes_the_frozen_drift_again_when_the_adapted_one_is_worse():
    """The backstop behind the weighing: intervals whose adapted errors are 3 times the frozen ones' put the
    frozen drift back; equal errors do not (no switch on chance)."""
    rng = np.random.default_rng(5)
    verdicts = {}
    for name, adapted_sigma in (("worse", 3.0), ("equal", 1.0), ("better", 0.3)):
        law = TableLaw(np.zeros(4), 0.0, 1.0, fit_residual_dph=0.02)
        law.bias_dph = 0.0  # captured
        for _ in range(60):
            law._add_window(rng.normal(0.0, 0.01), rng.normal(0.0, 0.01 * adapted_sigma))
        verdicts[name] = law.adapted_in_use
    assert verdicts == {"worse": False, "equal": True, "better": True}


@pytest.mark.parametrize("shape", ["candidates", "regressors"])
def test_step_equals_run_with_dwells(run, shape):
    samples, dwells, *_ = run
    part, use = first(samples, dwells, 2400.0)
    model_file = load_model(DEFAULT_MODEL) if shape == "candidates" else without_candidates()
    runner, whole = compensate(part, use, model_file)
    assert runner.table.shape == shape
    stepper = Compensator(model_file, 1.0 / RATE_HZ, table=True)
    stepper.add_dwells(use)
    stepped = [stepper.step(part.sample(i)) for i in range(len(part))]
    assert [repr(whole.sample(i)) for i in range(len(part))] == [repr(s) for s in stepped]
    assert [repr(o) for o in runner.table.outcomes] == [repr(o) for o in stepper.table.outcomes]
    assert sum(o.status == "learned" for o in runner.table.outcomes) >= 8


def test_the_shape_regressors_are_the_candidates_departures_from_the_frozen_drift(run, monkeypatch):
    """With a model file that has candidate structures, the law's shape regressors of each block are the
    candidates' drifts less the frozen one's: checked against each candidate compensating the run as the model
    (frozen, its own compensator), and the frozen drift against the model's."""
    samples, dwells, *_ = run
    part, _ = first(samples, dwells, 1500.0)
    model_file = load_model(DEFAULT_MODEL)
    seen: dict[int, tuple[float, np.ndarray]] = {}
    original = TableLaw.block

    def block(self, index, y_frozen, g, *args):
        seen[index] = (y_frozen, None if g is None else np.array(g))
        return original(self, index, y_frozen, g, *args)

    monkeypatch.setattr(TableLaw, "block", block)
    comp = Compensator(model_file, 1.0 / RATE_HZ, table=True)  # no dwells: the law records, the frozen drift is out
    comp.run(part)
    monkeypatch.undo()
    candidates = model_file.candidate_models()
    assert comp.table.shape == "candidates" and comp.table.n_features == len(candidates) >= 2

    def block_drifts(mf) -> dict[int, float]:
        """The drift each block left (applied from the next block's first frame), by a frozen compensator."""
        cols = Compensator(mf, 1.0 / RATE_HZ).run(part)
        block_s = 1.0 / mf.model_rate_hz
        k = np.floor((cols.t_s - cols.t_s[0]) / block_s + 1e-9).astype(int)
        first_frame = np.r_[True, k[1:] != k[:-1]]
        return {int(b) - 1: float(d) for b, d in zip(k[first_frame], cols.drift_dph[first_frame]) if b >= 1}

    frozen = block_drifts(model_file)
    blocks = sorted(i for i in seen if seen[i][1] is not None and i in frozen)
    assert len(blocks) > 1000
    assert np.array_equal([seen[i][0] for i in blocks], [frozen[i] for i in blocks])
    for c, candidate in enumerate(candidates):
        drift = block_drifts(dataclasses.replace(model_file, model=candidate, uncertainty=None))
        got = np.array([seen[i][1][c] for i in blocks])
        want = np.array([drift[i] - frozen[i] for i in blocks])
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)
    assert np.std([seen[i][1] for i in blocks], axis=0).min() > 1e-4  # the candidates do depart


def test_the_drift_in_use_is_the_frozen_one_and_the_shapes_change_not_the_level():
    """``D_hat + g . dw``: the level db is the bias's, learned but not published."""
    law = TableLaw(np.zeros(11), 0.0, 1.0, fit_residual_dph=0.02, shape="candidates", n_shape=3)
    law.bias_dph = 0.0  # captured
    law.delta = np.array([0.01, -0.02, 0.005, 0.3, 1.0, 0.1])  # dw, db, s0, s1
    g = np.array([0.5, 0.25, -1.0])
    frozen, in_use, flags = law.estimate(0.7, g)
    assert frozen == 0.7 and in_use == pytest.approx(0.7 + 0.005 - 0.005 - 0.005, abs=1e-15)
    assert flags & FLAG_ADAPTING
    law.delta[3] = math.inf  # a non-finite level still resets the law
    assert law.estimate(0.7, g)[1] == 0.7 and law.guards == 1 and not law.delta.any()


def test_without_candidates_the_law_learns_on_the_models_own_regressors(run):
    samples, dwells, *_ = run
    part, use = first(samples, dwells, 1500.0)
    comp, _ = compensate(part, use, without_candidates())
    assert comp.table.shape == "regressors" and comp.table.n_features == len(comp.model.weights)
    assert comp.table.summary()["shape"] == "regressors"


def _outcome_at(outcomes: list[TableOutcome], dwell: Dwell) -> TableOutcome:
    return next(o for o in outcomes if o.t_end_s == dwell.t_end_s)


def test_a_lie_of_five_sigmas_is_rejected_flagged_and_the_chain_goes_on(run):
    samples, dwells, *_ = run
    comp, _ = compensate(samples, dwells)
    k = 30
    honest = _outcome_at(comp.table.outcomes, dwells[k])
    assert honest.status == "learned"
    lied = lie(dwells, k, 5.0 * honest.sigma_arcsec / 3600.0)
    comp2, cols = compensate(samples, lied)
    assert _outcome_at(comp2.table.outcomes, lied[k]).status == "rejected"
    assert _outcome_at(comp2.table.outcomes, lied[k + 1]).status == "learned"  # from the last good dwell
    assert _outcome_at(comp2.table.outcomes, lied[k - 1]).status == "learned"  # its honest neighbour not blamed
    assert comp2.table.rejected == comp.table.rejected + 1
    t = cols.t_s - cols.t_s[0]
    after = (t > lied[k].t_end_s) & (t < lied[k].t_end_s + 3.0)
    assert (cols.flags[after] & FLAG_GUARD).any()
    assert not (cols.flags[(t > 600) & (t < lied[k].t_end_s)] & FLAG_GUARD).any()


def test_a_lie_its_own_interval_lets_through_is_undone_two_dwells_later(run, monkeypatch):
    """A wrong angle L at dwell k gives innovations +L over (k-1, k) and -L over (k, k+1).  A lie that its own
    interval's gate lets through (the interval's own error the other way) is learned; the next interval is
    rejected; at dwell k+2 the interval (k+1, k+2) agrees, so dwell k, not k+1, was the wrong one: the interval
    learned from it is undone, (k-1, k+1) and (k+1, k+2) learned in its place, dwell k rejected and the estimate
    flagged.  The drift afterwards is the one of the log without dwell k, not the lie's."""
    samples, dwells, *_ = run
    part, use = first(samples, dwells, 3000.0)
    honest, _ = compensate(part, use)
    by_end = {o.t_end_s: o for o in honest.table.outcomes}
    found = []
    for k in range(8, len(use) - 4):
        ok, nxt = by_end.get(use[k].t_end_s), by_end.get(use[k + 1].t_end_s)
        if ok and nxt and ok.status == nxt.status == "learned":
            off = 2.9 * ok.sigma_arcsec + ok.innovation_arcsec  # an angle L too large: its interval's -L
            if nxt.innovation_arcsec + off > 3.5 * nxt.sigma_arcsec:  # passes at -2.9 sigmas, the next's +L not
                found.append((k, off))
    assert found, "the run has no dwell whose interval's own error hides a lie"
    k, off_arcsec = found[0]
    assert off_arcsec > 2.9 * by_end[use[k].t_end_s].sigma_arcsec  # a lie larger than the gate
    lied = lie(use, k, off_arcsec / 3600.0)
    without = use[:k] + use[k + 1 :]
    comp, cols = compensate(part, lied)
    outcome = _outcome_at(comp.table.outcomes, lied[k])
    assert outcome.status == "rejected" and "both neighbours" in outcome.reason, outcome
    assert _outcome_at(comp.table.outcomes, lied[k + 1]).status == "learned"  # as (k-1, k+1)
    assert _outcome_at(comp.table.outcomes, lied[k + 2]).status == "learned"
    assert comp.table.rejected == honest.table.rejected + 1
    assert comp.table.accepted == honest.table.accepted - 1
    t = cols.t_s - cols.t_s[0]
    caught = (t > lied[k + 2].t_end_s) & (t < lied[k + 2].t_end_s + 3.0)
    assert (cols.flags[caught] & FLAG_GUARD).any()
    assert not (cols.flags[(t > 600) & (t < lied[k].t_end_s)] & FLAG_GUARD).any()
    # the drift after it: the log without dwell k's, far from the one learned from the lie
    _, ref = compensate(part, without)
    with monkeypatch.context() as m:
        m.setattr(TableLaw, "_judge_by_neighbours", lambda *a: None)
        kept_lie, fooled = compensate(part, lied)
    assert _outcome_at(kept_lie.table.outcomes, lied[k]).status == "learned"  # the gate alone is fooled
    later = t > lied[k + 2].t_end_s + 1.0
    undone = np.sqrt(np.mean((cols.drift_dph[later] - ref.drift_dph[later]) ** 2))
    learned = np.sqrt(np.mean((fooled.drift_dph[later] - ref.drift_dph[later]) ** 2))
    assert learned > 0 and undone < 0.2 * learned, (undone, learned)
    # step equals run through the undo
    stepper = Compensator(load_model(DEFAULT_MODEL), 1.0 / RATE_HZ, table=True)
    stepper.add_dwells(lied)
    stepped = [stepper.step(part.sample(i)) for i in range(len(part))]
    assert [repr(cols.sample(i)) for i in range(len(part))] == [repr(x) for x in stepped]
    assert [repr(o) for o in comp.table.outcomes] == [repr(o) for o in stepper.table.outcomes]


def test_the_honest_dwell_before_a_lie_is_not_blamed(run):
    """The case that one rejected interval cannot tell from a lie the gate let through: dwell k's own interval
    2 sigmas or more off, then a 5-sigma lie at dwell k+1 against it, so that (k, k+1)'s innovation cancels
    dwell k's to within twice their spreads (the judgement on one rejected interval blamed dwell k here).
    Dwell k+2 settles it: (k+1, k+2) disagrees as much the other way, so dwell k+1 is rejected and dwell k
    stays learned."""
    part, use, *_ = run
    honest, _ = compensate(part, use)
    by_end = {o.t_end_s: o for o in honest.table.outcomes}
    z = {
        k: by_end[use[k].t_end_s].innovation_arcsec / by_end[use[k].t_end_s].sigma_arcsec
        for k in range(8, len(use) - 4)
        if all(by_end.get(use[k + j].t_end_s, TableOutcome(0.0, "")).status == "learned" for j in range(3))
    }
    k = max(z, key=lambda j: abs(z[j]))
    assert abs(z[k]) >= 2.0, z[k]  # off by as much as a lie its gate lets through
    a, nxt = by_end[use[k].t_end_s], by_end[use[k + 1].t_end_s]
    # the lie at k+1 puts (k, k+1)'s innovation at 5 sigmas of it, against dwell k's sign: they nearly cancel
    target = -math.copysign(5.0 * nxt.sigma_arcsec, a.innovation_arcsec)
    off_arcsec = nxt.innovation_arcsec - target  # an angle off_arcsec too large takes it off r
    assert abs(a.innovation_arcsec + target) < 2.0 * math.hypot(a.sigma_arcsec, nxt.sigma_arcsec)
    lied = lie(use, k + 1, off_arcsec / 3600.0)
    comp, _ = compensate(part, lied)
    assert _outcome_at(comp.table.outcomes, lied[k]).status == "learned"
    assert _outcome_at(comp.table.outcomes, lied[k + 1]).status == "rejected"
    assert _outcome_at(comp.table.outcomes, lied[k + 2]).status == "learned"
    assert comp.table.rejected == honest.table.rejected + 1


def assert_rejected(samples: SampleBlock, dwells: list[Dwell], k: int, why: str, **change: float) -> None:
    """Dwell ``k`` changed by ``change`` is rejected, and ``why`` is in the reason."""
    changed = list(dwells)
    changed[k] = dataclasses.replace(dwells[k], **change)
    comp, _ = compensate(samples, changed)
    outcome = _outcome_at(comp.table.outcomes, changed[k])
    assert outcome.status == "rejected" and why in outcome.reason, outcome


def creeping_run(out: Path, rate_dph: float, start_s: float, seed: int) -> tuple[SampleBlock, list[Dwell]]:
    """``PROFILE`` with the table creeping at ``rate_dph`` from ``start_s`` to the run's end (not beyond: the
    simulator runs to it), simulated for the default instrument into ``out``: its samples and table log."""
    end_s = parse_profile(PROFILE).chamber.duration_s
    creep = {"kind": "creep", "rate_dph": rate_dph, "start_s": start_s, "stop_s": end_s}
    profile = {**PROFILE, "motion": [PROFILE["motion"], creep]}
    simulate_to_file(Simulator(parse_profile(profile), InstrumentConfig(), rate_hz=RATE_HZ, seed=seed), out)
    return SampleStream().run(decode_file(out)), read_table_log(out.with_suffix(".table.csv"))


def claimed_creep(dwells: list[Dwell], deg: float, every: int = 1, from_k: int = 0) -> list[Dwell]:
    """The log ``attack-round-3`` lied with: every dwell declares a creep (``angle_end_deg``), ``deg`` degrees at
    every ``every``-th dwell from ``from_k`` on, none at the others (``angle_end_deg = angle_deg``), the table
    truly still in all of them."""
    lied = {k for k in range(from_k, len(dwells), every)}
    return [
        dataclasses.replace(d, angle_end_deg=d.angle_deg + (deg if k in lied else 0.0)) for k, d in enumerate(dwells)
    ]


def creep_rejections(outcomes: list[TableOutcome]) -> list[TableOutcome]:
    return [o for o in outcomes if o.status == "rejected" and "the creep it declares" in o.reason]


@pytest.mark.parametrize("deg", [2.0, 5.0])
def test_a_table_log_claiming_a_creep_the_gyro_never_saw_teaches_the_law_nothing(run, deg):
    """Every dwell of the log declares that the table crept ``deg`` degrees while it stood still: the dwells'
    mean angles are all off by the same ``deg / 2``, so the intervals between them agree with the gyro, and the
    law learned from them (5 degrees: a scale factor of +11.4 ppm applied where the truthful log gives +0.4).
    The gyro's rate within each dwell says the table stood: from the first interval on (the bias it is judged
    against) every dwell is rejected, at thousands of sigma; nothing is learned, the scale factor is not
    applied and the drift published is the frozen model's."""
    samples, dwells, *_ = run
    lying = claimed_creep(dwells, deg)
    comp, cols = compensate(samples, lying)
    outcomes = list(comp.table.outcomes)
    assert [o.status for o in outcomes[:2]] == ["anchor", "bias"]  # no bias yet to judge the first two by
    assert creep_rejections(outcomes) == outcomes[2:] and len(outcomes) == len(dwells)
    z = [o.innovation_arcsec / o.sigma_arcsec for o in outcomes[2:]]
    assert min(z) < -100.0 and max(z) < -100.0  # the gyro saw less than the creep declared, by far
    assert all(f"{abs(o.innovation_arcsec) / o.sigma_arcsec:.1f} sigma" in o.reason for o in outcomes[2:])
    assert comp.table.accepted == 0 and not comp.table.scale_factor_applied and comp.table.bias_dph is None
    frozen = Compensator(load_model(DEFAULT_MODEL), 1.0 / RATE_HZ).run(samples)
    assert np.array_equal(cols.drift_dph, frozen.drift_dph, equal_nan=True) and np.array_equal(
        cols.angle_comp_arcsec, frozen.angle_comp_arcsec
    )


@pytest.mark.parametrize("deg", [2.0, 5.0])
def test_a_table_log_lying_about_every_other_dwells_creep_keeps_the_truthful_scale_factor(run, deg):
    """From dwell 6 on every other dwell declares a creep of ``deg`` degrees the gyro never saw, the others none
    (as the truth): exactly the lying dwells are rejected for it, the chain goes on from the honest ones, and the
    scale factor found is within the truthful log's interval (its value +- 2 sigma) and applied."""
    samples, dwells, *_ = run
    truthful, _ = compensate(samples, claimed_creep(dwells, 0.0))
    lying = claimed_creep(dwells, deg, every=2, from_k=6)
    comp, _ = compensate(samples, lying)
    rejected = [k for k, o in enumerate(comp.table.outcomes) if o.status == "rejected"]
    assert rejected == list(range(6, len(dwells), 2))
    assert len(creep_rejections(list(comp.table.outcomes))) == len(rejected)
    assert comp.table.accepted >= len(rejected) - 2
    s0, s0_truthful = comp.table.summary(), truthful.table.summary()
    assert s0_truthful["scale_factor_applied"] and s0["scale_factor_applied"]
    assert abs(s0["scale_factor_ppm"] - s0_truthful["scale_factor_ppm"]) < 2.0 * s0_truthful["scale_factor_sigma_ppm"]
    assert abs(s0["scale_factor_ppm_per_c"] - s0_truthful["scale_factor_ppm_per_c"]) < 0.2


def live_outcomes(run, dwells: list[Dwell]) -> list[TableOutcome]:
    """``dwells`` sent as ``?TABLE`` at each one's end (``angle_start_deg`` its declared start), the capture's
    bytes fed to the daemon as the port gives them: the law's outcomes."""
    from fog_driver.daemon.config import DriverConfig
    from fog_driver.daemon.service import Service

    samples, _, _, _, capture = run
    data = capture.read_bytes()
    t = samples.t_s - samples.t_s[0]
    service = Service(DriverConfig(), port="unused")
    fed = 0
    for d in dwells:
        i = int(np.searchsorted(t, d.t_end_s))  # the first frame after the dwell: the angle is sent then
        end = int(samples.offset[i]) if i < len(samples) else len(data)
        service.process(data[fed:end])
        fed = end
        args = {"angle_deg": d.angle_end_deg, "dwell_s": d.t_end_s - d.t_start_s, "angle_start_deg": d.angle_deg}
        assert service.control("TABLE", args, 0)["class"] == "TABLE"
    service.process(data[fed:])
    return service.compensator.table_outcomes


def test_the_same_claimed_creep_log_is_judged_alike_live_and_offline(run):
    """The claimed-creep log of every other dwell, offline (``compensate --table-log``'s law) and live
    (``?TABLE`` with ``angle_start_deg``): each dwell's outcome and its reason's kind are the same, the lying
    dwells rejected for their creep in both."""
    from fog_driver.compensation.table import reason_kind

    samples, dwells, *_ = run
    lying = claimed_creep(dwells, 5.0, every=2, from_k=6)
    offline, _ = compensate(samples, lying)
    live = live_outcomes(run, lying)
    assert [(o.status, reason_kind(o.reason)) for o in live] == [
        (o.status, reason_kind(o.reason)) for o in offline.table.outcomes
    ]
    assert len(creep_rejections(live)) == len(range(6, len(dwells), 2))


def test_a_creep_that_begins_within_a_dwell_is_rejected_there_and_only_there(run, tmp_path):
    """A table that begins to creep (2 deg/h) in the middle of a dwell: the log gives the dwell's start and end
    angles, whose mean is not the table's mean angle over it (off by tens of arcseconds, which the innovation
    gate can let through when the weighing has widened the innovation's spread).  The gyro sees the
    rate step within the dwell: that dwell is rejected, the steady creep's dwells after it are learned; no
    dwell of the run without the creep is rejected by the steadiness test."""
    samples, dwells, *_ = run
    k = 20
    start_s = 0.5 * (dwells[k].t_start_s + dwells[k].t_end_s)
    creeping, log = creeping_run(tmp_path / "creep.bin", 2.0, start_s, seed=11)
    assert log[k].angle_end_deg is not None and log[k].angle_end_deg != log[k].angle_deg
    comp, _ = compensate(creeping, log)
    unsteady = [i for i, o in enumerate(comp.table.outcomes) if "rate changed" in o.reason]
    assert unsteady == [k]
    assert all(o.status == "learned" for o in list(comp.table.outcomes)[k + 2 :])
    plain, _ = compensate(samples, dwells)
    assert not any("rate changed" in o.reason for o in plain.table.outcomes)


def test_a_fast_creep_is_learned_against_the_tables_angle_at_the_windows_mean_time(tmp_path, monkeypatch):
    """A table creeping at 20 deg/h (20 arcsec/s) all through the dwells: the gyro's angle at a dwell is the mean
    over the whole blocks of its trimmed window, whose mean time is not the dwell's middle; the table's angle is
    taken at that time (``dwell.angle_at_deg``).  Every dwell is learned, and the innovations are the noise's;
    with the mean of the start and end angles instead (the dwell's middle) they are tens of arcseconds off."""
    creeping, log = creeping_run(tmp_path / "creep20.bin", 20.0, 0.0, seed=12)
    assert all(d.angle_end_deg is not None and d.angle_end_deg - d.angle_deg > 0.6 for d in log)  # 120 s at 20 deg/h
    comp, _ = compensate(creeping, log)
    learned = [o for o in comp.table.outcomes if o.status == "learned"]
    assert len(learned) >= 0.9 * len(log) and comp.table.rejected <= 1
    z = np.array([o.innovation_arcsec / o.sigma_arcsec for o in learned])
    assert np.sqrt(np.mean(z**2)) < 1.5, z
    import fog_driver.compensation.table.law as table_law
    import fog_driver.compensation.table.screen as table_screen

    for module in (table_law, table_screen):  # the anchor's angle, and the creep a dwell declares
        monkeypatch.setattr(module, "angle_at_deg", lambda a, e, t0, t1, t: reference_deg(a, e))
    middle, _ = compensate(creeping, log)
    rms = np.sqrt(np.mean(np.array([o.innovation_arcsec for o in learned]) ** 2))
    off = np.array([o.innovation_arcsec for o in middle.table.outcomes if math.isfinite(o.innovation_arcsec)])
    assert np.sqrt(np.mean(off**2)) > 2.0 * rms, (off, rms)


def test_the_tables_angle_at_a_time_within_a_dwell():
    assert angle_at_deg(36.0, None, 100.0, 220.0, 150.0) == 36.0
    assert angle_at_deg(36.0, 37.2, 100.0, 220.0, 100.0) == 36.0
    assert angle_at_deg(36.0, 37.2, 100.0, 220.0, 220.0) == pytest.approx(37.2)
    assert angle_at_deg(36.0, 37.2, 100.0, 220.0, 130.0) == pytest.approx(36.3)
    assert angle_at_deg(36.0, 37.2, 100.0, 220.0, 160.0) == pytest.approx(reference_deg(36.0, 37.2))


def test_an_angle_sent_late_is_rejected_the_gyro_sees_the_move(run):
    samples, dwells, *_ = run
    sent_late = late(dwells, 20, 2.0)
    comp, _ = compensate(samples, sent_late)
    outcome = _outcome_at(comp.table.outcomes, sent_late[20])
    assert outcome.status == "rejected" and "motion" in outcome.reason, outcome


def test_wrapped_angles_give_the_same_outcomes_and_an_ambiguous_one_is_rejected(run):
    samples, dwells, *_ = run
    part, use = first(samples, dwells, 3000.0)
    cumulative, _ = compensate(part, use)
    wrapped, _ = compensate(part, [dataclasses.replace(d, angle_deg=d.angle_deg % 360.0) for d in use])
    assert [(o.status, o.innovation_arcsec) for o in cumulative.table.outcomes] == [
        (o.status, o.innovation_arcsec) for o in wrapped.table.outcomes
    ]
    assert_rejected(part, use, 10, "ambiguous", angle_deg=use[10].angle_deg + 180.0)


def test_dwells_out_of_order_are_refused(run):
    samples, dwells, *_ = run
    part, use = first(samples, dwells, 1500.0)
    overlapping = Dwell(use[3].t_start_s - 30.0, use[3].t_start_s + 20.0, use[2].angle_deg)
    comp = Compensator(load_model(DEFAULT_MODEL), 1.0 / RATE_HZ, table=True)
    comp.add_dwells([*use[:3], overlapping])
    comp.run(part)
    assert comp.table.outcomes[-1].status == "refused"
    assert "out of time order" in comp.table.outcomes[-1].reason


def test_a_link_gap_breaks_the_chain(run):
    samples, dwells, *_ = run
    t = samples.t_s - samples.t_s[0]
    d = dwells[8]
    lo, hi = d.t_end_s + 1.0, d.t_end_s + 4.0  # frames lost during the move after dwell 8
    keep = np.flatnonzero((t < 3000.0) & ((t < lo) | (t >= hi)))
    cut = SampleBlock(*(getattr(samples, f)[keep] for f in SampleBlock.__dataclass_fields__))
    comp, _ = compensate(cut, [x for x in dwells if x.t_end_s < 3000.0])
    assert _outcome_at(comp.table.outcomes, dwells[9]).status == "anchor"  # not learned across the gap
    later = [o.status for o in comp.table.outcomes if o.t_end_s > dwells[9].t_end_s]
    assert "learned" in later  # once the smoothers have settled after the gap (until then: skipped)
    assert set(later[: later.index("learned")]) <= {"skipped"}
    # a dwell that reaches back past the gap is refused
    across = Dwell(d.t_start_s, hi + 30.0, d.angle_deg)
    comp2, _ = compensate(cut, [*dwells[:8], across])
    assert comp2.table.outcomes[-1].status == "refused"


def test_compensate_table_log_cli(run, tmp_path, capsys):
    samples, dwells, truth, config, capture = run
    model = tmp_path / "model.yaml"
    model.write_bytes(Path(DEFAULT_MODEL).read_bytes())
    out = tmp_path / "out.csv"
    log = capture.with_suffix(".table.csv")
    args = ["compensate", str(capture), "--model", str(model), "--out", str(out), "--table-log", str(log)]
    assert main(args) == 0
    text = capsys.readouterr().out
    assert "table log:" in text and "learned" in text and "scale factor: +" in text
    assert "scale_factor" in out.read_text()
    # with --adapt-reference: a usage error, one line, nothing written
    out2 = tmp_path / "out2.csv"
    code = main([*args[:5], str(out2), "--table-log", str(log), "--adapt-reference", "0"])
    assert code == 64 and not out2.exists()
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--table-log" in err[0]
    # the log of a longer capture: refused, nothing left behind
    other = tmp_path / "other.csv"
    span = float(truth["second"][-1])
    other.write_text(f"t_start_s,t_end_s,angle_deg\n100,200,0\n{span + 50},{span + 200},36\n")
    out3 = tmp_path / "out3.csv"
    code = main([*args[:5], str(out3), "--table-log", str(other)])
    assert code != 0 and not out3.exists()
    assert "another capture" in capsys.readouterr().err
    assert math.isfinite(span)


def test_the_commands_reference_example_prints_what_it_shows(tmp_path, monkeypatch, capsys):
    """The ``compensate --table-log`` session of the commands reference, run as shown."""
    root = Path(__file__).resolve().parents[2]
    text = (root / "docs" / "reference" / "commands.md").read_text()
    start = text.index("$ fog-driver simulate --profile configs/profiles/table-run.yaml")
    block = text[start : text.index("```", start)].strip().splitlines()
    commands = [line[2:].split() for line in block if line.startswith("$ ")]
    shown = [line for line in block if not line.startswith("$ ")]
    for name in ("configs", "fog_driver"):
        (tmp_path / name).symlink_to(root / name)
    monkeypatch.chdir(tmp_path)
    assert main(commands[0][1:]) == 0
    capsys.readouterr()
    assert main(commands[1][1:]) == 0
    assert capsys.readouterr().out.strip().splitlines() == shown


def test_without_dwells_the_table_law_publishes_the_frozen_model_bit_for_bit(run):
    samples, dwells, *_ = run
    part, _ = first(samples, dwells, 1200.0)
    frozen = Compensator(load_model(DEFAULT_MODEL), 1.0 / RATE_HZ).run(part)
    table = Compensator(load_model(DEFAULT_MODEL), 1.0 / RATE_HZ, table=True).run(part)
    for name in ("drift_dph", "angle_comp_arcsec", "flags", "drift_sigma_dph"):
        assert np.array_equal(getattr(frozen, name), getattr(table, name), equal_nan=True), name


def test_table_angles_live_through_the_daemon(run):
    """``?TABLE`` at each dwell's end, the bytes fed as the port gives them: refusals are one-line ERRORs, the
    dwells are learned, STATUS says so, and the scale factor is found as offline."""
    from fog_driver.daemon.config import DriverConfig
    from fog_driver.daemon.service import Service

    samples, dwells, truth, config, capture = run
    data = capture.read_bytes()
    t = samples.t_s - samples.t_s[0]
    service = Service(DriverConfig(), port="unused")
    refused = service.control("TABLE", {"angle_deg": 0.0, "dwell_s": 60.0}, 0)
    assert refused["class"] == "ERROR" and "no samples yet" in refused["message"]
    fed = 0
    answers = []
    for k, d in enumerate(dwells):
        i = int(np.searchsorted(t, d.t_end_s))  # the first frame after the dwell: the angle is sent then
        end = int(samples.offset[i]) if i < len(samples) else len(data)
        service.process(data[fed:end])
        fed = end
        if k == 3:  # bad input: one line each, nothing learned
            for bad in ({"angle_deg": math.nan, "dwell_s": 60}, {"angle_deg": 1e7, "dwell_s": 60}):
                assert service.control("TABLE", bad, 0)["class"] == "ERROR"
            short = service.control("TABLE", {"angle_deg": d.angle_deg, "dwell_s": 5}, 0)
            assert short["class"] == "ERROR" and "12" in short["message"]
        answers.append(service.control("TABLE", {"angle_deg": d.angle_deg, "dwell_s": d.t_end_s - d.t_start_s}, 0))
        if k == 5:  # a second angle for a dwell already given: out of order
            again = service.control("TABLE", {"angle_deg": d.angle_deg, "dwell_s": 60}, 0)
            assert again["class"] == "ERROR" and "out of time order" in again["message"]
            on = service.control("ADAPT", {"enable": True, "reference_dph": 0}, 0)
            assert on["class"] == "ERROR" and "table" in on["message"]
    service.process(data[fed:])
    assert all(a["class"] == "TABLE" for a in answers), [a for a in answers if a["class"] != "TABLE"][:1]
    table = service.status_object()["table"]
    assert table["engaged"] is True and table["rejected"] == 0 and table["accepted"] >= len(dwells) - 6
    assert table["scale_factor_applied"] is True
    fiber = truth["fiber_c"][6300:8100]
    true_ppm = float(np.mean(config.gyro.scale_factor_error(fiber))) * 1e6
    found = table["scale_factor_ppm"] + table["scale_factor_ppm_per_c"] * (float(np.mean(fiber)) - SF_REF_C)
    assert abs(found - true_ppm) < 5.0
    # a zero breaks the chain: a dwell reaching back past it is refused; ?ADAPT off ends it
    assert service.control("ZERO", {}, 0)["class"] == "ZERO"
    past = service.control("TABLE", {"angle_deg": 0.0, "dwell_s": 60}, 0)
    assert past["class"] == "ERROR" and "reaches back past a break" in past["message"]
    assert service.control("ADAPT", {"enable": False}, 0)["class"] == "ADAPT"
    assert service.status_object()["table"]["engaged"] is False


def test_a_daemon_capture_with_table_and_adapt_events_compensates_offline_as_published(run, tmp_path, capsys):
    """Live == offline with control events: the daemon records its raw bytes and notes each ?TABLE and ?ADAPT
    with where it took effect; ``compensate`` of the capture replays them and gives the published angles and
    drifts bit for bit."""
    from fog_driver.daemon.config import DriverConfig
    from fog_driver.daemon.rawlog import CaptureSink, RotatingCapture
    from fog_driver.daemon.service import Service
    from fog_driver.offline.compensate import compensate_capture
    from fog_driver.offline.replay import control_events
    from fog_driver.samples.captures import read_provenance

    samples, dwells, _, _, capture = run
    data = capture.read_bytes()
    t = samples.t_s - samples.t_s[0]
    service = Service(DriverConfig(), port="unused")
    service.capture = CaptureSink(RotatingCapture(tmp_path / "cap", provenance=service._provenance()))
    published: list[dict] = []
    fed = taken = 0
    for k, d in enumerate(dwells[:40]):
        i = int(np.searchsorted(t, d.t_end_s)) + 3 * k % 7  # a few frames late, as a station's message is
        end = int(samples.offset[i]) + (5 if k % 3 == 0 else 0)  # and in the middle of a frame, sometimes
        published += service.process(data[fed:end])
        fed = end
        if k == 25:  # the operator stops adapting from the table, adapts against a rate, stops, table again
            assert service.control("ADAPT", {"enable": False}, 0)["class"] == "ADAPT"
        elif k == 27:
            assert service.control("ADAPT", {"enable": True, "reference_dph": 0.0}, 0)["class"] == "ADAPT"
        elif k == 30:
            assert service.control("ADAPT", {"enable": False}, 0)["class"] == "ADAPT"
        elif not 25 < k < 31:
            reply = service.control("TABLE", {"angle_deg": d.angle_deg % 360.0, "dwell_s": d.t_end_s - d.t_start_s}, 0)
            assert reply["class"] == "TABLE", reply
            taken += 1
    published += service.process(data[fed:])
    service.capture.close()
    (recorded,) = sorted((tmp_path / "cap").glob("*.bin"))
    assert recorded.read_bytes() == data
    table = service.status_object()["table"]
    assert table["accepted"] > 15 and table["scale_factor_applied"]
    out = tmp_path / "out.csv"
    assert main(["compensate", str(recorded), "--model", str(DEFAULT_MODEL), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert f"replayed the daemon's control events where they took effect: {taken} table, 3 adapt" in printed
    assert "table log:" in printed and "warning" not in printed
    events = control_events(read_provenance(recorded))
    assert [e.kind for e in events].count("table") == taken == 34
    cols = [c for _, c in compensate_capture(recorded, load_model(DEFAULT_MODEL), events=events)]
    angle = np.concatenate([c.angle_comp_arcsec for c in cols])
    drift = np.concatenate([c.drift_dph for c in cols])
    assert angle.tolist() == [o["angle_arcsec"] for o in published]
    assert [None if v != v else v for v in drift.tolist()] == [o.get("drift_dph") for o in published]  # NaN: absent
    # without the replay the angles differ (the scale factor learned from the dwells): the events matter
    plain = np.concatenate([c.angle_comp_arcsec for _, c in compensate_capture(recorded, load_model(DEFAULT_MODEL))])
    assert np.max(np.abs(plain - angle)) > 1.0


def test_a_daemon_capture_with_zero_and_bias_compensates_offline_as_published(tmp_path, capsys):
    """``?ZERO`` and a ``?BIAS`` capture's result, replayed where they took effect (the bias in the middle of
    a chunk of bytes): the published angles, raw and compensated, bit for bit."""
    from fog_driver.daemon.config import DriverConfig
    from fog_driver.daemon.rawlog import CaptureSink, RotatingCapture
    from fog_driver.daemon.service import Service
    from fog_driver.offline.compensate import compensate_capture
    from fog_driver.offline.replay import control_events
    from fog_driver.samples.captures import read_provenance

    data = (Path(__file__).parents[1] / "data" / "sim-short.bin").read_bytes()
    service = Service(DriverConfig(), port="unused")
    service.capture = CaptureSink(RotatingCapture(tmp_path / "cap", provenance=service._provenance()))
    published = service.process(data[:20003])
    assert service.control("ZERO", {}, 0)["class"] == "ZERO"
    published += service.process(data[20003:30011])
    assert service.control("BIAS", {"seconds": 5}, 0)["state"] == "started"
    published += service.process(data[30011:])  # the capture completes inside this chunk
    assert service.last_event["state"] == "done"
    service.capture.close()
    (recorded,) = sorted((tmp_path / "cap").glob("*.bin"))
    events = control_events(read_provenance(recorded))
    assert [e.kind for e in events] == ["zero", "bias"]
    cols = [c for _, c in compensate_capture(recorded, load_model(DEFAULT_MODEL), events=events)]
    for key, name in (("angle_arcsec", "angle_comp_arcsec"), ("angle_raw_arcsec", "angle_raw_arcsec")):
        assert np.concatenate([getattr(c, name) for c in cols]).tolist() == [o[key] for o in published], key
    out = tmp_path / "out.csv"
    assert main(["compensate", str(recorded), "--model", str(DEFAULT_MODEL), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "replayed the daemon's control events where they took effect: 1 zero, 1 bias" in printed


def test_what_the_table_law_learned_persists_across_a_restart(run, tmp_path):
    """The adaptation state carries the table law (weights, covariance, scale factor) exactly through YAML; a
    restored law starts a new run (its bias and chain afresh) and one for another model is refused."""
    import yaml

    from fog_driver.errors import InputFileError

    samples, dwells, *_ = run
    part, use = first(samples, dwells, 4000.0)
    comp, _ = compensate(part, use)
    saved = comp.table.get_state()
    doc = yaml.safe_load(yaml.safe_dump(comp.adaptation_document()))
    restored = Compensator(load_model(DEFAULT_MODEL), 1.0 / RATE_HZ, table=True, adapt=comp.adapt)
    restored.restore_adaptation(doc, "state.yaml")
    # the sums carried exactly, but for the level, the bias's: marginalized out for the new run (the Schur
    # complement of its entry), the shape's and the scale factor's information kept
    lvl = comp.table.n_features
    h = np.array(saved["h"])
    assert h[lvl, lvl] > 0 and abs(np.delete(h[:, lvl], lvl)).max() > 0  # there was a level, tied to the rest
    assert_level_marginalized(restored.table, saved)
    rest = {k: v for k, v in learned_part(restored.table.get_state()).items() if k not in ("h", "i", "delta", "cov")}
    assert rest == {k: v for k, v in learned_part(saved).items() if k not in ("h", "i", "delta", "cov")}
    # the scale factor as learned, within what the level's own uncertainty moved it by
    assert restored.table.scale_factor_ppm == pytest.approx(comp.table.scale_factor_ppm, abs=0.01)
    assert restored.table.bias_dph is None and restored.table.anchor is None  # a new run
    other = dict(doc)
    other["table"] = {**doc["table"], "frozen_intercept": doc["table"]["frozen_intercept"] + 1.0}
    fresh = Compensator(load_model(DEFAULT_MODEL), 1.0 / RATE_HZ, table=True, adapt=comp.adapt)
    with pytest.raises(InputFileError, match="another model"):
        fresh.restore_adaptation(other, "state.yaml")
    assert fresh.table.accepted == 0  # nothing changed
    # a state saved before the weighing of prior scales (no evidence): restored, the weighing afresh
    older = dict(doc)
    older["table"] = {k: v for k, v in doc["table"].items() if k != "evidence"}
    upgraded = Compensator(load_model(DEFAULT_MODEL), 1.0 / RATE_HZ, table=True, adapt=comp.adapt)
    upgraded.restore_adaptation(older, "state.yaml")
    assert upgraded.table.accepted == comp.table.accepted and not upgraded.table.evidence.any()
    assert np.array_equal(upgraded.table.h, restored.table.h)
    # a state of an earlier version, learned on the model's own regressors (no shape): refused by a law on the
    # candidates (the daemon sets it aside and starts afresh), restored by one without candidates
    own, _ = compensate(part, use, without_candidates())
    earlier = {
        k: v for k, v in yaml.safe_load(yaml.safe_dump(learned_part(own.table.get_state()))).items() if k != "shape"
    }
    with pytest.raises(InputFileError, match="'regressors' shape regressors, this law's are 'candidates'"):
        fresh.restore_adaptation({**doc, "table": earlier}, "state.yaml")
    assert fresh.table.accepted == 0
    plain = Compensator(without_candidates(), 1.0 / RATE_HZ, table=True, adapt=comp.adapt)
    plain.restore_adaptation({**doc, "table": earlier}, "state.yaml")
    assert plain.table.accepted == own.table.accepted
    assert_level_marginalized(plain.table, own.table.get_state())


def assert_level_marginalized(law: TableLaw, saved: dict) -> None:
    """``law``'s sums are ``saved``'s with the level (index ``n_features``) marginalized out: the Schur complement
    of its entry, its row and column 0."""
    lvl = law.n_features
    h, i = np.array(saved["h"]), np.array(saved["i"])
    keep = [k for k in range(len(i)) if k != lvl]
    schur = h[np.ix_(keep, keep)] - np.outer(h[keep, lvl], h[lvl, keep]) / h[lvl, lvl]
    np.testing.assert_allclose(law.h[np.ix_(keep, keep)], schur, rtol=1e-12, atol=1e-12 * abs(h).max())
    np.testing.assert_allclose(
        law.i[keep], i[keep] - h[keep, lvl] * i[lvl] / h[lvl, lvl], rtol=1e-12, atol=1e-12 * abs(i).max()
    )
    assert not law.h[lvl].any() and not law.h[:, lvl].any() and law.i[lvl] == 0


def test_compensate_table_log_saves_and_restores_the_state(run, tmp_path, capsys):
    samples, dwells, truth, config, capture = run
    state = tmp_path / "state.yaml"
    log = capture.with_suffix(".table.csv")
    base = ["compensate", str(capture), "--model", str(DEFAULT_MODEL), "--table-log", str(log)]
    assert main([*base, "--out", str(tmp_path / "a.csv"), "--adapt-state", str(state)]) == 0
    first_run = capsys.readouterr().out
    assert state.exists()
    assert main([*base, "--out", str(tmp_path / "b.csv"), "--adapt-state", str(state)]) == 0
    second_run = capsys.readouterr().out
    sf = [line for line in (first_run + second_run).splitlines() if line.startswith("scale factor:")]
    assert len(sf) == 2 and sf[0] != sf[1]  # the second run went on from what the first learned


def test_live_table_dwells_in_the_first_300_s_are_skipped_for_the_warm_up_and_say_so(run):
    """``?TABLE`` in the daemon's first minutes: the law learns nothing from blocks before ``warmup_s`` (300 s of
    device time), and the dwells there were ``skipped: degraded inputs in the interval``, which is not what was
    wrong.  Their reason now says the warm-up and when it ends; the intervals after it are learned."""
    from fog_driver.compensation.adapt_config import AdaptConfig
    from fog_driver.daemon.config import DriverConfig
    from fog_driver.daemon.service import Service

    samples, dwells, _, _, capture = run
    warmup_s = AdaptConfig().warmup_s
    data = capture.read_bytes()
    t = samples.t_s - samples.t_s[0]
    service = Service(DriverConfig(), port="unused")
    fed, reasons = 0, []
    ends_s = np.arange(40.0, 290.0, 25.0)  # the table still before the run's first move (300 s)
    for end_s in ends_s:
        i = int(np.searchsorted(t, end_s))
        service.process(data[fed : int(samples.offset[i])])
        fed = int(samples.offset[i])
        assert service.control("TABLE", {"angle_deg": 0.0, "dwell_s": 20.0}, 0)["class"] == "TABLE"
        service.process(data[fed : int(samples.offset[i + 5 * RATE_HZ])])  # the dwell's last block closes
        fed = int(samples.offset[i + 5 * RATE_HZ])
        last = service.status_object()["table"]["last"]
        reasons.append((last["status"], last["reason"]))
    assert reasons[0] == ("anchor", "")
    assert set(reasons[1:]) == {
        (
            "skipped",
            f"the warm-up: nothing is learned from the first {warmup_s:g} s of "
            f"device time (warmup_s), until {warmup_s:g} s",
        )
    }
    assert len(reasons) == len(ends_s) and 0 < ends_s[-1] < warmup_s
    for d in dwells[:4]:  # the table log's first dwells, after the warm-up: the bias is captured from them
        i = int(np.searchsorted(t, d.t_end_s))
        service.process(data[fed : int(samples.offset[i])])
        fed = int(samples.offset[i])
        args = {"angle_deg": d.angle_deg, "dwell_s": d.t_end_s - d.t_start_s}
        assert service.control("TABLE", args, 0)["class"] == "TABLE"
    service.process(data[fed:])
    after = [o.status for o in service.compensator.table_outcomes[len(ends_s) :]]
    assert after[0] == "skipped" and after[1:] == ["bias"] * 3  # the first interval holds warm-up blocks


def recorded_capture_with_a_table_event(tmp_path: Path) -> tuple[Path, Path, dict]:
    """``sim-short.bin`` through the daemon (recording its capture) with one ``?TABLE``: the capture, its
    sidecar and the sidecar's document."""
    import yaml

    from fog_driver.daemon.config import DriverConfig
    from fog_driver.daemon.rawlog import CaptureSink, RotatingCapture
    from fog_driver.daemon.service import Service
    from fog_driver.samples.captures import find_sidecar

    data = (Path(__file__).parents[1] / "data" / "sim-short.bin").read_bytes()
    service = Service(DriverConfig(), port="unused")
    service.capture = CaptureSink(RotatingCapture(tmp_path / "cap", provenance=service._provenance()))
    service.process(data[:40000])
    assert service.control("TABLE", {"angle_deg": 10.0, "dwell_s": 20.0}, 0)["class"] == "TABLE"
    service.process(data[40000:])
    service.capture.close()
    (recorded,) = sorted((tmp_path / "cap").glob("*.bin"))
    sidecar = find_sidecar(recorded)
    return recorded, sidecar, yaml.safe_load(sidecar.read_text())


def compensate_edited_sidecar(tmp_path: Path, capsys, **change) -> tuple[int, list[str], Path, Path]:
    """The recorded capture's table event changed by ``change`` in its sidecar, then ``compensate``: the exit
    status, the lines on stderr, the capture and the output path."""
    import yaml

    recorded, sidecar, doc = recorded_capture_with_a_table_event(tmp_path)
    (event,) = [e for e in doc["events"] if e["event"] == "table"]
    event.update(change)
    sidecar.write_text(yaml.safe_dump(doc))
    out = tmp_path / "out.csv"
    code = main(["compensate", str(recorded), "--model", str(DEFAULT_MODEL), "--out", str(out)])
    return code, capsys.readouterr().err.strip().splitlines(), recorded, out


def test_a_sidecar_event_that_cannot_be_replayed_is_a_one_line_error(tmp_path, capsys):
    """A hand-edited sidecar (a ?TABLE with a dwell longer than the data): one line, exit 65, nothing written."""
    code, err, _, out = compensate_edited_sidecar(tmp_path, capsys, dwell_s=1e5)  # longer than the data
    assert code == 65
    assert len(err) == 1 and "table event at byte" in err[0] and "cannot be replayed" in err[0]
    assert not out.exists()


@pytest.mark.parametrize("angle", [math.nan, math.inf, 1e308, True])
def test_compensate_of_a_capture_whose_sidecar_table_event_has_a_nan_angle_is_a_one_line_error(tmp_path, capsys, angle):
    """A hand-edited sidecar whose ``?TABLE`` event says ``angle_deg: .nan`` (or infinite, 1e308, true): the
    replay checks it as ``?TABLE`` did (``dwells.table_angle_deg``), one line naming the capture's event,
    exit 65, nothing written (a NaN ended in exit 70, or was taken as a dwell)."""
    code, err, recorded, out = compensate_edited_sidecar(tmp_path, capsys, angle_deg=angle)
    assert code == 65 and len(err) == 1 and "internal error" not in err[0], err
    assert str(recorded) in err[0] and "table event at byte" in err[0]
    assert "angle_deg must be a number within +-1e+06 degrees" in err[0]
    assert not out.exists()


def test_a_dwell_blamed_by_its_neighbours_gives_a_new_outcome_log_and_leaves_the_one_read_before_as_it_was():
    """The judge's verdict (``table.judge``): dwell 2, learned, was the wrong one; dwell 3, rejected, has the
    interval (1, 3).  The revised log has them so, dwell 2's figures kept; the log and the outcomes a reader
    held before are unchanged, and each log's tally counts its own outcomes."""
    from fog_driver.compensation.table.judge import BLAMED_REASON
    from fog_driver.compensation.table.outcomes import OutcomeLog, OutcomeStatus, Revision, outcome

    dwells = [Dwell(100.0 * k, 100.0 * k + 60.0, 36.0 * k) for k in range(4)]
    statuses = [OutcomeStatus.ANCHOR, OutcomeStatus.LEARNED, OutcomeStatus.LEARNED, OutcomeStatus.REJECTED]
    log = OutcomeLog()
    for k, status in enumerate(statuses):
        log.note(outcome(dwells[k], status, "" if k < 3 else "disagrees", {"innovation_arcsec": 1.0 + k}))
    held, before = log.recent, list(log.recent)
    merged = outcome(dwells[3], OutcomeStatus.LEARNED, "", {"innovation_arcsec": -0.5})
    revised = log.revised(Revision(dwells[2].t_end_s, merged, BLAMED_REASON))
    assert log.recent is held and list(held) == before
    assert list(revised.recent) == [
        before[0],
        before[1],
        before[2]._replace(status=OutcomeStatus.REJECTED, reason=BLAMED_REASON),
        merged,
    ]
    assert revised.recent[2].innovation_arcsec == before[2].innovation_arcsec == 3.0
    assert dict(log.tally().by_status) == {"anchor": 1, "learned": 2, "rejected": 1}
    assert dict(revised.tally().by_status) == {"anchor": 1, "learned": 2, "rejected": 1}
    assert revised.tally().by_reason[("rejected", BLAMED_REASON)][0] == [1]


def test_a_dwells_status_is_written_as_its_word_in_json_csv_and_text():
    """``OutcomeStatus`` is a ``StrEnum``: every way an outcome is written (STATUS's NDJSON, a CSV, a report
    line) gives the bare word, as the strings it replaced did."""
    import csv
    import io
    import json

    from fog_driver.compensation.table import OutcomeStatus

    for status in OutcomeStatus:
        word = status.value
        assert json.dumps({"status": status}) == json.dumps({"status": word})
        assert f"{status} {status:>9}" == f"{word} {word:>9}" and str(status) == word
        out = io.StringIO()
        csv.writer(out).writerow([status])
        assert out.getvalue() == f"{word}\r\n"
        assert status == word and {word: 1}[status] == 1
