"""Robot configuration: geometry, odometry and sensor error models, and every parameter of
every component, read from TOML (docs/design.md, 2, "One configuration path").

The default configuration (the paper's SLAMbot) ships in ``fgslam/data/robot_default.toml``;
a key it does not set takes the default written beside its field here (:func:`param`), with
its unit and meaning (``fgslam config --show`` lists them all). A user's file overrides any
subset of the keys; ``[[sonar.arrays]]`` replaces the whole list. Every error is a
:class:`ConfigError` with one line naming the file, the key and what was expected. Units are
SI; keys ending in ``_deg`` are degrees and have radian properties.
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

from fgslam.choices import CHOICES, SCANMATCH_CHOICES
from fgslam.errors import UserError

DEFAULT_CONFIG_NAME = "robot_default.toml"


class ConfigError(UserError, ValueError):
    """A robot configuration file is invalid; the message is one line for the user."""


def param(
    default: Any = dataclasses.MISSING,
    unit: str = "",
    doc: str = "",
    *,
    factory: Any = dataclasses.MISSING,
    derive: str = "",
) -> Any:
    """A configuration key: its default (written here and nowhere else), its unit and its
    one-line meaning, both shown by ``fgslam config --show``. ``derive``: the rule that gives
    the key's value when it holds its "derive" value (0, or negative where 0 is a value)."""
    return field(default=default, default_factory=factory, metadata=_meta(unit, doc, derive))


def _meta(unit: str, doc: str, derive: str = "") -> dict[str, str]:
    """A key's unit, meaning and derivation rule (:func:`param`), for a ``field`` itself."""
    return {"unit": unit, "doc": doc, "derive": derive}


def linked(key: str, default: Any, unit: str, doc: str) -> Any:
    """A component's parameter whose value is the configuration key ``key`` ("section.name",
    resolved by :class:`RobotConfig`: converted, or derived from the sensor), so it is no key
    of its own section. ``default``: its value when the class is built directly, the one the
    default configuration gives it."""
    return field(default=default, metadata={"unit": unit, "doc": doc, "from": key})


def linked_from(base: Any, resolved: Any) -> Any:
    """``base`` (a component's parameters) with the linked fields of ``resolved`` (the same
    class, e.g. a configuration's section), in nested sections too."""
    kw = {}
    for f in dataclasses.fields(base):
        value = getattr(resolved, f.name)
        if "from" in f.metadata:
            kw[f.name] = value
        elif dataclasses.is_dataclass(value):
            kw[f.name] = linked_from(getattr(base, f.name), value)
    return dataclasses.replace(base, **kw)


def keys(cls: type) -> list[dataclasses.Field]:
    """The fields of section ``cls`` that are keys of the TOML file (not linked ones)."""
    return [f for f in dataclasses.fields(cls) if f.name != "source" and "from" not in f.metadata]


@dataclass(frozen=True)
class Mount:
    """Sensor pose in the robot frame: x, y in m, yaw in degrees."""

    x: float = param(unit="m", doc="forward of the robot's origin")
    y: float = param(unit="m", doc="left of the robot's origin")
    yaw_deg: float = param(unit="deg", doc="heading, counter-clockwise from the robot's x")

    @property
    def pose(self) -> gtsam.Pose2:
        return gtsam.Pose2(self.x, self.y, math.radians(self.yaw_deg))


