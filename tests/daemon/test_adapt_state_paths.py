"""What the daemon does with the file at its ``adapt_state`` path (issue 46 item 3; the third attack round's
findings 3, 19 and 20): nothing that is not an adaptation state is renamed or replaced, a stale state it cannot
set aside leaves it running in memory, and a state it cannot save at exit ends the run in exit 73.

Each test failed on the code before its fix: the foreign file was renamed ``.stale-<UTC>`` (and ``?SAVE`` wrote
a state on a capture's name), the read-only directory stopped the start (exit 78), the lost state exited 0."""

from __future__ import annotations

import dataclasses
import errno
import os
import shutil
from pathlib import Path

import pytest
import yaml
from cli_run import run_cli
from daemon_hil import SHORT
from service_in_process import publish
from structlog.testing import capture_logs

from fog_driver.daemon.config import DEFAULT_MODEL, DriverConfig
from fog_driver.daemon.service import ConfigError, Service
from fog_driver.modelfiles import STATE_FIRST_LINE, not_a_state_file, read_state_doc

DATA = Path(__file__).resolve().parents[1] / "data"
REPLAY = f"replay://{DATA / 'sim-short.bin'}?rate=100"
ADAPT_AT_REST = '?ADAPT={"enable":true,"reference_dph":0.0};'


def _config(directory: Path, state: Path) -> Path:
    config = directory / "fog-driver.yaml"
    config.write_text(yaml.safe_dump({"adapt_state": str(state)}))
    return config


def _start(directory: Path, model: Path, config: Path):
    return run_cli(
        "run",
        "--port",
        REPLAY,
        "--listen",
        "127.0.0.1:0",
        "--capture-dir",
        str(directory / "captures"),
        "--model",
        str(model),
        "--config",
        str(config),
        cwd=directory,
    )


def _refusal(path: Path, kind: str) -> str:
    if kind.startswith("not a regular file"):  # the words every file reader gives (``files.bounded``)
        return f"fog-driver: error: {path}: {kind}: an adaptation state file must be one\n"
    refusing = "refusing to read, set aside or replace it"
    return f"fog-driver: error: {path}: adapt_state is {kind}, not an adaptation state; {refusing}\n"


def _the_model_itself(d: Path) -> tuple[Path, str]:
    return d / "model.yaml", "a fitted model"


def _another_model(d: Path) -> tuple[Path, str]:
    other = d / "other-model.yaml"
    other.write_bytes(DEFAULT_MODEL.read_bytes())
    return other, "a fitted model"


def _a_raw_capture(d: Path) -> tuple[Path, str]:
    capture = d / "run1.bin"
    capture.write_bytes(SHORT)
    return capture, "a capture"


def _a_capture_named_like_a_state(d: Path) -> tuple[Path, str]:
    capture = d / "adapt.yaml"
    capture.write_bytes(SHORT)
    return capture, "a capture"


def _a_captures_sidecar(d: Path) -> tuple[Path, str]:
    sidecar = d / "run1.bin.yaml"
    text = (DATA / "sim-short.bin.yaml").read_text()
    sidecar.write_text(text)
    return sidecar, f"a capture's provenance sidecar (of {yaml.safe_load(text)['capture']})"


def _the_config_file(d: Path) -> tuple[Path, str]:
    return d / "fog-driver.yaml", f"a file without {STATE_FIRST_LINE.strip()!r}"


def _a_text_file(d: Path) -> tuple[Path, str]:
    notes = d / "notes.txt"
    notes.write_text("calibration notes\n")
    return notes, f"a file without {STATE_FIRST_LINE.strip()!r}"


def _an_empty_file(d: Path) -> tuple[Path, str]:
    empty = d / "adapt.yaml"
    empty.touch()
    return empty, "an empty file"


def _a_directory(d: Path) -> tuple[Path, str]:
    folder = d / "states"
    folder.mkdir()
    (folder / "keep.txt").write_text("mine\n")
    return folder, "a directory"


def _a_fifo(d: Path) -> tuple[Path, str]:
    fifo = d / "adapt.yaml"
    os.mkfifo(fifo)
    return fifo, "not a regular file (it is a FIFO)"


