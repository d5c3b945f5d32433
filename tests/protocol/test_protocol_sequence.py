"""The unwrapping leaf: closed-form wrap cases, step against run at every split point, and greedy accept."""

from __future__ import annotations

import numpy as np
import pytest

from fog_driver.protocol.decoder import DecoderCounters
from fog_driver.protocol.greedy import greedy_accept
from fog_driver.protocol.sequence import Unwrapper, count_seq_step, count_seq_steps, missing_before


def test_closed_form_forward_wraps() -> None:
    u = Unwrapper(1 << 16)
    assert u.step(65534) is None and u.value == 65534
    assert u.step(65535) == 1 and u.value == 65535
    assert u.step(0) == 1 and u.value == 65536 and u.wraps == 1
    assert u.step(5) == 5 and u.value == 65541
    assert u.step(5) == 0 and u.value == 65541  # a repeat
    assert u.step(4) == 65535 and u.value == 65541 + 65535 and u.wraps == 2  # forward-only: all the way round
    clock = Unwrapper(1 << 32)
    clock.step((1 << 32) - 1000)
    clock.step(500)
    assert clock.value == (1 << 32) + 500 and clock.delta == 1500 and clock.wraps == 1


def test_closed_form_signed_steps_back() -> None:
    u = Unwrapper(1 << 32, signed=True)
    u.step(100)
    assert u.step(90) == -10 and u.value == 90 and u.wraps == 0
    assert u.step((1 << 32) - 5) == -95 and u.value == -5 and u.wraps == 0  # back across zero: no wrap
    assert u.step(3) == 8 and u.value == 3 and u.wraps == 1  # forward across the modulus
    half = 1 << 31
    v = Unwrapper(1 << 32, signed=True)
    v.step(0)
    assert v.step(half - 1) == half - 1  # just under half the range: forward
    w = Unwrapper(1 << 32, signed=True)
    w.step(0)
    assert w.step(half) == -half  # half the range or more: back


def test_a_modulus_that_is_not_a_power_of_two() -> None:
    u = Unwrapper(100)
    assert u.mask is None
    assert [u.step(r) for r in (98, 99, 0, 3)] == [None, 1, 1, 3] and u.value == 103 and u.wraps == 1
    v = Unwrapper(100)
    out = v.run(np.array([98, 99, 0, 3]))
    assert out.value.tolist() == [98, 99, 100, 103] and out.step.tolist() == [0, 1, 1, 3] and v.wraps == 1
    with pytest.raises(ValueError):
        Unwrapper(1)


def _readings(modulus: int, n: int, seed: int) -> np.ndarray:
    """A counter with normal steps, repeats, gaps, and wraps (several times round a small modulus)."""
    rng = np.random.default_rng(seed)
    steps = rng.choice([1, 1, 1, 1, 0, 2, 7, modulus // 2 + 1, modulus - 1], size=n)
    return (rng.integers(0, modulus) + np.cumsum(steps)) % modulus


@pytest.mark.parametrize(
    ("modulus", "signed", "dtype"),
    [(1 << 16, False, np.uint16), (1 << 32, False, np.uint32), (128, False, np.int64), (1 << 32, True, np.uint32)],
)
def test_step_and_run_agree_at_every_split_point(modulus: int, signed: bool, dtype: type) -> None:
    raw = _readings(modulus, 60, seed=modulus % 997 + signed).astype(dtype)
    ref = Unwrapper(modulus, signed)
    values, steps = [], []
    for r in raw.tolist():
        d = ref.step(r)
        values.append(ref.value)
        steps.append(0 if d is None else d)
    whole = Unwrapper(modulus, signed).run(raw)
    assert whole.value.tolist() == values and whole.step.tolist() == steps and whole.first
    assert whole.value.dtype == whole.step.dtype == np.int64
    for cut in range(len(raw) + 1):
        u = Unwrapper(modulus, signed)
        a = u.run(raw[:cut])
        b = u.run(raw[cut:])
        assert np.concatenate((a.value, b.value)).tolist() == values, cut
        assert np.concatenate((a.step, b.step)).tolist() == steps, cut
        assert (u.value, u.last_raw, u.delta, u.wraps) == (ref.value, ref.last_raw, ref.delta, ref.wraps), cut
        # and mixing the forms: run, then step
        v = Unwrapper(modulus, signed)
        v.advance(raw[:cut])
        for r in raw[cut:].tolist():
            v.step(r)
        assert (v.value, v.last_raw, v.delta, v.wraps) == (ref.value, ref.last_raw, ref.delta, ref.wraps), cut


def test_counting_steps_one_by_one_and_at_once() -> None:
    raw = _readings(1 << 16, 500, seed=3).astype(np.uint16)
    one, many = DecoderCounters(), DecoderCounters()
    u = Unwrapper(1 << 16)
    for r in raw.tolist():
        count_seq_step(one, u.step(r))
    for cut in (0, 1, 250, 499, 500):
        many = DecoderCounters()
        v = Unwrapper(1 << 16)
        count_seq_steps(many, v.advance(raw[:cut]).steps_taken)
        count_seq_steps(many, v.advance(raw[cut:]).steps_taken)
        assert (many.seq_gaps, many.missing_frames, many.seq_repeats) == (
            one.seq_gaps,
            one.missing_frames,
            one.seq_repeats,
        )
    d = np.diff(raw.astype(np.int64)) % (1 << 16)
    assert one.seq_repeats == int(np.sum(d == 0))
    assert one.seq_gaps == int(np.sum(d > 1)) and one.missing_frames == int(np.sum(d[d > 1] - 1))
    assert missing_before(np.array([0, 1, 2, 5, 0])).tolist() == [0, 0, 1, 4, 0]


def _greedy_reference(starts: list[int], ends: list[int]) -> list[bool]:
    keep, edge = [], -(1 << 62)
    for s, e in zip(starts, ends):
        keep.append(s >= edge)
        if keep[-1]:
            edge = e
    return keep


def test_greedy_accept_against_the_sequential_scan() -> None:
    rng = np.random.default_rng(5)
    assert greedy_accept(np.zeros(0, np.int64), np.zeros(0, np.int64)).tolist() == []
    for trial in range(300):
        n = int(rng.integers(1, 40))
        starts = np.sort(rng.integers(0, 200, n)).astype(np.int64)
        ends = starts + rng.integers(1, 30, n)
        if trial % 3 == 0:  # a blocking, open-ended interval at the end, as the batch decoder gives
            ends[-1] = np.iinfo(np.int64).max
        got = greedy_accept(starts, ends)
        assert got.dtype == bool
        assert got.tolist() == _greedy_reference(starts.tolist(), ends.tolist()), trial
