"""Reading and checking configurations: TOML files and dicts into :class:`RobotConfig`, every
value checked (type, sign, plausible size, choices, consistency) with one-line errors."""

from __future__ import annotations

import dataclasses
import math
import tomllib
import typing
from importlib import resources
from pathlib import Path
from typing import Any

from fgslam.choices import CHOICES
from fgslam.config.fields import DEFAULT_CONFIG_NAME, ConfigError, keys
from fgslam.config.robot import ASSOCIATION_METHODS, COMPONENTS, RobotConfig
from fgslam.config.sensors import LaserConfig

# "section.key" -> choices of the components' keys beyond fgslam.choices.CHOICES
_CHOICES = {"association.method": ASSOCIATION_METHODS}

# Fields that must be strictly positive; the rest of the numbers must be finite.
_POSITIVE = {
    "scanmatch.keyframe_distance",
    "scanmatch.keyframe_angle_deg",
    "scanmatch.loop_radius",
    "odometry.wheelbase",
    "odometry.wheel_radius_right",
    "odometry.wheel_radius_left",
    "odometry.encoder_steps_per_rev",
    "odometry.sample_period",
    "laser.n_beams",
    "laser.fov_deg",
    "laser.range_resolution",
    "laser.max_range",
    "laser.sigma_range",
    "laser.baud_rate",
    "sonar.sigma_bearing_deg",
    "sonar.sigma_sound_rel",
    "sonar.sound_bias_sigma",
    "sonar.max_range_plane",
    "sonar.max_range_corner",
    "sonar.max_range_edge",
    "sonar.beam_half_width_deg",
    "sonar.plane_incidence_deg",
    "sonar.cycle_rate",
    "sonar.arrays.sweep_period",
}
_NON_NEGATIVE = {
    "scanmatch.match_resolution",
    "scanmatch.loop_min_travel",
    "frontend.min_points",
    "frontend.outlier",
    "frontend.spread",
    "frontend.max_line_range",
    "frontend.map_max_range",
    "frontend.residual_level",
    "frontend.line_end_trim",
    "odometry.k_r",
    "odometry.k_l",
    "odometry.k_d",
    "odometry.alpha1",
    "odometry.alpha2",
    "odometry.alpha3",
    "odometry.alpha4",
    "odometry.alpha5",
    "odometry.hole_tolerance",
    "odometry.hole_speed",
    "odometry.hole_turn_rate",
    "odometry.resolution",
    "laser.systematic_offset",
    "laser.systematic_per_metre",
    "laser.sigma_time",
    "laser.delay_min",
    "laser.delay_max",
}


# Plausibility bounds (absolute value) of numbers that are surely a mistake beyond them; every
# other number must stay within _MAX_ANY. A 1e20 encoder would make every tick 0 m.
_MAXIMUM = {
    "odometry.wheelbase": 100.0,
    "odometry.wheel_radius_right": 10.0,
    "odometry.wheel_radius_left": 10.0,
    "odometry.encoder_steps_per_rev": 1e9,
    "odometry.sample_period": 60.0,
    "odometry.resolution": 1.0,
    "laser.n_beams": 100000,
    "laser.fov_deg": 360.0,
    "laser.max_range": 1e6,
    "laser.baud_rate": 1e10,
    "sonar.sigma_bearing_deg": 180.0,
    "sonar.beam_half_width_deg": 180.0,
    "sonar.plane_incidence_deg": 90.0,
}
_MAX_ANY = 1e9
# rad: the finest beam step a laser may have (0.2 arc-seconds; 360 deg over the most beams,
# 100000, is 6.3e-5 rad): below it the thresholds derived from the step overflow or divide
# by zero (frontend_thresholds, MatchParams.from_config)
MIN_BEAM_STEP = 1e-6


def _type_name(tp: Any) -> str:
    origin = typing.get_origin(tp)
    if origin is tuple:
        return f"a list of {_type_name(typing.get_args(tp)[0])}"
    if dataclasses.is_dataclass(tp):
        return "a table"
    names = {float: "a number", int: "an integer", str: "a string", bool: "true or false"}
    return names.get(tp, str(tp))


