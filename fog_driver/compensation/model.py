"""The model file's contents: a fitted drift model as plain numbers (``ModelFile``; read and written as
YAML, safe loading only, never pickle, by ``fog_driver.modelfiles``).

Everything needed to reproduce the outputs exactly on another machine is in
the file as plain numbers (floats written by ``yaml.safe_dump`` round-trip
exactly): the feature settings, the input normalization, and every matrix.
Also the schema version, the instrument serial the model was fitted for, and
provenance (the captures' SHA-256s, the fit configuration and metrics, the
date).  A model fitted for another serial is refused unless forced.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from .. import __version__
from ..errors import InputFileError
from ..files.kinds import MODEL_FORMAT
from ..files.stamps import utc_now_iso
from .domain import InputDomain
from .features import V1_CHANNELS, FeatureParams, Substitution, input_names, params_to_dict
from .model_checks import check_model_numbers
from .models.polynomial import PolynomialModel
from .models.svr import SvrModel
from .models.wesn import PaperKind, WesnKind
from .readout import Standardizer
from .uncertainty import UncertaintySpec

MODEL_SCHEMA_VERSION = 1


class DriftModel(Protocol):
    """What the compensator needs of a model: one step per block, or a batch; explicit state; and to adapt, its
    regressor row, weights and intercept (``D_hat = f . weights + intercept``), the estimate used fed back, and the
    coil's lag the fit found (the table law's scale factor follows the coil's temperature)."""

    kind: str

    def start(self, z: np.ndarray) -> None: ...

    def step(self, z: np.ndarray) -> float: ...

    def run(self, z: np.ndarray) -> np.ndarray: ...

    def get_state(self) -> dict: ...

    def set_state(self, state: dict) -> None: ...

    def reset(self) -> None: ...

    def to_dict(self) -> dict: ...

    @property
    def weights(self) -> np.ndarray: ...

    @property
    def intercept(self) -> float: ...

    def regressors_step(self, z: np.ndarray) -> np.ndarray: ...

    def feed_back(self, y: float) -> None: ...

    def coil_lag(self) -> tuple[float, int] | None:
        """The coil's lag the fit found, ``(stage time s, stages)``, for the table law's scale factor; None: none."""
        ...


#: Model kinds: name -> class with ``from_dict``.
MODEL_KINDS: dict[str, Any] = {"polynomial": PolynomialModel, "wesn": WesnKind, "paper": PaperKind, "pso-svr": SvrModel}


#: The drift model runs on block means of temperature, seconds to minutes apart: rates outside these are a
#: corrupt file (a block of under 1 ms would be 0 us long on the block grid).
MIN_MODEL_RATE_HZ = 1e-3
MAX_MODEL_RATE_HZ = 100.0