def _snapshot(path: Path) -> object:
    if path.is_fifo():
        return "fifo"
    if path.is_dir():
        return {p.name: p.read_bytes() for p in path.iterdir()}
    return path.read_bytes()


@pytest.mark.parametrize(
    "make",
    [
        _the_model_itself,
        _another_model,
        _a_raw_capture,
        _a_capture_named_like_a_state,
        _a_captures_sidecar,
        _the_config_file,
        _a_text_file,
        _an_empty_file,
        _a_directory,
        _a_fifo,
    ],
    ids=lambda make: make.__name__.strip("_").replace("_", "-"),
)
def test_adapt_state_naming_a_file_of_another_kind_refuses_to_start_and_renames_nothing(tmp_path, make):
    """The review's finding 3: the daemon's own model was renamed ``model.yaml.stale-...``, a capture
    ``run1.bin.stale-...`` (and a directory, a text file, a config file the same)."""
    model = tmp_path / "model.yaml"
    model.write_bytes(DEFAULT_MODEL.read_bytes())
    foreign, kind = make(tmp_path)
    config = _config(tmp_path, foreign)
    before = _snapshot(foreign)
    names = sorted(p.name for p in tmp_path.iterdir())
    start = _start(tmp_path, model, config)
    assert (start.returncode, start.stderr, start.stdout) == (78, _refusal(foreign, kind), "")
    assert _snapshot(foreign) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == names  # no .stale-*, no capture, nothing new


def test_compensate_and_the_daemon_say_the_same_of_a_file_that_is_not_a_state(tmp_path):
    """One judge for both: ``compensate --adapt-state`` refuses the daemon's model with the same name for it."""
    model = tmp_path / "model.yaml"
    model.write_bytes(DEFAULT_MODEL.read_bytes())
    offline = run_cli(
        "compensate",
        str(DATA / "sim-short.bin"),
        "--model",
        str(model),
        "--out",
        "o.csv",
        "--adapt-state",
        str(model),
        cwd=tmp_path,
    )
    assert offline.returncode == 73
    assert offline.stderr == (
        f"fog-driver: error: {model}: --adapt-state exists and is {not_a_state_file(model)}, not an adaptation "
        "state; refusing to read or replace it\n"
    )
    assert not_a_state_file(model) == "a fitted model" and model.read_bytes() == DEFAULT_MODEL.read_bytes()


# -- in process: a state file, stale or cut short ------------------------------------------------------------


@pytest.fixture
def saved_state(tmp_path) -> Path:
    """A state file the daemon saved after adapting on the short capture."""
    state = tmp_path / "adapt.yaml"
    adapting = Service(DriverConfig(adapt_state=str(state), adapt_reference_dph=0.0), port="unused")
    publish(adapting, SHORT)
    adapting.shutdown()
    assert adapting.adapt_state_not_saved is None and read_state_doc(state)["format"]
    return state


def _stale(state: Path) -> bytes:
    """``state`` made stale: learned for another model (its frozen weights changed); its bytes."""
    doc = yaml.safe_load(state.read_text())
    doc["readout"]["frozen_weights"][0] += 0.25
    state.write_text(yaml.safe_dump(doc, sort_keys=False))
    return state.read_bytes()


