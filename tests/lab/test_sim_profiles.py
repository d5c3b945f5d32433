"""Chamber profiles and turntable motion plans: exact shapes, the paper's runs, shipped files, bad input."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import given
from hypothesis import strategies as st

from fog_driver.dwells import Dwell
from fog_driver.errors import InputFileError
from fog_driver.lab.motion import ConstantRate, Creep, MotionPlan, Positioning, positioning_at_plateau
from fog_driver.lab.profiles import MAX_SEGMENTS, SimProfile, dump_profile, load_profile, parse_profile
from fog_driver.lab.program import ChamberProfile, Hold, Plateau, Ramp, Sinusoid, Step

PROFILES = Path(__file__).resolve().parents[2] / "configs" / "profiles"
SHIPPED = tuple(sorted(path.stem for path in PROFILES.glob("*.yaml")))  #: every profile the project ships


def move_breakpoints(seq: Positioning) -> np.ndarray:
    """Every time the rate's slope changes in ``seq`` (from its public timing properties)."""
    t = [seq.start_s, seq.end_s]
    for k in range(seq.moves):
        t0, move = seq.move_start_s(k), seq.shape(k)
        t += [t0, t0 + move.accel_time_s, t0 + move.accel_time_s + move.cruise_time_s, t0 + move.move_time_s]
    return np.array(sorted(t))


def cumulative_trapezoid(t: np.ndarray, y: np.ndarray) -> np.ndarray:
    return np.concatenate([[0.0], np.cumsum(np.diff(t) * (y[1:] + y[:-1]) / 2)])


# --- chamber profiles ----------------------------------------------------------------------------


def test_ramps_reach_their_targets_at_the_right_times():
    prof = ChamberProfile("t", 20.0, (Hold(300.0), Ramp(2.0, 30.0), Hold(600.0), Ramp(0.5, 25.0)))
    assert prof.duration_s == 300 + 300 + 600 + 600
    t = np.array([-5.0, 0.0, 300.0, 450.0, 600.0, 900.0, 1200.0, 1500.0, 1800.0, 1e6])
    np.testing.assert_array_equal(prof.air_temp_c(t), [20, 20, 20, 25, 30, 30, 30, 27.5, 25, 25])
    assert [s.t_end_s for s in prof.spans()] == [300.0, 600.0, 1200.0, 1800.0]


def test_steps_are_instantaneous_and_right_continuous():
    prof = ChamberProfile("t", 20.0, (Hold(100.0), Step(35.0), Hold(100.0), Step(-5.0)))
    assert prof.duration_s == 200.0
    np.testing.assert_array_equal(
        prof.air_temp_c([99.999, 100.0, 150.0, 199.999, 200.0, 300.0]), [20, 35, 35, 35, -5, -5]
    )
    assert prof.step_times_s() == [100.0, 200.0]
    assert prof.plateaus() == [Plateau(0.0, 100.0, 20.0), Plateau(100.0, 200.0, 35.0)]


def test_sinusoid_oscillates_around_its_start_and_the_next_segment_starts_from_its_end_value():
    whole = ChamberProfile("t", 10.0, (Sinusoid(2.0, 400.0, 800.0), Hold(50.0)))
    np.testing.assert_allclose(whole.air_temp_c([100.0, 300.0, 500.0]), [12.0, 8.0, 12.0], atol=1e-12)
    assert whole.spans()[1].start_c == 10.0  # whole number of periods: back at T0, exactly
    assert whole.air_temp_c(np.array([900.0]))[0] == 10.0
    part = ChamberProfile("t", 10.0, (Sinusoid(2.0, 400.0, 100.0), Ramp(1.0, 0.0)))
    assert part.spans()[1].start_c == pytest.approx(12.0)  # a quarter period: the ramp starts from the crest
    assert part.duration_s == pytest.approx(100.0 + 12.0 * 60.0)
    assert part.air_temp_c(np.array([100.0 + 6 * 60.0]))[0] == pytest.approx(6.0)


def test_air_temp_is_vectorized_and_keeps_shape():
    prof = load_profile("paper").chamber
    t = np.linspace(-100.0, prof.duration_s + 100.0, 2_600_000)
    temp = prof.air_temp_c(t)
    assert temp.shape == t.shape and temp.dtype == np.float64
    assert temp[0] == 20.0 and temp[-1] == -40.0
    assert prof.air_temp_c(np.zeros((3, 4))).shape == (3, 4)
    assert prof.air_temp_c(1800.0 + 150.0).shape == ()


