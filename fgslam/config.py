"""Robot configuration: geometry, odometry and sensor error models, read from TOML.

The default configuration (the paper's SLAMbot) ships in ``fgslam/data/robot_default.toml``.
A user's file overrides any subset of its keys; ``[[sonar.arrays]]`` replaces the whole list.
Every error is a :class:`ConfigError` with one line naming the file, the key and what was
expected. Units are SI; keys ending in ``_deg`` are degrees and have radian properties.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
import typing
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import gtsam

from fgslam.errors import UserError

DEFAULT_CONFIG_NAME = "robot_default.toml"


class ConfigError(UserError, ValueError):
    """A robot configuration file is invalid; the message is one line for the user."""


@dataclass(frozen=True)
class Mount:
    """Sensor pose in the robot frame: x, y in m, yaw in degrees."""

    x: float
    y: float
    yaw_deg: float

    @property
    def pose(self) -> gtsam.Pose2:
        return gtsam.Pose2(self.x, self.y, math.radians(self.yaw_deg))


@dataclass(frozen=True)
class OdometryConfig:
    """Differential drive odometry (paper eqs 1-5)."""

    wheelbase: float
    wheel_radius_right: float
    wheel_radius_left: float
    encoder_steps_per_rev: int
    sample_period: float
    k_r: float
    k_l: float
    k_d: float
    # motion error model (factors.odometry.OdometryParams; 0: the paper's eq 5 alone)
    alpha1: float = 0.0  # rad^2 of turn per rad turned
    alpha2: float = 0.0  # rad^2 of turn per m travelled
    alpha3: float = 0.0  # m^2 along track per m travelled
    alpha4: float = 0.0  # m^2 along track per rad turned
    alpha5: float = 0.0  # m^2 lateral per m travelled
    hole_tolerance: float = 0.5  # s without odometry samples that make a hole
    hole_speed: float = 1.0  # m/s the robot may have moved at in a hole
    hole_turn_rate: float = 1.0  # rad/s it may have turned at

    def params(self) -> Any:
        """The :class:`factors.odometry.OdometryParams` of this configuration."""
        from factors.odometry import OdometryParams

        return OdometryParams(
            self.wheelbase,
            self.k_r,
            self.k_l,
            self.k_d,
            self.alpha1,
            self.alpha2,
            self.alpha3,
            self.alpha4,
            self.alpha5,
            self.hole_tolerance,
            self.hole_speed,
            self.hole_turn_rate,
        )

    @property
    def metres_per_tick_right(self) -> float:
        return 2.0 * math.pi * self.wheel_radius_right / self.encoder_steps_per_rev

    @property
    def metres_per_tick_left(self) -> float:
        return 2.0 * math.pi * self.wheel_radius_left / self.encoder_steps_per_rev


@dataclass(frozen=True)
class LaserConfig:
    """SICK PLS geometry and error model (DESIGN 3.2-3.4)."""

    mount: Mount
    n_beams: int
    fov_deg: float
    range_resolution: float
    max_range: float
    sigma_range: float
    systematic_offset: float
    systematic_per_metre: float
    sigma_time: float
    baud_rate: int
    delay_min: float
    delay_max: float

    @property
    def bearings(self) -> Any:
        """Beam bearings in the laser frame, rad, first beam at -fov/2."""
        import numpy as np

        half = math.radians(self.fov_deg) / 2.0
        return np.linspace(-half, half, self.n_beams)

    @property
    def scan_period(self) -> float:
        """Seconds per scan at the line rate: 732-byte B0 frame, 11 bits a byte (8E1)."""
        return 732 * 11 / self.baud_rate


@dataclass(frozen=True)
class SonarArrayConfig:
    """One advanced sonar array on a panning mechanism."""

    name: str
    mount: Mount
    pan_min_deg: float
    pan_max_deg: float
    sweep_period: float


@dataclass(frozen=True)
class SonarConfig:
    """Advanced sonar error model (paper II-B, DESIGN 3.5) and the arrays."""

    sigma_bearing_deg: float
    sigma_sound_rel: float
    max_range_plane: float
    max_range_corner: float
    max_range_edge: float
    beam_half_width_deg: float
    plane_incidence_deg: float
    cycle_rate: float
    arrays: tuple[SonarArrayConfig, ...]

    @property
    def sigma_bearing(self) -> float:
        return math.radians(self.sigma_bearing_deg)


@dataclass(frozen=True)
class RobotInfo:
    name: str


@dataclass(frozen=True)
class RobotConfig:
    """Everything the system knows about the robot."""

    robot: RobotInfo
    odometry: OdometryConfig
    laser: LaserConfig
    sonar: SonarConfig
    source: str = field(default="<default>", compare=False)

    def to_dict(self) -> dict[str, Any]:
        """Plain nested dict (TOML/JSON serialisable), without ``source``."""
        d = dataclasses.asdict(self)
        d.pop("source")
        d["sonar"]["arrays"] = list(d["sonar"]["arrays"])
        return d


# Fields that must be strictly positive; the rest of the numbers must be finite.
_POSITIVE = {
    "odometry.wheelbase",
    "odometry.wheel_radius_right",
    "odometry.wheel_radius_left",
    "odometry.encoder_steps_per_rev",
    "odometry.sample_period",
    "odometry.hole_tolerance",
    "laser.n_beams",
    "laser.fov_deg",
    "laser.range_resolution",
    "laser.max_range",
    "laser.sigma_range",
    "laser.baud_rate",
    "sonar.sigma_bearing_deg",
    "sonar.sigma_sound_rel",
    "sonar.max_range_plane",
    "sonar.max_range_corner",
    "sonar.max_range_edge",
    "sonar.beam_half_width_deg",
    "sonar.plane_incidence_deg",
    "sonar.cycle_rate",
    "sonar.arrays.sweep_period",
}
_NON_NEGATIVE = {
    "odometry.k_r",
    "odometry.k_l",
    "odometry.k_d",
    "odometry.alpha1",
    "odometry.alpha2",
    "odometry.alpha3",
    "odometry.alpha4",
    "odometry.alpha5",
    "odometry.hole_speed",
    "odometry.hole_turn_rate",
    "laser.systematic_offset",
    "laser.systematic_per_metre",
    "laser.sigma_time",
    "laser.delay_min",
    "laser.delay_max",
}


def _type_name(tp: Any) -> str:
    origin = typing.get_origin(tp)
    if origin is tuple:
        return f"a list of {_type_name(typing.get_args(tp)[0])}"
    if dataclasses.is_dataclass(tp):
        return "a table"
    return {float: "a number", int: "an integer", str: "a string"}.get(tp, str(tp))


def _build(cls: type, data: Any, path: str, src: str) -> Any:
    """Build dataclass ``cls`` from ``data``, checking keys and types; ``path`` names the key."""
    where = f"{src}: key '{path}'" if path else f"{src}:"
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: expected a table, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.name != "source"}
    names = list(fields)
    for key in data:
        if key not in names:
            full = f"{path}.{key}" if path else key
            raise ConfigError(f"{src}: unknown key '{full}' (expected one of: {', '.join(names)})")
    kwargs = {}
    for name in names:
        full = f"{path}.{name}" if path else name
        if name not in data and fields[name].default is not dataclasses.MISSING:
            continue  # an optional key (added later: older logs' headers lack it)
        if name not in data:
            raise ConfigError(f"{src}: missing required key '{full}' ({_type_name(hints[name])})")
        kwargs[name] = _convert(hints[name], data[name], full, src)
    return cls(**kwargs)


def _convert(tp: Any, value: Any, path: str, src: str) -> Any:
    where = f"{src}: key '{path}'"
    if dataclasses.is_dataclass(tp):
        return _build(tp, value, path, src)
    if typing.get_origin(tp) is tuple:
        (item,) = typing.get_args(tp)[:1]
        if not isinstance(value, list):
            raise ConfigError(f"{where}: expected {_type_name(tp)}, got {type(value).__name__}")
        return tuple(_convert(item, v, path, src) for v in value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: expected a string, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where}: expected an integer, got {value!r}")
        out: float = value
    elif tp is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ConfigError(f"{where}: expected a number, got {value!r}")
        out = float(value)
        if not math.isfinite(out):
            raise ConfigError(f"{where}: expected a finite number, got {value!r}")
    else:  # pragma: no cover - only reached if a new field type is added without support
        raise TypeError(f"unsupported config field type {tp}")
    if path in _POSITIVE and out <= 0:
        raise ConfigError(f"{where}: expected a positive number, got {value!r}")
    if path in _NON_NEGATIVE and out < 0:
        raise ConfigError(f"{where}: expected a non-negative number, got {value!r}")
    return out


def _merge(base: dict[str, Any], override: dict[str, Any]) -> dict[str, Any]:
    """Recursive dict merge; lists (such as sonar arrays) are replaced whole."""
    out = dict(base)
    for key, value in override.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _merge(out[key], value)
        else:
            out[key] = value
    return out


def default_config_text() -> str:
    """The text of the shipped default configuration."""
    return resources.files("fgslam.data").joinpath(DEFAULT_CONFIG_NAME).read_text("utf-8")


def _read_toml(text: str, src: str) -> dict[str, Any]:
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{src}: not valid TOML: {exc}") from None


def from_dict(data: dict[str, Any], source: str = "<dict>") -> RobotConfig:
    """Validate a complete configuration given as nested dicts (as in a log header)."""
    cfg = _build(RobotConfig, data, "", source)
    _check_consistency(cfg, source)
    return dataclasses.replace(cfg, source=source)


def _check_consistency(cfg: RobotConfig, src: str) -> None:
    if cfg.laser.delay_max < cfg.laser.delay_min:
        raise ConfigError(f"{src}: key 'laser.delay_max': expected >= laser.delay_min")
    for arr in cfg.sonar.arrays:
        if arr.pan_max_deg < arr.pan_min_deg:
            raise ConfigError(
                f"{src}: key 'sonar.arrays.pan_max_deg' of array '{arr.name}': "
                "expected >= pan_min_deg"
            )


def load_config(path: str | Path | None = None) -> RobotConfig:
    """The default robot configuration, overridden by the TOML file at ``path`` if given."""
    base = _read_toml(default_config_text(), DEFAULT_CONFIG_NAME)
    if path is None:
        return from_dict(base, "<default>")
    path = Path(path)
    try:
        text = path.read_text("utf-8")
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read configuration: {exc.strerror}") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: not a UTF-8 text file") from None
    user = _read_toml(text, str(path))
    # Unknown keys must be reported against the user's file, not the merged result.
    _check_known_keys(user, RobotConfig, "", str(path))
    return from_dict(_merge(base, user), str(path))


def _check_known_keys(data: dict[str, Any], cls: type, path: str, src: str) -> None:
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls) if f.name != "source"}
    for key, value in data.items():
        full = f"{path}.{key}" if path else key
        if key not in names:
            raise ConfigError(
                f"{src}: unknown key '{full}' (expected one of: {', '.join(sorted(names))})"
            )
        tp = hints[key]
        if dataclasses.is_dataclass(tp) and isinstance(value, dict):
            _check_known_keys(value, tp, full, src)
