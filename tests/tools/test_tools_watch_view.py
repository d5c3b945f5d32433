"""What ``fog-driver watch`` shows (``fog_driver.tools.watch``): the angle's formats, the daemon's lines parsed and
bounded, the terminal block and the one-line log, the banners; as functions of its state, and as a watch of a fake
daemon printed them."""

from __future__ import annotations

import itertools
import re

import pytest
from watch_fakes import DEVICE, STATUS, VERSION, FakeDaemon, angle, ndjson, watch

from fog_driver.tools.watch import (
    MAX_LINE_BYTES,
    LineReader,
    compact_line,
    format_arcsec,
    format_dms,
    parse_line,
    render,
)


@pytest.mark.parametrize(
    ("arcsec", "text"),
    [
        (3723.5, "1°02'03.50\""),
        (-62.995000000000005, "-0°01'03.00\""),
        (-3723.5, "-1°02'03.50\""),
        (0.0, "0°00'00.00\""),
        (0, "0°00'00.00\""),
        (59.994, "0°00'59.99\""),
        (59.995, "0°01'00.00\""),  # rounding carries into the minutes
        (-59.995, "-0°01'00.00\""),
        (3599.995, "1°00'00.00\""),  # ... and into the degrees
        (-0.004, "0°00'00.00\""),  # no "-0"
        (-0.005, "-0°00'00.01\""),
        (0.125, "0°00'00.13\""),
        (1296000.0, "360°00'00.00\""),  # an integrated angle is not wrapped
        (float("nan"), "nan"),
        (float("-inf"), "-inf"),
    ],
)
def test_format_dms(arcsec, text):
    assert format_dms(arcsec) == text


def test_format_dms_ascii_degree():
    assert format_dms(3723.5, degree="d") == "1d02'03.50\""


@pytest.mark.parametrize(
    ("arcsec", "text"),
    [
        (1e30, "1e+30"),
        (-1e26, "-1e+26"),
        (1e15, "1000000000000000.0"),
        (10**400, "1.000000e+400"),
        (-(10**400), "-1.000000e+400"),
        (float("inf"), "inf"),
    ],
    ids=["1e30", "-1e26", "1e15", "10**400", "-10**400", "inf"],
)
def test_absurd_angles_are_shown_plainly(arcsec, text):
    # before: decimal.InvalidOperation from 1e26" on, OverflowError for an integer beyond float's range
    assert format_dms(arcsec) == text
    assert format_arcsec(arcsec) == text


def test_the_views_survive_absurd_values():
    absurd = angle(
        2,
        angle_arcsec=1e30,
        angle_raw_arcsec=-(10**400),
        rate_dph=10**400,
        t_s=1e300,
        temps_c={"top": 10**400, "housing": 20.0},
    )
    lines = render({**FULL_STATE, "angle": absurd}, width=200)
    assert 'angle       1e+30" (1e+30)    raw -1.000000e+400" (-1.000000e+400)' in lines
    assert "rate        1.000000e+400 deg/h (one sample)" in lines and "drift       0.1234 deg/h" in lines
    assert "temps       top 1.000000e+400  bottom -  housing 20.00 degC" in lines
    assert "1e+30" in compact_line({**FULL_STATE, "angle": absurd})
    daemon = FakeDaemon([ndjson(absurd)], then="wait")
    status, text = watch(daemon, count=1)
    assert status == 0 and "1e+30" in text


@pytest.mark.parametrize(
    ("line", "expected"),
    [
        (b'{"class":"ANGLE","seq":1}\n', {"class": "ANGLE", "seq": 1}),
        (b'{"class":"X"}\r\n', {"class": "X"}),
        (b"", None),
        (b"\n", None),
        (b"not json\n", None),
        (b"[1,2]\n", None),
        (b'"ANGLE"\n', None),
        (b'{"seq":1}\n', None),
        (b'{"class":5}\n', None),
        (b"\xff\xfe{}\n", None),
        (b'{"class":"ANGLE",', None),
        (b'{"class":"A","p":"' + b"x" * MAX_LINE_BYTES + b'"}', None),
        (b"[" * 100_000 + b"]" * 100_000, None),  # deeply nested: no RecursionError
    ],
)
def test_parse_line(line, expected):
    assert parse_line(line) == expected