@dataclass(frozen=True)
class OdometryConfig:
    """Differential drive odometry (paper eqs 1-5). The defaults of the optional keys are the
    values a log header without them was run with; the shipped configuration may set others."""

    wheelbase: float = param(unit="m", doc="D, distance between the driving wheels")
    wheel_radius_right: float = param(unit="m", doc="right wheel radius")
    wheel_radius_left: float = param(unit="m", doc="left wheel radius")
    encoder_steps_per_rev: int = param(unit="count", doc="encoder steps per wheel revolution")
    sample_period: float = param(unit="s", doc="time between encoder samples")
    k_r: float = param(unit="1", doc="paper eq 5: sigma(L_r) = k_r L_r per sample")
    k_l: float = param(unit="1", doc="sigma(L_l) = k_l L_l per sample")
    k_d: float = param(unit="1", doc="sigma(D) = k_d D per sample")
    # motion error model (factors.odometry.OdometryParams; 0: the paper's eq 5 alone)
    alpha1: float = param(0.0, "rad^2/rad", "variance of the turn per rad turned")
    alpha2: float = param(0.0, "rad^2/m", "variance of the turn per m travelled")
    alpha3: float = param(0.0, "m^2/m", "variance along track per m travelled")
    alpha4: float = param(0.0, "m^2/rad", "variance along track per rad turned")
    alpha5: float = param(0.0, "m^2/m", "lateral variance per m travelled")
    hole_tolerance: float = param(0.0, "s", "no odometry sample this long is a hole; 0 off")
    hole_speed: float = param(1.0, "m/s", "speed the robot may have moved at in a hole")
    hole_turn_rate: float = param(1.0, "rad/s", "turn rate it may have turned at in a hole")
    # "wheels": the wheel calibration errors (e_r, e_l, e_b: relative errors of the right and
    # left wheel distances and of the wheelbase) are estimated (a graph variable; EKF states);
    # "off": the nominal radii and wheelbase are taken as exact (a log header without the
    # key: off, as the log was run)
    calibration: str = param("off", "choice", "wheel calibration errors estimated: wheels, off")
    # prior standard deviations of (e_r, e_l, e_b): how far the nominal values may be off
    # (tyre wear and load change a radius by about 1 %, the contact patch the wheelbase)
    calibration_sigma: tuple[float, ...] = param(
        (0.01, 0.01, 0.01), "1", "prior sigmas of the relative errors e_r, e_l, e_b"
    )
    # m: the smallest wheel distance the encoders tell apart, a floor under every
    # preintegrated covariance (factors.odometry.resolution_floor); 0: one encoder tick,
    # 2 pi r / encoder_steps_per_rev of each wheel
    resolution: float = param(
        0.0,
        "m",
        "smallest wheel distance the encoders tell apart (covariance floor)",
        derive="one encoder tick, 2 pi r / encoder_steps_per_rev",
    )

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

    mount: Mount = field(metadata=_meta("", "the laser's pose in the robot frame"))
    n_beams: int = param(unit="count", doc="beams per scan")
    fov_deg: float = param(unit="deg", doc="field of view, first beam at -fov/2")
    range_resolution: float = param(unit="m", doc="range quantum")
    max_range: float = param(unit="m", doc="readings beyond are no return")
    sigma_range: float = param(unit="m", doc="random range error (incl. quantisation)")
    systematic_offset: float = param(unit="m", doc="systematic range error: offset")
    systematic_per_metre: float = param(unit="m/m", doc="systematic range error per m of range")
    sigma_time: float = param(unit="s", doc="time-registration uncertainty of a scan")
    baud_rate: int = param(unit="baud", doc="serial line rate; sets the scan period")
    delay_min: float = param(unit="s", doc="least delay between scan start and its stamp")
    delay_max: float = param(unit="s", doc="largest such delay")
    # which range errors are estimated (graph variable, EKF states) with the systematic
    # estimates as prior sigmas, their worst-case terms leaving the fits' covariances (the
    # features carry their Jacobians instead): "offset" (the scale keeps its worst case),
    # "range" (offset and scale), "off" (the paper's worst case for both)
    calibration: str = param("off", "choice", "range errors estimated: offset, range, off")

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

    name: str = param(unit="text", doc="the array's name")
    mount: Mount = field(metadata=_meta("", "pan axis pose in the robot frame; yaw at centre"))
    pan_min_deg: float = param(unit="deg", doc="pan angle at one end of the sweep")
    pan_max_deg: float = param(unit="deg", doc="pan angle at the other end")
    sweep_period: float = param(unit="s", doc="one sweep there and back")


@dataclass(frozen=True)
class SonarConfig:
    """Advanced sonar error model (paper II-B, docs/design.md, 3.5) and the arrays."""

    sigma_bearing_deg: float = param(unit="deg", doc="bearing error sigma (paper II-B)")
    sigma_sound_rel: float = param(unit="1", doc="relative std of the speed of sound")
    max_range_plane: float = param(unit="m", doc="planes echo up to this range")
    max_range_corner: float = param(unit="m", doc="corners echo up to this range")
    max_range_edge: float = param(unit="m", doc="edges echo up to this range")
    beam_half_width_deg: float = param(unit="deg", doc="corners and edges echo within this")
    plane_incidence_deg: float = param(unit="deg", doc="planes echo within this of normal")
    cycle_rate: float = param(unit="Hz", doc="measurement cycles per array")
    arrays: tuple[SonarArrayConfig, ...] = param(unit="", doc="the sonar arrays")
    # where the graph backends attach a sonar point or plane feature: "scan-frame" (the
    # paper: the reading moved by odometry into the laser scan's frame) or "own-time" (the
    # pose at the reading's own time, interpolated between the keyframes around it;
    # docs/design.md, 6). The EKF keeps no past poses and always uses the scan frame.
    timing: str = param("scan-frame", "choice", "graph: sonar at scan-frame or own-time")
    # "sound" estimates the relative error of the assumed speed of sound (every echo's range
    # reads r (1 + sound); one graph variable with the others, an EKF state) with the prior
    # sigma sound_bias_sigma; the sonar points, planes and fusions then carry its Jacobian.
    # "off": the paper's random relative range error alone (sigma_sound_rel).
    calibration: str = param("off", "choice", "speed-of-sound error estimated: sound, off")
    sound_bias_sigma: float = param(0.01, "1", "prior sigma of the speed-of-sound error")

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
    """The front end's sensor-dependent thresholds and options. A threshold at 0 is derived
    from the laser by the rule of its ``derive`` (:func:`frontend_thresholds`; the paper's PLS
    gives the values of :class:`SegmentParams` and :class:`MapParams`).

    ``residual_level`` is off for the PLS, whose range model the simulator reproduces; the
    readers' derived configurations (real logs) set 0.99.

    ``line_end_trim``: the segmentation bounds the perpendicular distance, so a line may end
    with a grazing beam of the next wall, its range tens of cm off; in the simulated room that
    biased lines 2 mm outward on average. Off by default: on the relations benchmark it left
    Intel and MIT unchanged but took Freiburg 079 from 0.039 to 0.136 m (experiments/README.md,
    real_relations.py).
    """

    min_points: int = param(
        0, "count", "a line needs more points than this", derive="ceil(4 deg / beam step)"
    )
    outlier: float = param(
        0.0, "m", "range-model threshold of the next-3-points test", derive="3.5 sigma_range"
    )
    spread: float = param(
        0.0, "m", "largest std of point-to-line distances", derive="1.25 sigma_range"
    )
    max_line_range: float = param(
        0.0,
        "m",
        "points farther end lines",
        derive="where beams lie 7 cm apart, 0.07 m / beam step to 0.5 m, <= max_range",
    )
    map_max_range: float = param(
        0.0, "m", "landmarks farther are no association candidates", derive="max_line_range + 2"
    )
    residual_level: float = param(
        0.0, "p", "chi-square level beyond which a fit's residual scales its covariance; 0 off"
    )
    corners: str = param(
        "with-lines", "choice", "corners keep their lines (with-lines), replace-lines, off"
    )
    points_from: str = param(
        "any-echo", "choice", "sonar points from any-echo, or unfused-echoes only"
    )
    line_end_trim: float = param(
        0.0, "sigma", "line fits drop end beams beyond this many robust sigmas; 0 off"
    )


