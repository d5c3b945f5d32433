"""A model file is checked whole before it is used: every number finite and within ``MAX_MODEL_NUMBER``, at
most ``MAX_CANDIDATES`` candidates and ``MAX_NEURONS`` neurons, and no YAML anchor or alias.  The same one
line at start-up (exit 78), on ``?RELOAD`` (refused, the old model goes on) and offline (exit 65)."""

from __future__ import annotations

import copy
from pathlib import Path

import pytest
import yaml
from cli_run import run_cli
from model_refusals import assert_start_up_and_offline_refuse, watching

from fog_driver.compensation.model_checks import MAX_MODEL_NUMBER
from fog_driver.compensation.uncertainty import MAX_CANDIDATES
from fog_driver.daemon.config import DEFAULT_MODEL
from fog_driver.errors import InputFileError
from fog_driver.modelfiles import load_model

DATA = Path(__file__).resolve().parents[1] / "data"


def _doc() -> dict:
    return yaml.safe_load(DEFAULT_MODEL.read_text())


def _write(path: Path, doc: dict) -> Path:
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def _refused(path: Path) -> str:
    with pytest.raises(InputFileError) as info:
        load_model(path)
    message = str(info.value)
    assert "\n" not in message and message.startswith(f"{path}: ")
    return message


def _aliased_candidates(n: int) -> str:
    """The review's hostile model: ``uncertainty.candidates`` as ``n`` aliases of the first candidate."""
    doc = _doc()
    first = doc["uncertainty"]["candidates"][0]
    doc["uncertainty"]["candidates"] = [first] * n  # safe_dump writes the repeats as aliases of one anchor
    text = yaml.safe_dump(doc, sort_keys=False)
    assert "*id001" in text
    return text


def test_a_model_whose_candidates_are_ten_thousand_aliases_is_refused_before_they_are_expanded(tmp_path):
    path = tmp_path / "aliases.yaml"
    path.write_text(_aliased_candidates(10_000))
    message = _refused(path)
    assert "corrupt model: a YAML anchor (&id001)" in message and "a model file has none" in message


@pytest.mark.parametrize(
    "where, value, needle",
    [
        (("model", "weights", 3), float("nan"), "model.weights[3] is not a finite number (nan)"),
        (("model", "weights", 0), 1e308, "model.weights[0] is 1e308: beyond 1e9"),
        (("model", "intercept"), float("inf"), "model.intercept is not a finite number (inf)"),
        (("noise_1min_dph",), -1e300, "noise_1min_dph is -1e300: beyond 1e9"),
        (("model", "weights", 1), 10**400, "an integer of 401 digits"),
        (("model", "reservoir", "n_neurons"), 1_000_000, "model.reservoir.n_neurons: 1000000 neurons; a fit makes"),
    ],
    ids=["nan-weight", "1e308-weight", "inf-intercept", "huge-noise", "400-digit-weight", "a-million-neurons"],
)
def test_a_model_with_a_non_finite_or_absurd_number_is_refused_naming_the_key(tmp_path, where, value, needle):
    doc = _doc()
    node = doc
    for key in where[:-1]:
        node = node[key]
    if isinstance(node.get(where[-1]) if isinstance(node, dict) else node[where[-1]], list):
        node[where[-1]][0] = value
    else:
        node[where[-1]] = value
    text = yaml.safe_dump(doc, sort_keys=False)
    if isinstance(value, int):  # safe_dump writes a big int as digits; the loader reads it back as one
        assert str(value) in text
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    assert needle in _refused(path)


def test_the_shipped_model_and_the_golden_ones_hold_numbers_far_inside_the_bound():
    """What fits write stays under a thousandth of the bound (so the bound refuses only what no fit wrote)."""
    for path in [DEFAULT_MODEL, *sorted((DATA / "golden" / "models").glob("*.yaml"))]:
        load_model(path)
        biggest = 0.0
        stack = [v for k, v in yaml.safe_load(path.read_text()).items() if k != "provenance"]
        while stack:
            v = stack.pop()
            if isinstance(v, dict):
                stack.extend(v.values())
            elif isinstance(v, list):
                stack.extend(v)
            elif isinstance(v, (int, float)) and not isinstance(v, bool):
                biggest = max(biggest, abs(v))
        assert biggest < MAX_MODEL_NUMBER / 1000, (path, biggest)


