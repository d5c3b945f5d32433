"""The simulated instrument: physics per frame, then the protocol v1 byte stream with link faults.

Time bases.  Physics runs in true time ``t`` (s since power-on).  The
instrument's clock runs ``clock_ppm`` fast, so frame k, stamped at
``k / rate_hz`` device seconds, is valid at ``t_k = k / rate_hz / (1 + ppm 1e-6)``
true seconds.  Slow quantities (temperatures, drift, bias instability, rate
random walk) live on a 1-s grid of true time, computed in fixed blocks of 600
steps and interpolated linearly to frame times; everything per frame is
element-wise arithmetic; angle quantization carries its remainder in exact
integer fixed point.  Every random draw is sequential per stream (one
``numpy`` child generator per noise source, spawned from the seed), so the
bytes depend on the seed and configuration only, never on how the frames were
asked for: a capture file and a live pty stream of one seed are identical.

Per frame k (interval ``(t_k - P, t_k]``, P the true frame period), in arcsec::

    dtheta_true = 3600 (angle(t_k) - angle(t_k - P)) (1 + s)      turntable, exact (closed form)
                + [ W_E (1 + s) + B0 + B_on + D + b_BI + b_RRW ] P   slow terms at the mid-point, deg/h = arcsec/s
                + 0.18 (N / 0.003) sqrt(P) w_k                      angle random walk, w_k ~ N(0, 1)
    counts_k    = floor(C_k) - floor(C_(k-1)),  C_k = sum of dtheta_true / scale   (remainder carried)
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass, field, fields, is_dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import UsageError
from ..files.typed_mapping import dataclass_from_mapping
from ..files.yamlio import read_yaml
from ..formats.ixblue import CHECKSUM_LEN, COUNTER_MODULUS, HEADER_LEN, TIME_LSB_S, TIME_MODULUS, encode_stdbin
from ..formats.kvh import ARCSEC_PER_RAD, SAMPLE_FORMATS, encode_kvh_frames
from ..lab.profiles import SimProfile
from ..protocol import (
    SAMPLE_FRAME_LEN,
    STATUS_LIGHT_SOURCE_FAULT,
    STATUS_LOOP_UNLOCKED,
    STATUS_STARTUP,
    STATUS_THERMOMETER_FAULT,
    THERMOMETER_COUNTS_PER_C,
    THERMOMETER_INVALID,
    encode_identity,
    encode_sample_frames,
)
from .families import FamilyPhysics, FamilyTerm
from .faults import FaultSpec
from .gyro import ARCSEC_PER_SQRT_S_PER_DEG_PER_SQRT_H, GyroParams, SlowNoise, drift_terms
from .thermal import ThermalModel, ThermalParams

GRID_DT_S = 1.0
GRID_BLOCK_STEPS = 600
#: Fixed-point resolution of the quantizer's running remainder: 2^-24 count.
_FIXED_ONE = 1 << 24


@dataclass(frozen=True)
class ThermometerParams:
    """The three thermometers (ring top, ring bottom, housing).

    Readings are taken at ``update_hz`` and held until the next one (a frame
    carries the latest); each is the node temperature through a first-order
    sensor lag (``lag_s`` for all three, or ``sensor_lags_s`` one each; 0: none),
    plus the sensor's calibration offset (``offsets_c``, fixed for the instrument)
    and a per-run one (drawn once per run, ``offset_sigma_c``), plus white noise
    ``noise_c``, rounded to 1/256 degC.
    """

    noise_c: float = 0.01
    update_hz: float = 10.0
    lag_s: float = 0.0
    offset_sigma_c: float = 0.05
    sensor_lags_s: tuple[float, ...] = ()  #: top, bottom, housing; () for lag_s on all three
    offsets_c: tuple[float, ...] = (0.0, 0.0, 0.0)  #: top, bottom, housing calibration offsets

    def __post_init__(self) -> None:
        if not self.update_hz > 0:
            raise ValueError("update_hz must be > 0")
        if self.lag_s < 0 or self.noise_c < 0 or self.offset_sigma_c < 0:
            raise ValueError("lag_s, noise_c and offset_sigma_c must be >= 0")
        if self.sensor_lags_s and (len(self.sensor_lags_s) != 3 or min(self.sensor_lags_s) < 0):
            raise ValueError(f"sensor_lags_s: three lags >= 0 (top, bottom, housing) or none, got {self.sensor_lags_s}")
        if len(self.offsets_c) != 3 or not all(math.isfinite(v) and abs(v) <= 10 for v in self.offsets_c):
            raise ValueError(f"offsets_c: three offsets within +-10 degC (top, bottom, housing), got {self.offsets_c}")
        object.__setattr__(self, "sensor_lags_s", tuple(float(v) for v in self.sensor_lags_s))
        object.__setattr__(self, "offsets_c", tuple(float(v) for v in self.offsets_c))

    def lags(self) -> tuple[float, float, float]:
        """The lag of each sensor (top, bottom, housing), s."""
        return self.sensor_lags_s if self.sensor_lags_s else (self.lag_s,) * 3


@dataclass(frozen=True)
class InstrumentConfig:
    """Everything about the simulated instrument; ``configs/sim/instrument.yaml`` lists every key."""

    serial: str = "FOG-SIM-0001"
    firmware: int = 0x0102
    scale_arcsec_per_count: float = 0.01
    clock_ppm: float = 15.0
    startup_s: float = 2.0
    thermal: ThermalParams = field(default_factory=ThermalParams)
    gyro: GyroParams = field(default_factory=GyroParams)
    thermometers: ThermometerParams = field(default_factory=ThermometerParams)
    #: Provenance: the ``fog_driver.sim.population`` instrument these physics were drawn for (None: not drawn).
    population_seed: int | None = None
    #: A physics family on top of the drawn instrument (``fog_driver.sim.families``; None: the population's own).
    family: FamilyPhysics | None = None

    def __post_init__(self) -> None:
        if len(self.serial.encode("ascii", errors="replace")) > 16:
            raise ValueError("serial is at most 16 ASCII characters")
        if not 0 <= self.firmware <= 0xFFFF:
            raise ValueError("firmware is a u16: (major << 8) + minor")
        if not self.scale_arcsec_per_count > 0:
            raise ValueError("scale_arcsec_per_count must be > 0")
        if abs(self.clock_ppm) > 1000:
            raise ValueError("clock_ppm beyond +-1000 is not a crystal oscillator")

    @property
    def scale_f32(self) -> float:
        """The scale factor as the instrument stores and sends it (float32)."""
        return float(np.float32(self.scale_arcsec_per_count))

    def as_dict(self) -> dict[str, Any]:
        """Every field as plain values; ``family`` only when there is one (a configuration without a family
        serializes as it did before families existed)."""
        plain = _to_plain(self)
        if self.family is None:
            del plain["family"]
        return plain


def _to_plain(obj: Any) -> Any:
    if is_dataclass(obj):
        return {f.name: _to_plain(getattr(obj, f.name)) for f in fields(obj)}
    if isinstance(obj, tuple):
        return [_to_plain(v) for v in obj]
    if isinstance(obj, dict):
        return {k: _to_plain(v) for k, v in obj.items()}
    return obj


def load_instrument_config(path: str | Path | None) -> InstrumentConfig:
    """The instrument configuration from a YAML file (``yaml.safe_load``), or the defaults for None."""
    if path is None:
        return InstrumentConfig()
    path = Path(path)
    doc = read_yaml(path, "instrument config")
    return dataclass_from_mapping(InstrumentConfig, doc if doc is not None else {}, str(path))


class _SlowGrid:
    """Slow quantities on a 1-s grid of true time, extended in fixed blocks, with explicit state.

    Grid point i is at ``t = i * GRID_DT_S``.  Arrays are kept from a moving start index, so an
    endless live stream keeps only a window.  An instrument with a physics family has one more column,
    ``drift_family_dph`` (``families.FamilyTerm``, from ``rng_family``), and the family's extra housing heat
    drives the thermal model.
    """

    COLUMNS = (
        "air_c",
        "housing_c",
        "top_c",
        "bottom_c",
        "fiber_c",
        "mount_c",
        "history_c",
        "sensor_top_c",
        "sensor_bottom_c",
        "sensor_housing_c",
        "drift_bias_temp_dph",
        "drift_shupe_dph",
        "drift_gradient_dph",
        "drift_hysteresis_dph",
        "bias_instability_dph",
        "rrw_dph",
    )

    def __init__(
        self,
        profile: SimProfile,
        config: InstrumentConfig,
        rng_noise: np.random.Generator,
        block_steps: int = GRID_BLOCK_STEPS,
        rng_family: np.random.Generator | None = None,
    ) -> None:
        self.profile = profile
        self.block_steps = block_steps
        self.config = config
        air0 = float(profile.chamber.air_temp_c(np.array([0.0]))[0])
        self.family = None if config.family is None else FamilyTerm(config.family, GRID_DT_S, rng_family)
        self.columns = self.COLUMNS + (("drift_family_dph",) if self.family else ())
        self._heats = self.family is not None and self.family.heat_c(np.zeros(1)) is not None
        self.thermal = ThermalModel(config.thermal, GRID_DT_S, air0, housing_heat=self._heats)
        self.noise = SlowNoise(config.gyro, GRID_DT_S, rng_noise)
        x = self.thermal.state
        self._history = float(x[3])
        self._history_a = 1.0 - math.exp(-GRID_DT_S / config.gyro.hysteresis_tau_s)
        self._sensor_a = np.array(
            [1.0 if lag == 0 else 1.0 - math.exp(-GRID_DT_S / lag) for lag in config.thermometers.lags()]
        )
        self._sensors = np.array([x[1], x[2], x[0]])
        self.start = 0  # grid index of the first kept point
        self.data = {name: np.zeros(0) for name in self.columns}
        self._append(np.array([air0]), x[None, :], self.noise.run(1))

    @property
    def end(self) -> int:
        """One past the last grid index computed."""
        return self.start + len(self.data["air_c"])

    def _append(self, air_c: np.ndarray, nodes: np.ndarray, noise: tuple[np.ndarray, np.ndarray]) -> None:
        n = len(air_c)
        history = np.empty(n)
        sensors = np.empty((n, 3))
        h, s = self._history, self._sensors
        a_h, a_s = self._history_a, self._sensor_a
        for k in range(n):
            h = h + a_h * (nodes[k, 3] - h)
            s = s + a_s * (nodes[k, [1, 2, 0]] - s)
            history[k] = h
            sensors[k] = s
        self._history, self._sensors = h, s
        p = self.config.thermal
        fiber_rate = p.fiber_rate_c_per_s(nodes)  # dTf/dt from the model
        boundary = p.boundary_c(nodes)
        terms = drift_terms(self.config.gyro, nodes[:, 3], fiber_rate, nodes[:, 1], nodes[:, 2], history, boundary)
        new = {
            "air_c": air_c,
            "housing_c": nodes[:, 0],
            "top_c": nodes[:, 1],
            "bottom_c": nodes[:, 2],
            "fiber_c": nodes[:, 3],
            "mount_c": nodes[:, 4],
            "history_c": history,
            "sensor_top_c": sensors[:, 0],
            "sensor_bottom_c": sensors[:, 1],
            "sensor_housing_c": sensors[:, 2],
            "drift_bias_temp_dph": terms.bias_vs_temperature,
            "drift_shupe_dph": terms.shupe,
            "drift_gradient_dph": terms.gradient,
            "drift_hysteresis_dph": terms.hysteresis,
            "bias_instability_dph": noise[0],
            "rrw_dph": noise[1],
        }
        if self.family is not None:
            new["drift_family_dph"] = self.family.run(nodes, fiber_rate, boundary)
        for name in self.columns:
            self.data[name] = np.concatenate((self.data[name], new[name]))

    def ensure(self, t_s: float) -> None:
        """Compute whole blocks until the grid reaches past ``t_s``."""
        while (self.end - 1) * GRID_DT_S < t_s + GRID_DT_S:
            first = self.end
            idx = np.arange(first, first + self.block_steps)
            air_mid = self.profile.chamber.air_temp_c((idx - 0.5) * GRID_DT_S)
            air_end = self.profile.chamber.air_temp_c(idx * GRID_DT_S)
            heat = self.family.heat_c((idx - 0.5) * GRID_DT_S) if self._heats and self.family else None
            nodes = self.thermal.run(air_mid, heat)
            self._append(air_end, nodes, self.noise.run(self.block_steps))

    def forget_before(self, t_s: float) -> None:
        """Drop grid points more than one step before ``t_s`` (live streams run for months)."""
        drop = int(t_s // GRID_DT_S) - 1 - self.start
        if drop > 4 * max(self.block_steps, GRID_BLOCK_STEPS):
            for name in self.columns:
                self.data[name] = self.data[name][drop:]
            self.start += drop

    def at(self, t_s: np.ndarray, names: tuple[str, ...]) -> dict[str, np.ndarray]:
        """Linear interpolation of the named columns at true times ``t_s`` (element-wise arithmetic)."""
        pos = np.asarray(t_s) / GRID_DT_S - self.start
        i = np.clip(np.floor(pos).astype(np.int64), 0, len(self.data["air_c"]) - 2)
        w = pos - i
        return {name: self.data[name][i] * (1.0 - w) + self.data[name][i + 1] * w for name in names}


@dataclass
class FrameBlock:
    """Physics and wire values of consecutive frames ``k0 .. k0 + n - 1`` (before link faults)."""

    k0: int
    t_true_s: np.ndarray  #: time of validity, true s since power-on
    seq: np.ndarray
    t_us: np.ndarray
    dtheta_counts: np.ndarray
    t_raw: np.ndarray  #: (n, 3) int16 thermometer words: top, bottom, housing
    status: np.ndarray
    components_arcsec: dict[str, np.ndarray]  #: per-frame angle increments by source
    truth_temps_c: dict[str, np.ndarray]  #: true node temperatures at t_k
    angle_deg: np.ndarray  #: turntable angle at t_k


#: The wire formats the simulator speaks (``fog_driver.formats.registry`` names).
WIRE_FORMATS = ("fog-v1", "kvh-a", "kvh-b", "kvh-c", "ixblue-stdbin")

#: The STDBIN protocol version the simulator sends: 5, the newest the decoder reads (its header has the
#: extended-navigation mask and the navigation size; the blocks are the same in every version).
STDBIN_VERSION = 5
#: STDBIN Temperatures-block channel -> the simulated thermometer whose reading it carries.
STDBIN_TEMPERATURE_CHANNELS = {"fog": "top", "accelerometer": "bottom", "board": "housing"}
_THERMOMETER_COLUMN = {"top": 0, "bottom": 1, "housing": 2}  #: the thermometer's column of ``FrameBlock.t_raw``

#: Per-frame angle components, in the order the truth file lists them.
COMPONENTS = (
    "input",
    "earth",
    "scale_factor_error",
    "constant_bias",
    "drift_bias_temp",
    "drift_shupe",
    "drift_gradient",
    "drift_hysteresis",
    "bias_instability",
    "rrw",
    "arw",
)
#: The per-frame component of an instrument's physics family (``InstrumentConfig.family``), when it has one.
FAMILY_COMPONENT = "drift_family"


def _stdbin_layout() -> tuple[np.dtype, np.ndarray]:
    """The simulator's STDBIN telegram as a numpy record (big-endian fields) and its constant first bytes
    (sync, version, masks, navigation size, telegram size), both taken from ``encode_stdbin``."""
    zeros = (0.0, 0.0, 0.0)
    template = encode_stdbin(
        STDBIN_VERSION,
        counter=0,
        validity_time_100us=0,
        attitude_deg=zeros,
        rotation_rate_dps=zeros,
        temperatures_c=zeros,
    )
    fixed = HEADER_LEN[STDBIN_VERSION] - 8  # the validity time and the counter end the header
    # The blocks in ascending bit order (attitude 0, rotation rate 5, temperatures 25), as encode_stdbin puts them.
    dtype = np.dtype(
        [
            ("prefix", "u1", (fixed,)),
            ("time", ">u4"),
            ("counter", ">u4"),
            ("attitude", ">f4", (3,)),
            ("rate", ">f4", (3,)),
            ("temps", ">f4", (3,)),
            ("checksum", ">u4"),
        ]
    )
    if dtype.itemsize != len(template):
        raise AssertionError(f"STDBIN layout of {dtype.itemsize} bytes, encode_stdbin says {len(template)}")
    return dtype, np.frombuffer(template[:fixed], dtype=np.uint8)


class Simulator:
    """A simulated instrument running ``profile``; ask it for frames in order, in any batches.

    ``frames(n)`` computes the next n frames' physics; ``emit(block)`` turns them into the
    link's bytes (IDENTITY each device second, faults applied).  ``stream(n)`` does both.
    """

    def __init__(
        self,
        profile: SimProfile,
        config: InstrumentConfig | None = None,
        *,
        rate_hz: int = 100,
        seed: int = 0,
        faults: FaultSpec | None = None,
        wire_format: str = "fog-v1",
        grid_block_steps: int = GRID_BLOCK_STEPS,
    ) -> None:
        """``grid_block_steps``: the slow grid (the air and the thermal model) is computed that many 1-s steps
        ahead at a time; a coupled run (the air from a served chamber) takes a few, so it does not use air the
        chamber has not reached (the default, 600, for a profile known in advance)."""
        if wire_format not in WIRE_FORMATS:
            raise ValueError(f"the simulator speaks {', '.join(WIRE_FORMATS)}, not {wire_format!r}")
        if not (isinstance(rate_hz, int) and 1 <= rate_hz <= 0xFFFF):
            raise ValueError(f"rate_hz must be an integer 1..65535 (a u16 on the wire), got {rate_hz!r}")
        if wire_format == "ixblue-stdbin" and rate_hz > 10_000:
            raise ValueError(f"STDBIN's validity time counts 100 us: at most 10000 telegrams/s, not {rate_hz} Hz")
        self.profile = profile
        self.config = config or InstrumentConfig()
        self.rate_hz = rate_hz
        self.seed = seed
        self.faults = faults or FaultSpec()
        self.wire_format = wire_format
        # One stream per source, each drawn strictly in order: decisions and contents of a fault
        # have separate streams, so no interleaving depends on how the frames are batched.
        streams = np.random.SeedSequence(seed).spawn(9)
        rng = [np.random.default_rng(s) for s in streams]
        self._rng_run, self._rng_slow, self._rng_arw, self._rng_thermo = rng[:4]
        self._rng_drop, self._rng_flip, self._rng_garbage, self._rng_garbage_bytes, self._rng_thermo_fault = rng[4:]
        g = self.config.gyro
        run = self._rng_run.random(5)
        self.seq0 = int(run[0] * 65536)
        self.t_us0 = int(run[1] * 2**32)
        self.turn_on_bias_dph = g.turn_on_bias_sigma_dph * float(self._rng_run.standard_normal())
        sensors = self.config.thermometers
        self.thermometer_offsets_c = np.array(
            sensors.offsets_c
        ) + sensors.offset_sigma_c * self._rng_run.standard_normal(3)
        # The family's stream is the seed's tenth child: the nine above are the same with or without it.
        rng_family = np.random.default_rng(np.random.SeedSequence(seed).spawn(10)[9]) if self.config.family else None
        self._grid = _SlowGrid(profile, self.config, self._rng_slow, grid_block_steps, rng_family)
        self.period_true_s = 1.0 / (rate_hz * (1.0 + self.config.clock_ppm * 1e-6))
        self._scale = self.config.scale_f32
        self._identity = encode_identity(self.config.serial, self.config.firmware, rate_hz, self._scale)
        self._stdbin_layout = _stdbin_layout() if wire_format == "ixblue-stdbin" else None
        self._next_k = 0
        self._remainder_fixed = 0  # quantizer remainder, in 2^-24 counts
        self._readings_done = 0  # thermometer readings generated so far
        self._reading_raw = np.zeros((0, 3), dtype=np.int16)
        self._reading_fault = np.zeros((0, 3), dtype=bool)
        self._reading_start = 0
        self._thermo_fault_until = np.zeros(3, dtype=np.int64)  # reading index each sensor's fault lasts to
        self._bytes_to_next_flip = self._next_flip_gap()
        self._cut_open = False  # the link was cut at the end of the last emit()

    # -- physics ------------------------------------------------------------------------------

    @property
    def next_frame(self) -> int:
        return self._next_k

    @property
    def frame_len_bytes(self) -> int:
        """Bytes of one frame in the wire format (protocol v1's IDENTITY not included)."""
        if self.wire_format == "fog-v1":
            return SAMPLE_FRAME_LEN
        if self._stdbin_layout is not None:
            return self._stdbin_layout[0].itemsize
        return SAMPLE_FORMATS[self.wire_format[-1]][1]

    def device_time_s(self, k: np.ndarray | int) -> np.ndarray | float:
        return np.asarray(k) / self.rate_hz

    def _thermometer_readings(self, last_index: int) -> None:
        """Generate readings up to index ``last_index`` (held until the next; sequential draws)."""
        cfg = self.config.thermometers
        first = self._readings_done
        n = last_index + 1 - first
        if n <= 0:
            return
        j = np.arange(first, first + n)
        t = j / cfg.update_hz
        self._grid.ensure(float(t[-1]))
        node = self._grid.at(t, ("sensor_top_c", "sensor_bottom_c", "sensor_housing_c"))
        values = np.stack([node["sensor_top_c"], node["sensor_bottom_c"], node["sensor_housing_c"]], axis=1)
        values = values + self.thermometer_offsets_c + cfg.noise_c * self._rng_thermo.standard_normal((n, 3))
        raw = np.clip(np.round(values * THERMOMETER_COUNTS_PER_C), -32767, 32767).astype(np.int16)
        fault = np.zeros((n, 3), dtype=bool)
        # Faults started in earlier calls that run on into this one.
        for sensor in range(3):
            carried = int(self._thermo_fault_until[sensor]) - first
            if carried > 0:
                fault[: min(carried, n), sensor] = True
        f = self.faults
        if f.thermo_faults_per_s:
            u = self._rng_thermo_fault.random((n, 2))  # (does a fault start?, on which sensor) per reading
            p = f.thermo_faults_per_s / cfg.update_hz
            length = max(1, round(f.thermo_fault_s * cfg.update_hz))
            for i in np.flatnonzero(u[:, 0] < p).tolist():
                sensor = min(2, int(u[i, 1] * 3))
                fault[i : i + length, sensor] = True
                self._thermo_fault_until[sensor] = max(self._thermo_fault_until[sensor], first + i + length)
        raw[fault] = THERMOMETER_INVALID
        keep_from = max(0, len(self._reading_raw) - 2)
        self._reading_start += keep_from
        self._reading_raw = np.concatenate((self._reading_raw[keep_from:], raw))
        self._reading_fault = np.concatenate((self._reading_fault[keep_from:], fault))
        self._readings_done += n

    def frames(self, n: int) -> FrameBlock:
        """The next ``n`` frames' physics and wire values."""
        cfg, g = self.config, self.config.gyro
        k = np.arange(self._next_k, self._next_k + n, dtype=np.int64)
        self._next_k += n
        period = self.period_true_s
        t_k = k * period
        t_mid = t_k - 0.5 * period
        if n:
            self._grid.ensure(float(t_k[-1]))
        slow = self._grid.at(
            t_mid,
            (
                "fiber_c",
                "drift_bias_temp_dph",
                "drift_shupe_dph",
                "drift_gradient_dph",
                "drift_hysteresis_dph",
                "bias_instability_dph",
                "rrw_dph",
                *(("drift_family_dph",) if self.config.family else ()),
            ),
        )
        temps = self._grid.at(t_k, ("air_c", "housing_c", "top_c", "bottom_c", "fiber_c"))
        motion = self.profile.motion
        angle_end = motion.angle_deg(t_k)
        sf = g.scale_factor_error(slow["fiber_c"])
        input_arcsec = 3600.0 * (angle_end - motion.angle_deg(t_k - period))
        comp = {
            "input": input_arcsec,
            "earth": np.full(n, g.earth_rate_dph * period),
            "scale_factor_error": sf * (input_arcsec + g.earth_rate_dph * period),
            "constant_bias": np.full(n, (g.constant_bias_dph + self.turn_on_bias_dph) * period),
            "drift_bias_temp": slow["drift_bias_temp_dph"] * period,
            "drift_shupe": slow["drift_shupe_dph"] * period,
            "drift_gradient": slow["drift_gradient_dph"] * period,
            "drift_hysteresis": slow["drift_hysteresis_dph"] * period,
            "bias_instability": slow["bias_instability_dph"] * period,
            "rrw": slow["rrw_dph"] * period,
            "arw": g.arw_deg_per_sqrt_h
            * ARCSEC_PER_SQRT_S_PER_DEG_PER_SQRT_H
            * math.sqrt(period)
            * self._rng_arw.standard_normal(n),
        }
        if self.config.family:
            comp[FAMILY_COMPONENT] = slow["drift_family_dph"] * period
        total_counts = sum(comp[name] for name in (*COMPONENTS, FAMILY_COMPONENT) if name in comp) / self._scale
        # Exact remainder carry: running sum in integer 2^-24 counts.
        fixed = np.round(total_counts * _FIXED_ONE).astype(np.int64)
        running = self._remainder_fixed + np.cumsum(fixed)
        whole = np.floor_divide(running, _FIXED_ONE)
        counts = np.diff(np.concatenate(([0], whole)))
        if n:
            self._remainder_fixed = int(running[-1] - whole[-1] * _FIXED_ONE)
        if np.any(np.abs(counts) > 2**31 - 1):
            raise UsageError(
                "an angle increment overflows the frame's i32 dtheta field: lower the table's rate, or raise the "
                "frame rate or the scale"
            )

        # Thermometers: the latest reading at each frame's time.
        t_cfg = cfg.thermometers
        reading = np.floor(t_k * t_cfg.update_hz).astype(np.int64)
        if n:
            self._thermometer_readings(int(reading[-1]))
        rows = reading - self._reading_start
        t_raw = self._reading_raw[rows]
        status = np.zeros(n, dtype=np.uint16)
        status[self._reading_fault[rows].any(axis=1)] |= STATUS_THERMOMETER_FAULT
        status[k / self.rate_hz < cfg.startup_s] |= STATUS_STARTUP
        self._grid.forget_before(float(t_k[0]) - 1.0 if n else 0.0)
        return FrameBlock(
            k0=int(k[0]) if n else self._next_k,
            t_true_s=t_k,
            seq=(self.seq0 + k) % 65536,
            t_us=(self.t_us0 + (k * 1_000_000) // self.rate_hz) % 2**32,
            dtheta_counts=counts.astype(np.int32),
            t_raw=t_raw,
            status=status,
            components_arcsec=comp,
            truth_temps_c=temps,
            angle_deg=angle_end,
        )

    # -- the link -----------------------------------------------------------------------------

    def _next_flip_gap(self) -> int:
        p = self.faults.flip_prob_per_byte
        if not p:
            return -1
        if p >= 1:
            return 0
        u = float(self._rng_flip.random())
        per_byte = math.log(1.0 - p) if 1.0 - p < 1.0 else math.log1p(-p)  # (a p under 1e-16 rounds 1 - p to 1)
        gap = math.log(1.0 - u) / per_byte  # bytes passed before the next flip (geometric)
        return int(min(gap, 2.0**62))  # (a p of 1e-300: none in any run)

    def encode(self, block: FrameBlock) -> np.ndarray:
        """``block``'s frames in the wire format, one row each (``(n, frame length)`` uint8).

        ``fog-v1``: SAMPLE frames (IDENTITY is added by ``emit``).  ``kvh-a/b/c``: KVH normal-mode frames as a
        DSP-1750 configured ``=ROTFMT,DELTA``, ``=ROTUNITS,RAD``, ``=TEMPUNITS,C_100`` sends them: the z gyro word
        is the frame's angle increment in rad (float32, the increment unquantized: no counts), x and y 0,
        the accelerometers 1 g on z, the temperature the housing thermometer's reading in 0.01 degC (Format
        C sends it in its multiplexed word every fourth frame and 0 gauss between), the status byte 0x77 (all
        valid) with the z gyro marked invalid while the light source or the loop reports a fault.
        ``ixblue-stdbin``: one STDBIN telegram per frame (``_encode_stdbin``).
        """
        if self.wire_format == "fog-v1":
            return encode_sample_frames(
                block.seq,
                block.t_us,
                block.dtheta_counts,
                block.t_raw[:, 0],
                block.t_raw[:, 1],
                block.t_raw[:, 2],
                block.status,
            )
        if self.wire_format == "ixblue-stdbin":
            return self._encode_stdbin(block)
        n = len(block.seq)
        fmt = self.wire_format[-1]
        gyro = np.zeros((n, 3), dtype=np.float32)
        gyro[:, 2] = sum(block.components_arcsec.values()) / ARCSEC_PER_RAD
        accel = np.zeros((n, 3), dtype=np.float32)
        accel[:, 2] = 1.0
        gyro_fault = (block.status & (STATUS_LIGHT_SOURCE_FAULT | STATUS_LOOP_UNLOCKED)) != 0
        status = np.where(gyro_fault, 0x73, 0x77)
        housing_raw = block.t_raw[:, 2].astype(np.int64)
        valid = housing_raw != -32768
        temp_c100 = np.where(valid, np.rint(housing_raw * (100.0 / 256.0)), -32768)
        k = np.arange(block.k0, block.k0 + n)
        if fmt == "c":
            temp = np.where(k % 4 == 0, np.where(valid, temp_c100 / 100.0, np.nan), 0.0).astype(np.float32)
        else:
            temp = temp_c100.astype(np.int16)
        return encode_kvh_frames(fmt, gyro, accel, status, k, temp)

    def stdbin_time_100us(self, k: np.ndarray | int) -> np.ndarray:
        """Device time of frame(s) ``k`` in STDBIN's 100-us steps, unwrapped (int64): the clock that stamps
        ``t_us`` (``t_us0 + k * 1e6 // rate_hz`` us, before its 2^32-us wrap), floored to 100 us."""
        return (self.t_us0 + (np.asarray(k, dtype=np.int64) * 1_000_000) // self.rate_hz) // 100

    def _encode_stdbin(self, block: FrameBlock) -> np.ndarray:
        """``block``'s frames as STDBIN telegrams (``STDBIN_VERSION``), one row each, byte-identical to
        ``fog_driver.formats.ixblue.encode_stdbin`` of the same values (vectorized).

        Blocks: Attitude (heading = the turntable angle mod 360 deg, roll and pitch 0), Rotation rate (z = the
        frame's angle increment, unquantized, divided by the validity-time step from the previous frame, in
        deg/s, so the decoder's rate x step gives the increment back; x and y 0; the increment includes the
        earth rate: a gyro's view, not a Phins' earth-compensated rate), Temperatures (float32 degC:
        ``STDBIN_TEMPERATURE_CHANNELS``; STDBIN has no invalid marker, so a faulted reading is sent as NaN).
        Header: validity time ``stdbin_time_100us(k) mod 2^32``, counter ``(seq0 + k) mod 2^32`` (its low 16
        bits are protocol v1's seq).  No status block: the decoder maps no STDBIN status to ``sensor_invalid``
        (their bits have no public meaning), so light-source and loop faults are not represented.
        """
        dtype, prefix = self._stdbin_layout
        n = len(block.seq)
        k = np.arange(block.k0, block.k0 + n, dtype=np.int64)
        time_100us = self.stdbin_time_100us(k)
        step_s = (time_100us - self.stdbin_time_100us(k - 1)) * TIME_LSB_S
        rows = np.zeros(n, dtype=dtype)
        rows["prefix"] = prefix
        rows["time"] = time_100us % TIME_MODULUS
        rows["counter"] = (self.seq0 + k) % COUNTER_MODULUS
        rows["attitude"][:, 0] = np.mod(block.angle_deg, 360.0)
        rows["rate"][:, 2] = sum(block.components_arcsec.values()) / 3600.0 / step_s
        raw = block.t_raw[
            :, [_THERMOMETER_COLUMN[STDBIN_TEMPERATURE_CHANNELS[c]] for c in ("fog", "accelerometer", "board")]
        ]
        rows["temps"] = np.where(raw == THERMOMETER_INVALID, np.nan, raw / THERMOMETER_COUNTS_PER_C)
        out = rows.view(np.uint8).reshape(n, dtype.itemsize)
        rows["checksum"] = out[:, :-CHECKSUM_LEN].sum(axis=1, dtype=np.uint64) & 0xFFFFFFFF
        return out

    def emit(self, block: FrameBlock) -> bytes:
        """The bytes the link carries for ``block``: (protocol v1: an IDENTITY at each device second, then) the
        frames, with the fault spec applied (drops, garbage, bit flips, disconnects)."""
        n = len(block.seq)
        encoded = self.encode(block)
        f = self.faults
        k = np.arange(block.k0, block.k0 + n)
        keep = np.ones(n, dtype=bool)
        if f.drop_prob:
            keep &= self._rng_drop.random(n) >= f.drop_prob
        garbage_before = np.zeros(n, dtype=bool)
        if f.garbage_bursts_per_s:
            garbage_before = self._rng_garbage.random(n) < f.garbage_bursts_per_s / self.rate_hz
        device_t = k / self.rate_hz
        in_cut = np.zeros(n, dtype=bool)
        for start, duration in f.disconnects:
            in_cut |= (device_t >= start) & (device_t < start + duration)

        # Assemble by segments: the frames between two insertion points (an IDENTITY at each
        # device second, a garbage burst, the edge of a cut) go out as one slice.
        insert_at = np.flatnonzero((k % self.rate_hz == 0) | garbage_before | (in_cut != np.roll(in_cut, 1)))
        bounds = np.unique(np.concatenate(([0], insert_at, [n])))
        kept_rows = np.cumsum(keep) - keep  # index among kept frames of each frame
        kept_frames = encoded[keep]
        pieces: list[bytes] = []
        for lo, hi in zip(bounds[:-1].tolist(), bounds[1:].tolist()):
            if in_cut[lo]:
                # The link dies while the cut's first frame is on the wire: half of it goes out.
                starts_here = not self._cut_open if lo == 0 else not in_cut[lo - 1]
                if starts_here and keep[lo]:
                    pieces.append(encoded[lo, : encoded.shape[1] // 2].tobytes())
                continue
            if k[lo] % self.rate_hz == 0 and self.wire_format == "fog-v1":
                pieces.append(self._identity)
            if garbage_before[lo]:
                pieces.append(self._garbage_burst())
            segment = kept_frames[kept_rows[lo] : kept_rows[hi - 1] + keep[hi - 1]]
            if len(segment):
                pieces.append(segment.tobytes())
        self._cut_open = bool(in_cut[-1]) if n else self._cut_open
        data = b"".join(pieces)
        return self._flip_bits(data)

    def _garbage_burst(self) -> bytes:
        u = self._rng_garbage_bytes.random(65)
        length = 1 + int(u[0] * 64)
        burst = bytearray((u[1 : 1 + length] * 256).astype(np.uint8).tobytes())
        if length >= 4:  # a false sync and a plausible header now and then: what hurts a decoder
            if self.wire_format == "fog-v1":
                burst[0:4] = b"\xaa\x55\x01\x12" if u[-1] < 0.5 else b"\xaa\x55\x7f\xff"
            elif self.wire_format == "ixblue-stdbin":  # 'IX', a version 2..5, the first byte of the simulator's mask
                burst[0:4] = b"IX" + bytes((2 + int(u[-1] * 4), 0x02))
            else:
                burst[0:4] = b"\xfe\x81\xff" + bytes((0x55 + int(u[-1] * 3),))
        return bytes(burst)

    def _flip_bits(self, data: bytes) -> bytes:
        if self._bytes_to_next_flip < 0 or not data:
            return data
        out = bytearray(data)
        pos = self._bytes_to_next_flip
        while pos < len(out):
            out[pos] ^= 1 << min(7, int(self._rng_flip.random() * 8))
            pos += 1 + self._next_flip_gap()
        self._bytes_to_next_flip = pos - len(out)
        return bytes(out)

    def stream(self, n: int) -> tuple[FrameBlock, bytes]:
        block = self.frames(n)
        return block, self.emit(block)

    def total_frames(self) -> int:
        """Frames in the profile's duration (device time, at the nominal rate)."""
        duration_true = max(self.profile.chamber.duration_s, self.profile.motion.duration_s)
        return int(math.ceil(duration_true * (1.0 + self.config.clock_ppm * 1e-6) * self.rate_hz))

    def batches(self, frames_per_batch: int, total: int | None = None) -> Iterator[tuple[FrameBlock, bytes]]:
        """Successive (block, bytes) until ``total`` frames (default: the whole profile)."""
        total = self.total_frames() if total is None else total
        while self._next_k < total:
            yield self.stream(min(frames_per_batch, total - self._next_k))
