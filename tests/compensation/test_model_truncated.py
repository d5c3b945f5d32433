"""A model file cut short (a copy interrupted, a full disk): one line naming what is missing, or that it is no
longer YAML, wherever the cut is; never a traceback, never a model read with a part of it gone.  The same
line at the daemon's start-up, in ``ctl reload`` (``?RELOAD``) and in ``compensate``."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml
from model_refusals import assert_start_up_and_offline_refuse

from fog_driver.daemon.config import DEFAULT_MODEL
from fog_driver.errors import InputFileError
from fog_driver.modelfiles import MODEL_FIRST_LINE, MODEL_LAST_LINE, load_model, save_model

DATA = Path(__file__).resolve().parents[1] / "data"
TRUNCATED = re.compile(r"model file truncated or incomplete: (?P<what>.+) missing \(it ends (?P<where>.+)\)")


def _verdict(path: Path) -> str:
    """``load_model``'s one line about ``path`` (the test fails if it reads it or raises anything else)."""
    with pytest.raises(InputFileError) as info:
        load_model(path)
    message = str(info.value)
    assert "\n" not in message and message.startswith(f"{path}: ")
    return message.removeprefix(f"{path}: ")


def _check_names_what_is_missing(message: str, text: str, full: str) -> None:
    """The line names what ``text`` (a start of the model file ``full``) lacks: the first key after the last one
    it holds whole (a key's line ``key:`` at a line's start in ``full``), skipping only the keys a model may
    not have (domain, noise_1min_dph, uncertainty); or, every key there, the end of provenance."""
    if not text.strip():
        assert message == "the model file is empty"
        return
    whole = list(yaml.load(full, Loader=yaml.CSafeLoader))
    held = [key for key in whole if f"\n{key}:" in "\n" + text]  # its line begun and its colon there
    found = TRUNCATED.fullmatch(message)
    assert found, message
    if not held:
        assert found["what"] == "'format'" and found["where"] == "before its first key"
        return
    last = held[-1]
    assert found["where"] == f"in or after {last!r}"
    if len(held) == len(whole):
        assert found["what"] == f"the end of {last!r} and the line {MODEL_LAST_LINE!r}"
        return
    key = found["what"].strip("'")
    between = whole[whole.index(last) + 1 : whole.index(key)]
    assert key not in held and set(between) <= {"domain", "noise_1min_dph", "uncertainty"}, (key, between)


@pytest.fixture(scope="module")
def written(tmp_path_factory) -> Path:
    """A real model file as ``fit`` writes it (``save_model``): the shipped default model's."""
    return save_model(tmp_path_factory.mktemp("model") / "model.yaml", load_model(DEFAULT_MODEL))


def test_a_model_file_cut_at_any_line_or_inside_one_is_one_line_naming_what_is_missing(tmp_path, written):
    """The review's finding 18: ``ctl reload`` with a truncated model file said "corrupt model: substitution needs
    the keys t_top_c, t_bottom_c, t_housing_c"; a cut inside the provenance was read as a whole model, and a
    number cut short in its last line as another number.  Every line boundary, and every 331st byte."""
    text = written.read_text()
    assert text.startswith(MODEL_FIRST_LINE + "\n") and text.endswith("\n" + MODEL_LAST_LINE + "\n")
    lines = text.splitlines(keepends=True)
    cuts = {len("".join(lines[:n])) for n in range(len(lines))} | set(range(1, len(text), 331))
    cut = tmp_path / "cut.yaml"
    for at in sorted(cuts):
        cut.write_text(text[:at])
        _check_names_what_is_missing(_verdict(cut), text[:at], text)
    assert load_model(written).kind == "wesn"  # the whole file reads


def test_the_shipped_default_model_is_written_as_fit_writes_one(written):
    """So a cut anywhere in it is seen as the test above sees it."""
    assert DEFAULT_MODEL.read_text() == written.read_text()


def test_a_model_file_of_an_older_fog_driver_cut_short_names_provenance_missing(tmp_path, written):
    """A file written before the first and last lines existed (no first line): cut anywhere before its last key,
    provenance (the last in every version), it is truncated."""
    body = written.read_text().removeprefix(MODEL_FIRST_LINE + "\n").removesuffix(MODEL_LAST_LINE + "\n")
    old = tmp_path / "old.yaml"
    old.write_text(body)
    assert load_model(old).kind == "wesn"  # whole: read as before
    lines = body.splitlines(keepends=True)
    cut = lines.index("provenance:\n")
    old.write_text("".join(lines[:cut]))
    assert (
        _verdict(old) == "model file truncated or incomplete: 'provenance' missing (it ends in or after 'uncertainty')"
    )


def test_a_truncated_model_is_the_same_line_at_start_up_in_ctl_reload_and_in_compensate(tmp_path, written):
    from daemon_hil import Client, Daemon

    model = tmp_path / "m.yaml"
    model.write_bytes(written.read_bytes())
    text = model.read_text()
    truncated = text[: text.index("substitution:")]  # the finding's cut: inside the substitution section
    expected = f"{model}: model file truncated or incomplete: 'substitution' missing (it ends in or after 'domain')"

    daemon = Daemon(tmp_path, f"replay://{DATA / 'sim-short.bin'}?rate=100", "--model", str(model))
    try:
        client = Client(daemon.address)
        model.write_text(truncated)
        client.send("?RELOAD;")
        assert client.next("ERROR")["message"] == expected  # ctl reload prints this message
        assert daemon.terminate() == 0
    finally:
        daemon.kill()

    assert_start_up_and_offline_refuse(model, tmp_path, f"fog-driver: error: {expected}\n")
