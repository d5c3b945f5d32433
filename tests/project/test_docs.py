"""The documentation works as written: every code block of README.md and docs/**/*.md is run, compiled or
parsed; the client library's examples run against a daemon; the site builds with ``mkdocs build --strict``
and loads nothing from another host (it must work offline, on an instrument PC without a network).

What each kind of block gets:

* ``python``: compiled; run where practical (from the repository's top, with a daemon for the client
  examples of docs/how-to/station-software.md);
* ``sh`` and transcripts (an untagged block's ``$ ...`` lines): every ``fog-driver SUBCOMMAND --option``
  they use exists in the command line's parser, and every ``tests/...`` script and ``python -m benchmarks.X``
  benchmark exists (the README's and the tutorial's walkthrough blocks also run, in
  tests/project/test_readme_walkthrough.py);
* ``yaml`` and ``json``: parsed; ``csv``: read, header first;
* ``d2``: drawn by the site's build (docs/hooks/d2.py), which fails on a diagram D2 cannot compile.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import html as html_lib
import io
import json
import os
import re
import select
import shlex
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from fog_driver.cli import main as cli_main
from fog_driver.cli.parser import COMMANDS, build_parser

ROOT = Path(__file__).resolve().parents[2]
DOCUMENTS = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
FENCE = re.compile(r"^(?P<indent>[ \t]*)```(?P<lang>[\w-]*)[^\n]*\n(?P<body>.*?)^(?P=indent)```[ \t]*$", re.S | re.M)
KNOWN = {"", "text", "sh", "python", "yaml", "json", "csv", "d2"}
#: Python blocks that run as they are, from the repository's top (the client examples run in their own test).
RUN_AS_IS = {"reference/api.md"}
CLIENT_EXAMPLES = "how-to/station-software.md"
GUARD_S = 120.0


def _name(path: Path) -> str:
    return str(path.relative_to(ROOT / "docs")) if path.parent != ROOT else path.name


def blocks() -> list[tuple[str, int, str, str]]:
    """Every fenced block of the documents: (document, line, language, body dedented)."""
    found = []
    for path in DOCUMENTS:
        text = path.read_text()
        for m in FENCE.finditer(text):
            indent = m.group("indent")
            body = "".join(line.removeprefix(indent) for line in m.group("body").splitlines(keepends=True))
            found.append((_name(path), text.count("\n", 0, m.start()) + 1, m.group("lang"), body))
    return found


BLOCKS = blocks()


def _ids(kind: str) -> list:
    return [pytest.param(doc, line, body, id=f"{doc}:{line}") for doc, line, lang, body in BLOCKS if lang == kind]


def test_every_block_is_of_a_kind_a_test_checks():
    assert len(BLOCKS) > 40
    unknown = [(doc, line, lang) for doc, line, lang, _ in BLOCKS if lang not in KNOWN]
    assert not unknown, unknown
    for kind in ("sh", "python", "yaml", "d2"):
        assert any(lang == kind for _, _, lang, _ in BLOCKS), kind


# --------------------------------------------------------------------------- python


@pytest.mark.parametrize(("doc", "line", "body"), _ids("python"))
def test_python_blocks_compile_and_run_where_practical(doc, line, body, monkeypatch, capsys):
    code = compile(body, f"{doc}:{line}", "exec")
    if doc in RUN_AS_IS:
        monkeypatch.chdir(ROOT)
        exec(code, {"__name__": "__docs__"})
    else:
        assert doc == CLIENT_EXAMPLES, f"{doc}:{line}: a python block that no test runs"


class SimulatedDaemon:
    """``fog-driver run --simulate`` on a free loopback port; ready once it prints its listening line."""

    def __init__(self, tmp_path: Path) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "fog_driver", "run", "--simulate", "--listen", "127.0.0.1:0"]
            + ["--capture-dir", str(tmp_path / "captures")],
            cwd=tmp_path,
            stdout=subprocess.PIPE,
            stderr=(tmp_path / "daemon.log").open("w"),  # a file: an unread pipe would block the daemon
            stdin=subprocess.DEVNULL,
            text=True,
        )
        ready, _, _ = select.select([self.proc.stdout], [], [], GUARD_S)
        line = self.proc.stdout.readline() if ready else ""
        assert "listening on" in line, (line, (tmp_path / "daemon.log").read_text()[-3000:])
        self.address = line.split("listening on ")[1].split(";")[0]

    def stop(self) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        try:
            return self.proc.wait(GUARD_S)
        finally:
            if self.proc.poll() is None:
                self.proc.kill()
                self.proc.wait()


def test_the_client_examples_run_against_a_daemon(tmp_path):
    """The blocking and the asyncio example of docs/how-to/station-software.md, as written, against a
    daemon: each reads its 20 samples (and the asyncio one sends two commands meanwhile) and exits 0."""
    examples = [body for doc, _, lang, body in BLOCKS if doc == CLIENT_EXAMPLES and lang == "python"]
    assert len(examples) == 2 and "asyncio" in examples[1], "the blocking and the asyncio example"
    daemon = SimulatedDaemon(tmp_path)
    try:
        for n, body in enumerate(examples):
            script = tmp_path / f"example{n}.py"
            script.write_text(body)
            done = subprocess.run(
                [sys.executable, str(script), daemon.address],
                cwd=tmp_path,
                capture_output=True,
                text=True,
                timeout=GUARD_S,
                env={k: v for k, v in os.environ.items() if k != "FOG_DRIVER_TOKEN"},
            )
            assert done.returncode == 0, (script.name, done.stdout[-2000:], done.stderr[-3000:])
            samples = [line for line in done.stdout.splitlines() if re.match(r"^\d+ \d", line)]
            assert len(samples) == 20, done.stdout
        assert "zeroed: ZERO" in done.stdout and "frames so far:" in done.stdout
    finally:
        status = daemon.stop()
    assert status == 0


# --------------------------------------------------------------------------- shell and transcripts


def _help(argv: list[str]) -> str:
    out = io.StringIO()
    with contextlib.redirect_stdout(out), pytest.raises(SystemExit):
        cli_main([*argv, "--help"])
    return out.getvalue()


_HELP_CACHE: dict[tuple[str, ...], str] = {}


def help_text(argv: tuple[str, ...]) -> str:
    if argv not in _HELP_CACHE:
        _HELP_CACHE[argv] = _help(list(argv))
    return _HELP_CACHE[argv]


def subcommands(argv: tuple[str, ...]) -> set[str]:
    """The sub-commands a (sub)parser lists in its help (under ``COMMAND``, one a line, indented by 4)."""
    text = help_text(argv)
    if not re.search(r"^usage: .*COMMAND \.\.\.\s*$", text, re.M | re.S) or "\n  COMMAND\n" not in text:
        return set()
    listing = text.split("\n  COMMAND\n", 1)[1].split("\n\n", 1)[0]
    return set(re.findall(r"^    ([a-z][\w-]*)\b", listing, re.M))


def check_fog_driver_line(tokens: list[str], where: str) -> None:
    """``fog-driver [GLOBAL] SUB [SUBSUB] ... --option``: the sub-command exists and so does every option."""
    words = [t for t in tokens[1:] if t not in ("-v", "-vv")]
    path: tuple[str, ...] = ()
    options = set(re.findall(r"(?<![\w-])(--?[\w][\w-]*)", help_text(())))
    for word in words:
        if word.startswith("-"):
            continue
        if word in subcommands(path):
            path = (*path, word)
            options |= set(re.findall(r"(?<![\w-])(--?[\w][\w-]*)", help_text(path)))
        elif not path:
            raise AssertionError(f"{where}: fog-driver has no sub-command {word!r}")
    assert path, f"{where}: no sub-command in {' '.join(tokens)!r}"
    for word in words:
        if word.startswith("--"):
            option = word.split("=", 1)[0]
            assert option in options, f"{where}: fog-driver {' '.join(path)} has no option {option}"


def command_lines(lang: str, body: str) -> list[str]:
    """The commands of a block: every line of a ``sh`` block (continuations joined), the ``$`` lines of a
    transcript."""
    joined = re.sub(r"\\\n\s*", " ", body)
    lines = [line.strip() for line in joined.splitlines()]
    if lang == "sh":
        return [line for line in lines if line and not line.startswith("#")]
    return [line[2:] for line in lines if line.startswith("$ ")]


def _tokens(command: str) -> list[list[str]]:
    """The simple commands of a line (split at ``&&``, ``|``, ``;``, ``&``), comments dropped."""
    lexer = shlex.shlex(command, posix=True, punctuation_chars="&|;")
    lexer.whitespace_split = True
    lexer.commenters = "#"
    parts: list[list[str]] = [[]]
    for token in lexer:
        if set(token) <= set("&|;"):
            parts.append([])
        else:
            parts[-1].append(token)
    return [p for p in parts if p]


SHELL_BLOCKS = [
    pytest.param(doc, line, lang, body, id=f"{doc}:{line}")
    for doc, line, lang, body in BLOCKS
    if lang in ("sh", "", "text")
]


@pytest.mark.parametrize(("doc", "line", "lang", "body"), SHELL_BLOCKS)
def test_shell_blocks_use_only_commands_and_options_that_exist(doc, line, lang, body):
    for command in command_lines(lang, body):
        for tokens in _tokens(command):
            while tokens and (tokens[0] in ("sudo", "exec") or "=" in tokens[0].split("/")[0]):
                tokens = tokens[1:]  # sudo, FOO=bar before the command
            if not tokens:
                continue
            if tokens[0] == "fog-driver":
                check_fog_driver_line(tokens, f"{doc}:{line}")
            elif tokens[0] in ("python", "python3") and len(tokens) > 1 and tokens[1].endswith(".py"):
                assert not tokens[1].startswith("benchmarks/"), f"{doc}:{line}: python -m benchmarks.X, not {tokens[1]}"
                assert (ROOT / tokens[1]).is_file() or tokens[1].startswith("/"), f"{doc}:{line}: {tokens[1]}"
            elif tokens[0] in ("python", "python3") and tokens[1:2] == ["-m"] and tokens[2].startswith("benchmarks"):
                module = ROOT.joinpath(*tokens[2].split("."))
                assert module.with_suffix(".py").is_file() or (module / "__main__.py").is_file(), f"{doc}:{line}"


def test_the_option_check_catches_what_does_not_exist():
    with pytest.raises(AssertionError, match="no option --colour"):
        check_fog_driver_line(["fog-driver", "watch", "--colour"], "x")
    with pytest.raises(AssertionError, match="no sub-command"):
        check_fog_driver_line(["fog-driver", "teleport"], "x")
    check_fog_driver_line(["fog-driver", "-v", "ctl", "adapt", "on", "--reference-dph", "0"], "x")


OPTION_TABLE = "| option | meaning | default |"


def option_table(text: str, where: str) -> set[str]:
    """What the one options table of ``text`` lists: the first word of each backticked span of its first column
    (`` `--port PORT_OR_URL` `` gives ``--port``, `` `-v`, `--verbose` `` both, `` `CAPTURE.bin` `` a positional)."""
    lines = text.splitlines()
    assert lines.count(OPTION_TABLE) == 1, (
        f"{where}: one options table ({OPTION_TABLE!r}), not {lines.count(OPTION_TABLE)}"
    )
    listed: set[str] = set()
    for line in lines[lines.index(OPTION_TABLE) + 2 :]:
        if not line.startswith("|"):
            break
        for span in re.findall(r"`([^`]+)`", re.split(r"(?<!\\)\|", line)[1]):  # a cell may hold an escaped \|
            listed.add(span.split()[0].split("=")[0])
    return listed


def parser_options(
    parser: argparse.ArgumentParser, leave_out: set[str] = frozenset(), *, nested: bool = False
) -> set[str]:
    """A parser's option strings and its positionals' metavars (their names in usage; the first word, as the
    table's: ``ctl``'s ``[HOST:PORT] COMMAND`` is ``[HOST:PORT]``), but ``leave_out``'s; ``nested``: with its
    subcommands' (``chamber status`` and ``chamber run`` share one table)."""
    names: set[str] = set()
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            if nested:
                for sub in action.choices.values():
                    names |= parser_options(sub, leave_out, nested=True)
            continue
        if action.dest in leave_out:
            continue
        names |= set(action.option_strings) or {(action.metavar or action.dest.upper()).split()[0]}
    return names


