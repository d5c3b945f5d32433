"""Configuration: safe YAML, validation, and the scale-factor rule it feeds to the sample stream."""

from __future__ import annotations

from pathlib import Path

import pytest

from fog_driver.daemon.config import DriverConfig, load_config
from fog_driver.errors import InputFileError
from fog_driver.protocol import IdentityFrame, SampleFrame

CONFIGS = Path(__file__).resolve().parents[2] / "configs"


def test_shipped_default_config_loads():
    cfg = load_config(CONFIGS / "default.yaml")
    assert cfg == DriverConfig()
    assert cfg.model_path.is_file()  # the shipped default model


def test_config_scale_rule_reaches_the_stream(tmp_path):
    frame = SampleFrame(0, 1, 0, 100, 0, 0, 0, 0)
    ident = IdentityFrame(0, "S", 1, 100, 0.5)
    path = tmp_path / "c.yaml"
    path.write_text("scale_arcsec_per_count: 0.25\n")
    stream = load_config(path).sample_stream()
    assert stream.step(frame).dtheta_arcsec == 25.0  # before IDENTITY: the configured default
    stream.step(ident)
    assert stream.step(frame._replace(seq=2)).dtheta_arcsec == 50.0  # then the instrument's
    path.write_text("scale_override_arcsec_per_count: 0.125\n")
    stream = load_config(path).sample_stream()
    stream.step(ident)
    assert stream.step(frame).dtheta_arcsec == 12.5  # an explicit override wins


@pytest.mark.parametrize(
    "text, needle",
    [
        ("baud: fast\n", "baud: expected an integer"),
        ("baud: 3\n", "baud must be an integer baud rate"),
        ("port: 5\n", "port: expected a string"),
        ("listen: 'localhost:http'\n", "is not a number"),
        ("token: short\n", "at least 8 characters"),
        ("scale_arcsec_per_count: -1\n", "positive number"),
        ("scale_override_arcsec_per_count: .nan\n", "expected a finite number"),
        ("sclae_arcsec_per_count: 0.1\n", "unknown key 'sclae_arcsec_per_count'"),
        ("capture_keep_days: 0\n", "capture_keep_days must be a positive number"),
        ("capture_max_gb: -5\n", "capture_max_gb must be a positive number"),
        ("open_stream: yes please\n", "open_stream: expected true or false"),
        ("http_hosts: [fog-bench1.lab, 'evil example']\n", "http_hosts: 'evil example' is not a host name"),
        ("http_hosts: fog-bench1.lab\n", "http_hosts: expected a list"),
        ("http_trusted_proxies: [10.0.0.0/8, proxy.lab]\n", "http_trusted_proxies: 'proxy.lab' is not an IP"),
        ("- a list\n", "expected a YAML mapping"),
        ("port: [unclosed\n", "not valid YAML"),
        ("port: !!python/object/apply:os.system ['true']\n", "not valid YAML"),
    ],
)
def test_bad_config_is_a_one_line_error(tmp_path, text, needle):
    path = tmp_path / "c.yaml"
    path.write_text(text)
    with pytest.raises(InputFileError, match=needle.replace("[", r"\[")) as info:
        load_config(path)
    assert "\n" not in str(info.value)


def test_missing_config(tmp_path):
    with pytest.raises(InputFileError, match="no such config file"):
        load_config(tmp_path / "nope.yaml")


def test_a_bad_value_names_the_file_then_the_key(tmp_path):
    """``badval.yaml.baud: expected an integer`` ran the file name and the key together."""
    from fog_driver.sim.instrument import load_instrument_config

    path = tmp_path / "badval.yaml"
    path.write_text("baud: fast\n")
    with pytest.raises(InputFileError) as info:
        load_config(path)
    assert str(info.value) == f"{path}: baud: expected an integer, got 'fast'"
    path.write_text("thermal:\n  tau_top_s: fast\n")
    with pytest.raises(InputFileError) as info:
        load_instrument_config(path)
    assert str(info.value).startswith(f"{path}: thermal.tau_top_s: expected")


@pytest.mark.parametrize(
    "text, message",
    [
        ("baud: true\n", "baud: expected an integer, got True"),
        ("baud: 9600.0\n", "baud: expected an integer, got 9600.0"),
        ("force_model: 1\n", "force_model: expected true or false, got 1"),
        ("scale_arcsec_per_count: .inf\n", "scale_arcsec_per_count: expected a finite number, got inf"),
        ("1: 2\n", "unknown key 1 (known: "),
        ("device: [1]\n", "device: expected a mapping"),
        ("device: null\n", "device: expected a mapping"),
        ("device: {xyz: 1}\n", "device: unknown key 'xyz' (known: rate_hz, rot_format, rot_units, serial, setup, "),
        ("device: {rate_hz: 1.5}\n", "device.rate_hz: expected an integer, got 1.5"),
        ("device: {setup: abc}\n", "device.setup: expected a list of strings, got 'abc'"),
        ("device: {setup: ['=DR,1', 2]}\n", "device.setup: expected a list of strings, got ['=DR,1', 2]"),
        ("device: {setup_reply_timeout_s: 99}\n", "device: setup_reply_timeout_s must be in (0, 30] s"),
        ("format: kvh-a\n", "device.rate_hz: kvh-a frames do not say the device's output rate: give it"),
        ("port_silence_s: 0\n", "port_silence_s must be a number of seconds > 0 (or null: never), got 0.0"),
        ("port_silence_s: .nan\n", "port_silence_s: expected a finite number, got nan"),
        (
            "port_silence_s: 1.5\nformat: kvh-a\ndevice: {rate_hz: 1}\n",
            "port_silence_s 1.5 s is shorter than two frame periods at device.rate_hz 1 (2 s)",
        ),
    ],
)
def test_each_problem_names_the_file_then_the_key_path(tmp_path, text, message):
    """The schema (msgspec) finds the problem; the message is the project's, naming the key's path."""
    path = tmp_path / "c.yaml"
    path.write_text(text)
    with pytest.raises(InputFileError) as info:
        load_config(path)
    assert str(info.value).startswith(f"{path}: {message}")
    assert "\n" not in str(info.value)


