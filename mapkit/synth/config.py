"""Typed configuration of the synthetic town: pydantic models, presets and YAML overrides.

The presets live in ``configs/synth/<name>.yaml`` of the source tree, installed with the package
(:mod:`mapkit.core.presets`); each of their values carries a comment naming its source (an MCVL or
semi-dense paper section, a sensor datasheet, or a mapkit choice with its reason). A user YAML is
merged over the preset (mappings key by key, lists replaced whole) and the result validated here;
an unknown or ill-typed field raises a ``ConfigError`` naming it. The resolved config is written
beside every output.
"""

from __future__ import annotations

import datetime as dt
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from mapkit.core.config import deep_merge
from mapkit.core.errors import ConfigError
from mapkit.core.presets import configs_dir, preset_path

FORMAT_VERSION = 1
PRESETS = ("tiny", "demo", "places", "benchmark")
Weather = Literal["clear", "sunny", "overcast", "cloudy", "foggy", "rainy", "snowy"]
WEATHERS: tuple[Weather, ...] = ("clear", "sunny", "overcast", "cloudy", "foggy", "rainy", "snowy")
Season = Literal["spring", "summer", "autumn", "winter"]


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class OriginConfig(_Model):
    lat_deg: float = Field(51.7520, ge=-80, le=84)
    lon_deg: float = Field(-1.2577, ge=-180, le=180)
    alt_m: float = 60.0
    timezone: str = "Europe/London"
    date: dt.date = dt.date(2014, 12, 9)


class BuildingConfig(_Model):
    frontage_m: tuple[float, float] = (8.0, 24.0)
    depth_m: tuple[float, float] = (8.0, 18.0)
    floors: tuple[int, int] = (2, 8)
    setback_m: tuple[float, float] = (0.5, 3.0)
    gap_probability: float = Field(0.18, ge=0, le=1)
    wing_probability: float = Field(0.35, ge=0, le=1)
    pitched_roof_probability: float = Field(0.25, ge=0, le=1)
    n_styles: int = Field(10, ge=1, le=64)


class TownConfig(_Model):
    size_m: tuple[float, float] = (1000.0, 1000.0)
    block_m: float = Field(110.0, gt=20)
    jitter: float = Field(0.16, ge=0, le=0.3)
    drop_edge_fraction: float = Field(0.15, ge=0, le=0.6)
    diagonal_fraction: float = Field(0.12, ge=0, le=1)
    curve_fraction: float = Field(0.3, ge=0, le=1)
    curve_amplitude: float = Field(0.12, ge=0, le=0.2)
    n_avenues: int = Field(2, ge=0, le=4)
    n_dead_ends: int = Field(4, ge=0)
    street_half_width_m: float = 6.0
    avenue_half_width_m: float = 9.5
    lane_half_width_m: float = 4.5
    parking_width_m: float = 2.3
    sidewalk_width_m: float = 3.0
    sidewalk_height_m: float = 0.15
    buildings: BuildingConfig = BuildingConfig()
    tree_spacing_m: float = Field(16.0, gt=2)
    park_trees_per_ha: float = Field(20.0, ge=0)
    lamp_spacing_m: float = Field(32.0, gt=5)
    fence_probability: float = Field(0.6, ge=0, le=1)
    sign_probability: float = Field(0.5, ge=0, le=1)
    parked_car_occupancy: float = Field(0.4, ge=0, le=1)
    margin_m: float = Field(200.0, ge=0)


class MountConfig(_Model):
    """A sensor's pose on the vehicle: translation in base_link (m) and roll, pitch, yaw (deg)."""

    xyz_m: tuple[float, float, float]
    rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)


class CameraConfig(_Model):
    width: int = Field(640, ge=16)
    height: int = Field(480, ge=16)
    hfov_deg: float = Field(75.0, gt=10, lt=170)
    rate_hz: float = Field(10.0, gt=0)
    # Video: every session's camera records at this rate whatever its own rate; a session's own
    # rate (its camera_rate_hz, else rate_hz) stays its image rate, the rate of its image database
    # and queries (manifest: image_rate_hz), so that maps can be made from every image, as DSO
    # consumes video (semi-dense paper Sec. 3), while retrieval sees the same images as without it.
    record_rate_hz: float | None = Field(None, gt=0)
    compression: Literal["jpeg", "png", "raw"] = "jpeg"
    mount: MountConfig = MountConfig(xyz_m=(1.6, 0.0, 1.55), rpy_deg=(0.0, 3.0, 0.0))


