"""The daemon as it is deployed: installed from a wheel, started from anywhere, run by the shipped systemd
unit with the example instrument config; the exit statuses systemd acts on.

Readiness comes from the daemon's "listening on" line on its stdout, or from READY=1 on a notify socket
the test listens on: never from sleeps.
"""

from __future__ import annotations

import os
import select
import shlex
import shutil
import signal
import socket
import stat
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import pytest
import yaml
from daemon_process import GUARD_S, daemon_process

from fog_driver.daemon.config import load_config

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT / "tests" / "data"
UNIT = ROOT / "configs" / "systemd" / "fog-driver@.service"
EXAMPLE_CONFIG = ROOT / "configs" / "systemd" / "example-instrument.yaml"
INSTALLED_FOG_DRIVER = "/opt/fog-driver/venv/bin/fog-driver"  # the unit's ExecStart (the README's install)
STATE_DIRECTORY = "/var/lib/fog-driver"
INSTANCE = "bench1"
#: Service.shutdown's own budget: the sum of its bounded waits (acquisition, capture, clients).
DAEMON_SHUTDOWN_BUDGET_S = 15.0
#: The environment systemd gives a service (no virtual environment on the PATH), before the unit's own.
SYSTEMD_PATH = "/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin"
INSTALL_GUARD_S = 600.0  # building a wheel and installing its dependencies into a new virtual environment


def _environment_outside_the_source_tree() -> dict[str, str]:
    """This process's environment less anything that would make Python import this source tree."""
    return {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")}


def run_until_ready_then_terminate(
    command: list[str],
    *,
    cwd: Path,
    log: Path,
    env: dict[str, str] | None = None,
    stdin: int = subprocess.DEVNULL,
    umask: int = -1,
) -> str:
    """Start ``command``; once it prints its readiness line, SIGTERM it; the line (asserting exit 0)."""
    with daemon_process(command, cwd=cwd, log=log, env=env, stdin=stdin, umask=umask) as proc:
        line = proc.stdout.readline()
        assert "listening on" in line, (line, log.read_text()[-5000:])
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(GUARD_S) == 0, log.read_text()[-5000:]
    return line


@pytest.mark.install
@pytest.mark.serial
def test_a_wheel_installed_in_a_new_environment_runs_the_daemon_from_anywhere(tmp_path):
    """The review's M5: from a wheel, the default model was looked for beside site-packages
    (``.../site-packages/configs/models/default.yaml``) and ``fog-driver run`` exited 78."""
    source = tmp_path / "source"  # what a wheel is built from, and nothing else (no stale build/)
    source.mkdir()
    shutil.copy2(ROOT / "pyproject.toml", source)
    shutil.copy2(ROOT / "README.md", source)
    shutil.copytree(ROOT / "fog_driver", source / "fog_driver", ignore=shutil.ignore_patterns("__pycache__"))
    wheels = tmp_path / "wheels"
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", str(source), "-w", str(wheels)],
        check=True,
        timeout=INSTALL_GUARD_S,
        capture_output=True,
    )
    (wheel,) = wheels.glob("fog_driver-*.whl")
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=INSTALL_GUARD_S)
    subprocess.run(
        [str(venv / "bin" / "python"), "-m", "pip", "install", "-q", str(wheel)],
        check=True,
        timeout=INSTALL_GUARD_S,
        capture_output=True,
    )

    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    env = _environment_outside_the_source_tree()
    where = subprocess.run(
        [
            str(venv / "bin" / "python"),
            "-c",
            "import fog_driver, fog_driver.daemon.config as c; print(fog_driver.__file__); "
            "print(c.DEFAULT_MODEL); print(c.DEFAULT_MODEL.is_file())",
        ],
        cwd=elsewhere,
        env=env,
        capture_output=True,
        text=True,
        check=True,
        timeout=GUARD_S,
    )
    package_file, model, model_is_file = where.stdout.split("\n")[:3]
    assert Path(package_file).is_relative_to(venv) and Path(model).is_relative_to(venv), where.stdout
    assert model_is_file == "True"
    simulated = subprocess.run(  # the built-in calibration program needs no configs/ folder
        [str(venv / "bin" / "fog-driver"), "simulate", "--profile", "calibration", "--rate-hz", "10"]
        + ["--duration", "60", "--out", "calibration.bin"],
        cwd=elsewhere,
        env=env,
        capture_output=True,
        text=True,
        timeout=GUARD_S,
    )
    assert simulated.returncode == 0 and "simulated calibration at 10 Hz" in simulated.stdout, simulated.stderr

    line = run_until_ready_then_terminate(
        [
            str(venv / "bin" / "fog-driver"),
            "run",
            "--port",
            f"replay://{DATA / 'sim-short.bin'}?rate=100",
            "--listen",
            "127.0.0.1:0",
        ],
        cwd=elsewhere,
        env=env,
        log=tmp_path / "daemon.log",
    )
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
    assert errors == [
        f"fog-driver: error: no instrument port: set 'port' in {config} or give --port PORT_OR_URL "
        "(--simulate runs the built-in simulated instrument)"
    ]
    assert not (tmp_path / "c").exists()


