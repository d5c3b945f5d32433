"""``compensate --table-log`` given what a station can put in a table log: each refusal one line naming the file
and the line, exit 65, nothing written; the table angle's bound the one ``?TABLE`` applies; and a log of more
dwells than the law keeps outcomes of, counted whole.  (A daemon capture's table events: ``test_table_law``.)"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from fog_driver.cli.app import main
from fog_driver.client.protocol import MAX_TABLE_ANGLE_DEG as CLIENT_MAX_TABLE_ANGLE_DEG
from fog_driver.compensation.dwell import DWELL_TRIM_S
from fog_driver.compensation.table import MAX_OUTCOMES
from fog_driver.daemon.config import DEFAULT_MODEL
from fog_driver.daemon.limits import MAX_TABLE_ANGLE_DEG
from fog_driver.dwells import read_table_log

CAPTURE = Path(__file__).parents[1] / "data" / "sim-short.bin"  # 300 s of the simulated instrument at rest, 10 Hz
HEADER = "t_start_s,t_end_s,angle_deg\n"


def compensate_with_log(tmp_path: Path, log: Path, capsys) -> tuple[int, str, str, Path]:
    out = tmp_path / "out.csv"
    code = main(["compensate", str(CAPTURE), "--model", str(DEFAULT_MODEL), "--out", str(out), "--table-log", str(log)])
    captured = capsys.readouterr()
    return code, captured.out, captured.err, out


def assert_one_line_exit_65(code: int, err: str, out: Path, *pieces: str) -> None:
    lines = err.strip().splitlines()
    assert code == 65 and len(lines) == 1 and lines[0].startswith("fog-driver: error: "), (code, err)
    assert "internal error" not in lines[0]
    for piece in pieces:
        assert piece in lines[0], (piece, lines[0])
    assert not out.exists() and not out.with_name(out.name + ".yaml").exists()


@pytest.mark.parametrize("column", ["angle_deg", "angle_end_deg"])
@pytest.mark.parametrize("angle", ["1e308", "-1e308", repr(MAX_TABLE_ANGLE_DEG * (1 + 1e-9))])
def test_compensate_with_a_table_log_angle_beyond_the_live_bound_is_refused_naming_the_line(
    tmp_path, capsys, column, angle
):
    """An angle of 1e308 ended in ``OverflowError`` (exit 70); the bound ``?TABLE`` applies, +-1e6 degrees, is a
    table log's too: one line naming the file and the line, exit 65."""
    log = tmp_path / "table.csv"
    second = f"40,80,{angle}\n" if column == "angle_deg" else f"40,80,36,{angle}\n"
    log.write_text(
        f"t_start_s,t_end_s,angle_deg{',angle_end_deg' if column != 'angle_deg' else ''}\n"
        + ("0,30,0\n" if column == "angle_deg" else "0,30,0,0\n")
        + second
    )
    code, _, err, out = compensate_with_log(tmp_path, log, capsys)
    assert_one_line_exit_65(code, err, out, f"{log}:3:", column, f"+-{MAX_TABLE_ANGLE_DEG:g}")


def test_compensate_with_a_table_log_at_the_live_bound_takes_it(tmp_path, capsys):
    """The bound itself is a table angle, as live (the law takes the move modulo whole turns of the gyro's)."""
    log = tmp_path / "table.csv"
    log.write_text(HEADER + f"20,60,{MAX_TABLE_ANGLE_DEG!r}\n70,110,{-MAX_TABLE_ANGLE_DEG!r}\n")
    code, printed, err, out = compensate_with_log(tmp_path, log, capsys)
    assert code == 0 and out.exists(), err
    assert "table log: 2 dwells" in printed


