"""Machine-independent arithmetic for the per-block path: the same bits on every CPU.

Why.  numpy chooses its kernels by CPU at run time.  ``np.exp`` on float64 has its own AVX-512F
code and otherwise calls the C library's ``exp``, which glibc chooses by CPU again (an FMA
version or an SSE2 one: on 300,000 random arguments in [-5, 5] they disagree in the last bit of
0.07 %, and with numpy's AVX-512 code in many more); ``a @ b`` goes to OpenBLAS, whose kernel,
summation order and use of fused multiply-adds depend on the CPU.  A compensated angle is the
sum of hours of drift estimates, so such last-bit differences reach every published number.

What is the same on every IEEE-754 machine: the basic operations ``+ - * /`` (each correctly
rounded), ``rint``, ``ldexp`` and comparisons (exact), and sums taken in a fixed order.  numpy
applies each elementwise operation as its own correctly rounded step (it never fuses a multiply
and an add), so a function built from those alone depends on its inputs only.  Everything the
compensator does per model block is built that way (``Compensator``, the drift models, the
adaptive law), so a model file compensates a capture to the same bits on the bench PC and on the
analysis workstation, whatever their CPUs; fitting (LAPACK, BLAS) is not (docs/explanation/determinism.md).

* ``exp(x)``: fdlibm's ``e_exp.c`` (Sun, 1993; the algorithm of Java's ``StrictMath.exp``) in
  numpy operations: ``x = k ln2 + r`` with ``k = rint(x / ln2)``, ``|r| <= ln2 / 2``, ``ln2``
  split in two (``k * LN2_HI`` is exact), then ``exp(r) = 1 + 2r / (2 - c(r))`` with
  ``c(r) = r - r^2 (P1 + P2 r^2 + ... + P5 r^8)``, a Remez fit of error < 2^-59, and
  ``exp(x) = 2^k exp(r)`` by ``ldexp``.  Bit for bit fdlibm (tested against Java's StrictMath),
  except below |x| = 2^-28, where fdlibm returns ``1 + x`` and this keeps the polynomial (which is
  correctly rounded there); within 1 ULP of the correctly rounded value everywhere (tested against
  decimal arithmetic); inf above 709.78, 0 below -745.13, NaN for NaN.
* ``dot(f, w)``: ``sum_j f[..., j] w[j]``, strictly left to right (a cumulative sum of the
  exact products: one row and many rows give the same bits, so ``step`` equals ``run``).
* ``matvec(a, x)``: ``a @ x``, each row summed strictly left to right.
* ``sum_last(a)``, ``sum_first(a)``, ``total(v)``: sums over the last or the first axis, strictly in
  order (a cumulative sum for short rows; one vectorized add per index for wide ones).
* ``exp_correctly_rounded(x)``, ``expm1_correctly_rounded(x)``: Python floats, correctly rounded
  (40-digit decimal arithmetic, then one rounding to binary), for constants computed once
  (filter coefficients), not for data.

Cost: ``exp`` is a few dozen numpy calls where ``np.exp`` is one, so on the small arrays of a model
step the calls' overhead dominates and a step costs more than with the platform's math; a model
block is a second of data.  ``benchmarks/bench_model_step.py`` times both (as shipped and with the
platform's math patched in).
"""

from __future__ import annotations

from decimal import Context, Decimal

import numpy as np

__all__ = ["dot", "exp", "exp_correctly_rounded", "expm1_correctly_rounded", "matvec", "sum_first", "sum_last", "total"]

