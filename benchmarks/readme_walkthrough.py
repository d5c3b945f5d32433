"""The README, the tutorial and the calibration how-to as one executable walkthrough: their marked command
blocks, in order (``DOCUMENTS``: the README's install and first session, then ``docs/tutorial.md``, then
``docs/how-to/calibration.md``, in the same directory).

A block runs when the line before its ```` ```sh ```` fence is a marker::

    <!-- walkthrough -->                                   each line runs in turn and must exit 0
    <!-- walkthrough: background, ready when "TEXT" -->    its one command starts on a terminal (a pty)
                                                           and runs on; ready once TEXT is on the screen
    <!-- walkthrough: stop -->                             (no block) Ctrl-C to the background command:
                                                           it must exit 0
    <!-- walkthrough: output -->                           before an untagged block ``$ COMMAND`` and the
                                                           lines it prints: COMMAND ran before, and its
                                                           stdout is those lines but for the numbers in
                                                           them (``same_but_numbers``: a fit's figures
                                                           may differ in the last digit between machines,
                                                           its words and lines may not)

Lines run with bash in the walkthrough's directory, in the project's virtual environment once
``.venv/bin/activate`` exists there (as after ``source .venv/bin/activate``; with ``venv_bin`` given,
that directory instead, for a benchmark that reuses an installed environment and skips the install
lines).  A line ending in a backslash continues on the next.  ``tests/project/test_readme_walkthrough.py`` runs
the walkthrough on a fresh clone; ``bench_walkthrough.py`` times it.
"""

from __future__ import annotations

import dataclasses
import os
import re
import select
import signal
import subprocess
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
#: The walkthrough's documents, in the order they run (paths relative to the repository).
DOCUMENTS = ("README.md", "docs/tutorial.md", "docs/how-to/calibration.md")
MARKER = re.compile(r"^<!-- walkthrough(?::\s*(?P<options>.*?))?\s*-->\n", re.M)
FENCE = re.compile(r"[ \t\n]*```sh\n(?P<body>.*?)^```\n", re.S | re.M)
TRANSCRIPT = re.compile(r"[ \t\n]*```\n\$ (?P<command>[^\n]*)\n(?P<output>.*?)^```\n", re.S | re.M)
#: A number in a command's output: an integer (with thousands commas), a decimal, an exponent.
NUMBER = re.compile(r"[-+]?\d[\d,]*(?:\.\d+)?(?:[eE][-+]?\d+)?")
READY = re.compile(r'^background, ready when "(?P<text>[^"]+)"$')
INSTALL = re.compile(r"^(python3 -m venv|pip install)\b")


@dataclasses.dataclass(frozen=True)
class Step:
    kind: str  # "run", "background", "stop" or "output"
    commands: tuple[str, ...] = ()
    ready_text: str = ""
    line: int = 0  # in its document, for messages
    source: str = "README.md"  # the document, for messages
    expected: str = ""  # "output": what the command prints


def same_but_numbers(expected: str, actual: str) -> bool:
    """Whether ``actual`` is ``expected`` but for the numbers in it (``NUMBER``), line by line, word by word."""

    def shape(text: str) -> list[str]:
        return [NUMBER.sub("#", line).rstrip() for line in text.strip("\n").splitlines()]

    return shape(expected) == shape(actual)


def _commands(body: str) -> tuple[str, ...]:
    joined = re.sub(r"\\\n\s*", " ", body)
    return tuple(line.strip() for line in joined.splitlines() if line.strip() and not line.lstrip().startswith("#"))


def all_steps(root: Path = ROOT) -> list[Step]:
    """The whole walkthrough: every document's steps, the documents in ``DOCUMENTS`` order."""
    return [step for name in DOCUMENTS for step in steps((root / name).read_text(), name)]


