"""What the benchmarks share: the seed sets of the population, the pool over instruments, the capture cache, and
the figure blocks they write into the documentation.

Every benchmark runs from the repository's top as a module, ``python -m benchmarks.bench_x [ARGS]``, and imports
this module as ``benchmarks._harness``; ``python -m benchmarks`` runs the quick ones and rewrites their blocks
(``benchmarks/__main__.py``, which also names the long ones).

**The seed sets and THE RULE.**  Instrument seeds (``fog_driver.sim.population.draw_instrument``) come in ranges,
``SEED_SETS``.  ``dev`` (0 ..) is for developing and tuning: look at it as often as you like.  Every other set is
reserved for evaluation: nobody looks at one while developing a model, choosing its settings or its structure; one
is run to report a model that is finished, and what it shows is reported as it is, never fed back.  Each model
version is evaluated on a range no earlier version was developed after: a range whose results have steered
development is spent, and the next version goes to a fresh one (which set was spent by which run:
``docs/decisions/``).  Individual evaluation instruments are not studied: to find what failed there, draw more
development instruments (``--set dev --first 72``) and look for the same failure among them.  Instrument K's run
of a profile has the run seed ``10 K + j``, ``j`` per profile (``FIT_RUN`` for the fit's; each benchmark names
its others).  ``families-screen`` (92 000 ..) and ``families-eval`` (93 000 ..) are for the physics families
(``fog_driver.sim.families``, ``--family``) and for nothing else: ``families-screen`` to see whether a method's
sigma misses a target on a family the development population never had, ``families-eval`` for the one
evaluation of the finished method on the families; the same rule holds for both.

**The capture cache.**  ``capture`` simulates instrument K's run of a profile once into a work directory
(``--workdir``, else a temporary one), keyed by instrument, profile, run seed and rate, and again only when the
cached sidecar holds another instrument.

**The pool.**  ``in_pool`` maps a function over instruments, ``--workers`` processes at a time (two by default:
the machine has two cores), results in order, each as soon as it and those before it are done;
``over_instruments`` does it for the instruments of ``instrument_arguments``.

**The figure blocks.**  The documentation's benchmark figures are written by the benchmarks, never copied by
hand.  The blocks live in the README and the documentation site's pages (``docs/**/*.md``; ``documents()``), each
block in one of them.  A benchmark whose figures the documents quote ends in ``run_main(main)`` and takes
``--update-readme``: it prints as always and then replaces its block in the document that holds it with
``$ COMMAND`` and what it printed.  A block is the fenced text between two markers named by the command that
makes it (the script's file name and its arguments, less ``--update-readme``, ``--workdir DIR``, ``--reuse DIR``
and ``--workers N``, which change no figure)::

    <!-- bench: bench_population.py --adapt -->
    ```
    $ python -m benchmarks.bench_population --adapt
    ...
    ```
    <!-- /bench -->

A command without a block in any document is an error before any work is done: a new figure gets its block
first, by hand, empty.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import re
import sys
import tempfile
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from fog_driver.lab.profiles import BUILTIN_PROFILES, SimProfile, load_profile
from fog_driver.samples.captures import read_provenance
from fog_driver.sim.capture import simulate_to_file
from fog_driver.sim.instrument import Simulator
from fog_driver.sim.population import draw_instrument

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


def command_of(key: str) -> str:
    """The command that writes block ``key``: ``bench_x.py ARGS`` -> ``python -m benchmarks.bench_x ARGS``."""
    script, _, arguments = key.partition(" ")
    return " ".join(["python -m benchmarks." + script.removesuffix(".py"), *([arguments] if arguments else [])])


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
    command = command_of(key)
    readme.write_text(replace_block(readme.read_text(), key, f"$ {command}\n{captured.getvalue()}"))
    print(f"{readme.name}: block {key!r} updated", file=sys.stderr)


def run_main(main: Callable[[], int | None]) -> None:
    """A benchmark's entry point: ``main()``, with ``--update-readme`` taken off the command line first; a
    non-zero status ``main`` returns is the process's exit status, and its block is left as it was."""
    update = "--update-readme" in sys.argv[1:]
    key = block_key(sys.argv[0], sys.argv[1:])
    sys.argv[1:] = [a for a in sys.argv[1:] if a != "--update-readme"]
    if update:  # a missing block is refused before the work (readme_output checks it too)
        try:
            replace_block(document_with(key).read_text(), key, "")
        except ValueError as exc:
            raise SystemExit(f"{Path(sys.argv[0]).name}: {exc}") from None
    with readme_output(key, update=update):
        status = main()
        if status:
            raise SystemExit(status)