def test_line_reader_limits_line_length_across_chunks():
    reader = LineReader(max_line=10)
    assert reader.feed(b"abc\nde") == [b"abc"]
    assert reader.feed(b"f\n" + b"x" * 8) == [b"def"]
    assert reader.feed(b"y" * 8) == []  # now over the limit: dropped up to its newline
    assert reader.feed(b"zzz\nok\n") == [b"ok"]
    assert reader.oversized == 1
    assert reader.feed(b"0123456789012\nfine\n") == [b"fine"]
    assert reader.oversized == 2


FULL_STATE = {
    "address": "127.0.0.1:2948",
    "elapsed_s": 3.25,
    "version": VERSION,
    "device": DEVICE,
    "angle": angle(2),
    "status": STATUS,
    "angles": 30,
    "angle_rate_hz": 10.0,
    "angle_age_s": 0.04,
    "malformed": 2,
    "unknown": 1,
    "error": "port lost",
}


def test_render_full_state():
    lines = render(FULL_STATE, width=200)
    assert lines[0] == "fog-driver watch 127.0.0.1:2948  |  server 0.1.0, protocol 1.0  |  3.2 s"
    assert lines[1:] == [
        "instrument  serial FOG-SYN-0001, firmware 1.2, 100 Hz",
        "model       -",  # a daemon before protocol 1.2 does not say
        "device      /tmp/fog-driver-sim.tty, activated, serial FOG-SYN-0001, 100 Hz",
        'angle       3725.50" (1°02\'05.50")    raw -62.00" (-0°01\'02.00")',  # the two forms agree
        "rate        15.0 deg/h (one sample)",
        "drift       0.1234 deg/h",
        "temps       top 20.25  bottom 19.88  housing 19.60 degC",
        "flags       gap",
        "sample      seq 2  t 12.440 s  (received 0.0 s ago)",
        "received    10.0 ANGLE/s  30 ANGLE  2 malformed  1 unknown class",
        "status      clients=1  cpu_percent=2.5  crc_errors=3  frames=4242  missing_frames=7  port_state=open  "
        "some_future_key=x",
        "error       port lost",
    ]


def test_render_wraps_the_status_counters():
    lines = render(FULL_STATE, width=60)
    first = next(i for i, line in enumerate(lines) if line.startswith("status"))
    status = [lines[first]] + list(itertools.takewhile(lambda line: line.startswith(" " * 12), lines[first + 1 :]))
    assert len(status) >= 2 and all(len(line) <= 60 for line in lines)
    assert " ".join(" ".join(status).split()) == (
        "status clients=1 cpu_percent=2.5 crc_errors=3 frames=4242 missing_frames=7 port_state=open some_future_key=x"
    )


def test_the_terminal_view_fits_80_columns_and_loses_nothing():
    """Before: at 80 columns the rate line lost its drift and sigma, the bias banner its command, the sample line
    its time of day: lines were cut at the terminal's edge.  Now they fold, under the label."""
    state = {
        **FULL_STATE,
        "address": "gyro-pc.lab.example.org:2948",
        "keys": True,
        "angle": angle(
            2,
            angle_arcsec=-1234567.891,
            angle_raw_arcsec=-1234560.5,
            drift_sigma_dph=0.0237,
            utc="2026-12-04T11:05:07.123456Z",
            temps_c={"housing": 19.6, "bottom": 19.88, "top": 20.25},  # sent in another order
        ),
        "angle_age_s": 0.1,
        "rate_mean_dph": -10.6123,
        "rate_span_s": 1.0,
        "status": {**FULL_STATE["status"], "bias_captured": False, "bias_sigma_dph": 0.0051},
    }
    for width in (80, 79):  # the view draws at the terminal's width less one
        lines = render(state, width=width)
        assert all(len(line) <= width for line in lines), [line for line in lines if len(line) > width]
        text = " ".join(" ".join(lines).split())
        for shown in (
            "press b (or `fog-driver ctl gyro-pc.lab.example.org:2948 bias 60`)",
            "rate -10.61 deg/h (mean over 1.0 s)",
            "drift 0.1234 deg/h +- 0.0237 (1-sigma)",
            "utc 2026-12-04T11:05:07.123456Z (received 0.1 s ago)",
            "q quit z zero the angle b capture the bias (60 s, table still)",
            "some_future_key=x",
        ):
            assert shown in text, shown
        assert "temps       top 20.25  bottom 19.88  housing 19.60 degC" in lines  # top, bottom, housing