class LidarConfig(_Model):
    enabled: bool = True  # off: camera, GPS, IMU and ground truth only (MCVL needs no LiDAR; a tenth of the bytes)
    beams: int = Field(32, ge=1, le=256)
    vertical_fov_deg: tuple[float, float] = (-30.67, 10.67)
    azimuth_steps: int = Field(1024, ge=16)
    rate_hz: float = Field(10.0, gt=0)
    min_range_m: float = Field(1.0, ge=0)
    max_range_m: float = Field(100.0, gt=0)
    range_noise_m: float = Field(0.01, ge=0)
    mount: MountConfig = MountConfig(xyz_m=(1.2, 0.0, 1.9))


class GpsConfig(_Model):
    rate_hz: float = Field(2.0, gt=0)
    white_sigma_m: float = Field(1.5, ge=0)
    vertical_factor: float = Field(2.0, ge=0)
    bias_sigma_m: float = Field(2.0, ge=0)
    bias_tau_s: float = Field(300.0, gt=0)
    multipath_rate_hz: float = Field(1.0 / 120.0, ge=0)
    multipath_duration_s: float = Field(8.0, gt=0)
    multipath_sigma_m: float = Field(8.0, ge=0)
    dropout_rate_hz: float = Field(1.0 / 180.0, ge=0)
    dropout_duration_s: float = Field(5.0, gt=0)
    mount: MountConfig = MountConfig(xyz_m=(0.3, 0.0, 1.8))


class ImuConfig(_Model):
    enabled: bool = True
    rate_hz: float = Field(100.0, gt=0)
    gyro_noise_rad_s: float = Field(0.002, ge=0)
    accel_noise_m_s2: float = Field(0.02, ge=0)
    gyro_bias_rad_s: float = Field(0.0005, ge=0)
    accel_bias_m_s2: float = Field(0.02, ge=0)
    mount: MountConfig = MountConfig(xyz_m=(1.2, 0.0, 0.5))


class MotionConfig(_Model):
    ground_truth_rate_hz: float = Field(100.0, gt=0)
    max_lateral_accel_m_s2: float = Field(2.0, gt=0)
    max_accel_m_s2: float = Field(1.5, gt=0)
    max_decel_m_s2: float = Field(2.5, gt=0)
    start_from_rest: bool = False
    lane_wander_m: float = Field(0.15, ge=0)
    roll_per_lateral_accel_deg: float = 0.4
    pitch_per_accel_deg: float = 0.3


class SessionConfig(_Model):
    name: str = Field(pattern=r"^[A-Za-z0-9_.-]+$")
    role: Literal["train", "test"] = "train"
    date: dt.date | None = None
    time: str = Field("12:00", pattern=r"^([01]\d|2[0-3]):[0-5]\d$")
    weather: Weather = "clear"
    length_m: float = Field(500.0, gt=0)
    max_duration_s: float | None = Field(None, gt=0)
    speed_mps: float = Field(10.0, gt=0, le=40)
    lane_offset_m: float = Field(0.0, ge=-1.0, le=1.0)
    exposure_ev: float = Field(0.0, ge=-6, le=6)
    white_balance_k: float = Field(5500.0, ge=1500, le=12000)
    camera_rate_hz: float | None = Field(None, gt=0)
    season: Season | None = None
    trajectory: Path | None = None
    follow: str | None = None
    follow_shift_m: float = 0.0
    # oncoming cars driving the route the other way in the opposite lane (mapkit.synth.traffic); their LiDAR
    # returns are written beside the log as the truth of dynamic-point removal
    moving_cars: int = Field(0, ge=0)


