"""``inspect`` on a capture of another instrument's format: sniffed, decoded whole, summarized axis by axis."""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import pytest

from fog_driver import cli
from fog_driver.cli.captures import EXIT_PROBLEMS
from fog_driver.lab.profiles import load_profile
from fog_driver.sim.capture import read_truth, simulate_to_file
from fog_driver.sim.faults import parse_fault_spec
from fog_driver.sim.instrument import Simulator

DATA = Path(__file__).parents[1] / "data"


def kvh_capture(
    tmp_path: Path, faults: str = "", seconds: float = 60.0, wire_format: str = "kvh-a"
) -> tuple[Path, Simulator]:
    sim = Simulator(
        load_profile("short-test"),
        rate_hz=50,
        seed=8,
        wire_format=wire_format,
        faults=parse_fault_spec(faults) if faults else None,
    )
    capture = tmp_path / ("kvh.bin" if wire_format == "kvh-a" else f"{wire_format}.bin")
    simulate_to_file(sim, capture, duration_s=seconds)
    return capture, sim


def test_inspect_summarizes_a_kvh_capture_against_the_simulators_truth(tmp_path, capsys):
    capture, _ = kvh_capture(tmp_path)
    truth = read_truth(capture.with_suffix(".truth.csv"))
    assert cli.main(["inspect", str(capture), "--json"]) == 0
    found = json.loads(capsys.readouterr().out)
    assert found["format"] == "kvh-a" and found["settings"]["rot_units"] == "rad"  # from the sidecar
    assert found["samples"] == found["counters"]["sample_frames"] == 3000 and found["problems"] == []
    assert found["seq"] == [0, 2999]
    # the mean rate over the run: the truth's measured rate, second by second (1 arcsec/s = 1 deg/h)
    assert abs(found["rate_dph"]["z"]["mean"] - truth["measured_dph"][:60].mean()) < 1e-3
    assert found["rate_dph"]["x"]["std"] == 0.0
    housing = truth["housing_c"][:60]
    assert abs(found["temps_c"]["sensor"]["min"] - housing.min()) < 0.05
    assert abs(found["temps_c"]["sensor"]["max"] - housing.max()) < 0.05
    assert cli.main(["inspect", str(capture)]) == 0
    text = capsys.readouterr().out
    assert "format        kvh-a: KVH (EMCORE) DSP-1750/1760/1775 normal mode, Format A" in text
    assert text.rstrip().endswith(
        "verdict       clean; fit, compensate and evaluate read it (a model applies to captures of the "
        "temperature channels it was fitted on; kvh-a has sensor)"
    )


def test_inspect_strict_fails_a_kvh_capture_with_gaps(tmp_path, capsys):
    capture, _ = kvh_capture(tmp_path, "drop=0.02")
    assert cli.main(["inspect", str(capture), "--strict"]) == EXIT_PROBLEMS
    assert "frames missing (sequence gaps)" in capsys.readouterr().out


def test_inspect_reads_ixblues_real_telegrams(capsys):
    # iXblue's own recording (tests/data/ixblue/README.md): 17 consecutive v3 telegrams, one a second
    assert cli.main(["inspect", str(DATA / "ixblue" / "log_STDBIN_V3.log"), "--json"]) == 0
    found = json.loads(capsys.readouterr().out)
    assert found["format"] == "ixblue-stdbin" and found["samples"] == 17 and found["seq"] == [8, 24]
    assert found["t_s"][1] - found["t_s"][0] == 16.0
    assert set(found["temps_c"]) == {"fog", "accelerometer", "board"}


def test_a_format_the_sniffer_contradicts_is_one_line_naming_what_it_saw(tmp_path, capsys):
    capture, _ = kvh_capture(tmp_path, seconds=10.0)
    assert cli.main(["inspect", str(capture), "--format", "ixblue-stdbin"]) == 65
    (line,) = capsys.readouterr().err.splitlines()
    assert line == (
        f"fog-driver: error: {capture}: --format ixblue-stdbin, but the sniffer saw kvh-a "
        "(500 valid frames in the first 18,000 bytes)"
    )
    v1 = DATA / "sim-short.bin"
    assert cli.main(["inspect", str(v1), "--format", "kvh-a"]) == 65
    assert "but the sniffer saw fog-v1" in capsys.readouterr().err
    assert cli.main(["inspect", str(v1)]) == 0 and "verdict" in capsys.readouterr().out  # protocol v1 as before