# fdlibm e_exp.c, as exact hexadecimal doubles (the words of its comments).
LN2_HI = float.fromhex("0x1.62e42fee00000p-1")  #: 0x3fe62e42 fee00000: 32 significant bits, k * LN2_HI is exact
LN2_LO = float.fromhex("0x1.a39ef35793c76p-33")  #: 0x3dea39ef 35793c76: ln 2 - LN2_HI
INV_LN2 = float.fromhex("0x1.71547652b82fep+0")  #: 0x3ff71547 652b82fe
P1 = float.fromhex("0x1.555555555553ep-3")  #: 0x3FC55555 5555553E
P2 = float.fromhex("-0x1.6c16c16bebd93p-9")  #: 0xBF66C16C 16BEBD93
P3 = float.fromhex("0x1.1566aaf25de2cp-14")  #: 0x3F11566A AF25DE2C
P4 = float.fromhex("-0x1.bbd41c5d26bf1p-20")  #: 0xBEBBBD41 C5D26BF1
P5 = float.fromhex("0x1.6376972bea4d0p-25")  #: 0x3E663769 72BEA4D0
#: Arguments are clamped here first: exp(710) overflows to inf and exp(-746) rounds to 0, so the
#: clamp changes no result, and it keeps k (and ldexp's exponent) small.
X_MIN, X_MAX = -746.0, 710.0
#: k for a NaN argument (any exponent: the NaN flows through y), so the cast to int is defined.
_K_NAN = -1100.0

_DECIMAL = Context(prec=40)


def exp(x: np.ndarray | float) -> np.ndarray:
    """``e^x`` elementwise, the same bits on every machine (fdlibm's algorithm; module docstring).

    Returns a new float64 array of x's shape (a 0-d array for a scalar).  Overflow to inf raises
    numpy's usual overflow warning; NaN gives NaN quietly, as ``np.exp`` does; underflow to 0 (also
    for -inf) sets numpy's underflow flag, which numpy ignores by default.
    """
    x = np.minimum(np.maximum(np.asarray(x, dtype=np.float64), X_MIN), X_MAX)  # NaN stays NaN
    k = np.rint(x * INV_LN2)
    hi = x - k * LN2_HI
    lo = k * LN2_LO
    r = hi - lo
    t = r * r
    c = r - t * (P1 + t * (P2 + t * (P3 + t * (P4 + t * P5))))
    y = 1.0 - ((lo - (r * c) / (2.0 - c)) - hi)
    return np.ldexp(y, np.fmax(k, _K_NAN).astype(np.int64))


def sum_last(a: np.ndarray) -> np.ndarray:
    """The sum over the last axis, strictly left to right: ``((a0 + a1) + a2) + ...`` (the last column
    of a cumulative sum, ``np.add.accumulate``, which can only be taken in that order).  Not
    ``np.sum``, whose pairwise order is numpy's to choose."""
    return np.add.accumulate(a, axis=-1)[..., -1]


def sum_first(a: np.ndarray) -> np.ndarray:
    """The sum over the first axis, strictly in order: ``((a[0] + a[1]) + a[2]) + ...``, elementwise
    over the other axes (one vectorized add per index: fast when the other axes are wide)."""
    acc = np.array(a[0], dtype=np.float64)
    for i in range(1, len(a)):
        acc += a[i]
    return acc


def dot(f: np.ndarray, w: np.ndarray) -> np.ndarray:
    """``f . w`` over the last axis of ``f`` (one row (n,) or many (T, n)), strictly left to right:
    ``((f0 w0 + f1 w1) + f2 w2) + ...``.  Not BLAS, whose order and fused multiply-adds depend on
    the CPU; and one row gives the same bits as the same row among many."""
    return sum_last(np.multiply(f, w))


def matvec(a: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``a @ x`` for a matrix (n, m) and a vector (m,), each row summed strictly left to right."""
    return sum_last(np.multiply(a, x))


def total(v: np.ndarray) -> float:
    """``sum_j v[j]`` of a vector, strictly left to right."""
    return float(sum_last(v)) if len(v) else 0.0


def exp_correctly_rounded(x: float) -> float:
    """``e^x`` correctly rounded to a double (decimal arithmetic: no CPU or C library involved)."""
    return float(_DECIMAL.exp(Decimal(float(x))))


def expm1_correctly_rounded(x: float) -> float:
    """``e^x - 1`` correctly rounded to a double, accurate for small x too (40 decimal digits)."""
    return float(_DECIMAL.subtract(_DECIMAL.exp(Decimal(float(x))), 1))
