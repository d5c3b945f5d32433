"""The store of kept models beside the raw captures (``daemon.modelstore``): pruned by its index, rebuilt from the
files when the index is missing or corrupt, keeping what the search of every sidecar's text kept.

No sleeps: the captures rotate on an injected clock.
"""

from __future__ import annotations

import hashlib
import json
import os
import random
from pathlib import Path

import pytest
from structlog.testing import capture_logs

from fog_driver.daemon.modelstore import INDEX_NAME, KeptModels
from fog_driver.daemon.rawlog import RotatingCapture
from fog_driver.samples.captures import sidecar_path, write_provenance

MODELS = [f"format: model {n}\n".encode() for n in range(4)]
SHAS = [hashlib.sha256(m).hexdigest() for m in MODELS]


@pytest.fixture(autouse=True)
def _no_fsync(monkeypatch):
    """Durability is test_daemon_rawlog's; here the hundreds of rotations need not wait for the disk."""
    monkeypatch.setattr(os, "fsync", lambda fd: None)


class FakeClock:
    def __init__(self, t: float = 1000.0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


def reload(cap: RotatingCapture, n: int) -> None:
    """What the daemon does at a reload to model ``n``: note it, keep its copy, name it in the later sidecars."""
    cap.note({"event": "model", "sha256": SHAS[n]})
    cap.keep_model(SHAS[n], MODELS[n])
    cap.update_provenance({"model": {"sha256": SHAS[n]}}, current_file=False)


def kept(directory: Path) -> set[str]:
    return {path.stem for path in (directory / "models").glob("*.yaml")}


def named_by_a_sidecar(directory: Path) -> set[str]:
    """The rule before the index: a copy stays while the text of a sidecar in the directory holds its SHA-256
    (of every model the runs keep, the copies deleted included)."""
    text = "".join(path.read_text() for path in directory.glob("*.yaml"))
    return {sha for sha in SHAS if sha in text}


def run_with_reloads(directory: Path, seed: int, steps: int = 300) -> RotatingCapture:
    """A daemon's capture with reloads among four models (back to earlier ones too), rotations by size and by age
    (a quiet port: a reload while no file is open), and the retention deleting the oldest; after each prune that
    deleted a capture, the copies kept are those a sidecar left names."""
    rng = random.Random(seed)
    clock = FakeClock()
    cap = RotatingCapture(directory, max_bytes=1000, max_age_s=60.0, max_total_bytes=4000, clock=clock)
    cap.update_provenance({"model": {"sha256": SHAS[0]}})
    cap.keep_model(SHAS[0], MODELS[0])  # as the daemon starts
    pruned = 0
    for _ in range(steps):
        action = rng.random()
        if action < 0.06:  # a model then serves a few files
            reload(cap, rng.randrange(len(MODELS)))
        elif action < 0.12:
            clock.t += 61.0
            cap.poll()  # the file closes by age: the next reload comes while none is open
        else:
            cap.write(b"x" * rng.randint(100, 700))
        if len(cap.pruned) > pruned:
            pruned = len(cap.pruned)
            assert kept(directory) == named_by_a_sidecar(directory) | {cap.models.in_use}
    cap.close()
    assert pruned > 5  # the run pruned, and often
    return cap


def test_the_copies_kept_through_reloads_and_pruning_are_those_a_sidecar_names(tmp_path):
    for seed in range(4):
        directory = tmp_path / f"run{seed}"
        run_with_reloads(directory, seed)
        assert kept(directory) == named_by_a_sidecar(directory)


def test_a_prune_goes_by_the_index_and_reads_no_sidecar(tmp_path):
    """Once indexed, the sidecars' text no longer counts: blanked, the copies the captures left name stay; a capture
    deleted by hand takes the copy only it named with it."""
    with RotatingCapture(tmp_path, max_bytes=1000) as cap:
        cap.keep_model(SHAS[0], MODELS[0])
        cap.write(b"x" * 1000)
        reload(cap, 1)
        cap.write(b"y" * 1000)  # a second file: model 1's alone
    first, second = cap.files
    for capture in cap.files:
        write_provenance(capture, {"status": "complete"})  # no SHA-256 left in any sidecar
    store = KeptModels(tmp_path, "fog")
    with capture_logs() as logs:
        assert store.prune() == []
    assert kept(tmp_path) == {SHAS[0], SHAS[1]} and logs == []
    first.unlink()
    sidecar_path(first).unlink()
    with capture_logs() as logs:
        assert [path.stem for path in store.prune()] == [SHAS[0]]
    assert kept(tmp_path) == {SHAS[1]}
    assert [entry["event"] for entry in logs] == ["model_copy_pruned"]
    index = json.loads((tmp_path / "models" / INDEX_NAME).read_text())
    assert sorted(index["models"]) == [SHAS[1]]
    assert index["models"][SHAS[1]]["captures"] == {"fog": [[0, 1]]}
    assert index["models"][SHAS[1]]["bytes"] == len(MODELS[1])


def test_a_directory_from_before_the_index_is_pruned_as_before(tmp_path):
    """Without an index (captures kept by an older version) the store rebuilds it from the sidecars once, in one
    log line, and keeps what the search of the sidecars kept."""
    run_with_reloads(tmp_path, seed=7)
    (tmp_path / "models" / INDEX_NAME).unlink()
    captures = sorted(tmp_path.glob("fog-*.bin"))
    for capture in captures[:2]:  # the retention's next deletions, done by hand
        capture.unlink()
        sidecar_path(capture).unlink()
    expected = named_by_a_sidecar(tmp_path)
    store = KeptModels(tmp_path, "fog")
    with capture_logs() as logs:
        store.prune()
    assert kept(tmp_path) == expected
    rebuilt = [entry for entry in logs if entry["event"] == "kept_models_index_rebuilt"]
    assert len(rebuilt) == 1 and "missing" in rebuilt[0]["reason"]
    with capture_logs() as logs:
        store.prune()  # the index is back: no second rebuild
    assert logs == [] and (tmp_path / "models" / INDEX_NAME).is_file()


def test_a_corrupt_index_is_rebuilt_from_the_files_and_is_never_fatal(tmp_path):
    for garbage in (b"{not json", b'{"format": "fog-driver-kept-models", "version": 1, "models": [1]}', b"\xff\xfe"):
        directory = tmp_path / f"run{len(list(tmp_path.iterdir()))}"
        run_with_reloads(directory, seed=3)
        expected = named_by_a_sidecar(directory)
        (directory / "models" / INDEX_NAME).write_bytes(garbage)
        with capture_logs() as logs, RotatingCapture(directory, max_bytes=1000, max_total_bytes=4000) as cap:
            reload(cap, 2)  # the daemon starts and goes on
            cap.write(b"z" * 10)
        rebuilt = [entry for entry in logs if entry["event"] == "kept_models_index_rebuilt"]
        assert len(rebuilt) == 1 and rebuilt[0]["log_level"] == "warning"
        assert kept(directory) == expected | {SHAS[2]}
        assert json.loads((directory / "models" / INDEX_NAME).read_text())["format"] == "fog-driver-kept-models"


def test_a_copy_the_index_does_not_list_is_indexed_from_the_sidecars(tmp_path):
    """A copy kept by an older version beside an index (or a lost update) makes the store rebuild: the copy stays
    while a capture names it."""
    with RotatingCapture(tmp_path, max_bytes=1000) as cap:
        cap.update_provenance({"model": {"sha256": SHAS[3]}})  # an older daemon named it, and kept it
        cap.write(b"x" * 10)
    (tmp_path / "models").mkdir()
    (tmp_path / "models" / f"{SHAS[3]}.yaml").write_bytes(MODELS[3])
    (tmp_path / "models" / "notes.yaml").write_text("not a kept model: no SHA-256 names it\n")
    (tmp_path / "models" / INDEX_NAME).write_text(
        json.dumps({"format": "fog-driver-kept-models", "version": 1, "models": {}})
    )
    store = KeptModels(tmp_path, "fog")
    with capture_logs() as logs:
        assert store.prune() == []
    assert [entry["event"] for entry in logs] == ["kept_models_index_rebuilt"]
    with capture_logs() as logs:
        assert store.prune() == []  # indexed now: no second rebuild
    assert logs == [] and kept(tmp_path) == {SHAS[3], "notes"}
