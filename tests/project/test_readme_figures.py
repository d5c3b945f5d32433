"""The documentation's benchmark figures (the README and the site's pages) are blocks a benchmark writes
(``--update-readme``), each named by the command that makes it: this checks the blocks are what their commands
printed, in form."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks"))

import readme_block  # noqa: E402


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
    assert readme_block.block_key("benchmarks/bench_population.py", argv) == "bench_population.py --set dev --adapt"


def test_a_block_is_replaced_in_place_and_a_missing_one_is_an_error():
    text = "a\n<!-- bench: x.py --n 1 -->\n```\nold\n```\n<!-- /bench -->\nb\n<!-- bench: x.py -->\n<!-- /bench -->\n"
    new = readme_block.replace_block(text, "x.py", "$ cmd\nfigures")
    assert readme_block.blocks(new) == {"x.py --n 1": "```\nold\n```\n", "x.py": "```\n$ cmd\nfigures\n```\n"}
    with pytest.raises(ValueError, match="no block"):
        readme_block.replace_block(text, "y.py", "z")


def test_update_readme_writes_the_output_and_refuses_before_the_work_without_a_block(tmp_path, capsys):
    readme = tmp_path / "README.md"
    readme.write_text("<!-- bench: b.py --k -->\n<!-- /bench -->\n")
    with readme_block.readme_output("b.py --k", update=True, readme=readme):
        print("figure 1.23")
    assert (
        readme_block.blocks(readme.read_text())["b.py --k"] == "```\n$ python benchmarks/b.py --k\nfigure 1.23\n```\n"
    )
    worked = []
    with pytest.raises(ValueError), readme_block.readme_output("other.py", update=True, readme=readme):
        worked.append(1)
    assert not worked


def test_a_block_is_found_in_the_document_that_holds_it(tmp_path):
    (tmp_path / "docs" / "explanation").mkdir(parents=True)
    (tmp_path / "README.md").write_text("no blocks\n")
    page = tmp_path / "docs" / "explanation" / "page.md"
    page.write_text("<!-- bench: b.py --k -->\n<!-- /bench -->\n")
    assert readme_block.document_with("b.py --k", tmp_path) == page
    with pytest.raises(ValueError, match="no document"):
        readme_block.document_with("b.py", tmp_path)


def test_every_readme_block_holds_its_own_command_and_a_script_that_can_write_it():
    blocks: dict[str, str] = {}
    for path in readme_block.documents():
        found = readme_block.blocks(path.read_text())
        assert not set(found) & set(blocks), f"{path}: a block that another document holds too"
        blocks.update(found)
    assert len(blocks) >= 12
    for key, body in blocks.items():
        script = ROOT / "benchmarks" / key.split()[0]
        assert script.exists(), key
        assert "run_main(main)" in script.read_text(), f"{script.name} cannot --update-readme"
        lines = body.splitlines()
        assert lines[0] == "```" and lines[-1] == "```" and len(lines) > 3, key
        assert lines[1] == f"$ python benchmarks/{key}", key