@pytest.mark.parametrize(
    "state",
    [
        {},
        {"angle": {"class": "ANGLE"}},
        {"angle": {"class": "ANGLE", "seq": 1, "temps_c": {"top": 20.0}}},  # two thermometers absent
        {"angle": {"class": "ANGLE", "angle_arcsec": None, "temps_c": None, "flags": None}},
        {"angle": {"class": "ANGLE", "angle_arcsec": "bad", "rate_dph": [1], "temps_c": "hot", "flags": "gap"}},
        {"version": {"class": "VERSION"}, "device": {"class": "DEVICE"}, "status": {"class": "STATUS"}},
        {"version": {"class": "VERSION", "instrument": None}, "device": {"class": "DEVICE", "state": "deactivated"}},
        {"version": "nonsense", "device": 5, "angle": [], "status": {"nested": {"a": None}, "list": [None]}},
        {"version": {"class": "VERSION", "proto_major": 2}},
    ],
)
def test_render_with_missing_fields_never_crashes_or_shows_none(state):
    for lines in (render(state), [compact_line(state)]):
        assert lines and all(isinstance(line, str) for line in lines)
        text = "\n".join(lines)
        assert "None" not in text and "null" not in text


def test_render_missing_fields_show_a_dash():
    lines = render({"angle": {"class": "ANGLE", "seq": 7, "temps_c": {"top": 20.0}}})
    assert "instrument  -" in lines
    assert "device      -" in lines
    assert "angle       -    raw -" in lines
    assert "temps       top 20.00  bottom -  housing - degC" in lines
    assert "flags       -" in lines
    assert "status      -" in lines
    assert not any(line.startswith("error") for line in lines)
    assert "waiting for ANGLE" in "\n".join(render({}))


@pytest.mark.parametrize(
    "angle_sigma, status, shown",
    [
        (0.03, {"bias_captured": False}, "drift 0.1234 deg/h +- 0.0300 (1-sigma)"),  # before a bias: sigma(t)
        (0.03, {}, "drift 0.1234 deg/h +- 0.0300 (1-sigma)"),  # no STATUS yet
        # sqrt(0.03^2 + 0.04^2) = 0.05 once a bias was captured with sigma(t_b) = 0.04
        (
            0.03,
            {"bias_captured": True, "bias_sigma_dph": 0.04},
            "drift 0.1234 deg/h +- 0.0500 (1-sigma since the bias)",
        ),
        (
            0.012,
            {"bias_captured": True, "bias_sigma_dph": 0.005},
            "drift 0.1234 deg/h +- 0.0130 (1-sigma since the bias)",
        ),
        (
            0.03,
            {"bias_captured": True},
            "drift 0.1234 deg/h +- - (1-sigma since the bias: unknown, the bias was captured without one)",
        ),
        (None, {"bias_captured": True, "bias_sigma_dph": 0.04}, "drift 0.1234 deg/h"),  # no estimate, or 1.0
    ],
)
def test_the_drift_sigma_is_shown_plain_before_a_bias_and_in_the_since_bias_form_after(angle_sigma, status, shown):
    sample = angle(1) if angle_sigma is None else angle(1, drift_sigma_dph=angle_sigma)
    state = {"angle": sample, "status": {"class": "STATUS", **status}}
    drift_line = next(line for line in render(state, width=200) if line.startswith("drift "))
    assert drift_line == f"drift       {shown.removeprefix('drift ')}"
    assert f"| {shown} |" in compact_line(state)
    if angle_sigma is None:
        assert "+-" not in compact_line(state) and "sigma" not in drift_line


