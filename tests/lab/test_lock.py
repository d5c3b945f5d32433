"""One runner per chamber (fog_driver.lab.lock): a second lock of the same address is refused in one line."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from fog_driver.errors import DeviceError
from fog_driver.lab.lock import ControllerLock, lock_folder, lock_path


def test_a_second_runner_for_the_same_address_is_refused_and_names_the_first(tmp_path: Path) -> None:
    with ControllerLock("espec:10.0.0.5:10001", tmp_path):
        with pytest.raises(DeviceError, match=r"another chamber run drives espec:10\.0\.0\.5:10001") as info:
            ControllerLock("espec:10.0.0.5:10001", tmp_path).acquire()
        assert f"pid {os.getpid()}" in str(info.value) and info.value.exit_status == 69
        assert "\n" not in str(info.value)


def test_another_address_is_not_blocked_and_a_released_lock_is_free_again(tmp_path: Path) -> None:
    with ControllerLock("espec:a:1", tmp_path), ControllerLock("espec:b:1", tmp_path):
        pass
    with ControllerLock("espec:a:1", tmp_path):
        pass


def test_a_lock_held_by_another_process_refuses_and_its_end_frees_it(tmp_path: Path) -> None:
    code = (
        "import sys; from pathlib import Path; from fog_driver.lab.lock import ControllerLock;"
        f"lock = ControllerLock('sim:x', Path({str(tmp_path)!r})); lock.acquire(); print('locked', flush=True);"
        "sys.stdin.readline()"
    )
    holder = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout is not None and holder.stdout.readline() == "locked\n"
        with pytest.raises(DeviceError, match=f"pid {holder.pid}"):
            ControllerLock("sim:x", tmp_path).acquire()
    finally:
        assert holder.stdin is not None
        holder.stdin.close()
        holder.wait(timeout=30)
    with ControllerLock("sim:x", tmp_path):  # the kernel released it with the process
        pass


def test_the_lock_lives_under_xdg_runtime_dir_or_tmp(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    assert lock_folder() == tmp_path and lock_path("a").parent == tmp_path
    monkeypatch.delenv("XDG_RUNTIME_DIR")
    assert lock_folder() == Path("/tmp")
    assert lock_path("a") != lock_path("b")
