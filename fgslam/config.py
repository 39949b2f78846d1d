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

from fgslam.choices import CHOICES
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
    hole_tolerance: float = 0.0  # s without odometry samples that make a hole; 0: off
    hole_speed: float = 1.0  # m/s the robot may have moved at in a hole
    hole_turn_rate: float = 1.0  # rad/s it may have turned at
    # "wheels": the wheel calibration errors (e_r, e_l, e_b: relative errors of the right and
    # left wheel distances and of the wheelbase) are estimated (a graph variable; EKF states);
    # "off": the nominal radii and wheelbase are taken as exact (a log header without the
    # key: off, as the log was run)
    calibration: str = "off"
    # prior standard deviations of (e_r, e_l, e_b): how far the nominal values may be off
    # (tyre wear and load change a radius by about 1 %, the contact patch the wheelbase)
    calibration_sigma: tuple[float, ...] = (0.01, 0.01, 0.01)
    # m: the smallest wheel distance the encoders tell apart, a floor under every
    # preintegrated covariance (factors.odometry.resolution_floor); 0: one encoder tick,
    # 2 pi r / encoder_steps_per_rev of each wheel
    resolution: float = 0.0

    def calibration_prior(self) -> Any:
        """The prior covariance (3x3) of the wheel calibration errors, or None when off."""
        if self.calibration == "off":
            return None
        import numpy as np

        return np.diag(np.square(self.calibration_sigma))

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
            self.hole_tolerance or math.inf,
            self.hole_speed,
            self.hole_turn_rate,
            self.resolution or self.metres_per_tick_right,
            self.resolution or self.metres_per_tick_left,
        )

    @property
    def metres_per_tick_right(self) -> float:
        return 2.0 * math.pi * self.wheel_radius_right / self.encoder_steps_per_rev

    @property
    def metres_per_tick_left(self) -> float:
        return 2.0 * math.pi * self.wheel_radius_left / self.encoder_steps_per_rev


@dataclass(frozen=True)
class LaserConfig:
    """SICK PLS geometry and error model (docs/design.md, 3.2-3.4)."""

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
    # which range errors are estimated (graph variable, EKF states) with the systematic
    # estimates as prior sigmas, their worst-case terms leaving the fits' covariances (the
    # features carry their Jacobians instead): "offset" (the scale keeps its worst case),
    # "range" (offset and scale), "off" (the paper's worst case for both)
    calibration: str = "off"

    def calibration_prior(self) -> Any:
        """The prior covariance of the estimated range errors (offset m; scale), or None."""
        if self.calibration == "off":
            return None
        import numpy as np

        sig = [self.systematic_offset, self.systematic_per_metre]
        return np.diag(np.square(sig[: 1 if self.calibration == "offset" else 2]))

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
    """Advanced sonar error model (paper II-B, docs/design.md, 3.5) and the arrays."""

    sigma_bearing_deg: float
    sigma_sound_rel: float
    max_range_plane: float
    max_range_corner: float
    max_range_edge: float
    beam_half_width_deg: float
    plane_incidence_deg: float
    cycle_rate: float
    arrays: tuple[SonarArrayConfig, ...]
    # where the graph backends attach a sonar point or plane feature: "scan-frame" (the
    # paper: the reading moved by odometry into the laser scan's frame) or "own-time" (the
    # pose at the reading's own time, interpolated between the keyframes around it;
    # docs/design.md, 6). The EKF keeps no past poses and always uses the scan frame.
    timing: str = "scan-frame"
    # "sound" estimates the relative error of the assumed speed of sound (every echo's range
    # reads r (1 + sound); one graph variable with the others, an EKF state) with the prior
    # sigma sound_bias_sigma; the sonar points, planes and fusions then carry its Jacobian.
    # "off": the paper's random relative range error alone (sigma_sound_rel).
    calibration: str = "off"
    sound_bias_sigma: float = 0.01

    def calibration_prior(self) -> Any:
        """The prior covariance (1x1) of the estimated speed-of-sound error, or None."""
        if self.calibration == "off":
            return None
        import numpy as np

        return np.array([[self.sound_bias_sigma**2]])

    @property
    def sigma_bearing(self) -> float:
        return math.radians(self.sigma_bearing_deg)


