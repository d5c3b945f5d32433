"""A fit that its data cannot support is refused (or written only on request, and recorded), and a model
knows the range it was fitted on: outside it the inputs are clamped, the estimate bounded, the rows flagged.

The scenario of the regression tests: a 10-minute capture once fitted with exit 0 and, on a chamber
run, estimated up to 530,000 deg/h, published unflagged."""

from __future__ import annotations

import csv
import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from fog_driver.cli import main
from fog_driver.compensation.domain import ESTIMATE_LIMIT_FACTOR, LEVEL_MARGIN, LINEAR_MARGIN, InputDomain
from fog_driver.compensation.features import INPUT_NAMES
from fog_driver.compensation.fitting.data import FitConfig, static_minute_means
from fog_driver.compensation.fitting.fit import WeakFitError
from fog_driver.compensation.fitting.quality import (
    MAX_CONDITION,
    MAX_TARGET_RANGE_DPH,
    MIN_FIT_MINUTES,
    MIN_RATE_SPAN_C_PER_MIN,
    MIN_RING_SPAN_C,
    assess,
    condition_number,
)
from fog_driver.compensation.fitting.report import applied_prediction
from fog_driver.errors import InputFileError
from fog_driver.flags import FLAG_BITS, FLAG_EXTRAPOLATING, FLAG_NAMES
from fog_driver.modelfiles import load_model, save_model
from fog_driver.offline.compensate import compensate_capture
from fog_driver.offline.fit import fit_model_file, load_capture

DATA = Path(__file__).resolve().parents[1] / "data"
SHORT_FIT = FitConfig(warmup_s=30.0)
LOW = (10.0, 11.0, 12.0, -1.0, -1.0, -2.0, -0.5, -3.0)
HIGH = (50.0, 51.0, 52.0, 0.5, 0.5, 1.0, 1.5, 6.0)


def domain(**kw) -> InputDomain:
    return InputDomain(LOW, HIGH, kw.pop("limit", 2.0), **kw)


# -- the domain itself ------------------------------------------------------------------------------


def test_inside_the_box_inputs_pass_bit_for_bit_and_are_not_flagged():
    d = domain()
    rng = np.random.default_rng(1)
    u = np.array(LOW) + rng.random((500, 8)) * (np.array(HIGH) - np.array(LOW))
    clamped, outside = d.clamp(u)
    assert np.array_equal(clamped, u) and not outside.any()
    one, out1 = d.clamp(u[3])
    assert np.array_equal(one, u[3]) and not out1


def test_outside_the_widened_box_inputs_are_clamped_to_its_edge():
    d = domain()
    span = np.array(HIGH) - np.array(LOW)
    margins = np.array([LEVEL_MARGIN] * 3 + [LINEAR_MARGIN] * 5)
    upper = np.array(HIGH) + margins * span
    lower = np.array(LOW) - margins * span
    for k in range(8):
        u = np.array(LOW) + 0.5 * span
        u[k] = upper[k] + 7.0  # beyond the widened box on input k only
        clamped, outside = d.clamp(u)
        assert outside and clamped[k] == upper[k]
        assert np.array_equal(np.delete(clamped, k), np.delete(u, k))
        assert d.outside_names(u) == [INPUT_NAMES[k]]
        u[k] = lower[k] - 1e-9
        clamped, outside = d.clamp(u)
        assert outside and clamped[k] == lower[k]
    # within the margin: not clamped, not flagged (a chamber overshoots its set points a little)
    u = np.array(HIGH) + 0.5 * margins * span
    clamped, outside = d.clamp(u)
    assert not outside and np.array_equal(clamped, u)


def test_nan_inputs_stay_nan_and_are_not_called_outside():
    u = np.array(LOW, dtype=float)
    u[1] = math.nan
    clamped, outside = domain().clamp(u)
    assert math.isnan(clamped[1]) and not outside


def test_the_estimate_is_bounded_by_its_limit_both_ways():
    d = domain(limit=0.5)
    assert d.bound(0.49) == (0.49, False)
    assert d.bound(-0.5) == (-0.5, False)
    assert d.bound(530197.0) == (0.5, True)
    assert d.bound(-3.0) == (-0.5, True)
    values, clipped = d.bound_many(np.array([0.49, -0.5, 530197.0, -3.0]))
    assert values.tolist() == [0.49, -0.5, 0.5, -0.5] and clipped.tolist() == [False, False, True, True]


