"""A static minute holding a second without a drift estimate (NaN, flagged uncompensated) is not scored: the
other minutes' errors are what they are without it, and no NaN reaches a figure."""

from __future__ import annotations

import numpy as np

from fog_driver.report.coverage import coverage_figures, minute_errors


def test_evaluating_a_run_with_a_second_without_an_estimate_drops_only_its_minute():
    rng = np.random.default_rng(7)
    n = 10 * 60
    truth = rng.normal(0.0, 0.01, n)
    estimate = truth + rng.normal(0.0, 0.02, n)
    sigma = np.full(n, 0.02)
    static = np.ones(n, dtype=bool)
    estimate[3 * 60 + 17] = np.nan  # one second of minute 3 had no estimate
    got = minute_errors(estimate, truth, sigma, static)
    # independently: the per-minute means of the nine other minutes, about their own mean
    keep = [m for m in range(10) if m != 3]
    e = np.array([np.mean(estimate[m * 60 : m * 60 + 60] - truth[m * 60 : m * 60 + 60]) for m in keep])
    np.testing.assert_allclose(got.error_dph, e - e.mean(), rtol=1e-12, atol=1e-15)
    figures = coverage_figures(got)
    assert figures["static_minutes"] == 9 and np.isfinite(figures["error_rms_1min_dph"])
