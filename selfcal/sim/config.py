"""Validated configuration of the insole simulator (the ``[sim]`` TOML section).

Every field carries its unit in its name. :class:`SimConfig` groups one sub-model per
part of the simulator; ``SimConfig.from_section(cfg["sim"])`` validates a TOML section
(unknown keys are rejected, so a typo never silently falls back to a default).
"""

from __future__ import annotations

import math
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from selfcal.errors import InputError

#: Names of the sensor effects, in the order used everywhere (truth, CLI, docs).
EFFECT_NAMES = ("temperature_bias", "temperature_scale", "time_drift_bias", "scale_nonlinearity", "temperature_cross",
                "bias_step")
#: Effects that happen at one moment (``at_day``) rather than all along.
EVENT_EFFECTS = ("bias_step",)
#: The effects that act all along (the others).
CONTINUOUS_EFFECTS = tuple(n for n in EFFECT_NAMES if n not in EVENT_EFFECTS)

Triple = tuple[float, float, float]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


def _range(v: tuple[float, float], limit: float, unit: str) -> tuple[float, float]:
    """A ``(lo, hi)`` range drawn from uniformly: ``-limit <= lo <= hi <= limit``."""
    lo, hi = v
    if not (math.isfinite(lo) and math.isfinite(hi)):
        raise ValueError(f"a range needs finite ends, got ({lo}, {hi})")
    if lo > hi:
        raise ValueError(f"a range needs lo <= hi, got ({lo}, {hi})")
    if max(abs(lo), abs(hi)) > limit:
        raise ValueError(f"a range within +-{limit:g} {unit}, got ({lo}, {hi})")
    return v


class LogNormalDuration(_Strict):
    """A clipped log-normal duration: median, geometric sd and clip range (s)."""

    median_s: float = Field(gt=0)
    gsd: float = Field(ge=1.0, allow_inf_nan=False, description="geometric standard deviation (>= 1)")
    # at least a millisecond (a sample at 1 kHz): the planner alternates still and moving
    # periods, and sizes its draws by how many fit in a bout
    min_s: float = Field(ge=1e-3)
    max_s: float = Field(gt=0, allow_inf_nan=False)

    @model_validator(mode="after")
    def _check(self) -> "LogNormalDuration":
        if not self.min_s <= self.median_s <= self.max_s:
            raise ValueError(f"need min_s <= median_s <= max_s, got {self.min_s}, {self.median_s}, {self.max_s}")
        return self


class DayConfig(_Strict):
    """When the shoe is worn: clock times of putting it on / taking it off, and breaks."""

    wear_start_h: float = Field(7.5, ge=0, le=24, description="mean clock time the shoe goes on (h)")
    wear_start_sd_h: float = Field(0.5, ge=0)
    wear_end_h: float = Field(21.0, ge=0, le=24, description="mean clock time the shoe comes off (h)")
    wear_end_sd_h: float = Field(1.0, ge=0)
    breaks_per_day: float = Field(1.0, ge=0, description="mean number of shoe-off breaks during the day (Poisson)")
    break_duration: LogNormalDuration = LogNormalDuration(median_s=1800, gsd=1.8, min_s=300, max_s=7200)

    @model_validator(mode="after")
    def _order(self) -> "DayConfig":
        if self.wear_start_h + 1 >= self.wear_end_h:
            raise ValueError("wear_start_h must be at least 1 h before wear_end_h")
        return self


class ActivityConfig(_Strict):
    """Semi-Markov chain of worn activities: dwell times and transition probabilities."""

    sit: LogNormalDuration = LogNormalDuration(median_s=600, gsd=2.5, min_s=60, max_s=10800)
    stand: LogNormalDuration = LogNormalDuration(median_s=60, gsd=3.0, min_s=3, max_s=1800)
    walk_short: LogNormalDuration = LogNormalDuration(median_s=25, gsd=2.5, min_s=4, max_s=600)
    walk_long: LogNormalDuration = LogNormalDuration(median_s=600, gsd=1.8, min_s=180, max_s=3600)
    walk_long_fraction: float = Field(0.05, ge=0, le=1, description="share of walking bouts drawn from walk_long")
    stairs: LogNormalDuration = LogNormalDuration(median_s=12, gsd=1.5, min_s=4, max_s=60)
    # transition probabilities: from -> {to: p}; rows are normalised
    from_sit: dict[str, float] = {"stand": 1.0}
    from_stand: dict[str, float] = {"walk": 0.6, "sit": 0.3, "stairs": 0.1}
    from_walk: dict[str, float] = {"stand": 0.75, "sit": 0.15, "stairs": 0.1}
    from_stairs: dict[str, float] = {"walk": 0.7, "stand": 0.3}

    @field_validator("from_sit", "from_stand", "from_walk", "from_stairs")
    @classmethod
    def _row(cls, v: dict[str, float]) -> dict[str, float]:
        bad = set(v) - {"sit", "stand", "walk", "stairs"}
        if bad:
            raise ValueError(f"unknown activity {sorted(bad)}; use sit, stand, walk, stairs")
        if any(p < 0 for p in v.values()) or sum(v.values()) <= 0:
            raise ValueError("probabilities must be >= 0 with a positive sum")
        return v