def test_a_model_with_more_candidates_than_a_fit_writes_is_refused(tmp_path):
    doc = _doc()
    candidates = doc["uncertainty"]["candidates"]
    assert len(candidates) == MAX_CANDIDATES
    doc["uncertainty"]["candidates"] = [copy.deepcopy(c) for c in candidates + candidates[:1]]
    message = _refused(_write(tmp_path / "seven.yaml", doc))
    assert f"7 candidates; a fit writes at most {MAX_CANDIDATES}" in message


def test_run_and_compensate_with_a_nan_weight_are_one_line_78_and_65(tmp_path):
    """The review: a NaN weight ended ``run`` in exit 70 after its banner; ``compensate`` ran on it."""
    doc = _doc()
    doc["model"]["weights"][3] = float("nan")
    model = _write(tmp_path / "nan.yaml", doc)
    expected = f"fog-driver: error: {model}: corrupt model: model.weights[3] is not a finite number (nan)\n"
    assert_start_up_and_offline_refuse(model, tmp_path, expected)


def test_a_reload_of_the_alias_model_is_refused_and_the_angle_goes_on(tmp_path):
    model = tmp_path / "m.yaml"
    with watching(tmp_path, model) as (daemon, client):
        model.write_text(_aliased_candidates(10_000))
        client.send("?RELOAD;")
        assert "a YAML anchor (&id001)" in client.next("ERROR")["message"]
        before = client.next("ANGLE")["t_s"]
        assert client.next("ANGLE")["t_s"] > before  # the old model publishes on
        assert daemon.terminate() == 0


@pytest.mark.parametrize("kept", [5, 0])
def test_a_reload_of_a_model_that_differs_only_in_its_candidates_is_accepted(tmp_path, kept):
    """The review's finding 11: 5 (or 0) candidates instead of 6 was refused ("uncertainty state needs 5
    candidate states"); it is another model now, started at rest, and reloads."""
    model = tmp_path / "m.yaml"
    with watching(tmp_path, model) as (daemon, client):
        doc = _doc()
        doc["uncertainty"]["candidates"] = doc["uncertainty"]["candidates"][:kept]
        if not kept:
            doc["uncertainty"]["sigma_kind"] = "residual"
        _write(model, doc)
        assert len(load_model(model).sigma_spec.candidates) == kept
        client.send("?RELOAD;")
        answer = client.next()
        while answer["class"] not in ("RELOAD", "ERROR"):
            answer = client.next()
        assert answer["class"] == "RELOAD", answer
        assert daemon.terminate() == 0


def test_a_model_or_a_config_with_an_integer_of_5000_digits_is_one_line(tmp_path):
    """Python reads no integer of over 4,300 digits from text: that was exit 70 for every YAML file."""
    text = DEFAULT_MODEL.read_text()
    weights = "weights: ["
    assert weights in text
    model = tmp_path / "digits.yaml"
    model.write_text(text.replace(weights, weights + "1" * 5000 + ", ", 1))
    assert _refused(model) == f"{model}: model file holds an integer of over 4,300 digits"
    config = tmp_path / "fog.yaml"
    config.write_text("status_every_s: " + "1" * 5000 + "\n")
    start = run_cli("run", "--config", str(config), "--port", "replay://x.bin", cwd=tmp_path)
    assert start.returncode == 78, start.stderr
    assert start.stderr.splitlines() == [
        f"fog-driver: error: {config}: config file holds an integer of over 4,300 digits"
    ]


@pytest.mark.parametrize("weight", [MAX_MODEL_NUMBER * 10, float("nan")])
def test_a_fit_whose_model_would_not_load_writes_no_file_and_says_why(tmp_path, weight):
    """``save_model`` reads its own text back with every reader's checks: the fit never writes a model that
    the daemon would refuse at start (a weight beyond the bound, or NaN, made by degenerate data)."""
    from fog_driver.modelfiles import save_model

    model_file = load_model(DEFAULT_MODEL)
    model_file.model.weights[0] = weight
    out = tmp_path / "fitted.yaml"
    with pytest.raises(InputFileError) as info:
        save_model(out, model_file)
    message = str(info.value)
    assert message.startswith(f"{out} not written: the fitted model would not load (") and "\n" not in message
    assert "weights" in message
    assert not out.exists() and list(tmp_path.iterdir()) == []


def test_a_fitted_model_within_the_bounds_is_written_and_reads_back_the_same(tmp_path):
    from fog_driver.modelfiles import model_text, save_model

    model_file = load_model(DEFAULT_MODEL)
    out = save_model(tmp_path / "fitted.yaml", model_file)
    assert model_text(load_model(out)) == model_text(model_file)
