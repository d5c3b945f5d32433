"""The pso-svr comparator: the particle swarm, the numpy prediction against scikit-learn, step == run,
the model file, fitting on a capture, the compensator (frozen and adapting), the missing optional extra."""

from __future__ import annotations

import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from importlib.util import find_spec
from pathlib import Path

import numpy as np
import pytest
import yaml

from fog_driver.compensation.fitting.data import FitConfig
from fog_driver.compensation.fitting.report import applied_prediction, minute_rms
from fog_driver.compensation.fitting.svr import (
    MISSING_SKLEARN,
    PsoSvrConfig,
    fit_pso_svr,
    minute_rows,
    pso_minimize,
    window_blocks,
)
from fog_driver.compensation.model import MODEL_KINDS
from fog_driver.compensation.models.svr import SvrModel
from fog_driver.compensation.numerics import dot
from fog_driver.compensation.pipeline import CompensatedColumns, Compensator
from fog_driver.errors import InputFileError, UsageError
from fog_driver.modelfiles import load_model, save_model
from fog_driver.offline.fit import fit_model_file, load_capture
from fog_driver.protocol import decode_file
from fog_driver.samples.stream import SampleBlock, SampleStream

#: Fitting needs the optional scikit-learn; the swarm, prediction, the model file and the error do not.
needs_sklearn = pytest.mark.skipif(find_spec("sklearn") is None, reason="scikit-learn not installed")

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT / "tests" / "data"
TEST_FIT = FitConfig(warmup_s=30.0)


# --- the particle swarm ---------------------------------------------------------------------------


def shifted_quadratic(x: np.ndarray) -> float:
    return float(np.sum((x - np.array([1.3, -0.7, 2.2])) ** 2))


def rosenbrockish(x: np.ndarray) -> float:
    return float((1.0 - x[0]) ** 2 + 10.0 * (x[1] - x[0] ** 2) ** 2)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_pso_finds_a_shifted_quadratic_minimum(seed):
    x, f = pso_minimize(shifted_quadratic, [(-5.0, 5.0)] * 3, seed=seed)  # the fit's budget: 16 x 20
    np.testing.assert_allclose(x, [1.3, -0.7, 2.2], atol=0.15)
    assert f == shifted_quadratic(x) and f < 0.02
    x, f = pso_minimize(shifted_quadratic, [(-5.0, 5.0)] * 3, iterations=60, seed=seed)
    np.testing.assert_allclose(x, [1.3, -0.7, 2.2], atol=0.01)
    assert f < 1e-4


def test_pso_finds_a_rosenbrock_like_minimum():
    x, f = pso_minimize(rosenbrockish, [(-2.0, 2.0), (-1.0, 3.0)], n_particles=30, iterations=100, seed=3)
    np.testing.assert_allclose(x, [1.0, 1.0], atol=0.05)
    assert f < 1e-3


def test_pso_is_deterministic_per_seed_and_respects_the_box():
    calls: list[np.ndarray] = []

    def f(x):
        calls.append(x)
        return rosenbrockish(x)

    a = pso_minimize(f, [(-2.0, 2.0), (-1.0, 3.0)], n_particles=8, iterations=5, seed=11)
    assert len(calls) == 8 * 6
    assert all(-2.0 <= c[0] <= 2.0 and -1.0 <= c[1] <= 3.0 for c in calls)
    b = pso_minimize(rosenbrockish, [(-2.0, 2.0), (-1.0, 3.0)], n_particles=8, iterations=5, seed=11)
    with ThreadPoolExecutor(2) as pool:
        c = pso_minimize(
            rosenbrockish, [(-2.0, 2.0), (-1.0, 3.0)], n_particles=8, iterations=5, seed=11, map_fn=pool.map
        )
    for other in (b, c):
        np.testing.assert_array_equal(a[0], other[0])
        assert a[1] == other[1]
    d = pso_minimize(rosenbrockish, [(-2.0, 2.0), (-1.0, 3.0)], n_particles=8, iterations=5, seed=12)
    assert not np.array_equal(a[0], d[0])


