"""What a refused model file must do wherever it is used: at start-up, offline, and on ``?RELOAD`` of a
watched daemon."""

from __future__ import annotations

import contextlib
from pathlib import Path

from cli_run import run_cli

from fog_driver.daemon.config import DEFAULT_MODEL

DATA = Path(__file__).resolve().parent / "data"


def assert_start_up_and_offline_refuse(model: Path, cwd: Path, stderr: str) -> None:
    """``run`` with ``model`` exits 78 and ``compensate`` 65, each with ``stderr`` alone, writing nothing."""
    start = run_cli(
        "run",
        "--port",
        "replay://x.bin",
        "--model",
        str(model),
        "--listen",
        "127.0.0.1:0",
        "--capture-dir",
        "c",
        cwd=cwd,
    )
    assert (start.returncode, start.stderr, start.stdout) == (78, stderr, "")
    offline = run_cli("compensate", str(DATA / "sim-short.bin"), "--model", str(model), "--out", "o.csv", cwd=cwd)
    assert (offline.returncode, offline.stderr) == (65, stderr)
    assert not (cwd / "o.csv").exists()


@contextlib.contextmanager
def watching(tmp_path: Path, model: Path):
    """A daemon on ``model`` (the shipped default's copy) replaying a capture, and a client that has its first
    ANGLE; the daemon killed at the end whatever happened."""
    from daemon_hil import Client, Daemon

    model.write_bytes(DEFAULT_MODEL.read_bytes())
    daemon = Daemon(tmp_path, f"replay://{DATA / 'sim-short.bin'}?rate=100", "--model", str(model))
    try:
        client = Client(daemon.address)
        client.send('?WATCH={"enable":true};')
        client.next("ANGLE")
        yield daemon, client
    finally:
        daemon.kill()
