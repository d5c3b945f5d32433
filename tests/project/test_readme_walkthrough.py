"""The README, the tutorial and the calibration how-to as one executable walkthrough: their marked blocks (the
README's install and first session, then docs/tutorial.md's calibration, then docs/how-to/calibration.md's
program and simulated calibration run) run in order on a fresh copy of the repository, from the install on,
and each must work as written and print what the documents show."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from benchmarks import readme_walkthrough as walkthrough

ROOT = Path(__file__).resolve().parents[2]

INSTALL_TIMEOUT_S = 900.0  # a new virtual environment and its dependencies from the package index
LINE_TIMEOUT_S = 300.0
READY_TIMEOUT_S = 60.0


def test_markers_parse_into_steps_and_nonsense_is_refused():
    text = (
        "<!-- walkthrough -->\n```sh\na --x \\\n  --y   # comment\n# only a comment\nb\n```\n"
        '<!-- walkthrough: background, ready when "go" -->\n```sh\nserve\n```\n<!-- walkthrough: stop -->\n'
    )
    assert walkthrough.steps(text) == [
        walkthrough.Step("run", ("a --x  --y   # comment", "b"), line=1),
        walkthrough.Step("background", ("serve",), "go", line=8),
        walkthrough.Step("stop", line=12),
    ]
    transcript = "<!-- walkthrough: output -->\n```\n$ fit a.bin\nfitted 1,234 blocks\nwarning: x\n```\n"
    assert walkthrough.steps(transcript) == [
        walkthrough.Step("output", ("fit a.bin",), line=1, expected="fitted 1,234 blocks\nwarning: x\n")
    ]
    for bad in (
        "<!-- walkthrough: output -->\n```\nno command\n```\n",
        "<!-- walkthrough -->\nno block\n",
        "<!-- walkthrough: sometimes -->\n```sh\na\n```\n",
        '<!-- walkthrough: background, ready when "x" -->\n```sh\na\nb\n```\n',
    ):
        with pytest.raises(ValueError, match="README.md:1"):
            walkthrough.steps(bad)


def test_an_output_is_the_same_but_for_its_numbers():
    expected = "fitted a wesn model on 1 capture(s) (26,101 static blocks)\nlag 286.1 s, a factor 35.53\n"
    assert walkthrough.same_but_numbers(
        expected, "fitted a wesn model on 1 capture(s) (26,100 static blocks)\nlag 290 s, a factor 1.2e+01\n"
    )
    assert not walkthrough.same_but_numbers(expected, expected.replace("wesn", "polynomial"))  # other words
    assert not walkthrough.same_but_numbers(expected, expected + "warning: one more line\n")  # another line
    assert not walkthrough.same_but_numbers(expected, expected.splitlines()[0])  # a line less


def test_a_step_names_its_document():
    text = "<!-- walkthrough: sometimes -->\n```sh\na\n```\n"
    with pytest.raises(ValueError, match="docs/tutorial.md:1"):
        walkthrough.steps(text, "docs/tutorial.md")
    sources = {step.source for step in walkthrough.all_steps()}
    assert sources == set(walkthrough.DOCUMENTS), sources


def test_the_walkthrough_covers_the_newcomers_path():
    """Deleting a marker must not quietly shorten the walkthrough: the main job and every step of a
    calibration are in it, in this order."""
    commands = [c for step in walkthrough.all_steps() for c in step.commands]
    wanted = [
        "python3 -m venv .venv",
        "pip install -e",
        "fog-driver run",
        "fog-driver watch",
        "fog-driver ctl bias",
        "fog-driver simulate",
        "fog-driver inspect",
        "fog-driver fit",
        "fog-driver compensate",
        "fog-driver evaluate",
        "fog-driver run --model model.yaml",
        "fog-driver plan",
        "fog-driver simulate --profile calibration",
        "fog-driver fit calibration.bin",
    ]
    positions = [next((i for i, c in enumerate(commands) if c.startswith(w)), None) for w in wanted]
    assert None not in positions, dict(zip(wanted, positions))
    assert positions == sorted(positions), dict(zip(wanted, positions))


def test_what_the_walkthrough_writes_is_ignored_by_git():
    """A clone's `git status` after the walkthrough lists nothing it wrote (its captures, model, CSV, report)."""
    written = {"fog-captures/fog-000000-20260101T000000Z.bin"}  # the daemon's raw capture
    for step in walkthrough.all_steps():
        for command in step.commands:
            words = command.split()
            for out in (words[i + 1] for i, word in enumerate(words[:-1]) if word == "--out"):
                if out.endswith(".bin"):  # a capture, its sidecar and its truth
                    written |= {out, f"{out}.yaml", out.removesuffix(".bin") + ".truth.csv"}
                elif out.endswith(".csv"):  # compensate's CSV and its sidecar
                    written |= {out, f"{out}.yaml"}
                elif out.endswith(".yaml"):
                    written.add(out)
                else:  # evaluate's report folder
                    written.add(f"{out}/report.md")
    assert {"chamber.bin", "check.csv.yaml", "model.yaml", "report/report.md", "my-chamber.yaml"} <= written
    assert {"calibration.bin", "calibration.bin.yaml", "calibration-model.yaml"} <= written
    ignored = subprocess.run(
        ["git", "check-ignore", "--no-index", "--stdin"],
        cwd=ROOT,
        input="\n".join(sorted(written)) + "\n",
        capture_output=True,
        text=True,
    ).stdout.split()
    assert set(ignored) == written, sorted(written - set(ignored))