class PostureConfig(_Strict):
    """Orientations (foot frame: x toes, y left, z up through the sole) and stillness."""

    shoe_pitch_deg: float = Field(-2.0, description="mean pitch of the insole when the shoe stands flat (toes up > 0)")
    shoe_pitch_sd_deg: float = Field(1.5, ge=0, description="per-wearer spread of shoe_pitch_deg")
    stand_tilt_sd_deg: float = Field(2.0, ge=0, description="pitch/roll spread of a standing foot")
    stand_quiet: LogNormalDuration = LogNormalDuration(median_s=4, gsd=2.2, min_s=0.5, max_s=120)
    stand_shift: LogNormalDuration = LogNormalDuration(median_s=1.2, gsd=1.6, min_s=0.4, max_s=4)
    stand_sway_sd_mg: float = Field(2.5, ge=0, description="sd of foot acceleration during quiet standing")
    stand_shift_sd_g: float = Field(0.08, ge=0, description="acceleration sd of a weight shift")
    sit_quiet: LogNormalDuration = LogNormalDuration(median_s=20, gsd=3.0, min_s=1, max_s=1200)
    sit_fidget: LogNormalDuration = LogNormalDuration(median_s=2.5, gsd=1.6, min_s=0.5, max_s=10)
    sit_fidget_sd_g: float = Field(0.15, ge=0)
    # sitting foot postures: probability, pitch range (deg), roll range (deg), sway (mg)
    sit_flat_p: float = Field(0.6, ge=0)
    sit_flat_tilt_sd_deg: float = Field(5.0, ge=0)
    sit_heel_p: float = Field(0.2, ge=0, description="on the heel, toes up")
    sit_heel_pitch_deg: tuple[float, float] = (10.0, 35.0)
    sit_toes_p: float = Field(0.12, ge=0, description="on the toes, heel up")
    sit_toes_pitch_deg: tuple[float, float] = (-40.0, -10.0)
    sit_crossed_p: float = Field(0.08, ge=0, description="legs crossed: foot hanging, rolled")
    sit_crossed_roll_deg: tuple[float, float] = (15.0, 45.0)
    sit_sway_sd_mg: float = Field(2.0, ge=0)

    @field_validator("sit_heel_pitch_deg", "sit_toes_pitch_deg", "sit_crossed_roll_deg")
    @classmethod
    def _ranges(cls, v: tuple[float, float]) -> tuple[float, float]:
        return _range(v, 360.0, "deg")

    sit_crossed_sway_sd_mg: float = Field(25.0, ge=0, description="a hanging foot swings")
    # shoe off the foot
    off_flat_p: float = Field(0.85, ge=0)
    off_side_p: float = Field(0.12, ge=0, description="on its side: roll +-90 deg (+y or -y up)")
    off_upside_down_p: float = Field(0.03, ge=0)
    off_tilt_sd_deg: float = Field(3.0, ge=0)
    off_sway_sd_mg: float = Field(0.0, ge=0, description="floor vibration while off the foot")
    handling: LogNormalDuration = LogNormalDuration(median_s=4, gsd=1.5, min_s=1.5, max_s=15)
    handling_sd_g: float = Field(0.4, ge=0, description="acceleration sd while the shoe is handled")
    sway_corner_hz: float = Field(1.0, gt=0, description="corner frequency of the sway noise")


class GaitConfig(_Strict):
    """Gait cycle of the simulated foot (walking and stairs)."""

    cycle_s: float = Field(1.05, gt=0.5, lt=2.0, description="mean stride (gait cycle) duration, walking")
    cycle_sd_s: float = Field(0.06, ge=0, description="spread of the per-bout mean cycle")
    cycle_jitter: float = Field(0.025, ge=0, description="stride-to-stride relative sd")
    stride_length_m: float = Field(1.35, gt=0)
    stride_length_sd_m: float = Field(0.12, ge=0)
    clearance_m: float = Field(0.12, gt=0, description="peak height of the sensor above the floor in swing")
    heel_strike_pitch_deg: float = Field(18.0)
    toe_off_pitch_deg: float = Field(-55.0)
    swing_roll_deg: float = Field(6.0, ge=0)
    lateral_m: float = Field(0.03, ge=0, description="lateral excursion of the foot in swing")
    impact_g: float = Field(6.0, ge=0, description="peak of the heel-strike impact (continuous time)")
    impact_tau_s: float = Field(0.012, gt=0, description="decay time of the impact")
    midstance_sd_g: float = Field(0.01, ge=0, description="residual motion in mid-stance")
    stairs_cycle_s: float = Field(1.3, gt=0.5, lt=2.5)
    stairs_step_height_m: float = Field(0.17, ge=0)
    stairs_stride_length_m: float = Field(0.6, gt=0)
    slope_sd_deg: float = Field(2.0, ge=0, description="terrain slope spread per walking bout")
    oversample: int = Field(5, ge=1, le=20, description="internal oversampling of moving segments (anti-alias average)")


