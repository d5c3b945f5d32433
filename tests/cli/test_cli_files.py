"""Files a user made are never overwritten without ``--force`` and never mistaken for another kind; inputs
are checked against each other; ``record`` does not wait for a port that never opened (issue 13)."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml
from cli_run import run_cli as cli

from fog_driver.daemon.rawlog import repair_interrupted
from fog_driver.samples.captures import read_provenance, sidecar_path, write_provenance

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT / "tests" / "data"
MODEL = ROOT / "fog_driver" / "data" / "models" / "default.yaml"
PROFILE = ROOT / "configs" / "profiles" / "short-test.yaml"


def started(*args: str, cwd: Path) -> subprocess.Popen:
    """``fog-driver ARGS`` running, its stdout and stderr piped (text), stdin closed."""
    return subprocess.Popen(
        [sys.executable, "-m", "fog_driver", *args],
        cwd=cwd,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def one_line(proc: subprocess.CompletedProcess, status: int) -> str:
    assert proc.returncode == status, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    return lines[0]


def simulate(cwd: Path, out: str, *extra: str, seconds: int = 60) -> subprocess.CompletedProcess:
    return cli(
        "simulate",
        "--profile",
        str(PROFILE),
        "--rate-hz",
        "10",
        "--duration",
        str(seconds),
        "--out",
        out,
        *extra,
        cwd=cwd,
    )


def digests(folder: Path) -> dict[str, str]:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in folder.iterdir() if p.is_file()}


# --- sidecar naming ------------------------------------------------------------------------------


def test_a_model_and_a_capture_can_share_a_stem(tmp_path):
    """Before: simulate --out mymodel.bin replaced the fitted model mymodel.yaml with its sidecar."""
    shutil.copy(MODEL, tmp_path / "run.yaml")
    model = (tmp_path / "run.yaml").read_bytes()
    proc = simulate(tmp_path, "run.bin")
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / "run.yaml").read_bytes() == model
    assert sidecar_path(tmp_path / "run.bin") == tmp_path / "run.bin.yaml"
    assert read_provenance(tmp_path / "run.bin")["source"] == "simulate"
    assert "run.bin.yaml" in proc.stdout
    # and the other way: a model named like the capture's stem is written beside it, the sidecar untouched
    side = (tmp_path / "run.bin.yaml").read_bytes()
    (tmp_path / "run.yaml").unlink()
    proc = cli("fit", "run.bin", "--out", "run.yaml", "--kind", "polynomial", "--accept-weak-fit", cwd=tmp_path)
    assert "exists" not in proc.stderr
    assert (tmp_path / "run.bin.yaml").read_bytes() == side


def test_an_old_named_sidecar_still_loads_and_a_model_there_is_not_taken_for_one(tmp_path):
    from fog_driver.samples.captures import find_sidecar, legacy_sidecar_path

    capture = tmp_path / "old.bin"
    shutil.copy(DATA / "sim-short.bin", capture)
    shutil.copy(DATA / "sim-short.bin.yaml", legacy_sidecar_path(capture))  # how captures were described before
    assert legacy_sidecar_path(capture) == tmp_path / "old.yaml"
    assert find_sidecar(capture) == tmp_path / "old.yaml"
    assert read_provenance(capture)["seed"] == 21
    assert "seed 21" in cli("inspect", "old.bin", cwd=tmp_path).stdout
    # the new name wins over the old one
    write_provenance(capture, {"source": "record", "seed": 5})
    assert find_sidecar(capture) == sidecar_path(capture) and read_provenance(capture)["seed"] == 5
    sidecar_path(capture).unlink()
    # a model (or anything not tagged as a sidecar) at the old name is not a sidecar
    for text in (MODEL.read_text(), "capture: [unclosed\n", "just text\n"):
        legacy_sidecar_path(capture).write_text(text)
        assert find_sidecar(capture) is None and read_provenance(capture) is None
    proc = cli("inspect", "old.bin", cwd=tmp_path)
    assert proc.returncode == 0 and "provenance    no sidecar" in proc.stdout


def test_repair_interrupted_fixes_old_and_new_sidecars_where_they_are(tmp_path):
    from fog_driver.samples.captures import legacy_sidecar_path

    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    for name, side in (("fog-000000-x.bin", legacy_sidecar_path), ("fog-000001-x.bin", sidecar_path)):
        capture = tmp_path / name
        capture.write_bytes(b"partial " + name.encode())
        write_provenance(capture, {"status": "recording", "pid": int(dead.stdout)}, sidecar=side(capture))
    (tmp_path / "fog-000002-x.bin").write_bytes(b"no sidecar")
    (tmp_path / "fog-000003-x.yaml").write_text(MODEL.read_text())  # a model, not a sidecar: left alone
    model = (tmp_path / "fog-000003-x.yaml").read_bytes()
    assert repair_interrupted(tmp_path) == [tmp_path / "fog-000000-x.bin", tmp_path / "fog-000001-x.bin"]
    assert not sidecar_path(tmp_path / "fog-000000-x.bin").exists()  # rewritten where it was: one sidecar
    for name in ("fog-000000-x.bin", "fog-000001-x.bin"):
        doc = read_provenance(tmp_path / name)
        assert doc["status"] == "interrupted" and doc["bytes"] == (tmp_path / name).stat().st_size
    assert (tmp_path / "fog-000003-x.yaml").read_bytes() == model


# --- nothing overwritten without --force; the message says what the file is --------------------


@pytest.fixture(scope="module")
def made(tmp_path_factory) -> Path:
    """A folder with a simulated capture (st.bin, st.bin.yaml, st.truth.csv: 240 s, long enough to evaluate
    past its warm-up), a model and a compensate CSV."""
    d = tmp_path_factory.mktemp("made")
    assert simulate(d, "st.bin", seconds=240).returncode == 0
    shutil.copy(MODEL, d / "model.yaml")
    shutil.copy(DATA / "sim-short.bin", d / "short.bin")
    proc = cli("compensate", "st.bin", "--model", "model.yaml", "--out", "st.csv", "--every", "10", cwd=d)
    assert proc.returncode == 0, proc.stderr
    shutil.copy(d / "st.csv.yaml", d / "st2.csv.yaml")  # a CSV's sidecar left behind, its CSV gone
    return d


@pytest.mark.parametrize(
    "args, kind",
    [
        (["fit", "short.bin", "--out", "st.bin.yaml"], "is a capture's provenance sidecar (of st.bin)"),
        (["fit", "short.bin", "--out", "st.truth.csv"], "is a simulator truth file"),
        (["fit", "short.bin", "--out", "model.yaml"], "is a fitted model"),
        (["compensate", "st.bin", "--model", "model.yaml", "--out", "st.csv"], "is a compensate CSV"),
        (
            ["compensate", "st.bin", "--model", "model.yaml", "--out", "st2.csv"],
            "st2.csv.yaml: exists and is a compensate CSV's provenance sidecar (of st.csv)",
        ),
        (
            [
                "compensate",
                "st.bin",
                "--model",
                "model.yaml",
                "--out",
                "x.csv",
                "--adapt-reference",
                "0",
                "--adapt-state",
                "model.yaml",
            ],
            "is a fitted model, not an adaptation state",
        ),
        (["simulate", "--profile", str(PROFILE), "--out", "st.bin"], "is a capture"),
        (["record", f"replay://{DATA / 'synthetic-clean.bin'}", "--out", "st.bin"], "is a capture"),
        (["evaluate", "st.bin", "--model", "model.yaml", "--out", "."], "is not empty"),
    ],
    ids=[
        "fit-sidecar",
        "fit-truth",
        "fit-model",
        "compensate-csv",
        "compensate-sidecar",
        "adapt-state-model",
        "simulate-capture",
        "record-capture",
        "evaluate-folder",
    ],
)
def test_existing_outputs_are_refused_naming_what_they_are(made, args, kind):
    before = digests(made)
    line = one_line(cli(*args, cwd=made), 73)
    assert kind in line and ("--force" in line or "adaptation state" in kind)
    assert digests(made) == before


def test_every_output_is_checked_before_any_is_written(tmp_path):
    """Before: simulate wrote run.bin and its truth, then found the sidecar name taken (or overwrote it)."""
    (tmp_path / "run.truth.csv").write_text("mine\n")
    line = one_line(simulate(tmp_path, "run.bin"), 73)
    assert "run.truth.csv: exists and is a file" in line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.truth.csv"]
    (tmp_path / "run.truth.csv").unlink()
    sidecar_path(tmp_path / "run.bin").write_text("format: fog_driver capture provenance\ncapture: run.bin\n")
    assert "is a capture's provenance sidecar (of run.bin)" in one_line(simulate(tmp_path, "run.bin"), 73)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.bin.yaml"]
    # with --force every output is replaced
    assert simulate(tmp_path, "run.bin", "--force").returncode == 0
    assert read_provenance(tmp_path / "run.bin")["source"] == "simulate"


def test_an_input_is_never_an_output_even_with_force(made):
    before = digests(made)
    line = one_line(cli("fit", "st.bin", "--out", "st.bin", "--force", cwd=made), 73)
    assert "is also an input" in line
    line = one_line(
        cli("compensate", "st.bin", "--model", "model.yaml", "--out", "model.yaml", "--force", cwd=made), 73
    )
    assert "is also an input" in line
    assert digests(made) == before


# --- inputs checked against each other ------------------------------------------------------------


def test_evaluate_refuses_the_truth_of_another_capture(made, tmp_path):
    assert simulate(tmp_path, "b.bin", "--seed", "3", seconds=240).returncode == 0
    shutil.copy(made / "st.truth.csv", tmp_path / "a.truth.csv")
    shutil.copy(made / "model.yaml", tmp_path / "model.yaml")
    base = ["evaluate", "b.bin", "--model", "model.yaml"]
    line = one_line(cli(*base, "--out", "r1", "--truth", "a.truth.csv", cwd=tmp_path), 65)
    assert "not the truth of b.bin: its sidecar names b.truth.csv" in line
    # a capture whose truth file is not beside it: its sidecar's frame count decides
    os.rename(tmp_path / "b.truth.csv", tmp_path / "b-own.csv")
    (tmp_path / "a.truth.csv").write_text("\n".join((made / "st.truth.csv").read_text().splitlines()[:32]) + "\n")
    line = one_line(cli(*base, "--out", "r2", "--truth", "a.truth.csv", cwd=tmp_path), 65)
    assert "30 s of truth, but b.bin holds 240 s (2,400 frames at 10 Hz" in line
    # no sidecar: the capture's own device time decides
    sidecar_path(tmp_path / "b.bin").unlink()
    line = one_line(cli(*base, "--out", "r3", "--truth", "a.truth.csv", cwd=tmp_path), 65)
    assert "30 s of truth, but b.bin holds 240 s of device time" in line
    assert not any((tmp_path / r).exists() for r in ("r1", "r2", "r3"))


def test_evaluate_refuses_reference_stops_outside_the_capture(made, tmp_path):
    stops = tmp_path / "stops.csv"
    stops.write_text("t_start_s,t_end_s,angle_deg\n10,20,0\n1500,1560,36\n")
    line = one_line(
        cli(
            "evaluate",
            "st.bin",
            "--model",
            "model.yaml",
            "--out",
            str(tmp_path / "r"),
            "--reference",
            str(stops),
            cwd=made,
        ),
        65,
    )
    assert "1 of 2 reference stops end after the capture does" in line and "240.0 s of device time" in line
    assert not (tmp_path / "r").exists()


def test_a_model_for_another_instrument_takes_force_model_never_force(made, tmp_path):
    """Before: ``--force`` both overwrote outputs and applied another instrument's model, silently; now
    ``--force-model`` (the daemon's ``force_model``) does the second, with a warning naming both serials."""
    other = tmp_path / "other.yaml"
    other.write_text(MODEL.read_text().replace("instrument_serial: FOG-SIM-0001", "instrument_serial: FOG-LAB-0042"))
    for command in (
        ["compensate", "st.bin", "--out", str(tmp_path / "c.csv")],
        ["evaluate", "st.bin", "--out", str(tmp_path / "r")],
    ):
        for force in ([], ["--force"]):
            line = one_line(cli(*command, "--model", str(other), *force, cwd=made), 64)
            assert "FOG-LAB-0042" in line and "FOG-SIM-0001" in line and "--force-model" in line, line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["other.yaml"]
    warning = (
        f"warning: --force-model: applying {other}, fitted for instrument 'FOG-LAB-0042', to st.bin, from "
        f"instrument 'FOG-SIM-0001'"
    )
    # compensate: the warning on stderr, and the use in the CSV's provenance sidecar
    proc = cli(
        "compensate", "st.bin", "--model", str(other), "--out", str(tmp_path / "c.csv"), "--force-model", cwd=made
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr.splitlines() == [warning]
    side = yaml.safe_load((tmp_path / "c.csv.yaml").read_text())
    assert side["settings"]["force_model"] is True and side["warnings"] == [warning.removeprefix("warning: ")]
    assert (
        side["model"]["instrument_serial"] == "FOG-LAB-0042" and side["capture"]["instrument_serial"] == "FOG-SIM-0001"
    )
    assert side["model"]["sha256"] == hashlib.sha256(other.read_bytes()).hexdigest()
    # evaluate: the warning on stderr, the use in summary.json and report.md
    proc = cli("evaluate", "st.bin", "--model", str(other), "--out", str(tmp_path / "r"), "--force-model", cwd=made)
    assert proc.returncode == 0, proc.stderr
    assert warning in proc.stderr.splitlines()
    summary = json.loads((tmp_path / "r" / "summary.json").read_text())
    assert summary["force_model"] is True and summary["capture_serial"] == "FOG-SIM-0001"
    assert summary["model"]["instrument_serial"] == "FOG-LAB-0042"
    assert (
        "**Warning: models of another instrument, applied with --force-model to this capture of FOG-SIM-0001: "
        "`other (wesn)` for FOG-LAB-0042.**"
    ) in (tmp_path / "r" / "report.md").read_text()


def test_compensate_describes_its_csv_in_a_sidecar_and_the_csv_stays_plain(made):
    csv_text = (made / "st.csv").read_text()
    assert csv_text.startswith("t_s,n_samples,") and "#" not in csv_text
    side = yaml.safe_load((made / "st.csv.yaml").read_text())
    assert side["format"] == "fog_driver compensate provenance" and side["schema_version"] == 1
    assert side["csv"] == "st.csv" and side["rows"] == len(csv_text.splitlines()) - 1
    assert side["capture"] == {
        "path": "st.bin",
        "sha256": hashlib.sha256((made / "st.bin").read_bytes()).hexdigest(),
        "instrument_serial": "FOG-SIM-0001",
    }
    assert side["model"]["path"] == "model.yaml" and side["model"]["instrument_serial"] == "FOG-SIM-0001"
    assert side["model"]["sha256"] == hashlib.sha256((made / "model.yaml").read_bytes()).hexdigest()
    assert side["settings"] == {
        "every_s": 10.0,
        "format": "auto",
        "scale_override_arcsec_per_count": None,
        "force_model": False,
        "adapt_reference_dph": None,
        "adapt_state": None,
        "adapt_state_sha256": None,
        "table_log": None,
        "table_log_sha256": None,
    }
    assert "warnings" not in side


# --- a raw capture is never replaced by another kind of file ------------------------------------


def test_no_output_of_another_kind_replaces_a_capture_force_or_not(made, tmp_path):
    """Before: ``compensate --out chamber.bin --force`` replaced a chamber run (hours, not to be had again)
    with a CSV; now every output other than a new capture refuses a capture's path, --force or not (exit 64)."""
    capture = (made / "st.bin").read_bytes()
    (tmp_path / "chamber.bin").write_bytes(capture)  # no sidecar: its frames say what it is
    (tmp_path / "program.yaml").write_bytes(capture)  # a capture under a profile's name
    (tmp_path / "run.raw").write_bytes(b"\x00garbage before the first frame")  # an interrupted recording ...
    write_provenance(tmp_path / "run.raw", {"source": "record", "status": "interrupted"})  # ... its sidecar says so
    (tmp_path / "rep").mkdir()
    (tmp_path / "rep" / "drift.png").write_bytes(capture)
    (tmp_path / "new.bin.yaml").write_bytes(capture)  # where simulate --out new.bin puts its sidecar
    (tmp_path / "t.truth.csv").write_bytes(capture)  # where simulate --out t.bin puts its truth
    st, model, short = str(made / "st.bin"), str(made / "model.yaml"), str(made / "short.bin")
    before = digests(tmp_path) | {"rep/drift.png": digests(tmp_path / "rep")["drift.png"]}
    cases = [
        (["compensate", st, "--model", model, "--out", "chamber.bin", "--force"], "chamber.bin"),
        (["compensate", st, "--model", model, "--out", "chamber.bin"], "chamber.bin"),
        (
            [
                "compensate",
                st,
                "--model",
                model,
                "--out",
                "x.csv",
                "--adapt-reference",
                "0",
                "--adapt-state",
                "chamber.bin",
            ],
            "chamber.bin",
        ),
        (["fit", short, "--out", "chamber.bin", "--force"], "chamber.bin"),
        (["fit", short, "--out", "run.raw", "--force"], "run.raw"),
        (["plan", "--out", "program.yaml", "--force"], "program.yaml"),
        (["evaluate", st, "--model", model, "--out", "rep", "--force"], str(Path("rep") / "drift.png")),
        (["simulate", "--profile", str(PROFILE), "--duration", "10", "--out", "new.bin"], "new.bin.yaml"),
        (["simulate", "--profile", str(PROFILE), "--duration", "10", "--out", "t.bin", "--force"], "t.truth.csv"),
    ]
    for args, name in cases:
        line = one_line(cli(*args, cwd=tmp_path), 64)
        assert line == (
            f"fog-driver: error: {name}: is a raw capture; no output of another kind replaces one, --force or not "
            f"(give another name)"
        ), args
    after = digests(tmp_path) | {"rep/drift.png": digests(tmp_path / "rep")["drift.png"]}
    assert after == before and not (tmp_path / "x.csv").exists()
    # a new capture replaces a capture with --force, as before
    assert simulate(tmp_path, "chamber.bin", "--force", seconds=10).returncode == 0
    assert read_provenance(tmp_path / "chamber.bin")["frames"] == 100


def test_a_capture_given_for_a_yaml_file_is_named_so(made, tmp_path):
    """Before: ``--model chamber.bin`` said "model file larger than 1048576 bytes" (or that it was not UTF-8)."""
    big = tmp_path / "chamber.bin"
    big.write_bytes((made / "st.bin").read_bytes() * 20)  # over 1 MB, as a chamber run is
    assert big.stat().st_size > 1 << 20
    for capture in (big, made / "st.bin"):
        line = one_line(
            cli("compensate", "st.bin", "--model", str(capture), "--out", str(tmp_path / "c.csv"), cwd=made), 65
        )
        assert line == f"fog-driver: error: {capture}: is a capture, not a model file"
    line = one_line(cli("fit", "st.bin", "--config", str(big), "--out", str(tmp_path / "m.yaml"), cwd=made), 65)
    assert line == f"fog-driver: error: {big}: is a capture, not a fit config"


# --- short captures: the real cause -------------------------------------------------------------


def test_a_short_capture_names_the_warm_up(tmp_path):
    line = one_line(cli("fit", str(DATA / "sim-short.bin"), "--out", "m.yaml", cwd=tmp_path), 65)
    assert "the capture is 300 s and its first 300 s are excluded as warm-up (warmup_s in the fit config" in line
    # the model of the capture's instrument: the serial is not what this test is about
    (tmp_path / "model.yaml").write_text(MODEL.read_text().replace("FOG-SIM-0001", "FOG-SYN-0001"))
    line = one_line(
        cli("evaluate", str(DATA / "synthetic-clean.bin"), "--model", "model.yaml", "--out", "r", cwd=tmp_path), 65
    )
    assert "no static, valid block to evaluate: the capture is 12 s and its first 120 s are excluded" in line
    assert "to fit" not in line


def test_evaluate_checks_its_extra_before_any_work(monkeypatch, tmp_path, capsys):
    import sys

    from fog_driver.cli import main

    # allantools missing, whether or not an earlier test in this process imported it (None in sys.modules
    # makes every import of it fail)
    monkeypatch.setitem(sys.modules, "allantools", None)
    # the capture does not exist: the extra is what it says first
    assert main(["evaluate", str(tmp_path / "none.bin"), "--model", str(MODEL), "--out", str(tmp_path / "r")]) == 64
    err = capsys.readouterr().err
    assert err == (
        "fog-driver: error: evaluate's report (Allan deviation, plots) needs allantools (the 'report' "
        "extra); in the project's virtual environment: pip install -e '.[report]'\n"
    )


# --- record: a port that never opened ----------------------------------------------------------------


def test_record_fails_at_once_on_a_port_that_never_opened(tmp_path):
    """Before: it retried forever (warnings every 2 s), and Ctrl-C left a 0-byte capture marked complete."""
    line = one_line(cli("record", str(tmp_path / "ttyUSB9"), "--out", "r.bin", cwd=tmp_path), 69)
    assert line == f"fog-driver: error: cannot open {tmp_path / 'ttyUSB9'}: no such device"
    assert list(tmp_path.iterdir()) == []


def test_record_wait_says_so_once_and_an_interrupt_leaves_nothing(tmp_path):
    port = tmp_path / "ttyUSB9"
    proc = started("record", str(port), "--out", "r.bin", "--wait", cwd=tmp_path)
    try:
        first = proc.stderr.readline()  # blocks until the recorder has tried once and said it waits
        assert first == f"waiting for {port} to appear (now: no such device); Ctrl-C to stop\n"
        proc.send_signal(signal.SIGINT)
        _, rest = proc.communicate(timeout=30)
    finally:
        proc.kill()
    assert proc.returncode == 69
    assert rest.strip().splitlines() == [rest.strip()] and "Traceback" not in rest  # the retries are not logged
    assert rest.startswith(f"fog-driver: error: nothing recorded: {port} never opened in ")
    assert rest.strip().endswith("s; no capture written")
    assert list(tmp_path.iterdir()) == []  # no empty capture, no sidecar: a rerun is not refused


def test_describe_knows_each_kind_by_content(made, tmp_path):
    from fog_driver.files.outputs import describe

    (tmp_path / "renamed.dat").write_bytes((made / "st.bin.yaml").read_bytes())
    assert describe(tmp_path / "renamed.dat") == "a capture's provenance sidecar (of st.bin)"
    (tmp_path / "model.bin").write_text(MODEL.read_text())
    assert describe(tmp_path / "model.bin") != "a capture"
    assert describe(made / "st.csv") == "a compensate CSV"
    assert (made / "st.csv").read_text().split("\n", 1)[0].endswith(",flags,drift_sigma_dph")
    # one written before the drift_sigma_dph column is known too
    old_header = "t_s,n_samples,rate_raw_dph,drift_dph,rate_comp_dph,angle_raw_arcsec,angle_comp_arcsec,"
    (tmp_path / "old.csv").write_text(old_header + "t_top_c,t_bottom_c,t_housing_c,flags\n1.0,10,0,0,0,0,0,20,20,20,\n")
    assert describe(tmp_path / "old.csv") == "a compensate CSV"
    assert describe(tmp_path) == "a directory"


# --- an interrupted simulate keeps what it wrote, described as interrupted ----------------------------


def _simulate_interrupted_by_ctrl_c(tmp_path: Path) -> tuple[int, str, str]:
    """``simulate --out run.bin`` of the paper profile, SIGINT once the capture has bytes: (status, stdout, stderr)."""
    out = tmp_path / "run.bin"
    proc = started("simulate", "--profile", "paper", "--rate-hz", "100", "--out", "run.bin", cwd=tmp_path)
    try:
        deadline = time.monotonic() + 120
        while not (out.exists() and out.stat().st_size > 0):  # the run is under way once the capture has bytes
            assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
            time.sleep(0.01)
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=120)
    finally:
        proc.kill()
    return proc.returncode, stdout, stderr


def test_ctrl_c_during_simulate_out_prints_only_the_interrupted_line(tmp_path):
    """The review's finding 12: Ctrl-C printed the success line ("simulated paper ... frames") and then
    "interrupted: big.bin holds the first 19860 s"; now the interrupted line alone, exit 130."""
    status, stdout, stderr = _simulate_interrupted_by_ctrl_c(tmp_path)
    assert status == 130, stderr
    assert stdout == ""
    side = read_provenance(tmp_path / "run.bin")
    assert stderr.splitlines() == [
        f"fog-driver: interrupted: run.bin holds the first {side['frames'] / 100:g} s "
        "(status: interrupted in run.bin.yaml)"
    ]


def test_an_interrupted_simulate_leaves_a_sidecar_that_says_so_and_inspect_reports_it(tmp_path):
    """Before: Ctrl-C left run.bin and its truth without a sidecar (or, rerun, a capture no sidecar described);
    now the sidecar says ``status: interrupted`` with what was written, as the daemon's captures do."""
    out = tmp_path / "run.bin"
    status, stdout, stderr = _simulate_interrupted_by_ctrl_c(tmp_path)
    assert status == 130, stderr
    assert stderr.startswith("fog-driver: interrupted: run.bin holds the first ") and "Traceback" not in stderr
    side = read_provenance(out)
    data = out.read_bytes()
    assert side["status"] == "interrupted" and side["source"] == "simulate"
    assert side["bytes"] == len(data) and side["sha256"] == hashlib.sha256(data).hexdigest()
    assert 0 < side["frames"] < side["frames_planned"] and side["end_reason"].startswith("stopped after")
    truth_rows = (tmp_path / "run.truth.csv").read_text().splitlines()[2:]  # its header line and the columns
    assert len(truth_rows) == side["frames"] // 100  # the capture and its truth hold the same seconds
    report = cli("inspect", "run.bin", "--strict", cwd=tmp_path)
    assert report.returncode == 1  # not clean
    lines = dict(line.split(None, 1) for line in report.stdout.splitlines())
    assert lines["provenance"].startswith("source simulate, status interrupted")
    assert lines["verdict"] == "sidecar status interrupted"
    assert json.loads(cli("inspect", "run.bin", "--json", cwd=tmp_path).stdout)["problems"] == [
        "sidecar status interrupted"
    ]


def test_a_keyboard_interrupt_mid_write_still_leaves_the_sidecar(tmp_path):
    from fog_driver.lab.profiles import load_profile
    from fog_driver.sim.capture import simulate_to_file
    from fog_driver.sim.instrument import Simulator

    def interrupt(done: int, total: int) -> None:
        raise KeyboardInterrupt

    sim = Simulator(load_profile(str(PROFILE)), rate_hz=10, seed=0)
    with pytest.raises(KeyboardInterrupt):
        simulate_to_file(sim, tmp_path / "k.bin", duration_s=60, progress=interrupt)
    side = read_provenance(tmp_path / "k.bin")
    assert side["status"] == "interrupted" and side["frames"] == 100 and side["frames_planned"] == 600
    assert side["bytes"] == (tmp_path / "k.bin").stat().st_size
