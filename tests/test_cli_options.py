"""No command crashes on any combination of its options: for each of ``plan``, ``simulate``, ``fit``,
``compensate``, ``evaluate``, ``record`` and ``inspect``, hypothesis draws every numeric and choice option
from wide ranges (zero, negative, tiny, huge, NaN and infinity where a float is parsed, and valid values) and
the flags in any combination, and runs ``fog_driver.cli.main`` in-process.  Each run must end in one of:

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
import re
import shutil
import tempfile
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import structlog
import yaml
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from fog_driver.cli import main
from fog_driver.cli.argtypes import positive_float, rate_hz
from fog_driver.cli.parser import command_in
from fog_driver.files.kinds import ROW_COLUMNS
from fog_driver.formats.registry import FORMATS
from fog_driver.modelfiles import load_model
from fog_driver.samples.captures import inspect_capture, read_provenance
from fog_driver.sim.chamber import Hold, Ramp, Sinusoid
from fog_driver.sim.instrument import WIRE_FORMATS
from fog_driver.sim.plan import DEFAULT_LIMITS
from fog_driver.sim.population import MAX_INSTRUMENT_SEED
from fog_driver.sim.profiles import load_profile

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "tests" / "data"
GOLDEN_MODELS = DATA / "golden" / "models"
INSTRUMENT = ROOT / "configs" / "sim" / "instrument.yaml"
KVH_CONFIG = ROOT / "configs" / "kvh-dsp1750.yaml"

#: README's exit-code table: what a command may exit with (70 is a bug; 1 is inspect --strict's alone).
DOCUMENTED_ERRORS = {64, 65, 69, 73, 75, 77, 78}
USAGE = 2  # argparse

#: The examples per command, and the settings every property here runs with.
EXAMPLES = 50
PROPERTY = settings(
    max_examples=EXAMPLES,
    derandomize=True,
    database=None,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.filter_too_much],
)

#: Frames a drawn simulation or capture may make: about a second of work.
FRAME_BUDGET = 20_000
#: Wall seconds a drawn real-time run (simulate --serve, record) may take.
WALL_BUDGET_S = 0.4


# --- running a command in-process ---------------------------------------------------------------------


@dataclass(frozen=True)
class Outcome:
    argv: tuple[str, ...]
    status: int
    stdout: str
    stderr: str
    warnings: tuple[str, ...]

    def __str__(self) -> str:
        argv = " ".join(self.argv)
        return f"fog-driver {argv}\n-> exit {self.status}\nstdout:\n{self.stdout}\nstderr:\n{self.stderr}"


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
    event(f"{command_in(outcome.argv)}: exit {outcome.status}")
    assert "Traceback" not in outcome.stderr, outcome
    assert "internal_error" not in outcome.stderr and "internal error" not in outcome.stderr, outcome
    assert outcome.status != 70, outcome
    assert not outcome.warnings, f"{outcome}\nPython warnings: {outcome.warnings}"
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
    "5e-324",
    "1e-9",
    "1e300",
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
    x for x in ODD_FLOATS if x not in ("1e300", "1.7976931348623157e308", "1e400", "inf", "Infinity")
)
#: Integer texts: zero, negative, the edges of u16, i32, u64, a hundred-digit number, and no integer at all.
ODD_INTS = ("0", "-1", "-0", "1", "65535", "65536", "2147483648", "18446744073709551616", "1" + "0" * 100)
ODD_INTS += ("1.5", "1e3", "nan", "", "x", " 7 ", "1_0")


def log_uniform(lo: float, hi: float) -> st.SearchStrategy[float]:
    """Floats from ``lo`` to ``hi`` (both > 0), as many in each decade."""
    return st.floats(math.log10(lo), math.log10(hi)).map(lambda e: min(max(10.0**e, lo), hi))


#: How often an option's text is valid, odd (``ODD_FLOATS``) or any float at all: mostly valid, so that
#: combinations of valid values are tried too.
_KINDS = st.sampled_from(["valid"] * 6 + ["odd"] * 3 + ["any"])


@st.composite
def float_text(draw, valid: st.SearchStrategy[float], odd: tuple[str, ...] = ODD_FLOATS) -> str:
    """An option's text: a valid value, an odd one, or any float at all."""
    kind = draw(_KINDS)
    if kind == "odd":
        return draw(st.sampled_from(odd))
    return repr(draw(valid if kind == "valid" else st.floats()))


