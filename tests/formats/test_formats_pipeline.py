"""Other instruments' formats through the whole pipeline: sample stream, fit, compensate, evaluate, daemon.

The bytes come from the simulator speaking each format (``Simulator(wire_format=...)``), so every value can be
checked against the simulator's truth: its per-frame angle increments and its thermometers.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from fog_driver.cli import main
from fog_driver.compensation.binding import ModelMismatchError
from fog_driver.compensation.fitting.data import FitConfig
from fog_driver.compensation.pipeline import Compensator
from fog_driver.daemon.config import DEFAULT_MODEL, DeviceConfig, DriverConfig, parse_config
from fog_driver.daemon.service import ConfigError, Service
from fog_driver.errors import InputFileError
from fog_driver.lab.profiles import load_profile
from fog_driver.modelfiles import load_model, save_model
from fog_driver.offline.compensate import compensate_capture
from fog_driver.offline.fit import fit_model_file
from fog_driver.samples.sources import (
    DTHETA_GRID_ARCSEC,
    AutoSampleSource,
    CaptureReader,
    SampleSource,
    WireSettings,
    wire_settings_for,
)
from fog_driver.samples.stream import Sample, SampleBlock
from fog_driver.sim.capture import simulate_to_file
from fog_driver.sim.faults import parse_fault_spec
from fog_driver.sim.instrument import Simulator

OTHER_FORMATS = ("kvh-a", "kvh-b", "kvh-c", "ixblue-stdbin")
SHORT_FIT = FitConfig(warmup_s=30.0)


def wire_of(sim: Simulator) -> WireSettings:
    """What the simulator's sidecar records, as the reader takes it."""
    from fog_driver.sim.capture import _wire_format

    doc = _wire_format(sim)
    return WireSettings.from_sidecar(doc.get("wire_format"), doc.get("wire_settings"))


def samples_of(items: list) -> SampleBlock:
    return SampleBlock.from_samples([s for s in items if isinstance(s, Sample)])


@pytest.fixture(scope="module")
def captures(tmp_path_factory) -> dict[str, Path]:
    """A 20-minute chamber ramp (short-test) at 10 Hz in every format, with its sidecar and truth file."""
    out = {}
    root = tmp_path_factory.mktemp("formats")
    for fmt in ("fog-v1", *OTHER_FORMATS):
        sim = Simulator(load_profile("short-test"), rate_hz=10, seed=4, wire_format=fmt)
        out[fmt] = simulate_to_file(sim, root / f"{fmt}.bin").capture
    return out


@pytest.mark.parametrize("fmt", OTHER_FORMATS)
def test_samples_carry_the_simulated_increments_and_thermometers(fmt):
    sim = Simulator(load_profile("short-test"), rate_hz=50, seed=1, wire_format=fmt)
    block, data = sim.stream(3000)
    got = samples_of(SampleSource(wire_of(sim)).feed(data))
    assert len(got) == 3000 and np.all(got.missing_before == 0)
    truth = sum(block.components_arcsec.values())  # what the frame's angle increment is, before the wire
    # float32 on the wire (KVH: rad; STDBIN: deg/s), then the 2^-24 arcsec grid
    assert np.allclose(got.dtheta_arcsec, truth, rtol=2e-7, atol=2 * DTHETA_GRID_ARCSEC)
    assert not np.array_equal(got.dtheta_arcsec, np.round(truth, 3))  # (the comparison above is not vacuous)
    assert np.all(np.diff(got.seq) == 1)
    assert np.allclose(np.diff(got.t_s), 1 / 50, atol=1e-6)
    housing_c = block.t_raw[:, 2] / 256.0
    if fmt.startswith("kvh"):
        # one channel, the housing thermometer in 0.01 degC (Format C: every fourth frame, held between)
        reported = np.isnan(got.t_bottom_c) & np.isnan(got.t_housing_c)
        assert reported.all()
        every = 4 if fmt == "kvh-c" else 1
        assert np.allclose(got.t_top_c[::every], housing_c[::every], atol=0.005 + 1e-9)
    else:
        for column, k in ((got.t_top_c, 0), (got.t_bottom_c, 1), (got.t_housing_c, 2)):
            assert np.allclose(column, block.t_raw[:, k] / 256.0, atol=1e-4)


