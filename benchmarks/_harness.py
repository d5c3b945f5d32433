"""The documentation's benchmark figures are written by the benchmarks, never copied by hand.

The blocks live in the README and the documentation site's pages (``docs/**/*.md``; ``documents()``), each
block in one of them.  Every benchmark takes ``--update-readme``: it prints as always and then replaces its
block in the document that holds it with ``$ COMMAND`` and what it printed.  A block is the fenced text
between two markers named by the command that makes it (the script and its arguments, less
``--update-readme`` and ``--workdir DIR``, a cache that changes no figure)::

    <!-- bench: bench_population.py --adapt -->
    ```
    $ python benchmarks/bench_population.py --adapt
    ...
    ```
    <!-- /bench -->

A command without a block in any document is an error before any work is done: a new figure gets its
block first, by hand, empty.
"""

from __future__ import annotations

import contextlib
import io
import re
import sys
from collections.abc import Callable, Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
END = "<!-- /bench -->"


class _Tee(io.TextIOBase):
    def __init__(self, *streams) -> None:
        self.streams = streams

    def write(self, text: str) -> int:
        for stream in self.streams:
            stream.write(text)
        return len(text)

    def flush(self) -> None:
        for stream in self.streams:
            stream.flush()


def block_key(script: str, argv: list[str]) -> str:
    """The block's name: the script's file name and its arguments, less ``--update-readme``,
    ``--workdir DIR``, ``--reuse DIR`` and ``--workers N`` (or ``=``): where it works, which captures it reads
    instead of simulating them again and how many processes it uses never change a figure."""
    shown, skip = [], False
    for arg in argv:
        if skip:
            skip = False
        elif arg == "--update-readme" or arg.startswith(("--workdir=", "--workers=", "--reuse=")):
            continue
        elif arg in ("--workdir", "--workers", "--reuse"):
            skip = True
        else:
            shown.append(arg)
    return " ".join([Path(script).name, *shown])


def documents(root: Path = ROOT) -> list[Path]:
    """The documents that may hold blocks: the README and every page of the documentation site."""
    return [root / "README.md", *sorted((root / "docs").rglob("*.md"))]


def document_with(key: str, root: Path = ROOT) -> Path:
    """The document holding block ``key`` (``ValueError`` when none does)."""
    for path in documents(root):
        if f"<!-- bench: {key} -->\n" in path.read_text():
            return path
    raise ValueError(f"no document has a block <!-- bench: {key} -->: add it (empty) first")


def blocks(text: str) -> dict[str, str]:
    """Every block of a README: key -> its text between the markers."""
    return {m.group(1): m.group(2) for m in re.finditer(r"<!-- bench: (.+?) -->\n(.*?)" + re.escape(END), text, re.S)}


def replace_block(text: str, key: str, body: str) -> str:
    """``text`` with block ``key`` replaced by ``body`` in a fence (``ValueError`` without the block)."""
    pattern = re.compile(rf"(<!-- bench: {re.escape(key)} -->\n)(.*?)({re.escape(END)})", re.S)
    if not pattern.search(text):
        raise ValueError(f"README.md has no block <!-- bench: {key} -->: add it (empty) first")
    fenced = "```\n" + body.rstrip("\n") + "\n```\n"
    return pattern.sub(lambda m: m.group(1) + fenced + m.group(3), text, count=1)


@contextlib.contextmanager
def readme_output(key: str, *, update: bool, readme: Path | None = None) -> Iterator[None]:
    """Print as usual; with ``update``, on success also write ``$ command`` and the output into block ``key``
    (in ``readme``; by default the document that holds the block)."""
    if not update:
        yield
        return
    if readme is None:
        readme = document_with(key)
    replace_block(readme.read_text(), key, "")  # the block exists: checked before the work, not after it
    captured = io.StringIO()
    with contextlib.redirect_stdout(_Tee(sys.stdout, captured)):
        yield
    command = "python benchmarks/" + key
    readme.write_text(replace_block(readme.read_text(), key, f"$ {command}\n{captured.getvalue()}"))
    print(f"{readme.name}: block {key!r} updated", file=sys.stderr)


def run_main(main: Callable[[], None]) -> None:
    """A benchmark's entry point: ``main()``, with ``--update-readme`` taken off the command line first."""
    update = "--update-readme" in sys.argv[1:]
    key = block_key(sys.argv[0], sys.argv[1:])
    sys.argv[1:] = [a for a in sys.argv[1:] if a != "--update-readme"]
    if update:  # a missing block is refused before the work (readme_output checks it too)
        try:
            replace_block(document_with(key).read_text(), key, "")
        except ValueError as exc:
            raise SystemExit(f"{Path(sys.argv[0]).name}: {exc}") from None
    with readme_output(key, update=update):
        main()