@dataclass(frozen=True)
class FrontendConfig:
    """The front end's sensor-dependent thresholds; 0 means derived from the laser
    (:func:`frontend_thresholds`, the rules below; the paper's PLS gives the values in
    brackets):

    - ``min_points``: a line needs more points than this: the beams in 4 deg,
      ``ceil(4 deg / angular step)`` [8];
    - ``outlier`` (m): the range-model threshold of the next-3-points test,
      ``3.5 sigma_range`` [0.07];
    - ``spread`` (m): largest std of point-to-line distances, ``1.25 sigma_range`` [0.025];
    - ``max_line_range`` (m): points farther end lines: where neighbouring beams lie 7 cm
      apart, ``0.07 m / angular step`` rounded to 0.5 m, at most the laser's maximum range
      [8.0];
    - ``map_max_range`` (m): landmarks farther are no association candidates,
      ``max_line_range + 2`` [10.0].

    ``residual_level``: chi-square level beyond which a line or corner fit's own residual
    scales its covariance (:func:`fgslam.frontend.fits.residual_scale`), 0 off. Off for the
    PLS, whose range model the simulator reproduces; the readers' derived configurations
    (real logs) set 0.99.

    ``corners``: a right-angle corner is fitted to the points of its two lines; "with-lines"
    (the paper) keeps both lines as measurements too, "replace-lines" keeps the corner alone
    (no point counted twice), "off" keeps the lines alone. ``points_from``: a sonar cluster
    that ends a laser line gives a point feature from its echo nearest its centre,
    "any-echo" (as before) even one already fused into a line or corner of the scan,
    "unfused-echoes" only from the others (an echo counts once).

    ``line_end_trim``: a line fit leaves out the beams at either end of its segment farther
    from the line than this many robust sigmas of its own perpendicular spread, and refits
    (:func:`fgslam.frontend.fits.fit_line`, ``trim_ends``); 0 off. The segmentation bounds
    the perpendicular distance, so a line may end with a grazing beam of the next wall,
    its range tens of cm off; in the simulated room that biased lines 2 mm outward on
    average. Off by default: on the relations benchmark it left Intel and MIT unchanged
    but took Freiburg 079 from 0.039 to 0.136 m (experiments/README.md, real_relations.py).
    """

    min_points: int = 0
    outlier: float = 0.0
    spread: float = 0.0
    max_line_range: float = 0.0
    map_max_range: float = 0.0
    residual_level: float = 0.0
    corners: str = "with-lines"
    points_from: str = "any-echo"
    line_end_trim: float = 0.0


@dataclass(frozen=True)
class ScanMatchConfig:
    """Laser scan matching, keyframes and loop closures (docs/design.md, 5b; beyond the paper, which
    links every scan to the next by wheel odometry alone).

    - ``odometry``: what links consecutive keyframes: ``wheels`` (the paper), ``scan`` (the
      scan match; wheels where it is rejected) or ``both`` (two robust between factors in
      the graph; their fusion in the EKF);
    - ``keyframes``: ``motion`` (a new keyframe after ``keyframe_distance`` m or
      ``keyframe_angle_deg`` of turn, or when the scan no longer overlaps the keyframe's) or
      ``every-scan`` (the paper);
    - ``loop_closures``: ``on`` or ``off`` (graph backends; an EKF keeps no past poses);
      candidates within ``loop_radius`` m and ``loop_min_travel`` m of path behind;
    - ``match_resolution`` (m): the correlative search's finest grid, 0 derived from the
      laser (:meth:`fgslam.scanmatch.MatchParams.from_config`);
    - ``model_error_xy`` (m), ``model_error_theta_deg``: the model error every scan match's
      covariance gets on top of its residual-based part (surfaces the two scans sample at
      other places, clutter that is not a line); negative: derived from the laser (half a
      grid cell, one beam; measured on the benchmark's relations: experiments/README.md,
      scanmatch_consistency.py; CHANGELOG.md, issue 14);
    - ``motion_gate_p``: with ``odometry`` both, where the scan match and the wheel
      odometry disagree at this chi-square level the EKF predicts with the scan match alone
      (wheels slip); the factor graph keeps both as robust factors (the rest of the graph
      decides).
    """

    odometry: str = "both"
    keyframes: str = "motion"
    keyframe_distance: float = 0.5
    keyframe_angle_deg: float = 20.0
    loop_closures: str = "on"
    loop_radius: float = 4.0
    loop_min_travel: float = 8.0
    match_resolution: float = 0.0
    model_error_xy: float = -1.0
    model_error_theta_deg: float = -1.0
    motion_gate_p: float = 0.999


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
    frontend: FrontendConfig = field(default_factory=FrontendConfig)
    scanmatch: ScanMatchConfig = field(default_factory=ScanMatchConfig)
    source: str = field(default="<default>", compare=False)

    def to_dict(self) -> dict[str, Any]:
        """Plain nested dict (TOML/JSON serialisable), without ``source``."""
        d = dataclasses.asdict(self)
        d.pop("source")
        d["sonar"]["arrays"] = list(d["sonar"]["arrays"])
        return d