def test_paper_profile_is_the_papers_440_minutes():
    prof = load_profile("paper")
    chamber = prof.chamber
    assert chamber.duration_s == 440 * 60.0
    assert prof.motion.kind == "static" and prof.motion.duration_s == 0.0
    plateaus = chamber.plateaus()
    temps = [p.temp_c for p in plateaus]
    assert temps == [20, 25, 30, 35, 40, 45, 50, 55, 20, 15, 10, 5, 0, -5, -10, -15, -20, -25, -30, -35, -40]
    lengths_min = [(p.t_end_s - p.t_start_s) / 60 for p in plateaus]
    assert lengths_min[0] == 30.0  # warm-up
    assert lengths_min[8] == 12.5  # after the quick return to 20 degC
    assert set(lengths_min[1:8] + lengths_min[9:]) == {15.0}
    assert plateaus[0].t_start_s == 0.0 and plateaus[-1].t_end_s == 440 * 60.0
    # every plateau really is at its temperature, start, middle and just before the end
    for p in plateaus:
        t = np.array([p.t_start_s, (p.t_start_s + p.t_end_s) / 2, p.t_end_s - 1e-6])
        np.testing.assert_array_equal(chamber.air_temp_c(t), p.temp_c)
    # rates: 1 degC/min everywhere except the 2 degC/min return from 55 to 20 (17.5 min)
    ramps = [s for s in chamber.spans() if isinstance(s.segment, Ramp)]
    assert [s.segment.rate_c_per_min for s in ramps] == [1.0] * 7 + [2.0] + [1.0] * 12
    ret = ramps[7]
    assert (ret.start_c, ret.end_c, ret.t_start_s / 60, ret.t_end_s / 60) == (55.0, 20.0, 170.0, 187.5)
    # the 5-degree ramps take 5 min each
    assert {s.t_end_s - s.t_start_s for s in ramps if s is not ret} == {300.0}
    # monotone up to 55, then down from 20 to -40
    t = np.arange(0.0, 440 * 60.0 + 1, 1.0)
    temp = chamber.air_temp_c(t)
    assert np.all(np.diff(temp[: 170 * 60 + 1]) >= 0) and np.all(np.diff(temp[200 * 60 :]) <= 0)
    assert temp.max() == 55.0 and temp.min() == -40.0


def test_paper_yaml_is_the_builtin_profile():
    builtin, shipped = load_profile("paper"), load_profile(PROFILES / "paper.yaml")
    assert shipped.chamber == builtin.chamber
    assert shipped.motion == builtin.motion
    assert shipped.name == builtin.name == "paper"
    assert builtin.source == "built-in" and shipped.source.endswith("paper.yaml")


def test_paper_validation_profile():
    prof = load_profile("paper-validation")
    chamber, motion = prof.chamber, prof.motion
    plateaus = chamber.plateaus()
    assert [p.temp_c for p in plateaus] == [20, -40, -30, -20, -10, 0, 10, 20, 25, 30, 40, 55]
    assert chamber.duration_s == 1010 * 60.0
    ramps = [s.segment for s in chamber.spans() if isinstance(s.segment, Ramp)]
    assert {r.rate_c_per_min for r in ramps} == {1.0}
    seqs = motion.items
    assert len(seqs) == 11 and all(isinstance(s, Positioning) for s in seqs)
    for seq, plateau in zip(seqs, plateaus[1:]):
        assert (seq.moves, seq.step_deg, seq.dwell_s) == (10, 36.0, 60.0)
        assert seq.start_s == plateau.t_start_s + 3600.0  # 60 min to settle
        assert seq.end_s < plateau.t_end_s  # the whole sequence on the plateau
        t = np.linspace(seq.start_s, seq.end_s, 1001)
        np.testing.assert_array_equal(chamber.air_temp_c(t), plateau.temp_c)
    stops = motion.dwells()
    assert len(stops) == 11 * 11
    assert stops[-1].angle_deg == 11 * 360.0  # cumulative angle, one full turn per temperature
    assert prof.duration_s == chamber.duration_s


def test_fast_ramps_is_a_different_profile_for_validation():
    prof = load_profile(PROFILES / "fast-ramps.yaml")
    chamber = prof.chamber
    assert 4 * 3600 <= chamber.duration_s <= 6 * 3600
    rates = {s.rate_c_per_min for s in chamber.segments if isinstance(s, Ramp)}
    assert {0.5, 2.0} <= rates
    assert any(isinstance(s, Sinusoid) for s in chamber.segments)
    assert any(isinstance(s, Step) for s in chamber.segments)
    t = np.arange(0.0, chamber.duration_s, 1.0)
    temp = chamber.air_temp_c(t)
    assert t[np.argmin(temp)] < t[np.argmax(temp)]  # cold first, then hot
    off_grid = [p.temp_c for p in chamber.plateaus() if p.temp_c % 5 != 0]
    assert len(off_grid) >= 4
    assert chamber != load_profile("paper").chamber


def test_chamber_cycle_is_a_scoring_profile_unlike_the_others():
    """What its header says: 344.1 min, irregular ramps of 0.5 to 2.5 degC/min (two in a row), 0.6 of a
    sinusoid's period, and a 10 x 36 degree sequence 10 min into each of plateaus 1 to 5."""
    prof = load_profile(PROFILES / "chamber-cycle.yaml")
    chamber = prof.chamber
    assert chamber.duration_s == pytest.approx(344.1 * 60, abs=30)
    rates = [s.rate_c_per_min for s in chamber.segments if isinstance(s, Ramp)]
    assert min(rates) == 0.5 and max(rates) == 2.5 and len(set(rates)) == len(rates)
    (sine,) = [s for s in chamber.segments if isinstance(s, Sinusoid)]
    assert not sine.whole_periods and sine.end_offset_c() == pytest.approx(6 * math.sin(1.2 * math.pi))
    plateaus = chamber.plateaus()
    assert [m.start_s for m in prof.motion.items] == [plateaus[k].t_start_s + 600.0 for k in range(1, 6)]
    assert all(m.moves == 10 and m.step_deg == 36.0 for m in prof.motion.items)
    for other in ("paper", "fast-ramps", "soak-cycle", "steps-moves", "calibration"):
        assert load_profile(other).chamber.segments != chamber.segments


def test_short_test_profile_is_about_twenty_minutes():
    chamber = load_profile(PROFILES / "short-test.yaml").chamber
    assert chamber.duration_s == 20 * 60.0
    assert [type(s) for s in chamber.segments] == [Hold, Ramp, Hold]
    span = chamber.spans()[1]
    assert span.segment.rate_c_per_min == 2.0 and span.end_c - span.start_c == 10.0


