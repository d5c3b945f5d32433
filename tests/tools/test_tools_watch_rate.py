"""The rate ``fog-driver watch`` shows: the mean over the last second of device time, every frame's rate in it
(the frames the decimation dropped included), after a replug too, and what it rests on in the daemon's lines."""

from __future__ import annotations

import math

import pytest
from watch_fakes import FakeDaemon, angle, ndjson, watch


def test_the_rate_shown_is_the_mean_over_the_last_second_not_one_sample():
    """The review's finding 6: one decimated sample's rate, quantized, with 4 decimals."""
    rates = [9.0, 12.0, 14.0, 9.0, 11.0, 10.0, 8.0, 13.0, 10.0, 9.0, 12.0, 11.0, 10.0]  # one count steps
    angles, arcsec = [], 100.0
    for k, rate in enumerate(rates):
        arcsec += rate * 0.1  # deg/h = arcsec/s: each sample's increment over its 0.1 s
        angles.append(angle(k + 1, t_s=20.0 + 0.1 * k, angle_arcsec=arcsec, rate_dph=rate, flags=[]))
    daemon = FakeDaemon([ndjson(*angles)], then="wait")
    status, text = watch(daemon, count=len(rates))
    assert status == 0
    mean = sum(rates[-10:]) / 10  # the last 1.0 s of device time: the samples after the window's first point
    assert f"rate {mean:.2f} deg/h (mean over 1.0 s)" in text.splitlines()[-1]


def test_the_daemons_rates_average_to_the_angle_difference(tmp_path):
    """What the averaged rate rests on: over every published sample, the mean of ``rate_dph`` is the angle's
    difference over the device time (1 arcsec/s = 1 deg/h)."""
    from daemon_hil import SHORT, watch_all, watched_daemon

    from fog_driver.protocol import decode_bytes

    with watched_daemon(tmp_path) as (pty, daemon, client):
        pty.write(SHORT[:20000])
        angles = watch_all(client, decode_bytes(SHORT[:20000], final=False).counters.sample_frames)
        assert daemon.terminate() == 0
    window = [a for a in angles if "gap" not in a["flags"]][-11:]
    mean = sum(a["rate_dph"] for a in window[1:]) / 10
    assert mean == pytest.approx(
        (window[-1]["angle_arcsec"] - window[0]["angle_arcsec"]) / (window[-1]["t_s"] - window[0]["t_s"]), abs=1e-9
    )


def frames_after_a_replug(rng_seed: int = 13) -> tuple[list[dict], list[int], list[float]]:
    """A 100 Hz instrument's frames as the daemon publishes them around a replug: 3 s, then 145 s of frames that
    never arrived (the angle holds, device time runs on), then 5 s all flagged ``gap`` while the estimate
    settles.  Each frame's rate is a whole number of deg/h (one count per frame), its angle the running sum of
    rate x 0.01 s.  Returns the frames and each one's seq and rate (the reference)."""
    import numpy as np

    rng = np.random.default_rng(rng_seed)
    seqs = [*range(0, 300), *range(14800, 15300)]
    frames, rates, arcsec = [], [], 1000.0
    for seq in seqs:
        rate = float(rng.integers(6, 15))
        arcsec += rate * 0.01  # deg/h = arcsec/s
        flags = ["gap"] if seq >= 14800 else []
        frames.append(angle(seq, t_s=50.0 + seq / 100, angle_arcsec=arcsec, rate_dph=rate, flags=flags))
        rates.append(rate)
    return frames, seqs, rates


def decimated(frames: list[dict], rate_hz: float) -> list[dict]:
    """The daemon's decimation (``Connection.keep_angles``): the first frame of each 1/rate_hz of device time."""
    kept, last = [], None
    for frame in frames:
        bucket = math.floor(frame["t_s"] * rate_hz)
        if bucket != last:
            kept.append(frame)
            last = bucket
    return kept


def test_watch_after_a_replug_shows_the_one_second_mean_while_the_samples_are_flagged_gap():
    """The review's finding 13: for the minutes after a replug every sample is flagged ``gap`` (the estimate
    settling), and watch showed one sample's rate (``8.0 deg/h (one sample)``, 1 deg/h steps) where the web view
    kept the 1-s mean.  The mean over the last second of device time is every frame's rate in it, the frames
    the decimation dropped included."""
    frames, seqs, rates = frames_after_a_replug()
    kept = decimated(frames, 10.0)
    daemon = FakeDaemon([ndjson(*kept)], then="wait")
    status, text = watch(daemon, count=len(kept), rate_hz=10)
    assert status == 0
    last = kept[-1]
    first = max((k for k in kept if k["t_s"] <= last["t_s"] - 1.0), key=lambda k: k["t_s"])  # the window's start
    window = [r for s, r in zip(seqs, rates) if first["seq"] < s <= last["seq"]]
    assert len(window) == 100
    mean = sum(window) / len(window)
    assert f"rate {mean:.2f} deg/h (mean over {last['t_s'] - first['t_s']:.1f} s)" in text.splitlines()[-1]