@st.composite
def int_text(draw, valid: st.SearchStrategy[int], odd: tuple[str, ...] = ODD_INTS) -> str:
    kind = draw(_KINDS)
    if kind == "odd":
        return draw(st.sampled_from(odd))
    return str(draw(valid if kind == "valid" else st.integers()))


def option(name: str, value: str) -> str:
    """``--name=value``: a value starting with ``-`` is the option's, not another option."""
    return f"{name}={value}"


@st.composite
def logging_options(draw) -> list[str]:
    """``-v`` up to three times and ``--log-format``, before the command or after it."""
    words = ["-v"] * draw(st.integers(0, 3))
    if draw(st.booleans()):
        words.append(option("--log-format", draw(st.sampled_from(["auto", "human", "json", "xml"]))))
    return words


@st.composite
def with_logging(draw, command: list[str]) -> list[str]:
    """``command`` with logging options drawn before or after its name."""
    words = draw(logging_options())
    return words + command if draw(st.booleans()) else command[:1] + words + command[1:]


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


@st.composite
def work_float_text(draw, hi: float, lo: float = 1e-3) -> str:
    """The text of an option that sizes the work: valid up to ``hi`` (what finishes in about a second), odd
    (``ODD_WORK_FLOATS``: non-positive, tiny, NaN, no number) or any float up to ``hi``."""
    kind = draw(_KINDS)
    if kind == "odd":
        text = draw(st.sampled_from(ODD_WORK_FLOATS))
        value = as_float(text)
        return repr(hi) if value is not None and value > hi else text  # ("1_0" is 10)
    if kind == "any":
        return repr(draw(st.floats(max_value=hi)))
    return repr(draw(log_uniform(min(lo, hi), hi)))


def maybe(strategy: st.SearchStrategy) -> st.SearchStrategy:
    """``strategy``'s value, or None (the option not given)."""
    return st.one_of(st.none(), strategy)


def options(values: dict[str, str | None]) -> list[str]:
    """``--name=value`` for each option given."""
    return [option(k, v) for k, v in values.items() if v is not None]


def flags(draw, *names: str) -> list[str]:
    """Each flag, or not."""
    return [name for name in names if draw(st.booleans())]


def choice_text(choices) -> st.SearchStrategy[str | None]:
    """A choice option: not given, one of ``choices``, or a word that is none of them."""
    return st.one_of(st.none(), st.sampled_from([*choices, "bogus", ""]))


# --- the fixtures: the short captures in tests/data, and what is made of them once -----------------------

CAPTURES = ("sim-short", "sim-faults", "synthetic-clean", "synthetic-faults")


@dataclass(frozen=True)
class Files:
    base: Path
    fit_config: Path  # warm-up cut to 30 s: tests/data's captures last 300 s
    wesn: Path  # fitted on sim-short
    polynomial: Path
    other_serial: Path  # a model of another instrument
    positioning: Path  # a simulated positioning run, 5 Hz, with its table log and truth
    kvh: Path  # a simulated KVH capture
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
    made(["simulate", "--profile", "positioning", "--rate-hz", "5", "--duration", "900", "--out", str(positioning)])
    kvh = base / "kvh.bin"
    made(["simulate", "--profile", "short-test", "--format", "kvh-a", "--rate-hz", "10", "--out", str(kvh)])
    not_a_capture = base / "notes.txt"
    not_a_capture.write_text("a text file, not a capture\n")
    minute = base / "minute.yaml"
    minute.write_text("name: minute\nstart_c: 20\nsegments:\n  - ramp: {rate_c_per_min: 2, target_c: 22}\n")
    assert load_profile(minute).chamber.duration_s == 60.0
    bad_instrument = base / "bad-instrument.yaml"
    bad_instrument.write_text("thermal:\n  tau_housing_s: -480\n")
    return Files(
        base, fit_config, wesn, polynomial, other_serial, positioning, kvh, not_a_capture, minute, bad_instrument
    )