def test_positioning_profile_has_the_ten_by_36_degree_sequence_on_a_plateau():
    prof = load_profile(PROFILES / "positioning.yaml")
    (seq,) = prof.motion.items
    plateau = prof.chamber.plateaus()[1]
    assert seq.start_s == plateau.t_start_s + 600.0 and seq.end_s <= plateau.t_end_s
    stops = prof.motion.dwells()
    assert [s.angle_deg for s in stops] == [36.0 * k for k in range(11)]


def test_segment_table_lists_every_segment():
    chamber = load_profile(PROFILES / "fast-ramps.yaml").chamber
    table = chamber.segment_table().splitlines()
    assert len(table) == 2 + len(chamber.segments)
    assert "sinusoid" in table[2 + 6] and "plateau 0" in table[2]
    assert "328.427 min" in table[0]


# --- chamber profiles: properties over random segment lists --------------------------------------

temps = st.floats(-60.0, 90.0, allow_nan=False).map(lambda x: round(x, 3))
durations = st.floats(1.0, 5000.0, allow_nan=False)
segments = st.one_of(
    st.builds(Hold, durations),
    st.builds(Ramp, st.floats(0.05, 10.0), temps),
    st.builds(Step, temps),
    st.builds(Sinusoid, st.floats(0.0, 10.0), st.floats(10.0, 3000.0), durations),
)


@given(temps, st.lists(segments, min_size=1, max_size=12))
def test_random_profiles_duration_continuity_and_monotone_ramps(start_c, segs):
    prof = ChamberProfile("random", start_c, tuple(segs))
    spans = prof.spans()
    # the duration is the sum of the parts
    parts = []
    temp = start_c
    for seg in segs:
        if isinstance(seg, (Hold, Sinusoid)):
            parts.append(seg.duration_s)
        elif isinstance(seg, Ramp):
            parts.append(abs(seg.target_c - temp) / seg.rate_c_per_min * 60)
        else:
            parts.append(0.0)
        temp = spans[len(parts) - 1].end_c
    assert prof.duration_s == pytest.approx(sum(parts), rel=1e-12, abs=1e-9)
    # each segment starts where the previous one ended; steps are the only jumps
    assert spans[0].start_c == start_c
    for a, b in zip(spans, spans[1:]):
        assert b.start_c == a.end_c and b.t_start_s == a.t_end_s
    # continuity: on a dense grid the change between neighbours is bounded by the steepest slope,
    # except across a step
    max_slope = max(
        [s.rate_c_per_min / 60 for s in segs if isinstance(s, Ramp)]
        + [2 * math.pi * s.amplitude_c / s.period_s for s in segs if isinstance(s, Sinusoid)]
        + [0.0]
    )
    t = np.linspace(-10.0, prof.duration_s + 10.0, 20_001)
    temp = prof.air_temp_c(t)
    jumps = np.abs(np.diff(temp)) > max_slope * (t[1] - t[0]) * (1 + 1e-9) + 1e-9
    step_times = np.array(prof.step_times_s())
    for i in np.flatnonzero(jumps):
        assert np.any((step_times > t[i]) & (step_times <= t[i + 1])), f"jump at t={t[i]}..{t[i + 1]} without a step"
    # and right at every boundary that is not a step, the two sides agree
    all_step_times = {s.t_start_s for s in spans if isinstance(s.segment, Step)}
    for s in spans[1:]:
        if s.t_start_s not in all_step_times:
            left, right = prof.air_temp_c(np.array([s.t_start_s - 1e-7, s.t_start_s]))
            assert abs(right - left) <= max_slope * 1e-6 + 1e-9
    # ramps are monotone and end exactly at their target at their end time
    for s in spans:
        if isinstance(s.segment, Ramp):
            assert s.end_c == s.segment.target_c
            tt = np.linspace(s.t_start_s, s.t_end_s, 201)[:-1]  # at t_end a following step has already happened
            d = np.diff(prof.air_temp_c(tt)) * np.sign(s.segment.target_c - s.start_c)
            assert np.all(d >= -1e-9)
            if s.t_end_s not in all_step_times:
                assert prof.air_temp_c(np.array(s.t_end_s))[()] == s.segment.target_c
    # before the start and after the end
    assert prof.air_temp_c(np.array([-1.0]))[0] == start_c
    assert prof.air_temp_c(np.array([prof.duration_s + 1e3]))[0] == spans[-1].end_c


# --- turntable motion ----------------------------------------------------------------------------


def test_default_positioning_move_is_triangular():
    seq = Positioning(start_s=100.0)
    assert seq.triangular  # 36 deg < 20^2 / 10 = 40 deg
    assert seq.peak_rate_dps == pytest.approx(math.sqrt(360.0))
    assert seq.move_time_s == pytest.approx(2 * math.sqrt(3.6))
    assert seq.duration_s == pytest.approx(60 + 10 * (2 * math.sqrt(3.6) + 60))
    plan = MotionPlan((seq,))
    t = np.linspace(seq.start_s, seq.end_s, 2_000_001)
    rate = plan.rate_dps(t)
    assert rate.max() == pytest.approx(math.sqrt(360.0), abs=1e-3) and rate.max() < 20.0
    assert rate.min() >= -1e-12


def test_trapezoidal_moves_cruise_at_the_top_rate():
    seq = Positioning(start_s=0.0, moves=3, step_deg=-36.0, max_rate_dps=10.0, accel_dps2=10.0, dwell_s=5.0)
    assert not seq.triangular
    assert (seq.accel_time_s, seq.cruise_time_s) == (1.0, pytest.approx(2.6))
    plan = MotionPlan((seq,))
    t0 = seq.move_start_s(1)
    np.testing.assert_allclose(plan.rate_dps(np.linspace(t0 + 1.0, t0 + 3.6, 50)), -10.0, rtol=1e-12)
    assert plan.rate_dps(np.array(t0 + 0.5))[()] == pytest.approx(-5.0)
    assert [s.angle_deg for s in plan.dwells()] == [0.0, -36.0, -72.0, -108.0]