@dataclass(frozen=True)
class ScanMatchConfig:
    """Laser scan matching, keyframes and loop closures (docs/design.md, 5b; beyond the paper,
    which links every scan to the next by wheel odometry alone). The paper's own scheme is
    ``odometry = "wheels"``, ``keyframes = "every-scan"``.

    The model error (``model_error_*``) is what every scan match's covariance gets on top of
    its residual-based part (surfaces the two scans sample at other places, clutter that is
    not a line); derived as half a grid cell and one beam, measured on the benchmark's
    relations (experiments/README.md, scanmatch_consistency.py; CHANGELOG.md, issue 14).
    ``motion_gate_p``: with ``odometry`` both the factor graph keeps both links as robust
    factors (the rest of the graph decides); the EKF predicts with the scan match alone where
    the two disagree at this level (wheels slip)."""

    odometry: str = param("both", "choice", "what links consecutive keyframes: wheels, scan, both")
    keyframes: str = param("motion", "choice", "keyframe policy: motion, every-scan")
    keyframe_distance: float = param(0.5, "m", "travel since the last keyframe: a new one")
    keyframe_angle_deg: float = param(20.0, "deg", "turn since the last keyframe: a new one")
    loop_closures: str = param("on", "choice", "loop closures (graph backends): on, off")
    loop_radius: float = param(4.0, "m", "old keyframes this near are loop candidates")
    loop_min_travel: float = param(8.0, "m", "path since a candidate, at least")
    match_resolution: float = param(
        0.0, "m", "correlative search's finest grid cell", derive="2 sigma_range in [3, 5] cm"
    )
    match_link_distance: float = param(
        0.0,
        "m",
        "reference neighbours closer than this are joined",
        derive="1.7 x the beam spacing at 10 m, at least 0.2 m",
    )
    match_corr_distance: float = param(
        0.0,
        "m",
        "largest distance to a corresponding reference point",
        derive="1.7 x the beam spacing at 10 m, at least 0.2 m",
    )
    match_normal_radius: float = param(
        0.0,
        "m",
        "neighbourhood of a reference point for its normal",
        derive="2.2 x the beam spacing at 10 m, at least 0.25 m",
    )
    model_error_xy: float = param(
        -1.0, "m", "model-error sigma of every match, in quadrature", derive="half a grid cell"
    )
    model_error_theta_deg: float = param(
        -1.0, "deg", "model-error sigma of every match in heading", derive="one beam step"
    )
    motion_gate_p: float = param(
        0.999, "p", "EKF: wheels and scan match disagreeing at this level: the scan alone"
    )


# m: the random range error of a SICK LMS, the laser of the foreign logs (CARMEN, ROS; 1 cm,
# docs/readers.md): the readers' derived configurations and a matcher built without a sensor.
# The paper's PLS has 2 cm ([laser] sigma_range of the shipped configuration).
SICK_LMS_SIGMA_RANGE = 0.01
ASSOCIATION_METHODS = ("jcbb", "nn")

# The components' sections (docs/design.md, 2, "One configuration path"): each class below is
# the parameters of one component and the TOML section of the same name in RobotConfig; its
# linked fields take their values from another section's key (RobotConfig resolves them).


@dataclass(frozen=True)
class SegmentParams:
    """Thresholds of the line growing (:mod:`fgslam.frontend.segmentation`; m unless stated);
    ``[features.segment]``."""

    min_points: int = linked("frontend.min_points", 8, "count", "a line needs more points")
    max_range: float = linked("frontend.max_line_range", 8.0, "m", "points farther end lines")
    jump: float = param(0.3, "m", "range discontinuity: |r_i - r_{i-1}| > jump + jump_rel r")
    jump_rel: float = param(0.05, "1", "the discontinuity's part proportional to range")
    spread: float = linked("frontend.spread", 0.025, "m", "std of point-to-line distances")
    outlier: float = linked("frontend.outlier", 0.07, "m", "next-3-points test threshold")
    sonar_radius: float = param(0.2, "m", "a corner/edge cluster this close to a point ends it")

    @classmethod
    def from_config(cls, cfg: RobotConfig) -> SegmentParams:
        """The ``[features.segment]`` section of ``cfg``, its thresholds linked to the sensor."""
        return cfg.features.segment