@dataclass
class ModelFile:
    kind: str
    instrument_serial: str
    model_rate_hz: float
    features: FeatureParams
    normalizer: Standardizer
    model: DriftModel
    provenance: dict[str, Any] = field(default_factory=dict)
    #: the fit data's input box and the estimate's bound (``domain``); None in files made before it existed
    domain: InputDomain | None = None
    #: how a faulted thermometer is predicted from the others, fitted on the fit data; files made before it
    #: existed substitute a partner plus its last offset (``Substitution.offsets``)
    substitution: Substitution = field(default_factory=Substitution.offsets)
    #: the frame format's temperature channels the model was fitted on (``features.input_names`` of them are
    #: its inputs); files made before other formats existed: protocol v1's three
    temperature_channels: tuple[str, ...] = V1_CHANNELS
    #: the gyro's white noise at 1 min on the fit data, deg/h (``report.noise_floor_dph``: the 1-s blocks'
    #: robust noise over sqrt(60)); None in files made before it existed
    noise_1min_dph: float | None = None
    #: how ``drift_sigma_dph`` is made (``uncertainty``); None in files made before it existed: the fit
    #: residual alone (``sigma_spec``)
    uncertainty: UncertaintySpec | None = None
    created_utc: str = field(default_factory=utc_now_iso)
    fog_driver_version: str = __version__

    @property
    def fit_residual_dph(self) -> float | None:
        """The 1-min drift RMS this model left on its own fit data (``provenance.metrics``), or None."""
        metrics = self.provenance.get("metrics") or {}
        row = metrics.get(f"after, {self.kind}") if isinstance(metrics, dict) else None
        value = row.get("fit") if isinstance(row, dict) else None
        return float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else None

    @property
    def sigma_spec(self) -> UncertaintySpec:
        """How this model's ``drift_sigma_dph`` is made: its ``uncertainty`` section, or for a file without
        one the fit residual alone (``sigma_kind: residual``)."""
        if self.uncertainty is not None:
            return self.uncertainty
        return UncertaintySpec.residual_only(self.fit_residual_dph, self.domain)

    def candidate_models(self) -> list[DriftModel]:
        """Fresh instances of the candidate structures (``uncertainty``), of this model's kind."""
        return [MODEL_KINDS[self.kind].from_dict(d) for d in self.sigma_spec.candidates]

    def warnings(self, name: str) -> list[str]:
        """What a user applying this model should know of its fit: a weak fit accepted, no stored range."""
        lines = []
        quality = self.provenance.get("fit_quality") or {}
        if isinstance(quality, dict) and quality.get("accepted_weak"):
            lines.append(
                f"{name} is a weak fit, accepted with --accept-weak-fit: "
                f"{'; '.join(map(str, quality.get('weak') or []))}"
            )
        calibration = self.sigma_spec.calibration
        if calibration is None:
            lines.append(
                f"{name} was made by an older fog-driver: its drift_sigma_dph uses factors fixed on simulated "
                f"instruments, not calibrated on its own data; refit it"
                + (
                    " (it has no candidate structures either: the validation residual and the fit box alone)"
                    if self.sigma_spec.sigma_kind == "residual"
                    else ""
                )
            )
        elif not calibration.calibrated:
            lines.append(
                f"{name}'s drift_sigma_dph is not calibrated on its own data ({calibration.reason}): it uses the "
                f"conservative fall-back rule"
            )
        if self.domain is None:
            lines.append(
                f"{name} stores no fit range (made by an older fog-driver): extrapolation cannot be "
                f"flagged; refit it to get the range checks"
            )
        return lines

    def to_doc(self) -> dict[str, Any]:
        return {
            "format": MODEL_FORMAT,
            "schema_version": MODEL_SCHEMA_VERSION,
            "kind": self.kind,
            "instrument_serial": self.instrument_serial,
            "created_utc": self.created_utc,
            "fog_driver_version": self.fog_driver_version,
            "model_rate_hz": self.model_rate_hz,
            "features": params_to_dict(self.features),
            "normalizer": self.normalizer.to_dict(),
            "model": self.model.to_dict(),
            **({"domain": self.domain.to_dict()} if self.domain is not None else {}),
            "substitution": self.substitution.to_dict(),
            "temperature_channels": list(self.temperature_channels),
            **({"noise_1min_dph": self.noise_1min_dph} if self.noise_1min_dph is not None else {}),
            **({"uncertainty": self.uncertainty.to_dict()} if self.uncertainty is not None else {}),
            "provenance": self.provenance,
        }


def _require(doc: dict, key: str, kind: type | tuple[type, ...], where: str) -> Any:
    if key not in doc:
        raise InputFileError(f"{where}: missing {key!r}")
    value = doc[key]
    if not isinstance(value, kind) or isinstance(value, bool) and kind is not bool:
        raise InputFileError(f"{where}: {key!r} has the wrong type ({type(value).__name__})")
    return value