def command_sections(text: str) -> dict[str, str]:
    """commands.md's sections by command: the text under each ``## `fog-driver NAME` `` heading."""
    parts = re.split(r"^## `fog-driver ([a-z-]+)`\n", text, flags=re.M)
    return dict(zip(parts[1::2], parts[2::2], strict=True))


def test_the_commands_reference_lists_exactly_the_parsers_options():
    """docs/reference/commands.md: a table of every command at the top, a section per command, and in each section
    one options table listing exactly the parser's options and positionals (build_parser: an option added to,
    renamed in or removed from the parser without its row fails here); the options every command takes are in
    the table before the first command's section."""
    text = (ROOT / "docs" / "reference" / "commands.md").read_text()
    parser = build_parser()
    commands = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices
    intro = text.split("\n## `fog-driver ", 1)[0]
    table = re.findall(r"^\| \[`fog-driver ([a-z-]+)`\]\(#fog-driver-\1\) \|", intro, re.M)
    assert sorted(table) == sorted(COMMANDS) and len(set(table)) == len(table), f"the table of commands: {table}"
    assert option_table(intro, "commands.md's introduction") == parser_options(parser), "every command's options"
    sections = command_sections(text)
    assert sorted(sections) == sorted(commands), sorted(sections)
    wrong = {}
    for name, sub in commands.items():
        listed = option_table(sections[name], f"fog-driver {name}")
        expected = parser_options(sub, leave_out={"help", "verbose", "log_format"}, nested=True)
        if listed != expected:
            wrong[name] = {
                "not in the table": sorted(expected - listed),
                "not in the parser": sorted(listed - expected),
            }
    assert not wrong, wrong