@pytest.mark.determinism
@pytest.mark.parametrize("fmt", OTHER_FORMATS)
def test_any_split_of_the_bytes_gives_bit_identical_samples(fmt, captures, tmp_path):
    path = captures[fmt]
    wire = wire_settings_for(path)
    assert wire.format == fmt
    whole = SampleBlock.concatenate([p.samples for p in CaptureReader(path, wire).parts()])
    small = SampleBlock.concatenate([p.samples for p in CaptureReader(path, wire).parts(block_bytes=4097)])
    for name in SampleBlock.__dataclass_fields__:
        np.testing.assert_array_equal(getattr(small, name), getattr(whole, name))
    data = path.read_bytes()[:5000]  # byte by byte, and cut at every position of the first frames
    one = SampleSource(wire)
    by_byte = samples_of([s for i in range(len(data)) for s in one.feed(data[i : i + 1])])
    reference = samples_of(SampleSource(wire).feed(data))
    assert len(reference) > 70
    for cut in range(0, 150):  # more than two frames of every format
        two = SampleSource(wire)
        split = samples_of(two.feed(data[:cut]) + two.feed(data[cut:]))
        assert repr(split) == repr(reference)
    assert repr(by_byte) == repr(reference)


@pytest.mark.parametrize("fmt", ["kvh-a", "ixblue-stdbin"])
def test_auto_detection_on_a_live_stream_gives_the_configured_formats_samples(fmt, captures):
    data = captures[fmt].read_bytes()[:30000]
    wire = wire_settings_for(captures[fmt])
    auto = AutoSampleSource(lambda name: wire if name == fmt else pytest.fail(f"sniffed {name}"))
    assert auto.wire is None
    items = [s for i in range(0, len(data), 7) for s in auto.feed(data[i : i + 7])]
    assert auto.wire == wire
    assert repr(samples_of(items)) == repr(samples_of(SampleSource(wire).feed(data)))
    assert auto.counters.bytes_in == len(data)


def test_a_format_the_bytes_contradict_or_a_capture_without_settings_is_a_clear_error(captures, tmp_path):
    with pytest.raises(InputFileError, match=r"--format kvh-a, but the sniffer saw fog-v1 \("):
        wire_settings_for(captures["fog-v1"], "kvh-a")
    bare = tmp_path / "bare.bin"  # a KVH capture from another tool: no sidecar, so no rate
    bare.write_bytes(captures["kvh-a"].read_bytes()[:50000])
    with pytest.raises(InputFileError, match=r"needs the device's settings .* write bare\.bin\.yaml"):
        wire_settings_for(bare)
    (tmp_path / "bare.bin.yaml").write_text("wire_format: kvh-a\nwire_settings: {rate_hz: 10, temp_units: c_100}\n")
    assert wire_settings_for(bare) == WireSettings("kvh-a", rate_hz=10, temp_units="c_100")
    (tmp_path / "bare.bin.yaml").write_text("wire_format: kvh-a\nwire_settings: {rate_hz: 10, units: deg}\n")
    with pytest.raises(InputFileError, match=r"bare\.bin\.yaml: wire_settings: unknown key 'units'"):
        wire_settings_for(bare)


@pytest.fixture(scope="module")
def kvh_model(captures, tmp_path_factory) -> Path:
    model_file, _ = fit_model_file([captures["kvh-a"]], kind="polynomial", config=SHORT_FIT, accept_weak=True)
    return save_model(tmp_path_factory.mktemp("model") / "kvh.yaml", model_file)


@pytest.fixture(scope="module")
def stdbin_model(captures, tmp_path_factory) -> Path:
    model_file, _ = fit_model_file([captures["ixblue-stdbin"]], kind="polynomial", config=SHORT_FIT, accept_weak=True)
    return save_model(tmp_path_factory.mktemp("model") / "stdbin.yaml", model_file)


