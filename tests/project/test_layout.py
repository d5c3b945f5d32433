"""The layout's rules that no linter keeps: no import cycle (imports inside functions counted), imports inside
functions only for an optional extra or start-up time, a short README, one formatter's style, no results of
evaluation runs in the package's docstrings and comments (they go to ``docs/decisions/``).

The layers themselves are import-linter's contracts (``pyproject.toml``, ``lint-imports`` in CI)."""

from __future__ import annotations

import ast
import io
import re
import tokenize
from pathlib import Path

import grimp

ROOT = Path(__file__).resolve().parents[2]
PACKAGE = ROOT / "fog_driver"
#: The issue that set the layout allows at most this many imports of the package's own modules inside functions.
MAX_IMPORTS_IN_FUNCTIONS = 10
REASONS = ("# optional extra", "# start-up time")
#: An evaluation set's name ("eval5"), a run's ratio ("1.10x frozen") or a timing figure ("10x faster", "twice the
#: speed", "about 11 us", "3 % of a core"): results of runs, which docs/decisions/ holds; a docstring names the
#: benchmark that measures them instead.
RUN_HISTORY = re.compile(
    r"\beval[0-9]+\b|\b[0-9]+\.[0-9]+x\b"
    r"|\b[0-9]+(?:\.[0-9]+)?\s*(?:x|times)\s+(?:faster|slower|quicker|cheaper|as fast|as slow|the speed)\b"
    r"|\b(?:twice|thrice|half|(?:two|three|four|five|ten|a hundred) times)"
    r"\s+(?:the speed|as fast|as slow|faster|slower)\b"
    r"|(?:\babout|\bsome|~|\bcosts?|\btakes?)\s*~?\s*[0-9]+(?:\.[0-9]+)?\s*(?:ns|us|\u00b5s|\u03bcs|ms)\b"
    r"|\b[0-9]+(?:\.[0-9]+)?\s*%\s*(?:of\s+(?:a|one|the)\s+)?(?:core|cpu)\b",
    re.IGNORECASE,
)


def import_cycles(graph: grimp.ImportGraph) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each a cycle of imports."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.find_modules_directly_imported_by(v):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for module in sorted(graph.modules):
        if module not in index:
            visit(module)
    return cycles


def test_no_import_cycle_even_counting_imports_inside_functions():
    graph = grimp.build_graph("fog_driver")  # grimp reads every import statement, inside functions too
    assert import_cycles(graph) == []


def test_the_cycle_finder_finds_a_cycle():
    graph = grimp.ImportGraph()
    for module in ("a", "a.b", "a.c", "a.d"):
        graph.add_module(module)
    graph.add_import(importer="a.b", imported="a.c")
    graph.add_import(importer="a.c", imported="a.b")
    graph.add_import(importer="a.c", imported="a.d")
    assert import_cycles(graph) == [["a.b", "a.c"]]


def imports_inside_functions() -> list[tuple[str, str]]:
    """(where, the line) of every import of the package's own modules inside a function."""
    found = []
    for path in sorted(PACKAGE.rglob("*.py")):
        lines = path.read_text().splitlines()
        for node in ast.walk(ast.parse("\n".join(lines))):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                for inner in ast.walk(node):
                    own = isinstance(inner, ast.ImportFrom) and (
                        inner.level or (inner.module or "").startswith("fog_driver")
                    )
                    if own:
                        found.append((f"{path.relative_to(ROOT)}:{inner.lineno}", lines[inner.lineno - 1].strip()))
    return sorted(set(found))


def test_imports_inside_functions_are_few_and_say_why():
    found = imports_inside_functions()
    assert len(found) <= MAX_IMPORTS_IN_FUNCTIONS, found
    unexplained = [(where, line) for where, line in found if not any(reason in line for reason in REASONS)]
    assert unexplained == []


def test_the_readme_is_short():
    assert len((ROOT / "README.md").read_text().splitlines()) <= 250


def test_one_formatter_keeps_the_style():
    """No formatter skip marks; at most 20 blocks where the formatter is off (an aligned table that reads better)."""
    files = [p for d in ("fog_driver", "tests", "benchmarks", "examples", "docs") for p in (ROOT / d).rglob("*.py")]
    text = [p.read_text() for p in files]
    marker = "# fmt: " + "skip"  # (spelled apart so that this file holds none)
    assert [str(p) for p, t in zip(files, text) if marker in t] == []
    assert sum(t.count("# fmt: " + "off") for t in text) <= 20


def docstrings_and_comments(source: str) -> list[tuple[int, str]]:
    """Every comment (by the tokenizer) and every string standing alone as a statement (by the AST: module, class
    and function docstrings and the ones after an assignment), each as (first line, text)."""
    found = [
        (tok.start[0], tok.string)
        for tok in tokenize.generate_tokens(io.StringIO(source).readline)
        if tok.type == tokenize.COMMENT
    ]
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant) and isinstance(node.value.value, str):
            found.append((node.lineno, node.value.value))
    return found


