"""The pieces every frame format shares."""

from __future__ import annotations

from fog_driver.formats.common import FormatCounters, SeqUnwrapper


def test_a_7_bit_counter_unwraps_and_counts_gaps_and_repeats():
    counters = FormatCounters()
    unwrap = SeqUnwrapper(128, counters)
    raw = [125, 126, 127, 0, 1, 1, 4, 127, 0]
    assert [unwrap.step(r) for r in raw] == [125, 126, 127, 128, 129, 129, 132, 255, 256]
    assert (counters.seq_repeats, counters.seq_gaps, counters.missing_frames) == (1, 2, 2 + 122)
