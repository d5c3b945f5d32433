"""``fog_driver.client`` needs the standard library only: no numpy, yaml, structlog or serial.

Two checks: a fresh interpreter of the test environment imports the client (and the operator's tools built on it)
without loading those packages; and an environment where only the standard library is installed (a bare venv made
``--without-pip``, the source tree on ``PYTHONPATH``) runs a real session, blocking and asyncio, against a daemon
started from the test environment.  Readiness is the daemon's "listening on" line, never a sleep.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from daemon_hil import Daemon

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT / "tests" / "data"
GUARD_S = 30.0
#: Packages the client library must not load.
FORBIDDEN = ("numpy", "yaml", "structlog", "serial")

_LOADED = "import sys; print(sorted(m for m in {forbidden!r} if m in sys.modules))"


def _loaded_by(module: str) -> list[str]:
    """The forbidden packages a fresh interpreter holds after ``import module``."""
    code = f"import {module}; " + _LOADED.format(forbidden=FORBIDDEN)
    proc = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=GUARD_S,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.replace("'", '"'))


@pytest.mark.parametrize(
    "module",
    [
        "fog_driver",
        "fog_driver.client",
        "fog_driver.client.udp",
        "fog_driver.client.display",
        "fog_driver.tools.watch",
        "fog_driver.tools.ctl",
    ],
)
def test_the_client_library_and_the_operators_tools_load_no_third_party_package(module):
    assert _loaded_by(module) == []


# The session run by the bare environment's interpreter: argv[1] is the daemon's HOST:PORT.
SESSION = textwrap.dedent(
    """
    import asyncio, sys

    FORBIDDEN = {forbidden!r}
    for name in FORBIDDEN:
        try:
            __import__(name)
        except ImportError:
            pass
        else:
            raise SystemExit(f"{{name}} is installed here: not a standard-library-only environment")

    import fog_driver.client
    from fog_driver.client import AsyncClient, Client, Status

    with Client(sys.argv[1], reconnect=False) as c:
        stream = c.angles(rate_hz=50)
        first = next(stream)
        later = next(a for a in stream if a.seq > first.seq)
        assert isinstance(c.status(), Status) and c.status().frames > 0
        assert c.zero().kind == "ZERO"
        print("blocking", c.version.proto_major, first.seq < later.seq, c.device.serial)

    async def main():
        async with AsyncClient(sys.argv[1], reconnect=False) as c:
            async for a in c.angles(rate_hz=50):
                status = await c.status()
                print("asyncio", a.seq > 0, status.frames > 0)
                break

    asyncio.run(asyncio.wait_for(main(), {guard_s}))
    print("loaded", sorted(m for m in FORBIDDEN if m in sys.modules))
    """
)


@pytest.fixture(scope="module")
def bare_python(tmp_path_factory) -> Path:
    """A venv with nothing installed (not even pip), made from this interpreter's base Python."""
    env_dir = tmp_path_factory.mktemp("bare") / "venv"
    subprocess.run(
        [sys.executable, "-m", "venv", "--without-pip", str(env_dir)], check=True, timeout=120, capture_output=True
    )
    return env_dir / "bin" / "python"


def test_a_session_in_an_environment_with_the_standard_library_only(bare_python, tmp_path):
    daemon = Daemon(tmp_path, f"replay://{DATA / 'sim-short.bin'}?rate=300")
    try:
        host, port = daemon.address
        script = tmp_path / "session.py"
        script.write_text(SESSION.format(forbidden=FORBIDDEN, guard_s=GUARD_S))
        env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTHON", "VIRTUAL_ENV"))}
        proc = subprocess.run(
            [str(bare_python), "-B", str(script), f"{host}:{port}"],
            capture_output=True,
            text=True,
            timeout=GUARD_S * 2,
            env={**env, "PYTHONPATH": str(ROOT)},
            cwd=tmp_path,
        )
        assert proc.returncode == 0, proc.stdout + proc.stderr
        assert proc.stdout.splitlines() == [
            "blocking 1 True FOG-SIM-0001",
            "asyncio True True",
            "loaded []",
        ], proc.stderr
        assert daemon.terminate() == 0
    finally:
        daemon.kill()