def test_the_options_table_check_sees_a_missing_and_an_extra_option():
    parser = argparse.ArgumentParser()
    parser.add_argument("capture", metavar="CAPTURE.bin")
    parser.add_argument("--out")
    section = f"{OPTION_TABLE}\n|---|---|---|\n| `CAPTURE.bin` | in | |\n| `--out FILE\\|-` | out | |\n\nmore\n"
    assert option_table(section, "x") == parser_options(parser, {"help"}) == {"CAPTURE.bin", "--out"}
    parser.add_argument("--count")
    assert option_table(section, "x") != parser_options(parser, {"help"})
    with pytest.raises(AssertionError, match="one options table"):
        option_table(section + section, "x")


def test_a_newcomer_on_the_site_gets_the_readmes_install_and_first_session():
    """docs/getting-started.md includes the README's install and first session (pymdownx.snippets, one source):
    rendered as the site renders it, it holds every command the walkthrough runs from the README (so what
    tests/project/test_readme_walkthrough.py runs is what the page shows), and a section that is not in the README
    fails the build instead of leaving a hole."""
    import markdown
    from pymdownx.snippets import SnippetMissingError

    from benchmarks import readme_walkthrough

    def rendered(text: str) -> str:
        page = markdown.markdown(
            text,
            extensions=["pymdownx.snippets", "pymdownx.superfences"],
            extension_configs={"pymdownx.snippets": {"base_path": [str(ROOT)], "check_paths": True}},
        )
        return html_lib.unescape(re.sub(r"<[^>]+>", "", page))

    source = (ROOT / "docs" / "getting-started.md").read_text()
    assert '--8<-- "README.md:install"' in source and '--8<-- "README.md:first-session"' in source
    page = rendered(source)
    commands = [c for step in readme_walkthrough.steps((ROOT / "README.md").read_text()) for c in step.commands]
    assert {"fog-driver run", "fog-driver watch --count 20", "fog-driver ctl status"} <= {
        c.split("#")[0].strip() for c in commands
    }
    missing = [c for c in commands if c not in page]
    assert not missing, f"README walkthrough commands not on the getting-started page: {missing}"
    assert "--8<--" not in page and "[start:" not in page  # the markers are gone from what the site shows
    with pytest.raises(SnippetMissingError):
        rendered('--8<-- "README.md:no-such-section"')


