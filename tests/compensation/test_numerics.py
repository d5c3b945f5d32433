"""The machine-independent arithmetic (``fog_driver.compensation.numerics``): accurate, fixed order,
and the same bits when numpy, OpenBLAS and libm are made to compute as another CPU would."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from decimal import Context, Decimal
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fog_driver.compensation import numerics

pytestmark = pytest.mark.determinism

HERE = Path(__file__).resolve().parents[1]
_CTX = Context(prec=50)


def correctly_rounded_exp(x: float) -> float:
    return float(_CTX.exp(Decimal(x)))


def ulps(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance in units in the last place between doubles of the same sign (finite, >= 0 here)."""
    return np.abs(np.asarray(a).view(np.int64) - np.asarray(b).view(np.int64))


# --- exp -------------------------------------------------------------------------------------------

#: Java 17's StrictMath.exp (fdlibm's e_exp.c, an independent implementation of the same algorithm), as
#: exact hexadecimal doubles: (x, StrictMath.exp(x)).  Our exp equals fdlibm everywhere except below
#: |x| = 2^-28, where fdlibm returns 1 + x and we keep the polynomial (correctly rounded; tested below).
STRICTMATH_EXP = [
    ("0x1.0000000000000p+0", "0x1.5bf0a8b14576ap+1"),
    ("-0x1.0000000000000p+0", "0x1.78b56362cef38p-2"),
    ("0x1.0000000000000p-1", "0x1.a61298e1e069cp+0"),
    ("-0x1.0000000000000p-1", "0x1.368b2fc6f960ap-1"),
    ("0x1.4000000000000p+3", "0x1.5829dcf950560p+14"),
    ("-0x1.4000000000000p+3", "0x1.7cd79b5647c9ap-15"),
    ("0x1.9000000000000p+6", "0x1.3494a9b171bf5p+144"),
    ("-0x1.9000000000000p+6", "0x1.a8c1f14e2af5dp-145"),
    ("0x1.5e00000000000p+9", "0x1.d945df4f8ec8ep+1009"),
    ("-0x1.5e00000000000p+9", "0x1.14f2b0fb9307fp-1010"),
    ("-0x1.7200000000000p+9", "0x0.0000000000055p-1022"),
    ("0x1.62e3d70a3d70ap+9", "0x1.fe9ce5c4c52b4p+1023"),
    ("0x1.62e42fefa39efp-2", "0x1.6a09e667f3bccp+0"),
    ("0x1.0c6f7a0b5ed8dp-20", "0x1.000010c6f82d7p+0"),
    ("-0x1.0c6f7a0b5ed8dp-20", "0x1.ffffde7211d81p-1"),
    ("-0x1.649296437f8d1p+4", "0x1.ccee2000c2806p-33"),
    ("-0x1.62f1ef059b000p-5", "0x1.ea4a278c4094cp-1"),
    ("0x1.85c0f20ad9b98p+2", "0x1.b960bf00cc198p+8"),
    ("-0x1.c47563a95450ap+4", "0x1.26949c686cf8cp-41"),
    ("-0x1.51fdaf79edeacp+4", "0x1.7014eeecc302ap-31"),
    ("0x1.9b152418c16ecp+4", "0x1.0c1bdf1d91e31p+37"),
    ("-0x1.9c65706fb2284p+4", "0x1.c25745ea69107p-38"),
    ("-0x1.636ac112f6f75p+4", "0x1.ef73d328f7166p-33"),
    ("0x1.ae65335fd4428p+4", "0x1.c03931174ea03p+38"),
]


def test_exp_is_fdlibm_bit_for_bit():
    x = np.array([float.fromhex(a) for a, _ in STRICTMATH_EXP])
    want = np.array([float.fromhex(b) for _, b in STRICTMATH_EXP])
    assert numerics.exp(x).tobytes() == want.tobytes()


@pytest.mark.parametrize("lo, hi", [(-0.7, 0.7), (-40.0, 40.0), (-745.1, -700.0), (-708.0, 709.7)])
def test_exp_is_within_one_ulp_of_the_correctly_rounded_value(lo, hi):
    x = np.random.default_rng(int(abs(1000 * hi))).uniform(lo, hi, 4000)
    ref = np.array([correctly_rounded_exp(v) for v in x.tolist()])
    got = numerics.exp(x)
    assert ulps(got, ref).max() <= 1
    assert (got == ref).mean() > 0.85  # mostly correctly rounded (np.exp: about 95 %)


def test_exp_is_correctly_rounded_where_fdlibm_takes_the_shortcut():
    x = np.random.default_rng(3).uniform(-(2.0**-28), 2.0**-28, 2000)
    ref = np.array([correctly_rounded_exp(v) for v in x.tolist()])
    assert numerics.exp(x).tobytes() == ref.tobytes()