def test_from_fit_is_the_box_of_the_data_and_three_times_the_targets_range():
    rng = np.random.default_rng(2)
    x = rng.normal(size=(300, 8))
    x[5, 2] = math.nan
    means = np.array([0.1, -0.2, 0.3])
    d = InputDomain.from_fit(x, means)
    assert d.low == tuple(np.nanmin(x, axis=0)) and d.high == tuple(np.nanmax(x, axis=0))
    assert d.estimate_limit_dph == pytest.approx(ESTIMATE_LIMIT_FACTOR * 0.5)


def test_domain_round_trips_and_bad_domains_are_refused():
    d = domain(limit=1.25)
    assert InputDomain.from_dict(yaml.safe_load(yaml.safe_dump(d.to_dict()))) == d
    bad = [
        {**d.to_dict(), "low": d.to_dict()["low"][:7]},
        {**d.to_dict(), "high": [*d.to_dict()["low"][:7], -1e9]},  # high < low
        {**d.to_dict(), "estimate_limit_dph": -1.0},
        {**d.to_dict(), "estimate_limit_dph": True},
        {**d.to_dict(), "margin": [0.1] * 7 + [math.nan]},
        {**d.to_dict(), "inputs": ["a"] * 8},
        {**d.to_dict(), "low": ["x"] * 8},
    ]
    for doc in bad:
        with pytest.raises(ValueError):
            InputDomain.from_dict(doc)


def test_a_model_file_with_a_corrupt_domain_is_a_one_line_input_error(tmp_path):
    model_file, _ = fit_model_file([DATA / "sim-short.bin"], kind="polynomial", config=SHORT_FIT, accept_weak=True)
    path = save_model(tmp_path / "m.yaml", model_file)
    assert load_model(path).domain == model_file.domain
    doc = yaml.safe_load(path.read_text())
    doc["domain"]["estimate_limit_dph"] = "lots"
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(InputFileError, match="corrupt model"):
        load_model(path)


def test_extrapolating_is_a_published_flag_with_the_same_bit_everywhere():
    assert FLAG_NAMES[FLAG_EXTRAPOLATING] == "extrapolating"
    assert FLAG_BITS["extrapolating"] == FLAG_EXTRAPOLATING == 1 << 6


# -- the compensator applies it ----------------------------------------------------------------------


@pytest.fixture(scope="module")
def short_model():
    """A polynomial fitted on 5 minutes (weak, accepted): sim-faults.bin lies outside its box."""
    model_file, _ = fit_model_file([DATA / "sim-short.bin"], kind="polynomial", config=SHORT_FIT, accept_weak=True)
    return model_file


def _compensated(model_file, path=DATA / "sim-faults.bin"):
    parts = [cols for _, cols in compensate_capture(path, model_file)]
    drift = np.concatenate([c.drift_dph for c in parts])
    flags = np.concatenate([c.flags for c in parts])
    return drift, flags


def test_outside_its_box_the_estimate_is_bounded_and_flagged(short_model):
    drift, flags = _compensated(short_model)
    limit = short_model.domain.estimate_limit_dph
    assert np.nanmax(np.abs(drift)) <= limit  # NaN: no estimate yet (the first block)
    assert ((flags & FLAG_EXTRAPOLATING) != 0).mean() > 0.5
    unbounded = dataclasses.replace(short_model, domain=None)  # what the model does with no domain
    drift_free, flags_free = _compensated(unbounded)
    assert np.nanmax(np.abs(drift_free)) > limit and not (flags_free & FLAG_EXTRAPOLATING).any()


def test_inside_its_box_the_domain_changes_nothing():
    """sim-short compensated with its own fit: every block inside the box (past the start), the same bits."""
    model_file, _ = fit_model_file([DATA / "sim-short.bin"], kind="wesn", config=SHORT_FIT, accept_weak=True)
    with_domain, flags = _compensated(model_file, DATA / "sim-short.bin")
    without, _ = _compensated(dataclasses.replace(model_file, domain=None), DATA / "sim-short.bin")
    inside = (flags & FLAG_EXTRAPOLATING) == 0
    assert inside.mean() > 0.8
    first_out = np.flatnonzero(~inside)
    upto = first_out[0] if len(first_out) else len(inside)
    assert np.array_equal(with_domain[:upto], without[:upto], equal_nan=True)  # NaN: the first block's


def test_the_fit_report_applies_the_model_as_the_compensator_does(short_model):
    """``applied_prediction`` (the fit report's, and own validation's) clamps and bounds as ``Compensator``."""
    capture = load_capture(DATA / "sim-faults.bin", SHORT_FIT)
    predicted = applied_prediction(short_model.model, capture, short_model.normalizer, short_model.domain)
    assert np.abs(predicted).max() <= short_model.domain.estimate_limit_dph
    drift, _ = _compensated(short_model)
    # the compensator's drift per frame is the block estimate: its distinct values are the prediction's
    estimated = drift[np.isfinite(drift)]  # the first block has none
    assert np.isin(np.unique(np.round(estimated, 12)), np.round(predicted, 12)).all()


