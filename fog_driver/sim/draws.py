"""Reproducible parameter draws: one uniform stream per parameter name, decimal arithmetic for log-uniform.

``Draws(seed, ranges)`` draws instrument ``seed``'s parameters from ``ranges`` (name -> ``Range``); the stream
of a name is keyed by ``(seed, crc32(name))``, so adding a parameter later changes no other, and the values are
the same on every machine (uniforms from numpy's PCG64, the log-uniform's exp/ln correctly rounded in
``decimal``).  ``fog_driver.sim.population`` and ``fog_driver.sim.families`` draw with it.
"""

from __future__ import annotations

import zlib
from collections.abc import Mapping
from dataclasses import dataclass
from decimal import Context, Decimal

import numpy as np

__all__ = ["Draws", "Range"]

_DECIMAL = Context(prec=40)


@dataclass(frozen=True)
class Range:
    """A parameter's range: uniform in ``lo..hi`` (``log``: log-uniform), with a random sign if ``signed``."""

    lo: float
    hi: float
    log: bool = False
    signed: bool = False


class Draws:
    """Uniform draws for one instrument, one stream per parameter name (independent of their order)."""

    def __init__(self, seed: int, ranges: Mapping[str, Range]) -> None:
        self.seed = seed
        self.ranges = ranges

    def uniforms(self, name: str, n: int) -> list[float]:
        stream = np.random.SeedSequence([self.seed, zlib.crc32(name.encode("ascii"))])
        return np.random.default_rng(stream).random(2 * n).tolist()  # (value, sign) pairs

    def values(self, name: str, n: int = 1) -> list[float]:
        r = self.ranges[name]
        u = self.uniforms(name, n)
        out = []
        for value_u, sign_u in zip(u[0::2], u[1::2]):
            if r.log:  # exp(ln lo + u (ln hi - ln lo)), correctly rounded: the same on every machine
                lo, hi = Decimal(r.lo).ln(_DECIMAL), Decimal(r.hi).ln(_DECIMAL)
                v = float(_DECIMAL.exp(lo + Decimal(value_u) * (hi - lo)))
            else:
                v = r.lo + value_u * (r.hi - r.lo)
            out.append(-v if r.signed and sign_u < 0.5 else v)
        return out

    def value(self, name: str) -> float:
        return self.values(name)[0]

    def integer(self, name: str) -> int:
        """An integer uniform in ``lo..hi`` (both included) from the name's stream."""
        r = self.ranges[name]
        span = int(r.hi) - int(r.lo) + 1
        return int(r.lo) + min(span - 1, int(self.uniforms(name, 1)[0] * span))