def steps(text: str, source: str = "README.md") -> list[Step]:
    """One document's steps in order; ``ValueError`` for a marker that makes no sense."""
    found = []
    for m in MARKER.finditer(text):
        line = text.count("\n", 0, m.start()) + 1
        options = m.group("options") or ""
        if options == "stop":
            found.append(Step("stop", line=line, source=source))
            continue
        if options == "output":
            transcript = TRANSCRIPT.match(text, m.end())
            if transcript is None:
                raise ValueError(f"{source}:{line}: an output marker without a ``` block starting '$ COMMAND' after it")
            command, expected = transcript.group("command").strip(), transcript.group("output")
            found.append(Step("output", (command,), line=line, source=source, expected=expected))
            continue
        fence = FENCE.match(text, m.end())
        if fence is None:
            raise ValueError(f"{source}:{line}: a walkthrough marker without a ```sh block after it")
        commands = _commands(fence.group("body"))
        if options == "":
            found.append(Step("run", commands, line=line, source=source))
        elif ready := READY.match(options):
            if len(commands) != 1:
                raise ValueError(f"{source}:{line}: a background step runs one command, not {len(commands)}")
            found.append(Step("background", commands, ready.group("text"), line=line, source=source))
        else:
            raise ValueError(f"{source}:{line}: unknown walkthrough marker options {options!r}")
    return found


class Background:
    """A command on a terminal of its own (a pty: what a person has), until stopped with Ctrl-C."""

    def __init__(self, command: str, cwd: Path, env: dict[str, str]) -> None:
        self.command = command
        self.master, slave = os.openpty()
        self.proc = subprocess.Popen(
            ["bash", "-c", f"exec {command}"],
            cwd=cwd,
            env=env,
            stdin=slave,
            stdout=slave,
            stderr=slave,
            start_new_session=True,
        )
        os.close(slave)
        self.screen = ""

    def read_until(self, text: str | None, timeout_s: float) -> None:
        """Read the terminal until ``text`` shows (or, with None, until the command closes it)."""
        deadline = time.monotonic() + timeout_s
        while text is None or text not in self.screen:
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError(
                    f"{self.command!r}: {text!r} not on its terminal within {timeout_s} s; "
                    f"it showed: {self.screen[-2000:]!r}"
                )
            ready, _, _ = select.select([self.master], [], [], left)
            if not ready:
                continue
            try:
                data = os.read(self.master, 65536)
            except OSError:  # EIO: the command and its children closed the terminal
                data = b""
            if not data:
                if text is None:
                    return
                raise RuntimeError(
                    f"{self.command!r} ended (exit {self.proc.wait()}) before showing {text!r}: {self.screen[-2000:]!r}"
                )
            self.screen += data.decode("utf-8", "replace")

    def stop(self, timeout_s: float) -> int:
        """Ctrl-C (SIGINT to its process group, as a terminal sends it); its exit status."""
        try:
            os.killpg(self.proc.pid, signal.SIGINT)
            status = self.proc.wait(timeout_s)
            self.read_until(None, timeout_s)
            return status
        finally:
            self.kill()

    def kill(self) -> None:
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait()
        if self.master >= 0:
            os.close(self.master)
            self.master = -1


def environment(cwd: Path, venv_bin: Path | None = None) -> dict[str, str]:
    """The environment a line runs in: the walkthrough's virtual environment on PATH, if there is one."""
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")}
    bin_dir = venv_bin if venv_bin is not None else cwd / ".venv" / "bin"
    if (bin_dir / "python").exists():
        env["PATH"] = f"{bin_dir}{os.pathsep}{env.get('PATH', '')}"
        env["VIRTUAL_ENV"] = str(bin_dir.parent)
    return env


def run_line(command: str, cwd: Path, env: dict[str, str], timeout_s: float) -> subprocess.CompletedProcess:
    """One foreground line, with bash, stdin closed (no terminal: what a script has)."""
    return subprocess.run(
        ["bash", "-euo", "pipefail", "-c", command],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        stdin=subprocess.DEVNULL,
        timeout=timeout_s,
    )