def test_a_state_file_cut_short_is_still_a_state_and_is_set_aside(saved_state):
    """A state file is told by its first line, as the daemon writes it: one cut short is set aside, not refused."""
    text = saved_state.read_text()
    cut = text[: len(text) // 2]
    saved_state.write_text(cut)
    assert not_a_state_file(saved_state) is None
    Service(DriverConfig(adapt_state=str(saved_state)), port="unused")
    aside = list(saved_state.parent.glob("adapt.yaml.stale-*"))
    assert not saved_state.exists() and len(aside) == 1 and aside[0].read_text() == cut


def _without_host_clock(angles: list[dict]) -> list[dict]:
    return [{k: v for k, v in angle.items() if k != "utc"} for angle in angles]


def test_a_stale_state_in_a_read_only_directory_runs_with_the_state_in_memory_and_says_so_once(
    saved_state, monkeypatch
):
    """The review's finding 19: the start was refused ("cannot be set aside: Read-only file system", exit 78).
    The daemon is driven in process, its file system read-only to it: every rename and write fails EROFS."""
    stale = _stale(saved_state)
    expected = publish(Service(DriverConfig(), port="unused"), SHORT)  # the same run, started at rest

    def read_only(*args, **kwargs):
        raise OSError(errno.EROFS, os.strerror(errno.EROFS))

    monkeypatch.setattr(os, "replace", read_only)
    with capture_logs() as logs:
        service = Service(DriverConfig(adapt_state=str(saved_state)), port="unused")
        published = publish(service, SHORT)
        assert service.control("ADAPT", {"enable": True, "reference_dph": 0.0}, 0)["class"] == "ADAPT"
        answer = service.control("SAVE", {}, 0)
        service.shutdown()
    assert _without_host_clock(published) == _without_host_clock(expected)
    said = [entry for entry in logs if entry["event"] == "adapt_state_in_memory"]
    assert len(said) == 1 and said[0]["path"] == str(saved_state)
    assert "Read-only file system" in said[0]["reason"] and "in memory" in said[0]["reason"]
    assert answer["class"] == "ERROR" and "in memory only" in answer["message"]
    assert service.adapt_state_not_saved is None  # not tried at exit: the start said so
    assert saved_state.read_bytes() == stale and not list(saved_state.parent.glob("*.stale-*"))


def test_a_reload_that_points_adapt_state_at_the_model_is_refused_and_changes_nothing(tmp_path):
    service = Service(DriverConfig(adapt_state=str(tmp_path / "adapt.yaml")), port="unused")
    model = tmp_path / "model.yaml"
    model.write_bytes(DEFAULT_MODEL.read_bytes())
    with pytest.raises(ConfigError, match="adapt_state is a fitted model, not an adaptation state"):
        service.reload_config(dataclasses.replace(service.config, adapt_state=str(model)))
    assert service.config.adapt_state == str(tmp_path / "adapt.yaml")
    assert model.read_bytes() == DEFAULT_MODEL.read_bytes()


# -- a running daemon: ?SAVE and the save at SIGTERM ---------------------------------------------------------


def _adapting(tmp_path: Path, state: Path):
    """A daemon replaying a capture with ``adapt_state`` = ``state``, adapting (the first ANGLE seen)."""
    from daemon_hil import Client, Daemon

    daemon = Daemon(tmp_path, REPLAY, "--config", str(_config(tmp_path, state)))
    client = Client(daemon.address)
    client.send('?WATCH={"enable":true};')
    client.next("ANGLE")
    client.send(ADAPT_AT_REST)
    client.next("ADAPT")
    return daemon, client


def _errors(daemon) -> list[str]:
    return [line for line in daemon.log_path.read_text().splitlines() if line.startswith("fog-driver: error:")]


def test_a_capture_put_at_the_state_path_while_running_is_never_replaced(tmp_path):
    """The review's finding 3, second half: ``?SAVE`` wrote a state file where the capture was."""
    state = tmp_path / "adapt.yaml"
    daemon, client = _adapting(tmp_path, state)
    try:
        shutil.copyfile(DATA / "sim-short.bin", state)
        client.send("?SAVE;")
        refused = f"{state}: is a capture, not an adaptation state: not replaced"
        assert client.next("ERROR")["message"] == refused
        assert daemon.terminate() == 73  # the state adapted in this run could not be saved
    finally:
        daemon.kill()
    assert state.read_bytes() == SHORT and not list(tmp_path.glob("*.stale-*"))
    assert _errors(daemon) == [f"fog-driver: error: {refused}"]


def test_a_state_that_cannot_be_saved_at_sigterm_ends_the_run_in_exit_73(tmp_path):
    """The review's finding 20: logged once and exit 0, so a script or systemd took the lost state for a clean
    stop.  Here the state's directory is gone when the daemon stops."""
    states = tmp_path / "states"
    states.mkdir()
    state = states / "adapt.yaml"
    daemon, _client = _adapting(tmp_path, state)
    try:
        shutil.rmtree(states)
        assert daemon.terminate() == 73
    finally:
        daemon.kill()
    assert _errors(daemon) == [f"fog-driver: error: {state}: cannot write adaptation state: No such file or directory"]
    assert not states.exists()