def test_simulate_runs_the_simulated_instrument_without_a_terminal(tmp_path):
    line = run_until_ready_then_terminate(
        _run_command("--simulate", "--capture-dir", "c"), cwd=tmp_path, log=tmp_path / "daemon.log"
    )
    assert line.startswith("fog-driver ") and " /dev/pts/" in line.split("->")[0]


def test_on_a_terminal_no_port_still_runs_the_demonstration(tmp_path):
    """``fog-driver run`` with no arguments, typed at a terminal: the README's first command."""
    terminal, terminal_peer = os.openpty()
    try:
        line = run_until_ready_then_terminate(
            _run_command(), cwd=tmp_path, log=tmp_path / "daemon.log", stdin=terminal_peer
        )
    finally:
        os.close(terminal)
        os.close(terminal_peer)
    assert " /dev/pts/" in line.split("->")[0]
    assert (tmp_path / "fog-captures").is_dir()


def test_simulate_and_port_together_are_a_usage_error(tmp_path):
    proc = subprocess.run(
        _run_command("--simulate", "--port", "/dev/ttyUSB0"),
        cwd=tmp_path,
        capture_output=True,
        text=True,
        stdin=subprocess.DEVNULL,
        timeout=GUARD_S,
    )
    assert proc.returncode == 2 and "not allowed with argument" in proc.stderr


# -- exit statuses systemd acts on ------------------------------------------------------------------


def test_a_listen_address_in_use_is_exit_75_so_systemd_tries_again(tmp_path):
    """The review's L5: EADDRINUSE was exit 78, which RestartPreventExitStatus=78 never restarts; a
    previous instance still closing, or another program for a while, stopped the unit for good."""
    with socket.create_server(("127.0.0.1", 0)) as holder:
        busy = f"127.0.0.1:{holder.getsockname()[1]}"
        proc = subprocess.run(
            [
                sys.executable,
                "-m",
                "fog_driver",
                "run",
                "--port",
                f"replay://{DATA / 'sim-short.bin'}",
                "--listen",
                busy,
                "--capture-dir",
                str(tmp_path / "c"),
            ],
            cwd=tmp_path,
            capture_output=True,
            text=True,
            stdin=subprocess.DEVNULL,
            timeout=GUARD_S,
        )
    assert proc.returncode == 75, proc.stderr
    errors = [line for line in proc.stderr.splitlines() if line.startswith("fog-driver:")]
    assert len(errors) == 1 and errors[0].startswith(f"fog-driver: error: cannot listen on {busy}: ")
    assert (
        "address already in use (another fog-driver run? give this one another address: --listen" in errors[0].lower()
    )
    assert "Traceback" not in proc.stderr