def test_watch_shows_the_since_bias_form_once_the_daemon_says_a_bias_was_captured():
    before = {**STATUS, "bias_captured": False}
    after = {**STATUS, "bias_captured": True, "bias_dph": 9.9, "bias_sigma_dph": 0.04}
    chunks = [
        ndjson(before, angle(1, drift_sigma_dph=0.03), angle(2, drift_sigma_dph=0.03)),
        ndjson(after, angle(3, drift_sigma_dph=0.03)),
    ]
    daemon = FakeDaemon(chunks, then="wait")
    status, text = watch(daemon, count=3, rate_hz=10)
    assert status == 0
    assert "drift 0.1234 deg/h +- 0.0500 (1-sigma since the bias)" in text.splitlines()[-1].split(" | ")


def test_render_flags_a_newer_protocol():
    assert (
        "protocol 2.0 (this client speaks 1.x)"
        in render({"version": {"class": "VERSION", "release": "9", "proto_major": 2}})[0]
    )


def test_compact_line_is_one_line():
    line = compact_line(FULL_STATE)
    assert "\n" not in line
    assert re.match(r"\[ +3\.2 s\] seq 2 \| t 12\.440 s \| angle 3725\.50\" \(1°02'05\.50\"\)", line)


@pytest.mark.parametrize(
    ("arcsec", "text"), [(3723.5, "3723.50"), (-59.995, "-60.00"), (-0.004, "0.00"), (2.675, "2.68")]
)
def test_format_arcsec_agrees_with_format_dms(arcsec, text):
    assert format_arcsec(arcsec) == text


def test_server_text_cannot_inject_control_characters():
    state = {
        "error": "bad\nline\x1b[2J",
        "status": {"class": "STATUS", "k\x1b[H": "v\r"},
        "device": {"class": "DEVICE", "path": "/dev/tty\x07", "state": "activated"},
    }
    for text in ("\n".join(render(state)), compact_line(state)):
        assert "\x1b" not in text and "\r" not in text and "\x07" not in text
    assert "error       bad?line?[2J" in render(state)


@pytest.mark.parametrize(
    ("policy", "shown"),
    [
        ({"enable": True, "rate_hz": 10}, "(WATCH 10 Hz)"),
        ({"enable": True, "rate_hz": None}, "(WATCH every sample)"),
        ({"enable": True}, "(WATCH every sample)"),
        ({"enable": False}, "(WATCH disabled)"),
    ],
)
def test_render_shows_the_watch_policy_in_force(policy, shown):
    received = [line for line in render({"watch": {"class": "WATCH", **policy}}) if line.startswith("received")]
    assert received[0].endswith(shown)


@pytest.mark.parametrize(
    ("state", "banner"),
    [
        ({"device": {"state": "deactivated"}}, "*** LINK DOWN: the daemon's instrument port is closed"),
        ({"status": {"port_state": "lost"}}, "*** LINK DOWN"),
        ({"elapsed_s": 7.2}, "*** NO DATA for 7 s ***"),
        ({"angle": angle(1), "angle_age_s": 4.0}, "*** NO DATA for 4 s ***"),
        (
            {"status": {"bias_captured": False}, "keys": True},
            "bias not removed: at rest the angle climbs with Earth rate + bias; press b (or `fog-driver ctl bias 60`)",
        ),
        (
            {"status": {"bias_captured": False}, "address": "gyro-pc:2948"},
            "bias not removed: at rest the angle climbs with Earth rate + bias; "
            "run `fog-driver ctl gyro-pc:2948 bias 60`",
        ),
        (
            {"status": {"bias_captured": False, "bias_capture_s": 12.0, "bias_capture_target_s": 60.0}},
            "capturing the bias: 12.0 / 60 s of data; keep the table still",
        ),
    ],
)
def test_banners(state, banner):
    lines = render(state)
    shown = " ".join(" ".join(lines[1:4]).split())  # a long banner folds at 80 columns
    assert shown.startswith(banner), lines  # right under the head line
    assert compact_line(state).split(" | ")[0].split("] ")[1] in banner  # and first in the log line


@pytest.mark.parametrize(
    "state",
    [
        {"status": {"bias_captured": True}, "elapsed_s": 1.0},
        {"angle": angle(1), "angle_age_s": 0.5, "device": {"state": "activated"}},
        {"status": {"bias_dph": 0.0}},
    ],
)
def test_no_banner_when_all_is_well(state):
    assert not any(line.startswith(("***", "bias", "capturing")) for line in render(state))