def test_a_model_records_its_channels_and_refuses_other_formats(kvh_model, captures):
    model = load_model(kvh_model)
    assert model.temperature_channels == ("sensor",)
    assert model.domain.names == ("t_sensor_c", "rate_sensor_c_per_min") and len(model.normalizer.mean) == 2
    with pytest.raises(
        ModelMismatchError,
        match=r"fitted on the temperature channels sensor; .*fog-v1 frames carry "
        r"top, bottom, housing: it cannot be applied",
    ):
        next(compensate_capture(captures["fog-v1"], model, force_model=True))
    with pytest.raises(
        ModelMismatchError, match="top, bottom, housing; .*ixblue-stdbin frames carry fog, accelerometer, board"
    ):
        next(compensate_capture(captures["ixblue-stdbin"], load_model(DEFAULT_MODEL)))
    with pytest.raises(InputFileError, match="one model is fitted on one instrument's channels"):
        fit_model_file([captures["kvh-a"], captures["fog-v1"]], kind="polynomial", config=SHORT_FIT, accept_weak=True)
    # the same channels in another KVH format: accepted
    assert len(next(compensate_capture(captures["kvh-c"], model))[1])


@pytest.mark.determinism
def test_a_one_channel_pipeline_steps_as_it_runs(kvh_model, captures):
    wire = wire_settings_for(captures["kvh-a"])
    samples = SampleBlock.concatenate([p.samples for p in CaptureReader(captures["kvh-a"], wire).parts()])
    model = load_model(kvh_model)
    comp = Compensator(model, 0.1)
    stepped = [comp.step(samples.sample(i)) for i in range(len(samples))]
    ran = Compensator(model, 0.1)
    cols = [ran.run(samples.take(slice(a, a + 777))) for a in range(0, len(samples), 777)]
    drift = np.concatenate([c.drift_dph for c in cols])
    angle = np.concatenate([c.angle_comp_arcsec for c in cols])
    flags = np.concatenate([c.flags for c in cols])
    assert [repr(s.drift_dph) for s in stepped] == [repr(v) for v in drift.tolist()]  # NaN: no estimate yet
    assert [s.angle_comp_arcsec for s in stepped] == angle.tolist()
    assert [s.flags for s in stepped] == flags.tolist()
    assert np.count_nonzero(np.isfinite(drift) & (drift != 0)) > len(drift) // 2  # the model estimated something
    assert not np.any(flags & 2)  # the two absent channels are no thermometer fault


@pytest.mark.determinism
@pytest.mark.parametrize("fmt", ["kvh-a", "ixblue-stdbin"])
@pytest.mark.parametrize("chunk", [1, 997])
def test_the_daemon_publishes_what_offline_compensation_gives(fmt, chunk, captures, kvh_model, stdbin_model):
    path = captures[fmt]
    wire = wire_settings_for(path)
    model = kvh_model if fmt.startswith("kvh") else stdbin_model
    config = DriverConfig(
        format=fmt,
        model=str(model),
        force_model=True,
        device=DeviceConfig(
            rate_hz=wire.rate_hz, rot_format=wire.rot_format, rot_units=wire.rot_units, temp_units=wire.temp_units
        ),
    )
    service = Service(config, port="unused")
    data = path.read_bytes()
    if chunk == 1:
        data = data[:60000]
    published = []
    for i in range(0, len(data), chunk):
        published += service.process(data[i : i + chunk])
    part = Path(str(path) + (".part.bin" if chunk == 1 else ".whole.bin"))
    part.write_bytes(data)
    Path(str(part) + ".yaml").write_text(
        yaml.safe_dump({"wire_format": fmt, "wire_settings": wire.sidecar_fields()["wire_settings"]})
    )
    parts = [cols for _, cols in compensate_capture(part, load_model(model), force_model=True)]
    offline = [a for cols in parts for a in cols.angle_comp_arcsec]
    assert [o["angle_arcsec"] for o in published] == offline and len(offline) > 500
    sigmas = [float(v) if math.isfinite(v) else None for cols in parts for v in cols.drift_sigma_dph]
    assert [o.get("drift_sigma_dph") for o in published] == sigmas  # omitted where NaN
    temps = published[-1]["temps_c"]
    assert set(temps) == ({"sensor"} if fmt.startswith("kvh") else {"fog", "accelerometer", "board"})
    status = service.status_object()
    assert status["frames"] == len(offline) and status["crc_errors"] == 0
    assert service.device_object()["format"] == fmt