def test_pso_treats_non_finite_values_as_worst_and_checks_its_bounds():
    x, f = pso_minimize(lambda x: float("nan") if x[0] < 0 else float(x[0] - 0.5) ** 2, [(-1.0, 1.0)])
    assert abs(x[0] - 0.5) < 0.05 and np.isfinite(f)
    for bad in ([(1.0, 1.0)], [(0.0, float("inf"))], []):
        with pytest.raises(ValueError):
            pso_minimize(shifted_quadratic, bad)


# --- the model's arithmetic --------------------------------------------------------------------------


def random_model(seed: int = 5, n_sv: int = 150) -> SvrModel:
    rng = np.random.default_rng(seed)
    return SvrModel(rng.normal(0.0, 1.0, (n_sv, 8)), rng.normal(0.0, 0.1, n_sv), 0.03, 0.07, C=3.0, epsilon=0.01)


@needs_sklearn
def test_numpy_prediction_equals_sklearn():
    from sklearn.svm import SVR

    rng = np.random.default_rng(5)
    z = rng.normal(0.0, 1.0, (240, 8))
    y = np.sin(z[:, 0]) + 0.3 * z[:, 1] * z[:, 2] - 0.2 * z[:, 6] + 0.01 * rng.normal(size=240)
    svr = SVR(kernel="rbf", C=10.0, gamma=0.05, epsilon=0.01).fit(z, y)
    model = SvrModel.from_sklearn(svr, C=10.0, epsilon=0.01)
    assert 10 < model.n_support < 240 and model.gamma == 0.05
    test = rng.normal(0.0, 1.5, (3000, 8))
    np.testing.assert_allclose(model.run(test), svr.predict(test), rtol=1e-9, atol=1e-12)
    with pytest.raises(ValueError, match="RBF"):
        SvrModel.from_sklearn(SVR(kernel="linear").fit(z, y))


@pytest.mark.determinism
def test_step_equals_run_bit_for_bit():
    model = random_model()
    z = np.random.default_rng(6).normal(0.0, 1.5, (5000, 8))
    ran = model.run(z)  # more rows than one chunk
    stepped = np.array([model.step(row) for row in z])
    np.testing.assert_array_equal(ran, stepped)
    np.testing.assert_array_equal(np.concatenate([model.run(z[:1]), model.run(z[1:777]), model.run(z[777:])]), ran)
    # The adapting readout's frozen estimate (numerics.dot over the kernel row) is the same number.
    via_regressors = np.array([dot(model.regressors_step(row), model.weights) + model.intercept for row in z[:300]])
    np.testing.assert_array_equal(via_regressors, ran[:300])
    assert model.get_state() == {}


def test_model_validates_its_arrays():
    sv = np.zeros((3, 8))
    with pytest.raises(ValueError, match="support vectors"):
        SvrModel(np.zeros((3, 7)), np.zeros(3), 0.0, 1.0)
    with pytest.raises(ValueError, match="dual coefficients"):
        SvrModel(sv, np.zeros(2), 0.0, 1.0)
    with pytest.raises(ValueError, match="gamma"):
        SvrModel(sv, np.zeros(3), 0.0, 0.0)
    with pytest.raises(ValueError, match="finite"):
        SvrModel(sv, np.array([0.0, np.nan, 0.0]), 0.0, 1.0)


# --- fitting, the model file, compensating ------------------------------------------------------------


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    model_file, report = fit_model_file([DATA / "sim-short.bin"], kind="pso-svr", config=TEST_FIT, accept_weak=True)
    path = save_model(tmp_path_factory.mktemp("svr") / "m.yaml", model_file)
    return model_file, report, path


def test_pso_svr_is_a_model_kind():
    assert MODEL_KINDS["pso-svr"] is SvrModel