@pytest.mark.parametrize(
    "seq",
    [
        Positioning(start_s=10.0),
        Positioning(start_s=0.0, moves=4, step_deg=90.0, max_rate_dps=15.0, accel_dps2=5.0, dwell_s=20.0),
        Positioning(start_s=3.0, moves=5, step_deg=-7.5, max_rate_dps=50.0, accel_dps2=2.0, dwell_s=10.0),
        Positioning(start_s=2.0, moves=7, step_deg=[36.0, -72.0, 10.0, -5.0], dwell_s=15.0),
    ],
    ids=["default-triangular", "trapezoidal", "negative-triangular", "list-of-steps"],
)
def test_positioning_angle_is_the_exact_integral_of_the_rate(seq):
    plan = MotionPlan((seq,))
    # a fine grid plus every breakpoint: the trapezoid rule is then exact for the piecewise-linear rate
    t = np.union1d(np.arange(0.0, seq.end_s + 20.0, 1e-3), move_breakpoints(seq))
    rate, angle = plan.rate_dps(t), plan.angle_deg(t)
    np.testing.assert_allclose(angle, cumulative_trapezoid(t, rate), rtol=0, atol=1e-6)
    # and on a uniform grid that misses the breakpoints, to within the trapezoid rule's own error
    u = np.arange(0.0, seq.end_s + 20.0, 1e-3)
    np.testing.assert_allclose(plan.angle_deg(u), cumulative_trapezoid(u, plan.rate_dps(u)), rtol=0, atol=1e-5)
    # the bounds: |rate| <= max rate, |d rate / dt| <= accel
    assert np.abs(rate).max() <= seq.max_rate_dps * (1 + 1e-12)
    assert np.abs(rate).max() == pytest.approx(seq.peak_rate_dps, rel=1e-6)
    assert np.all(np.abs(np.diff(rate)) <= seq.accel_dps2 * np.diff(t) * (1 + 1e-9) + 1e-12)
    # continuity: no jump at any breakpoint
    for b in move_breakpoints(seq):
        left, right = plan.angle_deg(np.array([b - 1e-9, b]))
        assert abs(right - left) <= seq.peak_rate_dps * 1e-9 + 1e-12
        r_left, r_right = plan.rate_dps(np.array([b - 1e-9, b]))
        assert abs(r_right - r_left) <= seq.accel_dps2 * 1e-9 + 1e-12


@pytest.mark.parametrize(
    "seq", [Positioning(start_s=10.0), Positioning(start_s=5.0, moves=7, step_deg=-50.0, max_rate_dps=10.0)]
)
def test_each_move_turns_exactly_step_deg_and_dwells_are_exact(seq):
    plan = MotionPlan((seq,))
    stops = plan.dwells()
    assert len(stops) == seq.moves + 1
    assert stops[0] == Dwell(seq.start_s, seq.move_start_s(0), 0.0)
    assert [s.angle_deg for s in stops] == [k * seq.step_deg for k in range(seq.moves + 1)]
    assert sum(b.angle_deg - a.angle_deg for a, b in zip(stops, stops[1:])) == seq.moves * seq.step_deg
    assert stops[-1].t_end_s == seq.end_s == plan.duration_s
    for s in stops:
        assert s.t_end_s - s.t_start_s == pytest.approx(seq.dwell_s)
        t = np.linspace(s.t_start_s, s.t_end_s, 101)
        assert np.all(plan.angle_deg(t) == s.angle_deg)  # exactly, not approximately
        assert np.all(plan.rate_dps(t) == 0.0)
    # before the sequence 0, long after it the last angle
    assert plan.angle_deg(np.array([-5.0, 0.0, seq.start_s]))[()].tolist() == [0.0, 0.0, 0.0]
    assert plan.angle_deg(np.array(seq.end_s + 1e5))[()] == seq.moves * seq.step_deg


@given(
    st.integers(1, 12),
    st.floats(0.5, 400.0).map(lambda x: round(x, 2)) | st.floats(-400.0, -0.5).map(lambda x: round(x, 2)),
    st.floats(1.0, 100.0),
    st.floats(0.5, 50.0),
    st.floats(0.5, 100.0),
)
def test_random_positioning_sequences(moves, step_deg, max_rate, accel, dwell):
    seq = Positioning(7.0, moves, step_deg, dwell_s=dwell, max_rate_dps=max_rate, accel_dps2=accel)
    plan = MotionPlan((seq,))
    stops = plan.dwells()
    assert [s.angle_deg for s in stops] == [k * step_deg for k in range(moves + 1)]
    for s in stops:
        assert np.all(plan.angle_deg(np.array([s.t_start_s, (s.t_start_s + s.t_end_s) / 2])) == s.angle_deg)
    assert seq.peak_rate_dps <= max_rate * (1 + 1e-12)
    t = np.union1d(np.linspace(0, seq.end_s + 1, 20_001), move_breakpoints(seq))
    rate = plan.rate_dps(t)
    assert np.abs(rate).max() <= max_rate * (1 + 1e-9)
    assert np.all(np.abs(np.diff(rate)) <= accel * np.diff(t) * (1 + 1e-9) + 1e-9)
    atol = 1e-6 * max(1.0, abs(step_deg) * moves / 100)  # float rounding grows with the total angle
    np.testing.assert_allclose(plan.angle_deg(t), cumulative_trapezoid(t, rate), rtol=0, atol=atol)
    assert seq.duration_s == pytest.approx(dwell + moves * (seq.move_time_s + dwell))


