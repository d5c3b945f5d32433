"""``inspect`` on a capture of another instrument's format: sniffed, decoded whole, summarized axis by axis."""

from __future__ import annotations

import json
from pathlib import Path

from fog_driver import cli
from fog_driver.cli.captures import EXIT_PROBLEMS
from fog_driver.sim.capture import read_truth, simulate_to_file
from fog_driver.sim.faults import parse_fault_spec
from fog_driver.sim.instrument import Simulator
from fog_driver.sim.profiles import load_profile

DATA = Path(__file__).parent / "data"


def kvh_capture(tmp_path: Path, faults: str = "", seconds: float = 60.0) -> tuple[Path, Simulator]:
    sim = Simulator(
        load_profile("short-test"),
        rate_hz=50,
        seed=8,
        wire_format="kvh-a",
        faults=parse_fault_spec(faults) if faults else None,
    )
    capture = tmp_path / "kvh.bin"
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
    assert text.rstrip().endswith("verdict       clean; the other commands read protocol v1 captures only so far")


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
