"""The calibration path agrees with itself: ``fit``'s lag warning knows the program the run followed (the
capture's sidecar, or ``fit --profile``) and never prescribes the program just run; ``--validate`` captures
come from the fit's instrument; the checks table gives units and the way each limit goes."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import yaml

from fog_driver.cli import main
from fog_driver.compensation.fitting.wesn import LAG_INTERVAL_WARN
from fog_driver.compensation.models.wesn import COIL_LAG_GRID_S
from fog_driver.lab.plan import ChamberLimits, design_program, identifiability_gaps
from fog_driver.lab.profiles import load_profile, parse_profile
from fog_driver.modelfiles import load_model
from fog_driver.samples.captures import read_provenance

DATA = Path(__file__).parents[1] / "data"

#: One slow ramp in an hour: lags of a minute to six explain it alike (the fit warns), and it leaves the rate
#: terms unidentified (one rate, under 1 degC/min) and no rate change.
SLOW_RAMP = """name: slow-ramp
start_c: 20
segments:
  - hold: {duration_min: 10}
  - ramp: {rate_c_per_min: 0.2, target_c: 26}
  - hold: {duration_min: 20}
"""


def _grid(lo_s: float, hi_s: float) -> list[float]:
    return [v for v in COIL_LAG_GRID_S if lo_s <= v <= hi_s]


@pytest.fixture(scope="module")
def slow_run(tmp_path_factory):
    """The slow-ramp run simulated at 1 Hz (a capture whose sidecar records its program), its profile file,
    and a copy of the capture without a sidecar (a recording made by hand)."""
    work = tmp_path_factory.mktemp("slow")
    profile = work / "slow-ramp.yaml"
    profile.write_text(SLOW_RAMP)
    capture = work / "run.bin"
    assert main(["simulate", "--profile", str(profile), "--rate-hz", "1", "--seed", "1", "--out", str(capture)]) == 0
    bare = work / "by-hand.bin"
    shutil.copy(capture, bare)
    return capture, profile, bare


def _warning(capsys) -> str:
    printed = capsys.readouterr().out
    (line,) = [w for w in printed.splitlines() if w.startswith("warning: the coil's lag")]
    return line


def test_simulate_records_the_whole_program_in_the_sidecar(tmp_path):
    for name in ("calibration", "paper-validation"):  # a static program, and one with positioning moves
        out = tmp_path / f"{name}.bin"
        assert main(["simulate", "--profile", name, "--rate-hz", "1", "--duration", "60", "--out", str(out)]) == 0
        recorded = parse_profile(read_provenance(out)["program"], "program")
        profile = load_profile(name)
        assert recorded.name == name and recorded.chamber.start_c == profile.chamber.start_c
        assert recorded.chamber.segments == profile.chamber.segments  # every segment, the whole run
        assert recorded.motion.dwells() == profile.motion.dwells()


def test_fit_of_a_simulated_run_names_what_its_recorded_program_leaves_unidentified(slow_run, tmp_path, capsys):
    capture, profile, _ = slow_run
    assert main(["fit", str(capture), "--out", str(tmp_path / "m.yaml"), "--accept-weak-fit"]) == 0
    warning = _warning(capsys)
    selection = load_model(tmp_path / "m.yaml").provenance["selection"]
    lags = selection["lags_explaining_equally_s"]
    assert max(lags) > LAG_INTERVAL_WARN * min(lags)  # the run leaves the lag to within a factor > 1.5
    assert f"{min(lags):g} s to {max(lags):g} s explain them" in warning
    assert "their program, slow-ramp (run.bin's sidecar), leaves unidentified: " in warning
    gaps = {g.what for g in identifiability_gaps(load_profile(str(profile)).chamber)}
    for what in ("the temperature-rate terms warming", "a rate that varies within the run"):
        assert what in gaps and what in warning
    assert "the bias curve's shape" not in warning  # a gap, but not one that bears on the lag
    assert "`fog-driver plan` writes for your chamber" in warning  # the remedy: a program that identifies them
    assert warning == f"warning: {selection['warning']}"  # the model file records the same
    assert load_model(tmp_path / "m.yaml").provenance["captures"][0]["program"] == {
        "name": "slow-ramp",
        "from": "run.bin's sidecar",
    }


def test_fit_of_a_recording_made_by_hand_gives_the_interval_only_and_with_profile_judges_it(slow_run, tmp_path, capsys):
    capture, profile, bare = slow_run
    assert main(["fit", str(bare), "--out", str(tmp_path / "a.yaml"), "--accept-weak-fit"]) == 0
    unknown = _warning(capsys)
    assert "The program the captures ran is not known" in unknown and "fit --profile" in unknown
    assert "Remedy" not in unknown and "calibration" not in unknown  # nothing prescribed without the program
    assert (
        main(["fit", str(bare), "--out", str(tmp_path / "b.yaml"), "--accept-weak-fit", "--profile", str(profile)]) == 0
    )
    given = _warning(capsys)
    assert main(["fit", str(capture), "--out", str(tmp_path / "c.yaml"), "--accept-weak-fit"]) == 0
    recorded = _warning(capsys)
    assert given == recorded.replace("(run.bin's sidecar)", f"(--profile {profile})")


def test_fit_profile_that_contradicts_the_sidecar_or_miscounts_is_one_line_and_exit_64(slow_run, tmp_path, capsys):
    capture, _, bare = slow_run
    out = tmp_path / "m.yaml"
    assert main(["fit", str(capture), "--out", str(out), "--profile", "paper"]) == 64
    (line,) = capsys.readouterr().err.splitlines()
    assert line.startswith(f"fog-driver: error: {capture}: its sidecar records the program it ran (slow-ramp, 60 min)")
    assert (
        main(["fit", str(capture), str(bare), "--out", str(out), "--profile", "a", "--profile", "b", "--profile", "c"])
        == 64
    )
    (line,) = capsys.readouterr().err.splitlines()
    assert "--profile given 3 times for 2 fit captures" in line
    assert not out.exists()


def _judge(profile, held_s: float, source: str):
    from fog_driver.offline.fit import judge_program

    return judge_program(profile, held_s, source)


def lag_warning(*args):
    from fog_driver.compensation.fitting.wesn import lag_warning

    return lag_warning(*args)


def test_fit_profile_that_is_no_profile_is_one_line_and_exit_65(tmp_path, capsys):
    """The profile is refused before any capture is decoded: sim-short.bin (300 s) is all warm-up under the
    default fit config, so a capture decoded first would be refused for that instead."""
    out = tmp_path / "m.yaml"
    assert main(["fit", str(DATA / "sim-short.bin"), "--out", str(out), "--profile", "no-such-program"]) == 65
    (line,) = capsys.readouterr().err.splitlines()
    assert line.startswith("fog-driver: error: no-such-program: no such profile (profiles: paper, ")
    assert not out.exists()


def _calibration_interval() -> list[float]:
    """The lags one simulated calibration run leaves tied (seed 1 at 10 Hz: 117.2 to 286.1 s, a factor 2.44)."""
    return _grid(117.0, 287.0)


def test_fit_after_the_calibration_program_gives_the_interval_and_never_prescribes_that_program():
    program = _judge(load_profile("calibration").chamber, 26400.0, "calibration.bin's sidecar")
    assert [g.what for g in program.gaps] == ["coil lags above 35.5 min"]  # far above the interval: not the lag's
    lags = _calibration_interval()
    warning = lag_warning(lags, 228.9, [program])
    assert warning is not None and "117.2 s to 286.1 s explain them" in warning
    assert "calibration (calibration.bin's sidecar), leaves nothing that bears on the lag unidentified" in warning
    assert "another run, fitted together with these captures" in warning
    assert "`fog-driver plan --max-rate-c-per-min 1.5`" in warning  # half its fastest ramp, 3 degC/min
    for prescribed in ("Remedy", "--profile calibration", "run the calibration program"):
        assert prescribed not in warning
    assert lag_warning(_grid(183.0, 229.0), 228.9, [program]) is None  # a factor 1.25: within the threshold


def test_fit_after_the_paper_program_names_its_gaps_and_prescribes_the_calibration_program():
    program = _judge(load_profile("paper").chamber, 26400.0, "chamber.bin's sidecar")
    warning = lag_warning(_grid(60.0, 2131.6), 286.1, [program])
    assert warning is not None
    named = warning.split("leaves unidentified: ")[1].split(". Remedy")[0].split("; ")
    assert named == [
        "coil lags above 35.5 min",
        "coil lags 18.2 min to 35.5 min",
        "the temperature-rate terms warming",
        "a rate that varies within the run",
    ]
    assert "Remedy: run the calibration program `fog-driver plan` writes for your chamber" in warning
    narrow = lag_warning(_grid(146.0, 287.0), 183.1, [program])  # an interval far below the unsettled lags
    assert narrow is not None and "coil lags" not in narrow.split("leaves unidentified: ")[1]


def test_fit_after_a_short_plan_program_prescribes_a_longer_one_not_the_same():
    limits = ChamberLimits(min_c=0.0, max_c=40.0, minutes=120.0)
    chamber = design_program(limits).chamber
    program = _judge(chamber, chamber.duration_s, "short.bin's sidecar")
    assert program.planned
    warning = lag_warning(_grid(60.0, 698.5), 228.9, [program])
    assert warning is not None and "it is `fog-driver plan`'s program for the chamber's limits" in warning
    assert "a longer program (`fog-driver plan --minutes` over 120" in warning
    assert "writes for your chamber" not in warning  # what it would write is what was run


def test_fit_of_a_capture_that_holds_part_of_its_program_judges_that_part():
    program = _judge(load_profile("calibration").chamber, 3600.0, "cut.bin's sidecar")
    assert program.cut and not program.planned
    warning = lag_warning(_grid(60.0, 357.6), 117.2, [program])
    assert warning is not None and "calibration (cut.bin's sidecar, its first 60 of 440 min)" in warning
    assert "Remedy: record the whole program" in warning


def test_fit_of_two_runs_names_only_what_both_programs_leave():
    paper = _judge(load_profile("paper").chamber, 26400.0, "paper.bin's sidecar")
    fast = load_profile("fast-ramps").chamber
    fast_ramps = _judge(fast, fast.duration_s, "fast.bin's sidecar")
    warning = lag_warning(_grid(60.0, 2131.6), 286.1, [paper, fast_ramps])
    assert warning is not None and "their programs, paper (paper.bin's sidecar), fast-ramps" in warning
    named = warning.split(" leave unidentified: ")[1].split(". Remedy")[0].split("; ")
    assert "the temperature-rate terms warming" not in named  # the fast run ramps at several rates
    assert "coil lags 18.2 min to 35.5 min" in named  # neither soaks long enough
    assert lag_warning(_grid(60.0, 2131.6), 286.1, [paper, None]) == lag_warning(_grid(60.0, 2131.6), 286.1, [None])


def test_fit_validated_on_another_instruments_capture_is_refused_as_two_fit_captures_are(tmp_path, capsys):
    other = tmp_path / "other.bin"
    assert (
        main(
            ["simulate", "--profile", "short-test", "--instrument-seed", "3", "--rate-hz", "10"]
            + ["--duration", "300", "--out", str(other)]
        )
        == 0
    )
    config = tmp_path / "fit.yaml"
    config.write_text("warmup_s: 30\n")
    short = DATA / "sim-short.bin"
    out = tmp_path / "m.yaml"
    base = ["fit", str(short), "--config", str(config), "--out", str(out), "--accept-weak-fit"]
    capsys.readouterr()
    assert main([*base, "--validate", str(other)]) == 65
    (line,) = capsys.readouterr().err.splitlines()
    assert line == (
        "fog-driver: error: the fit and validation captures come from different instruments: "
        "FOG-POP-00003: other.bin (--validate); FOG-SIM-0001: sim-short.bin"
    )
    assert main([*base[:2], str(other), *base[2:]]) == 65  # as two fit captures
    (line,) = capsys.readouterr().err.splitlines()
    assert line == (
        "fog-driver: error: the fit captures come from different instruments: "
        "FOG-POP-00003: other.bin; FOG-SIM-0001: sim-short.bin"
    )
    assert not out.exists()


def test_fit_checks_table_gives_each_figure_its_unit_and_each_limit_its_direction(tmp_path, capsys):
    config = tmp_path / "fit.yaml"
    config.write_text("warmup_s: 30\n")
    short = str(DATA / "sim-short.bin")
    out = tmp_path / "m.yaml"
    assert (
        main(
            ["fit", short, "--validate", short, "--config", str(config), "--out", str(out)]
            + ["--accept-weak-fit", "--kind", "polynomial"]
        )
        == 0
    )
    lines = {line.split()[0]: line for line in capsys.readouterr().out.splitlines() if line.split()}
    checks = load_model(out).provenance["fit_quality"]["checks"]
    expected = {  # the module docstring of compensation.fitting.quality: the unit, and the way the limit goes
        "duration": ("min", ">="),
        "ring_span": ("degC", ">="),
        "rate_span": ("degC/min", ">="),
        "target_range": ("deg/h", "<="),
        "condition": ("", "<="),
        "fit_residual": ("deg/h", "<"),
        "validation": ("deg/h", "<"),
    }
    assert set(checks) == set(expected)
    for name, (unit, relation) in expected.items():
        c = checks[name]
        verdict = "ok" if c["passed"] else "FAILS"
        words = f"{name} {c['value']:.4g} {unit} {relation} {c['limit']:.4g} {unit} {verdict}".split()
        assert lines[name].split() == words, lines[name]
    assert yaml.safe_load(out.read_text())["provenance"]["fit_quality"]["checks"] == checks
