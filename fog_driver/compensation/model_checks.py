"""The numbers a model file may hold: checked over its whole document before anything is built from it
(``model.model_file_from_doc``, which every load goes through: ``run`` at start, a reload, and every
offline command), so that no NaN, infinity or absurd number reaches the compensator, where it would end
a run mid-stream or pin the drift at its bound.

The rule (``check_model_numbers``): every number outside ``provenance`` (the fit's free-form record,
never used to compensate) is finite and of magnitude at most ``MAX_MODEL_NUMBER`` (1e9).  What fits
write is far inside it: the largest weight of the shipped default is 2.3e3 (the coil neuron's 4th power,
whose regressor is small), the golden models' weights stay under 300, their intercepts under 5 deg/h,
the inputs' means, scales and fit box (degC, degC/min) under 100, the estimate's bound under 4 deg/h,
time constants of minutes to hours (leaks 1e-4 to 1e-1 per s) and seeds single digits.  A number beyond
1e9 is a corrupt or hostile file, not a fit.  The counts are bounded where the fit bounds them, each by
the fit's own constant: at most ``uncertainty.MAX_CANDIDATES`` candidates (``UncertaintySpec``), at most
``reservoir.MAX_NEURONS`` neurons in any reservoir (here: every ``n_neurons``); every array's shape is checked
against the model's as it is built.
"""

from __future__ import annotations

import math
from typing import Any

from .reservoir import MAX_NEURONS

#: The largest magnitude of any number in a model file outside ``provenance`` (module docstring).
MAX_MODEL_NUMBER = 1e9

#: Top-level keys whose numbers are not checked: the fit's record, not used to compensate.
UNCHECKED_KEYS = frozenset({"provenance"})


def check_model_numbers(doc: dict[str, Any]) -> None:
    """``ValueError`` naming the first number of ``doc`` (a model file's document) outside
    ``UNCHECKED_KEYS`` that is not finite ("model.weights[3] is not a finite number (nan)") or whose
    magnitude exceeds ``MAX_MODEL_NUMBER``, or any ``n_neurons`` over ``MAX_NEURONS``; booleans are not numbers
    here (their keys check them)."""
    for key, value in doc.items():
        if key not in UNCHECKED_KEYS:
            _check(value, str(key))


def _check(value: Any, where: str) -> None:
    stack = [(value, where)]
    while stack:  # iterative: a deeply nested document cannot exhaust the stack
        value, where = stack.pop()
        if isinstance(value, dict):
            stack.extend((v, f"{where}.{k}") for k, v in reversed(value.items()))
        elif isinstance(value, list):
            stack.extend((v, f"{where}[{i}]") for i, v in reversed(list(enumerate(value))))
        elif isinstance(value, bool):
            continue
        elif isinstance(value, float) and not math.isfinite(value):
            raise ValueError(f"{where} is not a finite number ({value!r})")
        elif isinstance(value, (int, float)) and abs(value) > MAX_MODEL_NUMBER:
            raise ValueError(f"{where} is {_shown(value)}: beyond {_shown(MAX_MODEL_NUMBER)}, more than any fit writes")
        elif where.endswith(".n_neurons") and isinstance(value, int) and value > MAX_NEURONS:
            raise ValueError(f"{where}: {value} neurons; a fit makes at most {MAX_NEURONS}")


def _shown(value: float) -> str:
    """A number as a message shows it: 3 significant digits, ``1e308`` (an integer too long: its digit count)."""
    if isinstance(value, int) and len(str(abs(value))) > 20:
        return f"an integer of {len(str(abs(value)))} digits"
    mantissa, _, exponent = f"{value:.3g}".partition("e")
    return f"{mantissa}e{int(exponent)}" if exponent else mantissa
