"""Every command that reads or writes files, driven into every file-system failure a user meets: the
answer is always exactly one line on stderr (never a traceback) and a sysexits status.

The failures:

- a missing output directory (``--out nodir/x``);
- a directory where a file goes, and a regular file where a directory goes;
- an unreadable input.  The tests run as root, for whom ``chmod 000`` changes nothing, so an unreadable
  input is made the two ways root meets too: a directory where a file is expected (EISDIR), and a path
  under a regular file (``file.bin/x``: ENOTDIR);
- a full disk: the command runs with ``RLIMIT_FSIZE`` at 1 kB and ``SIGXFSZ`` ignored, so a write past
  the limit fails with EFBIG as it would with ENOSPC.

Inputs are the small fixtures in tests/data and a 60-s simulation, so the whole file runs in seconds.
"""

from __future__ import annotations

import os
import resource
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from fog_driver.samples.captures import sidecar_path

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT / "tests" / "data"
MODEL = ROOT / "fog_driver" / "data" / "models" / "default.yaml"
PROFILE = ROOT / "configs" / "profiles" / "short-test.yaml"
EX = {"usage": 64, "dataerr": 65, "noinput": 66, "unavailable": 69, "cantcreat": 73, "ioerr": 74, "config": 78}
SYSEXITS = set(EX.values())


def _full_disk(limit_bytes: int):
    def preexec() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails with EFBIG instead
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit_bytes, limit_bytes))

    return preexec


def run_cli(
    args: list[str], cwd: Path, fsize: int | None = None, env: dict[str, str] | None = None
) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "fog_driver", *args],
        capture_output=True,
        text=True,
        cwd=cwd,
        timeout=60,
        stdin=subprocess.DEVNULL,
        preexec_fn=_full_disk(fsize) if fsize else None,
        env=env,
    )


def fontconfig_cache_made(where: Path) -> dict[str, str]:
    """An environment whose fontconfig cache is in ``where``, made there first, and whose matplotlib cache is not
    made yet: on a full disk, matplotlib's first run cannot save its font list (a warning the report silences),
    and fontconfig, a C library matplotlib runs, would say on stderr that it cannot write its own cache, which no
    Python code can keep to one line."""
    env = {**os.environ, "XDG_CACHE_HOME": str(where / "cache")}
    warm = "import matplotlib; matplotlib.use('Agg'); import matplotlib.pyplot"
    made = {**env, "MPLCONFIGDIR": str(where / "mpl-made")}
    subprocess.run([sys.executable, "-c", warm], env=made, check=True, timeout=120, capture_output=True)
    return {**env, "MPLCONFIGDIR": str(where / "mpl")}


def assert_one_line(proc: subprocess.CompletedProcess, status: int, *needles: str, json_log: bool = False) -> str:
    """Exactly one line on stderr, the error (``json_log``: ``run``, a service, also logs JSON lines there)."""
    assert "Traceback" not in proc.stderr, proc.stderr
    lines = [line for line in proc.stderr.strip().splitlines() if not (json_log and line.startswith("{"))]
    assert len(lines) == 1, proc.stderr
    assert proc.returncode == status, (proc.returncode, proc.stderr)
    assert proc.returncode in SYSEXITS
    assert lines[0].startswith("fog-driver: error: ")
    for needle in needles:
        assert needle in lines[0], lines[0]
    return lines[0]


@pytest.fixture(scope="module")
def work(tmp_path_factory) -> Path:
    """A folder with a capture (and sidecar and truth), a model, a fit config, a regular file and a
    directory; every command runs in it."""
    d = tmp_path_factory.mktemp("errors")
    for suffix in (".bin", ".bin.yaml", ".truth.csv"):
        shutil.copy(DATA / f"sim-short{suffix}", d / f"cap{suffix}")
    (d / "cap.bin.yaml").write_text((d / "cap.bin.yaml").read_text().replace("sim-short", "cap"))
    shutil.copy(MODEL, d / "model.yaml")
    (d / "fit.yaml").write_text("warmup_s: 30.0\n")
    (d / "plain.txt").write_text("a user's file\n")
    (d / "adir").mkdir()
    (d / "adir" / "keep.txt").write_text("mine\n")
    (d / "x.bin").mkdir()  # a directory with a capture's name
    (d / "stops.csv").write_text("t_start_s,t_end_s,angle_deg\n100,140,0\n150,190,36\n")
    return d