class TemperatureConfig(_Strict):
    """Sensor temperature: ambient off the foot, in-shoe on the foot, heat of long walks."""

    ambient_c: tuple[float, float] = Field((15.0, 25.0), description="range of the daily mean ambient")
    ambient_daily_swing_c: float = Field(2.0, ge=0, description="amplitude of the ambient day/night cycle")
    foot_c: tuple[float, float] = Field((28.0, 33.0), description="range of the daily in-shoe plateau")
    walk_heat_c: tuple[float, float] = Field((2.0, 5.0), description="range of the extra heat of a long walk")
    tau_on_s: float = Field(600.0, gt=0, description="time constant towards the in-shoe plateau")
    tau_off_s: float = Field(900.0, gt=0, description="time constant back to ambient off the foot")
    tau_walk_s: float = Field(600.0, gt=0, description="time constant of the walking heat")
    noise_sd_c: float = Field(0.05, ge=0, description="measurement noise of the reported temperature")
    lsb_c: float = Field(0.01, ge=0, description="resolution of the reported temperature (0: none)")

    @field_validator("ambient_c", "foot_c", "walk_heat_c")
    @classmethod
    def _ranges(cls, v: tuple[float, float]) -> tuple[float, float]:
        return _range(v, 1000.0, "degC")


class PressureConfig(_Strict):
    """4 pressure channels: heel, midfoot, 1st metatarsal, toe (kPa)."""

    stand_kpa: tuple[float, float, float, float] = Field(
        (60.0, 15.0, 45.0, 20.0), description="standing load per channel (heel, midfoot, met1, toe)"
    )
    wearer_sd: float = Field(0.25, ge=0, description="relative per-wearer spread of stand_kpa")
    walk_peak_factor: float = Field(2.2, gt=0, description="walking peak / standing level")
    sit_factor: float = Field(0.3, ge=0, description="sitting load / standing load")
    sway_rel: float = Field(0.15, ge=0, description="relative slow load variation while standing")
    noise_kpa: float = Field(0.5, ge=0)
    offset_kpa: float = Field(0.5, ge=0, description="reading of an unloaded cell")


class SensorConfig(_Strict):
    """Per-device error draw (uniform in +-limit) and the read-out chain."""

    offset_mg: float = Field(60.0, ge=0, description="|offset| limit per axis")
    scale_rel: float = Field(0.03, ge=0, description="|scale - 1| limit per axis")
    nonorth_deg: float = Field(0.6, ge=0, description="|non-orthogonality| limit per axis pair")
    misalign_deg: float = Field(0.6, ge=0, description="|mounting misalignment| limit per rotation axis")
    noise_sd_mg: Triple = (2.5, 2.5, 3.0)
    range_g: float = Field(8.0, gt=0, description="full scale; readings clip at +-range_g")
    lsb_mg: float = Field(3.90625, ge=0, description="quantisation step, mg (12 bit at +-8 g: 16 g / 4096, "
                          "16 of the BLE codec's 1/4096 g units, so the codec carries it exactly; 0: none)")


class EffectConfig(_Strict):
    """One sensor effect: switch, magnitude (per axis, in the effect's unit), explicit values."""

    enabled: bool = False
    magnitude: Triple = (0.0, 0.0, 0.0)
    coefficients: Triple | None = Field(
        None, description="explicit per-axis values (override the random draw)"
    )


def _eff(m: float) -> EffectConfig:
    return EffectConfig(magnitude=(m, m, m))


class StepConfig(EffectConfig):
    """A bias step: the offset jumps by the drawn (or given) size, in mg per axis, at ``at_day``."""

    at_day: float = Field(10.0, ge=0, description="when the offset jumps (days since the start)")


