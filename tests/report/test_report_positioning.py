"""Positioning accuracy (the paper's Table 1): dwell means, trimming, grouping, the reference CSV, end to end."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from fog_driver.dwells import MAX_TABLE_LOG_BYTES, TABLE_LOG_FORMAT, Dwell, read_table_log
from fog_driver.errors import InputFileError, UsageError
from fog_driver.report.positioning import (
    NO_SEQUENCES,
    RAW,
    Row,
    dwell_reference_deg,
    format_table,
    group_sequences,
    improvement,
    improvement_per_row,
    load_stops,
    positioning_errors,
    positioning_table,
    stops_from_sidecar,
)

ROOT = Path(__file__).resolve().parents[2]
RATE_HZ = 50


# --- synthetic data ------------------------------------------------------------------------------


def make_stops(n=11, start=100.0, dwell=60.0, move=4.0, step=36.0):
    stops, t = [], start
    for k in range(n):
        stops.append(Dwell(t, t + dwell, k * step))
        t += dwell + move
    return stops


def synthetic(stops, *, drift=0.0, noise=0.0, settle=0.0, seed=0):
    """Angle in arcsec at 50 Hz: the table (linear during moves) + drift * t + noise + a settling wobble."""
    t = np.arange(int((stops[-1].t_end_s + 20.0) * RATE_HZ)) / RATE_HZ
    starts = np.array([s.t_start_s for s in stops])
    ends = np.array([s.t_end_s for s in stops])
    angles = np.array([s.angle_deg for s in stops]) * 3600.0
    # table: the dwell angles, linear ramps between one dwell's end and the next one's start
    knots_t = np.ravel(np.column_stack([starts, ends]))
    knots_a = np.repeat(angles, 2)
    table = np.interp(t, knots_t, knots_a)
    angle = table + drift * t
    if noise:
        angle = angle + np.random.default_rng(seed).normal(0.0, noise, len(t))
    if settle:
        k = np.searchsorted(starts, t, side="right") - 1
        since = t - starts[np.maximum(k, 0)]
        ringing = (k >= 0) & (since < 3.0)
        amp = settle * (1.0 + (k % 3))  # a different overshoot at each stop
        angle = angle + np.where(ringing, amp * np.exp(-since), 0.0)
    return t, angle


def dwell_midpoints(stops, trim=5.0):
    return np.array([(s.t_start_s + trim + s.t_end_s - trim) / 2 for s in stops])


def test_exact_steps_give_zero_error():
    stops = make_stops()
    t, a = synthetic(stops)
    e = positioning_errors(t, a, stops)
    assert e.shape == (10,)
    assert np.abs(e).max() < 1e-6


def test_injected_drift_gives_the_known_error():
    drift = 0.25  # arcsec/s = 0.25 deg/h
    stops = make_stops()  # every dwell edge on the 50 Hz grid: the dwell means sit exactly at the midpoints
    t, a = synthetic(stops, drift=drift)
    e = positioning_errors(t, a, stops)
    np.testing.assert_allclose(e, drift * 64.0, atol=1e-6)
    stops = make_stops(move=3.795)  # off the grid: within one sample of drift
    t, a = synthetic(stops, drift=drift)
    e = positioning_errors(t, a, stops)
    expected = drift * np.diff(dwell_midpoints(stops))  # 0.25 * 63.795 s
    np.testing.assert_allclose(e, expected, atol=drift / RATE_HZ)
    # removing the drift as a bias gives zero
    assert np.abs(positioning_errors(t, a, stops, bias_arcsec_per_s=drift)).max() < 1e-6


def test_noise_averages_out_over_a_dwell():
    stops = make_stops()
    t, a = synthetic(stops, drift=0.1, noise=2.0, seed=4)
    e = positioning_errors(t, a, stops)
    expected = 0.1 * 64.0
    # a dwell mean of 2500 samples of 2 arcsec noise: 0.04 arcsec; a move: 0.057 arcsec std
    assert np.abs(e - expected).max() < 0.3
    assert abs(e.mean() - expected) < 0.1


def test_trimming_excludes_the_settling():
    stops = make_stops()
    t, a = synthetic(stops, settle=50.0)  # a decaying overshoot of 50..150 arcsec for 3 s after every stop starts
    trimmed = positioning_errors(t, a, stops, dwell_trim_s=5.0)
    untrimmed = positioning_errors(t, a, stops, dwell_trim_s=0.0)
    assert np.abs(trimmed).max() < 1e-6
    # with no trim the ringing is in the dwell means
    assert np.abs(untrimmed).min() > 0.1
    with pytest.raises(ValueError, match="twice dwell_trim_s"):
        positioning_errors(t, a, stops, dwell_trim_s=30.0)


def test_a_dwell_without_samples_gives_nan_moves():
    stops = make_stops(n=4)
    t, a = synthetic(stops)
    keep = ~((t > stops[1].t_start_s) & (t < stops[1].t_end_s))  # a gap over dwell 1
    e = positioning_errors(t[keep], a[keep], stops)
    assert np.isnan(e[0]) and np.isnan(e[1]) and abs(e[2]) < 1e-6


def test_errors_need_matching_columns():
    with pytest.raises(ValueError, match="same length"):
        positioning_errors(np.zeros(3), np.zeros(4), make_stops(n=2))
    assert len(positioning_errors(np.zeros(3), np.zeros(3), make_stops(n=1))) == 0


# --- grouping ------------------------------------------------------------------------------------


def test_grouping_by_gap():
    a = make_stops(n=3, start=0.0)  # ends at 3 * 64 - 4 = 188 s
    end = a[-1].t_end_s
    b = make_stops(n=4, start=end + 119.9)  # just under 120 s: same sequence
    c = make_stops(n=2, start=b[-1].t_end_s + 120.0)  # exactly 120 s: a new sequence
    lone = [Dwell(c[-1].t_end_s + 1000, c[-1].t_end_s + 1060, 0.0)]  # one stop: no move, dropped
    groups = group_sequences(a + b + c + lone)
    assert [len(g) for g in groups] == [7, 2]
    assert groups[0][0] == a[0] and groups[1] == c
    assert [len(g) for g in group_sequences(a + b, gap_s=60.0)] == [3, 4]
    assert group_sequences([]) == [] and group_sequences(lone) == []


# --- the reference CSV ---------------------------------------------------------------------------


def write(tmp_path, text, name="ref.csv", encoding="utf-8"):
    path = tmp_path / name
    path.write_text(text, encoding=encoding)
    return path


def test_reference_csv_good(tmp_path):
    text = (
        "# turntable reference\n\n"
        "t_start_s, t_end_s, angle_deg   # the header\n"
        "1500.0,1560.0,0\n"
        "# a comment between rows\n"
        "1563.8,1623.8,36  # trailing comment\n"
        "1627.6,1687.6,72\n"
    )
    assert read_table_log(write(tmp_path, text)) == [
        Dwell(1500.0, 1560.0, 0.0),
        Dwell(1563.8, 1623.8, 36.0),
        Dwell(1627.6, 1687.6, 72.0),
    ]
    # any column order, extra columns, a BOM, touching dwells
    text = "angle_deg,t_end_s,note,t_start_s\n0,10,a,0\n-36,20,b,10\n"
    assert read_table_log(write(tmp_path, text, "b.csv", "utf-8-sig")) == [Dwell(0, 10, 0), Dwell(10, 20, -36)]


def test_a_dwell_the_table_moved_in_is_held_against_its_mean_angle(tmp_path):
    """A table creeping through some dwells (the log gives each dwell's start and end angle): the measured
    angle, exactly the table's, leaves zero error when the reference is the dwell's mean angle
    (``angle_end_deg``, read from the CSV), and the creep's own angle over a dwell without it."""
    creep = 0.3  # deg/h... as arcsec/s: 0.3 arcsec/s, a creep the dwell means show clearly
    plain = make_stops()
    t = np.arange(int((plain[-1].t_end_s + 20.0) * RATE_HZ)) / RATE_HZ
    t_a, t_b = plain[3].t_start_s + 10.0, plain[6].t_end_s - 20.0  # the creep's span, through dwells 3..6
    base = synthetic(plain)[1] / 3600.0
    table_deg = base + creep / 3600.0 * (np.clip(t, t_a, t_b) - t_a)
    lagged = [
        Dwell(
            s.t_start_s,
            s.t_end_s,
            float(np.interp(s.t_start_s, t, table_deg)),
            float(np.interp(s.t_end_s, t, table_deg)),
        )
        for s in plain
    ]
    rows = "".join(f"{s.t_start_s!r},{s.t_end_s!r},{s.angle_deg!r},{s.angle_end_deg!r}\n" for s in lagged)
    logged = read_table_log(write(tmp_path, "t_start_s,t_end_s,angle_deg,angle_end_deg\n" + rows))
    assert logged == lagged
    angle = table_deg * 3600.0
    with_end = positioning_errors(t, angle, logged)
    # dwells fully inside the creep's span are linear: exact; the two it starts or ends in are not
    inside = [k for k in range(len(plain) - 1) if t_a <= plain[k].t_start_s and plain[k + 1].t_end_s <= t_b]
    assert inside and np.abs(with_end[inside]).max() < 1e-6
    for k in inside:  # the reference is the table's own mean over the trimmed window
        window = (t >= logged[k].t_start_s + 5.0) & (t <= logged[k].t_end_s - 5.0)
        assert dwell_reference_deg(logged[k]) == pytest.approx(table_deg[window].mean(), abs=1e-9)
    assert dwell_reference_deg(plain[0]) == plain[0].angle_deg  # no angle_end_deg: the dwell's angle


def test_reference_csv_format_text_is_documented():
    assert "t_start_s,t_end_s,angle_deg" in TABLE_LOG_FORMAT and "#" in TABLE_LOG_FORMAT


@pytest.mark.parametrize(
    "text, match",
    [
        ("t_start_s,angle_deg\n0,0\n", "missing column t_end_s"),
        ("start,end,angle\n0,1,0\n", "missing columns t_start_s, t_end_s, angle_deg"),
        ("t_start_s,t_end_s,angle_deg\n0,10,zero\n", r"ref.csv:2: angle_deg is not a number: 'zero'"),
        ("t_start_s,t_end_s,angle_deg\n0,10,nan\n", "angle_deg must be finite"),
        ("t_start_s,t_end_s,angle_deg\n0,10,0\n5,20,36\n", r"ref.csv:3: times must increase"),
        (
            "t_start_s,t_end_s,angle_deg\n0,10,0\n20,15,36\n",
            r"ref.csv:3: t_end_s \(15\) must be after t_start_s \(20\)",
        ),
        ("t_start_s,t_end_s,angle_deg\n-1,10,0\n", "must not be negative"),
        ("t_start_s,t_end_s,angle_deg\n0,10\n", "2 fields, the header has 3"),
        ("# only a comment\n\n", "reference CSV is empty"),
        ("t_start_s,t_end_s,angle_deg\n", "has a header but no stops"),
    ],
)
def test_reference_csv_bad(tmp_path, text, match):
    with pytest.raises(InputFileError, match=match) as info:
        read_table_log(write(tmp_path, text))
    assert "\n" not in str(info.value)


def test_reference_csv_bad_files(tmp_path):
    big = tmp_path / "big.csv"
    big.write_text("t_start_s,t_end_s,angle_deg\n" + "#" * MAX_TABLE_LOG_BYTES + "\n")
    for path, match in (
        (big, "over the limit"),
        (tmp_path / "none.csv", "no such reference CSV"),
        (tmp_path, "is a directory"),
    ):
        with pytest.raises(InputFileError, match=match) as info:
            read_table_log(path)
        assert "\n" not in str(info.value)
    binary = tmp_path / "bin.csv"
    binary.write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(InputFileError, match="not UTF-8"):
        read_table_log(binary)


# --- statistics and formatting -------------------------------------------------------------------


def row(label, raw_mean, comp_mean):
    return Row(label, 10, {RAW: (raw_mean, 0.1), "wesn": (comp_mean, 0.05)})


def test_improvement_definitions():
    rows = [row("-40 degC", 0.168, 0.097), row("-30 degC", -0.2, 0.05)]
    per_row = improvement_per_row(rows, "wesn")
    assert per_row[0] == pytest.approx(100 * (1 - 0.097 / 0.168))  # the paper's -40 degC: 42.3 % (printed 42.1)
    assert per_row[1] == pytest.approx(75.0)  # |mean| on both sides
    assert improvement(rows, "wesn") == pytest.approx(100 * (1 - (0.097 + 0.05) / (0.168 + 0.2)))
    assert math.isnan(improvement([], "wesn"))


def test_format_table():
    rows = [row("-40 degC", 0.168, 0.097), Row("sequence 2", 1, {RAW: (1.0, math.nan), "wesn": (0.5, math.nan)})]
    text = format_table(rows)
    lines = text.splitlines()
    assert lines[0] == "| Temperature | moves | uncompensated mean | uncompensated std | wesn mean | wesn std |"
    assert lines[2] == "| -40 degC | 10 | 0.168 | 0.100 | 0.097 | 0.050 |"
    assert lines[3] == "| sequence 2 | 1 | 1.000 | n/a | 0.500 | n/a |"
    assert format_table([]) == NO_SEQUENCES == "no positioning sequences in this capture: the table is skipped"


# --- end to end on a simulated capture -----------------------------------------------------------


@pytest.fixture(scope="module")
def positioning_capture(tmp_path_factory):
    from fog_driver.lab.profiles import load_profile
    from fog_driver.sim.capture import simulate_to_file
    from fog_driver.sim.instrument import Simulator

    out = tmp_path_factory.mktemp("pos") / "positioning.bin"
    sim = Simulator(load_profile(ROOT / "configs" / "profiles" / "positioning.yaml"), rate_hz=RATE_HZ, seed=1)
    simulate_to_file(sim, out, duration_s=40 * 60)
    return out


@pytest.fixture(scope="module")
def default_model():
    from fog_driver.daemon.config import DEFAULT_MODEL
    from fog_driver.modelfiles import load_model

    return load_model(DEFAULT_MODEL)


def test_end_to_end_simulated_positioning(positioning_capture, default_model):
    stops = load_stops(positioning_capture)
    assert len(stops) == 11 and stops == stops_from_sidecar(positioning_capture)
    rows = positioning_table(positioning_capture, {"wesn": default_model}, stops)
    assert len(rows) == 1
    r = rows[0]
    print("\n" + format_table(rows))
    print(f"improvement {improvement(rows, 'wesn'):.1f} %, bias {r.bias_dph} deg/h over {r.bias_window_s} s")
    assert r.n_moves == 10 and r.errors["wesn"].shape == (10,)
    assert r.label == f"{round(r.temp_c)} degC" and 24 < r.temp_c < 30  # housing, above the 25 degC air
    mean, std = r.stats["wesn"]
    assert math.isfinite(mean) and math.isfinite(std) and np.isfinite(r.errors["wesn"]).all()
    assert abs(mean) < 2.0 and std < 3.0
    # the uncompensated drift since the bias window (20 -> 25 degC) is several arcsec per step
    assert abs(r.stats[RAW][0]) > 3.0 and improvement(rows, "wesn") > 50.0
    # the bias (Earth rate + constant + turn-on, ~10 deg/h) is what the table removes first
    assert 5.0 < r.bias_dph[RAW] < 15.0
    kept = positioning_table(positioning_capture, {"wesn": default_model}, stops, remove_bias=False)
    assert kept[0].stats["wesn"][0] > 300.0  # ~10 arcsec/s over every 64-s step


def test_end_to_end_with_a_station_csv(positioning_capture, default_model, tmp_path):
    stops = stops_from_sidecar(positioning_capture)
    ref = tmp_path / "ref.csv"
    ref.write_text(
        "# reference\nt_start_s,t_end_s,angle_deg\n"
        + "".join(f"{s.t_start_s!r},{s.t_end_s!r},{s.angle_deg!r}\n" for s in stops)
    )
    assert load_stops(positioning_capture, ref) == stops
    a = positioning_table(positioning_capture, {"wesn": default_model}, stops, plateau_temps_c=[25])
    b = positioning_table(positioning_capture, {}, read_table_log(ref), bias_window_s=(60.0, 360.0))
    assert a[0].label == "25 degC" and list(b[0].stats) == [RAW]
    assert abs(a[0].stats[RAW][0] - b[0].stats[RAW][0]) < 1.0  # another bias window, the same drift
    with pytest.raises(UsageError, match="2 plateau temperatures for 1 positioning sequences"):
        positioning_table(positioning_capture, {}, stops, plateau_temps_c=[25, 30])


def test_capture_without_stops_skips_the_table(tmp_path, default_model):
    from fog_driver.lab.profiles import load_profile
    from fog_driver.sim.capture import simulate_to_file
    from fog_driver.sim.instrument import Simulator

    out = tmp_path / "static.bin"
    simulate_to_file(
        Simulator(load_profile(ROOT / "configs" / "profiles" / "short-test.yaml"), rate_hz=10, seed=2),
        out,
        duration_s=30,
    )
    stops = load_stops(out)
    assert stops == []
    rows = positioning_table(out, {"wesn": default_model}, stops)
    assert rows == [] and format_table(rows) == NO_SEQUENCES


def test_report_for_evaluate(positioning_capture, default_model):
    import json

    from fog_driver.report.positioning import report_for

    summary: dict = {}
    text = report_for(str(positioning_capture), default_model, summary)
    assert text.startswith("| Temperature | moves | uncompensated mean") and "precision improvement" in text
    assert summary["positioning"]["rows"][0]["moves"] == 10
    json.dumps(summary, allow_nan=False)


def test_evaluate_command_with_reference_and_compare(positioning_capture, tmp_path):
    """The CLI end to end: the table from a station's reference CSV, with a second model compared;
    a bad reference CSV is one line on stderr and a non-zero exit, no report written."""
    import json
    import subprocess
    import sys

    from fog_driver.daemon.config import DEFAULT_MODEL

    stops = load_stops(positioning_capture)
    ref = tmp_path / "stops.csv"
    ref.write_text(
        "t_start_s,t_end_s,angle_deg\n" + "".join(f"{s.t_start_s!r},{s.t_end_s!r},{s.angle_deg!r}\n" for s in stops)
    )
    other = tmp_path / "other.yaml"
    other.write_bytes(Path(DEFAULT_MODEL).read_bytes())
    out = tmp_path / "rep"
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "fog_driver",
            "evaluate",
            str(positioning_capture),
            "--model",
            str(DEFAULT_MODEL),
            "--out",
            str(out),
            "--reference",
            str(ref),
            "--compare",
            str(other),
            "--json",
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(proc.stdout)
    row = summary["positioning"]["rows"][0]
    main, other = "default (wesn)", "other (wesn)"  # every model by its file stem and kind
    assert row["moves"] == 10 and set(row["methods"]) == {RAW, main, other}
    assert row["methods"][other] == row["methods"][main]  # the same model under another name
    assert abs(row["methods"][main]["mean_arcsec"]) < 2.0 < abs(row["methods"][RAW]["mean_arcsec"])
    report = (out / "report.md").read_text()
    assert "| Temperature | moves | uncompensated mean" in report and "other (wesn) mean" in report

    zeroed = subprocess.run(
        [
            sys.executable,
            "-m",
            "fog_driver",
            "evaluate",
            str(positioning_capture),
            "--model",
            str(DEFAULT_MODEL),
            "--out",
            str(tmp_path / "rep-z"),
            "--zero-window",
            "400:700",
            "--json",
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert zeroed.returncode == 0, zeroed.stderr
    zrow = json.loads(zeroed.stdout)["positioning"]["rows"][0]
    assert zrow["bias_window_s"] == [400.0, 700.0] and row["bias_window_s"] != [400.0, 700.0]
    assert zrow["bias_dph"][main] != row["bias_dph"][main]
    for window in ("700:400", "abc", "-5:10", "5"):
        proc = subprocess.run(
            [
                sys.executable,
                "-m",
                "fog_driver",
                "evaluate",
                str(positioning_capture),
                "--model",
                str(DEFAULT_MODEL),
                "--out",
                str(tmp_path / "rep-bad"),
                "--zero-window",
                window,
            ],
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert proc.returncode == 2 and "START:END" in proc.stderr and "Traceback" not in proc.stderr, window

    bad = tmp_path / "bad.csv"
    bad.write_text("t_start_s,t_end_s,angle_deg\n10,5,0\n")
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "fog_driver",
            "evaluate",
            str(positioning_capture),
            "--model",
            str(DEFAULT_MODEL),
            "--out",
            str(tmp_path / "rep2"),
            "--reference",
            str(bad),
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode != 0 and "Traceback" not in proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "bad.csv:2: t_end_s (5) must be after t_start_s (10)" in lines[0], proc.stderr
    assert not (tmp_path / "rep2" / "report.md").exists()