@dataclass(frozen=True)
class FrontEndParams:
    """Thresholds of the front end (:class:`fgslam.frontend.pipeline.FrontEnd`; m, rad, s);
    ``[features]``."""

    segment: SegmentParams = field(
        default_factory=SegmentParams, metadata=_meta("", "line growing ([features.segment])")
    )
    window: float = param(6.0, "s", "sonar readings this long before and after a scan")
    cluster_radius: float = param(0.15, "m", "single-linkage distance of sonar clusters")
    visible_dist: float = param(0.3, "m", "a cluster farther from every laser point: invisible")
    phantom_margin: float = param(0.3, "m", "echoes this far behind a laser surface: phantoms")
    support_dist: float = param(0.1, "m", "sonar echoes this close to a segment support it")
    right_angle_tol: float = param(math.radians(12), "rad", "two lines form a right angle")
    corner_gap: float = param(0.3, "m", "laser only: line ends this close to the intersection")
    min_cluster: int = param(3, "count", "echoes in a sonar-only point cluster")
    sonar_step: float = param(0.2, "s", "sonar-only logs without laser: output step")
    residual_level: float | None = linked(
        "frontend.residual_level", None, "p", "fits: residual covariance scaling (None: off)"
    )
    corners: str = linked("frontend.corners", FrontendConfig.corners, "choice", "corner mode")
    points_from: str = linked(
        "frontend.points_from", FrontendConfig.points_from, "choice", "sonar points from"
    )
    # which of the laser's range errors are estimated: their worst-case terms leave the
    # covariances (the features always carry the Jacobians of both, Feature.Jc)
    range_calibration: str = linked(
        "laser.calibration", LaserConfig.calibration, "choice", "laser range errors estimated"
    )
    line_end_trim: float = linked(
        "frontend.line_end_trim", FrontendConfig.line_end_trim, "sigma", "line end trimming"
    )

    @classmethod
    def from_config(cls, cfg: RobotConfig) -> FrontEndParams:
        """The ``[features]`` section of ``cfg``, its options and thresholds linked to
        ``[frontend]`` and the laser (:func:`fgslam.frontend.pipeline.frontend_params`)."""
        return cfg.features


@dataclass(frozen=True)
class AssociationParams:
    """Association thresholds (:mod:`fgslam.slam.association`); gates are probabilities,
    lengths m, angles rad; ``[association]``."""

    method: str = param("jcbb", "choice", "jcbb (joint compatibility) or nn (nearest)")
    gate_p: float = param(0.99, "p", "individual and joint chi-square gate")
    ambiguous_p: float = param(0.9999, "p", "a miss inside this gate is a near miss")
    ambiguity_margin: float = param(1.0, "chi2", "two hypotheses this close: equally good")
    merge_overlap: float = param(0.4, "1", "a measurement covering this of two lines merges")
    max_gap: float = param(0.5, "m", "a line measurement may extend a map line by this gap")
    sonar_line_gap: float = param(1.0, "m", "a sonar plane's foot point this near a map line")
    # residuals beyond these (rad or m, per component) cannot pass any sensible gate
    pregate: tuple[float, float, float] = param(
        (0.35, 1.0, 0.6), "rad|m", "residuals beyond these pass no gate (per component)"
    )
    max_nodes: int = param(1000, "count", "branch-and-bound budget per scan")

    @classmethod
    def from_config(cls, cfg: RobotConfig) -> AssociationParams:
        """The ``[association]`` section of ``cfg``."""
        return cfg.association


def _assoc(name: str, doc: str, unit: str) -> Any:
    return linked(f"association.{name}", getattr(AssociationParams, name), unit, doc)


@dataclass(frozen=True)
class MapParams:
    """Map management thresholds (:mod:`fgslam.slam.mapping`; m, rad; gates as
    probabilities); ``[map]``, the association's in ``[association]``."""

    # association (see fgslam.slam.association)
    association: str = linked("association.method", AssociationParams.method, "choice", "method")
    gate_p: float = _assoc("gate_p", "chi-square gate", "p")
    ambiguous_p: float = _assoc("ambiguous_p", "near-miss gate", "p")
    ambiguity_margin: float = _assoc("ambiguity_margin", "equally good within", "chi2")
    merge_overlap: float = _assoc("merge_overlap", "overlap that merges two lines", "1")
    max_gap: float = _assoc("max_gap", "gap a measurement may extend a line by", "m")
    sonar_line_gap: float = _assoc("sonar_line_gap", "sonar plane's foot to a line", "m")
    pregate: tuple[float, float, float] = _assoc("pregate", "residual pre-gate", "rad|m")
    # geometry
    min_line_length: float = param(0.7, "m", "only longer lines enter the map")
    big_step: float = param(0.5, "1", "endpoint moved this fraction toward a reliable end")
    small_step: float = param(0.1, "1", "... toward an unreliable one")
    max_range: float = linked(
        "frontend.map_max_range", 10.0, "m", "landmarks farther are no association candidates"
    )
    fov: float = param(math.pi, "rad", "field of view for predicted in view")
    # lifecycle (see fgslam.slam.lifecycle; N and the window: CHANGELOG.md, issue 12)
    confirm_sightings: int = param(2, "count", "sightings that confirm a tentative landmark")
    confirm_keyframes: int = param(2, "count", "in at least this many keyframes")
    confirm_sigma_m: float = param(
        0.0, "m", "sightings constrain a landmark this well", derive="max_range / 4"
    )
    confirm_sigma_rad: float = param(0.5, "rad", "likewise in angle")
    tentative_keyframes: int = param(10, "count", "a tentative unseen this long is discarded")
    tentative_gate_p: float = param(0.99, "p", "gate of the tentative landmarks")
    duplicate_p: float = param(0.99, "p", "two landmarks this alike are one")
    duplicate_pregate_m: float = param(0.5, "m", "duplicate test only this near")
    duplicate_pregate_rad: float = param(0.2, "rad", "and this close in angle")
    duplicate_retest: int = param(10, "count", "a pair that failed is tested again after")
    unseen_limit: int = param(30, "count", "predicted in view this often, unseen: unreliable")
    max_nodes: int = _assoc("max_nodes", "branch-and-bound budget", "count")

    @classmethod
    def from_config(cls, cfg: RobotConfig) -> MapParams:
        """The ``[map]`` section of ``cfg``, its thresholds linked to the sensor and to
        ``[association]``."""
        return cfg.map

    def association_params(self) -> AssociationParams:
        names = {f.name for f in dataclasses.fields(AssociationParams)}
        kw = {k: getattr(self, k) for k in names if hasattr(self, k)}
        return AssociationParams(method=self.association, **kw)


