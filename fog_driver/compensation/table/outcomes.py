"""What became of each dwell: its status, the outcome record, the log of the last ``MAX_OUTCOMES`` and their tally.

A dwell's outcome is noted once, when the law has judged it.  The judge by the neighbours
(``judge``) may later find that a dwell learned was the wrong one: its verdict (``Revision``) gives a new
log (``OutcomeLog.revised``) in which that dwell's outcome is rejected and the dwell after it has the
interval learned in its place; the outcome values and the log they were in are left as they were.
``OutcomeLog.get_state`` is the log and its tally as plain values (exact), ``set_state`` its inverse.
"""

from __future__ import annotations

import enum
import math
import re
from collections import Counter, deque
from typing import Any, NamedTuple

from ...dwells import Dwell

__all__ = ["MAX_OUTCOMES", "OutcomeLog", "OutcomeStatus", "OutcomeTally", "Revision", "TableOutcome", "reason_kind"]

#: The outcomes kept (a daemon runs for months; the counters count every dwell).
MAX_OUTCOMES = 10_000


class OutcomeStatus(enum.StrEnum):
    """A dwell's status (its value is the word written in reports, STATUS and NDJSON), in report order."""

    #: the start of a chain
    ANCHOR = "anchor"
    #: an interval of the bias capture
    BIAS = "bias"
    LEARNED = "learned"
    #: degraded inputs in the interval, or the warm-up's blocks (``AdaptConfig.warmup_s``): not learned, not a fault
    SKIPPED = "skipped"
    #: flagged ``guard``: motion, an unsteady rate, a creep or an interval that disagrees with the gyro
    REJECTED = "rejected"
    #: bad input: nothing changed
    REFUSED = "refused"


class TableOutcome(NamedTuple):
    """What became of one dwell (``OutcomeStatus``), why, and the interval's figures when there was one."""

    t_end_s: float
    status: OutcomeStatus
    reason: str = ""
    innovation_arcsec: float = math.nan
    sigma_arcsec: float = math.nan
    move_deg: float = math.nan
    interval_s: float = math.nan


def outcome(
    dwell: Dwell, status: OutcomeStatus, reason: str = "", values: dict[str, float] | None = None
) -> TableOutcome:
    """The outcome of ``dwell``; ``values``: the interval's figures by field name (the others NaN)."""
    v = values or {}
    return TableOutcome(
        dwell.t_end_s,
        status,
        reason,
        v.get("innovation_arcsec", math.nan),
        v.get("sigma_arcsec", math.nan),
        v.get("move_deg", math.nan),
        v.get("interval_s", math.nan),
    )


def outcome_state(o: TableOutcome) -> list[Any]:
    """An outcome as plain values: its fields in order, the status as its word."""
    return [float(o.t_end_s), str(o.status), o.reason, *(float(v) for v in o[3:])]


def outcome_from(values: list[Any]) -> TableOutcome:
    """Inverse of ``outcome_state``; ``ValueError`` for values that are not an outcome."""
    t_end_s, status, reason, *figures = values
    if not isinstance(reason, str) or len(figures) != 4:
        raise ValueError(f"not an outcome: {values!r}")
    return TableOutcome(float(t_end_s), OutcomeStatus(status), reason, *(float(v) for v in figures))


#: A number in a reason (``reason_kind`` leaves them out).
_NUMBER = re.compile(r"[-+]?\d[\d,]*(?:\.\d+)?(?:e[-+]?\d+)?|\bnan\b|\binf\b")


def reason_kind(reason: str) -> str:
    """What a reason says, its numbers left out (``#``): the outcomes of one kind, whatever their figures."""
    return _NUMBER.sub("#", reason)


