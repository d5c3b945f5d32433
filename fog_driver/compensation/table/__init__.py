"""Adapting from the turntable's angles (``law``): the readout learns from dwell-to-dwell intervals."""

from .law import (
    MAX_OUTCOMES,
    SF_REF_C,
    SHAPE_CANDIDATES,
    SHAPE_REGRESSORS,
    TABLE_SIGMAS,
    OutcomeTally,
    TableLaw,
    TableOutcome,
    reason_kind,
)

__all__ = [
    "MAX_OUTCOMES",
    "SF_REF_C",
    "SHAPE_CANDIDATES",
    "SHAPE_REGRESSORS",
    "TABLE_SIGMAS",
    "OutcomeTally",
    "TableLaw",
    "TableOutcome",
    "reason_kind",
]
