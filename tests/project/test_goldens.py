"""Golden outputs: what the daemon publishes and what ``compensate`` writes, compared with checked-in files
within the stated tolerance (``tests/golden.py``), on any machine; and the comparison itself."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from fog_driver.samples.captures import read_provenance

HERE = Path(__file__).resolve().parents[1]
DATA = HERE / "data"
sys.path.insert(0, str(DATA))
try:
    import make_fixtures
    import make_goldens
finally:
    sys.path.remove(str(DATA))

import golden  # noqa: E402

pytestmark = pytest.mark.determinism


def test_watch_golden_matches_its_generator():
    """The daemon's 1 Hz ANGLE lines for sim-faults.bin with the shipped default model."""
    golden.assert_matches_ndjson(make_goldens.watch_lines(), make_goldens.WATCH_GOLDEN)


@pytest.mark.parametrize("name", make_goldens.COMPENSATE_GOLDENS)
def test_a_checked_in_model_file_compensates_a_checked_in_capture_as_recorded(name):
    """Model files written by an earlier version (and fitted on another machine) compensate the same way."""
    kind, _ = make_goldens.COMPENSATE_GOLDENS[name]
    assert make_goldens.model_path(kind).stat().st_size < 64 * 1024
    golden.assert_matches_ndjson(make_goldens.compensate_lines(name), make_goldens.compensate_path(name))


def test_the_golden_models_are_of_their_kind_and_fitted_on_the_short_fixture():
    import yaml

    for kind in make_goldens.MODEL_KINDS:
        doc = yaml.safe_load(make_goldens.model_path(kind).read_text())
        assert doc["kind"] == kind
        assert doc["provenance"]["captures"][0]["file"] == make_goldens.FIT_CAPTURE.name
    cascade = yaml.safe_load(make_goldens.model_path("wesn-cascade").read_text())
    assert cascade["kind"] == "wesn" and cascade["model"]["coil_rate"] is True
    assert cascade["model"]["reservoir"]["params"]["chain_from"][0] >= 0  # the coil integrates an inner stage


@pytest.mark.parametrize("name", make_fixtures.SIM_FIXTURES)
def test_simulated_fixtures_match_their_generator(name, tmp_path):
    """The capture byte for byte; the truth file (9 significant digits) to one unit in its last digit."""
    make_fixtures.make_sim(name, tmp_path)
    assert (tmp_path / f"{name}.bin").read_bytes() == (DATA / f"{name}.bin").read_bytes()
    golden.assert_matches_csv((tmp_path / f"{name}.truth.csv").read_text(), DATA / f"{name}.truth.csv", rel_tol=1e-8)
    want, got = read_provenance(DATA / f"{name}.bin"), read_provenance(tmp_path / f"{name}.bin")
    for key in ("profile", "seed", "rate_hz", "faults", "frames", "bytes", "sha256", "instrument", "model"):
        assert got[key] == want[key], key
    golden.compare_values(got["run"], want["run"], "run")  # the run's draws: floats within the tolerance


# --- the comparison ---------------------------------------------------------------------------------

LINE = '{"class":"ANGLE","seq":7,"angle_arcsec":1528.047431515089,"flags":["gap"],"temps_c":{"top":20.5}}'


def _write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "g.ndjson"
    path.write_text(text)
    return path


def _failure(got: list[str], path: Path) -> str:
    with pytest.raises(pytest.fail.Exception) as info:
        golden.assert_matches_ndjson(got, path)
    message = str(info.value)
    assert "\n" not in message  # one line, never a repr of 300 lines
    return message