def test_constant_rate_and_mixed_plans():
    seq = Positioning(start_s=200.0, moves=2, step_deg=90.0, max_rate_dps=30.0)
    plan = MotionPlan((seq, ConstantRate(5.0, 10.0, 110.0)))
    assert plan.kind == "mixed"
    assert isinstance(plan.items[0], ConstantRate)  # kept in time order
    np.testing.assert_allclose(plan.angle_deg(np.array([0.0, 10.0, 60.0, 110.0, 150.0])), [0, 0, 250, 500, 500])
    np.testing.assert_array_equal(plan.rate_dps(np.array([9.9, 10.0, 109.9, 110.0])), [0, 5, 5, 0])
    assert [s.angle_deg for s in plan.dwells()] == [500.0, 590.0, 680.0]
    forever = MotionPlan((ConstantRate(-2.5, 100.0),))
    assert forever.final_rate_dps == -2.5 and forever.duration_s == 100.0
    assert forever.angle_deg(np.array(1100.0))[()] == -2500.0
    static = MotionPlan.static()
    assert static.kind == "static" and static.duration_s == 0.0 and static.dwells() == []
    t = np.linspace(-1.0, 1e4, 1000)
    assert np.all(static.rate_dps(t) == 0) and np.all(static.angle_deg(t) == 0)


def test_motion_evaluation_is_vectorized():
    plan = load_profile("paper-validation").motion
    t = np.linspace(0.0, 1010 * 60.0, 2_600_000)
    angle = plan.angle_deg(t)
    assert angle.shape == t.shape and angle[0] == 0.0 and angle[-1] == 11 * 360.0
    assert np.all(np.diff(angle) >= 0)
    assert plan.rate_dps(t.reshape(1000, 2600)).shape == (1000, 2600)


def test_overlapping_motion_is_refused():
    with pytest.raises(ValueError, match="overlaps"):
        MotionPlan((Positioning(start_s=0.0), Positioning(start_s=500.0)))
    with pytest.raises(ValueError, match="overlaps"):
        MotionPlan((ConstantRate(1.0, 0.0), Positioning(start_s=500.0)))
    MotionPlan((Positioning(start_s=0.0), ConstantRate(1.0, Positioning(start_s=0.0).end_s)))  # touching is fine


def test_positioning_at_plateau_must_fit_the_plateau():
    chamber = ChamberProfile("c", 20.0, (Hold(600.0), Ramp(1.0, 25.0), Hold(1200.0)))
    seq = positioning_at_plateau(chamber, 1, settle_s=300.0)
    assert seq.start_s == 900.0 + 300.0
    with pytest.raises(ValueError, match="would end at"):
        positioning_at_plateau(chamber, 0)
    with pytest.raises(ValueError, match="has 2 plateaus"):
        positioning_at_plateau(chamber, 2)


# --- YAML ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", SHIPPED)
def test_shipped_profiles_round_trip(name, tmp_path):
    prof = load_profile(PROFILES / f"{name}.yaml")
    assert prof.name == name
    path = tmp_path / f"{name}.yaml"
    path.write_text(dump_profile(prof))
    again = load_profile(path)
    assert again.chamber == prof.chamber and again.motion == prof.motion and again.name == prof.name


def test_every_profile_named_in_the_docs_is_shipped():
    assert {"paper", "fast-ramps", "short-test", "positioning", "calibration", "chamber-cycle"} <= set(SHIPPED)
    assert {"steps-moves", "soak-cycle", "table-run", "scale-factor-run"} <= set(SHIPPED)


@pytest.mark.parametrize("name", SHIPPED)
def test_a_shipped_profiles_table_motion_ends_within_its_chamber_program(name):
    prof = load_profile(PROFILES / f"{name}.yaml")
    assert prof.motion.duration_s <= prof.chamber.duration_s


def test_the_scale_factor_run_holds_long_and_moves_both_ways_at_every_hold():
    """What its comment promises: holds of 60 min or more at 20, 45, -15 and 20 degC, and dwells all through
    them between moves of both signs that sum to 0 (so a scale factor is told from a drift)."""
    prof = load_profile(PROFILES / "scale-factor-run.yaml")
    plateaus = prof.chamber.plateaus()
    assert [round(p.temp_c) for p in plateaus] == [20, 45, -15, 20]
    assert all(p.t_end_s - p.t_start_s >= 40 * 60 for p in plateaus)
    assert all(p.t_end_s - p.t_start_s >= 60 * 60 for p in plateaus[1:])
    (positioning,) = prof.motion.items
    assert sum(positioning.step_deg) == 0 and min(positioning.step_deg) < 0 < max(positioning.step_deg)
    stops = prof.motion.dwells()
    for p in plateaus:
        inside = [s for s in stops if p.t_start_s + 300 <= s.t_start_s and s.t_end_s <= p.t_end_s]
        moves = np.diff([s.angle_deg for s in inside])
        assert len(inside) >= 6 and (moves > 0).any() and (moves < 0).any()


@pytest.mark.parametrize("name", ["paper", "paper-validation", "calibration"])
def test_builtin_profiles_round_trip(name):
    prof = load_profile(name)
    again = parse_profile(yaml.safe_load(dump_profile(prof)), "dumped")
    assert again.chamber == prof.chamber and again.motion == prof.motion