# -- fit quality -------------------------------------------------------------------------------------


def _assess(**kw):
    args = dict(
        static_minutes=60.0,
        ring=np.array([0.0, 10.0]),
        rate=np.array([-1.0, 1.0]),
        means=np.array([0.0, 1.0]),
        condition=1e3,
        fit=(0.2, 0.03),
        validate=(0.25, 0.04),
    )
    args.update(kw)
    return assess(
        args["static_minutes"],
        args["ring"],
        args["rate"],
        args["means"],
        args["condition"],
        args["fit"],
        args["validate"],
    )


@pytest.mark.parametrize(
    "change, failed",
    [
        ({}, []),
        ({"static_minutes": MIN_FIT_MINUTES - 0.1}, ["duration"]),
        ({"ring": np.array([0.0, MIN_RING_SPAN_C - 0.01])}, ["ring_span"]),
        ({"rate": np.array([0.0, MIN_RATE_SPAN_C_PER_MIN - 0.001])}, ["rate_span"]),
        ({"means": np.array([0.0, MAX_TARGET_RANGE_DPH + 0.1])}, ["target_range"]),
        ({"condition": MAX_CONDITION * 10}, ["condition"]),
        ({"fit": (0.2, 0.21)}, ["fit_residual"]),
        ({"validate": (0.25, 0.3)}, ["validation"]),
        ({"validate": (0.25, math.nan)}, ["validation"]),
    ],
)
def test_each_check_fails_just_past_its_limit_and_only_it(change, failed):
    quality = _assess(**change)
    assert [c.name for c in quality.failed] == failed
    assert all(c.message for c in quality.failed)
    assert quality.to_dict(False).get("weak", []) == [c.message for c in quality.failed]


def test_the_limits_themselves_pass():
    quality = _assess(
        static_minutes=MIN_FIT_MINUTES,
        ring=np.array([0.0, MIN_RING_SPAN_C]),
        rate=np.array([0.0, MIN_RATE_SPAN_C_PER_MIN]),
        means=np.array([0.0, MAX_TARGET_RANGE_DPH]),
        condition=MAX_CONDITION,
        validate=None,
    )
    assert quality.failed == [] and [c.name for c in quality.checks][-1] == "fit_residual"


def test_condition_number_is_numpys_on_standardized_columns():
    rng = np.random.default_rng(3)
    x = rng.normal(size=(200, 3)) * [1.0, 100.0, 0.01] + [5.0, -3.0, 0.0]
    x = np.column_stack([x, np.full(200, 7.0)])  # a constant column carries nothing: left out
    z = (x[:, :3] - x[:, :3].mean(axis=0)) / x[:, :3].std(axis=0)
    assert condition_number(x) == pytest.approx(np.linalg.cond(z), rel=1e-12)
    collinear = np.column_stack([x[:, 0], x[:, 0] * 2 + 1e-9 * rng.normal(size=200)])
    assert condition_number(collinear) > 1e6


def test_a_five_minute_fit_is_refused_and_says_why():
    with pytest.raises(WeakFitError) as info:
        fit_model_file([DATA / "sim-short.bin"], kind="polynomial", config=SHORT_FIT)
    names = [c.name for c in info.value.quality.failed]
    assert "duration" in names and "ring_span" in names
    assert str(info.value).startswith("the fit data cannot support this model: only 4.5 min of static fit data")


def test_an_accepted_weak_fit_is_recorded_in_the_model_file(tmp_path):
    model_file, _ = fit_model_file([DATA / "sim-short.bin"], kind="polynomial", config=SHORT_FIT, accept_weak=True)
    quality = load_model(save_model(tmp_path / "m.yaml", model_file)).provenance["fit_quality"]
    assert quality["accepted_weak"] is True and len(quality["weak"]) >= 2
    assert quality["checks"]["duration"]["passed"] is False
    assert quality["checks"]["duration"]["value"] == pytest.approx(4.5, abs=0.05)


def test_static_minute_means_use_whole_static_minutes_only():
    values = np.arange(300, dtype=float)
    mask = np.ones(300, bool)
    mask[70] = False  # minute 1 is not whole
    assert static_minute_means(values, mask, 1.0).tolist() == [29.5, 149.5, 209.5, 269.5]