@needs_sklearn
def test_fit_reduces_the_drift_on_its_own_data(fitted):
    model_file, report, _ = fitted
    rows = {what: fit for what, fit, _ in report.rows}
    assert model_file.kind == "pso-svr" and isinstance(model_file.model, SvrModel)
    assert rows["after, pso-svr"] < 0.8 * rows["before compensation"]
    m = model_file.model
    assert 1e-2 <= m.C <= 1e3 and 1e-3 <= m.gamma <= 1e1 and 1e-4 <= m.epsilon <= 1e-1 and np.isfinite(m.cv_rms_dph)
    # A 300-s capture is too short for 30 one-minute rows: 9-s windows.
    capture = load_capture(DATA / "sim-short.bin", TEST_FIT)
    per = window_blocks([capture], 1.0)
    _, y = minute_rows([capture], model_file.normalizer, 1.0, per=per)
    assert m.average_s == per == 9 and len(y) >= 25
    # The drift the compensator applies, scored as the report does (1-min means of the residual).
    residual = capture.target_dph - applied_prediction(m, capture, model_file.normalizer)
    assert minute_rms(residual, capture.static) == rows["after, pso-svr"]


@needs_sklearn
def test_fit_is_deterministic(fitted):
    model_file, _, _ = fitted
    capture = load_capture(DATA / "sim-short.bin", TEST_FIT)
    again = fit_pso_svr([capture], model_file.normalizer, TEST_FIT, PsoSvrConfig(workers=1))
    assert again.to_dict() == model_file.model.to_dict()


@needs_sklearn
def test_model_file_round_trip_predicts_identically(fitted):
    model_file, _, path = fitted
    loaded = load_model(path)
    assert loaded.kind == "pso-svr"
    assert loaded.model.to_dict() == model_file.model.to_dict()  # exact floats
    z = np.random.default_rng(1).normal(0.0, 1.0, (500, 8))
    np.testing.assert_array_equal(loaded.model.run(z), model_file.model.run(z))
    doc = yaml.safe_load(path.read_text())
    assert len(doc["model"]["support_vectors"]) == len(doc["model"]["dual_coef"]) == model_file.model.n_support


def test_a_hand_built_model_file_round_trips_exactly(tmp_path):
    from fog_driver.compensation.features import FeatureParams
    from fog_driver.compensation.model import ModelFile
    from fog_driver.compensation.readout import Standardizer

    model = random_model(9, 40)
    model_file = ModelFile("pso-svr", "FOG-X", 1.0, FeatureParams(), Standardizer(np.zeros(8), np.ones(8)), model)
    loaded = load_model(save_model(tmp_path / "m.yaml", model_file)).model
    assert loaded.to_dict() == model.to_dict()
    z = np.random.default_rng(2).normal(0.0, 1.0, (100, 8))
    np.testing.assert_array_equal(loaded.run(z), model.run(z))
    no_provenance = {k: v for k, v in model.to_dict().items() if k not in ("C", "epsilon", "cv_rms_dph", "average_s")}
    np.testing.assert_array_equal(SvrModel.from_dict(no_provenance).run(z), model.run(z))


@needs_sklearn
def test_a_corrupt_model_file_is_a_one_line_error(fitted, tmp_path):
    _, _, path = fitted
    doc = yaml.safe_load(path.read_text())
    doc["model"]["support_vectors"][0] = doc["model"]["support_vectors"][0][:7]
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(doc))
    with pytest.raises(InputFileError, match="corrupt model"):
        load_model(bad)


def slice_block(s: SampleBlock, lo: int, hi: int) -> SampleBlock:
    return SampleBlock(*(getattr(s, f)[lo:hi] for f in SampleBlock.__dataclass_fields__))