@st.composite
def output(draw, here: Path, name: str, force: bool = True) -> tuple[Path, list[str]]:
    """An output path (new, or already there: a file, or a directory for a name without a suffix) and
    ``--force`` or not."""
    path = here / name
    if draw(st.booleans()):
        path.write_text("already here\n") if "." in name else path.mkdir()
    return path, ["--force"] if force and draw(st.booleans()) else []


def file_choice(paths: list[Path], others: list[Path]) -> st.SearchStrategy[Path]:
    """One of ``paths`` mostly, else one of ``others``."""
    return st.one_of(st.sampled_from(paths), st.sampled_from(paths), st.sampled_from(others))


def unchanged(path: Path, before: bytes | None) -> bool:
    """A file that was there is as it was; one that was not is still not there (a refused run writes nothing)."""
    return path.read_bytes() == before if before is not None else not path.is_file()


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


@st.composite
def plan_limits(draw) -> dict[str, str]:
    """The options given, each as text; a narrow range (max just above min) as often as a wide one."""
    given_ = {}
    for name, valid in PLAN_OPTIONS.items():
        if draw(st.booleans()):
            given_[name] = draw(float_text(valid))
    if "--min-c" in given_ and draw(st.booleans()) and (low := as_float(given_["--min-c"])) is not None:
        given_["--max-c"] = repr(low + draw(log_uniform(1e-6, 20)))
    return given_


def check_program(path: Path, limits: dict[str, float]) -> None:
    """The written program read back as a profile stays within the limits: every temperature within
    min..max (every segment's ends, a sinusoid's peaks, and the air temperature on a fine grid), no ramp
    and no sinusoid faster than the fastest ramp, and the whole within the minutes."""
    chamber = load_profile(path).chamber
    lo, hi, rate, minutes = (limits[k] for k in ("--min-c", "--max-c", "--max-rate-c-per-min", "--minutes"))
    tol = 1e-9 * max(1.0, abs(lo), abs(hi))
    assert chamber.duration_s <= minutes * 60.0 * (1 + 1e-12), (chamber.duration_s, minutes)
    assert chamber.duration_s > 0
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
    with example_dir(files.base) as here:
        limits = data.draw(plan_limits(), "limits")
        name = data.draw(st.sampled_from(["p.yaml", "p.yml", "p.txt"]), "out")
        out, force = data.draw(output(here, name), "output")
        before = out.read_bytes() if out.is_file() else None
        argv = ["plan", option("--out", str(out)), *options(limits), *force]
        outcome = run_main(data.draw(with_logging(argv), "argv"))
        if check_outcome(outcome) == "ok":
            values = {k: float(limits.get(k, getattr(DEFAULT_LIMITS, f))) for k, f in PLAN_FIELDS.items()}
            check_program(out, values)
            assert outcome.stdout.startswith(f"wrote {out}: a "), outcome
        else:
            assert unchanged(out, before), outcome  # a refused plan writes nothing


# --- simulate ------------------------------------------------------------------------------------------

#: Frames and device seconds a drawn simulation may make, and the wall seconds a drawn real-time run may
#: take: about a second of work at most.
FRAME_BUDGET = 20_000
DEVICE_S_BUDGET = 6_000.0
WALL_BUDGET_S = 0.2


@st.composite
def fault_spec(draw) -> str | None:
    """``--faults``: not given, a malformed spec, or some of the five faults with numbers drawn wide (the
    garbage and thermometer rates size the work: drawn valid up to a few a second)."""
    if draw(st.integers(0, 4)) == 0:
        return draw(st.sampled_from([None, "none", "", "drop", "drop=", "bogus=1", "drop=0.1,drop=0.2", "x" * 5000]))
    items = []
    for name in draw(st.lists(st.sampled_from(["drop", "flip", "garbage", "thermo", "disconnect"]), unique=True)):
        if name in ("drop", "flip"):
            value = draw(float_text(st.floats(0, 1)))
        elif name == "garbage":
            value = draw(work_float_text(10.0))
        elif name == "thermo":
            value = draw(work_float_text(1.0))
            if draw(st.booleans()):
                value += ":" + draw(float_text(st.floats(0, 100)))
        else:
            cuts = draw(st.lists(st.tuples(float_text(st.floats(0, 600)), float_text(st.floats(0, 60))), min_size=1))
            value = "+".join(f"{t}:{d}" for t, d in cuts[:3])
        items.append(f"{name}={value}")
    return ",".join(items)