def test_durations_in_minutes_or_seconds_and_default_name(tmp_path):
    path = tmp_path / "my-run.yaml"
    path.write_text(
        "start_c: 5\nsegments:\n  - hold: {duration_s: 90}\n  - hold: {duration_min: 1.5}\n"
        "  - sinusoid: {amplitude_c: 1, period_s: 30, duration_min: 2}\n"
    )
    prof = load_profile(path)
    assert prof.name == "my-run" and prof.motion == MotionPlan.static()
    assert prof.chamber.segments == (Hold(90.0), Hold(90.0), Sinusoid(1.0, 30.0, 120.0))


SEGS = "start_c: 20\nsegments:\n"
GOOD = SEGS + "  - hold: {duration_min: 30}\n"


@pytest.mark.parametrize(
    "text, needle",
    [
        (
            SEGS + "  - ramp: {rate_c_per_min: -1, target_c: 30}\n",
            "segments[0] (ramp): rate_c_per_min must be positive, got -1",
        ),
        (
            SEGS + "  - hold: {duration_s: 5}\n  - ramp: {rate_c_per_min: 0, target_c: 30}\n",
            "segments[1] (ramp): rate_c_per_min must be positive",
        ),
        (
            SEGS + "  - ramp: {rate_c_per_min: fast, target_c: 30}\n",
            "rate_c_per_min must be a finite number, got 'fast'",
        ),
        (SEGS + "  - ramp: {rate_c_per_min: 1}\n", "segments[0] (ramp): missing target_c"),
        (SEGS + "  - hold: {duraton_min: 3}\n", "segments[0] (hold): unknown key 'duraton_min'"),
        (SEGS + "  - soak: {duration_min: 3}\n", "segments[0]: unknown segment kind 'soak'"),
        (
            SEGS + "  - hold: {duration_min: 3, duration_s: 180}\n",
            "exactly one of duration_min and duration_s, not both",
        ),
        (SEGS + "  - hold: {}\n", "segments[0] (hold): give exactly one of duration_min and duration_s"),
        (SEGS + "  - hold: {duration_min: -3}\n", "duration_min must be positive"),
        (
            SEGS + "  - sinusoid: {amplitude_c: -1, period_min: 3, duration_min: 3}\n",
            "amplitude_c must not be negative",
        ),
        (SEGS + "  - sinusoid: {amplitude_c: 1, duration_min: 3}\n", "exactly one of period_min and period_s"),
        (SEGS + "  - {hold: {duration_min: 3}, step: {target_c: 4}}\n", "segments[0]: expected a one-key mapping"),
        (SEGS + "  - hold\n", "segments[0]: expected a one-key mapping"),
        ("start_c: 20\nsegments: []\n", "segments must be a non-empty list"),
        ("start_c: 20\n", "missing segments"),
        ("segments:\n  - hold: {duration_min: 3}\n", "missing start_c"),
        ("start_c: .nan\nsegments:\n  - hold: {duration_min: 3}\n", "start_c must be a finite number"),
        ("stat_c: 20\nstart_c: 20\nsegments:\n  - hold: {duration_min: 3}\n", "unknown key 'stat_c'"),
        ("name: [a]\n" + GOOD, "name must be a one-line string"),
        ("- a list\n", "expected a mapping with start_c and segments, got a list"),
        ("", "expected a mapping with start_c and segments, got nothing"),
        ("start_c: [unclosed\n", "not valid YAML at line"),
        ("start_c: !!python/object/apply:os.system ['true']\n", "not valid YAML"),
        (GOOD + "motion: {kind: spin}\n", "motion: unknown motion kind 'spin'"),
        (GOOD + "motion: {rate_dps: 3}\n", "motion: missing kind"),
        (GOOD + "motion: {kind: constant_rate}\n", "motion (constant_rate): missing rate_dps"),
        (
            GOOD + "motion: {kind: constant_rate, rate_dps: 1, start_s: 50, stop_s: 10}\n",
            "stop_s (10) must be after start_s (50)",
        ),
        (GOOD + "motion: {kind: static, rate_dps: 1}\n", "motion (static): unknown key 'rate_dps'"),
        (GOOD + "motion: {kind: positioning}\n", "motion (positioning): give exactly one of start_s and at_plateau"),
        (GOOD + "motion: {kind: positioning, start_s: 0, at_plateau: 0}\n", "exactly one of start_s and at_plateau"),
        (GOOD + "motion: {kind: positioning, start_s: 0, settle_s: 10}\n", "settle_s goes with at_plateau"),
        (GOOD + "motion: {kind: positioning, at_plateau: 3}\n", "at_plateau 3 but the chamber profile has 1 plateaus"),
        (GOOD + "motion: {kind: positioning, at_plateau: 0, settle_s: 1200}\n", "would end at 1897.9"),
        (GOOD + "motion: {kind: positioning, start_s: 0, moves: 0}\n", "moves must be an integer >= 1, got 0"),
        (GOOD + "motion: {kind: positioning, start_s: 0, max_rate_dps: 0}\n", "max_rate_dps must be positive"),
        (
            GOOD + "motion: {kind: positioning, start_s: 0, moves: 10, step_deg: 36, dwel_s: 60}\n",
            "unknown key 'dwel_s'",
        ),
        (
            GOOD + "motion:\n  - {kind: positioning, start_s: 0}\n  - {kind: positioning, start_s: 600}\n",
            "motion: positioning 10 x 36 deg from 600 s",
        ),
        (GOOD + "motion:\n  - {kind: positioning, start_s: 0}\n  - 7\n", "motion[1]: expected a mapping"),
    ],
)
def test_bad_profile_is_a_one_line_error_naming_the_file_and_item(tmp_path, text, needle):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(InputFileError) as info:
        load_profile(path)
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith(f"{path}: ")
    assert needle in message