@dataclass(frozen=True)
class KeyframeParams:
    """Keyframe policy and scan odometry (:mod:`fgslam.slam.keyframes`); ``[keyframes]``,
    the policy in ``[scanmatch]``.

    ``min_tracked``: a keyframe with at least ``min_features`` features of which fewer than
    this many went to landmarks already in the map (confirmed or tentative) makes the next
    scan a keyframe, so that a new place's features are seen again soon. ``match_min_score``,
    ``match_min_overlap``: the consecutive matches' rejection thresholds, below the matcher's
    (0.5 / 0.25, sized to tell places apart over a loop closure's window): within the small
    window around the wheels' guess a right match of scans 1 m apart in clutter often scores
    0.2-0.5 (Intel: 11 % of the pairs rejected at 0.5, each a wheels-only link up to 14 deg
    off; at 0.2 / 0.1, 3 %, with 23 instead of 18 of 909 accepted pairs more than 10 cm or
    2 deg from GMapping's poses: experiments/README.md), and the ambiguity test still guards
    the corridors. ``motion_gate_p``: :func:`factors.odometry.link_motions` (3 dof)."""

    policy: str = linked(
        "scanmatch.keyframes", ScanMatchConfig.keyframes, "choice", "keyframe policy"
    )
    odometry: str = linked(
        "scanmatch.odometry", ScanMatchConfig.odometry, "choice", "what links keyframes"
    )
    distance: float = linked(
        "scanmatch.keyframe_distance", ScanMatchConfig.keyframe_distance, "m", "travel: a keyframe"
    )
    angle: float = linked(
        "scanmatch.keyframe_angle_deg",
        math.radians(ScanMatchConfig.keyframe_angle_deg),
        "rad",
        "turn: a keyframe",
    )
    # 0.35 until 2026-12-02, shadowed by a second field of the same name (a bug)
    min_overlap: float = param(0.1, "1", "a scan overlapping the keyframe's less: a keyframe")
    min_tracked: int = param(2, "count", "fewer features to map landmarks: next scan keyframe")
    min_features: int = param(3, "count", "... of a keyframe with at least this many features")
    local_map: int = param(1, "count", "scans matched against this many last keyframes' scans")
    # 2.5 recovered matches but took Intel from 0.23 to 1.0 m
    retry_window: float = param(1.0, "1", "a rejected match retried with a window this larger")
    match_min_score: float = param(0.2, "1", "consecutive matches scoring less: rejected")
    match_min_overlap: float = param(0.1, "1", "consecutive matches overlapping less: rejected")
    motion_gate_p: float = linked(
        "scanmatch.motion_gate_p", ScanMatchConfig.motion_gate_p, "p", "EKF wheels/scan gate"
    )

    def __post_init__(self) -> None:
        policies, odometry = SCANMATCH_CHOICES["keyframes"], SCANMATCH_CHOICES["odometry"]
        if self.policy not in policies:
            raise ValueError(f"unknown keyframe policy {self.policy!r}; expected one of {policies}")
        if self.odometry not in odometry:
            raise ValueError(f"unknown odometry {self.odometry!r}; expected one of {odometry}")
        if not 0.0 < self.motion_gate_p < 1.0:
            raise ValueError(f"motion_gate_p must lie in (0, 1), got {self.motion_gate_p!r}")

    @classmethod
    def from_config(cls, cfg: RobotConfig) -> KeyframeParams:
        """The ``[keyframes]`` section of ``cfg``, its policy from ``[scanmatch]``."""
        return cfg.keyframes

    @property
    def matching(self) -> bool:
        """Whether scans are matched at all."""
        return self.odometry != "wheels" or self.policy == "motion"