def profile_seconds(profile: str) -> float | None:
    """The length of a profile ``--profile`` names, or None when it names none."""
    try:
        return load_profile(profile).chamber.duration_s
    except Exception:
        return None


@st.composite
def simulate_case(draw, files: Files, here: Path) -> tuple[list[str], dict]:
    """``simulate``'s argv and what it asks for (the mode, the capture's path, the rate, the duration)."""
    profiles = [str(files.minute), "short-test", "positioning", "paper", "no-such-profile", str(files.not_a_capture)]
    profile = draw(maybe(st.sampled_from(profiles)))
    mode = draw(st.sampled_from(["out"] * 5 + ["pty"] * 2 + ["device", "both", "neither"]))
    values: dict[str, str | None] = {
        "--profile": profile,
        "--rate-hz": draw(maybe(int_text(st.integers(1, 2000)))),
        "--seed": draw(maybe(int_text(st.integers(0, 2**64)))),
        "--format": draw(choice_text(WIRE_FORMATS)),
        "--faults": draw(fault_spec()),
        "--instrument": draw(maybe(st.sampled_from([str(INSTRUMENT), str(files.bad_instrument), "missing.yaml"]))),
        "--instrument-seed": draw(maybe(int_text(st.integers(0, MAX_INSTRUMENT_SEED)))),
    }
    out, force = draw(output(here, draw(st.sampled_from(["run.bin", "run.dat"]))))
    if mode in ("out", "both"):
        values["--out"] = str(out)
    serving = mode in ("pty", "device", "both")
    if serving:
        values["--serve"] = "pty" if mode != "device" else draw(st.sampled_from(["/dev/null", str(here / "no-tty")]))
        values["--speed"] = draw(maybe(float_text(log_uniform(1e2, 1e7))))
        values["--baud"] = draw(maybe(int_text(st.sampled_from([9600, 115200, 460800, 921600]))))
    if mode != "device":  # the link, never the default's /tmp/fog-driver-sim.tty (other runs may serve there)
        link = draw(st.sampled_from(["sim.tty", "notes.txt", ".", "no-dir/sim.tty"]))
        if link == "notes.txt":
            (here / link).write_text("not a link\n")
        if mode in ("pty", "both") or draw(st.booleans()):
            values["--link"] = str(here / link)
    # the work: the duration, drawn valid up to what the budgets allow at the rate (and the speed) drawn
    rate = 100 if values["--rate-hz"] is None else parsed(rate_hz, values["--rate-hz"])  # None: refused
    speed = parsed(positive_float, values.get("--speed")) or 1.0
    bound = min(FRAME_BUDGET / (rate or 100), DEVICE_S_BUDGET, WALL_BUDGET_S * speed if serving else math.inf)
    length = profile_seconds(profile or "paper")
    duration = draw(maybe(work_float_text(bound)))
    if duration is None and length is not None and length > bound:
        duration = repr(draw(log_uniform(min(1e-3, bound), bound)))
    values["--duration"] = duration
    words = ["simulate", *options(values), *(force if mode in ("out", "both") else [])]
    return words, {"mode": mode, "out": out, "rate": rate, "duration": parsed(positive_float, duration)}


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


