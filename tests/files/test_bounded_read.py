"""Every file read is bounded and regular (issue 46, item 1; the review's finding 2).

Before: the one YAML reader checked the size by ``stat`` only and opened the file blocking, so an
``adapt_state`` on ``/dev/zero`` grew the daemon to 3.3 GB in 6 s, a FIFO hung its start with no log line, and
``compensate --model /dev/zero`` ended in ``internal error: MemoryError``.  Now a directory, a FIFO, a socket or a
device is one line "PATH: not a regular file (it is ...)", and no more than the limit is ever read.

A reader that could block on a FIFO runs in a thread (or a subprocess) with a hang guard: a join with a timeout
that fails the test, never a sleep; a subprocess that would read ``/dev/zero`` to its end runs under an address
space limit, so that the reader of before fails quickly instead of filling the machine's memory.
"""

from __future__ import annotations

import json
import os
import resource
import signal
import socket
import stat
import subprocess
import sys
import threading
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path

import pytest
from cli_run import assert_one_line_error

from fog_driver.daemon.config import DEFAULT_MODEL
from fog_driver.errors import InputFileError
from fog_driver.files import yamlio
from fog_driver.files.yamlio import MAX_YAML_BYTES, read_yaml_text

DATA = Path(__file__).resolve().parents[1] / "data"
CAPTURE = DATA / "sim-short.bin"
#: The hang guard: a read that has not returned by then is a read that blocks.
GUARD_S = 30.0
#: The address space a command's process may take here: far more than any command needs, far less than reading
#: /dev/zero to its end would (the reader of before: a MemoryError, exit 70, instead of gigabytes).
ADDRESS_SPACE_BYTES = 3 << 30


def _returned_within_the_guard(read: Callable[[], object], fifo: Path | None = None) -> object:
    """``read()``'s result or exception, from a thread joined with the hang guard; a read still blocked then fails
    the test (and is let go: the FIFO's writer end is opened and closed, so the blocked open returns)."""
    outcome: list[object] = []

    def run() -> None:
        try:
            outcome.append(read())
        except Exception as exc:  # noqa: BLE001 (the test looks at it)
            outcome.append(exc)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    thread.join(GUARD_S)
    if thread.is_alive():
        if fifo is not None:
            os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))  # the reader's open returns, then reads EOF
            thread.join(GUARD_S)
        pytest.fail(f"the read did not return within {GUARD_S} s: it blocks")
    return outcome[0]


@pytest.fixture
def unix_socket(tmp_path: Path) -> Iterator[Path]:
    path = tmp_path / "s.sock"
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.bind(str(path))
        yield path


def _not_regular(tmp_path: Path, kind: str, unix_socket: Path) -> tuple[Path, str]:
    """A path of ``kind`` (none of them a regular file) and what the error says it is."""
    if kind == "fifo":
        os.mkfifo(tmp_path / "state.yaml")
        return tmp_path / "state.yaml", "a FIFO"
    if kind == "directory":
        (tmp_path / "d.yaml").mkdir()
        return tmp_path / "d.yaml", "a directory"
    if kind == "socket":
        return unix_socket, "a socket"
    link = tmp_path / "zero.yaml"
    link.symlink_to("/dev/zero")  # the review's: a symlink to /dev/zero
    return link, "a character device"


@pytest.mark.parametrize("kind", ["fifo", "directory", "socket"])
def test_a_yaml_file_that_is_a_fifo_a_directory_or_a_socket_is_one_line_at_once(tmp_path, kind, unix_socket):
    path, what = _not_regular(tmp_path, kind, unix_socket)
    outcome = _returned_within_the_guard(lambda: read_yaml_text(path, "adaptation state file"), path)
    assert isinstance(outcome, InputFileError), outcome
    assert str(outcome) == f"{path}: not a regular file (it is {what}): an adaptation state file must be one"
    assert stat.S_ISREG(os.stat(path).st_mode) is False  # (what was refused is indeed no regular file)


def test_a_yaml_file_that_is_a_symlink_to_dev_zero_is_one_line(tmp_path, unix_socket):
    """In a process of its own, under the address space limit: the reader of before read /dev/zero until the
    memory ran out."""
    path, _ = _not_regular(tmp_path, "dev-zero", unix_socket)
    read = (
        "import sys\nfrom fog_driver.files.yamlio import read_yaml_text\n"
        "try:\n    read_yaml_text(sys.argv[1], 'state file')\nexcept Exception as exc:\n    print(exc)\n"
    )
    proc = subprocess.run(
        [sys.executable, "-c", read, str(path)],
        capture_output=True,
        text=True,
        timeout=GUARD_S,
        preexec_fn=_limit_address_space,
    )
    assert (proc.returncode, proc.stdout, proc.stderr) == (
        0,
        f"{path}: not a regular file (it is a character device): a state file must be one\n",
        "",
    )


