"""A drift sigma for tests of where ``drift_sigma_dph`` is published, independent of how it is estimated.

``stub_sigma(monkeypatch)`` makes every ``Compensator`` hold a known sigma per model block, set where the
estimate is (``_on_block``), so ``step`` and ``run``, the daemon and ``compensate`` all see it::

    sigma_dph = STUB_BASE_DPH + STUB_STEP_DPH * (block.index % STUB_PERIOD)     NaN while uncompensated

It tests the publishing (the CSV, ANGLE, UDP, the views), never the estimate's calibration.
"""

from __future__ import annotations

import math

from fog_driver.compensation.pipeline import Compensator
from fog_driver.flags import FLAG_UNCOMPENSATED

STUB_BASE_DPH = 0.01
STUB_STEP_DPH = 0.0001
STUB_PERIOD = 50


def stub_value(block_index: int) -> float:
    """The stub's sigma for a block with an estimate (deg/h)."""
    return STUB_BASE_DPH + STUB_STEP_DPH * (block_index % STUB_PERIOD)


def stub_sigma(monkeypatch, *, none: bool = False) -> None:
    """Every ``Compensator`` from now on (this test) holds ``stub_value`` of each block it closes (``none``:
    NaN throughout, a model that gives no sigma)."""
    on_block = Compensator._on_block

    def with_sigma(self, block):
        on_block(self, block)
        no_estimate = none or self.estimate_flags & FLAG_UNCOMPENSATED
        self.sigma_dph = math.nan if no_estimate else stub_value(block.index)

    monkeypatch.setattr(Compensator, "_on_block", with_sigma)