@given(st.data())
@PROPERTY
def test_simulate_with_any_options_writes_a_capture_or_serves_or_says_why_not(files, data):
    with example_dir(files.base) as here:
        words, case = data.draw(simulate_case(files, here), "case")
        out = case["out"]
        before = out.read_bytes() if out.is_file() else None
        outcome = run_main(data.draw(with_logging(words), "argv"))
        kind = check_outcome(outcome)
        if kind == "ok" and case["mode"] == "out":
            check_simulated(outcome, case)
        elif kind == "ok":  # served: the readiness line, the summary line, and the link removed
            assert outcome.stdout.startswith("serving "), outcome
            assert re.search(r"^(served|stopped after) [\d,]+ frames", outcome.stdout, re.M), outcome
            assert not (here / "sim.tty").is_symlink(), outcome
        else:
            assert unchanged(out, before), outcome


# --- fit -----------------------------------------------------------------------------------------------

FIT_KINDS = ("wesn", "polynomial", "paper", "pso-svr")


@st.composite
def fit_config(draw, files: Files, here: Path) -> str | None:
    """``--config``: none, the fixtures' (a 30-s warm-up), a missing file, a text file, an unknown key, or a
    warm-up drawn wide (YAML's own spellings of NaN and infinity included)."""
    kind = draw(st.sampled_from(["none", "fixture", "fixture", "missing", "text", "unknown", "drawn"]))
    if kind in ("none", "fixture"):
        return None if kind == "none" else str(files.fit_config)
    if kind in ("missing", "text"):
        return str(here / "missing.yaml" if kind == "missing" else files.not_a_capture)
    path = here / "fit.yaml"
    if kind == "unknown":
        path.write_text("warmup: 30\n")
    else:
        value = draw(st.sampled_from([".nan", ".inf", "-.inf", "1e400", "-5", "0", "30", "1e300", "x", "[]"]))
        path.write_text(f"warmup_s: {value}\n")
    return str(path)


@given(st.data())
@PROPERTY
def test_fit_with_any_options_writes_a_model_or_says_why_not(files, data):
    with example_dir(files.base) as here:
        pool = file_choice(files.captures, files.others)
        captures = data.draw(st.lists(pool, min_size=1, max_size=2), "captures")
        validate = data.draw(st.lists(pool, max_size=2), "validate")
        copy = here / "copy.bin"  # a capture as --out: never overwritten, whatever --force says
        shutil.copyfile(DATA / "sim-short.bin", copy)
        name = data.draw(st.sampled_from(["model.yaml", "model.yaml", "model", "copy.bin"]), "out")
        out, force = (
            (copy, data.draw(st.sampled_from([[], ["--force"]])))
            if name == "copy.bin"
            else data.draw(output(here, name))
        )
        before = out.read_bytes() if out.is_file() else None
        values = {
            "--out": str(out),
            "--kind": data.draw(choice_text(FIT_KINDS), "kind"),
            "--config": data.draw(fit_config(files, here), "config"),
            "--format": data.draw(choice_text(FORMATS), "format"),
        }
        words = ["fit", *map(str, captures), *options(values), *(option("--validate", str(v)) for v in validate)]
        words += [*force, *flags(data.draw, "--accept-weak-fit")]
        outcome = run_main(data.draw(with_logging(words), "argv"))
        if check_outcome(outcome) == "ok":
            model = load_model(out)
            said = re.search(r"^fitted a (\S+) model for (\S+) on (\d+) capture\(s\)", outcome.stdout, re.M)
            assert said and (said[1], said[2]) == (model.kind, model.instrument_serial), outcome
            assert int(said[3]) == len(captures)
            if values["--kind"] is not None:
                assert model.kind == values["--kind"]
        else:
            assert unchanged(out, before), outcome
        assert copy.read_bytes() == (DATA / "sim-short.bin").read_bytes()


# --- compensate ----------------------------------------------------------------------------------------


def read_rows(path: Path) -> tuple[list[str], np.ndarray]:
    """A compensate CSV's header and its numeric columns (t_s, n_samples)."""
    lines = path.read_text().splitlines()
    rows = [line.split(",") for line in lines[1:]]
    return lines[0].split(","), np.array([[float(r[0]), float(r[1])] for r in rows]).reshape(-1, 2)