@pytest.mark.determinism
@needs_sklearn
def test_compensator_step_equals_run_and_adapting_without_reference_is_frozen(fitted):
    from fog_driver.compensation.adapt import AdaptConfig

    _, _, path = fitted
    samples = SampleStream().run(decode_file(DATA / "sim-short.bin"))
    n = len(samples)
    frozen = Compensator(load_model(path), 0.1).run(samples)
    stepper = Compensator(load_model(path), 0.1)
    assert [repr(stepper.step(samples.sample(i))) for i in range(n)] == [repr(frozen.sample(i)) for i in range(n)]
    # The daemon always builds the adapting readout: without a reference it is the frozen model exactly.
    gated_off = Compensator(load_model(path), 0.1, adapt=AdaptConfig(), reference_rate_dph=None).run(samples)
    for f in CompensatedColumns.__dataclass_fields__:
        np.testing.assert_array_equal(getattr(gated_off, f), getattr(frozen, f), err_msg=f)
    assert np.any(frozen.drift_dph != 0.0)
    # Adapting the dual coefficients runs (a short run: adapt soon).
    short = AdaptConfig(warmup_s=5.0, bias_capture_s=10.0, static_window_s=5.0)
    adapting = Compensator(load_model(path), 0.1, adapt=short, reference_rate_dph=0.0)
    out = adapting.run(samples)
    first_block = out.t_s - out.t_s[0] < 1.0 - 1e-9  # no estimate yet: NaN, flagged uncompensated
    assert np.all(np.isfinite(out.drift_dph[~first_block])) and np.all(np.isnan(out.drift_dph[first_block]))
    assert adapting.online.updates > 0


@needs_sklearn
def test_cli_fit_and_compensate(tmp_path):
    config = tmp_path / "fit.yaml"
    config.write_text("warmup_s: 30.0\n")
    model = tmp_path / "m.yaml"

    def cli(*args):
        return subprocess.run([sys.executable, "-m", "fog_driver", *args], capture_output=True, text=True, timeout=120)

    proc = cli(
        "fit",
        str(DATA / "sim-short.bin"),
        "--kind",
        "pso-svr",
        "--config",
        str(config),
        "--out",
        str(model),
        "--accept-weak-fit",
    )
    assert proc.returncode == 0, proc.stderr
    assert "after, pso-svr" in proc.stdout
    proc = cli("compensate", str(DATA / "sim-short.bin"), "--model", str(model), "--out", str(tmp_path / "o.csv"))
    assert proc.returncode == 0, proc.stderr
    assert "(pso-svr)" in proc.stdout


# --- without scikit-learn -----------------------------------------------------------------------------


def test_missing_scikit_learn_is_a_one_line_usage_error(monkeypatch, tmp_path, capsys):
    from fog_driver.cli import main

    monkeypatch.setitem(sys.modules, "sklearn.svm", None)  # ``from sklearn.svm import SVR`` -> ImportError
    with pytest.raises(UsageError) as info:
        fit_model_file([DATA / "sim-short.bin"], kind="pso-svr", config=TEST_FIT, accept_weak=True)
    assert str(info.value) == MISSING_SKLEARN
    assert MISSING_SKLEARN == (
        "fitting a pso-svr model needs scikit-learn (the 'svr' extra); in the project's "
        "virtual environment: pip install -e '.[svr]'"
    )
    config = tmp_path / "fit.yaml"
    config.write_text("warmup_s: 30.0\n")
    status = main(
        [
            "fit",
            str(DATA / "sim-short.bin"),
            "--kind",
            "pso-svr",
            "--config",
            str(config),
            "--out",
            str(tmp_path / "m.yaml"),
        ]
    )
    err = capsys.readouterr().err
    assert status == 64 and err == f"fog-driver: error: {MISSING_SKLEARN}\n"
    assert not (tmp_path / "m.yaml").exists()


@needs_sklearn
def test_a_stored_model_predicts_without_scikit_learn(fitted, monkeypatch):
    _, _, path = fitted
    expected = load_model(path).model.run(np.ones((3, 8)))
    monkeypatch.setitem(sys.modules, "sklearn", None)
    monkeypatch.setitem(sys.modules, "sklearn.svm", None)
    np.testing.assert_array_equal(load_model(path).model.run(np.ones((3, 8))), expected)