# -- through the command line: the review's scenario --------------------------------------------------


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """A 10-minute paper-profile capture and a 1-hour fast-ramps run, at 10 Hz (simulated)."""
    d = tmp_path_factory.mktemp("c1")
    profiles = Path(__file__).resolve().parents[2] / "configs" / "profiles"
    assert (
        main(
            [
                "simulate",
                "--profile",
                "paper",
                "--duration",
                "600",
                "--seed",
                "5",
                "--rate-hz",
                "10",
                "--out",
                str(d / "short.bin"),
            ]
        )
        == 0
    )
    assert (
        main(
            [
                "simulate",
                "--profile",
                str(profiles / "fast-ramps.yaml"),
                "--duration",
                "3600",
                "--seed",
                "6",
                "--rate-hz",
                "10",
                "--out",
                str(d / "fast.bin"),
            ]
        )
        == 0
    )
    (d / "hold.yaml").write_text("name: hold\nstart_c: 20\nsegments:\n  - hold: {duration_min: 120}\n")
    assert (
        main(
            [
                "simulate",
                "--profile",
                str(d / "hold.yaml"),
                "--seed",
                "4",
                "--rate-hz",
                "10",
                "--out",
                str(d / "hold.bin"),
            ]
        )
        == 0
    )
    return d


def test_cli_refuses_a_ten_minute_fit_writes_nothing_and_exits_65(runs, capsys):
    out = runs / "refused.yaml"
    status = main(
        [
            "fit",
            str(runs / "short.bin"),
            "--kind",
            "polynomial",
            "--validate",
            str(runs / "fast.bin"),
            "--out",
            str(out),
        ]
    )
    captured = capsys.readouterr()
    assert status == 65 and not out.exists()
    assert captured.err.count("\n") == 1 and "--accept-weak-fit" in captured.err
    assert "Traceback" not in captured.err
    assert "duration" in captured.out and "FAILS" in captured.out


def test_cli_refuses_a_two_hour_hold_at_one_temperature(runs, capsys):
    """Long enough, but the ring moves only by its self-heating: no temperature or rate range to model."""
    status = main(["fit", str(runs / "hold.bin"), "--out", str(runs / "hold-model.yaml")])
    captured = capsys.readouterr()
    assert status == 65 and not (runs / "hold-model.yaml").exists()
    failed = [line.split()[0] for line in captured.out.splitlines() if line.endswith("FAILS")]
    assert "ring_span" in failed and "rate_span" in failed and "duration" not in failed


def test_cli_accepted_weak_fit_never_publishes_an_absurd_estimate(runs, capsys):
    model = runs / "weak.yaml"
    assert main(["fit", str(runs / "short.bin"), "--kind", "polynomial", "--out", str(model), "--accept-weak-fit"]) == 0
    assert "warning: weak fit accepted" in capsys.readouterr().out
    out = runs / "fast.csv"
    assert main(["compensate", str(runs / "fast.bin"), "--model", str(model), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "is a weak fit" in printed and "the model extrapolated for" in printed
    rows = list(csv.DictReader(out.open()))
    drift = np.array([float(r["drift_dph"]) for r in rows])
    limit = load_model(model).domain.estimate_limit_dph
    assert limit < 1.0 and np.nanmax(np.abs(drift)) <= limit + 1e-6  # (CSV: 6 decimals) the review measured 530,197
    assert sum("extrapolating" in r["flags"] for r in rows) > 0.5 * len(rows)


def test_cli_an_old_model_without_a_domain_still_compensates_and_says_so(runs, capsys):
    model_file = load_model(DATA / "golden" / "models" / "polynomial.yaml")
    assert model_file.domain is None
    out = runs / "old.csv"
    assert (
        main(
            [
                "compensate",
                str(DATA / "sim-short.bin"),
                "--model",
                str(DATA / "golden" / "models" / "polynomial.yaml"),
                "--out",
                str(out),
            ]
        )
        == 0
    )
    assert "stores no fit range" in capsys.readouterr().out


def test_a_missing_capture_is_a_one_line_error(tmp_path, capsys):
    assert main(["fit", str(tmp_path / "nothere.bin"), "--out", str(tmp_path / "m.yaml")]) == 65
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{tmp_path / 'nothere.bin'}: no such capture file" in err


def test_evaluate_reports_the_time_spent_extrapolating(runs, capsys):
    model = runs / "weak-eval.yaml"
    assert main(["fit", str(runs / "short.bin"), "--kind", "polynomial", "--out", str(model), "--accept-weak-fit"]) == 0
    capsys.readouterr()
    assert main(["evaluate", str(runs / "fast.bin"), "--model", str(model), "--out", str(runs / "rep"), "--json"]) == 0
    captured = capsys.readouterr()
    summary = json.loads(captured.out)
    assert summary["extrapolating_seconds"] > 0.5 * summary["seconds"]
    assert "is a weak fit" in captured.err
    assert f"for {summary['extrapolating_seconds']:,} s" in (runs / "rep" / "report.md").read_text()