class EffectsConfig(_Strict):
    """The effects; units: mg/degC, ppm/degC, mg/day, mg/g^2, ppm/degC, mg."""

    temp_ref_c: float = 25.0
    temperature_bias: EffectConfig = _eff(0.5)          # mg/degC
    temperature_scale: EffectConfig = _eff(200.0)       # ppm/degC
    time_drift_bias: EffectConfig = _eff(0.3)           # mg/day
    scale_nonlinearity: EffectConfig = _eff(3.0)        # mg/g^2
    # cross-axis coupling per degC (nxy, nxz, nyz); 100 ppm/degC over 20 degC is 2 mrad,
    # a bending package's order of magnitude (the datasheets give cross-axis sensitivity,
    # ~1-2 %, but not its tempco: this is a stress case, not a typical part)
    temperature_cross: EffectConfig = _eff(100.0)       # ppm/degC
    # a bias that jumps once (a shock, a battery change, a re-soldered board): 1-2 mg per
    # axis, the order of the turn-on repeatability consumer datasheets give (+-1-5 mg)
    bias_step: StepConfig = StepConfig(magnitude=(2.0, 2.0, 2.0))  # mg, at at_day

    @model_validator(mode="before")
    @classmethod
    def _default_magnitudes(cls, data: Any) -> Any:
        """An effect given without ``magnitude`` (``[sim.effects.bias_step] at_day = 4``) keeps
        its own default magnitude, not the zero of a bare :class:`EffectConfig`."""
        if not isinstance(data, dict):
            return data
        out = dict(data)
        for name, value in data.items():
            field = cls.model_fields.get(name)
            if isinstance(value, dict) and "magnitude" not in value and field is not None \
                    and isinstance(field.default, EffectConfig):
                out[name] = {**value, "magnitude": field.default.magnitude}
        return out


class BleConfig(_Strict):
    """Radio link: samples per notification and the loss rate."""

    rate_hz: float = Field(20.0, gt=0, le=1000)
    samples_per_packet: int = Field(1, ge=1)
    packet_loss_rate: float = Field(0.01, ge=0, lt=1)


class SimConfig(_Strict):
    """The whole simulator configuration (``[sim]`` section).

    Examples
    --------
    >>> cfg = SimConfig.from_section({"ble": {"packet_loss_rate": 0.0}})
    >>> cfg.ble.rate_hz
    20.0
    """

    days: float = Field(1.0, gt=0, description="default length of a simulation (days)")
    chunk_s: float = Field(3600.0, gt=0, description="length of one streamed chunk")
    pose_window_s: float = Field(10.0, gt=0, description="poses: still periods are cut into windows this long (detector max_window_s)")
    pose_min_s: float = Field(1.0, gt=0, description="poses: shorter windows are dropped (detector min_duration_s)")
    pose_trim_s: float = Field(0.2, ge=0, description="poses: cut from both ends of a still period (detector trim_s)")
    day: DayConfig = DayConfig()
    activity: ActivityConfig = ActivityConfig()
    posture: PostureConfig = PostureConfig()
    gait: GaitConfig = GaitConfig()
    temperature: TemperatureConfig = TemperatureConfig()
    pressure: PressureConfig = PressureConfig()
    sensor: SensorConfig = SensorConfig()
    effects: EffectsConfig = EffectsConfig()
    ble: BleConfig = BleConfig()

    @classmethod
    def from_section(cls, section: dict[str, Any] | None) -> "SimConfig":
        """Validate a ``[sim]`` TOML section (a dict); raise InputError naming the field."""
        try:
            return cls.model_validate(section or {})
        except ValidationError as exc:
            err = exc.errors()[0]
            loc = ".".join(str(p) for p in err["loc"])
            raise InputError(f"config [sim].{loc}: {err['msg']}") from exc

    def with_effects(self, names: list[str] | tuple[str, ...], only: bool = True) -> "SimConfig":
        """A copy with the effects ``names`` enabled (and, if ``only``, all others off)."""
        for n in names:
            if n not in EFFECT_NAMES:
                raise InputError(f"effects: unknown effect {n!r}; choose from {', '.join(EFFECT_NAMES)}")
        upd = {}
        for n in EFFECT_NAMES:
            e: EffectConfig = getattr(self.effects, n)
            on = n in names or (e.enabled and not only)
            upd[n] = e.model_copy(update={"enabled": on})
        return self.model_copy(update={"effects": self.effects.model_copy(update=upd)})

    def updated(self, **sections: dict[str, Any]) -> "SimConfig":
        """A validated copy with some fields of some sections replaced.

        ``cfg.updated(ble={"packet_loss_rate": 0.0}, sensor={"lsb_mg": 0.0})``.
        """
        data = self.model_dump()
        for name, vals in sections.items():
            if isinstance(data.get(name), dict):
                data[name] = {**data[name], **vals}
            else:
                data[name] = vals
        return SimConfig.from_section(data)
