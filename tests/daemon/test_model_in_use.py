"""Which model the daemon runs, in every place a station looks (the review's finding 3: ``run --model
model.yaml``, then nothing but ``ctl reload`` named the file; VERSION said ``"model":"wesn"`` as for the shipped
default): the start-up line, STATUS, VERSION (after ``?AUTH`` on a daemon with a token), ``ctl status``,
``watch``'s header, the web page and ``/metrics``; after ``ctl reload`` and after SIGHUP, the new model in each.

A daemon (``fog-driver run``) reads a recorded capture through ``replay://``.  What each place shows is compared
with the model file itself: its absolute path, ``hashlib.sha256`` of its bytes, and its kind, fit date and
serial read with ``yaml.safe_load``.  Readiness: the daemon's start-up line and the protocol's own answers
(each ``?STATUS`` answered after the one before); the web view's STATUS is read after the NDJSON client got the
next one (both are published by the same thread, in order).  No sleeps.
"""

from __future__ import annotations

import asyncio
import hashlib
import json
import os
import re
import select
import shutil
import signal
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest
import yaml
from daemon_hil import GUARD_S, Client, Daemon
from web_helpers import check_exposition

from fog_driver.cli import main
from fog_driver.client import AsyncClient as AsyncStationClient
from fog_driver.client import Client as StationClient
from fog_driver.client import ModelInUse
from fog_driver.daemon.config import DEFAULT_MODEL
from fog_driver.tools.render import render

DATA = Path(__file__).resolve().parents[1] / "data"
PORT = f"replay://{DATA / 'sim-short.bin'}?rate=10"  # 300 s of samples: more than the test takes
TOKEN = "a-long-token-for-the-model"


def expected(path: Path) -> dict[str, str]:
    """The model file as every place must name it, from the file itself."""
    doc = yaml.safe_load(path.read_text())
    return {
        "path": os.path.abspath(path),
        "sha256": hashlib.sha256(path.read_bytes()).hexdigest(),
        "kind": doc["kind"],
        "created_utc": doc["created_utc"],
        "serial": doc["instrument_serial"],
    }


def described(model: dict[str, str]) -> str:
    """The one line ``ctl status``, ``watch`` and the web page give the model."""
    return f"{model['path']} ({model['kind']}, fitted {model['created_utc']}, for {model['serial']})"


def address(daemon: Daemon) -> str:
    return f"{daemon.address[0]}:{daemon.address[1]}"


def web_url(daemon: Daemon) -> str:
    return re.search(r"web view on (http://\S+/)", daemon.readiness).group(1)


def polynomial_model(path: Path) -> Path:
    from fog_driver.compensation.fitting.data import FitConfig
    from fog_driver.modelfiles import save_model
    from fog_driver.offline.fit import fit_model_file

    model_file, _ = fit_model_file(
        [DATA / "sim-short.bin"], kind="polynomial", config=FitConfig(warmup_s=30.0), accept_weak=True
    )
    return save_model(path, model_file)


def status_naming(client: Client, path: str) -> dict:
    """``?STATUS`` again and again (each answered after the one before) until its model is the file at ``path``:
    a SIGHUP's reload runs in the daemon's signal thread."""
    for _ in range(10000):
        client.send("?STATUS;")
        status = client.next("STATUS")
        if status["model_file"]["path"] == path:
            return status
    pytest.fail(f"no STATUS named {path}")


def check_everywhere(daemon: Daemon, client: Client, capsys, model: dict[str, str]) -> None:
    """STATUS, VERSION (raw and typed), ``ctl status``, ``watch``, the web page and ``/metrics`` name ``model``.

    STATUS first, until one names ``model``: the periodic STATUS lines sent before the swap may still be queued
    to this client (``status_every_s``), and the swap lands between two chunks."""
    for _ in range(100):
        client.send("?STATUS;")
        if (status := client.next("STATUS"))["model_file"] == model:
            break
    assert status["model_file"] == model
    client.send("?VERSION;")
    version = client.next("VERSION")
    assert version["model_file"] == model and version["model"] == model["kind"]  # "model" kept for old clients
    with StationClient(daemon.address, reconnect=False) as station:
        assert station.version.model_file == ModelInUse(**model)
        assert station.status().model_file == ModelInUse(**model)

    assert main(["ctl", "--connect", address(daemon), "status"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("port ")
    assert lines[1:] == [f"model {described(model)}", f"sha256: {model['sha256']}"]

    assert main(["watch", address(daemon), "--count", "1"]) == 0  # piped: a line names the model
    shown = capsys.readouterr().out.splitlines()
    assert f"model {described(model)}  sha256 {model['sha256'][:12]}" in shown, shown

    # the web page's STATUS: the one after the STATUS that named the model has reached the view
    while client.next("STATUS")["model_file"] != model:
        pass
    client.next("STATUS")
    with urllib.request.urlopen(web_url(daemon) + "api/view", timeout=GUARD_S) as answer:
        page = json.load(answer)
    assert page["text"]["model"] == described(model) and page["text"]["model_sha256"] == model["sha256"]
    assert page["status"]["model_file"] == model

    with urllib.request.urlopen(web_url(daemon) + "metrics", timeout=GUARD_S) as answer:
        families = check_exposition(answer.read().decode())
    (info,) = [s for f in families for s in f.samples if s.name == "fog_driver_model_info"]
    assert info.labels == model and info.value == 1.0


class Watching:
    """``fog-driver watch`` piped, left running: the model lines it prints as they come."""

    def __init__(self, daemon: Daemon) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "fog_driver", "watch", address(daemon)],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            stdin=subprocess.DEVNULL,
            text=True,
        )
        self.lines: list[str] = []

    def model_line(self, model: dict[str, str]) -> None:
        """Read its output until the line naming ``model`` (GUARD_S at most)."""
        line = f"model {described(model)}  sha256 {model['sha256'][:12]}"
        deadline = time.monotonic() + GUARD_S
        while line not in self.lines:
            assert time.monotonic() < deadline, f"watch never printed {line!r}: {self.lines[-20:]}"
            if select.select([self.proc.stdout], [], [], 0.5)[0]:
                self.lines.append(self.proc.stdout.readline().rstrip("\n"))

    def stop(self) -> None:
        self.proc.kill()
        self.proc.communicate(timeout=GUARD_S)