def test_the_daemon_never_creates_world_writable_files(tmp_path):
    """Started with umask 0, the daemon's capture directory was 0777 (anyone could plant or replace files)."""
    run_until_ready_then_terminate(
        [
            sys.executable,
            "-m",
            "fog_driver",
            "run",
            "--port",
            f"replay://{DATA / 'sim-short.bin'}",
            "--listen",
            "127.0.0.1:0",
            "--capture-dir",
            "c",
        ],
        cwd=tmp_path,
        log=tmp_path / "daemon.log",
        umask=0,
    )
    assert stat.S_IMODE((tmp_path / "c").stat().st_mode) == 0o775
    for path in (tmp_path / "c").iterdir():
        assert not path.stat().st_mode & 0o002, path


# -- the systemd unit and the example instrument config, as shipped ---------------------------------


def parse_unit(text: str) -> dict[str, dict[str, list[str]]]:
    """systemd's INI-like unit syntax: [Section], Key=value, '#'/';' comments, repeatable keys."""
    sections: dict[str, dict[str, list[str]]] = {}
    current = None
    for number, raw in enumerate(text.splitlines(), 1):
        line = raw.strip()
        if not line or line[0] in "#;":
            continue
        assert not line.endswith("\\"), f"line {number}: continuation lines not expected"
        if line.startswith("[") and line.endswith("]"):
            current = sections.setdefault(line[1:-1], {})
            continue
        assert current is not None and "=" in line, f"line {number}: not Key=value inside a section: {raw!r}"
        key, value = line.split("=", 1)
        current.setdefault(key.strip(), []).append(value.strip())
    return sections


def unit_service_keys() -> dict[str, str]:
    """The unit's [Service] settings (the last value of a repeated key)."""
    return {key: values[-1] for key, values in parse_unit(UNIT.read_text(encoding="utf-8"))["Service"].items()}


def this_machines_fog_driver() -> Path:
    """The ``fog-driver`` this test environment installed, standing in for the unit's /opt/fog-driver one."""
    path = Path(sys.executable).with_name("fog-driver")
    assert path.is_file(), f"{path}: the tests need the package installed in their virtual environment"
    return path


def test_the_unit_and_the_example_config_fit_together():
    unit = parse_unit(UNIT.read_text(encoding="utf-8"))
    assert set(unit) == {"Unit", "Service"}
    assert "%i" in unit["Unit"]["Description"][0] and unit["Unit"]["StartLimitIntervalSec"] == ["0"]
    service = unit_service_keys()
    assert service["Type"] == "notify"
    assert service["ExecStart"] == f"{INSTALLED_FOG_DRIVER} run --config /etc/fog-driver/%i.yaml"
    assert (service["User"], service["Group"], service["SupplementaryGroups"]) == (
        "fog-driver",
        "fog-driver",
        "dialout",
    )
    assert service["StateDirectory"] == "fog-driver" and service["StateDirectoryMode"] == "0750"
    assert service["WorkingDirectory"] == service["ReadWritePaths"] == STATE_DIRECTORY
    assert service["UMask"] == "0027"
    assert service["Restart"] == "on-failure"
    assert service["RestartPreventExitStatus"].split() == ["64", "78"]  # a bad config or model; a missing extra
    assert service["KillSignal"] == "SIGTERM" and float(service["TimeoutStopSec"]) > DAEMON_SHUTDOWN_BUDGET_S
    assert (service["NoNewPrivileges"], service["ProtectSystem"], service["PrivateTmp"]) == ("yes", "strict", "yes")
    assert "PrivateDevices" not in service and "DevicePolicy" not in service  # they would hide the serial port

    config = load_config(EXAMPLE_CONFIG)
    assert config.port  # with none the daemon exits 78 under systemd
    assert Path(config.capture_dir).is_absolute() and Path(config.capture_dir).is_relative_to(STATE_DIRECTORY)
    assert config.adapt_state is None  # documented, commented out, below the state directory too
    assert f"adapt_state: {STATE_DIRECTORY}/{INSTANCE}/" in EXAMPLE_CONFIG.read_text()
    assert config.status_every_s <= float(service["WatchdogSec"]) / 2