@given(st.data())
@PROPERTY
def test_compensate_with_any_options_writes_rows_or_says_why_not(files, data):
    with example_dir(files.base) as here:
        capture = data.draw(file_choice(files.captures, files.others), "capture")
        model = data.draw(file_choice(files.models, files.others), "model")
        out, force = data.draw(output(here, data.draw(st.sampled_from(["out.csv", "out.csv", "out"]))), "out")
        before = out.read_bytes() if out.is_file() else None
        state = here / "state.yaml"
        state_kind = data.draw(st.sampled_from(["none", "none", "new", "text", "directory"]), "adapt state")
        if state_kind == "text":
            state.write_text("not a state\n")
        elif state_kind == "directory":
            state.mkdir()
        every = data.draw(maybe(float_text(log_uniform(1e-3, 1e4))), "every")
        values = {
            "--model": str(model),
            "--out": str(out),
            "--every": every,
            "--adapt-reference": data.draw(maybe(float_text(st.floats(-1e3, 1e3))), "adapt reference"),
            "--table-log": data.draw(maybe(file_choice([files.table_log], files.others)), "table log"),
            "--adapt-state": None if state_kind == "none" else str(state),
            "--scale-override": data.draw(maybe(float_text(log_uniform(1e-4, 1.0))), "scale override"),
            "--format": data.draw(choice_text(FORMATS), "format"),
        }
        values["--table-log"] = None if values["--table-log"] is None else str(values["--table-log"])
        words = ["compensate", str(capture), *options(values), *force, *flags(data.draw, "--force-model")]
        outcome = run_main(data.draw(with_logging(words), "argv"))
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


@st.composite
def zero_window(draw) -> str | None:
    """``--zero-window START:END``: not given, two numbers drawn wide, or no window at all."""
    kind = draw(st.sampled_from(["none", "drawn", "drawn", "odd"]))
    if kind == "none":
        return None
    if kind == "odd":
        return draw(st.sampled_from(["", ":", "10", "10:", ":10", "1:2:3", "a:b", "nan:10", "0:inf", "10:5", "5:5"]))
    start = draw(float_text(st.floats(0, 400)))
    return f"{start}:{draw(float_text(st.floats(0, 600)))}"


@given(st.data())
@PROPERTY
def test_evaluate_with_any_options_writes_a_report_or_says_why_not(files, data):
    with example_dir(files.base) as here:
        capture = data.draw(file_choice(files.captures, files.others), "capture")
        truths = [c.with_suffix(".truth.csv") for c in files.captures if c.with_suffix(".truth.csv").is_file()]
        report = here / "report"
        kind = data.draw(st.sampled_from(["new", "new", "empty", "full", "file"]), "report folder")
        if kind == "empty":
            report.mkdir()
        elif kind == "full":
            report.mkdir()
            (report / "notes.txt").write_text("a file of the user's\n")
        elif kind == "file":
            report.write_text("a file, not a folder\n")
        before = sorted(p.name for p in report.iterdir()) if report.is_dir() else None
        values = {
            "--model": str(data.draw(file_choice(files.models, files.others), "model")),
            "--out": str(report),
            "--truth": data.draw(maybe(file_choice(truths, files.others)), "truth"),
            "--reference": data.draw(maybe(file_choice([files.table_log], files.others)), "reference"),
            "--zero-window": data.draw(zero_window(), "zero window"),
            "--format": data.draw(choice_text(FORMATS), "format"),
        }
        values = {k: None if v is None else str(v) for k, v in values.items()}
        compare = data.draw(st.lists(file_choice(files.models, files.others), max_size=2), "compare")
        words = ["evaluate", str(capture), *options(values), *(option("--compare", str(m)) for m in compare)]
        words += flags(data.draw, "--json", "--force", "--force-model")
        outcome = run_main(data.draw(with_logging(words), "argv"))
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

IXBLUE = sorted((DATA / "ixblue").glob("*.log"))