def test_floats_within_the_tolerance_agree_and_everything_else_must_be_exact(tmp_path):
    path = _write(tmp_path, LINE + "\n" + LINE + "\n")
    golden.assert_matches_ndjson([LINE, LINE.replace("1528.047431515089", "1528.0474315150895")], path)
    cases = [  # (what is changed in line 1, into what, the message)
        ("1528.047431515089", "1528.04743151", "line 1, angle_arcsec: got 1528.04743151, golden 1528.047431515089"),
        ('"seq":7', '"seq":8', "seq: got 8, golden 7"),
        ('"seq":7', '"seq":7.0', "not the same type"),
        ('["gap"]', '["gap","guard"]', "flags: 2 items, golden 1"),
        ('"top":20.5', '"top":20.6', "temps_c.top: got 20.6, golden 20.5"),
        ('"top":20.5', '"bottom":20.5', "temps_c: keys ['bottom'] != golden keys ['top']"),
        ('"ANGLE"', '"STATUS"', "class: got 'STATUS', golden 'ANGLE'"),
    ]
    for old, new, needle in cases:
        assert needle in _failure([LINE.replace(old, new), LINE], path)
    assert "1 lines, golden 2" in _failure([LINE], path)
    assert "3 lines, golden 2" in _failure([LINE, LINE, LINE], path)
    # The tolerance is relative, with an absolute floor near zero.
    assert golden.floats_agree(1.0, 1.0 + 5e-13) and not golden.floats_agree(1.0, 1.0 + 5e-12)
    assert golden.floats_agree(0.0, 5e-13) and not golden.floats_agree(0.0, 5e-12)
    assert golden.floats_agree(float("nan"), float("nan")) and not golden.floats_agree(float("nan"), 1.0)


def test_a_missing_or_malformed_golden_fails_with_one_line(tmp_path):
    assert "is missing: regenerate it on purpose" in _failure([LINE], tmp_path / "absent.ndjson")
    assert "is empty" in _failure([LINE], _write(tmp_path, ""))
    assert "line 2: not JSON" in _failure([LINE, LINE], _write(tmp_path, LINE + "\n{truncated\n"))
    assert "line 1: not a JSON object" in _failure([LINE], _write(tmp_path, "[1, 2]\n"))
    (tmp_path / "binary.ndjson").write_bytes(b"\xff\xfe\x00")
    assert "cannot be read" in _failure([LINE], tmp_path / "binary.ndjson")
    assert "output line 1: not JSON" in _failure(["not json"], _write(tmp_path, LINE + "\n"))


def test_csv_goldens_compare_cells_as_numbers(tmp_path):
    path = tmp_path / "t.csv"
    path.write_text("# comment\na,b,c\n1,20.0000001,x\n")
    golden.assert_matches_csv("a,b,c\n1,20.0000002,x\n", path, rel_tol=1e-8)
    with pytest.raises(pytest.fail.Exception, match="line 1, b: got 20.000001"):
        golden.assert_matches_csv("a,b,c\n1,20.000001,x\n", path, rel_tol=1e-8)
    with pytest.raises(pytest.fail.Exception, match="2 cells, the header has 3"):
        golden.assert_matches_csv("a,b,c\n1,20\n", path, rel_tol=1e-8)


def test_make_goldens_check_reports_a_change_beyond_the_tolerance(tmp_path, monkeypatch, capsys):
    """``make_goldens.py --check`` tells a last-bit change from a real one, and writes nothing."""
    original = make_goldens.WATCH_GOLDEN.read_text()
    lines = original.splitlines(keepends=True)
    edited = tmp_path / "watch.ndjson"
    edited.write_text("".join(lines[:-1]) + lines[-1].replace('"seq":', '"seq":1'))
    monkeypatch.setattr(make_goldens, "outputs", lambda: {edited: [line.encode() for line in lines]})
    assert make_goldens.main(["--check"]) == 1
    assert f"changed BEYOND tolerance: line {len(lines)}, seq" in capsys.readouterr().out
    first = json.loads(lines[0])
    nudged = repr(first["angle_arcsec"] * (1 + 1e-14))  # a last-bits change, whatever the golden holds
    assert nudged != repr(first["angle_arcsec"])
    edited.write_text(original.replace(repr(first["angle_arcsec"]), nudged, 1))
    assert make_goldens.main(["--check"]) == 0
    assert "changed within tolerance" in capsys.readouterr().out
    assert edited.read_text() != original  # --check never writes
