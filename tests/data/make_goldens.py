"""Regenerate the golden outputs in tests/data/golden/ (only on purpose; say why in the commit).

    python tests/data/make_goldens.py                  rewrite every golden output, saying how each changed
    python tests/data/make_goldens.py --check          compare only; exit 1 if any differs beyond the tolerance
    python tests/data/make_goldens.py --refit-models   also refit the golden model files (new inputs)

Goldens (floats compared within ``tests/golden.py``'s tolerance on any machine, the rest exactly):

* ``sim-faults.watch-1hz.ndjson``: the ANGLE lines a client that sent
  ``?WATCH={"enable":true,"rate_hz":1};`` receives when ``tests/data/sim-faults.bin`` is fed to
  ``fog-driver run`` with the shipped default model (``fog_driver/data/models/default.yaml``), as sent.
  The HIL test feeds the capture through a real pty into the daemon and compares.
* ``models/<kind>.yaml``: one small model file of each kind, fitted on ``sim-short.bin``.  They are
  inputs, not outputs: a fit uses LAPACK, whose last bits differ between machines, so they are
  only refitted with ``--refit-models``, and a model file written by an older version must keep
  compensating the same way.
* ``models/wesn-cascade.yaml``: a wesn whose coil is forced to three stages in series with the coil's
  rate among its regressors (a 5-minute fit would never choose a cascade on its own), so the
  cascade's arithmetic is in the goldens too; its kind is ``wesn``.
* ``models/polynomial-domain.yaml``: a polynomial fitted since model files store their fit range
  (``domain``); the other golden models predate it.  ``sim-faults.bin`` leaves the 5-minute fit's
  box, so its compensate golden has the inputs clamped, the estimate bounded and the rows flagged
  ``extrapolating``.
* ``sim-faults.compensate-<name>.ndjson``: ``fog-driver compensate`` of ``sim-faults.bin`` with
  those model files (one wesn run also adapting against a known rate of 0), one row every
  5 s as in ``compensate --every 5``, at full precision: one JSON object per row with the CSV's
  columns (absent temperatures and an absent ``drift_sigma_dph`` omitted, flags as a list).

A change of any published value (compensation, flags, formatting) shows up here.  When output
changes on purpose, regenerate and check what this script prints: files it reports as changed
"within tolerance" changed only in last bits (e.g. another exp or summation order); "BEYOND
tolerance" must be a change you meant.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parents[1]))
sys.path.insert(0, str(HERE.parent))

import golden  # noqa: E402  (tests/golden.py: the comparison the tests make)

from fog_driver.compensation.adapt import AdaptConfig  # noqa: E402
from fog_driver.compensation.fitting.data import FitConfig  # noqa: E402
from fog_driver.daemon.config import DriverConfig  # noqa: E402
from fog_driver.daemon.hub import encode  # noqa: E402
from fog_driver.daemon.service import Service  # noqa: E402
from fog_driver.files.kinds import ROW_COLUMNS  # noqa: E402
from fog_driver.modelfiles import load_model, save_model  # noqa: E402
from fog_driver.offline.compensate import compensate_capture  # noqa: E402
from fog_driver.offline.fit import fit_model_file  # noqa: E402
from fog_driver.offline.rows import compensated_rows  # noqa: E402

GOLDEN_DIR = HERE / "golden"
WATCH_GOLDEN = GOLDEN_DIR / "sim-faults.watch-1hz.ndjson"
MODEL_DIR = GOLDEN_DIR / "models"
CAPTURE = HERE / "sim-faults.bin"
FIT_CAPTURE = HERE / "sim-short.bin"
FIT_CONFIG = FitConfig(warmup_s=30.0)
MODEL_KINDS = ("polynomial", "wesn", "paper", "pso-svr")
EVERY_S = 5.0
#: A short run adapts soon (the defaults wait 5 min and capture the bias for 5 min).
ADAPT = AdaptConfig(warmup_s=5.0, bias_capture_s=10.0, static_window_s=5.0)
#: Golden model files beyond one per kind: name -> (kind, the wesn structure it is fitted with).
EXTRA_MODELS = {
    "wesn-cascade": ("wesn", {"coil_orders": (3,), "fiber_lag_grid_s": (60.0,)}),
    "polynomial-domain": ("polynomial", None),
}
#: name -> (model file name, adapt against a reference of 0 deg/h)
COMPENSATE_GOLDENS = {kind: (kind, False) for kind in (*MODEL_KINDS, *EXTRA_MODELS)} | {"wesn-adapting": ("wesn", True)}


def watch_lines(rate_hz: float = 1.0) -> list[bytes]:
    """The daemon's ANGLE objects for the capture, decimated as ``?WATCH`` does, encoded as sent."""
    service = Service(DriverConfig(), port="unused")
    lines, last_period = [], None
    for obj in service.process(CAPTURE.read_bytes()):
        period = math.floor(obj["t_s"] * rate_hz)
        if period != last_period:
            lines.append(encode(obj))
            last_period = period
    return lines


