"""Model-rate blocks and the input features: step == run, exact values, gaps and NaN handling."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fog_driver.compensation.blocks import BlockAverager, BlockColumns
from fog_driver.compensation.features import FeatureExtractor, FeatureParams
from fog_driver.flags import FLAG_GAP, FLAG_THERMOMETER_FAULT
from fog_driver.samples.stream import SampleBlock


def make_samples(n: int, rate_hz: int = 10, seed: int = 0, missing: tuple[int, ...] = (), nan_at: tuple[int, ...] = ()):
    rng = np.random.default_rng(seed)
    k = np.arange(n + len(missing) + 5)
    keep = np.ones(len(k), bool)
    for m in missing:
        if m < len(k):
            keep[m] = False
    k = k[keep][:n]
    t_s = (1_000_000 + k * (1_000_000 // rate_hz)) / 1e6
    counts = rng.integers(-50, 50, n)
    scale = float(np.float32(0.01))  # the wire's float32 scale, as SampleStream holds it
    temps = np.round(rng.normal(20, 3, (n, 3)) * 256) / 256
    for i in nan_at:
        temps[i, i % 3] = np.nan
    missing_before = np.r_[0, np.diff(k) - 1]
    return SampleBlock(
        seq=k.astype(np.int64),
        t_s=t_s,
        dtheta_arcsec=counts * scale,
        t_top_c=temps[:, 0],
        t_bottom_c=temps[:, 1],
        t_housing_c=temps[:, 2],
        status=np.zeros(n, np.uint16),
        missing_before=missing_before.astype(np.int64),
        offset=k * 26,
    )


def slice_block(s: SampleBlock, lo: int, hi: int) -> SampleBlock:
    return SampleBlock(*(getattr(s, f)[lo:hi] for f in SampleBlock.__dataclass_fields__))


def assert_columns_equal(a: BlockColumns, b: BlockColumns) -> None:
    for f in BlockColumns.__dataclass_fields__:
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f), err_msg=f)


@settings(max_examples=60, deadline=None)
@pytest.mark.determinism
@given(
    st.integers(1, 400),
    st.lists(st.integers(0, 400), max_size=6),
    st.lists(st.integers(0, 399), max_size=5),
    st.lists(st.integers(0, 399), max_size=5),
)
def test_run_equals_step_for_any_split(n, cuts, missing, nan_at):
    samples = make_samples(n, missing=tuple(sorted(set(missing))), nan_at=tuple(i for i in nan_at if i < n))
    stepper = BlockAverager(0.1)
    stepped = [b for i in range(n) for b in stepper.step(samples.sample(i))] + stepper.flush()
    reference = BlockColumns.from_blocks(stepped)
    runner = BlockAverager(0.1)
    bounds = sorted({0, n, *(min(c, n) for c in cuts)})
    parts = [runner.run(slice_block(samples, lo, hi)) for lo, hi in zip(bounds, bounds[1:])]
    parts.append(runner.run(slice_block(samples, n, n), final=True))
    joined = BlockColumns(*(np.concatenate([getattr(p, f) for p in parts]) for f in BlockColumns.__dataclass_fields__))
    assert_columns_equal(joined, reference)


def test_block_values_by_hand():
    samples = make_samples(25, rate_hz=10, missing=(12,), nan_at=(3,))
    blocks = BlockAverager(0.1).run(samples, final=True)
    assert blocks.index.tolist() == [0, 1, 2]
    assert blocks.n_samples.tolist() == [10, 9, 6]  # sample 12 never arrived
    first = slice(0, 10)
    assert blocks.rate_dph[0] == pytest.approx(samples.dtheta_arcsec[first].sum() / 1.0)
    assert blocks.temps_c[0, 0] == pytest.approx(np.nanmean(samples.t_top_c[first]))
    assert blocks.flags.tolist() == [FLAG_THERMOMETER_FAULT, FLAG_GAP, 0]
    assert blocks.t_end_s.tolist() == pytest.approx([1.0, 2.0, 2.6])


def test_features_rate_is_exact_for_a_ramp_and_gradients_are_differences():
    fx = FeatureExtractor(FeatureParams(sample_time_s=1.0, rate_tau_fast_s=30, rate_tau_slow_s=90))
    t = np.arange(1500.0)
    temps = np.column_stack([20 + t / 60.0, 19 + t / 120.0, 25 - t / 60.0])  # 1, 0.5, -1 degC/min
    u, flags = fx.run(temps)
    np.testing.assert_allclose(u[-1, 3:6], [1.0, 0.5, -1.0], rtol=1e-6)
    np.testing.assert_allclose(u[:, 6], temps[:, 0] - temps[:, 1])
    np.testing.assert_allclose(u[:, 7], temps[:, 0] - temps[:, 2])
    assert not flags.any()


def test_features_step_state_round_trip():
    rng = np.random.default_rng(1)
    temps = np.cumsum(rng.normal(0, 0.05, (200, 3)), axis=0) + 20
    whole, _ = FeatureExtractor().run(temps)
    first = FeatureExtractor()
    a, _ = first.run(temps[:77])
    second = FeatureExtractor(state=first.get_state())
    b, _ = second.run(temps[77:])
    np.testing.assert_array_equal(np.vstack([a, b]), whole)