def test_a_station_sees_the_model_file_everywhere_and_the_new_one_after_ctl_reload_and_sighup(tmp_path, capsys):
    model_path = tmp_path / "models" / "model.yaml"
    model_path.parent.mkdir()
    shutil.copy(DEFAULT_MODEL, model_path)
    config = tmp_path / "fog.yaml"
    config.write_text(f"model: {model_path}\nstatus_every_s: 0.2\n")
    daemon = Daemon(tmp_path, PORT, "--config", str(config), "--http", "127.0.0.1:0")
    watching = None
    try:
        first = expected(model_path)
        line = daemon.readiness.rstrip("\n")
        assert f"; model {first['path']} (fitted for {first['serial']}); " in line, line
        ndjson = address(daemon)
        assert f"connect with: fog-driver watch {ndjson} or fog-driver ctl {ndjson} status" in line, line
        assert line.endswith("  (Ctrl-C to stop)")
        client = Client(daemon.address)
        assert client.next("VERSION")["model_file"] == first  # the greeting
        watching = Watching(daemon)
        watching.model_line(first)
        check_everywhere(daemon, client, capsys, first)

        # another model written over the same file, then `ctl reload`
        polynomial_model(model_path)
        second = expected(model_path)
        assert second["kind"] == "polynomial" and second["sha256"] != first["sha256"]
        assert main(["ctl", "--connect", ndjson, "reload"]) == 0
        assert capsys.readouterr().out.startswith("reloaded the model: polynomial")
        check_everywhere(daemon, client, capsys, second)
        watching.model_line(second)  # the watch that was running says so too

        # the config names another file, then SIGHUP
        other = tmp_path / "models" / "other.yaml"
        shutil.copy(DEFAULT_MODEL, other)
        config.write_text(f"model: {other}\nstatus_every_s: 0.2\n")
        daemon.proc.send_signal(signal.SIGHUP)
        third = expected(other)
        assert status_naming(client, third["path"])["model_file"] == third
        check_everywhere(daemon, client, capsys, third)
        watching.model_line(third)
        assert daemon.terminate() == 0
    finally:
        if watching is not None:
            watching.stop()
        daemon.kill()


def test_version_names_the_model_file_only_after_auth_on_a_daemon_with_a_token_and_a_station_sees_it(tmp_path, capsys):
    """Like the instrument's serial: a client without the token gets the release and protocol only; after
    ``?AUTH`` VERSION names the model (here the shipped default, by its real path)."""
    config = tmp_path / "fog.yaml"
    config.write_text(f"token: {TOKEN}\n")
    daemon = Daemon(tmp_path, PORT, "--config", str(config))
    try:
        shipped = expected(DEFAULT_MODEL)
        assert Path(shipped["path"]).is_file() and shipped["path"].endswith("fog_driver/data/models/default.yaml")
        assert f"; model {shipped['path']} (fitted for {shipped['serial']}); " in daemon.readiness
        client = Client(daemon.address)
        greeting = client.next("VERSION")
        assert set(greeting) == {"class", "release", "proto_major", "proto_minor"}
        client.send("?VERSION;")
        assert "model_file" not in client.next("VERSION")
        client.send(f'?AUTH={{"token":"{TOKEN}"}};')
        client.next("AUTH")
        client.send("?VERSION;")
        assert client.next("VERSION")["model_file"] == shipped
        client.send("?STATUS;")
        assert client.next("STATUS")["model_file"] == shipped
        # the client libraries ask for VERSION again after ?AUTH: the greeting before it held the release only
        with StationClient(daemon.address, token=TOKEN, reconnect=False) as station:
            assert station.version.model_file == ModelInUse(**shipped)
            assert station.version.instrument is not None
            assert station.status().model_file == ModelInUse(**shipped)

        async def station_async():
            async with AsyncStationClient(daemon.address, token=TOKEN, reconnect=False) as station:
                return station.version

        version = asyncio.run(station_async())
        assert version.model_file == ModelInUse(**shipped) and version.instrument is not None
        assert daemon.terminate() == 0
    finally:
        daemon.kill()


