"""Before the model gives an estimate, none is published: drift_dph and drift_sigma_dph are NaN (absent), the
frame is flagged uncompensated and compensated by nothing (dtheta_comp = dtheta), so the compensated angle is
the raw one's increments and never NaN.  step == run for every split; the daemon omits the keys, the UDP
datagram and the CSV carry NaN; a state saved then round-trips."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from fog_driver.client.udp import decode_datagram
from fog_driver.compensation.pipeline import MAX_GAP_S, CompensatedColumns, Compensator
from fog_driver.daemon.config import DEFAULT_MODEL
from fog_driver.daemon.udp import encode_datagram, fields_from_angle
from fog_driver.flags import FLAG_UNCOMPENSATED
from fog_driver.modelfiles import load_model
from fog_driver.offline.rows import RowAggregator, format_row
from fog_driver.protocol import decode_file
from fog_driver.samples.stream import SampleBlock, SampleStream

DATA = Path(__file__).resolve().parents[1] / "data"
PERIOD_S = 0.1


@pytest.fixture(scope="module")
def samples() -> SampleBlock:
    return SampleStream().run(decode_file(DATA / "sim-short.bin")).take(slice(0, 600))  # 60 s


@pytest.fixture(scope="module")
def gapped(samples) -> SampleBlock:
    """The first 30 s, then the next 30 s a little more than MAX_GAP_S later (the link was down)."""
    t_s = samples.t_s.copy()
    t_s[300:] += MAX_GAP_S + 5.0
    missing = samples.missing_before.copy()
    missing[300] = int((MAX_GAP_S + 5.0) / PERIOD_S)
    return dataclasses.replace(samples, t_s=t_s, missing_before=missing)


def stepped(model_file, block: SampleBlock) -> CompensatedColumns:
    comp = Compensator(model_file, PERIOD_S)
    rows = [comp.step(block.sample(i)) for i in range(len(block))]
    return CompensatedColumns(
        *(np.array([getattr(r, f) for r in rows]) for f in CompensatedColumns.__dataclass_fields__)
    )


def assert_no_estimate_where_uncompensated(cols: CompensatedColumns) -> np.ndarray:
    """Where a frame is flagged uncompensated: no drift, no sigma, nothing subtracted; elsewhere an estimate.
    The compensated angle is finite everywhere and, over the frames before the first estimate, the raw one."""
    none = (cols.flags & FLAG_UNCOMPENSATED) != 0
    assert np.isnan(cols.drift_dph[none]).all() and np.isnan(cols.drift_sigma_dph[none]).all()
    assert np.isfinite(cols.drift_dph[~none]).all()
    np.testing.assert_array_equal(cols.dtheta_comp_arcsec[none], cols.dtheta_arcsec[none])
    assert np.isfinite(cols.angle_comp_arcsec).all()
    head = np.argmax(~none)  # the frames before the first estimate
    np.testing.assert_array_equal(cols.angle_comp_arcsec[:head], np.cumsum(cols.dtheta_arcsec[:head]))
    np.testing.assert_array_equal(cols.angle_comp_arcsec[:head], cols.angle_raw_arcsec[:head])
    return none


def test_the_first_block_of_a_run_publishes_no_estimate(samples):
    cols = Compensator(load_model(DEFAULT_MODEL), PERIOD_S).run(samples)
    first_block = cols.t_s - cols.t_s[0] < 1.0 - 1e-9
    none = assert_no_estimate_where_uncompensated(cols)
    np.testing.assert_array_equal(none, first_block)  # exactly the first block: then the model estimates


def test_after_a_gap_longer_than_max_gap_the_first_block_publishes_no_estimate(gapped):
    """The pipeline restarts at rest: the frames of the first block after the gap have no estimate (the one from
    before the gap is stale), as at switch-on; the next block's estimate is the restarted model's."""
    cols = Compensator(load_model(DEFAULT_MODEL), PERIOD_S).run(gapped)
    none = assert_no_estimate_where_uncompensated(cols)
    rel = cols.t_s - cols.t_s[0]
    after = cols.t_s - cols.t_s[300]
    want = (rel < 1.0 - 1e-9) | ((after >= 0) & (after < 1.0 - 1e-9) & (np.arange(len(cols)) >= 300))
    np.testing.assert_array_equal(none, want)
    # the restarted model estimates as a fresh run of the frames after the gap does
    fresh = Compensator(load_model(DEFAULT_MODEL), PERIOD_S).run(gapped.take(slice(300, None)))
    np.testing.assert_array_equal(cols.drift_dph[300:], fresh.drift_dph)


def test_a_thermometer_never_valid_publishes_no_estimate(samples):
    nan = np.full(len(samples), math.nan)
    dead = dataclasses.replace(samples, t_top_c=nan, t_bottom_c=nan, t_housing_c=nan)
    cols = Compensator(load_model(DEFAULT_MODEL), PERIOD_S).run(dead)
    none = assert_no_estimate_where_uncompensated(cols)
    assert none.all()
    np.testing.assert_array_equal(cols.angle_comp_arcsec, cols.angle_raw_arcsec)


@settings(max_examples=8, deadline=None)
@given(st.lists(st.integers(0, 600), max_size=6))
def test_step_equals_run_for_any_split_across_the_first_block_and_a_long_gap(gapped, cuts):
    model_file = load_model(DEFAULT_MODEL)
    want = stepped(model_file, gapped)
    runner = Compensator(model_file, PERIOD_S)
    bounds = sorted({0, len(gapped), *cuts})
    parts = [runner.run(gapped.take(slice(lo, hi))) for lo, hi in zip(bounds, bounds[1:])]
    for f in CompensatedColumns.__dataclass_fields__:
        got = np.concatenate([getattr(p, f) for p in parts])
        np.testing.assert_array_equal(got, getattr(want, f), err_msg=f)  # NaN equals NaN here


def test_a_datagram_of_a_sample_without_an_estimate_carries_nan():
    """The daemon's first ANGLE object omits both keys; its datagram (as the UDP publisher sends it) has NaN."""
    from fog_driver.daemon.config import DriverConfig
    from fog_driver.daemon.service import Service

    published = Service(DriverConfig(), port="unused").process((DATA / "sim-short.bin").read_bytes()[:4096])
    first = published[0]
    assert "drift_dph" not in first and "drift_sigma_dph" not in first and "uncompensated" in first["flags"]
    for version in (1, 2):
        got = decode_datagram(encode_datagram(**fields_from_angle(first), version=version))
        assert math.isnan(got["drift_dph"]) and math.isnan(got["drift_sigma_dph"])
        assert got["angle_arcsec"] == first["angle_arcsec"] == first["angle_raw_arcsec"]