def test_systemd_analyze_verifies_the_unit(tmp_path):
    analyze = shutil.which("systemd-analyze")
    if analyze is None:
        message = "systemd-analyze is missing (apt-get install systemd); .ci/run installs it"
        if os.environ.get("CI"):
            pytest.fail(message)
        pytest.skip(message)
    # The only change: ExecStart names a binary that exists here (verify checks that it is executable).
    text = UNIT.read_text(encoding="utf-8").replace(
        f"ExecStart={INSTALLED_FOG_DRIVER} ", f"ExecStart={this_machines_fog_driver()} "
    )
    assert text != UNIT.read_text(encoding="utf-8")
    (tmp_path / UNIT.name).write_text(text, encoding="utf-8")
    proc = subprocess.run(
        [analyze, "verify", "--man=no", str(tmp_path / f"fog-driver@{INSTANCE}.service")],
        capture_output=True,
        text=True,
        timeout=GUARD_S,
    )
    about_the_unit = [line for line in (proc.stdout + proc.stderr).splitlines() if "fog-driver@" in line]
    assert proc.returncode == 0 and about_the_unit == [], proc.stdout + proc.stderr


def test_systemctl_reload_runs_the_units_exec_reload_and_the_daemon_reloads_its_config(tmp_path):
    """The review: `systemctl reload` was not defined (the unit had no ExecReload=).  Its command, as systemd
    runs it ($MAINPID the daemon's pid), makes the daemon read its config again: a new token closes every
    connection authorized by the old one ("the client token changed")."""
    from daemon_hil import Client, Daemon

    command = unit_service_keys()["ExecReload"]
    config = tmp_path / "fog.yaml"
    config.write_text("token: the-first-token\n")
    daemon = Daemon(tmp_path, f"replay://{DATA / 'sim-short.bin'}?rate=100", "--config", str(config))
    try:
        client = Client(daemon.address)
        client.next("VERSION")
        client.send('?AUTH={"token": "the-first-token"};')
        assert client.next("AUTH")["authorized"] is True
        config.write_text("token: the-second-token\n")
        argv = shlex.split(command.replace("$MAINPID", str(daemon.proc.pid)))
        assert subprocess.run(argv, capture_output=True, text=True, timeout=GUARD_S).returncode == 0
        error = client.next("ERROR")
        assert error["message"] == "the client token changed: connect again"
        assert daemon.proc.poll() is None  # reloaded, not stopped
        assert daemon.terminate() == 0
    finally:
        daemon.kill()


