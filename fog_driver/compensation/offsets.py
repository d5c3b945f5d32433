"""What ``?ZERO`` and ``?BIAS`` do to the published angles: offsets on the compensator's output, one definition
for the daemon (sample by sample) and for a capture replayed offline (in columns), bit for bit alike::

    angle_arcsec     = angle_comp_arcsec - zero_comp_arcsec - bias_angle_arcsec
    angle_raw_arcsec = angle_raw_arcsec - zero_raw_arcsec
    rate_dph         = dtheta_comp_arcsec / period_s - bias_dph          (arcsec/s is deg/h)

``bias_angle_arcsec`` is the running sum of ``bias_dph * period_s``, one term per sample from the one the bias
was set at on (that sample included).  ``?ZERO`` takes the current angles as the zero, less the bias angle so
far (the bias keeps being removed from the zeroed angle).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .pipeline import CompensatedColumns

__all__ = ["PublishOffsets"]


@dataclass
class PublishOffsets:
    zero_raw_arcsec: float = 0.0
    zero_comp_arcsec: float = 0.0
    bias_dph: float = 0.0
    bias_angle_arcsec: float = 0.0

    def zero(self, angle_raw_arcsec: float, angle_comp_arcsec: float) -> None:
        """``?ZERO`` at the compensator's current angles."""
        self.zero_raw_arcsec = angle_raw_arcsec
        self.zero_comp_arcsec = angle_comp_arcsec - self.bias_angle_arcsec

    def advance(self, period_s: float) -> None:
        """One sample: the bias angle grows by ``bias_dph * period_s``."""
        self.bias_angle_arcsec += self.bias_dph * period_s

    def angle_arcsec(self, angle_comp_arcsec: float) -> float:
        return angle_comp_arcsec - self.zero_comp_arcsec - self.bias_angle_arcsec

    def angle_raw_arcsec(self, angle_raw_arcsec: float) -> float:
        return angle_raw_arcsec - self.zero_raw_arcsec

    def rate_dph(self, dtheta_comp_arcsec: float, period_s: float) -> float:
        return dtheta_comp_arcsec / period_s - self.bias_dph

    def published(self, cols: CompensatedColumns, period_s: float) -> CompensatedColumns:
        """``cols`` as published (each sample ``advance``d first, as the daemon does): the angles less the
        offsets, and ``dtheta_comp_arcsec`` less ``bias_dph * period_s`` so that a row's compensated rate is
        the published ``rate_dph``."""
        n = len(cols)
        if not n:
            return cols
        bias_angle = np.cumsum(np.r_[self.bias_angle_arcsec, np.full(n, self.bias_dph * period_s)])[1:]
        self.bias_angle_arcsec = float(bias_angle[-1])
        return CompensatedColumns(
            cols.seq,
            cols.t_s,
            cols.dtheta_arcsec,
            cols.drift_dph,
            cols.dtheta_comp_arcsec - self.bias_dph * period_s if self.bias_dph else cols.dtheta_comp_arcsec,
            cols.angle_raw_arcsec - self.zero_raw_arcsec,
            cols.angle_comp_arcsec - self.zero_comp_arcsec - bias_angle,
            cols.temps_c,
            cols.flags,
            cols.drift_sigma_dph,
        )