def _build(cls: type, data: Any, path: str, src: str) -> Any:
    """Build dataclass ``cls`` from ``data``, checking keys and types; ``path`` names the key."""
    where = f"{src}: key '{path}'" if path else f"{src}:"
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: expected a table, got {type(data).__name__}")
    _check_known_keys(data, cls, path, src, nested=False)
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for f in keys(cls):
        name = f.name
        full = f"{path}.{name}" if path else name
        has_default = f.default is not dataclasses.MISSING
        if name not in data and (has_default or f.default_factory is not dataclasses.MISSING):
            continue  # an optional key (added later: older logs' headers lack it)
        if name not in data:
            raise ConfigError(f"{src}: missing required key '{full}' ({_type_name(hints[name])})")
        kwargs[name] = _convert(hints[name], data[name], full, src, f.metadata.get("unit", ""))
    out = cls(**kwargs)
    if cls is LaserConfig:
        _check_beam_step(out, src)
    return out


def _convert(tp: Any, value: Any, path: str, src: str, unit: str = "") -> Any:
    where = f"{src}: key '{path}'"
    if dataclasses.is_dataclass(tp):
        return _build(tp, value, path, src)
    if typing.get_origin(tp) is tuple:
        args = typing.get_args(tp)
        if not isinstance(value, list | tuple):  # tuple: from to_dict
            raise ConfigError(f"{where}: expected {_type_name(tp)}, got {type(value).__name__}")
        if Ellipsis not in args and len(value) != len(args):
            raise ConfigError(f"{where}: expected {len(args)} numbers, got {len(value)}")
        return tuple(_convert(args[0], v, path, src, unit) for v in value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: expected a string, got {value!r}")
        choices = CHOICES.get(tuple(path.split(".", 1))) or _CHOICES.get(path)  # type: ignore
        if choices and value not in choices:
            raise ConfigError(f"{where}: expected one of {', '.join(choices)}, got {value!r}")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: expected true or false, got {value!r}")
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
    top = _MAXIMUM.get(path, _MAX_ANY)
    if abs(out) > top:
        raise ConfigError(f"{where}: {value!r} is not plausible (expected at most {top:g})")
    if path.split(".")[0] in COMPONENTS and out < 0:
        raise ConfigError(f"{where}: expected a non-negative number, got {value!r}")
    if unit == "p" and not 0 <= out < 1:
        raise ConfigError(f"{where}: expected a level in [0, 1), got {value!r}")
    if path == "scanmatch.motion_gate_p" and not out > 0:
        raise ConfigError(f"{where}: expected a value in (0, 1), got {value!r}")
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
    except RecursionError:  # arrays or inline tables nested deeper than tomllib recurses
        raise ConfigError(f"{src}: not valid TOML: nested too deeply") from None


def from_dict(data: dict[str, Any], source: str = "<dict>") -> RobotConfig:
    """Validate a complete configuration given as nested dicts (as in a log header)."""
    try:
        cfg = _build(RobotConfig, data, "", source)
    except ValueError as exc:  # a component's own check (ConfigError is one too)
        if isinstance(exc, ConfigError):
            raise
        raise ConfigError(f"{source}: {exc}") from None
    _check_consistency(cfg, source)
    return dataclasses.replace(cfg, source=source)


def _check_beam_step(las: LaserConfig, src: str) -> None:
    """Checked as the laser section is built, before the thresholds derived from the step."""
    step = math.radians(las.fov_deg) / max(las.n_beams - 1, 1)
    if not step >= MIN_BEAM_STEP:
        raise ConfigError(
            f"{src}: key 'laser.fov_deg': {las.fov_deg:g} deg over {las.n_beams} beams is a "
            f"beam step of {step:.3g} rad, below {MIN_BEAM_STEP:g} rad (no scanner is that fine)"
        )


def _check_consistency(cfg: RobotConfig, src: str) -> None:
    for (section, key), choices in CHOICES.items():
        value = getattr(getattr(cfg, section), key)
        if value not in choices:
            raise ConfigError(
                f"{src}: key '{section}.{key}': expected one of {', '.join(choices)}, got {value!r}"
            )
    if not 0.0 < cfg.scanmatch.motion_gate_p < 1.0:
        raise ConfigError(f"{src}: key 'scanmatch.motion_gate_p': expected a value in (0, 1)")
    sig = cfg.odometry.calibration_sigma
    if len(sig) != 3 or not all(v > 0 for v in sig):
        raise ConfigError(
            f"{src}: key 'odometry.calibration_sigma': expected 3 positive numbers "
            "(right wheel, left wheel, wheelbase; relative)"
        )
    las = cfg.laser
    positive = las.systematic_offset > 0 and (
        las.systematic_per_metre > 0 or las.calibration != "range"
    )
    if las.calibration != "off" and not positive:
        raise ConfigError(
            f"{src}: key 'laser.calibration': estimating the range errors needs a positive "
            "laser.systematic_offset (and systematic_per_metre for 'range'): their prior sigmas"
        )
    if cfg.laser.delay_max < cfg.laser.delay_min:
        raise ConfigError(f"{src}: key 'laser.delay_max': expected >= laser.delay_min")
    for arr in cfg.sonar.arrays:
        if arr.pan_max_deg < arr.pan_min_deg:
            raise ConfigError(
                f"{src}: key 'sonar.arrays.pan_max_deg' of array '{arr.name}': "
                "expected >= pan_min_deg"
            )


def load_config(
    path: str | Path | None = None, base_config: RobotConfig | None = None
) -> RobotConfig:
    """The default robot configuration (or ``base_config``, e.g. the one a log reader derived),
    overridden by the TOML file at ``path`` if given."""
    if base_config is not None:
        base = base_config.to_dict()
    else:
        base = _read_toml(default_config_text(), DEFAULT_CONFIG_NAME)
    if path is None and base_config is not None:
        return base_config
    if path is None:
        return from_dict(base, "<default>")
    return from_dict(_merge(base, _user_file(path)), str(path))


def _user_file(path: str | Path) -> dict[str, Any]:
    """The keys of a user's TOML file, unknown keys reported against that file."""
    path = Path(path)
    try:
        text = path.read_text("utf-8")
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read configuration: {exc.strerror}") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: not a UTF-8 text file") from None
    user = _read_toml(text, str(path))
    _check_known_keys(user, RobotConfig, "", str(path))
    return user


