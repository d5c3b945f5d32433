"""The chamber log: written row by row, read back exactly, and every file that is not one refused in one line."""

from __future__ import annotations

import math
import os
from datetime import UTC, datetime, timedelta, timezone

import numpy as np
import pytest

from fog_driver.errors import InputFileError, OutputFileError
from fog_driver.lab.chamberlog import (
    LOG_COLUMNS,
    LOG_FORMAT_LINE,
    ChamberLogWriter,
    LogHeader,
    LogRow,
    format_utc,
    program_sha256,
    read_chamber_log,
)
from fog_driver.lab.program import ChamberProfile, Hold, Ramp

HEADER = LogHeader('fast, ramps "quoted"\nname', "ab" * 32, "watlow-f4t://10.0.0.5?unit=1", "run-1", None)


def _rows(n: int = 5) -> list[LogRow]:
    t0 = datetime(2026, 12, 7, 17, 0, tzinfo=UTC)
    rows = [LogRow(format_utc(t0), None, None, 20.0, 24.5, "settling", 20.0, None)]
    for i in range(1, n):
        rows.append(
            LogRow(
                format_utc(t0 + timedelta(seconds=i)),
                i * 1.1,
                100.0 + i / 3,
                20.0 + i / 7,
                20.1 + i / 9,
                "running",
                20 + i / 7,
                i % 3,
            )
        )
    rows.append(LogRow(format_utc(t0 + timedelta(seconds=n)), n * 1.1, None, None, None, "link_lost", None, 1))
    return rows


def _write(path, rows, header=HEADER, **kw):
    with ChamberLogWriter(path, header, **kw) as log:
        for row in rows:
            log.write(row)


def test_a_chamber_log_written_row_by_row_reads_back_exactly(tmp_path):
    path = tmp_path / "run.chamber.csv"
    rows = _rows()
    _write(path, rows)
    log = read_chamber_log(path)
    assert log.header == HEADER
    assert log.rows == rows
    assert not log.cut_last_row and log.cut_warning() is None
    expected_air = np.array([np.nan if r.air_c is None else r.air_c for r in rows])
    np.testing.assert_array_equal(log.air_c, expected_air)
    assert np.isnan(log.t_s[0]) and log.t_s[1] == rows[1].t_s
    assert np.isnan(log.device_t_s[-1]) and log.device_t_s[2] == rows[2].device_t_s
    assert np.isnan(log.setpoint_c[-1]) and log.setpoint_c[3] == rows[3].setpoint_c
    assert log.utc_s[1] - log.utc_s[0] == pytest.approx(1.0)
    text = path.read_text().splitlines()
    assert text[0] == LOG_FORMAT_LINE and text[6] == ",".join(LOG_COLUMNS)


def test_a_chamber_log_saved_with_crlf_line_ends_reads_the_same(tmp_path):
    path = tmp_path / "run.chamber.csv"
    rows = _rows()
    _write(path, rows)
    path.write_bytes(path.read_bytes().replace(b"\n", b"\r\n"))
    log = read_chamber_log(path)
    assert log.rows == rows and log.header == HEADER and not log.cut_last_row


def test_each_row_is_on_disk_as_soon_as_it_is_written(tmp_path):
    path = tmp_path / "run.chamber.csv"
    writer = ChamberLogWriter(path, HEADER)
    rows = _rows(3)
    for i, row in enumerate(rows, 1):
        writer.write(row)
        assert read_chamber_log(path).rows == rows[:i]  # another process reading it sees every row
    writer.close()
    writer.close()


def test_a_log_cut_mid_row_by_a_crash_reads_its_complete_rows_with_one_warning(tmp_path):
    path = tmp_path / "run.chamber.csv"
    rows = _rows()
    _write(path, rows)
    data = path.read_bytes()
    path.write_bytes(data[:-9])  # the last row half written
    log = read_chamber_log(path)
    assert log.rows == rows[:-1]
    assert log.cut_last_row
    assert "last row was cut" in log.cut_warning()


def test_a_chamber_log_over_an_existing_file_is_refused_without_force(tmp_path):
    path = tmp_path / "run.chamber.csv"
    path.write_text("precious\n")
    with pytest.raises(OutputFileError, match="refusing to overwrite") as err:
        ChamberLogWriter(path, HEADER)
    assert err.value.exit_status == 73
    assert path.read_text() == "precious\n"
    _write(path, _rows(2), force=True)
    assert len(read_chamber_log(path).rows) == 3


def test_program_sha256_follows_the_segments_not_the_name():
    a = ChamberProfile("a", 20.0, (Ramp(1.0, 60.0), Hold(600.0)))
    b = ChamberProfile("b", 20.0, (Ramp(1.0, 60.0), Hold(600.0)))
    c = ChamberProfile("a", 20.0, (Ramp(1.0, 60.0), Hold(601.0)))
    d = ChamberProfile("a", 21.0, (Ramp(1.0, 60.0), Hold(600.0)))
    assert program_sha256(a) == program_sha256(b)
    assert len({program_sha256(a), program_sha256(c), program_sha256(d)}) == 3
    assert len(program_sha256(a)) == 64


