"""``fog-driver ctl`` and ``?BIAS`` against a real daemon (``fog-driver run`` on a pty, test_daemon_faults'
fixtures): every command with and without a token, ``?BIAS`` acknowledged at once with its result as an event
later, other commands answered meanwhile, a client that hangs up mid-capture.  Readiness from the daemon's own
lines (its readiness line, DEVICE activated, the ctl's printed acknowledgement), never sleeps; every wait is
bounded by GUARD_S."""

from __future__ import annotations

import io
import json
import math
import subprocess
import sys

import pytest
from daemon_hil import GUARD_S, N_SHORT, SHORT, Client, Daemon, next_status, watch_all, watched_daemon

from fog_driver.cli import main
from fog_driver.errors import UsageError
from fog_driver.protocol import decode_bytes
from fog_driver.tools.ctl import describe, parse_request, run_ctl
from fog_driver.transport import PtyPair

TOKEN = "a-long-token-for-ctl"
HEAD = 20000  # the bytes written before the commands: the daemon has a compensator
N_HEAD = decode_bytes(SHORT[:HEAD], final=False).counters.sample_frames


def ctl(capsys, daemon: Daemon, *args: str) -> tuple[int, str, str]:
    """``fog-driver ctl --connect ADDRESS ARGS...`` in this process: (exit status, stdout, stderr)."""
    host, port = daemon.address
    status = main(["ctl", "--connect", f"{host}:{port}", *args])
    out, err = capsys.readouterr()
    return status, out, err