SEED_SETS = {
    "dev": 0,
    "eval": 10_000,
    "eval2": 20_000,
    "eval3": 30_000,
    "eval4": 40_000,
    "eval5": 50_000,
    "eval6": 60_000,
    "eval7": 70_000,
    "eval8": 80_000,
    "eval9": 90_000,
    "eval10": 95_000,
    "eval11": 96_000,
    "eval12": 97_000,
    "eval13": 98_000,
    "eval14": 99_000,
    "families-screen": 92_000,  # the physics families only (THE RULE)
    "families-eval": 93_000,  # the physics families only (THE RULE)
}  #: first instrument seed of each set (THE RULE above)
#: The profile every population benchmark fits on, and its run seed's j.
FIT_PROFILE = "paper"
FIT_RUN = 1
#: Where the population benchmarks score by default (never fitted on).
SCORE_PROFILES = ("soak-cycle", "steps-moves")
#: The first minutes of a run are not scored (the chamber and the model settling).
SKIP_MINUTES = 10


def instrument_seeds(seed_set: str, first: int, count: int) -> list[int]:
    """The instrument seeds of ``count`` instruments of ``seed_set`` from its ``first``."""
    return [SEED_SETS[seed_set] + first + k for k in range(count)]


def instrument_arguments(parser: argparse.ArgumentParser, instruments: int) -> None:
    """The instruments a population benchmark runs on: ``--set`` (default dev), ``--first``, ``--instruments``,
    and how: ``--workers``, ``--workdir`` (captures kept there; default a temporary directory)."""
    parser.add_argument("--set", choices=SEED_SETS, default="dev")
    parser.add_argument("--first", type=int, default=0)
    parser.add_argument("--instruments", type=int, default=instruments)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--workdir", type=Path)


@contextlib.contextmanager
def kept_or_temporary(workdir: Path | None) -> Iterator[Path]:
    """``workdir`` (kept), or a temporary directory removed at the end."""
    with tempfile.TemporaryDirectory() as tmp:
        yield workdir or Path(tmp)


def in_pool(function: Callable[..., Any], workers: int, *columns: Iterable[Any]) -> Iterator[Any]:
    """``function(*row)`` for each row of ``columns`` (as ``map``), ``workers`` processes at a time: the results
    in order, each as soon as it and those before it are done."""
    with ProcessPoolExecutor(workers) as pool:
        yield from pool.map(function, *columns)


def over_instruments(args: argparse.Namespace, score: Callable[..., Any], *same: object) -> tuple[list[int], list]:
    """``score(seed, *same, workdir)`` for each instrument of ``args`` (``instrument_arguments``), ``--workers``
    at a time; returns the seeds and the results, in order."""
    seeds = instrument_seeds(args.set, args.first, args.instruments)
    with kept_or_temporary(args.workdir) as workdir:
        columns = [[value] * len(seeds) for value in same]
        return seeds, list(in_pool(score, args.workers, seeds, *columns, [workdir] * len(seeds)))


def resolve_profile(name: str) -> SimProfile:
    """A profile by name: built-in, else ``configs/profiles/<name>.yaml`` (``calibration``: the built-in once it
    ships, the file until then); a missing one is a one-line ``InputFileError``."""
    return load_profile(name if name in BUILTIN_PROFILES else ROOT / "configs" / "profiles" / f"{name}.yaml")


def capture(
    workdir: Path, seed: int, profile: str | SimProfile, run_seed: int, rate_hz: int, family: str | None = None
) -> Path:
    """Instrument ``seed``'s run of ``profile`` (a name for ``resolve_profile``, or a profile made here), with
    the physics ``family`` (None: the development population's), cached by its name (in ``i<seed>``, with a
    family ``i<seed>-<family>``), and simulated again when the cached one's sidecar holds another instrument K
    (a cache made before the population changed)."""
    name = profile if isinstance(profile, str) else profile.name
    out = workdir / (f"i{seed}" if family is None else f"i{seed}-{family}") / f"{name}-r{run_seed}-{rate_hz}hz.bin"
    config = draw_instrument(seed, family=family)
    if out.exists() and (read_provenance(out) or {}).get("model") != config.as_dict():
        out.unlink()  # simulated by a version whose instrument K differed (e.g. before its scale-factor draws)
    if not out.exists():
        out.parent.mkdir(parents=True, exist_ok=True)
        sim_profile = resolve_profile(profile) if isinstance(profile, str) else profile
        sim = Simulator(sim_profile, config, rate_hz=rate_hz, seed=run_seed)
        simulate_to_file(sim, out.with_suffix(".part.bin"))
        for suffix in (".bin", ".bin.yaml", ".truth.csv", ".table.csv"):  # complete files only: an interrupted
            part = out.with_suffix(".part" + suffix)  # run redoes them (a table log only with dwells)
            if suffix != ".table.csv" or part.exists():
                part.rename(out.with_suffix(suffix))
    return out


def static_minutes_mask(truth: dict[str, np.ndarray], n: int) -> np.ndarray:
    """Seconds that count: no table motion (true input rate 0) and after the first ``SKIP_MINUTES``."""
    mask = truth["input_dph"][:n] == 0.0
    mask[: SKIP_MINUTES * 60] = False
    return mask
