"""``compensate --table-log``: whether the table log's dwells reached the compensator, and what became of them."""

from __future__ import annotations

from pathlib import Path

from ..compensation.pipeline import Compensator
from ..compensation.table import SHAPE_CANDIDATES, OutcomeStatus, TableLaw
from ..errors import InputFileError

__all__ = ["check_table_log_used", "table_summary_lines"]


def check_table_log_used(compensator: Compensator, table_log: str | Path, capture: str | Path) -> TableLaw:
    """The compensator's table law, once the capture is through; a one-line ``InputFileError`` when dwells of
    the log were never reached (they end after the capture does: the log of another capture)."""
    law = compensator.table
    if law is None:
        raise ValueError("the compensator did not adapt from table angles")
    end = compensator.device_time_s or 0.0
    left = [d for d in compensator.pending_dwells if d.t_end_s > end + 1.0]  # within the last block: not reached
    if left:
        raise InputFileError(
            f"{table_log}: {len(left)} dwells end after {capture} does (the first at {left[0].t_end_s:,.1f} s of "
            f"device time from its first sample): the table log of another capture?"
        )
    return law


def table_summary_lines(compensator: Compensator) -> list[str]:
    """The report ``compensate --table-log`` prints: every dwell counted by outcome; the rejected and refused
    ones grouped by reason (``table.reason_kind``), one line a reason with its count, the first one's reason in
    full and when the first few ended; the scale factor."""
    law = compensator.table
    if law is None:
        return []
    tally = law.tally()
    counts = tally.by_status
    order = tuple(OutcomeStatus)  # report order
    parts = ", ".join(f"{counts[k]:,} {k}" for k in order if counts[k])
    lines = [f"table log: {tally.total:,} dwells: {parts or 'none reached'}"]
    for status in (OutcomeStatus.REJECTED, OutcomeStatus.REFUSED):
        kinds = [(n[0], examples) for (st, _), (n, examples) in tally.by_reason.items() if st == status]
        for n, examples in sorted(kinds, key=lambda k: -k[0]):
            ends = ", ".join(f"{o.t_end_s:,.1f}" for o in examples)
            more = ", ..." if n > len(examples) else ""
            lines.append(f"  {n:,} {status}: {examples[0].reason} (the dwells ending at {ends}{more} s)")
    s = law.summary()
    applied = "applied to the angle" if s["scale_factor_applied"] else "not applied (not yet known to 5 ppm)"
    lines.append(
        f"scale factor: {s['scale_factor_ppm']:+.1f} +- {s['scale_factor_sigma_ppm']:.1f} ppm at 25 degC, "
        f"{s['scale_factor_ppm_per_c']:+.2f} ppm/degC; {applied}"
    )
    if s["adapted_in_use"]:
        w = s["frozen_weight"]
        on = (
            f"blending the fit's {s['shape_regressors']} candidate structures"
            if s["shape"] == SHAPE_CANDIDATES
            else "on the model's own regressors"
        )
        state = f"the drift in use: the frozen model's at weight {w:.2f}, the adapted ones' ({on}) at {1 - w:.2f}"
    elif s["bias_dph"] is None:
        state = "the frozen drift in use (the bias not yet captured)"
    else:
        state = "the frozen drift in use (the comparison guard found the adapted one worse)"
    lines.append(f"at the end: {state}; blocks held at the runaway bound {s['clamped_blocks']:,}, resets {s['guards']}")
    return lines
