"""Choosing between models by a margin that accounts for sampling noise.

Two models' residuals on the same blocks are paired: over blocks ``b = 1..n`` (chunks of device time,
long against the residual's correlation), with ``a_b`` and ``p_b`` the mean squared residual of each
model in block ``b``::

    d_b    = a_b - p_b                          (how much more the first leaves in block b)
    margin = mean(d_b)                          ((deg/h)^2: the difference of the mean squares)
    se     = std(d_b, ddof=1) / sqrt(n)         (its standard error)

The same in deg/h, as the report prints it: ``rms_a - rms_p`` and its standard error by the delta
method, ``se / (rms_a + rms_p)`` (d(r^2) = 2 r dr at r = (rms_a + rms_p) / 2).

A choice is made only when the margin exceeds ``SE_MULTIPLE`` (2) standard errors; otherwise the
models are tied and the preferred one (the physical model, or the simpler structure) is kept.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np

#: A difference counts when it exceeds this many standard errors.
SE_MULTIPLE = 2.0


class Margin(NamedTuple):
    """Paired comparison of model A's residual with model B's over ``n`` blocks (``paired_margin``)."""

    rms_a_dph: float
    rms_b_dph: float
    margin_dph: float  #: rms_a - rms_b: positive when A leaves more
    se_dph: float  #: its standard error
    n_blocks: int

    @property
    def b_better(self) -> bool:
        """B leaves less than A by more than ``SE_MULTIPLE`` standard errors."""
        return self.margin_dph > SE_MULTIPLE * self.se_dph and self.n_blocks >= 2

    @property
    def a_better(self) -> bool:
        """A leaves less than B by more than ``SE_MULTIPLE`` standard errors."""
        return -self.margin_dph > SE_MULTIPLE * self.se_dph and self.n_blocks >= 2

    @property
    def tied(self) -> bool:
        return not (self.a_better or self.b_better)

    def to_dict(self) -> dict[str, float | int]:
        return {
            "rms_a_dph": self.rms_a_dph,
            "rms_b_dph": self.rms_b_dph,
            "margin_dph": self.margin_dph,
            "se_dph": self.se_dph,
            "n_blocks": self.n_blocks,
        }


def paired_margin(squares_a: np.ndarray, squares_b: np.ndarray) -> Margin:
    """The paired margin (module docstring) from each block's mean squared residual of A and of B."""
    a = np.asarray(squares_a, dtype=float)
    b = np.asarray(squares_b, dtype=float)
    if a.shape != b.shape or a.ndim != 1:
        raise ValueError("paired_margin needs two equal 1-D arrays of block mean squares")
    n = len(a)
    if n == 0:
        return Margin(math.nan, math.nan, math.nan, math.nan, 0)
    rms_a, rms_b = math.sqrt(float(a.mean())), math.sqrt(float(b.mean()))
    d = a - b
    se_sq = float(d.std(ddof=1)) / math.sqrt(n) if n > 1 else math.inf
    scale = rms_a + rms_b
    se = se_sq / scale if scale > 0 else 0.0
    return Margin(rms_a, rms_b, rms_a - rms_b, se, n)


