"""Adapting from the turntable's angles: the readout learns from dwell-to-dwell intervals (``law.TableLaw``).

The package's rooms: ``window`` (the blocks' sums by named column), ``screen`` (what a dwell is refused or
rejected for), ``estimate`` (the law's sums and estimate), ``bias`` (the run's bias capture), ``judge`` (a
dwell judged by its neighbours), ``outcomes`` (what became of each dwell), ``state`` (what the law learned
and its chain, saved and restored), and ``law``, the ``TableLaw`` in front of them.
"""

from .estimate import SF_REF_C, SHAPE_CANDIDATES, SHAPE_REGRESSORS, TABLE_SIGMAS
from .law import TableLaw
from .outcomes import MAX_OUTCOMES, OutcomeStatus, OutcomeTally, TableOutcome, reason_kind
from .state import CHAIN_KEY, learned_part

__all__ = [
    "CHAIN_KEY",
    "MAX_OUTCOMES",
    "SF_REF_C",
    "SHAPE_CANDIDATES",
    "SHAPE_REGRESSORS",
    "TABLE_SIGMAS",
    "OutcomeStatus",
    "OutcomeTally",
    "TableLaw",
    "TableOutcome",
    "learned_part",
    "reason_kind",
]