def test_watchs_terminal_header_names_the_model_statuss_over_the_greetings():
    """The block on a terminal: the model line under the instrument's, from STATUS (a reload shows in the next
    one), else from VERSION; ``-`` from a daemon before protocol 1.2."""
    greeted = expected(DEFAULT_MODEL)
    reloaded = {**greeted, "path": "/etc/fog-driver/new.yaml", "sha256": "f" * 64, "kind": "polynomial"}
    version = {"class": "VERSION", "release": "0.1.0", "proto_major": 1, "proto_minor": 2, "model_file": greeted}
    for status, model in (({}, greeted), ({"class": "STATUS", "model_file": reloaded}, reloaded)):
        lines = render({"address": "127.0.0.1:2948", "version": version, "status": status}, width=400)
        assert lines[2] == f"model       {described(model)}  sha256 {model['sha256'][:12]}", lines
    lines = render({"address": "127.0.0.1:2948", "version": {"proto_major": 1, "proto_minor": 1}}, width=400)
    assert lines[2] == "model       -"


@pytest.mark.serial  # a browser
def test_the_web_page_shows_the_model_and_the_new_one_after_a_reload(tmp_path):
    from playwright.sync_api import expect, sync_playwright
    from web_helpers import WAIT_MS, open_page

    from fog_driver.daemon.web.server import WebView

    first = expected(DEFAULT_MODEL)
    second = {**first, "path": "/etc/fog-driver/new model.yaml", "sha256": "0" * 64, "kind": "polynomial"}
    view = WebView("127.0.0.1", 0, update_hz=10.0)
    view.start()
    problems: list[str] = []
    try:
        view.publish({"class": "VERSION", "release": "0.1.0", "model": "wesn", "model_file": first})
        view.publish({"class": "STATUS", "port_state": "open", "model_file": first})
        host, port = view.address
        with sync_playwright() as p:
            browser, page = open_page(p, problems)
            page.goto(f"http://{host}:{port}/")
            expect(page.locator("#model")).to_have_text(described(first), timeout=WAIT_MS)
            expect(page.locator("#model-sha256")).to_have_text(first["sha256"])
            view.publish({"class": "STATUS", "port_state": "open", "model_file": second})  # the STATUS after a reload
            expect(page.locator("#model")).to_have_text(described(second), timeout=WAIT_MS)
            expect(page.locator("#model-sha256")).to_have_text(second["sha256"])
            page.screenshot(path=str(tmp_path / "web-view-model.png"), full_page=True)
            browser.close()
    finally:
        view.stop()
    assert problems == [], problems


def test_on_an_80x24_terminal_the_model_line_leaves_the_keys_and_the_last_key_on_screen():
    """The model line (two lines at 80 columns) pushed the last key's outcome and the keys off a 24-line
    terminal: ``b``'s "bias captured" was never seen.  A block that does not fit loses the end of its STATUS
    counters instead, and says how many lines of them."""
    model = expected(DEFAULT_MODEL)
    status = {"class": "STATUS", "model_file": model, **{f"counter_{i:02d}": i for i in range(60)}}
    state = {
        "address": "127.0.0.1:2948",
        "version": {"proto_major": 1, "proto_minor": 2, "model_file": model},
        "status": status,
        "angle": {"seq": 1, "t_s": 1.0, "angle_arcsec": 1.0, "angle_raw_arcsec": 1.0, "flags": []},
        "action": "bias captured: 10.2883 deg/h over 60.0 s, removed from rate and angle from now on",
        "keys": True,
    }
    whole = render(state, width=79)
    lines = render(state, width=79, height=23)
    assert len(whole) > 23 and len(lines) == 23
    (cut,) = [i for i, line in enumerate(lines) if "more line(s) of counters" in line]
    hidden = int(re.search(r"\.\.\. (\d+) more line\(s\) of counters", lines[cut]).group(1))
    tail = lines[cut + 1 :]
    assert tail == whole[len(whole) - len(tail) :]  # the last key's outcome and the keys, whole
    assert tail[0].startswith("last key") and tail[-1].startswith("keys")
    assert lines[:cut] == whole[:cut]  # everything above the cut as it was, the model's lines included
    assert [line for line in lines if line.startswith("model")][0].startswith(f"model       {model['path']} (")
    assert hidden == len(whole) - len(tail) - cut  # the counters' lines it left out, counted right