def test_the_daemon_refuses_a_model_of_other_channels_and_bad_device_settings(kvh_model):
    with pytest.raises(
        ConfigError,
        match=r"the model .*default\.yaml was fitted on the temperature channels top, "
        r"bottom, housing; the instrument's kvh-a frames carry sensor",
    ):
        Service(DriverConfig(format="kvh-a", device=DeviceConfig(rate_hz=1000)), port="unused")
    with pytest.raises(InputFileError, match=r"x\.yaml: device\.rate_hz: kvh-b frames do not say"):
        parse_config({"format": "kvh-b"}, "x.yaml")
    with pytest.raises(InputFileError, match=r"x\.yaml: format: unknown frame format 'kvh'"):
        parse_config({"format": "kvh"}, "x.yaml")
    with pytest.raises(InputFileError, match=r"x\.yaml: device\.temp_units: must be one of c, c_100"):
        parse_config({"format": "kvh-a", "device": {"rate_hz": 100, "temp_units": "f"}}, "x.yaml")


def test_fit_compensate_and_evaluate_a_kvh_chamber_run_from_the_command_line(tmp_path, capsys):
    """The paper's 440-minute chamber run from a KVH DSP-1750 (1 Hz, Format A), fitted with the default kind and
    judged on another profile against the simulator's truth."""
    for name, profile, seed in (("chamber", "paper", 5), ("check", "fast-ramps", 6)):
        assert (
            main(
                [
                    "simulate",
                    "--format",
                    "kvh-a",
                    "--profile",
                    profile,
                    "--rate-hz",
                    "1",
                    "--seed",
                    str(seed),
                    "--out",
                    str(tmp_path / f"{name}.bin"),
                ]
            )
            == 0
        )
    assert main(["fit", str(tmp_path / "chamber.bin"), "--out", str(tmp_path / "m.yaml")]) == 0
    assert load_model(tmp_path / "m.yaml").temperature_channels == ("sensor",)
    assert (
        main(
            [
                "compensate",
                str(tmp_path / "check.bin"),
                "--model",
                str(tmp_path / "m.yaml"),
                "--format",
                "kvh-a",
                "--out",
                str(tmp_path / "c.csv"),
            ]
        )
        == 0
    )
    capsys.readouterr()
    assert (
        main(
            [
                "evaluate",
                str(tmp_path / "check.bin"),
                "--model",
                str(tmp_path / "m.yaml"),
                "--truth",
                str(tmp_path / "check.truth.csv"),
                "--out",
                str(tmp_path / "report"),
                "--json",
            ]
        )
        == 0
    )
    summary = yaml.safe_load(capsys.readouterr().out.strip().splitlines()[-1])
    raw, left = summary["truth"]["drift_rms_1min_dph"], summary["truth"]["residual_rms_1min_dph"]
    assert math.isfinite(raw) and left < 0.7 * raw, (raw, left)
    # the protocol v1 model cannot be applied to it, whatever --force-model says
    assert (
        main(
            [
                "compensate",
                str(tmp_path / "check.bin"),
                "--model",
                str(DEFAULT_MODEL),
                "--force-model",
                "--out",
                str(tmp_path / "d.csv"),
            ]
        )
        == 64
    )
    assert "cannot be applied" in capsys.readouterr().err


def test_the_daemon_can_publish_all_three_axes(captures, kvh_model):
    path = captures["kvh-a"]
    wire = wire_settings_for(path)
    device = DeviceConfig(rate_hz=wire.rate_hz, temp_units=wire.temp_units)
    data = path.read_bytes()[: 36 * 400]
    plain = Service(DriverConfig(format="kvh-a", model=str(kvh_model), device=device), port="unused").process(data)
    axes = Service(
        DriverConfig(format="kvh-a", model=str(kvh_model), device=device, publish_axes=True), port="unused"
    ).process(data)
    assert len(axes) == len(plain) == 400 and "axes_rate_raw_dph" not in plain[0]
    for a, p in zip(axes, plain):
        rates = a.pop("axes_rate_raw_dph")
        assert a == p  # the angle, rate and flags do not change
        assert set(rates) == {"x", "y", "z"} and rates["x"] == rates["y"] == 0.0  # the simulator turns about z
        assert rates["z"] == pytest.approx(p["rate_raw_dph"], rel=1e-6, abs=1e-4)