def fresh_copy(destination: Path) -> Path:
    """The files a fresh clone of this working tree would hold (tracked ones and new ones not ignored)."""
    listed = (
        subprocess.run(
            ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
            cwd=ROOT,
            capture_output=True,
            check=True,
        )
        .stdout.decode()
        .split("\0")
    )
    for name in filter(None, listed):
        source = ROOT / name
        if source.is_file():  # a tracked file deleted in the working tree is not in the next commit
            (destination / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, destination / name)
    return destination


def untracked_files(clone: Path) -> set[str]:
    """What ``git status`` in ``clone`` would list as untracked (``clone`` made a repository of its own, nothing
    committed: every file is untracked unless .gitignore leaves it out)."""
    if not (clone / ".git").exists():
        subprocess.run(["git", "init", "-q", str(clone)], check=True)
    listed = subprocess.run(
        ["git", "ls-files", "-z", "--others", "--exclude-standard"], cwd=clone, capture_output=True, check=True
    )
    return set(filter(None, listed.stdout.decode().split("\0")))


@pytest.mark.install
def test_the_readme_walkthrough_runs_as_written(tmp_path):
    clone = fresh_copy(tmp_path / "fog_driver")
    clone_files = untracked_files(clone)  # as a clone's first `git status` would list them: none of its own
    background: walkthrough.Background | None = None
    printed: dict[str, str] = {}  # each command's stdout, for the outputs the documents show
    try:
        for step in walkthrough.all_steps(clone):
            where = f"{step.source}:{step.line}"
            env = walkthrough.environment(clone)
            if step.kind == "output":
                assert step.commands[0] in printed, f"{where}: {step.commands[0]!r} shown before it ran"
                shown = printed[step.commands[0]]
                assert walkthrough.same_but_numbers(step.expected, shown), (
                    f"{where}: {step.commands[0]!r} printed, but for numbers, other lines than the document "
                    f"shows:\n{shown}"
                )
            elif step.kind == "stop":
                assert background is not None, f"{where}: stop without a background command"
                status = background.stop(READY_TIMEOUT_S)
                assert status == 0, f"{where}: {background.command!r} exited {status}: {background.screen[-3000:]}"
                background = None
            elif step.kind == "background":
                assert background is None, f"{where}: a second background command"
                background = walkthrough.Background(step.commands[0], clone, env)
                background.read_until(step.ready_text, READY_TIMEOUT_S)
            else:
                for command in step.commands:
                    timeout_s = INSTALL_TIMEOUT_S if walkthrough.INSTALL.match(command) else LINE_TIMEOUT_S
                    done = walkthrough.run_line(command, clone, walkthrough.environment(clone), timeout_s)
                    assert done.returncode == 0, (
                        f"{where}: {command!r} exited {done.returncode}\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}"
                    )
                    printed[command] = done.stdout
        assert background is None, f"{background.command!r} was never stopped"
        # what the walkthrough wrote is not news to `git status` in the clone (.gitignore)
        assert untracked_files(clone) == clone_files
    finally:
        if background is not None:
            background.kill()