def test_a_file_larger_than_the_limit_is_refused_and_a_symlink_to_a_regular_file_is_read(tmp_path):
    doc = tmp_path / "doc.yaml"
    doc.write_text("a: 1\n")
    link = tmp_path / "link.yaml"
    link.symlink_to(doc)
    assert read_yaml_text(link, "config file") == doc.read_text()
    big = tmp_path / "big.yaml"
    big.write_bytes(b"#" * (MAX_YAML_BYTES + 1))
    with pytest.raises(InputFileError) as info:
        read_yaml_text(big, "config file")
    assert str(info.value) == f"{big}: config file larger than {MAX_YAML_BYTES} bytes"
    big.write_bytes(b"#" * MAX_YAML_BYTES)  # the limit itself is read
    assert len(read_yaml_text(big, "config file") or "") == MAX_YAML_BYTES


def test_a_file_that_holds_more_than_its_stat_says_is_capped_at_the_limit(monkeypatch):
    """A file that grows while it is read, as the kernel's own files do: /proc/self/maps is a regular file of
    size 0 by ``stat`` that reads as kilobytes.  The bytes read are counted, not the size ``stat`` gave."""
    maps = Path("/proc/self/maps")
    assert os.stat(maps).st_size == 0 and stat.S_ISREG(os.stat(maps).st_mode)
    held = len(maps.read_bytes())
    limit = held // 2
    monkeypatch.setattr(yamlio, "MAX_YAML_BYTES", limit)
    with pytest.raises(InputFileError) as info:
        read_yaml_text(maps, "model file")
    assert str(info.value) == f"{maps}: model file larger than {limit} bytes"


def test_a_missing_file_keeps_its_words(tmp_path):
    assert read_yaml_text(tmp_path / "none.yaml", "adaptation state", missing_ok=True) is None
    with pytest.raises(InputFileError) as info:
        read_yaml_text(tmp_path / "none.yaml", "profile file", hint=" (profiles: paper)")
    assert str(info.value) == f"{tmp_path / 'none.yaml'}: no such profile file (profiles: paper)"


def _limit_address_space() -> None:
    resource.setrlimit(resource.RLIMIT_AS, (ADDRESS_SPACE_BYTES, ADDRESS_SPACE_BYTES))


