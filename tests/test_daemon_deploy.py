"""The daemon as it is deployed: installed from a wheel, started from anywhere.

Readiness comes from the daemon's "listening on" line on its stdout: never from sleeps.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "tests" / "data"
GUARD_S = 60.0
INSTALL_GUARD_S = 600.0  # building a wheel and installing its dependencies into a new virtual environment


def _environment_outside_the_source_tree() -> dict[str, str]:
    """This process's environment less anything that would make Python import this source tree."""
    return {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")}


@contextlib.contextmanager
def daemon_process(command: list[str], *, cwd: Path, log: Path, env: dict[str, str] | None = None,
                   stdin: int = subprocess.DEVNULL) -> Iterator[subprocess.Popen]:  # fmt: skip
    """``command`` running with its stdout piped and its stderr in ``log``; killed if still running at the end."""
    with log.open("w") as stderr:
        proc = subprocess.Popen(command, cwd=cwd, env=env, stdin=stdin, stdout=subprocess.PIPE, stderr=stderr,
                                text=True)  # fmt: skip
        try:
            yield proc
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait(GUARD_S)


def run_until_ready_then_terminate(command: list[str], *, cwd: Path, log: Path, env: dict[str, str] | None = None,
                                   stdin: int = subprocess.DEVNULL) -> str:  # fmt: skip
    """Start ``command``; once it prints its readiness line, SIGTERM it; the line (asserting exit 0)."""
    with daemon_process(command, cwd=cwd, log=log, env=env, stdin=stdin) as proc:
        line = proc.stdout.readline()
        assert "listening on" in line, (line, log.read_text()[-5000:])
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(GUARD_S) == 0, log.read_text()[-5000:]
    return line


@pytest.mark.install
def test_a_wheel_installed_in_a_new_environment_runs_the_daemon_from_anywhere(tmp_path):
    """The review's M5: from a wheel, the default model was looked for beside site-packages
    (``.../site-packages/configs/models/default.yaml``) and ``fog-driver run`` exited 78."""
    source = tmp_path / "source"  # what a wheel is built from, and nothing else (no stale build/)
    source.mkdir()
    shutil.copy2(ROOT / "pyproject.toml", source)
    shutil.copy2(ROOT / "README.md", source)
    shutil.copytree(ROOT / "fog_driver", source / "fog_driver", ignore=shutil.ignore_patterns("__pycache__"))
    wheels = tmp_path / "wheels"
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", str(source), "-w", str(wheels)],
                   check=True, timeout=INSTALL_GUARD_S, capture_output=True)  # fmt: skip
    (wheel,) = wheels.glob("fog_driver-*.whl")
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=INSTALL_GUARD_S)
    subprocess.run([str(venv / "bin" / "python"), "-m", "pip", "install", "-q", str(wheel)],
                   check=True, timeout=INSTALL_GUARD_S, capture_output=True)  # fmt: skip

    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    env = _environment_outside_the_source_tree()
    where = subprocess.run([str(venv / "bin" / "python"), "-c",
                            "import fog_driver, fog_driver.config as c; print(fog_driver.__file__); "
                            "print(c.DEFAULT_MODEL); print(c.DEFAULT_MODEL.is_file())"],
                           cwd=elsewhere, env=env, capture_output=True, text=True, check=True, timeout=GUARD_S)  # fmt: skip
    package_file, model, model_is_file = where.stdout.split("\n")[:3]
    assert Path(package_file).is_relative_to(venv) and Path(model).is_relative_to(venv), where.stdout
    assert model_is_file == "True"

    line = run_until_ready_then_terminate(
        [str(venv / "bin" / "fog-driver"), "run", "--port", f"replay://{DATA / 'sim-short.bin'}?rate=100",
         "--listen", "127.0.0.1:0"],
        cwd=elsewhere, env=env, log=tmp_path / "daemon.log",
    )  # fmt: skip
    assert "raw capture in fog-captures/" in line
    assert (elsewhere / "fog-captures").is_dir()  # relative to the working directory