def test_the_table_angle_bound_is_the_same_live_in_the_client_and_offline():
    """One bound: the daemon's ``?TABLE`` check, the client's and the table log's are the same number."""
    from fog_driver import dwells

    assert MAX_TABLE_ANGLE_DEG is dwells.MAX_TABLE_ANGLE_DEG and CLIENT_MAX_TABLE_ANGLE_DEG == MAX_TABLE_ANGLE_DEG


def test_compensate_with_a_table_log_of_cr_only_line_ends_reads_its_rows(tmp_path, capsys):
    """CR alone ending each line (an old Mac's export) ended in csv's ``new-line character seen in unquoted
    field`` (exit 70): the rows are read as with LF, and the log is used."""
    rows = ["# a station's log, CR line ends", "t_start_s,t_end_s,angle_deg", "20,60,0", "70,110,36", "120,160,72"]
    cr, lf = tmp_path / "cr.csv", tmp_path / "lf.csv"
    cr.write_bytes("\r".join(rows).encode() + b"\r")
    lf.write_bytes("\n".join(rows).encode() + b"\n")
    assert read_table_log(cr) == read_table_log(lf)
    code, printed, err, out = compensate_with_log(tmp_path, cr, capsys)
    assert code == 0 and out.exists(), err
    assert "table log: 3 dwells" in printed
    # and a mistake in a CR-only file is named by its line
    cr.write_bytes("\r".join([*rows[:3], "70,110,thirty-six"]).encode() + b"\r")
    out.unlink()
    out.with_name(out.name + ".yaml").unlink()
    code, _, err, out = compensate_with_log(tmp_path, cr, capsys)
    assert_one_line_exit_65(code, err, out, f"{cr}:4:", "angle_deg is not a number")


def test_compensate_with_a_140_kb_field_in_a_table_log_is_refused_naming_the_line(tmp_path, capsys):
    """A field over csv's limit (131,072 characters) ended in ``field larger than field limit`` (exit 70)."""
    log = tmp_path / "long.csv"
    log.write_text(HEADER + "20,60,0\n70,110," + "1" * 140_000 + "\n")
    code, _, err, out = compensate_with_log(tmp_path, log, capsys)
    assert_one_line_exit_65(code, err, out, f"{log}:3:", "not a CSV row", "field limit")


def test_compensate_with_a_table_log_of_17000_dwells_counts_every_dwell_and_groups_the_reasons(tmp_path, capsys):
    """A log of 17,000 dwells, more than the law keeps outcomes of (``MAX_OUTCOMES``): the summary said
    "10000 dwells: 10000 refused" and printed one line a dwell.  Every dwell is counted, and the refusals are
    one line a reason with its count and the first few dwells."""
    n = 17_000
    assert n > MAX_OUTCOMES
    long_s = 2 * DWELL_TRIM_S + 0.6  # a trimmed window of 0.6 s: no whole 1-s block in it (refused)
    rows = [f"{1 + k * (long_s + 0.5):.3f},{1 + k * (long_s + 0.5) + long_s:.3f},0" for k in range(10)]
    start, step_s = 112.0, 0.011  # then 16,990 dwells of 5 ms (not longer than two trims: refused), to 299 s
    rows += [f"{start + i * step_s:.3f},{start + i * step_s + 0.005:.3f},0" for i in range(n - 10)]
    log = tmp_path / "many.csv"
    log.write_text(HEADER + "\n".join(rows) + "\n")
    code, printed, err, out = compensate_with_log(tmp_path, log, capsys)
    assert code == 0, err
    lines = printed.strip().splitlines()
    (summary,) = [line for line in lines if line.startswith("table log:")]
    assert summary == f"table log: {n:,} dwells: {n:,} refused"
    grouped = [line for line in lines if re.match(r"  [\d,]+ refused: ", line)]
    counts = sorted(int(line.split()[0].replace(",", "")) for line in grouped)
    assert counts == [10, n - 10], grouped  # one line a reason, whatever its figures
    assert len(lines) <= 8, lines
    assert all("the dwells ending at" in line and "..." in line for line in grouped)