def test_format_utc_is_the_ndjson_stamp_and_refuses_a_naive_time():
    dt = datetime(2026, 12, 7, 18, 49, 50, 123999, tzinfo=timezone(timedelta(hours=1)))
    assert format_utc(dt) == "2026-12-07T17:49:50.123Z"
    with pytest.raises(ValueError, match="naive"):
        format_utc(datetime(2026, 1, 1))


@pytest.mark.parametrize(
    "row",
    [
        LogRow("2026-12-07T17:00:00.000Z", math.nan, None, None, None, "running", None, None),
        LogRow("2026-12-07T17:00:00.000Z", None, None, None, None, "flying", None, None),
        LogRow("2026-12-07T17:00:00.000Z", None, None, None, None, "running", None, -1),
        LogRow("2026,12", None, None, None, None, "running", None, None),
    ],
)
def test_a_row_the_log_cannot_hold_is_refused_and_nothing_is_written(tmp_path, row):
    path = tmp_path / "run.chamber.csv"
    with ChamberLogWriter(path, HEADER) as log, pytest.raises(ValueError):
        log.write(row)
    assert read_chamber_log(path).rows == []


def _good_text(tmp_path):
    path = tmp_path / "good.csv"
    _write(path, _rows(2))
    return path.read_text()


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda t: "", "empty, not a chamber log"),
        (lambda t: "t_utc,t_s\n", "not a chamber log"),
        (lambda t: t.replace("chamber log 1", "chamber log 2", 1), "version '2'"),
        (lambda t: t.replace("# run_id", "# run_di"), "line 5: expected the header line '# run_id: ...'"),
        (lambda t: t.replace('# run_id: "run-1"', "# run_id: run-1"), "line 5: run_id is not a JSON string"),
        (lambda t: t.replace('# run_id: "run-1"', "# run_id: 3"), "line 5: run_id must be a JSON string"),
        (lambda t: "\n".join(t.split("\n")[:4]) + "\n", "header ends before run_id"),
        (lambda t: "\n".join(t.split("\n")[:6]) + "\n", "ends before its column line"),
        (lambda t: t.replace("t_utc,t_s,", "t_s,t_utc,"), "line 7: expected the column line"),
        (lambda t: t.replace(",running,", ",flying,", 1), "line 9: state 'flying' is not one of"),
        (lambda t: t.replace(",running,", ",running,x,", 1), "line 9: 9 fields"),
        (lambda t: t.replace("2026-12-07T17:00:01.000Z", "yesterday"), "line 9: t_utc 'yesterday'"),
        (lambda t: t.replace(",1.1,", ",nan,"), "line 9: t_s must be finite, got 'nan'"),
        (lambda t: t.replace(",1.1,", ",abc,"), "line 9: t_s is not a number: 'abc'"),
        (lambda t: t.replace(",running,20.142857142857142,1", ",running,20.1,-1"), "segment '-1'"),
        (lambda t: t + "\n\n", "1 fields"),
    ],
)
def test_a_file_that_is_not_a_chamber_log_is_one_line(tmp_path, edit, message):
    path = tmp_path / "bad.csv"
    path.write_text(edit(_good_text(tmp_path)))
    with pytest.raises(InputFileError) as err:
        read_chamber_log(path)
    assert message in str(err.value)
    assert "\n" not in str(err.value) and str(path) in str(err.value)
    assert err.value.exit_status == 65


def test_a_chamber_log_that_is_not_utf8_a_directory_or_missing_is_one_line(tmp_path):
    path = tmp_path / "bin.csv"
    path.write_bytes(LOG_FORMAT_LINE.encode() + b"\n\xff\xfe\n")
    with pytest.raises(InputFileError, match="not UTF-8"):
        read_chamber_log(path)
    with pytest.raises(InputFileError, match="not a regular file"):
        read_chamber_log(tmp_path)
    with pytest.raises(InputFileError, match="no such chamber log"):
        read_chamber_log(tmp_path / "none.csv")
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    with pytest.raises(InputFileError, match="FIFO"):
        read_chamber_log(fifo)


def test_a_chamber_log_larger_than_its_limit_is_refused(tmp_path, monkeypatch):
    import fog_driver.lab.chamberlog as chamberlog

    path = tmp_path / "big.csv"
    _write(path, _rows(50))
    monkeypatch.setattr(chamberlog, "MAX_CHAMBER_LOG_BYTES", 1000)
    with pytest.raises(InputFileError, match="larger than 1000 bytes"):
        read_chamber_log(path)