class OutcomeTally:
    """Every outcome counted, by status and by status and reason kind (``reason_kind``), with the first
    ``EXAMPLES`` outcomes of each kind."""

    EXAMPLES = 3

    def __init__(self) -> None:
        self.by_status: Counter[str] = Counter()
        #: (status, reason kind) -> [count, the first outcomes], in the order the kinds first came
        self.by_reason: dict[tuple[str, str], tuple[list[int], list[TableOutcome]]] = {}

    def add(self, outcome: TableOutcome) -> None:
        self.by_status[outcome.status] += 1
        count, examples = self.by_reason.setdefault((outcome.status, reason_kind(outcome.reason)), ([0], []))
        count[0] += 1
        if len(examples) < self.EXAMPLES:
            examples.append(outcome)

    @property
    def total(self) -> int:
        return sum(self.by_status.values())

    def get_state(self) -> dict[str, Any]:
        """The counts as plain values: by status, and by reason kind with their first outcomes (in order)."""
        return {
            "by_status": [[str(s), n] for s, n in self.by_status.items()],
            "by_reason": [
                [str(s), kind, n[0], [outcome_state(o) for o in e]] for (s, kind), (n, e) in self.by_reason.items()
            ],
        }

    def set_state(self, state: dict[str, Any]) -> None:
        """Inverse of ``get_state``."""
        by_status: Counter[str] = Counter({OutcomeStatus(s): int(n) for s, n in state["by_status"]})
        self.by_reason = {
            (OutcomeStatus(s), str(kind)): ([int(n)], [outcome_from(o) for o in e])
            for s, kind, n, e in state["by_reason"]
        }
        self.by_status = by_status

    def copy(self) -> OutcomeTally:
        out = OutcomeTally()
        out.by_status = Counter(self.by_status)
        out.by_reason = {k: ([n[0]], list(e)) for k, (n, e) in self.by_reason.items()}
        return out


class Revision(NamedTuple):
    """The judge's verdict on two past dwells (``judge``): the one learned at ``blamed_t_end_s`` was wrong
    (rejected, for ``reason``), and the one rejected at ``merged.t_end_s`` has ``merged``, the interval learned
    in place of the two."""

    blamed_t_end_s: float
    merged: TableOutcome
    reason: str


class OutcomeLog:
    """The dwells' outcomes in order: the last ``MAX_OUTCOMES`` in ``recent``, and those that fell off its old
    end counted (``tally`` counts them all)."""

    def __init__(self, recent: deque[TableOutcome] | None = None, dropped: OutcomeTally | None = None) -> None:
        self.recent: deque[TableOutcome] = recent if recent is not None else deque(maxlen=MAX_OUTCOMES)
        self._dropped = dropped if dropped is not None else OutcomeTally()

    def note(self, outcome: TableOutcome) -> TableOutcome:
        """``outcome`` at the end (the oldest counted and dropped once ``MAX_OUTCOMES`` are kept)."""
        if len(self.recent) == self.recent.maxlen:
            self._dropped.add(self.recent[0])
        self.recent.append(outcome)
        return outcome

    def get_state(self) -> dict[str, Any]:
        """The log as plain values (exact): the outcomes kept, oldest first, and the tally of those dropped."""
        return {"recent": [outcome_state(o) for o in self.recent], "dropped": self._dropped.get_state()}

    def set_state(self, state: dict[str, Any]) -> None:
        """Inverse of ``get_state``; ``ValueError`` (nothing changed) for values that are not outcomes."""
        recent = [outcome_from(o) for o in state["recent"]]
        if len(recent) > MAX_OUTCOMES:
            raise ValueError(f"an outcome log keeps at most {MAX_OUTCOMES} outcomes, got {len(recent)}")
        dropped = OutcomeTally()
        dropped.set_state(state["dropped"])
        self.recent, self._dropped = deque(recent, maxlen=MAX_OUTCOMES), dropped

    def tally(self) -> OutcomeTally:
        """Every outcome noted, counted (``recent`` keeps the last ``MAX_OUTCOMES``)."""
        out = self._dropped.copy()
        for o in self.recent:
            out.add(o)
        return out

    def revised(self, revision: Revision) -> OutcomeLog:
        """A new log with ``revision`` in it: from the newest back, the rejected outcomes at the merged dwell's
        end become ``revision.merged``, up to the learned outcome at the blamed dwell's end, which becomes
        rejected for ``revision.reason`` (its figures kept); the outcomes before it as they were.  This log is
        left as it was."""
        merged_t, blamed_t = revision.merged.t_end_s, revision.blamed_t_end_s
        newest: list[TableOutcome] = []
        older = list(self.recent)
        while older:
            o = older.pop()
            if o.t_end_s == merged_t and o.status == OutcomeStatus.REJECTED:
                newest.append(revision.merged)
            elif o.t_end_s == blamed_t and o.status == OutcomeStatus.LEARNED:
                newest.append(o._replace(status=OutcomeStatus.REJECTED, reason=revision.reason))
                break
            else:
                newest.append(o)
        older.extend(reversed(newest))
        return OutcomeLog(deque(older, maxlen=self.recent.maxlen), self._dropped.copy())