def block_squares(residual: np.ndarray, groups: np.ndarray, windows: np.ndarray, chunks: np.ndarray) -> np.ndarray:
    """Per chunk, the mean square of the residual's window means about each group's mean of them::

        m_w   = mean of the residual over window w
        c_w   = m_w - mean(m_v for the windows v of w's group)
        s_b   = mean(c_w^2 for the windows w of block b)        b = (group, chunk)

    ``residual``, ``groups`` (e.g. a capture, or a capture and a fold: whatever has its own mean), ``windows``
    (window index within the group: the residual is averaged per window, e.g. 10-min means) and ``chunks``
    (chunk index within the group, each window wholly in one chunk): equal-length 1-D arrays.  Returns
    ``s_b`` for every (group, chunk) that holds a window, in sorted order: what ``paired_margin`` pairs
    (the same ``groups``, ``windows`` and ``chunks`` for both models give the same blocks).  A group of one
    window says nothing (its mean removed, nothing is left) and gives no block."""
    residual = np.asarray(residual, dtype=float)
    groups, windows, chunks = (np.asarray(a, dtype=np.int64) for a in (groups, windows, chunks))
    if not residual.ndim == groups.ndim == windows.ndim == chunks.ndim == 1 or not (
        len(residual) == len(groups) == len(windows) == len(chunks)
    ):
        raise ValueError("block_squares needs four equal-length 1-D arrays")
    if not len(residual):
        return np.zeros(0)
    uniq_w, inverse = np.unique(np.stack([groups, windows]).T, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    means = np.bincount(inverse, weights=residual) / np.bincount(inverse)
    group_of_w = uniq_w[:, 0]
    chunk_of_w = np.zeros(len(uniq_w), dtype=np.int64)
    chunk_of_w[inverse] = chunks
    _, group_index, windows_in_group = np.unique(group_of_w, return_inverse=True, return_counts=True)
    group_index = group_index.ravel()
    means -= (np.bincount(group_index, weights=means) / windows_in_group)[group_index]
    said = windows_in_group[group_index] > 1
    key_c = np.stack([group_of_w[said], chunk_of_w[said]]).T
    if not len(key_c):
        return np.zeros(0)
    _, inverse_c = np.unique(key_c, axis=0, return_inverse=True)
    inverse_c = inverse_c.ravel()
    return np.bincount(inverse_c, weights=means[said] ** 2) / np.bincount(inverse_c)


def choose(margin: Margin, kind: str, *, fall_back: bool) -> dict[str, Any]:
    """The decision between the physical model ``kind`` (A of ``margin``) and the polynomial (B), with what
    it rests on (the model file's ``provenance.selection.choice``)::

        decision = "polynomial saved"  when fall_back and the polynomial leaves less by > SE_MULTIPLE se
                 = f"{kind} as asked"   without fall_back (``--kind``: nothing is switched)
                 = f"{kind} kept"       otherwise

    ``margin_dph``: how much less the polynomial leaves than ``kind`` (rms_kind - rms_polynomial), ``se_dph``
    its standard error, over ``n_blocks`` chunks of the fit's own validation split."""
    if not fall_back:
        decision = f"{kind} as asked"
    elif margin.b_better:
        decision = "polynomial saved"
    else:
        decision = f"{kind} kept"
    return {
        "decision": decision,
        "rms_dph": {kind: margin.rms_a_dph, "polynomial": margin.rms_b_dph},
        "margin_dph": margin.margin_dph,
        "se_dph": margin.se_dph,
        "n_blocks": margin.n_blocks,
        "se_multiple": SE_MULTIPLE,
    }


def paired(choice: dict[str, Any]) -> Margin:
    """The ``Margin`` a ``choose`` record rests on (A: the physical model, B: the polynomial)."""
    kind = next(k for k in choice["rms_dph"] if k != "polynomial")
    rms = choice["rms_dph"]
    return Margin(rms[kind], rms["polynomial"], choice["margin_dph"], choice["se_dph"], choice["n_blocks"])


def polynomial_lead(choice: dict[str, Any]) -> str:
    """How much less the polynomial leaves, in words: "the polynomial leaves 0.0123 +- 0.0020 deg/h less
    than the wesn on the fit's own validation split (6.2 standard errors; saving it needs 2)"."""
    m = paired(choice)
    kind = next(k for k in choice["rms_dph"] if k != "polynomial")
    errors = abs(m.margin_dph) / m.se_dph if m.se_dph > 0 else math.inf
    return (
        f"the polynomial leaves {abs(m.margin_dph):.4f} +- {m.se_dph:.4f} deg/h "
        f"{'less' if m.margin_dph >= 0 else 'more'} than the {kind} on the fit's own validation split "
        f"({errors:.1f} standard errors{f'; saving it needs {SE_MULTIPLE:g}' if m.margin_dph > 0 else ''})"
    )


def describe(choice: dict[str, Any]) -> str:
    """The fit report's line for a ``choose`` record: the decision, the margin and its standard error."""
    decision, m = choice["decision"], paired(choice)
    kind = next(k for k in choice["rms_dph"] if k != "polynomial")
    if m.n_blocks < 2 or not (math.isfinite(m.margin_dph) and math.isfinite(m.se_dph)):
        return (
            f"model choice: {decision}: the fit's own validation split has {m.n_blocks} chunk"
            f"{'s' if m.n_blocks != 1 else ''} of whole 10-min windows, too few to compare the {kind} with the "
            f"polynomial"
        )
    lead = polynomial_lead(choice)
    if decision.endswith(" as asked"):
        return f"model choice: {kind}, as --kind asked: {lead}" + (
            "; without --kind the polynomial would be saved" if m.b_better else ""
        )
    return f"model choice: {decision}: {lead}"