def override_config(base: RobotConfig, path: str | Path | None) -> RobotConfig:
    """``base`` (e.g. a log's configuration) with the keys of the TOML file at ``path``
    replaced, key by key (``[[sonar.arrays]]`` replaces the whole list); ``base`` if no path."""
    if path is None:
        return base
    return from_dict(_merge(base.to_dict(), _user_file(path)), str(path))


def check_against_log(cfg: RobotConfig, log_cfg: RobotConfig, log_name: str) -> None:
    """A configuration used on a log must not contradict the data: the same number of laser
    beams, at least as many sonar arrays. One-line :class:`ConfigError` naming both."""
    if cfg.laser.n_beams != log_cfg.laser.n_beams:
        raise ConfigError(
            f"{cfg.source}: laser.n_beams = {cfg.laser.n_beams} contradicts the log {log_name} "
            f"({log_cfg.laser.n_beams} beams per scan)"
        )
    if len(cfg.sonar.arrays) < len(log_cfg.sonar.arrays):
        raise ConfigError(
            f"{cfg.source}: {len(cfg.sonar.arrays)} sonar arrays, but the log {log_name} has "
            f"{len(log_cfg.sonar.arrays)}"
        )


def _check_known_keys(
    data: dict[str, Any], cls: type, path: str, src: str, nested: bool = True
) -> None:
    """Unknown keys of ``data`` (section ``cls`` at ``path``) refused, naming the known ones;
    a linked field's name refused naming the key that sets it."""
    hints = typing.get_type_hints(cls)
    own = {f.name for f in keys(cls)}
    links = {f.name: f.metadata["from"] for f in dataclasses.fields(cls) if "from" in f.metadata}
    for key, value in data.items():
        full = f"{path}.{key}" if path else key
        if key in links:
            raise ConfigError(
                f"{src}: key '{full}' is set by '{links[key]}' (set that key instead)"
            )
        if key not in own:
            known = [f.name for f in keys(cls)]
            raise ConfigError(f"{src}: unknown key '{full}' (expected one of: {', '.join(known)})")
        tp = hints[key]
        if nested and dataclasses.is_dataclass(tp) and isinstance(value, dict):
            _check_known_keys(value, tp, full, src)


def with_scanmatch(cfg: RobotConfig, overrides: dict[str, Any] | None) -> RobotConfig:
    """``cfg`` with keys of its ``[scanmatch]`` section replaced (None values ignored), checked
    as a configuration file's would be (command-line options such as ``--odometry``)."""
    return with_options(cfg, {"scanmatch": overrides or {}})


def with_options(cfg: RobotConfig, sections: dict[str, dict[str, Any]] | None) -> RobotConfig:
    """``cfg`` with keys of its sections replaced (``{"odometry": {"calibration": "wheels"}}``;
    None values ignored), checked as a configuration file's would be (command-line options)."""
    given = {
        name: {k: v for k, v in keys.items() if v is not None}
        for name, keys in (sections or {}).items()
    }
    given = {name: keys for name, keys in given.items() if keys}
    if not given:
        return cfg
    data = cfg.to_dict()
    for name, values in given.items():
        data[name].update(values)
    return dataclasses.replace(from_dict(data, "command line"), source=cfg.source)