def test_record_writes_the_format_and_device_settings_into_the_sidecar(captures, tmp_path, capsys):
    config = tmp_path / "kvh.yaml"
    config.write_text("format: kvh-a\ndevice: {rate_hz: 10, temp_units: c_100}\n")
    out = tmp_path / "rec.bin"
    assert (
        main(
            [
                "record",
                f"replay://{captures['kvh-a']}?unplug=1",
                "--no-reconnect",
                "--config",
                str(config),
                "--out",
                str(out),
            ]
        )
        == 0
    )
    assert "sample frames, 0 CRC errors" in capsys.readouterr().out
    assert out.read_bytes() == captures["kvh-a"].read_bytes()
    doc = yaml.safe_load((tmp_path / "rec.bin.yaml").read_text())
    assert doc["wire_format"] == "kvh-a" and doc["wire_settings"]["temp_units"] == "c_100"
    wire = wire_settings_for(out)
    assert wire == wire_settings_for(captures["kvh-a"])
    n = sum(len(p.samples) for p in CaptureReader(out, wire).parts())
    assert doc["decoded_while_recording"]["sample_frames"] == n > 10000
    # a format that needs the device's settings, without them: one line, exit 64, nothing recorded
    assert (
        main(
            ["record", f"replay://{captures['kvh-a']}?unplug=1", "--format", "kvh-b", "--out", str(tmp_path / "no.bin")]
        )
        == 64
    )
    assert "kvh-b frames do not say the device's output rate" in capsys.readouterr().err
    assert not (tmp_path / "no.bin").exists()


def test_a_port_configured_for_the_wrong_format_says_what_it_sees(captures, kvh_model):
    wire = wire_settings_for(captures["kvh-a"])
    config = DriverConfig(format="kvh-a", model=str(kvh_model), device=DeviceConfig(rate_hz=wire.rate_hz))
    service = Service(config, port="unused")
    data = captures["fog-v1"].read_bytes()[:100_000]  # the port sends protocol v1
    assert [o for i in range(0, len(data), 4096) for o in service.process(data[i : i + 4096])] == []
    problem = service.status_object()["format_problem"]
    assert problem.startswith("no kvh-a sample frame in the first 65,536 bytes; the sniffer sees fog-v1 (")
    right = Service(config, port="unused")
    right.process(captures["kvh-a"].read_bytes()[:100_000])
    assert "format_problem" not in right.status_object()


def test_format_auto_in_the_daemon_finds_the_format_and_publishes_as_configured_for_it(captures, kvh_model):
    wire = wire_settings_for(captures["kvh-a"])
    device = DeviceConfig(rate_hz=wire.rate_hz, temp_units=wire.temp_units)
    data = captures["kvh-a"].read_bytes()[: 36 * 3000]
    auto = Service(DriverConfig(format="auto", model=str(kvh_model), device=device), port="unused")
    assert auto.device_object().get("format") is None  # not known before the first bytes
    got = [o for i in range(0, len(data), 500) for o in auto.process(data[i : i + 500])]
    fixed = Service(DriverConfig(format="kvh-a", model=str(kvh_model), device=device), port="unused").process(data)
    assert got == fixed and len(got) == 3000
    assert auto.device_object()["format"] == "kvh-a"
    # a model of other channels than the format found: the acquisition stops (exit 78 in the daemon)
    wrong = Service(DriverConfig(format="auto", device=device), port="unused")
    with pytest.raises(ModelMismatchError, match="frames carry sensor"):
        wrong.process(data)


def test_a_float_word_that_passed_its_checksum_as_nan_never_poisons_the_angle(captures, kvh_model):
    from fog_driver.formats.kvh import encode_kvh_frame

    wire = wire_settings_for(captures["kvh-a"])
    data = bytearray(captures["kvh-a"].read_bytes()[: 36 * 300])
    bad = [
        encode_kvh_frame("a", (0.0, 0.0, value), (0.0, 0.0, 1.0), seq=(100 + k) % 128, temp=2500)
        for k, value in enumerate((math.nan, math.inf, -1e30))
    ]
    for k, frame in enumerate(bad):  # CRC-valid frames in place of three of the capture's
        data[36 * (100 + k) : 36 * (101 + k)] = frame
    service = Service(
        DriverConfig(
            format="kvh-a", model=str(kvh_model), device=DeviceConfig(rate_hz=wire.rate_hz, temp_units=wire.temp_units)
        ),
        port="unused",
    )
    published = service.process(bytes(data))
    assert len(published) == 300
    assert all(math.isfinite(o["angle_arcsec"]) and math.isfinite(o["rate_raw_dph"]) for o in published)
    assert [o["rate_raw_dph"] for o in published[100:103]] == [0.0, 0.0, 0.0]
    assert service.status_object()["increments_rejected"] == 3
    samples = samples_of(SampleSource(wire).feed(bytes(data)))
    assert list(samples.status[100:103] & 2) == [2, 2, 2]  # flagged as protocol v1's loop-unlocked bit