def test_valid_values_are_held_as_before(tmp_path):
    """Integers given for numbers become floats, lists become tuples, null unsets an optional key, and a key
    the file leaves out keeps its default."""
    path = tmp_path / "c.yaml"
    path.write_text(
        "scale_arcsec_per_count: 1\ncapture_keep_days: null\nformat: kvh-a\n"
        "device: {rate_hz: 1000, setup: ['=DR,1000']}\n"
    )
    cfg = load_config(path)
    assert cfg.scale_arcsec_per_count == 1.0 and type(cfg.scale_arcsec_per_count) is float
    assert cfg.capture_keep_days is None and cfg.baud == DriverConfig().baud
    assert cfg.device.setup == ("=DR,1000",) and cfg.device.rate_hz == 1000
    assert cfg.device.setup_reply_timeout_s == 1.0
    path.write_text("port_silence_s: 2\n")
    assert load_config(path).port_silence_s == 2.0
    path.write_text("port_silence_s: null\n")  # never
    assert load_config(path).port_silence_s is None


def test_the_instrument_and_fit_configs_share_the_schema_checks(tmp_path):
    from fog_driver.compensation.features import FeatureParams
    from fog_driver.compensation.fitting.fit import FitConfig
    from fog_driver.files.typed_mapping import dataclass_from_mapping
    from fog_driver.sim.instrument import InstrumentConfig

    with pytest.raises(InputFileError) as info:
        dataclass_from_mapping(InstrumentConfig, {"thermal": {"coil_coupling": [1, True]}}, "i.yaml")
    assert str(info.value) == "i.yaml: thermal.coil_coupling: expected a list of numbers, got [1, True]"
    with pytest.raises(InputFileError) as info:
        dataclass_from_mapping(FitConfig, {"features": {"rate_tau_fast_s": 100}}, "fit.yaml")
    assert str(info.value) == "fit.yaml: features: need 0 < rate_tau_fast_s < rate_tau_slow_s"
    fit = dataclass_from_mapping(FitConfig, {"features": {"hold_s": 5}, "poly_alpha": None}, "fit.yaml")
    assert fit == FitConfig(features=FeatureParams(hold_s=5.0), poly_alpha=None)


def _config(path: Path):
    return load_config(path)


def _fit_config(path: Path):
    import yaml

    from fog_driver.compensation.fitting.data import FitConfig
    from fog_driver.files.typed_mapping import dataclass_from_mapping

    return dataclass_from_mapping(FitConfig, yaml.safe_load(path.read_text()), str(path))


def _instrument(path: Path):
    from fog_driver.sim.instrument import load_instrument_config

    return load_instrument_config(path)


def _profile(path: Path):
    from fog_driver.lab.profiles import load_profile

    return load_profile(str(path))


@pytest.mark.parametrize(
    "read, text, message",
    [
        (_config, "lisen: 127.0.0.1:2948\n", "unknown key 'lisen' (did you mean 'listen'?)"),
        (_config, "Listen: 127.0.0.1:2948\n", "unknown key 'Listen' (did you mean 'listen'?)"),
        (_config, "device: {rate: 100}\n", "device: unknown key 'rate' (did you mean 'rate_hz'?)"),
        (_fit_config, "warmup: 30\n", "unknown key 'warmup' (did you mean 'warmup_s'?)"),
        (_fit_config, "features: {hold: 30}\n", "features: unknown key 'hold' (did you mean 'hold_s'?)"),
        (
            _instrument,
            "gyro: {arw_deg_per_sqrt: 1}\n",
            "gyro: unknown key 'arw_deg_per_sqrt' (did you mean 'arw_deg_per_sqrt_h'?)",
        ),
        (
            _profile,
            "stat_c: 20\nsegments:\n  - hold: {duration_min: 3}\n",
            "unknown key 'stat_c' (did you mean 'start_c'?)",
        ),
        (
            _profile,
            "start_c: 20\nsegments:\n  - hold: {duraton_min: 3}\n",
            "segments[0] (hold): unknown key 'duraton_min' (did you mean 'duration_min'?)",
        ),
    ],
)
def test_a_typo_in_a_key_of_a_yaml_file_asks_did_you_mean(tmp_path, read, text, message):
    """The review's finding 19: an unknown config key got the list of every known key and no "did you mean";
    now the close one is named, in every YAML file a user writes (config, fit config, instrument, profile)."""
    path = tmp_path / "f.yaml"
    path.write_text(text)
    with pytest.raises(InputFileError) as info:
        read(path)
    assert str(info.value) == f"{path}: {message}"


def test_run_with_a_config_key_misspelt_says_did_you_mean_and_exits_78(tmp_path):
    import subprocess
    import sys

    (tmp_path / "fog.yaml").write_text("lisen: 127.0.0.1:0\n")
    proc = subprocess.run(
        [sys.executable, "-m", "fog_driver", "run", "--config", "fog.yaml", "--simulate"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        stdin=subprocess.DEVNULL,
        timeout=120,
    )
    assert proc.returncode == 78
    assert proc.stderr == "fog-driver: error: fog.yaml: unknown key 'lisen' (did you mean 'listen'?)\n"
