"""Live == offline across model reloads: the daemon keeps a copy of every model it compensates with beside its
captures (``models/<sha256>.yaml``) and notes each reload in the sidecar; ``compensate`` swaps the kept model in
where the reload took effect, as the daemon did, and gives what it published bit for bit."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest

from fog_driver.cli import main
from fog_driver.compensation.fitting.data import FitConfig
from fog_driver.daemon.config import DEFAULT_MODEL, DriverConfig
from fog_driver.daemon.rawlog import CaptureSink, RotatingCapture
from fog_driver.daemon.service import Service
from fog_driver.modelfiles import load_model, save_model
from fog_driver.offline.compensate import compensate_capture
from fog_driver.offline.fit import fit_model_file
from fog_driver.offline.replay import control_events, unreplayed
from fog_driver.samples.captures import kept_model_path, read_provenance

DATA = Path(__file__).resolve().parents[1] / "data"


@pytest.fixture(scope="module")
def reloaded(tmp_path_factory):
    """A daemon capture of ``sim-faults.bin`` with the model reloaded twice (to another model, then back),
    a ?ZERO and ?ADAPT between them, the bytes cut mid-frame: (capture, ANGLE objects, the other model's path)."""
    tmp = tmp_path_factory.mktemp("reload")
    other_model, _ = fit_model_file(
        [DATA / "sim-short.bin"], kind="polynomial", config=FitConfig(warmup_s=30.0), accept_weak=True
    )
    other = save_model(tmp / "other.yaml", other_model)
    data = (DATA / "sim-faults.bin").read_bytes()
    service = Service(DriverConfig(), port="unused")
    service.capture = CaptureSink(RotatingCapture(tmp / "cap", provenance=service._provenance()))
    service.capture.keep_model(service.model_sha256, service.model_bytes)  # as start() does
    cuts = [0, 20003, 31007, 45011, len(data)]
    published: list[dict] = []
    for k, (a, b) in enumerate(zip(cuts, cuts[1:])):
        published += service.process(data[a:b])
        if k == 0:
            assert service.reload_from_file(DriverConfig(model=str(other)))["changed"] is True
            assert service.control("ADAPT", {"enable": True, "reference_dph": 0.0}, 0)["class"] == "ADAPT"
        elif k == 1:
            assert service.control("ZERO", {}, 0)["class"] == "ZERO"
        elif k == 2:
            assert service.reload_from_file(DriverConfig())["changed"] is True  # back to the first model
    assert service.reloads == 2
    service.capture.close()
    (capture,) = sorted((tmp / "cap").glob("*.bin"))
    assert capture.read_bytes() == data
    return capture, published, other


def test_the_daemon_keeps_each_model_it_used_beside_its_captures(reloaded):
    capture, _, other = reloaded
    models = [e for e in read_provenance(capture)["events"] if e["event"] == "model"]
    assert [m["sha256"] for m in models] == [
        hashlib.sha256(other.read_bytes()).hexdigest(),
        hashlib.sha256(DEFAULT_MODEL.read_bytes()).hexdigest(),
    ]
    for m, source in zip(models, (other, DEFAULT_MODEL)):
        assert kept_model_path(capture, m["sha256"]).read_bytes() == source.read_bytes()
    assert len(list(kept_model_path(capture, "x").parent.glob("*.yaml"))) == 2  # each content once
    # the sidecar names the model the file began with; a later file would name the one in use
    assert read_provenance(capture)["model"]["sha256"] == hashlib.sha256(DEFAULT_MODEL.read_bytes()).hexdigest()


def test_a_capture_with_model_reloads_compensates_offline_as_published(reloaded, capsys):
    capture, published, _ = reloaded
    events = control_events(read_provenance(capture), capture)
    assert [e.kind for e in events] == ["model", "adapt", "zero", "model"]
    assert unreplayed(read_provenance(capture), capture) == []
    cols = [c for _, c in compensate_capture(capture, load_model(DEFAULT_MODEL), events=events)]
    for key, name in (
        ("angle_arcsec", "angle_comp_arcsec"),
        ("drift_dph", "drift_dph"),
        ("angle_raw_arcsec", "angle_raw_arcsec"),
    ):
        got = np.concatenate([getattr(c, name) for c in cols])
        # an absent drift (no estimate, flagged uncompensated) is NaN offline
        assert [None if v != v else v for v in got.tolist()] == [o.get(key) for o in published], key
    # the reloads matter: without the other model the drift differs
    plain = np.concatenate([c.drift_dph for _, c in compensate_capture(capture, load_model(DEFAULT_MODEL))])
    assert np.nanmax(np.abs(plain - np.array([o.get("drift_dph", np.nan) for o in published]))) > 1e-3
    out = capture.parent / "out.csv"
    assert main(["compensate", str(capture), "--model", str(DEFAULT_MODEL), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "replayed the daemon's control events where they took effect: 1 adapt, 1 zero, 2 model" in printed
    assert "not what the daemon published" not in printed


@pytest.mark.parametrize("damage", ["missing", "tampered"])
def test_a_reload_whose_model_is_not_kept_is_named_not_replayed(reloaded, tmp_path, capsys, damage):
    """A copy deleted, or changed since (its bytes no longer of its SHA-256): the reload is not replayed and
    ``compensate`` says so on its warning line; the other events still are."""
    capture, _, other = reloaded
    copy = tmp_path / capture.name
    copy.write_bytes(capture.read_bytes())
    sidecar = capture.with_name(capture.name + ".yaml")
    (tmp_path / sidecar.name).write_bytes(sidecar.read_bytes())
    kept = tmp_path / "models"
    kept.mkdir()
    sha = hashlib.sha256(other.read_bytes()).hexdigest()
    if damage == "tampered":
        (kept / f"{sha}.yaml").write_bytes(other.read_bytes() + b"# changed\n")
    default_sha = hashlib.sha256(DEFAULT_MODEL.read_bytes()).hexdigest()
    (kept / f"{default_sha}.yaml").write_bytes(DEFAULT_MODEL.read_bytes())
    assert [e.kind for e in control_events(read_provenance(copy), copy)] == ["adapt", "zero", "model"]
    out = tmp_path / "out.csv"
    assert main(["compensate", str(copy), "--model", str(DEFAULT_MODEL), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    (line,) = [x for x in printed.splitlines() if "not what the daemon published" in x]
    assert "1 model reload whose model is not kept beside the capture" in line and "models/" in line