REPLAY = f"replay://{DATA / 'synthetic-clean.bin'}?unplug=1"
SIM = ["simulate", "--profile", str(PROFILE), "--rate-hz", "10", "--duration", "60"]
FIT = ["fit", "cap.bin", "--config", "fit.yaml", "--kind", "polynomial", "--accept-weak-fit"]
COMP = ["compensate", "cap.bin", "--model", "model.yaml"]
EVAL = ["evaluate", "cap.bin", "--model", "model.yaml"]
RUN = ["run", "--port", REPLAY, "--listen", "127.0.0.1:0"]

# (id, arguments, status, words the line must hold)
CASES = [
    # a missing output directory
    ("simulate-no-dir", SIM + ["--out", "nodir/s.bin"], 73, ["no such directory"]),
    ("record-no-dir", ["record", REPLAY, "--out", "nodir/r.bin", "--no-reconnect"], 73, ["no such directory"]),
    ("fit-no-dir", FIT + ["--out", "nodir/m.yaml"], 73, ["no such directory"]),
    ("plan-no-dir", ["plan", "--out", "nodir/p.yaml"], 73, ["no such directory"]),
    ("compensate-no-dir", COMP + ["--out", "nodir/c.csv"], 73, ["no such directory"]),
    (
        "compensate-adapt-state-no-dir",
        COMP + ["--out", "c1.csv", "--adapt-reference", "0", "--adapt-state", "nodir/s.yaml"],
        73,
        ["no such directory"],
    ),
    ("evaluate-no-parent", EVAL + ["--out", "nodir/sub/report"], 73, ["no such directory"]),
    # a directory where a file goes
    ("simulate-out-is-dir", SIM + ["--out", "x.bin"], 73, ["is a directory"]),
    ("record-out-is-dir", ["record", REPLAY, "--out", "x.bin", "--no-reconnect"], 73, ["is a directory"]),
    ("fit-out-is-dir", FIT + ["--out", "adir"], 73, ["is a directory"]),
    ("compensate-out-is-dir", COMP + ["--out", "adir"], 73, ["is a directory"]),
    ("compensate-out-is-dir-force", COMP + ["--out", "adir", "--force"], 73, ["is a directory"]),
    # a file where a directory goes
    ("evaluate-out-is-file", EVAL + ["--out", "plain.txt"], 73, ["not a directory"]),
    ("evaluate-out-is-file-force", EVAL + ["--out", "plain.txt", "--force"], 73, ["not a directory"]),
    ("evaluate-out-under-file", EVAL + ["--out", "plain.txt/report"], 73, ["not a directory"]),
    ("simulate-out-under-file", SIM + ["--out", "plain.txt/s.bin"], 73, ["not a directory"]),
    ("compensate-out-under-file", COMP + ["--out", "plain.txt/c.csv"], 73, ["not a directory"]),
    ("plan-out-under-file", ["plan", "--out", "plain.txt/p.yaml"], 73, ["not a directory"]),
    ("run-capture-dir-is-file", RUN + ["--capture-dir", "plain.txt"], 73, ["not a directory"]),
    # an unreadable input: a directory, or a path under a regular file
    ("inspect-dir", ["inspect", "adir"], 65, ["adir"]),
    ("inspect-under-file", ["inspect", "plain.txt/c.bin"], 65, ["plain.txt/c.bin"]),
    ("record-replay-dir", ["record", "replay://adir", "--out", "r1.bin"], 69, ["cannot open"]),
    ("record-device-under-file", ["record", "plain.txt/tty", "--out", "r2.bin"], 69, ["cannot open"]),
    ("simulate-profile-dir", ["simulate", "--profile", "adir", "--out", "s1.bin"], 65, ["adir"]),
    (
        "simulate-instrument-under-file",
        SIM + ["--instrument", "plain.txt/i.yaml", "--out", "s2.bin"],
        65,
        ["plain.txt/i.yaml"],
    ),
    ("fit-capture-dir", ["fit", "adir", "--out", "m1.yaml"], 65, ["adir"]),
    ("fit-config-dir", ["fit", "cap.bin", "--config", "adir", "--out", "m2.yaml"], 65, ["adir"]),
    ("compensate-capture-dir", ["compensate", "adir", "--model", "model.yaml", "--out", "c2.csv"], 65, ["adir"]),
    (
        "compensate-model-under-file",
        ["compensate", "cap.bin", "--model", "plain.txt/m.yaml", "--out", "c3.csv"],
        65,
        ["plain.txt/m.yaml"],
    ),
    ("compensate-adapt-state-dir", COMP + ["--out", "c4.csv", "--adapt-state", "adir"], 65, ["adir"]),
    ("evaluate-capture-dir", ["evaluate", "adir", "--model", "model.yaml", "--out", "r1"], 65, ["adir"]),
    ("evaluate-model-dir", ["evaluate", "cap.bin", "--model", "adir", "--out", "r2"], 65, ["adir"]),
    ("evaluate-truth-dir", EVAL + ["--out", "r3", "--truth", "adir"], 65, ["adir"]),
    ("evaluate-truth-under-file", EVAL + ["--out", "r4", "--truth", "plain.txt/t.csv"], 65, ["plain.txt/t.csv"]),
    ("evaluate-reference-dir", EVAL + ["--out", "r5", "--reference", "adir"], 65, ["adir"]),
    ("evaluate-compare-dir", EVAL + ["--out", "r6", "--compare", "adir"], 65, ["adir"]),
    ("run-config-dir", ["run", "--config", "adir"], 78, ["adir"]),
    ("run-model-dir", RUN + ["--model", "adir"], 78, ["adir"]),
    ("run-model-under-file", RUN + ["--model", "plain.txt/m.yaml"], 78, ["plain.txt/m.yaml"]),
]