LINE_SPAN_DEG = 4.0  # a line spans more than this many degrees of beams (PLS: 8 beams)
OUTLIER_SIGMAS = 3.5  # the outlier test, in range sigmas (PLS: 7 cm)
SPREAD_SIGMAS = 1.25  # the largest point-to-line std, in range sigmas (PLS: 2.5 cm)
LINE_SPACING = 0.07  # m between neighbouring beams beyond which lines end (PLS: at 8 m)
MAP_RANGE_MARGIN = 2.0  # m: association candidates this much beyond the line range


def frontend_thresholds(cfg: RobotConfig) -> dict[str, Any]:
    """The front end's sensor-dependent thresholds: the configured ones, the rest derived
    from the laser (rules in :class:`FrontendConfig`)."""
    las, fe = cfg.laser, cfg.frontend
    step = math.radians(las.fov_deg) / max(las.n_beams - 1, 1)
    out: dict[str, Any] = {
        "min_points": fe.min_points or math.ceil(math.radians(LINE_SPAN_DEG) / step - 1e-9),
        "outlier": fe.outlier or OUTLIER_SIGMAS * las.sigma_range,
        "spread": fe.spread or SPREAD_SIGMAS * las.sigma_range,
        "max_line_range": fe.max_line_range
        or min(las.max_range, 0.5 * round(2 * LINE_SPACING / step)),
    }
    out["map_max_range"] = fe.map_max_range or out["max_line_range"] + MAP_RANGE_MARGIN
    out["residual_level"] = fe.residual_level or None
    return out


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
    for name, keys in given.items():
        data[name].update(keys)
    return dataclasses.replace(from_dict(data, "command line"), source=cfg.source)


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
        f = fields[name]
        has_default = f.default is not dataclasses.MISSING
        if name not in data and (has_default or f.default_factory is not dataclasses.MISSING):
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
        if not isinstance(value, list | tuple):  # tuple: from to_dict
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
    top = _MAXIMUM.get(path, _MAX_ANY)
    if abs(out) > top:
        raise ConfigError(f"{where}: {value!r} is not plausible (expected at most {top:g})")
    if path == "frontend.residual_level" and not out < 1:
        raise ConfigError(f"{where}: expected a level in [0, 1), got {value!r}")
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
    cfg = _build(RobotConfig, data, "", source)
    _check_consistency(cfg, source)
    return dataclasses.replace(cfg, source=source)


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
    step = math.radians(las.fov_deg) / max(las.n_beams - 1, 1)
    if not step >= MIN_BEAM_STEP:
        raise ConfigError(
            f"{src}: key 'laser.fov_deg': {las.fov_deg:g} deg over {las.n_beams} beams is a "
            f"beam step of {step:.3g} rad, below {MIN_BEAM_STEP:g} rad (no scanner is that fine)"
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