def model_file_from_doc(doc: dict[str, Any], where: str) -> ModelFile:
    """Validate a model file's document (its format and schema version already checked) and build the
    ``ModelFile``; anything corrupt is a one-line ``InputFileError`` naming ``where``.  Every number is
    checked first (``model_checks.check_model_numbers``: finite, within bounds), then the counts and shapes
    as each part is built (at most ``MAX_CANDIDATES`` candidates, ``MAX_NEURONS`` neurons)."""
    kind = _require(doc, "kind", str, where)
    if kind not in MODEL_KINDS:
        raise InputFileError(f"{where}: unknown model kind {kind!r} (known: {', '.join(sorted(MODEL_KINDS))})")
    try:
        check_model_numbers(doc)
        features = FeatureParams(**_require(doc, "features", dict, where))
        normalizer = Standardizer.from_dict(_require(doc, "normalizer", dict, where))
        channels = doc.get("temperature_channels", list(V1_CHANNELS))
        if (
            not isinstance(channels, list)
            or not 1 <= len(channels) <= 3
            or not all(isinstance(c, str) and c.isidentifier() for c in channels)
        ):
            raise ValueError("temperature_channels must list 1 to 3 channel names")
        channels = tuple(channels)
        names = input_names(channels)
        if len(normalizer.mean) != len(names) or len(normalizer.scale) != len(names):
            raise ValueError(f"the normalizer needs {len(names)} means and scales ({', '.join(names)})")
        model = MODEL_KINDS[kind].from_dict(_require(doc, "model", dict, where))
        copy.deepcopy(model).run(np.zeros((1, len(names))))  # a model of another input count fails here
        rate = float(_require(doc, "model_rate_hz", (int, float), where))
        domain = InputDomain.from_dict(doc["domain"]) if "domain" in doc else None
        substitution = Substitution.from_dict(doc["substitution"]) if "substitution" in doc else Substitution.offsets()
        if domain is not None and domain.names != names:
            raise ValueError(f"the domain's inputs must be {', '.join(names)}")
        noise = doc.get("noise_1min_dph")
        if "noise_1min_dph" in doc and (
            not isinstance(noise, (int, float)) or isinstance(noise, bool) or not 0 <= noise < math.inf
        ):
            raise ValueError(f"noise_1min_dph must be a finite number >= 0 (deg/h), not {noise!r}")
        uncertainty = UncertaintySpec.from_dict(doc["uncertainty"]) if "uncertainty" in doc else None
        for candidate in uncertainty.candidates if uncertainty is not None else ():
            m = MODEL_KINDS[kind].from_dict(candidate)
            m.run(np.zeros((1, len(names))))  # a candidate of another input count fails here
    except InputFileError:
        raise
    except (TypeError, ValueError, KeyError, IndexError) as exc:
        raise InputFileError(f"{where}: corrupt model: {exc}") from None
    if not np.all(np.isfinite(normalizer.scale)) or not MIN_MODEL_RATE_HZ <= rate <= MAX_MODEL_RATE_HZ:
        raise InputFileError(
            f"{where}: corrupt model: non-finite normalizer, or a model rate outside "
            f"{MIN_MODEL_RATE_HZ:g}..{MAX_MODEL_RATE_HZ:g} Hz"
        )
    if abs(features.sample_time_s * rate - 1.0) > 1e-9:
        raise InputFileError(f"{where}: corrupt model: features.sample_time_s is not 1 / model_rate_hz")
    return ModelFile(
        kind=kind,
        instrument_serial=str(_require(doc, "instrument_serial", str, where)),
        model_rate_hz=rate,
        features=features,
        normalizer=normalizer,
        model=model,
        provenance=doc.get("provenance") or {},
        domain=domain,
        substitution=substitution,
        temperature_channels=channels,
        noise_1min_dph=float(noise) if noise is not None else None,
        uncertainty=uncertainty,
        created_utc=str(doc.get("created_utc", "")),
        fog_driver_version=str(doc.get("fog_driver_version", "")),
    )