def test_bad_profile_files(tmp_path):
    with pytest.raises(
        InputFileError,
        match=r"no such profile file \(profiles: paper, paper-validation, calibration, chamber-cycle, fast-ramps",
    ):
        load_profile(tmp_path / "nope.yaml")
    with pytest.raises(InputFileError, match=r"papper: no such profile \(profiles: paper, "):
        load_profile("papper")
    with pytest.raises(InputFileError, match="is a directory"):
        load_profile(tmp_path)
    big = tmp_path / "big.yaml"
    big.write_text(GOOD + "#" * (1 << 20))
    with pytest.raises(InputFileError, match="larger than 1048576 bytes"):
        load_profile(big)
    many = tmp_path / "many.yaml"
    many.write_text("start_c: 20\nsegments:\n" + "  - hold: {duration_s: 1}\n" * (MAX_SEGMENTS + 1))
    with pytest.raises(InputFileError, match=f"{MAX_SEGMENTS + 1} segments, more than the limit of {MAX_SEGMENTS}"):
        load_profile(many)
    ok = tmp_path / "ok.yaml"
    ok.write_text("start_c: 20\nsegments:\n" + "  - hold: {duration_s: 1}\n" * MAX_SEGMENTS)
    assert load_profile(ok).chamber.duration_s == MAX_SEGMENTS
    binary = tmp_path / "bin.yaml"
    binary.write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(InputFileError, match="cannot read profile"):
        load_profile(binary)


def test_segment_dataclasses_validate_their_arguments():
    with pytest.raises(ValueError, match="rate_c_per_min must be positive"):
        Ramp(0.0, 10.0)
    with pytest.raises(ValueError, match="duration_s must be positive"):
        Hold(-1.0)
    with pytest.raises(ValueError, match="step_deg must not be 0"):
        Positioning(start_s=0.0, step_deg=0.0)
    with pytest.raises(TypeError, match="not a chamber segment"):
        ChamberProfile("x", 0.0, ("hold",))


def test_profile_names_resolve_from_configs_profiles(tmp_path, monkeypatch):
    """``--profile fast-ramps`` failed ("built-in profiles: paper, paper-validation"); a name now also
    means ``configs/profiles/<name>.yaml``, from the current directory or the source tree."""
    from fog_driver.errors import InputFileError
    from fog_driver.lab.profiles import load_profile, profile_names

    repo = Path(__file__).resolve().parents[2]
    by_path = load_profile(str(repo / "configs" / "profiles" / "fast-ramps.yaml"))
    monkeypatch.chdir(tmp_path)  # not the repository: the source tree's folder serves
    assert load_profile("fast-ramps") == by_path
    assert {"paper", "paper-validation", "fast-ramps", "positioning", "soak-cycle"} <= set(profile_names())
    (tmp_path / "configs" / "profiles").mkdir(parents=True)  # the current directory's folder comes first
    (tmp_path / "configs" / "profiles" / "fast-ramps.yaml").write_text(
        "name: mine\nstart_c: 20\nsegments:\n  - hold: {duration_min: 5}\n"
    )
    assert load_profile("fast-ramps").name == "mine"
    with pytest.raises(
        InputFileError, match=r"nope: no such profile \(profiles: paper, paper-validation, .*fast-ramps"
    ):
        load_profile("nope")


def test_a_list_of_steps_is_taken_in_turn_with_each_moves_own_shape():
    """Moves of both signs and several sizes: move k steps step_deg[k % len]; each move's shape (triangle or
    trapezoid) from its own size; the dwells' angles are the running sums; the sequence's duration adds
    each move's time; through YAML and back the same plan."""
    seq = Positioning(start_s=5.0, moves=5, step_deg=[36.0, -72.0, 45.0], dwell_s=12.0)
    assert seq.steps_deg == (36.0, -72.0, 45.0, 36.0, -72.0)
    shapes = [seq.shape(k) for k in range(seq.moves)]
    assert [m.triangular for m in shapes] == [True, False, False, True, False]  # 40 deg = 20^2 / 10
    assert shapes[1].move_time_s == pytest.approx(2 * 2.0 + (72.0 - 40.0) / 20.0)
    assert seq.duration_s == pytest.approx(12.0 + sum(m.move_time_s + 12.0 for m in shapes))
    plan = MotionPlan((seq,))
    stops = plan.dwells()
    assert [s.angle_deg for s in stops] == [0.0, 36.0, -36.0, 9.0, 45.0, -27.0]
    t = np.array([(s.t_start_s + s.t_end_s) / 2 for s in stops])
    np.testing.assert_array_equal(plan.angle_deg(t), [s.angle_deg for s in stops])
    assert np.abs(plan.rate_dps(np.arange(0.0, seq.end_s, 0.01))).max() <= 20.0
    doc = yaml.safe_load(dump_profile(SimProfile("p", ChamberProfile("p", 20.0, (Hold(seq.end_s + 10),)), plan, "t")))
    assert doc["motion"]["step_deg"] == [36, -72, 45]
    again = parse_profile(doc)
    assert again.motion.dwells() == stops
    with pytest.raises(ValueError, match="step_deg"):
        Positioning(start_s=0.0, step_deg=[36.0, 0.0])
    with pytest.raises(ValueError, match="empty"):
        Positioning(start_s=0.0, step_deg=[])