def ctl_process(daemon: Daemon, *args: str, env: dict | None = None) -> subprocess.Popen:
    host, port = daemon.address
    return subprocess.Popen(
        [sys.executable, "-m", "fog_driver", "ctl", "--connect", f"{host}:{port}", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        stdin=subprocess.DEVNULL,
        env=env,
    )


def test_ctl_zero_adapt_reload_status_save(tmp_path, capsys):
    with watched_daemon(tmp_path) as (pty, daemon, client):
        pty.write(SHORT[:HEAD])
        watch_all(client, N_HEAD)
        status, out, err = ctl(capsys, daemon, "status")
        assert status == 0 and err == "" and len(out.splitlines()) == 3  # the state, the model, its SHA-256
        assert "port open" in out and "bias 0.0000 deg/h (not captured)" in out and "adapting no" in out
        assert ctl(capsys, daemon, "zero")[:2] == (0, "zeroed: the published angle starts again from 0 here\n")
        assert ctl(capsys, daemon, "adapt", "on")[0] == 0
        status, out, _ = ctl(capsys, daemon, "reload")
        assert status == 0 and out.startswith("model unchanged (wesn")
        status, out, _ = ctl(capsys, daemon, "--json", "status")
        reply = json.loads(out)
        # the review's finding 10: ?RELOAD switched off a client's ?ADAPT; it is kept now
        assert status == 0 and reply["class"] == "STATUS" and reply["adapting"] is True
        assert reply["bias_captured"] is False
        assert ctl(capsys, daemon, "adapt", "off")[:2] == (0, "adaptation off: the weights are frozen\n")
        status, out, err = ctl(capsys, daemon, "table", "36", "--dwell", "12")  # no data since the zero
        assert status == 65 and out == "" and "reaches back past a break in the data" in err
        status, out, err = ctl(capsys, daemon, "save")  # no adapt_state configured: refused, 65
        assert (status, out) == (65, "") and err == "fog-driver: error: ?SAVE refused: no adapt_state file configured\n"
        pty.write(SHORT[HEAD:])
        angles = watch_all(client, N_SHORT - N_HEAD)
        assert abs(angles[0]["angle_arcsec"]) < 5.0  # zeroed
        status, out, err = ctl(capsys, daemon, "table", "36", "--dwell", "12")
        assert status == 0 and out.startswith("table angle 36 deg taken for the dwell ") and err == "", err
        assert ctl(capsys, daemon, "adapt", "off")[0] == 0  # ends adapting from table angles too
        assert daemon.terminate() == 0


def test_ctl_with_a_token(tmp_path, capsys, monkeypatch):
    config = tmp_path / "fog.yaml"
    config.write_text(f"token: {TOKEN}\n")
    token_file = tmp_path / "token"
    token_file.write_text(TOKEN + "\n")
    with PtyPair() as pty:
        daemon = Daemon(tmp_path, pty.slave_path, "--config", str(config))
        try:
            monkeypatch.delenv("FOG_DRIVER_TOKEN", raising=False)
            status, out, err = ctl(capsys, daemon, "zero")
            assert (status, out) == (77, "")
            assert (
                err
                == "fog-driver: error: the daemon needs a token for ?ZERO: set FOG_DRIVER_TOKEN or give --token-file\n"
            )
            monkeypatch.setenv("FOG_DRIVER_TOKEN", "not-the-token")
            status, _, err = ctl(capsys, daemon, "status")
            assert status == 77 and err == "fog-driver: error: the daemon refused the token: bad token\n"
            monkeypatch.setenv("FOG_DRIVER_TOKEN", TOKEN)
            assert ctl(capsys, daemon, "status")[0] == 0
            monkeypatch.delenv("FOG_DRIVER_TOKEN")
            assert ctl(capsys, daemon, "--token-file", str(token_file), "reload")[0] == 0
            status, _, err = ctl(capsys, daemon, "--token-file", str(tmp_path / "none"), "status")
            assert status == 65 and "cannot read the token file" in err
            assert daemon.terminate() == 0
        finally:
            daemon.kill()


def test_bias_is_acknowledged_at_once_and_its_result_is_an_event(tmp_path):
    """The review's finding 10: ?BIAS answered only after its N seconds, and every later command on the
    connection (even an invalid one) waited as long."""
    with watched_daemon(tmp_path) as (pty, daemon, watcher):
        pty.write(SHORT[:HEAD])
        watch_all(watcher, N_HEAD)
        operator = Client(daemon.address)
        operator.send('?BIAS={"seconds":3};')
        started = operator.next("BIAS")  # no more data has been written: the capture cannot have completed
        assert started["state"] == "started" and started["seconds"] == 3 and started["timeout_s"] == 33
        operator.send("?NOPE;")
        assert operator.next("ERROR")["command"] == "NOPE"  # answered meanwhile
        operator.send("?ZERO;")
        assert operator.next("ZERO") == {"class": "ZERO", "zeroed": True}
        operator.send('?BIAS={"seconds":3};')
        assert operator.next("ERROR")["message"] == "a bias capture is already running"
        status = next_status(operator, lambda s: "bias_capture_target_s" in s, "the capture's progress")
        assert status["bias_capture_target_s"] == 3 and status["bias_capture_s"] == 0 and not status["bias_captured"]
        pty.write(SHORT[HEAD:])  # now the 3 s of data
        done = operator.next("BIAS")
        assert done["state"] == "done" and done["capture_id"] == started["capture_id"] and 5 < done["bias_dph"] < 15
        assert watcher.next("BIAS") == done  # every authorized client gets the event
        assert next_status(operator, lambda s: s["bias_captured"], "bias_captured")["bias_dph"] == done["bias_dph"]
        assert daemon.terminate() == 0


def test_ctl_bias_waits_for_the_result(tmp_path):
    with watched_daemon(tmp_path) as (pty, daemon, client):
        pty.write(SHORT[:HEAD])
        watch_all(client, N_HEAD)
        proc = ctl_process(daemon, "bias", "3")
        try:
            first = proc.stdout.readline()  # the acknowledgement: the capture runs
            assert first.startswith("bias capture started: 3 s of data"), (first, proc.stderr.read())
            pty.write(SHORT[HEAD:])
            out, err = proc.communicate(timeout=GUARD_S)
        finally:
            proc.kill()
        assert proc.returncode == 0 and err == ""
        assert out.startswith("bias captured: ") and "deg/h over 3.0 s" in out and len(out.splitlines()) == 1
        assert daemon.terminate() == 0


def test_ctl_on_a_daemon_that_is_not_there_is_one_line_and_69(tmp_path):
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))  # bound, never listening: refuses connections
        port = s.getsockname()[1]
        proc = subprocess.run(
            [sys.executable, "-m", "fog_driver", "ctl", "--connect", f"127.0.0.1:{port}", "zero"],
            capture_output=True,
            text=True,
            timeout=GUARD_S,
            stdin=subprocess.DEVNULL,
        )
    assert proc.returncode == 69 and proc.stdout == ""
    assert proc.stderr == (
        f"fog-driver: error: could not connect to 127.0.0.1:{port}: Connection refused (is `fog-driver run` running?)\n"
    )