def test_the_units_command_with_the_example_config_gets_ready_and_stops_cleanly(tmp_path):
    """ExecStart= exactly, with the unit's Environment=, UMask= and working directory, the example config
    copied with its paths moved into a temporary root and a replay port: READY=1, WATCHDOG=1 and STOPPING=1
    on the notify socket, exit 0 on SIGTERM, and everything written below the (mapped) state directory."""
    service = unit_service_keys()
    root = tmp_path / "root"
    state = root / STATE_DIRECTORY.lstrip("/")
    state.mkdir(parents=True, mode=int(service["StateDirectoryMode"], 8))  # what StateDirectory= makes

    config_doc = yaml.safe_load(EXAMPLE_CONFIG.read_text().replace(STATE_DIRECTORY, str(state)))
    config_doc.update(port=f"replay://{DATA / 'sim-short.bin'}?rate=100", listen="127.0.0.1:0")
    argv = shlex.split(service["ExecStart"].replace("%i", INSTANCE))
    assert argv[0] == INSTALLED_FOG_DRIVER
    argv[0] = str(this_machines_fog_driver())
    for k, arg in enumerate(argv):
        if arg.startswith("/etc/fog-driver/"):
            argv[k] = str(root / arg.lstrip("/"))
            Path(argv[k]).parent.mkdir(parents=True, exist_ok=True)
            Path(argv[k]).write_text(yaml.safe_dump(config_doc))
    assert argv[1:3] == ["run", "--config"] and Path(argv[3]).is_file()

    notify_dir = Path(tempfile.mkdtemp(prefix="fog-notify-"))  # short: an AF_UNIX path has at most 107 bytes
    notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    try:
        notify.bind(str(notify_dir / "notify"))
        notify.settimeout(GUARD_S)
        env = {
            "PATH": SYSTEMD_PATH,
            "HOME": str(state),
            "NOTIFY_SOCKET": str(notify_dir / "notify"),
            "WATCHDOG_USEC": str(int(service["WatchdogSec"]) * 1_000_000),
        }
        for assignment in shlex.split(service["Environment"]):
            key, value = assignment.split("=", 1)
            env[key] = value
        messages: list[str] = []

        def wait_for(wanted: str) -> None:
            """Read notify datagrams until one has the line ``wanted`` (socket.timeout after GUARD_S)."""
            while not messages or wanted not in messages[-1].split("\n"):
                messages.append(notify.recv(4096).decode())

        with daemon_process(
            argv, cwd=state, log=tmp_path / "daemon.log", env=env, umask=int(service["UMask"], 8)
        ) as proc:
            wait_for("READY=1")
            wait_for("WATCHDOG=1")
            proc.send_signal(signal.SIGTERM)
            assert proc.wait(GUARD_S) == 0, (tmp_path / "daemon.log").read_text()[-5000:]
        wait_for("STOPPING=1")
    finally:
        notify.close()
        shutil.rmtree(notify_dir)
    captures = state / INSTANCE / "captures"
    assert captures.is_dir() and stat.S_IMODE(captures.stat().st_mode) == 0o750
    files = sorted(str(p.relative_to(root)) for p in root.rglob("*") if not p.is_dir())
    assert files[0] == f"etc/fog-driver/{INSTANCE}.yaml"  # the config, then what the daemon wrote:
    assert all(p.startswith(f"{STATE_DIRECTORY.lstrip('/')}/{INSTANCE}/captures/") for p in files[1:]), files
    assert all(stat.S_IMODE((root / p).stat().st_mode) == 0o640 for p in files[1:])  # UMask=0027


def _read_terminal(fd: int, until: Callable[[str], bool], guard_s: float = GUARD_S) -> str:
    """What a terminal shows from ``fd`` (a pty's master) until ``until(text)`` or the far end closes."""
    text = ""
    deadline = time.monotonic() + guard_s
    while not until(text):
        left = deadline - time.monotonic()
        assert left > 0, f"the terminal showed, within {guard_s} s: {text!r}"
        ready, _, _ = select.select([fd], [], [], left)
        if not ready:
            continue
        try:
            data = os.read(fd, 4096)
        except OSError:  # EIO: every holder of the pty's other end has closed it
            break
        if not data:
            break
        text += data.decode("utf-8", "replace")
    return text


def test_on_a_terminal_the_banner_comes_first_and_ctrl_c_stops_quietly(tmp_path):
    """The review: at a terminal, JSON log lines came before the banner, a status line each second pushed
    it away, and Ctrl-C logged two warnings (port lost).  Now: the banner is the first thing on screen,
    nothing follows it without ``-v``, and Ctrl-C ends with exit 0 and no warning or error."""
    terminal, terminal_peer = os.openpty()
    try:
        proc = subprocess.Popen(
            _run_command("--simulate", "--capture-dir", "c"),
            cwd=tmp_path,
            stdin=terminal_peer,
            stdout=terminal_peer,
            stderr=terminal_peer,
            start_new_session=True,
        )
        os.close(terminal_peer)
        try:
            shown = _read_terminal(terminal, lambda text: "(Ctrl-C to stop)" in text)
            os.killpg(proc.pid, signal.SIGINT)  # what the terminal sends on Ctrl-C: the whole foreground group
            assert proc.wait(GUARD_S) == 0
            shown += _read_terminal(terminal, lambda text: False)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait(GUARD_S)
    finally:
        os.close(terminal)
    lines = [line for line in shown.replace("\r", "").splitlines() if line.strip()]
    assert lines[0].startswith("fog-driver ") and "connect with: fog-driver watch" in lines[0], lines
    assert not [line for line in lines if line.lstrip().startswith("{")], lines  # no JSON at a terminal
    assert not [line for line in lines[1:] if " warning " in line or " error " in line or "port_state" in line], lines