class SessionPlanConfig(_Model):
    """Sessions drawn automatically (MCVL Sec. IV-B: uniform times 1am-11pm, 7 weathers)."""

    n_train: int = Field(0, ge=0)
    hours: tuple[float, float] = (1.0, 23.0)
    weathers: tuple[Weather, ...] = WEATHERS
    length_m: tuple[float, float] = (800.0, 2000.0)
    speed_mps: tuple[float, float] = (8.0, 13.0)
    lane_offset_m: tuple[float, float] = (-0.5, 0.5)
    night_exposure_ev: float = -1.0
    dates: tuple[dt.date, ...] = ()
    camera_rate_hz: float | None = None
    # Planned routes (listed or drawn) steer away from roads earlier sessions planned: a road driven
    # n times is exp(-new_road_weight * n) times less likely at each junction. 0 = independent walks.
    new_road_weight: float = Field(0.0, ge=0)


class SynthConfig(_Model):
    format_version: int = FORMAT_VERSION
    preset: str = "custom"
    seed: int = 0
    origin: OriginConfig = OriginConfig()
    town: TownConfig = TownConfig()
    camera: CameraConfig = CameraConfig()
    lidar: LidarConfig = LidarConfig()
    gps: GpsConfig = GpsConfig()
    imu: ImuConfig = ImuConfig()
    motion: MotionConfig = MotionConfig()
    sessions: tuple[SessionConfig, ...] = ()
    session_plan: SessionPlanConfig = SessionPlanConfig()
    workers: int = Field(1, ge=1, le=64)

    @field_validator("sessions")
    @classmethod
    def _unique_names(cls, v: tuple[SessionConfig, ...]) -> tuple[SessionConfig, ...]:
        names = [s.name for s in v]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"session names must be unique, repeated: {dup}")
        return v

    @model_validator(mode="after")
    def _some_session(self) -> SynthConfig:
        if not self.sessions and self.session_plan.n_train == 0:
            raise ValueError("no sessions: give `sessions` or `session_plan.n_train`")
        seen: set[str] = set()
        for s in self.sessions:
            if s.follow is not None and s.follow not in seen:
                raise ValueError(f"session {s.name!r} follows {s.follow!r}, which is not an earlier session")
            seen.add(s.name)
        return self


# --- loading --------------------------------------------------------------------------------------


def presets_dir() -> Path:
    """The folder of the synth presets: ``configs/synth`` of the source tree, installed with the package."""
    return configs_dir() / "synth"


def _read_yaml(path: Path, what: str) -> dict:
    if not path.is_file():
        raise ConfigError(f"{what} {path} does not exist")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML ({exc})") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: the top level must be a mapping, not {type(data).__name__}")
    return data


def validate(data: dict, source: str) -> SynthConfig:
    try:
        return SynthConfig.model_validate(data)
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"]) or "(top level)"
        more = f" (and {exc.error_count() - 1} more)" if exc.error_count() > 1 else ""
        raise ConfigError(f"{source}: field `{where}`: {first['msg']}{more}") from None


def preset_dict(name: str) -> dict:
    if name not in PRESETS:
        raise ConfigError(f"unknown synth preset {name!r}; choose one of {', '.join(PRESETS)}")
    return _read_yaml(preset_path("synth", name), f"preset {name!r}:")


def load_config(
    preset: str = "tiny",
    config: Path | None = None,
    seed: int | None = None,
    overrides: dict[str, Any] | None = None,
) -> SynthConfig:
    """The resolved configuration: preset, then the user's YAML, then ``overrides``, then ``seed``."""
    data = preset_dict(preset)
    data["preset"] = preset
    source = f"preset {preset!r}"
    if config is not None:
        data = deep_merge(data, _read_yaml(Path(config), "config file"))
        source = str(config)
    if overrides:
        data = deep_merge(data, overrides)
    if seed is not None:
        data["seed"] = int(seed)
    cfg = validate(data, source)
    if cfg.format_version != FORMAT_VERSION:
        raise ConfigError(
            f"{source}: field `format_version`: {cfg.format_version} is not supported (expected {FORMAT_VERSION})"
        )
    return cfg


def dump_yaml(cfg: SynthConfig) -> str:
    body = yaml.safe_dump(cfg.model_dump(mode="json"), sort_keys=False, default_flow_style=None, width=100)
    return "# Resolved configuration of this synthetic town (mapkit synth); re-run with --config to reproduce.\n" + body
