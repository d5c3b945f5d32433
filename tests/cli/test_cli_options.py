"""No command crashes on any combination of its options: for each of ``plan``, ``simulate`` (and ``simulate
--serve`` on its own), ``fit``, ``compensate``, ``evaluate``, ``record``, ``inspect``, ``ctl`` and ``watch``,
hypothesis draws every numeric and choice option from wide ranges (zero, negative, tiny, subnormal, huge, NaN
and infinity where a float is parsed, and valid values) and the flags in any combination, and runs
``fog_driver.cli.main`` in-process.  ``ctl`` and ``watch`` talk to a closed loopback port: their exit status
is predicted from their documented rules (argparse's 2, 64, or 69: the daemon not there).  Each run must end
in one of:

* exit 0 with the command's documented output, checked where it can be (a file written and read back);
* one ``fog-driver: error: ...`` line on stderr and a documented non-zero exit (README's table, never 70);
* argparse's usage error (exit 2);

and never a traceback (on stderr, or a Python exception out of ``main``), an ``internal_error`` log line or a
Python warning.  ``plan``'s program is checked against its limits independently, from the written YAML.

Options that size the work (durations, rates, the faults' rates) are drawn valid only up to what finishes in
about a second; huge ones are refused, or interrupted, in ``test_huge_work_is_refused_or_interrupted_...``.
Paths are not drawn: each path option takes one of the fixtures below, a file of another kind, a missing
file, or (outputs) a new or an existing file.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import math
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from subprocess import PIPE

import numpy as np
import pytest
import structlog
import yaml
from hypothesis import HealthCheck, currently_in_test_context, event, given, settings
from hypothesis import strategies as st

from fog_driver.cli import main
from fog_driver.cli.argtypes import positive_float, rate_hz
from fog_driver.cli.parser import command_in
from fog_driver.files.kinds import ROW_COLUMNS
from fog_driver.formats.registry import FORMATS
from fog_driver.lab.plan import DEFAULT_LIMITS
from fog_driver.lab.profiles import load_profile
from fog_driver.lab.program import Hold, Ramp, Sinusoid
from fog_driver.modelfiles import load_model
from fog_driver.samples.captures import inspect_capture, read_provenance
from fog_driver.sim.instrument import WIRE_FORMATS
from fog_driver.sim.population import MAX_INSTRUMENT_SEED

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT / "tests" / "data"
GOLDEN_MODELS = DATA / "golden" / "models"
INSTRUMENT = ROOT / "configs" / "sim" / "instrument.yaml"
KVH_CONFIG = ROOT / "configs" / "kvh-dsp1750.yaml"

#: README's exit-code table: what a command may exit with (70 is a bug; 1 is inspect --strict's alone).
DOCUMENTED_ERRORS = {64, 65, 69, 73, 75, 77, 78}
USAGE = 2  # argparse

#: The examples per command, and the settings every property here runs with: the same examples at every run
#: (``FOG_OPTIONS_EXAMPLES=N``: N examples, new ones at each run, to look further).
EXAMPLES = int(os.environ.get("FOG_OPTIONS_EXAMPLES", "50"))
PROPERTY = settings(
    max_examples=EXAMPLES,
    derandomize="FOG_OPTIONS_EXAMPLES" not in os.environ,
    database=None,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.filter_too_much],
)
#: ``evaluate``'s: fewer, as each report it writes draws its plots (0.7 s a report, four in five examples).
EVALUATE = settings(PROPERTY, max_examples=EXAMPLES * 3 // 5)
#: ``ctl``'s and ``watch``'s against a closed port: more, as each takes some 10 ms (a refused connection).
CLIENT = settings(PROPERTY, max_examples=EXAMPLES * 4)
#: ``simulate --serve``'s: fewer, as a stream drawn valid runs for up to ``WALL_BUDGET_S``.
SERVE = settings(PROPERTY, max_examples=EXAMPLES * 2 // 5)

#: Frames and device seconds a drawn simulation may make, and the wall seconds a drawn real-time run
#: (``simulate --serve``, ``record``) may take: about a second of work at most.
FRAME_BUDGET = 20_000
DEVICE_S_BUDGET = 6_000.0
WALL_BUDGET_S = 0.2


# --- running a command in-process ---------------------------------------------------------------------


@dataclass(frozen=True, repr=False)
class Outcome:
    argv: tuple[str, ...]
    status: int
    stdout: str
    stderr: str
    warnings: tuple[str, ...]

    def __repr__(self) -> str:  # what an assertion shows: the whole run
        argv = " ".join(self.argv)
        text = f"fog-driver {argv}\n-> exit {self.status}\nstdout:\n{self.stdout}\nstderr:\n{self.stderr}"
        return text + (f"Python warnings: {self.warnings}" if self.warnings else "")


def run_main(argv: list[str]) -> Outcome:
    """``fog-driver ARGV`` in this process: its exit status (``SystemExit``'s for argparse), stdout, stderr
    (the log's lines with it: structlog looks ``sys.stderr`` up at each line) and the Python warnings it
    raised.  An exception out of ``main`` is not caught: the test fails on it, as a user would see a
    traceback."""
    out, err = io.StringIO(), io.StringIO()
    with (
        warnings.catch_warnings(record=True) as caught,
        contextlib.redirect_stdout(out),
        contextlib.redirect_stderr(err),
    ):
        warnings.simplefilter("always")
        try:
            status = main(argv)
        except SystemExit as exc:  # argparse
            status = exc.code if isinstance(exc.code, int) else 1
        finally:
            structlog.reset_defaults()
    seen = tuple(f"{w.category.__name__}: {w.message} ({w.filename}:{w.lineno})" for w in caught)
    return Outcome(tuple(argv), status, out.getvalue(), err.getvalue(), seen)


def error_lines(outcome: Outcome) -> list[str]:
    return [line for line in outcome.stderr.splitlines() if line.startswith("fog-driver: error:")]


def check_outcome(outcome: Outcome, *, strict: bool = False) -> str:
    """The outcome is one the module docstring allows: "ok", "error" (one line, a documented status) or
    "usage" (argparse's exit 2); with ``strict`` (``inspect --strict``) also "problems": exit 1 with the
    report and no error line."""
    if currently_in_test_context():  # (hypothesis' statistics: what the examples ended in)
        event(f"{command_in(outcome.argv)}: exit {outcome.status}")
    assert "Traceback" not in outcome.stderr, outcome
    assert "internal_error" not in outcome.stderr and "internal error" not in outcome.stderr, outcome
    assert outcome.status != 70, outcome
    assert not outcome.warnings, outcome
    if outcome.status == 0 or (strict and outcome.status == 1):
        assert error_lines(outcome) == [], outcome
        return "ok" if outcome.status == 0 else "problems"
    if outcome.status == USAGE:
        assert "usage: fog-driver" in outcome.stderr and "error:" in outcome.stderr, outcome
        return "usage"
    assert outcome.status in DOCUMENTED_ERRORS, outcome
    lines = error_lines(outcome)
    assert len(lines) == 1, outcome
    assert outcome.stderr.rstrip("\n").splitlines()[-1] == lines[0], outcome  # the last word on stderr
    return "error"


@contextlib.contextmanager
def example_dir(base: Path):
    """A fresh directory for one example, removed after it."""
    path = Path(tempfile.mkdtemp(dir=base))
    try:
        yield path
    finally:
        shutil.rmtree(path, ignore_errors=True)


# --- values -------------------------------------------------------------------------------------------

#: Float texts no option should crash on: zero, negative, tiny, subnormal, huge, overflowing, NaN, infinity,
#: Python's float() spellings, and no number at all.
ODD_FLOATS = (
    "0",
    "-0",
    "-1",
    "-1e-300",
    "1e-300",
    "1e-308",
    "5e-324",
    "1e-9",
    "1e300",
    "1e308",
    "1.7976931348623157e308",
    "1e400",
    "-1e400",
    "nan",
    "-nan",
    "NaN",
    "inf",
    "-inf",
    "Infinity",
    "1_0",
    " 2 ",
    "",
    "x",
    "0x10",
)
#: The same, without the huge ones: for options that size the work (huge ones: their own test below).
ODD_WORK_FLOATS = tuple(
    x for x in ODD_FLOATS if x not in ("1e300", "1e308", "1.7976931348623157e308", "1e400", "inf", "Infinity")
)
#: Integer texts: zero, negative, the edges of u16, i32, u64, a hundred-digit number, and no integer at all.
ODD_INTS = ("0", "-1", "-0", "1", "65535", "65536", "2147483648", "18446744073709551616", "1" + "0" * 100)
ODD_INTS += ("1.5", "1e3", "nan", "", "x", " 7 ", "1_0")
#: Odd words for a choice option.
ODD_CHOICES = ("bogus", "", "AUTO", "fog-v1 ")


def log_uniform(lo: float, hi: float) -> st.SearchStrategy[float]:
    """Floats from ``lo`` to ``hi`` (both > 0), as many in each decade."""
    return st.floats(math.log10(lo), math.log10(hi)).map(lambda e: min(max(10.0**e, lo), hi))


def as_float(text: str) -> float | None:
    """What Python's ``float`` makes of an option's text, or None."""
    try:
        return float(text)
    except ValueError:
        return None


def parsed(argtype, text: str | None):
    """The value the option's argument type makes of ``text``, or None (not given, or refused: exit 2)."""
    if text is None:
        return None
    try:
        return argtype(text)
    except argparse.ArgumentTypeError:
        return None


def option(name: str, value: str) -> str:
    """``--name=value``: a value starting with ``-`` is the option's, not another option."""
    return f"{name}={value}"


def options(values: dict[str, object]) -> list[str]:
    """``--name=value`` for each option given (not None)."""
    return [option(k, str(v)) for k, v in values.items() if v is not None]


class Drawer:
    """An example's draws.  Each option's text is valid, or odd with the example's ``odds`` (drawn first:
    none in half the examples, so that combinations of valid values are tried as often as odd ones)."""

    def __init__(self, data) -> None:
        self.data = data
        #: how many in twenty of the example's options are odd
        self.odds = data.draw(st.sampled_from([0, 0, 0, 1, 3, 6]), "odds")

    def __call__(self, strategy: st.SearchStrategy, label: str | None = None):
        return self.data.draw(strategy, label)

    def odd(self) -> bool:
        """Whether the next option is odd (a list, not a float below the odds: hypothesis draws the ends of a
        range far more often than their share, and shrinks to its first element, valid)."""
        return self.odds > 0 and self(st.sampled_from([False] * (20 - self.odds) + [True] * self.odds))

    def given(self) -> bool:
        """An optional option: given or not."""
        return self(st.booleans())

    def float(self, valid: st.SearchStrategy[float], odd: tuple[str, ...] = ODD_FLOATS) -> str:
        """A float option's text: valid, or odd (one of ``odd``, or any float at all)."""
        if not self.odd():
            return repr(self(valid))
        return self(st.sampled_from(odd)) if self.given() else repr(self(st.floats()))

    def work(self, hi: float, lo: float = 1e-3) -> str:
        """The text of an option that sizes the work: valid up to ``hi`` (what finishes in about a second),
        or odd (``ODD_WORK_FLOATS``: non-positive, tiny, NaN, no number; or any float up to ``hi``)."""
        if not self.odd():
            return repr(self(log_uniform(min(lo, hi), hi)))
        if self.given():
            return repr(self(st.floats(max_value=hi)))
        text = self(st.sampled_from(ODD_WORK_FLOATS))
        value = as_float(text)
        return repr(hi) if value is not None and value > hi else text  # ("1_0" is 10)

    def int(self, valid: st.SearchStrategy[int], odd: tuple[str, ...] = ODD_INTS) -> str:
        if not self.odd():
            return str(self(valid))
        return self(st.sampled_from(odd)) if self.given() else str(self(st.integers()))

    def file(self, paths: list[Path], others: list[Path]) -> Path:
        """One of ``paths``, or (odd) one of ``others``."""
        return self(st.sampled_from(others if self.odd() else paths))

    def choice(self, choices) -> str | None:
        """A choice option: not given, one of ``choices``, or (odd) a word that is none of them."""
        if self.odd():
            return self(st.sampled_from(ODD_CHOICES))
        return self(st.sampled_from([None, *choices]))

    def format_for(self, formats: set[str], auto: bool = True) -> str | None:
        """``--format`` for inputs in ``formats``: not given, ``auto``, or theirs (when they share one); or
        (odd) any format, or a word that is none."""
        if self.odd():
            return self(st.sampled_from([*FORMATS, *ODD_CHOICES]))
        return self(st.sampled_from([None, *(["auto"] if auto else []), *(formats if len(formats) == 1 else ())]))

    def flags(self, *names: str) -> list[str]:
        """Each flag, or not."""
        return [name for name in names if self.given()]

    def logging(self, command: list[str]) -> list[str]:
        """``command`` with ``-v`` up to three times and ``--log-format`` before or after its name."""
        words = ["-v"] * self(st.integers(0, 3))
        if self.given():
            words.append(option("--log-format", self.choice(["auto", "human", "json"]) or "auto"))
        return words + command if self.given() else command[:1] + words + command[1:]

    def output(self, here: Path, name: str) -> tuple[Path, list[str]]:
        """An output path: new, or (odd) already there (a file; a directory for a name without a suffix),
        with ``--force`` or not."""
        path = here / name
        if self.odd():
            path.write_text("already here\n") if "." in name else path.mkdir()
        return path, self.flags("--force")


def unchanged(path: Path, before: bytes | None) -> bool:
    """A file that was there is as it was; one that was not is still not there (a refused run writes nothing)."""
    return path.read_bytes() == before if before is not None else not path.is_file()


def contents(path: Path) -> bytes | None:
    return path.read_bytes() if path.is_file() else None


# --- the fixtures: the short captures in tests/data, and what is made of them once -----------------------

CAPTURES = ("sim-short", "sim-faults", "synthetic-clean", "synthetic-faults")
IXBLUE = sorted((DATA / "ixblue").glob("*.log"))[:2]


@dataclass(frozen=True)
class Files:
    base: Path
    fit_config: Path  # warm-up cut to 30 s: tests/data's captures last 300 s
    wesn: Path  # fitted on sim-short
    polynomial: Path
    other_serial: Path  # a model of another instrument
    positioning: Path  # a simulated positioning run, 5 Hz, with its table log and truth
    kvh: Path  # a simulated KVH capture
    kvh_model: Path  # fitted on it
    not_a_capture: Path  # a text file
    minute: Path  # a profile of one minute
    bad_instrument: Path  # an instrument file with a negative time constant

    @property
    def captures(self) -> list[Path]:
        return [*(DATA / f"{name}.bin" for name in CAPTURES), self.positioning, self.kvh]

    @property
    def models(self) -> list[Path]:
        return [
            self.wesn,
            self.polynomial,
            self.other_serial,
            *(GOLDEN_MODELS / name for name in ("paper.yaml", "wesn-cascade.yaml", "polynomial-domain.yaml")),
        ]

    @property
    def table_log(self) -> Path:
        return self.positioning.with_suffix(".table.csv")

    @property
    def truths(self) -> list[Path]:
        return [c.with_suffix(".truth.csv") for c in self.captures if c.with_suffix(".truth.csv").is_file()]

    def models_for(self, capture: Path) -> list[Path]:
        """The models of the capture's instrument (none for the synthetic captures' FOG-SYN-0001)."""
        if capture == self.kvh:
            return [self.kvh_model]
        return [] if capture.name.startswith("synthetic") else [m for m in self.models if m != self.other_serial]

    def format_of(self, capture: Path) -> str:
        return "kvh-a" if capture == self.kvh else "fog-v1"

    def truth_of(self, capture: Path) -> Path | None:
        truth = capture.with_suffix(".truth.csv")
        return truth if truth.is_file() else None

    @property
    def others(self) -> list[Path]:
        """Inputs of other kinds than asked: a text file, a missing file, a directory."""
        return [self.not_a_capture, self.base / "missing.bin", self.base]


def made(argv: list[str]) -> None:
    outcome = run_main(argv)
    assert outcome.status == 0, outcome


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> Files:
    base = tmp_path_factory.mktemp("cli-options")
    fit_config = base / "fit.yaml"
    fit_config.write_text("warmup_s: 30\n")
    short = str(DATA / "sim-short.bin")
    wesn, polynomial = base / "wesn.yaml", base / "polynomial.yaml"
    for kind, path in (("wesn", wesn), ("polynomial", polynomial)):
        made(["fit", short, "--config", str(fit_config), "--accept-weak-fit", "--kind", kind, "--out", str(path)])
    other_serial = base / "other.yaml"
    doc = yaml.safe_load(polynomial.read_text())
    doc["instrument_serial"] = "FOG-SIM-9999"
    other_serial.write_text(yaml.safe_dump(doc, sort_keys=False))
    assert load_model(other_serial).instrument_serial == "FOG-SIM-9999"
    positioning = base / "pos.bin"
    made(["simulate", "--profile", "positioning", "--rate-hz", "5", "--out", str(positioning)])
    kvh, kvh_model = base / "kvh.bin", base / "kvh.yaml"
    made(["simulate", "--profile", "short-test", "--format", "kvh-a", "--rate-hz", "10", "--out", str(kvh)])
    made(["fit", str(kvh), "--config", str(fit_config), "--accept-weak-fit", "--out", str(kvh_model)])
    not_a_capture = base / "notes.txt"
    not_a_capture.write_text("a text file, not a capture\n")
    minute = base / "minute.yaml"
    minute.write_text("name: minute\nstart_c: 20\nsegments:\n  - ramp: {rate_c_per_min: 2, target_c: 22}\n")
    assert load_profile(minute).chamber.duration_s == 60.0
    bad_instrument = base / "bad-instrument.yaml"
    bad_instrument.write_text("thermal:\n  tau_housing_s: -480\n")
    return Files(
        base,
        fit_config,
        wesn,
        polynomial,
        other_serial,
        positioning,
        kvh,
        kvh_model,
        not_a_capture,
        minute,
        bad_instrument,
    )


# --- plan ----------------------------------------------------------------------------------------------

PLAN_FIELDS = {
    "--min-c": "min_c",
    "--max-c": "max_c",
    "--max-rate-c-per-min": "max_rate_c_per_min",
    "--minutes": "minutes",
}
PLAN_OPTIONS = {
    "--min-c": st.floats(-80, 60),
    "--max-c": st.floats(-20, 120),
    "--max-rate-c-per-min": log_uniform(1e-3, 120),
    "--minutes": log_uniform(1e-2, 12_000),
}


def plan_limits(d: Drawer) -> dict[str, str]:
    """The options given, each as text; a narrow range (max just above min) as often as a wide one."""
    limits = {name: d.float(valid) for name, valid in PLAN_OPTIONS.items() if d.given()}
    if "--min-c" in limits and d.given() and (low := as_float(limits["--min-c"])) is not None:
        limits["--max-c"] = repr(low + d(log_uniform(1e-6, 20)))
    return limits


def check_program(path: Path, limits: dict[str, float]) -> None:
    """The written program read back as a profile stays within the limits: every temperature within
    min..max (every segment's ends, a sinusoid's peaks, and the air temperature on a fine grid), no ramp
    and no sinusoid faster than the fastest ramp, and the whole within the minutes."""
    chamber = load_profile(path).chamber
    lo, hi, rate, minutes = (limits[k] for k in ("--min-c", "--max-c", "--max-rate-c-per-min", "--minutes"))
    tol = 1e-9 * max(1.0, abs(lo), abs(hi))
    assert 0 < chamber.duration_s <= minutes * 60.0 * (1 + 1e-12), (chamber.duration_s, minutes)
    assert lo - tol <= chamber.start_c <= hi + tol
    for span in chamber.spans():
        segment = span.segment
        assert isinstance(segment, (Hold, Ramp, Sinusoid)), segment  # no step: an infinite rate
        for temp in (span.start_c, span.end_c):
            assert lo - tol <= temp <= hi + tol, (span, lo, hi)
        if isinstance(segment, Ramp):
            assert segment.rate_c_per_min <= rate * (1 + 1e-12), (segment, rate)
        if isinstance(segment, Sinusoid):
            assert lo - tol <= span.start_c - segment.amplitude_c and span.start_c + segment.amplitude_c <= hi + tol
            peak = 2 * math.pi * segment.amplitude_c / (segment.period_s / 60.0)
            assert peak <= rate * (1 + 1e-9), (segment, rate)
    t = np.linspace(0.0, chamber.duration_s, 4001)
    air = chamber.air_temp_c(t)
    assert np.all(np.isfinite(air))
    assert lo - tol <= air.min() and air.max() <= hi + tol


@given(st.data())
@PROPERTY
def test_plan_with_any_limits_writes_a_program_within_them_or_says_why_not(files, data):
    d = Drawer(data)
    with example_dir(files.base) as here:
        limits = plan_limits(d)
        out, force = d.output(here, d(st.sampled_from(["p.yaml", "p.yaml", "p.yml", "p.txt"])))
        before = contents(out)
        outcome = run_main(d.logging(["plan", option("--out", str(out)), *options(limits), *force]))
        if check_outcome(outcome) == "ok":
            values = {k: float(limits.get(k, getattr(DEFAULT_LIMITS, f))) for k, f in PLAN_FIELDS.items()}
            check_program(out, values)
            assert outcome.stdout.startswith(f"wrote {out}: a "), outcome
        else:
            assert unchanged(out, before), outcome  # a refused plan writes nothing


# --- simulate ------------------------------------------------------------------------------------------


def fault_spec(d: Drawer) -> str | None:
    """``--faults``: not given, a malformed spec, or some of the five faults with numbers drawn wide (the
    garbage and thermometer rates size the work: drawn valid up to a few a second)."""
    if d.odd():
        return d(st.sampled_from(["drop", "drop=", "bogus=1", "drop=0.1,drop=0.2", "disconnect=5", "x" * 5000]))
    items = []
    for name in d(st.lists(st.sampled_from(["drop", "flip", "garbage", "thermo", "disconnect"]), unique=True)):
        if name in ("drop", "flip"):
            value = d.float(st.floats(0, 1))
        elif name == "garbage":
            value = d.work(10.0)
        elif name == "thermo":
            value = d.work(1.0) + (":" + d.float(st.floats(0.1, 100)) if d.given() else "")
        else:
            starts = sorted(d(st.lists(st.floats(0, 600), min_size=1, max_size=3, unique=True)))
            ends = [*starts[1:], math.inf]  # each cut shorter than the time to the next: none overlap
            value = "+".join(f"{t!r}:{d.float(st.floats(0, min(60, (e - t) / 2)))}" for t, e in zip(starts, ends))
        items.append(f"{name}={value}")
    return ",".join(items) or d(st.sampled_from([None, "none", ""]))


def profile_seconds(profile: str) -> float | None:
    """The length of the profile ``--profile`` names, or None when it names none."""
    try:
        return load_profile(profile).chamber.duration_s
    except Exception:
        return None


def simulate_case(d: Drawer, files: Files, here: Path, *, serving: bool = False) -> tuple[list[str], dict]:
    """``simulate``'s argv and what it asks for (the mode, the capture's path, the rate); with ``serving`` a
    ``--serve`` always (a pty, a device that is none, or both it and ``--out``)."""
    profiles = [str(files.minute), "short-test", "positioning", None]
    profile = d.file(profiles, ["no-such-profile", str(files.not_a_capture)])
    if serving:
        mode = d(st.sampled_from(["pty", "pty", "device", "both"]))
    else:
        mode = (
            "out" if not d.odd() and d(st.integers(0, 3)) else d(st.sampled_from(["pty", "device", "both", "neither"]))
        )
    values: dict[str, str | None] = {
        "--profile": profile,
        "--rate-hz": d.int(st.integers(1, 2000)) if d.given() else None,
        "--seed": d.int(st.integers(0, 2**64)) if d.given() else None,
        "--format": d.choice(WIRE_FORMATS),
        "--faults": fault_spec(d),
        "--instrument": d.file([None, str(INSTRUMENT)], [str(files.bad_instrument), "missing.yaml"]),
        "--instrument-seed": d.int(st.integers(0, MAX_INSTRUMENT_SEED)) if d.given() else None,
    }
    out, force = d.output(here, d.file(["run.bin"], ["run.dat"]))
    if mode in ("out", "both"):
        values["--out"] = str(out)
    serving = mode in ("pty", "device", "both")
    if serving:
        devices = ["/dev/null", str(here / "no-tty"), str(here), str(here / "notes.txt")]  # (none is a tty)
        values["--serve"] = "pty" if mode != "device" else d(st.sampled_from(devices))
        if values["--serve"] == str(here / "notes.txt"):
            (here / "notes.txt").write_text("not a tty\n")
        values["--speed"] = d.float(log_uniform(1e3, 1e6)) if d.given() else None
        values["--baud"] = d.int(st.sampled_from([9600, 115200, 460800, 921600])) if d.given() else None
    if mode in ("pty", "both") or d.odd():  # the link, never the default /tmp/fog-driver-sim.tty (others' runs)
        link = d.file(["sim.tty"], ["notes.txt", ".", "no-dir/sim.tty"])
        if link == "notes.txt":
            (here / link).write_text("not a link\n")
        values["--link"] = str(here / link)
    # the work: the duration, drawn valid up to what the budgets allow at the rate (and the speed) drawn
    rate = 100 if values["--rate-hz"] is None else parsed(rate_hz, values["--rate-hz"])  # None: refused
    speed = parsed(positive_float, values.get("--speed")) or 1.0
    bound = min(FRAME_BUDGET / (rate or 100), DEVICE_S_BUDGET, WALL_BUDGET_S * speed if serving else math.inf)
    length = profile_seconds(profile or "paper")
    duration = d.work(bound) if d.given() or length is None or length > bound else None
    values["--duration"] = duration
    words = ["simulate", *options(values), *(force if mode in ("out", "both") else [])]
    return words, {"mode": mode, "out": out, "rate": rate}


def check_simulated(outcome: Outcome, case: dict) -> None:
    """A capture written: its size as said, its sidecar complete, its truth beside it."""
    out = case["out"]
    said = r"simulated \S+ at (\d+) Hz, seed \d+: ([\d,]+) frames, ([\d,]+) bytes -> (.+) \(\+ .*\)\n"
    found = re.fullmatch(said, outcome.stdout)
    assert found, outcome
    assert int(found[1]) == case["rate"] and found[4] == str(out), outcome
    assert out.stat().st_size == int(found[3].replace(",", "")), outcome
    assert read_provenance(out)["status"] == "complete"
    assert out.with_suffix(".truth.csv").is_file()


def check_simulate(d: Drawer, files: Files, *, serving: bool = False) -> None:
    """One ``simulate`` example: drawn, run, and its outcome checked (a capture, a stream, or a refusal)."""
    with example_dir(files.base) as here:
        words, case = simulate_case(d, files, here, serving=serving)
        out = case["out"]
        before = contents(out)
        outcome = run_main(d.logging(words))
        kind = check_outcome(outcome)
        if kind == "ok" and case["mode"] == "out":
            check_simulated(outcome, case)
        elif kind == "ok":  # served: the readiness line, the summary line, and the link removed
            assert outcome.stdout.startswith("serving "), outcome
            assert re.search(r"^(served|stopped after) [\d,]+ frames", outcome.stdout, re.M), outcome
            assert not (here / "sim.tty").is_symlink(), outcome
        else:
            assert unchanged(out, before), outcome


@given(st.data())
@PROPERTY
def test_simulate_with_any_options_writes_a_capture_or_serves_or_says_why_not(files, data):
    check_simulate(Drawer(data), files)


@given(st.data())
@SERVE
def test_simulate_serve_with_any_options_streams_briefly_or_says_why_not(files, data):
    """``simulate --serve`` alone: a pty (or a device that is none: /dev/null, a missing path, a directory, a
    text file) with ``--speed`` (1e-308, 5e-324, 1e308, inf, nan among the odd), ``--baud``, ``--link`` and
    the rest; a stream drawn valid lasts at most ``WALL_BUDGET_S`` (its duration drawn for it at its speed)."""
    check_simulate(Drawer(data), files, serving=True)


# --- fit -----------------------------------------------------------------------------------------------

FIT_KINDS = ("wesn", "polynomial", "paper", "pso-svr")
#: ``fit --profile``'s: built-in names and a file's stem; (odd) names that are none
FIT_PROFILES: list[str | Path] = ["calibration", "paper", "short-test", "positioning"]
FIT_BAD_PROFILES: list[str | Path] = ["no-such-profile", ""]


def fit_config(d: Drawer, files: Files, here: Path) -> str | None:
    """``--config``: none, the fixtures' (a 30-s warm-up), or (odd) a missing file, a text file, an unknown
    key, or a warm-up drawn wide (YAML's own spellings of NaN and infinity included)."""
    if not d.odd():
        return str(files.fit_config)
    kind = d(st.sampled_from(["none", "missing", "text", "unknown", "drawn", "drawn"]))
    if kind in ("none", "missing", "text"):
        return {"none": None, "missing": str(here / "missing.yaml"), "text": str(files.not_a_capture)}[kind]
    path = here / "fit.yaml"
    if kind == "unknown":
        path.write_text("warmup: 30\n")
    else:
        value = d(st.sampled_from([".nan", ".inf", "-.inf", "1e400", "-5", "0", "30", "1e300", "x", "[]"]))
        path.write_text(f"warmup_s: {value}\n")
    return str(path)


@given(st.data())
@PROPERTY
def test_fit_with_any_options_writes_a_model_or_says_why_not(files, data):
    d = Drawer(data)
    with example_dir(files.base) as here:
        # the captures of one instrument (else another's, a capture too short to fit, or no capture)
        instrument = d(
            st.sampled_from([[DATA / "sim-short.bin", DATA / "sim-faults.bin", files.positioning], [files.kvh]])
        )
        others = [*files.others, DATA / "synthetic-clean.bin", files.kvh, DATA / "sim-short.bin"]
        captures = [d.file(instrument, others) for _ in range(d(st.integers(1, 2)))]
        validate = [d.file(instrument, others) for _ in range(d(st.integers(0, 2)))]
        copy = here / "copy.bin"  # a capture as --out: never overwritten, whatever --force says
        shutil.copyfile(DATA / "sim-short.bin", copy)
        out, force = (copy, d.flags("--force")) if d.odd() else d.output(here, d.file(["model.yaml"], ["model"]))
        before = contents(out)
        values = {
            "--out": out,
            "--kind": d.choice(FIT_KINDS),
            "--config": fit_config(d, files, here),
            "--format": d.format_for({files.format_of(c) for c in [*captures, *validate]}),
        }
        # --profile: none (the sidecars' programs), once for all or once per capture; (odd) a name that is
        # none, a text file, or one too many
        profiles = (
            []
            if not d.given()
            else [str(d.file(FIT_PROFILES + [files.minute], FIT_BAD_PROFILES + [files.not_a_capture]))]
        )
        if profiles and d.given():
            profiles += [str(d.file(FIT_PROFILES, FIT_BAD_PROFILES)) for _ in range(len(captures) - 1 + d.odd())]
        words = ["fit", *map(str, captures), *options(values), *(option("--validate", str(v)) for v in validate)]
        words += [option("--profile", profile) for profile in profiles]
        words += [*force, *(["--accept-weak-fit"] if not d.odd() else d.flags("--accept-weak-fit"))]
        outcome = run_main(d.logging(words))
        if check_outcome(outcome) == "ok":
            model = load_model(out)
            said = re.search(r"^fitted a (\S+) model for (\S*) on (\d+) capture\(s\)", outcome.stdout, re.M)
            assert said and (said[1], said[2]) == (model.kind, model.instrument_serial), outcome
            assert int(said[3]) == len(captures)
            assert model.kind in ((values["--kind"],) if values["--kind"] else ("wesn", "polynomial"))
        else:
            assert unchanged(out, before), outcome
        assert copy.read_bytes() == (DATA / "sim-short.bin").read_bytes()


# --- compensate ----------------------------------------------------------------------------------------


def read_rows(path: Path) -> tuple[list[str], np.ndarray]:
    """A compensate CSV's header and its first two columns (t_s, n_samples)."""
    lines = path.read_text().splitlines()
    rows = [line.split(",") for line in lines[1:]]
    return lines[0].split(","), np.array([[float(r[0]), float(r[1])] for r in rows]).reshape(-1, 2)


@given(st.data())
@PROPERTY
def test_compensate_with_any_options_writes_rows_or_says_why_not(files, data):
    d = Drawer(data)
    with example_dir(files.base) as here:
        capture = d.file(files.captures, files.others)
        model = d.file(files.models_for(capture) or files.models, [*files.models, *files.others])
        out, force = d.output(here, d.file(["out.csv"], ["out"]))
        before = contents(out)
        state = here / "state.yaml"
        state_kind = d.file(["none", "new"], ["text", "directory"])
        if state_kind == "text":
            state.write_text("not a state\n")
        elif state_kind == "directory":
            state.mkdir()
        adapting = d(st.sampled_from(["frozen", "frozen", "reference", "table"]))  # (the table: the positioning run's)
        if capture != files.positioning and adapting == "table" and not d.odd():
            adapting = "frozen"
        values = {
            "--model": model,
            "--out": out,
            "--every": d.float(log_uniform(1e-3, 1e4)) if d.given() else None,
            "--adapt-reference": d.float(st.floats(-1e3, 1e3)) if adapting == "reference" or d.odd() else None,
            "--table-log": d.file([files.table_log], files.others) if adapting == "table" or d.odd() else None,
            "--adapt-state": None if state_kind == "none" else state,
            "--scale-override": d.float(log_uniform(1e-4, 1.0)) if d.given() else None,
            "--format": d.format_for({files.format_of(capture)}),
        }
        force_model = ["--force-model"] if model not in files.models_for(capture) else d.flags("--force-model")
        words = ["compensate", str(capture), *options(values), *force, *(force_model if not d.odd() else [])]
        outcome = run_main(d.logging(words))
        if check_outcome(outcome) == "ok":
            header, rows = read_rows(out)
            assert tuple(header) == ROW_COLUMNS
            said = re.search(r"^compensated .*: ([\d,]+) rows every (\S+) s -> ", outcome.stdout, re.M)
            assert said and int(said[1].replace(",", "")) == len(rows), outcome
            assert len(rows) and np.all(np.diff(rows[:, 0]) > 0) and np.all(rows[:, 1] >= 1)
            if capture in files.captures[:4]:  # protocol v1: every SAMPLE frame inspect counts is in one row
                assert rows[:, 1].sum() == inspect_capture(capture).sample_frames, outcome
            assert out.with_name(out.name + ".yaml").is_file()  # its provenance
        else:
            assert unchanged(out, before), outcome


# --- evaluate ------------------------------------------------------------------------------------------


def zero_window(d: Drawer) -> str | None:
    """``--zero-window START:END``: not given, two numbers drawn wide, or (odd) no window at all."""
    if d.odd():
        return d(st.sampled_from(["", ":", "10", "10:", ":10", "1:2:3", "a:b", "nan:10", "0:inf", "10:5", "5:5"]))
    if not d.given():
        return None
    start = d(st.floats(0, 280))
    return f"{d.float(st.just(start))}:{d.float(st.floats(start + 1, 600))}"


@given(st.data())
@EVALUATE
def test_evaluate_with_any_options_writes_a_report_or_says_why_not(files, data):
    d = Drawer(data)
    with example_dir(files.base) as here:
        evaluated = [DATA / "sim-short.bin", files.positioning, files.kvh]  # (the others: too short, or moving)
        capture = d.file(evaluated, [*files.captures, *files.others])
        report = here / "report"
        kind = d.file(["new", "empty"], ["full", "file"])
        if kind in ("empty", "full"):
            report.mkdir()
        if kind == "full":
            (report / "notes.txt").write_text("a file of the user's\n")
        elif kind == "file":
            report.write_text("a file, not a folder\n")
        before = sorted(p.name for p in report.iterdir()) if report.is_dir() else None
        models = files.models_for(capture) or files.models
        truth, reference = files.truth_of(capture), files.table_log if capture == files.positioning else None
        values = {
            "--model": d.file(models, [*files.models, *files.others]),
            "--out": report,
            "--truth": d.file([truth], [*files.truths, *files.others]) if d.given() else None,
            "--reference": d.file([reference], [files.table_log, *files.others]) if d.given() else None,
            "--zero-window": zero_window(d),
            "--format": d.format_for({files.format_of(capture)}),
        }
        compare = [d.file(models, [*files.models, *files.others]) for _ in range(d(st.integers(0, 2)))]
        words = ["evaluate", str(capture), *options(values), *(option("--compare", str(m)) for m in compare)]
        words += d.flags("--json", "--force")
        if any(m not in files.models_for(capture) for m in [values["--model"], *compare]):
            words += ["--force-model"] if not d.odd() else []
        else:
            words += d.flags("--force-model")
        outcome = run_main(d.logging(words))
        if check_outcome(outcome) == "ok":
            summary = json.loads((report / "summary.json").read_text())
            assert (report / "report.md").is_file()
            if "--json" in words:
                assert json.loads(outcome.stdout.splitlines()[-1]).keys() == summary.keys(), outcome
        elif kind == "file":
            assert report.read_text() == "a file, not a folder\n"
        elif before is not None:
            assert sorted(p.name for p in report.iterdir()) == before, outcome  # nothing written on a refusal


# --- inspect -------------------------------------------------------------------------------------------


@given(st.data())
@PROPERTY
def test_inspect_with_any_options_reports_or_says_why_not(files, data):
    d = Drawer(data)
    capture = d.file([*files.captures, *IXBLUE], files.others)
    own = {"fog-v1"} if capture in files.captures[:-1] else {"kvh-a"} if capture == files.kvh else {"ixblue-stdbin"}
    words = ["inspect", str(capture), *options({"--format": d.format_for(own)})]
    words += d.flags("--json", "--strict")
    outcome = run_main(d.logging(words))
    if check_outcome(outcome, strict="--strict" in words) in ("ok", "problems"):
        if "--json" in words:
            found = json.loads(outcome.stdout)
            problems = found["problems"] if isinstance(found.get("problems"), list) else None
        else:
            verdict = re.search(r"^verdict +(.*)$", outcome.stdout, re.M)
            assert verdict, outcome
            problems = [] if verdict[1].startswith("clean") else [verdict[1]]  # (clean; a note on the format)
        if problems is not None and "--strict" in words:
            assert (outcome.status == 1) == bool(problems), outcome


# --- record --------------------------------------------------------------------------------------------


def record_port(d: Drawer, files: Files, here: Path) -> tuple[str, Path | None, bool]:
    """A port: a capture replayed (paced or not, unplugged at its end or idle), or (odd) a missing capture
    or device, ``/dev/null``, a malformed URL; with the capture it replays, and whether it surely ends by
    itself (unplugged at its end, unpaced) rather than going idle."""
    if d.odd():
        return (
            d(
                st.sampled_from(
                    [
                        f"replay://{here / 'missing.bin'}",
                        str(here / "ttyUSB9"),
                        "/dev/null",
                        "replay://",
                        "nosuch://x",
                        f"replay://{DATA / 'sim-short.bin'}?rate=",
                        f"replay://{DATA / 'sim-short.bin'}?rate=0",
                        f"replay://{DATA / 'sim-short.bin'}?unplug=2",
                    ]
                )
            ),
            None,
            False,
        )
    capture = d(st.sampled_from([*files.captures[:4], files.kvh]))
    query = {"unplug": d(st.sampled_from(["1", "1", "0"]))} if d(st.integers(0, 3)) else {}
    if not d(st.integers(0, 3)):  # paced (never slower than the budget: a drawn duration ends it)
        query["rate"] = d.float(log_uniform(2e5, 1e7))
    url = f"replay://{capture}" + ("?" + "&".join(f"{k}={v}" for k, v in query.items()) if query else "")
    return url, capture, query.get("unplug") == "1" and "rate" not in query


@given(st.data())
@PROPERTY
def test_record_with_any_options_records_or_says_why_not(files, data):
    d = Drawer(data)
    with example_dir(files.base) as here:
        port, replayed, unplugged = record_port(d, files, here)
        out, force = d.output(here, d.file(["rec.bin"], ["rec.dat"]))
        before = contents(out)
        words = d.flags("--no-reconnect", "--wait")
        ends = unplugged and "--no-reconnect" in words  # else it records until --duration
        values = {
            "--out": out,
            "--duration": d.work(WALL_BUDGET_S) if not ends or d.given() else None,
            "--baud": d.int(st.sampled_from([9600, 115200, 460800, 921600])) if d.given() else None,
            "--silence-s": d.float(st.floats(0, 30)) if d.given() else None,  # (a replay is no network port)
            "--notes": d(st.text(max_size=200)) if d.given() else None,
            "--config": d.file(
                [None], [KVH_CONFIG, files.not_a_capture, here / "missing.yaml"]
            ),  # (no setup on a replay)
            "--format": d.format_for({"fog-v1"}, auto=False),  # (another needs --config's device: settings)
        }
        outcome = run_main(d.logging(["record", port, *options(values), *words, *force]))
        if check_outcome(outcome) == "ok":
            said = re.match(r"recorded ([\d,]+) bytes in \S+ s to (.+) \(", outcome.stdout)
            assert said and said[2] == str(out), outcome
            recorded = out.read_bytes()
            assert len(recorded) == int(said[1].replace(",", "")) > 0
            if replayed is not None:  # the port's bytes, as they came (from the start again after a reopen)
                source = replayed.read_bytes()
                assert (source * (len(recorded) // len(source) + 1)).startswith(recorded), outcome
            assert read_provenance(out) is not None
        else:
            assert unchanged(out, before), outcome


# --- ctl and watch: against a closed loopback port ----------------------------------------------------


@pytest.fixture(scope="module")
def closed_port():
    """A loopback port bound and never listening (so no other program takes it): every connection refused."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        yield sock.getsockname()[1]


def refused_connection(outcome: Outcome, port: int) -> bool:
    """The one line of a daemon that is not there (exit 69)."""
    return outcome.status == 69 and error_lines(outcome) == [
        f"fog-driver: error: could not connect to 127.0.0.1:{port}: Connection refused (is `fog-driver run` running?)"
    ]


def logging_read(argv: tuple[str, ...]) -> bool:
    """Whether argparse reads the ``--log-format`` of ``argv`` (``Drawer.logging``'s; an odd one it refuses)."""
    return all(w.partition("=")[2] in ("auto", "human", "json") for w in argv if w.startswith("--log-format="))


def within(text: str | None, lo: float, hi: float) -> bool:
    """``text`` (Python's float of it) is a number from ``lo`` to ``hi``."""
    value = None if text is None else as_float(text)
    return value is not None and lo <= value <= hi


#: ``ctl``'s numeric options -> their valid draws.
CTL_OPTIONS = {
    "--timeout": log_uniform(1e-3, 86400.0),
    "--reference-dph": st.floats(-1e7, 1e7),
    "--dwell": st.floats(12.0, 86400.0),
    "--angle-start": st.floats(-1e6, 1e6),
}


def ctl_status(command: str, args: list[str], values: dict[str, str | None]) -> int:
    """The exit status ``fog-driver ctl`` must end in against a closed port, from ctl's documented rules (not its
    code): 2 for an option argparse cannot read (a ``--timeout`` not > 0 and at most a day, a float that is
    none), 64 for arguments the command does not take (ranges as the daemon checks them), else 69."""
    timeout, reference, dwell, start = (values.get(name) for name in CTL_OPTIONS)
    if timeout is not None and not (within(timeout, 0.0, 86400.0) and as_float(timeout) > 0):
        return USAGE
    if any(text is not None and as_float(text) is None for text in (reference, dwell, start)):
        return USAGE
    if command not in ("zero", "bias", "adapt", "table", "reload", "status", "save"):
        return 64
    if reference is not None and (command, args) != ("adapt", ["on"]):
        return 64
    if (dwell is not None or start is not None) and command != "table":
        return 64
    if command == "bias":
        ok = not args or (len(args) == 1 and within(args[0], 1.0, 86400.0))
    elif command == "adapt":
        ok = args in (["on"], ["off"]) and (reference is None or within(reference, -1e7, 1e7))
    elif command == "table":
        ok = len(args) == 1 and within(args[0], -1e6, 1e6) and (dwell is None or within(dwell, 12.0, 86400.0))
        ok = ok and (start is None or within(start, -1e6, 1e6))
    else:
        ok = not args
    return 69 if ok else 64


@given(st.data())
@CLIENT
def test_ctl_with_any_command_and_options_to_a_closed_port_is_one_line(closed_port, data):
    """``ctl`` with every command, its numeric arguments and options drawn wide (``--timeout``, ``bias
    SECONDS``, ``table ANGLE --dwell --angle-start``, ``adapt on --reference-dph``): a refusal of its
    arguments (64, or argparse's 2) before any connection, else the one line of a daemon not there (69)."""
    d = Drawer(data)
    command = d(st.sampled_from(["zero", "bias", "adapt", "table", "reload", "status", "save"]))
    if d.odd():
        command = d(st.sampled_from(["stauts", "", "ZERO"]))
    args: list[str] = {
        "bias": [d.float(st.floats(1.0, 86400.0))] if d.given() else [],
        "adapt": [d(st.sampled_from(["on", "off"])) if not d.odd() else d(st.sampled_from(["maybe", "1", ""]))],
        "table": [d.float(st.floats(-1e6, 1e6))],
    }.get(command, [])
    if d.odd():
        args.append(d.float(st.floats()))  # one argument too many
    own = {"adapt": ("--reference-dph",), "table": ("--dwell", "--angle-start")}.get(command, ())
    values = {  # the command's own options, or not; another's only as an odd one
        name: d.float(valid)
        for name, valid in CTL_OPTIONS.items()
        if (d.given() if name in own or name == "--timeout" else d.odd())
    }
    words = ["ctl", "--connect", f"127.0.0.1:{closed_port}", *options(values), *d.flags("--json"), command]
    outcome = run_main(d.logging([*words, "--", *args] if args else words))
    check_outcome(outcome)
    expected = ctl_status(command, args, values) if logging_read(outcome.argv) else USAGE
    assert outcome.status == expected, outcome
    assert outcome.stdout == "", outcome
    if expected == 69:
        assert refused_connection(outcome, closed_port), outcome


#: ``watch``'s float options -> their draws (a rate past the protocol's 10000 in a third of them).
WATCH_OPTIONS = {
    "--rate-hz": log_uniform(1e-3, 1e6),
    "--duration": log_uniform(1e-3, 1e9),
    "--idle-s": log_uniform(1e-3, 1e9),
}


@given(st.data())
@CLIENT
def test_watch_with_any_options_to_a_closed_port_is_one_line(closed_port, data):
    """``watch`` with ``--rate-hz`` (0 < R <= 10000, the protocol's bound), ``--count``, ``--duration`` and
    ``--idle-s`` drawn wide, ``--json`` or not: argparse's refusal (2) of a value out of range, else the one
    line of a daemon not there (69), at once."""
    d = Drawer(data)
    values: dict[str, str | None] = {name: d.float(valid) for name, valid in WATCH_OPTIONS.items() if d.given()}
    values["--count"] = d.int(st.integers(1, 10**6)) if d.given() else None
    address = f"127.0.0.1:{closed_port}"
    words = ["watch", *(["--connect", address] if d.given() else [address]), *options(values), *d.flags("--json")]
    outcome = run_main(d.logging(words))
    check_outcome(outcome)
    floats_ok = all(
        text is None or (within(text, 0.0, 1e4 if name == "--rate-hz" else math.inf) and 0 < as_float(text) < math.inf)
        for name, text in values.items()
        if name != "--count"
    )
    count = values["--count"]
    count_ok = count is None or (re.fullmatch(r"\s*[+-]?[\d_]+\s*", count) is not None and int(count) >= 1)
    assert outcome.status == (69 if floats_ok and count_ok and logging_read(outcome.argv) else USAGE), outcome
    if outcome.status == 69:
        assert refused_connection(outcome, closed_port) and outcome.stdout == "", outcome


# --- what the property tests found: each a one-line refusal now, or a run -------------------------------


def refused(argv: list[str], here: Path) -> Outcome:
    """``argv`` run in ``here``: one line (argparse's: after its usage) and a documented status, no traceback,
    no warning, nothing written."""
    outcome = run_main(argv)
    lines = outcome.stderr.strip().splitlines()
    if check_outcome(outcome) == "usage":
        assert lines[-1].startswith(f"fog-driver {argv[0]}: error: argument "), outcome
    else:
        assert len(lines) == 1, outcome
    assert list(here.iterdir()) == [], outcome
    return outcome


@pytest.mark.parametrize(
    "words, status, needle",
    [
        ("simulate --profile short-test --out s.bin --duration=inf", 2, "--duration: must be > 0 and finite"),
        ("compensate {short} --model {model} --out c.csv --every=inf", 2, "--every: must be > 0 and finite"),
        ("compensate {short} --model {model} --out c.csv --every=1e-9", 2, "rows are cut in whole microseconds"),
        ("compensate {short} --model {model} --out c.csv --every=1e300", 2, "to 1e+09 s: '1e300'"),
        ("compensate {short} --model {model} --out c.csv --adapt-reference=nan", 2, "must be a finite number"),
        ("compensate {short} --model {model} --out c.csv --scale-override=1e300", 2, "a scale factor is a float32"),
        ("compensate {short} --model {model} --out c.csv --scale-override=1e-300", 2, "a scale factor is a float32"),
        ("simulate --serve pty --link l.tty --speed=1e-300", 64, "--speed 1e-300: a stream runs 0.001 to 1e+06"),
        ("simulate --profile short-test --out s.bin --duration=1e300", 64, "more than the 31 days"),
        ("simulate --out s.bin --faults=thermo=1:1e300", 64, "a fault lasts > 0 s and at most 31 days"),
        ("evaluate {short} --model {model} --out report --truth {text}", 65, "not a truth file"),
        # the third review's findings 10, 15 and 16, as its script ran them
        ("plan --out p.yaml --max-rate-c-per-min=1e-308", 64, "plan: impossible limits: --minutes 440"),
        ("plan --out p.yaml --max-rate-c-per-min=5e-324", 64, "plan: impossible limits: --minutes 440"),
        ("simulate --profile short-test --out f.bin --rate-hz 10 --duration=1e308", 64, "more than the 31 days"),
        (
            "simulate --profile short-test --out f.bin --rate-hz 10 --duration 5 --faults=thermo=1e308:1e308",
            64,
            "a fault lasts > 0 s and at most 31 days",
        ),
        ("simulate --serve pty --link tty --rate-hz 10 --duration 3 --speed=1e-308", 64, "a stream runs 0.001 to"),
        ("ctl --connect 127.0.0.1:1 --timeout 1e10 status", 2, "at most 86400 s (a day): '1e10'"),
        ("watch 127.0.0.1:1 --rate-hz 20000", 2, "at most 10000 ANGLE updates a second: '20000'"),
        ("simulate --profile short-test --duration 1e9 --out f.bin", 64, "--duration 1e+09 s: more than the 31 days"),
        ("simulate --profile short-test --duration 1e9 --serve pty --link tty", 64, "more than the 31 days"),
    ],
    ids=[
        "simulate --duration inf",
        "compensate --every inf",
        "compensate --every 1e-9",
        "compensate --every 1e300",
        "compensate --adapt-reference nan",
        "compensate --scale-override 1e300",
        "compensate --scale-override 1e-300",
        "simulate --serve pty --speed 1e-300",
        "simulate --duration 1e300",
        "simulate --faults thermo=1:1e300",
        "evaluate --truth a-text-file",
        "plan --max-rate-c-per-min 1e-308",
        "plan --max-rate-c-per-min 5e-324",
        "simulate --duration 1e308",
        "simulate --faults thermo=1e308:1e308",
        "simulate --serve pty --speed 1e-308",
        "ctl --timeout 1e10",
        "watch --rate-hz 20000",
        "simulate --profile short-test --duration 1e9",
        "simulate --serve pty --profile short-test --duration 1e9",
    ],
)
def test_an_option_value_that_crashed_or_ran_for_ever_is_one_line(files, tmp_path, monkeypatch, words, status, needle):
    """Before: exit 70 (a traceback at a terminal) for inf, 1e300, 1e-300 or a flip probability of 1e-212;
    ``--duration 1e300`` ran until the disk was full; ``--every 1e-9`` cut every row in 0 us;
    ``--adapt-reference nan`` and ``--scale-override 1e-300`` ran on NaN or a zero scale; the empty truth
    file added numpy's warning to the one line.  The third review's: exit 70 (``ZeroDivisionError``,
    ``OverflowError``), ``--duration 1e9`` ran 610,030 s of device time in 40 s, ``watch --rate-hz 20000``
    waited for ever."""
    monkeypatch.chdir(tmp_path)
    argv = words.format(short=DATA / "sim-short.bin", model=files.wesn, text=files.not_a_capture).split()
    outcome = refused(argv, tmp_path)
    assert outcome.status == status and needle in outcome.stderr, outcome


def test_simulate_with_a_vanishing_flip_probability_writes_the_fault_free_capture(tmp_path):
    """``--faults flip=2e-212`` (exit 70 before: 1 - p rounded to 1, a division by zero): no byte of a
    short run is flipped, so the capture is the one without faults."""
    run = ["simulate", "--profile", "short-test", "--rate-hz", "10", "--duration", "60"]
    for name, faults in (("flip.bin", "flip=2e-212"), ("clean.bin", "none")):
        outcome = run_main([*run, "--faults", faults, "--out", str(tmp_path / name)])
        assert check_outcome(outcome) == "ok", outcome
    assert (tmp_path / "flip.bin").read_bytes() == (tmp_path / "clean.bin").read_bytes()


def test_compensate_every_microsecond_writes_a_row_per_frame(files, tmp_path):
    """The shortest period ``--every`` takes (1 us, the rows' grid): each frame its own row."""
    out = tmp_path / "c.csv"
    outcome = run_main(["compensate", str(DATA / "sim-short.bin"), "--model", str(files.wesn), "--out", str(out)])
    assert check_outcome(outcome) == "ok", outcome
    outcome = run_main([*outcome.argv, "--every", "1e-6", "--force"])
    assert check_outcome(outcome) == "ok", outcome
    _, rows = read_rows(out)
    assert np.all(rows[:, 1] == 1) and len(rows) == inspect_capture(DATA / "sim-short.bin").sample_frames


# --- huge work: refused at once, or stopped by Ctrl-C -------------------------------------------------


@pytest.mark.parametrize(
    "words, status",
    [
        ("plan --out p.yaml --minutes=1e300", 64),
        ("simulate --profile paper --out s.bin --duration=2.7e6", 64),  # (31 days: 2,678,400 s)
        ("simulate --serve pty --link l.tty --duration=1e300", 64),
        ("simulate --profile paper --out s.bin --rate-hz=1e9", 2),
        ("simulate --profile paper --out s.bin --rate-hz=65536", 2),
        ("simulate --out s.bin --faults=thermo=1:1e300", 64),
        ("compensate {short} --model {model} --out c.csv --every=5e-324", 2),
        ("record {replay} --out r.bin --baud=1e12", 2),
    ],
    ids=lambda v: v if isinstance(v, str) else None,
)
def test_huge_work_is_refused_at_once_in_one_line(files, tmp_path, monkeypatch, words, status):
    monkeypatch.chdir(tmp_path)
    replay = f"replay://{DATA / 'sim-short.bin'}"
    argv = words.format(short=DATA / "sim-short.bin", model=files.wesn, replay=replay).split()
    assert refused(argv, tmp_path).status == status


def started(argv: list[str], cwd: Path) -> subprocess.Popen:
    """``fog-driver ARGV`` running, its stdout and stderr piped (text), stdin closed."""
    command = [sys.executable, "-m", "fog_driver", *argv]
    return subprocess.Popen(command, cwd=cwd, stdin=subprocess.DEVNULL, stdout=PIPE, stderr=PIPE, text=True)


def interrupted(proc: subprocess.Popen, ready) -> tuple[int, str, str]:
    """SIGINT to ``proc`` once ``ready()`` (the readiness signal: a line read, a file with bytes) says it is
    under way; its status, stdout and stderr."""
    try:
        deadline = time.monotonic() + 120
        while not ready():
            assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=120)
    finally:
        proc.kill()
    return proc.returncode, stdout, stderr


def has_bytes(path: Path) -> bool:
    """Whether ``path`` has bytes yet: the readiness of a command that writes a file (a short wait between
    looks: the file, not the clock, says when)."""
    if path.exists() and path.stat().st_size > 0:
        return True
    time.sleep(0.01)
    return False


def test_huge_work_simulated_to_a_file_is_stopped_by_ctrl_c_in_one_line(tmp_path):
    """30 days at 1 kHz (2.6e9 frames, 70 GB): allowed (under the 31 days), and Ctrl-C ends it with the
    interrupted line alone, exit 130, the sidecar saying what the capture holds."""
    out = tmp_path / "big.bin"
    proc = started(
        ["simulate", "--profile", "paper", "--rate-hz", "1000", "--duration", "2.592e6", "--out", "big.bin"], tmp_path
    )
    status, stdout, stderr = interrupted(proc, lambda: has_bytes(out))
    assert status == 130 and stdout == "", stderr
    side = read_provenance(out)
    assert side["status"] == "interrupted" and side["bytes"] == out.stat().st_size
    held_s = side["frames"] / 1000
    assert stderr.splitlines() == [
        f"fog-driver: interrupted: big.bin holds the first {held_s:g} s (status: interrupted in big.bin.yaml)"
    ]


def test_huge_work_served_live_is_stopped_by_ctrl_c_in_one_line(tmp_path):
    """30 days served in real time: Ctrl-C stops the stream (exit 0, as documented: a stream is stopped so),
    its summary line after the readiness line, the link removed, nothing on stderr."""
    link = tmp_path / "sim.tty"
    argv = [
        "simulate",
        "--profile",
        "paper",
        "--rate-hz",
        "10",
        "--duration",
        "2.592e6",
        "--serve",
        "pty",
        "--link",
        str(link),
    ]
    proc = started(argv, tmp_path)
    ready = proc.stdout.readline()  # blocks until the pty is up
    assert ready.startswith("serving paper at 10 Hz on /dev/pts/") and f"(link {link})" in ready, ready
    status, stdout, stderr = interrupted(proc, lambda: True)
    assert status == 0 and stderr == "", stderr
    assert re.fullmatch(r"stopped after [\d,]+ frames \(.*\), .* disconnects\n", stdout), stdout
    assert not link.is_symlink()


def test_a_recording_of_huge_duration_is_stopped_by_ctrl_c_in_one_line(tmp_path):
    """``record --duration 1e300`` records until stopped: Ctrl-C ends it cleanly (exit 0, as documented), its
    one line on stdout, nothing on stderr, and the capture what the port sent."""
    out = tmp_path / "r.bin"
    port = f"replay://{DATA / 'sim-short.bin'}?rate=100"
    proc = started(["record", port, "--out", "r.bin", "--duration", "1e300"], tmp_path)
    status, stdout, stderr = interrupted(proc, lambda: has_bytes(out))
    assert status == 0 and "Traceback" not in stderr and error_lines(Outcome((), status, stdout, stderr, ())) == []
    assert re.fullmatch(r"recorded [\d,]+ bytes in \S+ s to r\.bin \(.*\); provenance in r\.bin\.yaml\n", stdout), (
        stdout
    )
    assert (DATA / "sim-short.bin").read_bytes().startswith(out.read_bytes())