# -- which instrument: a port, or the simulator only when asked ----------------------------------


def _run_command(*args: str) -> list[str]:
    return [sys.executable, "-m", "fog_driver", "run", "--listen", "127.0.0.1:0", *args]


def test_no_port_without_a_terminal_is_a_one_line_config_error(tmp_path):
    """The review's M5: ``port: null`` (the shipped default.yaml copied as the unit's config) quietly
    served the embedded simulator in production.  Under systemd (stdin not a terminal) it is exit 78."""
    config = tmp_path / "instrument.yaml"
    config.write_text("port: null\n")
    command = _run_command("--config", str(config), "--capture-dir", str(tmp_path / "c"))
    with daemon_process(command, cwd=tmp_path, log=tmp_path / "daemon.log") as proc:
        first_line = proc.stdout.readline()
        assert first_line == "", first_line  # a readiness line: the simulator is serving
        status = proc.wait(GUARD_S)
    assert status == 78
    errors = [line for line in (tmp_path / "daemon.log").read_text().splitlines() if line.startswith("fog-driver:")]
    assert errors == [f"fog-driver: error: no instrument port: set 'port' in {config} or give --port PORT_OR_URL "
                      "(--simulate runs the built-in simulated instrument)"]  # fmt: skip
    assert not (tmp_path / "c").exists()


def test_simulate_runs_the_simulated_instrument_without_a_terminal(tmp_path):
    line = run_until_ready_then_terminate(_run_command("--simulate", "--capture-dir", "c"), cwd=tmp_path,
                                          log=tmp_path / "daemon.log")  # fmt: skip
    assert line.startswith("fog-driver ") and " /dev/pts/" in line.split("->")[0]


def test_on_a_terminal_no_port_still_runs_the_demonstration(tmp_path):
    """``fog-driver run`` with no arguments, typed at a terminal: the README's first command."""
    terminal, terminal_peer = os.openpty()
    try:
        line = run_until_ready_then_terminate(_run_command(), cwd=tmp_path, log=tmp_path / "daemon.log",
                                              stdin=terminal_peer)  # fmt: skip
    finally:
        os.close(terminal)
        os.close(terminal_peer)
    assert " /dev/pts/" in line.split("->")[0]
    assert (tmp_path / "fog-captures").is_dir()


def test_simulate_and_port_together_are_a_usage_error(tmp_path):
    proc = subprocess.run(_run_command("--simulate", "--port", "/dev/ttyUSB0"), cwd=tmp_path, capture_output=True,
                          text=True, stdin=subprocess.DEVNULL, timeout=GUARD_S)  # fmt: skip
    assert proc.returncode == 2 and "not allowed with argument" in proc.stderr


# -- exit statuses systemd acts on ------------------------------------------------------------------


def test_a_listen_address_in_use_is_exit_75_so_systemd_tries_again(tmp_path):
    """The review's L5: EADDRINUSE was exit 78, which RestartPreventExitStatus=78 never restarts; a
    previous instance still closing, or another program for a while, stopped the unit for good."""
    with socket.create_server(("127.0.0.1", 0)) as holder:
        busy = f"127.0.0.1:{holder.getsockname()[1]}"
        proc = subprocess.run([sys.executable, "-m", "fog_driver", "run", "--port", f"replay://{DATA / 'sim-short.bin'}",
                               "--listen", busy, "--capture-dir", str(tmp_path / "c")],
                              cwd=tmp_path, capture_output=True, text=True, stdin=subprocess.DEVNULL,
                              timeout=GUARD_S)  # fmt: skip
    assert proc.returncode == 75, proc.stderr
    errors = [line for line in proc.stderr.splitlines() if line.startswith("fog-driver:")]
    assert len(errors) == 1 and errors[0].startswith(f"fog-driver: error: cannot listen on {busy}: ")
    assert "address already in use" in errors[0].lower()
    assert "Traceback" not in proc.stderr