@dataclass(frozen=True)
class LoopParams:
    """Loop-closure search (:mod:`fgslam.slam.loops`; m, rad); ``[loops]``, whether and
    where in ``[scanmatch]``.

    ``min_search_xy``, the window's floor: the estimate is overconfident after closures
    (Intel: 0.8 m off at 2500 s with 3 sigma below 0.3 m, every closure there "diverged"; 0.3
    m / 5 deg before, Intel 0.076 -> 0.048 m, MIT and Freiburg unchanged: CHANGELOG.md, issue
    14). The search's cost (the module doc): no match over less view than ``min_view`` (0:
    always match); none at a place with a match rejected ``retry_after`` keyframes ago or less
    (0: always); local maps kept (``cache_size``, 0: none) while no keyframe of one moved more
    than ``cache_xy``, ``cache_theta`` relative to it. ``doubt`` False: weak, slightly
    seeing-through and inconsistent closures are rejected outright (the rule before; Intel
    0.100 -> 0.051 m with it, CHANGELOG.md, issue 14)."""

    enabled: bool = linked("scanmatch.loop_closures", True, "bool", "loop closures on")
    radius: float = linked(
        "scanmatch.loop_radius", ScanMatchConfig.loop_radius, "m", "candidates this near"
    )
    min_travel: float = linked(
        "scanmatch.loop_min_travel", ScanMatchConfig.loop_min_travel, "m", "path behind a candidate"
    )
    max_candidates: int = param(2, "count", "candidates matched per keyframe")
    neighbours: int = param(2, "count", "keyframes each side in a candidate's local map")
    every: int = param(1, "count", "try at most every this many keyframes")
    max_search_xy: float = param(2.0, "m", "search window (3 sigma) half-width, at most")
    min_search_xy: float = param(1.0, "m", "search window half-width, at least")
    max_search_theta: float = param(math.radians(30.0), "rad", "heading window, at most")
    min_search_theta: float = param(math.radians(10.0), "rad", "heading window, at least")
    min_score: float = param(0.55, "1", "matches scoring less: rejected")
    min_overlap: float = param(0.35, "1", "matches overlapping less: rejected")
    gate_p: float = param(0.999, "p", "closure against the estimate: chi-square gate")
    min_view: float = param(
        0.3, "1", "no match where the old map covers less of the scan; 0 always"
    )
    retry_after: int = param(3, "count", "no match where one was rejected this recently")
    cache_size: int = param(64, "count", "local maps kept; 0 none")
    cache_xy: float = param(0.01, "m", "a kept local map's keyframes moved less than this")
    cache_theta: float = param(math.radians(0.06), "rad", "... and turned less than this")
    see_through_margin: float = param(0.3, "m", "a beam this far beyond a surface sees through")
    max_see_through: float = param(0.05, "1", "fraction seen through above: in doubt")
    grey_see_through: float = param(0.10, "1", "fraction seen through above: rejected")
    doubt: bool = param(True, "bool", "closures in doubt wait for confirmation (else rejected)")
    confident_xy: float = param(0.3, "m", "estimate sure of the relative pose: 3 sigma within")
    confident_theta: float = param(math.radians(3.0), "rad", "... and this in heading")
    confirm_window: int = param(10, "count", "keyframes a doubtful closure waits for a pair")
    pair_xy: float = param(0.2, "m", "two closures agreeing within this confirm each other")
    pair_theta: float = param(math.radians(2.0), "rad", "... and within this in heading")

    @classmethod
    def from_config(cls, cfg: RobotConfig) -> LoopParams:
        """The ``[loops]`` section of ``cfg``, whether and where from ``[scanmatch]``."""
        return cfg.loops