def test_sidecar_settings_of_the_wrong_kind_are_one_line_errors(captures, tmp_path):
    bare = tmp_path / "k.bin"
    bare.write_bytes(captures["kvh-a"].read_bytes()[:5000])
    for text, expected in (
        ("wire_format: kvh-z\n", r"wire_format: unknown frame format 'kvh-z'"),
        ("wire_format: kvh-a\nwire_settings: {rate_hz: true}\n", r"rate_hz: must be an integer"),
        ("wire_format: kvh-a\nwire_settings: [1, 2]\n", r"wire_settings: expected a mapping"),
        ("wire_format: kvh-a\nwire_settings: {rate_hz: 10, axis: w}\n", r"axis: must be one of"),
        ("wire_format: kvh-a\nwire_settings: {rate_hz: 10, serial: 7}\n", r"serial: at most 64"),
    ):
        (tmp_path / "k.bin.yaml").write_text(text)
        with pytest.raises(InputFileError, match=expected):
            wire_settings_for(bare)
        assert main(["compensate", str(bare), "--model", str(DEFAULT_MODEL), "--out", str(tmp_path / "o.csv")]) == 65


@pytest.mark.determinism
@pytest.mark.parametrize("fmt", ["kvh-a", "kvh-b", "kvh-c"])
def test_the_kvh_batch_path_gives_the_streaming_samples_bit_for_bit(fmt, tmp_path):
    """Files are read by the numpy batch decoder, the daemon by the streaming one: the same samples, with
    drops, flips, garbage with false headers and link gaps, for any block size."""
    sim = Simulator(
        load_profile("short-test"),
        rate_hz=50,
        seed=3,
        wire_format=fmt,
        faults=parse_fault_spec("drop=0.01,flip=2e-5,garbage=0.5,disconnect=5:2"),
    )
    path = simulate_to_file(sim, tmp_path / "f.bin", duration_s=120).capture
    wire = wire_settings_for(path)
    data = path.read_bytes()
    streamed = SampleSource(wire)
    reference = samples_of(streamed.feed(data) + streamed.close())
    assert np.count_nonzero(reference.missing_before) > 10 and len(reference) > 5000
    for block_bytes in (1 << 24, 4096, 1001, 97):
        reader = CaptureReader(path, wire)
        parts = list(reader.parts(block_bytes=block_bytes))
        got = SampleBlock.concatenate([p.samples for p in parts])
        for name in SampleBlock.__dataclass_fields__:
            np.testing.assert_array_equal(getattr(got, name), getattr(reference, name), err_msg=f"{name} {block_bytes}")
        assert [i for p in parts for i in p.identities] == [streamed.identity]
        assert parts[-1].bytes_in == len(data)


def test_bytes_read_during_a_device_setup_are_left_out_offline_at_any_block_size():
    from fog_driver.samples.sources import _without

    data = bytes(range(256)) * 40
    ranges = [(0, 3), (100, 250), (251, 252), (5000, 7000), (10230, 10240)]
    expected = b"".join(data[b:a] for (_, b), (a, _) in zip([(0, 0), *ranges], [*ranges, (len(data), 0)]))
    for size in (1, 7, 100, 4096, len(data)):
        blocks = [(data[i : i + size], i + size >= len(data)) for i in range(0, len(data), size)]
        assert b"".join(b for b, _ in _without(iter(blocks), ranges)) == expected
        assert [f for _, f in _without(iter(blocks), ranges)] == [f for _, f in blocks]


def test_format_auto_finding_a_format_without_its_device_settings_is_a_config_error(captures):
    service = Service(DriverConfig(format="auto"), port="unused")
    with pytest.raises(
        ConfigError,
        match=r"format auto: device\.rate_hz: kvh-a frames do not say the device's "
        r"output rate",
    ):
        service.process(captures["kvh-a"].read_bytes()[:10000])