def test_a_temperature_read_in_the_wrong_units_is_a_problem(tmp_path, capsys):
    """A KVH capture recorded without its settings: the decoder's default whole degC reads a device sending
    hundredths as 2,000 degC; inspect says so instead of calling the capture clean."""
    capture, _ = kvh_capture(tmp_path, seconds=10.0)
    (tmp_path / "kvh.bin.yaml").unlink()  # no wire_settings: the defaults
    assert cli.main(["inspect", str(capture), "--strict"]) == EXIT_PROBLEMS
    assert "outside -55 .. 125 (the device's temperature units? temp_units in wire_settings)" in capsys.readouterr().out


@pytest.mark.parametrize("wire_format", ["kvh-a", "ixblue-stdbin"])
def test_inspect_of_a_kvh_or_stdbin_capture_says_what_fit_compensate_and_evaluate_do_with_it(
    tmp_path, capsys, wire_format
):
    """What the verdict says the commands do, they do: with its sidecar, fit, compensate and evaluate read the
    capture; a copy without one, they refuse for the reason the verdict gives."""
    capture, _ = kvh_capture(tmp_path, seconds=300.0, wire_format=wire_format)
    config = tmp_path / "fit.yaml"
    config.write_text("warmup_s: 5\n")
    model = tmp_path / "model.yaml"

    def verdict(path: Path) -> str:
        assert cli.main(["inspect", str(path)]) == 0
        return capsys.readouterr().out.splitlines()[-1]

    assert verdict(capture).startswith("verdict       clean; fit, compensate and evaluate read it")
    fit = ["fit", str(capture), "--config", str(config), "--out", str(model), "--kind", "polynomial"]
    assert cli.main([*fit, "--accept-weak-fit"]) == 0
    assert cli.main(["compensate", str(capture), "--model", str(model), "--out", str(tmp_path / "c.csv")]) == 0
    assert cli.main(["evaluate", str(capture), "--model", str(model), "--out", str(tmp_path / "report")]) == 0
    capsys.readouterr()
    bare = tmp_path / "by-hand.bin"
    shutil.copy(capture, bare)
    said = verdict(bare)
    assert f"fit, compensate and evaluate read {wire_format} captures, but not this one as it is: " in said
    reason = said.split("but not this one as it is: ")[1]
    for command in (
        ["fit", str(bare), "--out", str(tmp_path / "m2.yaml")],
        ["compensate", str(bare), "--model", str(model), "--out", str(tmp_path / "c2.csv")],
        ["evaluate", str(bare), "--model", str(model), "--out", str(tmp_path / "report2")],
    ):
        assert cli.main(command) == 65
        (line,) = capsys.readouterr().err.splitlines()
        assert line == f"fog-driver: error: {bare}: {reason}"


def test_the_commands_inspect_names_are_every_command_that_reads_any_format():
    """``CAPTURE_READERS`` (what inspect's verdict names) is every command that takes a capture file and a
    --format of every format (``run`` takes a port)."""
    from fog_driver.cli.captures import CAPTURE_READERS
    from fog_driver.cli.parser import build_parser
    from fog_driver.formats.registry import FORMATS

    parser = build_parser()
    (sub,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    readers = set()
    for name, command in sub.choices.items():
        takes_capture = any(not a.option_strings and a.metavar == "CAPTURE.bin" for a in command._actions)
        for action in command._actions:
            every_format = list(action.choices or ()) == ["auto", *FORMATS]
            if takes_capture and "--format" in action.option_strings and every_format:
                readers.add(name)
    assert readers - {"inspect"} == set(CAPTURE_READERS), readers
