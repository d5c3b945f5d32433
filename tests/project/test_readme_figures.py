"""The documentation's benchmark figures (the README and the site's pages) are blocks a benchmark writes
(``--update-readme``), each named by the command that makes it: this checks the blocks are what their commands
printed, in form, that ``python -m benchmarks`` names every one, and that every figure the prose quotes stands in
one of them.

A figure quoted in prose (``prose_figures``): a number (its sign kept) with a unit of what the benchmarks measure
(``UNITS``: ms, us, MB, kB, GB and their binary kin, %, frames/s, deg/h, arcsec, ppm, and a ratio written ``1.23x``)
in a document's prose: the README and ``docs/**/*.md`` but the changelog and ``docs/decisions/`` (dated records of
past runs, never rewritten), outside fenced code, inline code, HTML comments, benchmark blocks and tables under a
``<!-- constants -->`` line (reference constants: limits, defaults, formats), not a bound (after ``<=``,
``at most``, ``under``, ``within``, ``up to``, ``more than`` and the like: a target or a limit), and not a constant
its paragraph declares: ``<!-- constants: 64 kB, 20 ms -->`` anywhere in a paragraph (lines without a blank one
between; a table is one) says those figures of it are not measured: constants of the code or of its inputs (a
default, a limit, a threshold, a simulator's parameter) or arithmetic on them (a worked example); each figure it
names must stand in that paragraph's prose.  Such a figure must appear in a benchmark block of some document: with
its unit, or, a decimal fraction of 3 significant digits or more, as a bare number in a block of its own document (a
table's column whose header names the unit)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from benchmarks import _harness

ROOT = Path(__file__).resolve().parents[2]


def test_the_block_key_is_the_command_less_the_cache_and_the_flag():
    argv = [
        "--set",
        "dev",
        "--workdir",
        "/tmp/x",
        "--update-readme",
        "--workdir=/y",
        "--workers",
        "1",
        "--workers=2",
        "--reuse",
        "/z",
        "--reuse=/w",
        "--adapt",
    ]
    assert _harness.block_key("benchmarks/bench_population.py", argv) == "bench_population.py --set dev --adapt"


def test_a_block_is_replaced_in_place_and_a_missing_one_is_an_error():
    text = "a\n<!-- bench: x.py --n 1 -->\n```\nold\n```\n<!-- /bench -->\nb\n<!-- bench: x.py -->\n<!-- /bench -->\n"
    new = _harness.replace_block(text, "x.py", "$ cmd\nfigures")
    assert _harness.blocks(new) == {"x.py --n 1": "```\nold\n```\n", "x.py": "```\n$ cmd\nfigures\n```\n"}
    with pytest.raises(ValueError, match="no block"):
        _harness.replace_block(text, "y.py", "z")


def test_update_readme_writes_the_output_and_refuses_before_the_work_without_a_block(tmp_path, capsys):
    readme = tmp_path / "README.md"
    readme.write_text("<!-- bench: b.py --k -->\n<!-- /bench -->\n")
    with _harness.readme_output("b.py --k", update=True, readme=readme):
        print("figure 1.23")
    assert _harness.blocks(readme.read_text())["b.py --k"] == "```\n$ python -m benchmarks.b --k\nfigure 1.23\n```\n"
    worked = []
    with pytest.raises(ValueError), _harness.readme_output("other.py", update=True, readme=readme):
        worked.append(1)
    assert not worked


def test_a_block_is_found_in_the_document_that_holds_it(tmp_path):
    (tmp_path / "docs" / "explanation").mkdir(parents=True)
    (tmp_path / "README.md").write_text("no blocks\n")
    page = tmp_path / "docs" / "explanation" / "page.md"
    page.write_text("<!-- bench: b.py --k -->\n<!-- /bench -->\n")
    assert _harness.document_with("b.py --k", tmp_path) == page
    with pytest.raises(ValueError, match="no document"):
        _harness.document_with("b.py", tmp_path)


def test_every_readme_block_holds_its_own_command_and_a_script_that_can_write_it():
    blocks: dict[str, str] = {}
    for path in _harness.documents():
        found = _harness.blocks(path.read_text())
        assert not set(found) & set(blocks), f"{path}: a block that another document holds too"
        blocks.update(found)
    assert len(blocks) >= 12
    for key, body in blocks.items():
        script = ROOT / "benchmarks" / key.split()[0]
        assert script.exists(), key
        assert "run_main(main)" in script.read_text(), f"{script.name} cannot --update-readme"
        lines = body.splitlines()
        assert lines[0] == "```" and lines[-1] == "```" and len(lines) > 3, key
        assert lines[1] == f"$ {_harness.command_of(key)}", key


def test_every_block_is_named_once_in_the_quick_or_the_long_list_of_python_m_benchmarks():
    from benchmarks.__main__ import LONG, QUICK

    listed = [e.key for e in (*QUICK, *LONG)]
    assert len(listed) == len(set(listed)), "an entry named twice"
    held = {key for path in _harness.documents() for key in _harness.blocks(path.read_text())}
    assert set(listed) == held, (
        f"listed without a block: {set(listed) - held}; a block not listed: {held - set(listed)}"
    )
    assert all(e.run_s > 0 for e in (*QUICK, *LONG))


def test_python_m_benchmarks_runs_the_chosen_quick_entries_with_update_readme_from_the_top(monkeypatch):
    from benchmarks import __main__ as runner

    ran = []

    def fake_run(command, cwd):
        ran.append((command[1:], cwd))
        return runner.subprocess.CompletedProcess(command, 0)

    monkeypatch.setattr(runner.subprocess, "run", fake_run)
    monkeypatch.setattr(runner.sys, "argv", ["benchmarks", "--only", "bench_decode,paper_experiment"])
    runner.main()
    assert ran == [
        (["-m", "benchmarks.bench_decode", "--update-readme"], _harness.ROOT),
        (["-m", "benchmarks.paper_experiment", "--update-readme"], _harness.ROOT),
    ]


UNITS = r"(?:ms|us|µs|ns|MB|MiB|kB|KiB|GB|GiB|%|frames/s|samples/s|deg/h|arcsec|ppm)"
FIGURE = re.compile(
    r"(?<![\w.+\-/^])(?P<number>-?(?:\d{1,3}(?:,\d{3})+|\d+)(?:\.\d+)?)(?:\s?" + UNITS + r"(?![\w/])|x(?![\w/]))"
)
BLOCK_FIGURE = re.compile(
    r"(?<![\w.+\-/^])(?P<number>-?(?:\d{1,3}(?:,\d{3})+|\d+)(?:\.\d+)?)\s?(?:" + UNITS + r"|x)(?![\w/])"
)
BOUND = re.compile(
    r"(?:<=|>=|≤|≥|<|(?<!-)>|\bat most|\bat least|\bunder|\bup to|\bwithin|\blimit(?:ed)? (?:of|to)"
    r"|\b(?:more|less) than)\s*$"  # (?<!-): an arrow, ``0.238 -> 0.0256 deg/h``, is no bound
)
CONSTANTS = "<!-- constants -->"
DECLARED = re.compile(r"<!-- constants: (.*?) -->")


def prose_lines(text: str, comments: bool = False) -> list[tuple[int, str]]:
    """(line number, text) of a document's prose: outside fences, benchmark blocks and tables under
    ``<!-- constants -->``, with inline code and HTML comments (unless ``comments``) taken out."""
    lines: list[tuple[int, str]] = []
    fence, in_block, constants = "", False, ""
    for number, line in enumerate(text.splitlines(), 1):
        stripped = line.strip()
        if fence:
            fence = "" if stripped.startswith(fence) else fence
            continue
        if opening := re.match(r"(```+|~~~+)", stripped):
            fence = opening.group(1)
            continue
        if stripped.startswith("<!-- bench: ") or stripped == _harness.END:
            in_block = stripped != _harness.END
            continue
        if stripped == CONSTANTS:
            constants = "before"
            continue
        if constants and (stripped.startswith("|") or (constants == "before" and not stripped)):
            constants = "table" if stripped else constants
            continue
        constants = ""
        if not in_block:
            lines.append((number, re.sub(r"`[^`]*`" if comments else r"`[^`]*`|<!--.*?-->", "", line)))
    return lines


def _unit(figure: str, number: str) -> str:
    return figure[len(number) :].strip()


def _key(match: re.Match) -> tuple[str, str]:
    return match.group("number"), _unit(match.group(0), match.group("number"))


def paragraph_constants(text: str) -> tuple[list[int], dict[int, set[tuple[str, str]]]]:
    """Each line's paragraph (by line number - 1), and the figures each paragraph declares constants
    (``<!-- constants: ... -->``, comma-separated); a declared item that is not a figure is an error."""
    paragraph, of_line, declared = 0, [], {}
    for line in text.splitlines():
        paragraph += not line.strip()
        of_line.append(paragraph)
    for number, line in prose_lines(text, comments=True):  # a declaration in code is an example of one
        paragraph = of_line[number - 1]
        for listed in DECLARED.findall(line):
            for item in re.split(r",\s+", listed.strip()):
                match = FIGURE.fullmatch(item)
                assert match, f"<!-- constants: {listed} -->: {item!r} is not a figure"
                declared.setdefault(paragraph, set()).add(_key(match))
    return of_line, declared


def prose_figures(text: str) -> list[tuple[int, str, tuple[str, str]]]:
    """(line number, figure, (its number, its unit)) of every figure ``text`` quotes in its prose (an
    ``AssertionError`` when a paragraph declares a constant its prose does not quote)."""
    of_line, declared = paragraph_constants(text)
    found, used = [], set()
    for number, line in prose_lines(text):
        for match in FIGURE.finditer(line):
            if not BOUND.search(line[: match.start()][-16:]):
                key, paragraph = _key(match), of_line[number - 1]
                if key in declared.get(paragraph, ()):
                    used.add((paragraph, key))
                else:
                    found.append((number, match.group(0), key))
    first_line = {paragraph: n for n, paragraph in reversed(list(enumerate(of_line, 1)))}
    unused = sorted(
        f"line {first_line[p]}: {n} {u}" for p, keys in declared.items() for n, u in keys if (p, (n, u)) not in used
    )
    assert not unused, f"constants declared that their paragraph does not quote: {unused}"
    return found


BARE_NUMBER = re.compile(r"(?<![\w.+\-/^])(?P<number>-?(?:\d{1,3}(?:,\d{3})+|\d+)(?:\.\d+)?)(?![\w.]*\d)")


def significant_digits(number: str) -> int:
    """The digits of a decimal fraction, leading zeros left out (``0.0360``: 3); 0 for a whole number (``100``:
    its zeros may be padding)."""
    return len(number.replace(",", "").replace(".", "").lstrip("-0")) if "." in number else 0


def printed_figures(documents: list[Path] | None = None) -> set[tuple[str, str]]:
    """(number, unit) of every figure the benchmark blocks of ``documents`` (by default every document) print (a
    ratio as ``1.2x`` or ``1.2 x``), and (number, "") of every decimal fraction of 3 significant digits or more
    they print, unit or not (a column of a table whose header names the unit)."""
    printed = set()
    for document in _harness.documents() if documents is None else documents:
        for body in _harness.blocks(document.read_text()).values():
            for match in BLOCK_FIGURE.finditer(body):
                printed.add((match.group("number"), _unit(match.group(0), match.group("number"))))
            for match in BARE_NUMBER.finditer(body):
                if significant_digits(match.group("number")) >= 3:
                    printed.add((match.group("number"), ""))
    return printed


def stands_in_a_block(key: tuple[str, str], printed: set[tuple[str, str]], its_own: set[tuple[str, str]]) -> bool:
    """Figure ``key`` (number, unit) stands in a block: printed with its unit in any document's (``printed``), or
    its number, a decimal fraction of 3 significant digits or more, printed bare in its own document's
    (``its_own``: ``printed_figures([document])``, where the block's header says the unit)."""
    return key in printed or (significant_digits(key[0]) >= 3 and (key[0], "") in its_own)


def _figure_pages() -> list:
    pages = []
    for path in _harness.documents():
        name = path.relative_to(_harness.ROOT).as_posix()
        if name == "docs/changelog.md" or name.startswith("docs/decisions/"):
            continue
        pages.append(pytest.param(path, id=name))
    return pages


def test_a_prose_figure_is_a_number_with_a_unit_outside_code_blocks_constants_and_bounds():
    text = (
        "The batch decodes 11,764,396 frames/s, 8.9x the baseline, in 0.085 s; p99 under 5 ms; `64 kB` read.\n"
        "```\n$ run\n12 ms\n```\n<!-- bench: b.py -->\n```\n3 MB\n```\n<!-- /bench -->\n"
        "<!-- constants -->\n\n| limit | 1 MiB |\n|---|---|\nafter the table 2.5 %, 10 x 36 deg, 0.13 deg/h.\n"
    )
    assert [(n, f) for n, f, _ in prose_figures(text)] == [
        (1, "11,764,396 frames/s"),
        (1, "8.9x"),
        (15, "2.5 %"),
        (15, "0.13 deg/h"),
    ]


def test_a_figure_after_an_arrow_or_a_negative_one_is_a_figure_and_after_more_than_a_bound():
    text = "RMS 0.238 -> 0.0256 deg/h; warned when more than 5 deg/h off, not 6 deg/h; -0.024 deg/h, 2^-24 arcsec.\n"
    assert [f for _, f, _ in prose_figures(text)] == ["0.0256 deg/h", "6 deg/h", "-0.024 deg/h"]
    assert significant_digits("-0.0360") == 3


def test_a_prose_figure_stands_in_a_block_by_its_unit_or_by_three_significant_digits():
    anywhere, here = {("1.2", "x"), ("0.0250", "")}, {("0.0360", ""), ("12", "")}
    assert stands_in_a_block(("0.0360", "deg/h"), anywhere, here)
    assert stands_in_a_block(("1.2", "x"), anywhere, here)
    assert not stands_in_a_block(("0.0250", "deg/h"), anywhere, here)  # bare in another document's block
    assert not stands_in_a_block(("12", "%"), anywhere, here)
    assert not stands_in_a_block(("0.036", "deg/h"), anywhere, here)
    assert not stands_in_a_block(("100", "GB"), anywhere, {("100", "")})


def test_a_constant_its_paragraph_declares_is_not_a_figure_and_a_stale_declaration_fails():
    text = (
        "Files rotate at 256 MB; the daemon\nused 94.2 MB. <!-- constants: 256 MB -->\n\n"
        "Here 256 MB is measured, and a warning above 0.05 deg/h <!-- constants: 0.05 deg/h -->.\n"
    )
    assert [(n, f) for n, f, _ in prose_figures(text)] == [(2, "94.2 MB"), (4, "256 MB")]
    with pytest.raises(AssertionError, match="does not quote"):
        prose_figures("A limit of 1 MB. <!-- constants: 2 MB -->\n")
    with pytest.raises(AssertionError, match="not a figure"):
        prose_figures("A limit of 1 MB. <!-- constants: one MB -->\n")
    assert prose_figures("Declare them: `<!-- constants: 2 MB -->`.\n") == []


@pytest.mark.parametrize("path", _figure_pages())
def test_every_figure_the_prose_quotes_stands_in_a_benchmark_block(path):
    printed, its_own = printed_figures(), printed_figures([path])
    missing = [
        f"{n}: {figure}"
        for n, figure, key in prose_figures(path.read_text())
        if not stands_in_a_block(key, printed, its_own)
    ]
    assert not missing, f"{path.name}: figures quoted in prose that no benchmark block prints: {missing}"