def model_path(kind: str) -> Path:
    return MODEL_DIR / f"{kind}.yaml"


def compensate_path(name: str) -> Path:
    return GOLDEN_DIR / f"sim-faults.compensate-{name}.ndjson"


def compensate_lines(name: str) -> list[bytes]:
    """``compensate --every 5`` of the capture with a golden model, one JSON object per row, full precision."""
    kind, adapting = COMPENSATE_GOLDENS[name]
    model_file = load_model(model_path(kind))
    chunks = compensate_capture(
        CAPTURE, model_file, adapt=ADAPT if adapting else None, reference_rate_dph=0.0 if adapting else None
    )
    lines = []
    for row in compensated_rows(chunks, EVERY_S):
        obj = {}
        for key, value in zip(ROW_COLUMNS, row):
            if key == "flags":
                obj[key] = value.split("|") if value else []
            elif key == "n_samples":
                obj[key] = int(value)
            elif not math.isnan(value):  # a thermometer with no valid reading in the row, no sigma: omitted
                obj[key] = float(value)
        lines.append(json.dumps(obj, separators=(",", ":")).encode() + b"\n")
    return lines


def _shown(path: Path) -> Path:
    """A path as printed: relative to the project when inside it."""
    return path.relative_to(HERE.parents[1]) if path.is_relative_to(HERE.parents[1]) else path


def refit_models(names=(*MODEL_KINDS, *EXTRA_MODELS)) -> None:
    import dataclasses

    from fog_driver.compensation.fitting import fit
    from fog_driver.compensation.fitting.wesn import fit_wesn
    from fog_driver.compensation.models.wesn import WESN_DEFAULTS

    MODEL_DIR.mkdir(parents=True, exist_ok=True)
    for name in names:
        kind, structure = EXTRA_MODELS.get(name, (name, None))
        fitters = dict(fit.FITTERS)
        if structure:  # the wesn fitter with a forced structure, for this file only
            wc = dataclasses.replace(WESN_DEFAULTS, **structure)
            fit.FITTERS[kind] = lambda captures, normalizer, config, *, kind=kind, wc=wc: fit_wesn(
                kind, wc, captures, normalizer, config
            )
        try:
            model_file, _ = fit_model_file([FIT_CAPTURE], kind=kind, config=FIT_CONFIG, accept_weak=True)
        finally:
            fit.FITTERS.clear()
            fit.FITTERS.update(fitters)
        model_file.provenance["note"] = "golden test model: refit only with make_goldens.py --refit-models"
        save_model(model_path(name), model_file)
        print(f"{_shown(model_path(name))}: refitted")


def outputs() -> dict[Path, list[bytes]]:
    """Every golden output: path -> its lines as generated now."""
    out = {WATCH_GOLDEN: watch_lines()}
    for name in COMPENSATE_GOLDENS:
        out[compensate_path(name)] = compensate_lines(name)
    return out


def how_it_changed(path: Path, lines: list[bytes]) -> tuple[str, bool]:
    """(a description of how ``lines`` differ from the file on disk, True when beyond the tolerance)."""
    if not path.exists():
        return "new", True
    if path.read_bytes() == b"".join(lines):
        return "unchanged", False
    old_text = path.read_text(encoding="utf-8", errors="replace")
    try:
        old = [json.loads(line) for line in old_text.splitlines()]
    except ValueError:
        return "replaces a malformed file", True
    difference = golden.first_difference([json.loads(line) for line in lines], old)
    if difference is None:
        return f"changed within tolerance (floats within {golden.REL_TOL:g})", False
    return f"changed BEYOND tolerance: {difference}", True


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "--check", action="store_true", help="compare only; exit 1 if any golden differs beyond tolerance"
    )
    parser.add_argument("--refit-models", action="store_true", help="refit the golden model files first")
    args = parser.parse_args(argv)
    if args.refit_models and not args.check:
        refit_models()
    elif not args.check:  # a golden model file added since the last refit
        missing = [name for name in EXTRA_MODELS if not model_path(name).exists()]
        if missing:
            refit_models(missing)
    beyond = False
    for path, lines in outputs().items():
        change, is_beyond = how_it_changed(path, lines)
        beyond |= is_beyond
        print(f"{_shown(path)}: {len(lines)} lines, {change}")
        if not args.check:
            path.write_bytes(b"".join(lines))
    return 1 if args.check and beyond else 0


if __name__ == "__main__":
    sys.exit(main())