@dataclass(frozen=True)
class MatchParams:
    """Parameters of :func:`fgslam.scanmatch.match` (m, rad); ``[matcher]``, the ones derived
    from the laser linked to it and to their overrides in ``[scanmatch]``. Zero for a
    parameter of the search means "derive it" (its meaning says how); :meth:`for_laser`
    derives the rest from the sensor. Built directly (no sensor), a matcher assumes a SICK LMS
    (1 cm, 30 m)."""

    search_xy: float = param(0.3, "m", "half-width of the search window around the guess")
    search_theta: float = param(0.25, "rad", "half-width of the search window in heading")
    resolution: float = linked("scanmatch.match_resolution", 0.03, "m", "finest grid cell")
    sigma_range: float = linked("laser.sigma_range", SICK_LMS_SIGMA_RANGE, "m", "range noise")
    max_range: float = linked("laser.max_range", 30.0, "m", "beams beyond are ignored")
    # correlative search
    angular_step: float = param(0.0, "rad", "between rotations; 0: resolution / far range")
    blur: float = param(0.0, "m", "likelihood grid's Gaussian s; 0: max(resolution, 2 sigma)")
    levels: int = param(0, "count", "branch-and-bound depth; 0: coarsest block ~ window / 2")
    voxel: float = param(0.0, "m", "query voxel filter of the search; 0: resolution")
    link_distance: float = linked(
        "scanmatch.match_link_distance", 0.3, "m", "reference neighbours closer are joined"
    )
    max_candidates: int = param(3000, "count", "most branch-and-bound nodes kept per level")
    max_cells: int = param(16_000_000, "count", "largest grid; a wider reference: coarser")
    mode_nats: float = param(7.0, "nats", "response poses this near the best are kept")
    min_coverage: float = param(0.3, "1", "fewer query points in the reference's view: all")
    response_gain: float = param(3.0, "nats", "per point per unit of score, response weights")
    basin_chi2: float = param(11.34, "chi2", "response poses within: the best's basin")
    # ICP
    icp_iterations: int = param(15, "count", "ICP iterations")
    corr_distance: float = linked(
        "scanmatch.match_corr_distance", 0.3, "m", "largest distance to a correspondence"
    )
    normal_radius: float = linked(
        "scanmatch.match_normal_radius", 0.25, "m", "neighbourhood for a point's normal"
    )
    normal_k: int = param(24, "count", "at most this many neighbours (incl. the point)")
    robust_scale: float = param(3.0, "sigma", "Cauchy scale in residual sigmas")
    inlier_sigmas: float = param(3.0, "sigma", "inlier: point-to-line residual below")
    # covariance
    hac_lags: int = param(10, "count", "beams over which residuals may be correlated")
    max_kappa: float = param(25.0, "1", "cap on the inflation from correlated residuals")
    cov_inflation: float = param(1.3, "1", "constant factor on the measured inflation")
    # model error the residuals cannot show (surfaces sampled at other places by the two
    # scans, clutter that is not a line): independent variance added to every match
    floor_xy: float = linked("scanmatch.model_error_xy", 0.0, "m", "model error of a match")
    floor_theta: float = linked(
        "scanmatch.model_error_theta_deg", 0.0, "rad", "model error in heading"
    )
    # rejection
    min_points: int = param(20, "count", "fewer query or reference points: rejected")
    min_score: float = param(0.5, "1", "correlative score below: rejected")
    min_overlap: float = param(0.25, "1", "inlier fraction below: rejected")
    max_ambiguity: float = param(0.5, "1", "1-sigma extent / window half-width above: rejected")
    max_basins: int = param(4, "count", "ICP from this many basins of the response")
    # response poses within this (score x points) below the best are basin starts: on the
    # 3-5 cm grid a basin one door period off scored 8 below the right one in a periodic
    # corridor (tests), so the starts reach further than the response's mode_nats
    basin_nats: float = param(20.0, "nats", "response poses this near the best: basin starts")

    @classmethod
    def for_laser(
        cls,
        sigma_range: float,
        angular_step: float,
        max_range: float,
        base: MatchParams | None = None,
        **kw: float,
    ) -> MatchParams:
        """``base`` (default: the defaults) with the parameters derived from the sensor: range
        noise ``sigma_range`` (m), beam spacing ``angular_step`` (rad), ``max_range`` (m);
        ``kw`` overrides. The grid cell is 2 sigma (3 cm to 5 cm); neighbouring beams at 10 m
        are joined and corresponded (at least 0.2 m); the model error is half a grid cell and
        one beam (measured on real logs' relations)."""
        import numpy as np

        spacing = 10.0 * abs(angular_step)
        derived: dict[str, Any] = {
            "sigma_range": float(sigma_range),
            "max_range": float(max_range),
            "resolution": float(np.clip(2.0 * sigma_range, 0.03, 0.05)),
            "link_distance": max(0.2, 1.7 * spacing),
            "corr_distance": max(0.2, 1.7 * spacing),
            "normal_radius": max(0.25, 2.2 * spacing),
        }
        derived.update(kw)
        derived.setdefault("floor_xy", 0.5 * float(derived["resolution"]))
        derived.setdefault("floor_theta", abs(float(angular_step)))
        return dataclasses.replace(base or cls(), **derived)

    @classmethod
    def from_config(cls, cfg: RobotConfig) -> MatchParams:
        """The ``[matcher]`` section of ``cfg``: the matcher for its laser (:meth:`for_laser`)
        with ``[scanmatch]``'s ``match_*`` and ``model_error_*`` where they are set."""
        return cfg.matcher


def _matcher(cfg: RobotConfig) -> MatchParams:
    las, sm = cfg.laser, cfg.scanmatch
    step = math.radians(las.fov_deg) / max(las.n_beams - 1, 1)
    kw: dict[str, float] = {}
    for key in ("resolution", "link_distance", "corr_distance", "normal_radius"):
        if getattr(sm, f"match_{key}"):
            kw[key] = getattr(sm, f"match_{key}")
    if sm.model_error_xy >= 0:
        kw["floor_xy"] = sm.model_error_xy
    if sm.model_error_theta_deg >= 0:
        kw["floor_theta"] = math.radians(sm.model_error_theta_deg)
    return MatchParams.for_laser(las.sigma_range, step, las.max_range, cfg.matcher, **kw)


@dataclass(frozen=True)
class RobotInfo:
    name: str = param(unit="text", doc="the robot's name")


# the components' sections of RobotConfig, in the order of the pipeline
COMPONENTS = ("features", "keyframes", "matcher", "loops", "association", "map")


@dataclass(frozen=True)
class RobotConfig:
    """Everything the system knows about the robot, and every parameter of every component.

    The components' sections (``features``, ``keyframes``, ``matcher``, ``loops``,
    ``association``, ``map``) are the components' parameter classes themselves; their linked
    fields are resolved here from the keys they name (also after ``dataclasses.replace``), so
    ``cfg.map`` is the map management's parameters as the configuration gives them."""

    robot: RobotInfo
    odometry: OdometryConfig
    laser: LaserConfig
    sonar: SonarConfig
    frontend: FrontendConfig = field(default_factory=FrontendConfig)
    scanmatch: ScanMatchConfig = field(default_factory=ScanMatchConfig)
    features: FrontEndParams = field(default_factory=FrontEndParams)
    keyframes: KeyframeParams = field(default_factory=KeyframeParams)
    matcher: MatchParams = field(default_factory=MatchParams)
    loops: LoopParams = field(default_factory=LoopParams)
    association: AssociationParams = field(default_factory=AssociationParams)
    map: MapParams = field(default_factory=MapParams)
    source: str = field(default="<default>", compare=False)

    def __post_init__(self) -> None:
        for name, value in _resolve(self).items():
            object.__setattr__(self, name, value)

    def to_dict(self) -> dict[str, Any]:
        """Plain nested dict (TOML/JSON serialisable) of the keys, without ``source`` and
        without the linked fields (their keys are elsewhere)."""
        d = _keys_dict(self)
        d["sonar"]["arrays"] = list(d["sonar"]["arrays"])
        return d