def test_docstrings_and_comments_carry_no_evaluation_runs():
    found = [
        f"{path.relative_to(ROOT)}:{line}: {match.group()}"
        for path in sorted(PACKAGE.rglob("*.py"))
        for line, text in docstrings_and_comments(path.read_text())
        for match in RUN_HISTORY.finditer(text)
    ]
    assert found == []


def test_the_history_finder_finds_a_ratio_and_a_set_name():
    source = '"""On eval5 it was 1.10x frozen."""\nX = 1  # 0.73x at the bound\nY = "1.10x in code is no history"\n'
    found = [match.group() for _, text in docstrings_and_comments(source) for match in RUN_HISTORY.finditer(text)]
    assert found == ["0.73x", "eval5", "1.10x"]


def test_the_history_finder_finds_timing_figures_and_passes_the_rules():
    timings = [
        "about 10x faster than numpy",
        "~10x faster to update",
        "three times faster with six candidates",
        "twice the speed of one pass",
        "a step costs about 11 us",
        "some 12 us on a small array",
        "costs ~25 ms of start-up",
        "was 3 % of a core",
        "0.03 % of a core at 1 kHz",
        "under 2 % CPU",
    ]
    rules = [
        "a validity time in 100 us steps",
        "a block of under 1 ms would be 0 us long",
        "waits 200 ms between commands",
        "a 5x5 step",
        "three times as much is extrapolating",
        "10 times as long",
    ]
    source = "".join(f'def f{i}():\n    """{text}."""\n' for i, text in enumerate(timings + rules))
    found = [text for _, text in docstrings_and_comments(source) if RUN_HISTORY.search(text)]
    assert found == [f"{text}." for text in timings]


MAX_MODULE_LINES = 800
#: The one state contract of a streaming stage, and the names it replaced.
STATE_NAMES = ("get_state", "set_state")
RETIRED_STATE_NAMES = ("state_dict", "load_state", "pipeline_state", "set_pipeline_state")


def test_no_module_of_the_package_is_over_800_lines():
    long = {
        str(path.relative_to(ROOT)): n
        for path in PACKAGE.rglob("*.py")
        if (n := len(path.read_text(encoding="utf-8").splitlines())) > MAX_MODULE_LINES
    }
    assert not long, f"modules over {MAX_MODULE_LINES} lines: split them by job: {long}"


def sys_path_edits(source: str) -> list[int]:
    """Line numbers of ``sys.path.insert``/``append``/``extend`` calls and assignments to ``sys.path``."""
    lines = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute):
            target = node.func.value
            if (
                node.func.attr in ("insert", "append", "extend")
                and isinstance(target, ast.Attribute)
                and target.attr == "path"
                and isinstance(target.value, ast.Name)
                and target.value.id == "sys"
            ):
                lines.append(node.lineno)
        elif isinstance(node, (ast.Assign, ast.AugAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            for t in targets:
                if (
                    isinstance(t, ast.Attribute)
                    and t.attr == "path"
                    and isinstance(t.value, ast.Name)
                    and t.value.id == "sys"
                ):
                    lines.append(node.lineno)
    return sorted(lines)


def test_no_benchmark_edits_the_import_path():
    edits = [
        f"{path.relative_to(ROOT)}:{line}"
        for path in sorted((ROOT / "benchmarks").rglob("*.py"))
        for line in sys_path_edits(path.read_text(encoding="utf-8"))
    ]
    assert not edits, f"benchmarks import the harness as a package (python -m benchmarks.X): {edits}"


def test_the_path_edit_finder_finds_an_insert_an_append_and_an_assignment():
    source = "import sys\nsys.path.insert(0, 'x')\nsys.path.append('y')\nsys.path = []\nlist.insert(0, 1)\n"
    assert sys_path_edits(source) == [2, 3, 4]


def state_contract_breaches(source: str) -> list[str]:
    """What breaks the one state contract in a module: a retired name defined, or a class with one half only."""
    breaches = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and node.name in RETIRED_STATE_NAMES:
            breaches.append(f"{node.name} (line {node.lineno}): say get_state/set_state")
        if isinstance(node, ast.ClassDef):
            methods = {item.name for item in node.body if isinstance(item, (ast.FunctionDef, ast.AsyncFunctionDef))}
            halves = methods & set(STATE_NAMES)
            if len(halves) == 1:
                breaches.append(f"class {node.name} (line {node.lineno}) has {halves.pop()} without its pair")
    return breaches


def test_every_stage_saves_and_restores_by_one_pair_of_names():
    breaches = [
        f"{path.relative_to(ROOT)}: {breach}"
        for path in sorted(PACKAGE.rglob("*.py"))
        for breach in state_contract_breaches(path.read_text(encoding="utf-8"))
    ]
    assert not breaches, breaches


def test_the_state_contract_finder_finds_a_retired_name_and_a_lone_half():
    source = (
        "class A:\n    def get_state(self): ...\n    def set_state(self, s): ...\n"
        "class B:\n    def get_state(self): ...\n"
        "class C:\n    def state_dict(self): ...\n"
    )
    assert state_contract_breaches(source) == [
        "class B (line 4) has get_state without its pair",
        "state_dict (line 7): say get_state/set_state",
    ]