def test_every_config_key_is_in_the_configuration_reference():
    """Every key of configs/default.yaml (which lists them all), and the ``device`` mapping's, has its row."""
    text = (ROOT / "docs" / "reference" / "config.md").read_text()
    config = yaml.safe_load((ROOT / "configs" / "default.yaml").read_text())
    missing = [key for key in config if f"`{key}`" not in text]
    missing += [f"device.{key}" for key in config["device"] if f"`{key}`" not in text]
    assert not missing, missing


# --------------------------------------------------------------------------- data blocks


DATA_BLOCKS = [
    pytest.param(doc, line, lang, body, id=f"{doc}:{line}")
    for doc, line, lang, body in BLOCKS
    if lang in ("yaml", "json", "csv")
]


@pytest.mark.parametrize(("doc", "line", "lang", "body"), DATA_BLOCKS)
def test_data_blocks_parse(doc, line, lang, body):
    """YAML with ``yaml.safe_load`` (a mapping, as every config is), JSON, CSV (a header, then rows as wide)."""
    if lang == "yaml":
        assert isinstance(yaml.safe_load(body), dict), f"{doc}:{line}"
    elif lang == "json":
        json.loads(body)
    else:
        rows = list(csv.reader(row for row in body.splitlines() if not row.startswith("#")))
        assert len(rows) >= 2 and all(len(row) == len(rows[0]) for row in rows), f"{doc}:{line}"