@given(st.data())
@PROPERTY
def test_inspect_with_any_options_reports_or_says_why_not(files, data):
    capture = data.draw(file_choice([*files.captures, *IXBLUE[:2]], files.others), "capture")
    values = {"--format": data.draw(choice_text(["auto", *FORMATS]), "format")}
    words = ["inspect", str(capture), *options(values), *flags(data.draw, "--json", "--strict")]
    outcome = run_main(data.draw(with_logging(words), "argv"))
    if check_outcome(outcome, strict="--strict" in words) in ("ok", "problems"):
        if "--json" in words:
            found = json.loads(outcome.stdout)
            problems = found["problems"] if isinstance(found.get("problems"), list) else None
        else:
            verdict = re.search(r"^verdict +(.*)$", outcome.stdout, re.M)
            assert verdict, outcome
            problems = [] if verdict[1] == "clean" else [verdict[1]]
        if problems is not None and "--strict" in words:
            assert (outcome.status == 1) == bool(problems), outcome


# --- record --------------------------------------------------------------------------------------------


@st.composite
def record_port(draw, files: Files, here: Path) -> tuple[str, Path | None, bool]:
    """A port: a capture replayed (paced or not, unplugged at its end or idle), a missing capture or
    device, ``/dev/null``, a malformed URL; with the fixture it replays, and whether it surely ends by
    itself (unplugged at its end, unpaced) rather than going idle."""
    kind = draw(st.sampled_from(["replay"] * 6 + ["missing-replay", "missing-device", "null", "bad-url"]))
    if kind == "replay":
        capture = draw(st.sampled_from([*files.captures[:4], files.kvh]))
        query = {}
        if draw(st.booleans()):
            query["unplug"] = draw(st.sampled_from(["1", "1", "0", "2", ""]))
        if draw(st.integers(0, 3)) == 0:  # paced (a rate too slow to end: with a --duration, below)
            query["rate"] = draw(float_text(log_uniform(2e5, 1e7)))
        url = f"replay://{capture}" + ("?" + "&".join(f"{k}={v}" for k, v in query.items()) if query else "")
        return url, capture, query.get("unplug") == "1" and "rate" not in query
    port = {
        "missing-replay": f"replay://{here / 'missing.bin'}",
        "missing-device": str(here / "ttyUSB9"),
        "null": "/dev/null",
        "bad-url": draw(st.sampled_from(["replay://", "nosuch://x", "replay://x?rate=", "socket://127.0.0.1:0"])),
    }[kind]
    return port, None, False


@given(st.data())
@PROPERTY
def test_record_with_any_options_records_or_says_why_not(files, data):
    with example_dir(files.base) as here:
        port, replayed, unplugged = data.draw(record_port(files, here), "port")
        out, force = data.draw(output(here, data.draw(st.sampled_from(["rec.bin", "rec.bin", "rec.dat"]))), "out")
        before = out.read_bytes() if out.is_file() else None
        words = flags(data.draw, "--no-reconnect", "--wait")
        ends = unplugged and "--no-reconnect" in words  # else it records until --duration
        duration = data.draw(maybe(work_float_text(WALL_BUDGET_S)) if ends else work_float_text(WALL_BUDGET_S))
        values = {
            "--out": str(out),
            "--duration": duration,
            "--baud": data.draw(maybe(int_text(st.sampled_from([9600, 115200, 460800, 921600]))), "baud"),
            "--notes": data.draw(maybe(st.text(max_size=200)), "notes"),
            "--config": data.draw(maybe(st.sampled_from([str(KVH_CONFIG), str(files.not_a_capture), "missing.yaml"]))),
            "--format": data.draw(choice_text(FORMATS), "format"),
        }
        words = ["record", port, *options(values), *words, *force]
        outcome = run_main(data.draw(with_logging(words), "argv"))
        if check_outcome(outcome) == "ok":
            said = re.match(r"recorded ([\d,]+) bytes in \S+ s to (.+) \(", outcome.stdout)
            assert said and said[2] == str(out), outcome
            recorded = out.read_bytes()
            assert len(recorded) == int(said[1].replace(",", "")) > 0
            if replayed is not None:  # the port's bytes, as they came
                assert replayed.read_bytes().startswith(recorded), outcome
            assert read_provenance(out) is not None
        else:
            assert unchanged(out, before), outcome