@pytest.mark.parametrize(
    ("command", "words", "expected"),
    [
        ("zero", [], ("ZERO", None)),
        ("bias", [], ("BIAS", {"seconds": 60})),
        ("bias", ["2.5"], ("BIAS", {"seconds": 2.5})),
        ("adapt", ["on"], ("ADAPT", {"enable": True, "reference_dph": 0.0})),
        ("adapt", ["off"], ("ADAPT", {"enable": False})),
        ("reload", [], ("RELOAD", None)),
        ("status", [], ("STATUS", None)),
        ("save", [], ("SAVE", None)),
        ("table", ["-36"], ("TABLE", {"angle_deg": -36.0, "dwell_s": 12.0})),
    ],
)
def test_parse_request(command, words, expected):
    assert parse_request(command, words) == expected


def test_a_bias_result_names_the_drift_sigma_when_the_daemon_gives_one():
    done = {"class": "BIAS", "state": "done", "capture_id": 1, "bias_dph": 10.543, "seconds": 60.0}
    plain = "bias captured: 10.5430 deg/h over 60.0 s; removed from rate_dph and angle_arcsec from now on"
    assert describe(done) == plain  # protocol 1.0, or no sigma during the capture
    assert describe({**done, "bias_sigma_dph": 0.01234}) == plain.replace(
        " s;", " s (the drift's 1-sigma then 0.0123 deg/h);"
    )


@pytest.mark.parametrize(
    ("command", "words"),
    [
        ("bias", ["0"]),
        ("bias", ["1e9"]),
        ("bias", ["nan"]),
        ("bias", ["x"]),
        ("bias", ["1", "2"]),
        ("adapt", []),
        ("adapt", ["yes"]),
        ("zero", ["1"]),
        ("nope", []),
        ("table", []),
        ("table", ["x"]),
        ("table", ["nan"]),
        ("table", ["1e7"]),
        ("table", ["1", "2"]),
    ],
)
def test_parse_request_refuses(command, words):
    with pytest.raises(UsageError):
        parse_request(command, words)


def test_parse_request_table_options():
    assert parse_request("table", ["36"], dwell_s=60, angle_start_deg=35.9) == (
        "TABLE",
        {"angle_deg": 36.0, "dwell_s": 60.0, "angle_start_deg": 35.9},
    )
    for bad in ({"dwell_s": 5}, {"dwell_s": math.inf}, {"angle_start_deg": math.nan}):
        with pytest.raises(UsageError):
            parse_request("table", ["36"], **bad)
    with pytest.raises(UsageError, match="go with `table` only"):
        parse_request("zero", [], dwell_s=60)


def test_ctl_takes_the_daemons_address_as_watch_does(tmp_path, capsys):
    """The review's finding 10: ``fog-driver ctl 127.0.0.1:13014 status`` said ``invalid choice``; ``watch`` takes
    the address as its first word.  A first word that is not a command is the address; ``--connect`` still
    works, and both forms give the same answer."""
    with watched_daemon(tmp_path) as (pty, daemon, client):
        pty.write(SHORT[:HEAD])
        watch_all(client, N_HEAD)
        host, port = daemon.address
        status, out, err = run_main(capsys, "ctl", "--json", f"{host}:{port}", "status")
        assert (status, err) == (0, "") and json.loads(out)["class"] == "STATUS"
        assert run_main(capsys, "ctl", f"{host}:{port}", "zero")[:2] == (
            0,
            "zeroed: the published angle starts again from 0 here\n",
        )
        assert run_main(capsys, "ctl", f"{host}:{port}", "adapt", "on")[:2] == ctl(capsys, daemon, "adapt", "on")[:2]
        assert run_main(capsys, "ctl", f"{host}:{port}", "adapt", "off")[:2] == (
            0,
            "adaptation off: the weights are frozen\n",
        )
        assert ctl(capsys, daemon, "zero")[:2] == run_main(capsys, "ctl", f"{host}:{port}", "zero")[:2]
        assert daemon.terminate() == 0