def test_a_creep_is_motion_that_adds_to_the_other_items_and_moves_the_dwells():
    """A creep of rate_dph over its span: the angle gains rate (clip(t) - start) on top of the positioning it
    overlaps, the rate is its integral's derivative, and the dwells it covers turn from angle_deg to
    angle_end_deg (the table log's truth); stops outside it keep their commanded angle."""
    seq = Positioning(start_s=100.0, moves=4, step_deg=[36.0, -18.0], dwell_s=30.0)
    creep = Creep(rate_dph=20.0, start_s=150.0, stop_s=260.0)
    plan, still = MotionPlan((seq, creep)), MotionPlan((seq,))
    t = np.union1d(np.arange(0.0, seq.end_s + 60.0, 1e-3), [*move_breakpoints(seq), 150.0, 260.0])
    extra = plan.angle_deg(t) - still.angle_deg(t)
    np.testing.assert_allclose(extra, 20.0 / 3600.0 * (np.clip(t, 150.0, 260.0) - 150.0), rtol=0, atol=1e-12)
    # the rate steps at the creep's ends: the trapezoid rule errs by at most half a step times 1 ms at each
    np.testing.assert_allclose(plan.angle_deg(t), cumulative_trapezoid(t, plan.rate_dps(t)), rtol=0, atol=6e-6)
    assert plan.rate_dps(np.array([149.999, 150.0, 259.999, 260.0])).tolist() == pytest.approx(
        [still.rate_dps(np.array([149.999]))[0], *(still.rate_dps(np.array([150.0, 259.999])) + 20.0 / 3600.0), 0.0]
    )
    for a, b in zip(plan.dwells(), still.dwells()):
        assert (a.t_start_s, a.t_end_s) == (b.t_start_s, b.t_end_s)
        covered = min(a.t_end_s, 260.0) - max(a.t_start_s, 150.0)
        start_gain = 20.0 / 3600.0 * (min(max(a.t_start_s, 150.0), 260.0) - 150.0)
        assert a.angle_deg == pytest.approx(b.angle_deg + start_gain, abs=1e-12)
        assert a.angle_end_deg - a.angle_deg == pytest.approx(20.0 / 3600.0 * max(covered, 0.0), abs=1e-12)
    assert plan.kind == "mixed" and MotionPlan((creep,)).kind == "creep"
    assert plan.duration_s == seq.end_s and MotionPlan((creep,)).duration_s == 260.0
    doc = yaml.safe_load(dump_profile(SimProfile("p", ChamberProfile("p", 20.0, (Hold(600.0),)), plan, "t")))
    assert parse_profile(doc).motion.dwells() == plan.dwells()
    with pytest.raises(InputFileError, match="missing start_s"):
        parse_profile(
            {"start_c": 20, "segments": [{"hold": {"duration_s": 60}}], "motion": {"kind": "creep", "rate_dph": 1}}
        )
    with pytest.raises(ValueError, match="after start_s"):
        Creep(rate_dph=1.0, start_s=10.0, stop_s=10.0)
    with pytest.raises(ValueError, match="rate_dph"):
        Creep(rate_dph=math.nan, start_s=0.0, stop_s=10.0)


@pytest.mark.parametrize(
    "motion, segments, match",
    [
        (None, [{"hold": {"duration_s": 1e300}}], "the chamber program lasts .* more than the limit of 31 days"),
        ({"kind": "creep", "rate_dph": 0.2, "start_s": 10, "stop_s": 1e300}, None, "the motion lasts .* 31 days"),
        ({"kind": "constant_rate", "rate_dps": 1e9}, None, "rate_dps 1e\\+09 is beyond a turntable's 1000 deg/s"),
        ({"kind": "creep", "rate_dph": -1e12, "start_s": 0, "stop_s": 5}, None, "rate_dph -1e\\+12 is beyond"),
        ({"kind": "positioning", "start_s": 0, "max_rate_dps": 5000}, None, "max_rate_dps 5000 is beyond"),
        ({"kind": "positioning", "start_s": 0, "moves": 10**8}, None, "must not exceed 10,000"),
        ({"kind": "positioning", "start_s": 0, "step_deg": [1.0] * 10_001}, None, "must not exceed 10,000"),
    ],
)
def test_a_profile_that_would_never_end_or_turn_beyond_a_table_is_one_line_and_refused_at_once(motion, segments, match):
    """Absurd numbers in a profile are refused when it is read (a run of 1e300 s would fill the disk; a
    sequence of 1e8 moves would take minutes to plan), each as one line naming the place."""
    doc = {"start_c": 20, "segments": segments or [{"hold": {"duration_s": 60}}]}
    if motion is not None:
        doc["motion"] = motion
    with pytest.raises(InputFileError, match=match) as info:
        parse_profile(doc)
    assert "\n" not in str(info.value)


def test_a_rate_that_overflows_a_frame_is_a_usage_error_and_leaves_no_files(tmp_path):
    """1000 deg/s is a table's rate, but at 0.0001 arcsec per count one 10-Hz frame of it overflows the i32
    dtheta field: a one-line usage error, and the run's capture and truth are removed."""
    from fog_driver.errors import UsageError
    from fog_driver.sim.capture import simulate_to_file
    from fog_driver.sim.instrument import InstrumentConfig, Simulator

    doc = {
        "start_c": 20,
        "segments": [{"hold": {"duration_s": 60}}],
        "motion": {"kind": "constant_rate", "rate_dps": 1000},
    }
    sim = Simulator(parse_profile(doc), InstrumentConfig(scale_arcsec_per_count=1e-4), rate_hz=10, seed=1)
    with pytest.raises(UsageError, match="overflows the frame's i32 dtheta field"):
        simulate_to_file(sim, tmp_path / "fast.bin")
    assert list(tmp_path.iterdir()) == []