def test_exp_special_values_and_limits():
    with np.errstate(over="ignore"):
        got = numerics.exp(np.array([0.0, -0.0, np.inf, -np.inf, 709.78, 709.79, 1e300, -745.13, -745.14, -1e300]))
    assert got[0] == got[1] == 1.0
    assert got[2] == np.inf and got[3] == 0.0
    assert got[4] == correctly_rounded_exp(709.78) and got[5] == np.inf and got[6] == np.inf
    assert got[7] == 5e-324 and got[8] == 0.0 and got[9] == 0.0
    with np.errstate(all="raise"):  # NaN in, NaN out, quietly (no invalid-cast warning)
        assert np.isnan(numerics.exp(np.array([np.nan, 1.0]))[0])
        assert np.isnan(numerics.exp(math.nan))
    assert numerics.exp(2.0).shape == () and float(numerics.exp(2.0)) == correctly_rounded_exp(2.0)


@settings(max_examples=200)
@given(st.floats(-745.0, 709.0))
def test_exp_any_argument_is_within_one_ulp(x):
    assert ulps(numerics.exp(x), np.float64(correctly_rounded_exp(x))) <= 1


def test_exp_of_one_element_equals_the_same_element_among_many():
    x = np.random.default_rng(4).uniform(-50, 50, 500)
    assert np.array([float(numerics.exp(v)) for v in x]).tobytes() == numerics.exp(x).tobytes()


def test_correctly_rounded_scalars():
    x = np.random.default_rng(6).uniform(-3, 3, 300).tolist()
    for v in x:
        assert numerics.exp_correctly_rounded(v) == correctly_rounded_exp(v)
        assert abs(numerics.exp_correctly_rounded(v) - math.exp(v)) <= math.ulp(math.exp(v))
    # expm1 keeps its relative accuracy for tiny arguments, where exp(x) - 1 has none.
    for v in (1e-10, -1e-10, 1 / 7200, -1 / 3600):
        series = v + v * v / 2 + v**3 / 6 + v**4 / 24
        assert numerics.expm1_correctly_rounded(v) == pytest.approx(series, rel=1e-15)
        assert abs(numerics.expm1_correctly_rounded(v) - math.expm1(v)) <= math.ulp(math.expm1(v))


# --- sums in a fixed order -------------------------------------------------------------------------


def left_to_right(values) -> float:
    acc = None
    for v in values:
        acc = v if acc is None else acc + v
    return acc


def test_dot_matvec_total_sum_strictly_left_to_right():
    rng = np.random.default_rng(7)
    f, w = rng.normal(size=(50, 13)) * 10.0 ** rng.integers(-8, 8, (50, 13)), rng.normal(size=13)
    want = np.array([left_to_right((row * w).tolist()) for row in f])
    assert numerics.dot(f, w).tobytes() == want.tobytes()
    assert numerics.matvec(f, w).tobytes() == want.tobytes()
    assert float(numerics.dot(f[3], w)) == want[3]  # one row: the same bits as among many
    assert numerics.total(f[4]) == left_to_right(f[4].tolist()) and numerics.total(np.zeros(0)) == 0.0
    # The same numbers as BLAS, to rounding (values of mixed magnitudes: cancellation is fine here).
    np.testing.assert_allclose(numerics.matvec(f[:, :4], w[:4]), f[:, :4] @ w[:4], rtol=1e-12, atol=1e-300)


# --- as another CPU would ---------------------------------------------------------------------------

_CHILD = """
import json, sys
import numpy as np
from fog_driver.compensation import numerics
from fog_driver.modelfiles import load_model
rng = np.random.default_rng(8)
x = rng.uniform(-30, 30, 20000)
a, v = rng.normal(size=(40, 40)), rng.normal(size=40)
z = rng.normal(size=(300, 8))
out = {"numerics.exp": numerics.exp(x).tobytes().hex(), "numerics.matvec": numerics.matvec(a, v).tobytes().hex(),
       "np.exp": np.exp(x).tobytes().hex(), "BLAS matvec": (a @ v).tobytes().hex()}
for kind in ("polynomial", "wesn", "paper", "pso-svr"):
    model = load_model(sys.argv[1] + f"/{kind}.yaml").model
    model.reset(); model.start(z[0])
    out[kind] = model.run(z).tobytes().hex()
print(json.dumps(out))
"""


def _child(env: dict[str, str] | None) -> dict[str, str]:
    import os

    proc = subprocess.run(
        [sys.executable, "-c", _CHILD, str(HERE / "data" / "golden" / "models")],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, **(env or {})},
    )
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout)


@pytest.mark.parametrize("profile", ["generic", "avx2"])
def test_the_same_bits_when_numpy_openblas_and_libm_compute_as_another_cpu(profile):
    sys.path.insert(0, str(HERE))
    try:
        import other_cpu
    finally:
        sys.path.remove(str(HERE))
    here, there = _child(None), _child(other_cpu.environment(profile))
    for key in ("numerics.exp", "numerics.matvec", "polynomial", "wesn", "paper", "pso-svr"):
        assert here[key] == there[key], f"{key} differs under {profile}"
    # The settings are not a no-op: the platform's own math changed (where this CPU has what they turn off).
    if profile == "generic" and other_cpu.numpy_dispatch_targets_on():
        assert here["np.exp"] != there["np.exp"] or here["BLAS matvec"] != there["BLAS matvec"]