# --------------------------------------------------------------------------- the site

EXTERNAL = re.compile(
    r"""<(?:script|img|iframe|source|audio|video)\b[^>]*\bsrc=["']?(?:https?:)?//"""
    r"""|<link\b[^>]*\bhref=["']?(?:https?:)?//"""
    r"""|@import\s+(?:url\()?["']?(?:https?:)?//"""
    r"""|url\(\s*["']?(?:https?:)?//""",
    re.I,
)


def test_mkdocs_builds_strict_and_the_site_loads_nothing_from_another_host(tmp_path):
    site = tmp_path / "site"
    done = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(site)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
        env={**os.environ, "NO_MKDOCS_2_WARNING": "1"},
    )
    assert done.returncode == 0, done.stderr[-5000:]
    loaded = []
    for path in site.rglob("*"):
        if path.suffix in (".html", ".css", ".js", ".svg"):
            for m in EXTERNAL.finditer(path.read_text(errors="replace")):
                loaded.append(f"{path.relative_to(site)}: {m.group(0)}")
    assert not loaded, loaded[:20]
    design = (site / "explanation" / "design.html").read_text()
    assert design.count('<div class="d2-diagram"') == 2 and "<svg" in design  # the layers and the threads
    assert "```d2" not in design and "mermaid" not in design
    api = (site / "reference" / "api.html").read_text()
    for name in ("fog_driver.client.Client", "fog_driver.client.AsyncClient", "fog_driver.protocol.FrameDecoder"):
        assert f'id="{name}"' in api, name
    wire = (site / "reference" / "wire-protocol.html").read_text()
    assert "Type 0x01: SAMPLE" in wire  # firmware_protocol/PROTOCOL.md, included, not copied
    assert "Map of the code" in (site / "explanation" / "design.html").read_text()


def test_the_external_check_sees_a_cdn():
    for html in (
        '<script src="https://unpkg.com/mermaid/dist/mermaid.min.js"></script>',
        "<link rel=stylesheet href='//fonts.googleapis.com/css?family=Roboto'>",
        "@import url(https://fonts.googleapis.com/css2)",
    ):
        assert EXTERNAL.search(html), html
    assert not EXTERNAL.search('<svg xmlns="http://www.w3.org/2000/svg"><a href="https://example.org/">x</a>')


def test_the_readme_is_short_and_points_to_the_site():
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= 250
    for needed in ("doi:10.19708/j.ckjs.2415539", "python -m pytest -n 2", "mkdocs build --strict", "mkdocs serve"):
        assert needed in text, needed
    assert "<!-- map of the code: the lead updates it -->" in (ROOT / "docs/explanation/design.md").read_text()