@pytest.mark.parametrize("args, status, needles", [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_file_errors_are_one_line_with_a_sysexits_status(work, args, status, needles):
    before = sorted(p.name for p in work.iterdir())
    assert_one_line(run_cli(args, work), status, *needles, json_log=args[0] == "run")
    assert sorted(p.name for p in work.iterdir()) == before  # nothing left behind
    assert (work / "adir" / "keep.txt").read_text() == "mine\n" and (
        work / "plain.txt"
    ).read_text() == "a user's file\n"


# (id, arguments, the files the command starts and must not leave half-written: None to keep them)
FULL_DISK = [
    ("simulate", SIM + ["--out", "full.bin"], ["full.bin", "full.truth.csv", "full.bin.yaml"]),
    ("record", ["record", REPLAY, "--out", "full.bin", "--no-reconnect"], None),
    ("fit", FIT + ["--out", "full.yaml"], ["full.yaml"]),
    ("plan", ["plan", "--out", "full.yaml"], ["full.yaml"]),
    ("compensate", COMP + ["--out", "full.csv"], ["full.csv"]),
    ("evaluate", EVAL + ["--out", "full-report"], None),
]


@pytest.mark.parametrize("args, removed", [c[1:] for c in FULL_DISK], ids=[c[0] for c in FULL_DISK])
def test_a_full_disk_is_one_line_and_exit_73(tmp_path, work, args, removed):
    for name in ("cap.bin", "cap.bin.yaml", "cap.truth.csv", "model.yaml", "fit.yaml"):
        os.link(work / name, tmp_path / name)  # the inputs, in a folder of the test's own
    env = fontconfig_cache_made(tmp_path / "fonts") if args[0] == "evaluate" else None
    line = assert_one_line(run_cli(args, tmp_path, fsize=1024, env=env), 73)
    assert "File too large" in line or "cannot" in line
    for name in removed or ():
        assert not (tmp_path / name).exists(), name
    if args[0] == "record":  # a recording keeps what the disk took, and its sidecar says how it ended
        assert (tmp_path / "full.bin").stat().st_size <= 1024
        assert (
            not sidecar_path(tmp_path / "full.bin").exists()
            or "failed" in sidecar_path(tmp_path / "full.bin").read_text()
        )