def _command(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    """``fog-driver ARGS`` under the address space limit, with the hang guard (a hang fails the test)."""
    return subprocess.run(
        [sys.executable, "-m", "fog_driver", *args],
        capture_output=True,
        text=True,
        cwd=cwd,
        timeout=GUARD_S * 2,
        stdin=subprocess.DEVNULL,
        preexec_fn=_limit_address_space,
    )


def test_compensate_with_the_model_dev_zero_is_one_line_65(tmp_path):
    """The review: ``internal error: MemoryError`` (exit 70)."""
    proc = _command("compensate", str(CAPTURE), "--model", "/dev/zero", "--out", "o.csv", cwd=tmp_path)
    assert_one_line_error(proc, 65, "/dev/zero: not a regular file (it is a character device): a model file")
    assert not (tmp_path / "o.csv").exists()


@pytest.mark.parametrize(
    "command",
    [
        ["inspect", "{capture}"],
        ["compensate", "{capture}", "--model", str(DEFAULT_MODEL), "--out", "o.csv"],
        ["fit", "{capture}", "--out", "m.yaml"],
        ["compensate", str(CAPTURE), "--model", str(DEFAULT_MODEL), "--out", "o.csv", "--table-log", "{capture}"],
    ],
    ids=["inspect", "compensate", "fit", "table-log"],
)
@pytest.mark.parametrize("kind", ["fifo", "dev-zero", "directory"])
def test_a_capture_or_a_table_log_that_is_a_fifo_dev_zero_or_a_directory_is_one_line_65(
    tmp_path, command, kind, unix_socket
):
    """Before: a FIFO hung ``inspect``, ``fit`` and ``compensate``; ``fit /dev/zero`` read zeros for ever."""
    path, what = _not_regular(tmp_path, kind, unix_socket)
    proc = _command(*(a.format(capture=path) for a in command), cwd=tmp_path)
    assert_one_line_error(proc, 65, f"{path}: not a regular file (it is {what})")
    assert not (tmp_path / "o.csv").exists() and not (tmp_path / "m.yaml").exists()


@pytest.mark.parametrize("kind", ["fifo", "dev-zero"])
def test_compensate_with_an_adapt_state_on_a_fifo_or_dev_zero_refuses_it_as_an_output_73(tmp_path, kind, unix_socket):
    """``--adapt-state`` names an input and an output: what is there is told by its content first, and a FIFO was
    opened blocking for that look (a hang); now it is never opened."""
    state, _ = _not_regular(tmp_path, kind, unix_socket)
    proc = _command(
        "compensate",
        str(CAPTURE),
        "--model",
        str(DEFAULT_MODEL),
        "--out",
        "o.csv",
        "--adapt-state",
        str(state),
        cwd=tmp_path,
    )
    what = "a FIFO" if kind == "fifo" else "a character device"
    assert_one_line_error(proc, 73, f"{state}: --adapt-state exists and is not a regular file (it is {what}), not an")
    assert not (tmp_path / "o.csv").exists() and os.path.lexists(state)


@pytest.mark.parametrize("command", ["ctl", "watch"])
def test_ctl_or_watch_with_a_token_file_that_is_a_fifo_is_one_line_65(tmp_path, command, unix_socket):
    """Before: the client waited for a writer of the FIFO, for ever, before it connected."""
    fifo, _ = _not_regular(tmp_path, "fifo", unix_socket)
    args = ["status"] if command == "ctl" else ["--count", "1"]
    proc = _command(command, "--token-file", str(fifo), *args, cwd=tmp_path)
    assert_one_line_error(proc, 65, f"{fifo}: not a regular file: a token file must be one")


def _run_daemon(tmp_path: Path, config: Path) -> subprocess.CompletedProcess:
    return _command(
        "run",
        "--config",
        str(config),
        "--port",
        f"replay://{CAPTURE}",
        "--listen",
        "127.0.0.1:0",
        "--capture-dir",
        str(tmp_path / "captures"),
        cwd=tmp_path,
    )


@pytest.mark.parametrize("kind", ["dev-zero", "fifo"])
def test_run_with_an_adapt_state_on_dev_zero_or_a_fifo_exits_78_with_one_line(tmp_path, kind, unix_socket):
    """The review: ``/dev/zero`` grew the daemon to 3.3 GB in 6 s, a FIFO hung its start with no log line.  The
    path is refused, not set aside: it is left as it was."""
    state, what = _not_regular(tmp_path, kind, unix_socket)
    config = tmp_path / "fog.yaml"
    config.write_text(f"adapt_state: {state}\n")
    proc = _run_daemon(tmp_path, config)
    expected = f"{state}: not a regular file (it is {what}): an adaptation state file must be one"
    assert (proc.returncode, proc.stderr, proc.stdout) == (78, f"fog-driver: error: {expected}\n", "")
    assert os.path.lexists(state) and sorted(p.name for p in tmp_path.iterdir()) == sorted(
        [state.name, config.name, unix_socket.name]
    )


def test_run_with_a_config_that_is_a_fifo_exits_78_with_one_line(tmp_path, unix_socket):
    config, _ = _not_regular(tmp_path, "fifo", unix_socket)
    proc = _run_daemon(tmp_path, config)
    expected = f"{config}: not a regular file (it is a FIFO): a config file must be one"
    assert (proc.returncode, proc.stderr, proc.stdout) == (78, f"fog-driver: error: {expected}\n", "")


def _log_events(log: Path, keys: Iterable[str]) -> list[dict]:
    """The daemon's JSON log lines so far, each cut to ``keys``."""
    events = [json.loads(line) for line in log.read_text().splitlines() if line.startswith("{")]
    return [{k: e.get(k) for k in keys} for e in events]


def test_a_reload_of_a_model_path_that_became_a_fifo_is_refused_and_the_old_model_goes_on(tmp_path):
    """``?RELOAD`` and SIGHUP read the model the same way (``Service.reload_from_file``): a FIFO is one line, at
    once, and the angle goes on with the model in use."""
    from model_refusals import watching

    model = tmp_path / "m.yaml"
    with watching(tmp_path, model) as (daemon, client):
        client.send("?STATUS;")
        in_use = client.next("STATUS")["model_file"]
        model.unlink()
        os.mkfifo(model)
        expected = f"{model}: not a regular file (it is a FIFO): a model file must be one"
        client.send("?RELOAD;")
        assert client.next("ERROR")["message"] == expected
        daemon.proc.send_signal(signal.SIGHUP)
        refused = {"event": "config_reload_failed", "reason": expected}
        for _ in range(10000):  # each answer after the one before: a bounded poll of the log, no sleep
            if refused in _log_events(daemon.log_path, refused.keys()):
                break
            client.send("?STATUS;")
            client.next("STATUS")
        assert refused in _log_events(daemon.log_path, refused.keys())
        before = client.next("ANGLE")["t_s"]
        assert client.next("ANGLE")["t_s"] > before  # the old model publishes on
        client.send("?STATUS;")
        assert client.next("STATUS")["model_file"] == in_use
        assert daemon.terminate() == 0


@pytest.mark.parametrize("kind", ["fifo", "dev-zero", "directory"])
def test_a_replay_port_on_a_fifo_dev_zero_or_a_directory_cannot_be_opened_and_never_waits(tmp_path, kind, unix_socket):
    """Before: ``run --port replay://FIFO`` waited in the port's open for ever (the port stayed ``opening``)."""
    import serial

    import fog_driver.transport  # noqa: F401 (registers replay://)

    path, _ = _not_regular(tmp_path, kind, unix_socket)
    outcome = _returned_within_the_guard(lambda: serial.serial_for_url(f"replay://{path}"), path)
    assert isinstance(outcome, serial.SerialException), outcome
    assert str(outcome).endswith("not a regular file")