def _keys_dict(obj: Any) -> Any:
    if dataclasses.is_dataclass(obj):
        return {f.name: _keys_dict(getattr(obj, f.name)) for f in keys(type(obj))}
    if isinstance(obj, tuple | list):
        return type(obj)(_keys_dict(v) for v in obj)
    return obj


def _resolve(cfg: RobotConfig) -> dict[str, Any]:
    """The components' sections with their linked fields set from the keys they name."""
    th = frontend_thresholds(cfg)
    fe, sm, a = cfg.frontend, cfg.scanmatch, cfg.association
    seg = dataclasses.replace(
        cfg.features.segment,
        min_points=th["min_points"],
        max_range=th["max_line_range"],
        outlier=th["outlier"],
        spread=th["spread"],
    )
    shared = {  # MapParams' copies of the association's keys
        f.name: getattr(a, f.metadata["from"].split(".")[1])
        for f in dataclasses.fields(MapParams)
        if f.metadata.get("from", "").startswith("association.")
    }
    return {
        "features": dataclasses.replace(
            cfg.features,
            segment=seg,
            residual_level=th["residual_level"],
            corners=fe.corners,
            points_from=fe.points_from,
            range_calibration=cfg.laser.calibration,
            line_end_trim=fe.line_end_trim,
        ),
        "keyframes": dataclasses.replace(
            cfg.keyframes,
            policy=sm.keyframes,
            odometry=sm.odometry,
            distance=sm.keyframe_distance,
            angle=math.radians(sm.keyframe_angle_deg),
            motion_gate_p=sm.motion_gate_p,
        ),
        "matcher": _matcher(cfg),
        "loops": dataclasses.replace(
            cfg.loops,
            enabled=sm.loop_closures == "on",
            radius=sm.loop_radius,
            min_travel=sm.loop_min_travel,
        ),
        "map": dataclasses.replace(
            cfg.map,
            max_range=th["map_max_range"],
            **shared,
        ),
    }


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


def derived_values(cfg: RobotConfig) -> dict[str, Any]:
    """The value each key with a derivation rule (``param(derive=...)``) takes for ``cfg``
    when it holds its "derive" value ("section.key" -> value in the key's unit)."""
    th = frontend_thresholds(cfg)
    m = cfg.matcher
    ticks = (cfg.odometry.metres_per_tick_right, cfg.odometry.metres_per_tick_left)
    out: dict[str, Any] = {f"frontend.{k}": th[k] for k in _DERIVED_FRONTEND}
    out.update(
        {
            "odometry.resolution": ticks[0] if ticks[0] == ticks[1] else ticks,
            "scanmatch.match_resolution": m.resolution,
            "scanmatch.match_link_distance": m.link_distance,
            "scanmatch.match_corr_distance": m.corr_distance,
            "scanmatch.match_normal_radius": m.normal_radius,
            "scanmatch.model_error_xy": m.floor_xy,
            "scanmatch.model_error_theta_deg": math.degrees(m.floor_theta),
            "map.confirm_sigma_m": cfg.map.max_range / 4,
        }
    )
    return out


_DERIVED_FRONTEND = ("min_points", "outlier", "spread", "max_line_range", "map_max_range")


@dataclass(frozen=True)
class Entry:
    """One parameter as ``fgslam config --show`` lists it: ``key`` ("section.name"), its
    ``value`` in ``cfg`` and its ``default`` (the shipped configuration's), ``unit`` and
    ``meaning`` (the field's :func:`param`), ``derived`` (the value its rule gives, when the
    key holds its "derive" value; else None) and ``source`` (a linked field's key)."""

    section: str
    name: str
    value: Any
    default: Any
    unit: str
    meaning: str
    rule: str = ""
    derived: Any = None
    source: str = ""

    @property
    def key(self) -> str:
        return f"{self.section}.{self.name}"


def entries(cfg: RobotConfig | None = None) -> list[Entry]:
    """Every parameter of ``cfg`` (default: the shipped configuration), section by section:
    each key and each linked field, nested sections and each sonar array in turn."""
    default = load_config()
    cfg = cfg or default
    derived = derived_values(cfg)
    out: list[Entry] = []

    def walk(obj: Any, base: Any, section: str) -> None:
        later = []
        for f in dataclasses.fields(obj):
            if f.name == "source":
                continue
            value = getattr(obj, f.name)
            dflt = getattr(base, f.name, None) if base is not None else None
            path = f"{section}.{f.name}" if section else f.name
            if dataclasses.is_dataclass(value):
                later.append((value, dflt, path))
                continue
            if isinstance(value, tuple) and value and dataclasses.is_dataclass(value[0]):
                for i, item in enumerate(value):
                    other = dflt[i] if dflt is not None and i < len(dflt) else None
                    later.append((item, other, f"{path}.{i}"))
                continue
            meta = f.metadata
            rule = meta.get("derive", "")
            holds = rule and (value < 0 if (dflt or 0) < 0 else value == 0)
            out.append(
                Entry(
                    section,
                    f.name,
                    value,
                    dflt,
                    meta.get("unit", ""),
                    meta.get("doc", ""),
                    rule,
                    derived.get(path) if holds else None,
                    meta.get("from", ""),
                )
            )
        for value, dflt, path in later:
            walk(value, dflt, path)

    walk(cfg, default, "")
    return out
