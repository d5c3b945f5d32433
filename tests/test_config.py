"""Configuration: safe YAML, validation, and the scale-factor rule it feeds to the sample stream."""

from __future__ import annotations

from pathlib import Path

import pytest

from fog_driver.daemon.config import DriverConfig, load_config
from fog_driver.errors import InputFileError
from fog_driver.protocol import IdentityFrame, SampleFrame

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


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