def run_main(capsys, *args: str) -> tuple[int, str, str]:
    status = main(list(args))
    out, err = capsys.readouterr()
    return status, out, err


COMMAND_NAMES = "zero, bias, adapt, table, reload, status, save"


@pytest.mark.parametrize(
    ("words", "message"),
    [
        (["stauts"], f"'stauts' is not a command ({COMMAND_NAMES}), and no command follows it"),
        (["bais", "60"], f"neither 'bais' nor '60' is a command ({COMMAND_NAMES})"),
        (
            ["127.0.0.1:99999", "status"],
            f"'127.0.0.1:99999': port 99999 is out of range (and not a command: {COMMAND_NAMES})",
        ),
        (["foo:bar", "zero"], f"'foo:bar': port 'bar' is not a number (and not a command: {COMMAND_NAMES})"),
        (
            ["--connect", "127.0.0.1:1", "127.0.0.1:2", "zero"],
            "the daemon's address given twice: '127.0.0.1:2' and --connect 127.0.0.1:1",
        ),
    ],
)
def test_ctl_with_a_first_word_that_is_neither_a_command_nor_an_address_is_one_line_and_64(words, message):
    """Checked after argparse (its grammar cannot say ``[HOST:PORT] COMMAND``), so one line and 64, the exit of
    every other bad ctl argument (``bias abc``, ``adapt maybe``), never a connection attempt."""
    proc = subprocess.run(
        [sys.executable, "-m", "fog_driver", "ctl", *words],
        capture_output=True,
        text=True,
        timeout=GUARD_S,
        stdin=subprocess.DEVNULL,
    )
    assert (proc.returncode, proc.stdout) == (64, "")
    assert proc.stderr == f"fog-driver: error: {message}\n"


@pytest.mark.parametrize(
    ("timeout", "message"),
    [
        ("1e10", "an answer is waited for at most 86400 s (a day): '1e10'"),
        ("86400.5", "an answer is waited for at most 86400 s (a day): '86400.5'"),
        ("inf", "must be > 0 and finite: 'inf'"),
        ("nan", "must be > 0 and finite: 'nan'"),
        ("0", "must be > 0 and finite: '0'"),
    ],
)
def test_ctl_with_a_timeout_beyond_a_day_is_refused_before_connecting(capsys, timeout, message):
    """Finding 10: ``ctl --timeout 1e10 status`` ended in exit 70 (``OverflowError: timestamp out of range for
    platform time_t``, from ``select``); the timeout is > 0 and at most a day, checked by argparse (exit 2)."""
    with pytest.raises(SystemExit) as exc:
        main(["ctl", "--connect", "127.0.0.1:1", f"--timeout={timeout}", "status"])
    out, err = capsys.readouterr()
    assert exc.value.code == 2 and out == ""
    assert err.splitlines()[-1] == f"fog-driver ctl: error: argument --timeout: {message}"


@pytest.mark.parametrize("timeout_s", [86400.0, 1e10, math.inf])
def test_a_command_waiting_longer_than_select_can_wait_gets_its_answer(make_hub, timeout_s):
    """The longest ``--timeout`` (a day) and, through the library, 1e10 s and no limit at all: the answer comes
    (before: 1e10 s and infinity raised ``OverflowError`` out of ``select``, whatever the daemon answered)."""
    calls = []
    _, (host, port), _ = make_hub(control=lambda name, args, client: calls.append(name) or {"class": "ZERO"})
    out = io.StringIO()
    assert run_ctl(host, port, "ZERO", None, out=out, timeout_s=timeout_s) == 0
    assert out.getvalue() == "zeroed: the published angle starts again from 0 here\n" and calls == ["ZERO"]
