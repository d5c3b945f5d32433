"""Writing the project's YAML files (sidecars, adaptation states, models): atomic, durable, and never
through a file or symlink someone planted in the directory."""

from __future__ import annotations

import errno
import os
import re
import stat
from pathlib import Path

import pytest
import yaml

from fog_driver.errors import OutputFileError
from fog_driver.files import yamlio as yamlfile
from fog_driver.files.yamlio import write_yaml

DOC = {"format": "test", "values": [1, 2, 3]}


def test_planted_symlinks_are_never_written_through(tmp_path):
    """The review's E15: a symlink at the old fixed temporary name (``<name>.tmp``) made the writer
    overwrite the link's target.  Links at that name and at the final name leave their targets alone."""
    victim = tmp_path / "victim.conf"
    victim.write_text("important: config\n")
    target = tmp_path / "side.yaml"
    (tmp_path / "side.yaml.tmp").symlink_to(victim)
    write_yaml(target, DOC, "sidecar")
    assert victim.read_text() == "important: config\n"
    assert yaml.safe_load(target.read_text()) == DOC
    target.unlink()
    target.symlink_to(victim)  # a link at the final name: replaced by the file, its target untouched
    write_yaml(target, DOC, "sidecar")
    assert victim.read_text() == "important: config\n"
    assert not target.is_symlink() and yaml.safe_load(target.read_text()) == DOC
    assert sorted(p.name for p in tmp_path.iterdir()) == ["side.yaml", "side.yaml.tmp", "victim.conf"]


def test_the_file_gets_the_umask_mode_and_nothing_is_left_behind(tmp_path):
    previous = os.umask(0o027)
    try:
        write_yaml(tmp_path / "state.yaml", DOC, "state")
    finally:
        os.umask(previous)
    assert stat.S_IMODE((tmp_path / "state.yaml").stat().st_mode) == 0o640
    assert [p.name for p in tmp_path.iterdir()] == ["state.yaml"]


def test_the_file_and_its_directory_are_fsynced_before_and_after_the_rename(tmp_path, monkeypatch):
    synced: list[tuple[str, bool]] = []  # (what the descriptor is, whether the final name existed then)
    real_fsync = os.fsync
    target = tmp_path / "model.yaml"

    def spy(fd: int) -> None:
        kind = "directory" if stat.S_ISDIR(os.fstat(fd).st_mode) else "file"
        synced.append((kind, target.exists()))
        real_fsync(fd)

    monkeypatch.setattr(yamlfile.os, "fsync", spy)
    write_yaml(target, DOC, "model")
    assert synced == [("file", False), ("directory", True)]


def test_a_failed_write_keeps_the_old_file_and_leaves_no_temporary(tmp_path, monkeypatch):
    target = tmp_path / "state.yaml"
    write_yaml(target, {"old": True}, "state")

    def disk_full(fd: int) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(yamlfile.os, "fsync", disk_full)
    with pytest.raises(OutputFileError, match="state.yaml: cannot write state: No space left on device"):
        write_yaml(target, {"new": True}, "state")
    assert yaml.safe_load(target.read_text()) == {"old": True}
    assert [p.name for p in tmp_path.iterdir()] == ["state.yaml"]


def test_the_package_reads_yaml_with_safe_load_only():
    """Configs, profiles, sidecars and models: ``yaml.safe_load`` and nothing that can build a Python object."""
    package = Path(yamlfile.__file__).resolve().parents[1]
    unsafe = re.compile(r"yaml\.(load|load_all|full_load|unsafe_load|unsafe_load_all|Loader|FullLoader|UnsafeLoader)\b")
    found = [
        f"{path.relative_to(package)}:{n}"
        for path in sorted(package.rglob("*.py"))
        for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1)
        if unsafe.search(line)
    ]
    assert found == []
