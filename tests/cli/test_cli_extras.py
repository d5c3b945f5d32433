"""A command whose extra is not installed: its ``--help`` still shows; running it is one line with the pip
command and exit 64 (the README's exit-code table), for every command that needs an extra.

The extra is made unimportable in a subprocess (each of its modules set to None in ``sys.modules`` before
fog_driver is imported), as on a machine where it was never installed."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from fog_driver.extras import EXTRAS

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT / "tests" / "data"
MODEL = ROOT / "fog_driver" / "data" / "models" / "default.yaml"
GUARD_S = 120.0
#: A distribution's import name where it is not the distribution's name.
IMPORT_NAMES = {"scikit-learn": "sklearn", "prometheus-client": "prometheus_client"}

#: extra -> a command line that needs it (every such command: the list of EXTRAS must be covered).
COMMANDS = {
    "web": ["run", "--simulate", "--http", "127.0.0.1:0", "--listen", "127.0.0.1:0", "--capture-dir", "c"],
    "report": ["evaluate", str(DATA / "sim-short.bin"), "--model", str(MODEL), "--out", "report"],
    "svr": ["fit", str(DATA / "sim-short.bin"), "--kind", "pso-svr", "--out", "m.yaml"],
    "lab": ["chamber", "status", "sim://"],
}


def distributions_of(extra: str) -> list[str]:
    """The distributions pyproject.toml lists for ``extra``."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    return [re.split(r"[<>=!~\[ ]", spec, maxsplit=1)[0] for spec in project["optional-dependencies"][extra]]


def modules_of(extra: str) -> list[str]:
    """The import names of ``extra``'s distributions."""
    return [IMPORT_NAMES.get(name, name) for name in distributions_of(extra)]


def without(extra: str, argv: list[str], cwd: Path) -> subprocess.CompletedProcess:
    """``fog-driver ARGV`` in a Python where ``extra``'s modules cannot be imported."""
    hide = "".join(f"sys.modules[{module!r}] = None\n" for module in modules_of(extra))
    code = f"import sys\n{hide}from fog_driver.cli.app import main\nsys.exit(main({argv!r}))\n"
    env = {k: v for k, v in os.environ.items() if k != "NOTIFY_SOCKET"}
    return subprocess.run(
        [sys.executable, "-c", code],
        cwd=cwd,
        capture_output=True,
        text=True,
        stdin=subprocess.DEVNULL,
        env=env,
        timeout=GUARD_S,
    )


def test_every_extra_a_command_needs_is_tried():
    assert set(COMMANDS) == set(EXTRAS)


@pytest.mark.parametrize("extra", sorted(COMMANDS))
def test_a_command_whose_extra_is_missing_shows_its_help(tmp_path, extra):
    command = COMMANDS[extra][0]
    proc = without(extra, [command, "--help"], tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith(f"usage: fog-driver {command} ") and proc.stderr == ""


@pytest.mark.parametrize("extra", sorted(COMMANDS))
def test_running_a_command_whose_extra_is_missing_is_one_line_with_pip_and_exit_64(tmp_path, extra):
    """The review's finding 17: ``run --http`` without the web extra exited 78, the table says 64."""
    proc = without(extra, COMMANDS[extra], tmp_path)
    assert proc.returncode == 64, proc.stderr
    lines = proc.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("fog-driver: error: "), proc.stderr
    assert f"pip install -e '.[{extra}]'" in lines[0]
    assert all(name in lines[0] for name in distributions_of(extra))  # what is missing, by the name pip takes
    assert list(tmp_path.iterdir()) == []  # refused before any work: nothing written
