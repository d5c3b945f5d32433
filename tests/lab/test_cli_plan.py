"""``fog-driver plan``: the calibration program for a chamber, as a user runs it, including every kind of bad input;
the built-in ``calibration`` profile is its default design; what a program leaves unidentified."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from cli_run import assert_one_line_error, run_cli

from fog_driver.lab.plan import ChamberLimits, design_program, identifiability_gaps
from fog_driver.lab.profiles import BUILTIN_PROFILES, load_profile
from fog_driver.lab.program import Hold, Ramp, Sinusoid
from fog_driver.sim.capture import read_truth

ROOT = Path(__file__).resolve().parents[2]
SHIPPED = ROOT / "configs" / "profiles" / "calibration.yaml"


def air_c(chamber, step_s: float = 5.0) -> tuple[np.ndarray, np.ndarray]:
    t = np.arange(0.0, chamber.duration_s + step_s, step_s)
    return t, chamber.air_temp_c(t)


def crossings(t: np.ndarray, temp: np.ndarray, level: float) -> set[int]:
    """The directions (+1 warming, -1 cooling) in which the air temperature passes ``level``."""
    d = np.diff(np.sign(temp - level))
    return {int(np.sign(v)) for v in d if v != 0}


# --- the default design: the built-in calibration profile ----------------------------------------------


def test_plan_with_default_options_writes_the_shipped_calibration_profile(tmp_path):
    proc = run_cli("plan", "--out", "calibration.yaml", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    written = tmp_path / "calibration.yaml"
    assert written.read_text() == SHIPPED.read_text()  # configs/profiles/calibration.yaml is plan's output
    builtin = BUILTIN_PROFILES["calibration"]()
    for profile in (load_profile(written), load_profile(SHIPPED), load_profile("calibration")):
        assert profile.chamber == builtin.chamber and profile.motion == builtin.motion
        assert profile.name == "calibration"
    assert builtin.source == "built-in"  # found without any file: a wheel's install has no configs/
    assert "wrote calibration.yaml: a 440-min program" in proc.stdout
    assert "coil lags above 35.5 min" in proc.stdout  # a tenth of 440 min: the grid's 2131.6 s


def test_the_default_design_holds_what_identifiability_asks_within_the_paper_limits():
    chamber = load_profile("calibration").chamber
    assert chamber.duration_s == 440 * 60.0
    t, temp = air_c(chamber, 1.0)
    assert temp.min() == -40.0 and temp.max() == 55.0
    assert np.abs(np.diff(temp)).max() <= 3.0 / 60.0 + 1e-9  # never faster than 3 degC/min, sinusoid included
    for level in (-30.0, -10.0, 0.0, 10.0, 30.0, 50.0):  # every temperature crossed warming and cooling
        assert crossings(t, temp, level) == {-1, 1}, level
    spans = chamber.spans()
    ramps = [s for s in spans if isinstance(s.segment, Ramp)]
    for sign in (1, -1):
        rates = {s.segment.rate_c_per_min for s in ramps if (s.end_c - s.start_c) * sign > 0}
        assert rates == {0.75, 1.5, 3.0}, sign
    soaks = {s.start_c: (s.t_end_s - s.t_start_s) / 60 for s in spans if isinstance(s.segment, Hold)}
    assert soaks[55.0] >= 44.0 and soaks[-40.0] >= 44.0  # a tenth of the run, the longest lag the fit tries
    assert any(isinstance(s.segment, Sinusoid) for s in spans)
    assert any(a.t_end_s == b.t_start_s for a, b in zip(ramps, ramps[1:]))  # a rate step: ramps in a row
    assert [g.what for g in identifiability_gaps(chamber)] == ["coil lags above 35.5 min"]


def test_what_the_papers_program_leaves_unidentified():
    """Worked by hand from configs/profiles/paper.yaml: 15-min soaks, +1 degC/min the only warming rate, ramps
    always one after a hold, 20..55 degC only warmed and -40..20 only cooled (overlap 20..55: 35 degC)."""
    gaps = {g.what: g.why for g in identifiability_gaps(load_profile("paper").chamber)}
    assert set(gaps) == {
        "coil lags above 35.5 min",
        "coil lags 18.2 min to 35.5 min",  # the grid's 1091.4 s is the first above 15 min
        "the temperature-rate terms warming",
        "a rate that varies within the run",
        "the thermal history against the bias curve (hysteresis)",
    }
    assert "15 min" in gaps["coil lags 18.2 min to 35.5 min"]
    assert "over 35 of the program's 95 degC" in gaps["the thermal history against the bias curve (hysteresis)"]


# --- other chambers ---------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "limits",
    [
        ChamberLimits(),
        ChamberLimits(min_c=-20, max_c=70, max_rate_c_per_min=5.0, minutes=600),
        ChamberLimits(min_c=0, max_c=40, max_rate_c_per_min=1.0, minutes=300),
        ChamberLimits(min_c=30, max_c=50, max_rate_c_per_min=2.0, minutes=200),  # room temperature outside
        ChamberLimits(min_c=-40, max_c=55, max_rate_c_per_min=0.1, minutes=60),
        ChamberLimits(min_c=-55, max_c=85, max_rate_c_per_min=10.0, minutes=2000),
        ChamberLimits(minutes=0.5),
    ],
    ids=str,
)
def test_a_program_stays_within_its_chamber_limits(limits):
    chamber = design_program(limits).chamber
    assert math.isclose(chamber.duration_s, limits.minutes * 60.0, rel_tol=1e-12)
    _, temp = air_c(chamber, 0.5)
    assert limits.min_c - 1e-9 <= temp.min() and temp.max() <= limits.max_c + 1e-9
    for s in chamber.spans():
        if isinstance(s.segment, Ramp):
            assert s.segment.rate_c_per_min <= limits.max_rate_c_per_min
        if isinstance(s.segment, Sinusoid):  # peak rate 2 pi A / P
            peak = 2 * math.pi * s.segment.amplitude_c / (s.segment.period_s / 60)
            assert peak <= limits.max_rate_c_per_min
        assert s.t_end_s >= s.t_start_s


# --- the command ------------------------------------------------------------------------------------


def test_limits_that_cannot_identify_everything_write_the_best_program_and_say_what_is_left(tmp_path):
    proc = run_cli("plan", "--out", "short.yaml", "--minutes", "60", "--max-rate-c-per-min", "0.1", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr == ""
    profile = load_profile(tmp_path / "short.yaml")
    assert profile.name == "short" and profile.chamber.duration_s == 3600.0
    out = proc.stdout
    assert "left unidentified under these limits:" in out
    for what in (
        "coil lags above 5.96 min",  # a tenth of 60 min: the grid's 357.6 s
        "a coil of several stages in series",
        "thermal history at 30 min",
        "thermal history at 120 min",
        "the bias curve's shape",
        "the temperature-rate terms warming",
        "the temperature-rate terms cooling",
    ):
        assert f"  - {what}" in out, what
    text = (tmp_path / "short.yaml").read_text()
    assert text.startswith("# A calibration program written by `fog-driver plan --max-rate-c-per-min 0.1 --minutes 60`")
    assert "#   - thermal history at 30 min" in text


def test_plan_with_a_narrow_range_and_a_slow_ramp_writes_a_program(tmp_path):
    """The review's finding: 20..25 degC at 0.1 degC/min in 60 min (exit 70, a ZeroDivisionError, before).  A
    whole cycle takes 100 min of ramps: the program written is a smaller cycle within the limits, and says so."""
    limits = ["--min-c", "20", "--max-c", "25", "--max-rate-c-per-min", "0.1", "--minutes", "60"]
    proc = run_cli("plan", *limits, "--out", "w.yaml", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr == ""
    chamber = load_profile(tmp_path / "w.yaml").chamber
    assert math.isclose(chamber.duration_s, 3600.0, rel_tol=1e-12)
    _, temp = air_c(chamber, 0.5)
    assert temp.min() >= 20.0 and temp.max() <= 25.0
    # the last resort's cycle: ramps at 0.1 degC/min for 0.6 of the 57 min after the 3-min warm-up, out and back
    assert temp.max() - temp.min() == pytest.approx(0.6 * (60 - 3) * 0.1 / 2, rel=0.01)
    ramps = [s for s in chamber.spans() if isinstance(s.segment, Ramp)]
    assert {s.end_c > s.start_c for s in ramps} == {True, False}
    assert all(s.segment.rate_c_per_min <= 0.1 for s in ramps)
    assert "simplified to fit the limits: " in proc.stdout and "the cycle shrunk to" in proc.stdout
    assert "  - the bias curve's shape: the program spans" in proc.stdout


@pytest.mark.parametrize(
    "low, high", [("20", "40"), ("0", "20")], ids=["room temperature at the bottom", "room temperature at the top"]
)
def test_plan_with_room_temperature_at_a_limit_and_little_time_writes_a_program(tmp_path, low, high):
    """Room temperature (the start) at a limit of the range: one leg out, one back, and (no time for a
    sinusoid) no short hold to take the spare time (exit 70 before: a ZeroDivisionError)."""
    proc = run_cli("plan", "--min-c", low, "--max-c", high, "--minutes", "30", "--out", "p.yaml", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    chamber = load_profile(tmp_path / "p.yaml").chamber
    assert math.isclose(chamber.duration_s, 1800.0, rel_tol=1e-12)
    _, temp = air_c(chamber, 0.5)
    assert float(low) <= temp.min() and temp.max() <= float(high)
    assert temp.max() - temp.min() > 1.0


@pytest.mark.parametrize(
    "args, needles",
    [
        (["--minutes", "1e-6"], ["--minutes 1e-06 at --max-rate-c-per-min 3", "no program is possible"]),
        (["--max-rate-c-per-min", "1e-300"], ["--max-rate-c-per-min 1e-300", "no program is possible"]),
        (["--min-c", "20", "--max-c", "20.01"], ["--min-c 20 .. --max-c 20.01 span 0.01 degC", "no program"]),
    ],
    ids=["a minute's millionth", "a rate of 1e-300", "a range of 0.01 degC"],
)
def test_plan_with_limits_that_leave_no_room_to_move_says_why_in_one_line(tmp_path, args, needles):
    proc = run_cli("plan", "--out", "p.yaml", *args, cwd=tmp_path)
    assert_one_line_error(proc, 64, "plan: impossible limits: ", *needles)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    "args, needle",
    [
        (["--min-c", "60"], "--min-c must be below --max-c, got 60 >= 55"),
        (["--min-c", "10", "--max-c", "10"], "--min-c must be below --max-c, got 10 >= 10"),
        (["--max-rate-c-per-min", "0"], "--max-rate-c-per-min must be in (0, 100]"),
        (["--max-rate-c-per-min", "-1"], "--max-rate-c-per-min must be in (0, 100]"),
        (["--min-c", "nan"], "--min-c must be a finite number, got nan"),
        (["--max-c", "inf"], "--max-c must be a finite number, got inf"),
        (["--max-rate-c-per-min=-inf"], "--max-rate-c-per-min must be a finite number"),
        (["--minutes", "0"], "--minutes must be in (0, 10080]"),
        (["--minutes", "1e9"], "--minutes must be in (0, 10080]"),
        (["--min-c", "-300"], "between -273.15 and 1000 degC"),
    ],
    ids=lambda v: " ".join(v) if isinstance(v, list) else None,
)
def test_impossible_limits_are_a_one_line_usage_error_and_write_nothing(tmp_path, args, needle):
    proc = run_cli("plan", "--out", "p.yaml", *args, cwd=tmp_path)
    assert_one_line_error(proc, 64, "plan: impossible limits: ", needle)
    assert list(tmp_path.iterdir()) == []


def test_an_existing_output_is_refused_without_force(tmp_path):
    out = tmp_path / "mine.yaml"
    out.write_text("a chamber program of my own\n")
    assert_one_line_error(run_cli("plan", "--out", str(out)), 73, "mine.yaml", "refusing to overwrite", "--force")
    assert out.read_text() == "a chamber program of my own\n"
    assert_one_line_error(run_cli("plan", "--out", str(tmp_path / "p.txt")), 64, "must end in .yaml")
    proc = run_cli("plan", "--out", str(out), "--force")
    assert proc.returncode == 0, proc.stderr
    written = load_profile(out)
    assert written.name == "mine" and written.chamber.segments == design_program().chamber.segments


def test_simulate_runs_the_written_program(tmp_path):
    """A 30-min program on a 10..30 degC chamber at 2 degC/min, simulated at 10 Hz: the truth's air
    temperature is the program's, second by second."""
    proc = run_cli(
        "plan",
        "--out",
        "p.yaml",
        "--min-c",
        "10",
        "--max-c",
        "30",
        "--max-rate-c-per-min",
        "2",
        "--minutes",
        "30",
        cwd=tmp_path,
    )
    assert proc.returncode == 0, proc.stderr
    proc = run_cli("simulate", "--profile", "p.yaml", "--rate-hz", "10", "--out", "run.bin", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "simulated p at 10 Hz" in proc.stdout
    truth = read_truth(tmp_path / "run.truth.csv")
    chamber = load_profile(tmp_path / "p.yaml").chamber
    whole = truth["n_frames"] == 10  # whole seconds (a last frame at the end stands alone)
    assert whole.sum() == 30 * 60
    assert truth["air_c"].max() > 25.0  # the cycle goes somewhere
    # each second's mean over frames at t, t + 0.1, ... t + 0.9 s
    expected = np.mean([chamber.air_temp_c(truth["t_true_s"][whole] + k / 10) for k in range(10)], axis=0)
    np.testing.assert_allclose(truth["air_c"][whole], expected, atol=1e-6)


def plan_transcripts() -> list[tuple[str, str, str]]:
    """Each ``$ fog-driver plan ...`` transcript in the docs: (where, the command's words, what it shows)."""
    found = []
    for doc in (ROOT / "docs" / "reference" / "commands.md", ROOT / "docs" / "how-to" / "calibration.md"):
        lines = doc.read_text().splitlines()
        for i, line in enumerate(lines):
            if line.startswith("$ fog-driver plan "):
                shown = []
                for rest in lines[i + 1 :]:
                    if rest.startswith("```"):
                        break
                    shown.append(rest + "\n")
                found.append((f"{doc.name}:{i + 1}", line.removeprefix("$ fog-driver "), "".join(shown)))
    return found


@pytest.mark.parametrize("where, words, shown", plan_transcripts(), ids=lambda v: v if ":" in str(v) else "")
def test_the_docs_plan_transcripts_are_what_plan_prints(tmp_path, where, words, shown):
    """``plan`` is deterministic: the docs show its output word for word and number for number."""
    proc = run_cli(*words.split(), cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout == shown, where