def test_the_csv_row_of_the_first_block_writes_nan_for_the_drift_and_its_sigma(samples):
    cols = Compensator(load_model(DEFAULT_MODEL), PERIOD_S).run(samples)
    rows = RowAggregator(1.0, PERIOD_S).add(cols)
    cells = format_row(rows[0]).split(",")
    assert cells[3] == "nan" and cells[-1] == "nan" and "uncompensated" in cells[-2]
    assert cells[2] == cells[4]  # rate_comp_dph = rate_raw_dph: nothing subtracted
    later = format_row(rows[1]).split(",")
    assert later[3] != "nan" and later[-1] != "nan" and "uncompensated" not in later[-2]


def test_a_state_saved_before_the_first_estimate_round_trips(samples):
    model_file = load_model(DEFAULT_MODEL)
    whole = Compensator(model_file, PERIOD_S).run(samples)
    first = Compensator(model_file, PERIOD_S)
    head = first.run(samples.take(slice(0, 5)))
    assert np.isnan(head.drift_dph).all() and math.isnan(first.estimate_dph)
    state = yaml.safe_load(yaml.safe_dump(first.get_state()))  # as the adaptation file stores it
    assert math.isnan(state["estimate_dph"])
    second = Compensator(model_file, PERIOD_S)
    second.set_state(state)
    tail = second.run(samples.take(slice(5, None)))
    for f in CompensatedColumns.__dataclass_fields__:
        got = np.concatenate([getattr(head, f), getattr(tail, f)])
        np.testing.assert_array_equal(got, getattr(whole, f), err_msg=f)
