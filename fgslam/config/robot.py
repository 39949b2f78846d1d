"""The components' configuration sections (docs/design.md, 2, "One configuration path"):
``[frontend]``, ``[scanmatch]`` and each component's parameters (front end, keyframes,
matcher, loops, association, map), every default written once beside its field; and the whole
configuration, :class:`RobotConfig`, with its linked fields resolved and the front end's
thresholds derived from the laser."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

from fgslam.choices import LOCALIZE_MOTION_CHOICES, SCANMATCH_CHOICES
from fgslam.config.fields import _meta, keys, linked, param
from fgslam.config.sensors import LaserConfig, OdometryConfig, SonarConfig


@dataclass(frozen=True)
class FrontendConfig:
    """The front end's sensor-dependent thresholds and options. A threshold at 0 is derived
    from the laser by the rule of its ``derive`` (:func:`frontend_thresholds`; the paper's PLS
    gives the values of :class:`SegmentParams` and :class:`MapParams`).

    ``residual_level`` is off for the PLS, whose range model the simulator reproduces; the
    readers' derived configurations (real logs) set 0.99.

    ``line_end_trim``: the segmentation bounds the perpendicular distance, so a line may end
    with a grazing beam of the next wall, 2 cm off the line but its range tens of cm off, which
    the range fit weighs by its range. With it, at most two beams at either end whose range
    residual exceeds this many robust sigmas are left out (:func:`fgslam.frontend.fits
    .fit_line`). In the simulated corridor it takes most of the laser offset's bias out and
    holds the pose NEES (CHANGELOG, issue 37). Off by default: on the relations benchmark
    (real_relations.py, 3) it took Freiburg 079 from 0.039 to 0.045 m, MIT CSAIL from 0.035
    to 0.036 and the Intel bag from 0.141 to 0.403 m (Intel: 0.050 either way).

    ``line_ends = "at-vertex"``: the segmentation gives the beams next to a vertex to the
    segment scanned first, so that wall's line ends on a beam or two of the next (2.5 mrad,
    4.3 mm outward on a wall 1 m away); with it both lines are refitted on their own side of
    the vertex. In the simulated corridor it takes the lines' bias out and, with the scale's
    Jacobian at the prediction, the free range scale's pull (CHANGELOG, issue 37). Off by
    default: on the relations benchmark it took Freiburg 079 from 0.039 to 0.048-0.054 m and
    the Intel bag from 0.14 to 0.30-1.9 m (experiments/README.md).
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
        0.0,
        "m",
        "landmarks farther are no association candidates",
        derive="max(max_line_range + 2, 10)",
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
        0.0, "sigma", "line fits drop end beams beyond this many robust range sigmas; 0 off"
    )
    line_ends: str = param(
        "as-segmented", "choice", "lines end as segmented, or at-vertex where two meet"
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
    loop_radius: float = param(6.0, "m", "old keyframes this near are loop candidates")
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
    line_ends: str = linked(
        "frontend.line_ends", FrontendConfig.line_ends, "choice", "where lines end"
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
    landmarks: bool = param(
        True, "bool", "features become landmarks (false: poses, motions and loops only)"
    )
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

    ``min_search_xy``, the window's floor, and ``radius``: the estimate's covariance
    understates how far it drifts between visits of a place (Intel: 0.8 m off at 2500 s with 3
    sigma below 0.3 m, every closure there "diverged"; a floor of 0.3 m / 5 deg before, Intel
    0.076 -> 0.048 m, CHANGELOG.md, issue 14; ``intel.orig.bag``'s first loop came back 2-5 m
    off with 3 sigma under 2 m, and a quarter of the closures that mended it lay beyond the
    99.9 % gate: floor 1 -> 3 m, cap 2 -> 6 m, radius 4 -> 6 m, its relations 1.82 -> 0.32 m,
    issue 34). The search's cost (the module doc): no match over less view than ``min_view`` (0:
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
    max_search_xy: float = param(6.0, "m", "search window (3 sigma) half-width, at most")
    min_search_xy: float = param(3.0, "m", "search window half-width, at least")
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
class GraphParams:
    """The factor graph's solver (:class:`fgslam.slam.graph.GraphBackend`): iSAM2's
    relinearisation, the estimate refreshes and the final convergence; ``[graph]``."""

    robust: str = param("cauchy", "choice", "landmark and merge factors' M-estimator")
    merge_sigma: float = param(0.01, "m|rad", "a merge's tie between one landmark's variables")
    relinearize_threshold: float = param(
        0.1, "m|rad", "iSAM2 relinearises variables whose step exceeds this"
    )
    relinearize_skip: int = param(10, "count", "iSAM2 updates between relinearisation checks")
    refresh_every: int = param(10, "count", "keyframes between refreshes of the whole estimate")
    loop_updates: int = param(2, "count", "extra iSAM2 updates after a loop closure")
    max_final_updates: int = param(20, "count", "final Gauss-Newton steps at most")
    converge_tol: float = param(0.01, "m|rad", "the final steps stop when none moves more")
    factorization: str = param("QR", "choice", "QR or CHOLESKY (faster, may refuse sound systems)")

    @classmethod
    def from_config(cls, cfg: RobotConfig) -> GraphParams:
        """The ``[graph]`` section of ``cfg``."""
        return cfg.graph


@dataclass(frozen=True)
class LocalizeParams:
    """Localization on a saved map (:mod:`fgslam.session.localize`; m, rad); ``[localize]``.

    A scan is matched when the robot has moved ``every_distance`` or turned ``every_angle``
    since the last matched one (a standing robot costs nothing), against the local map at
    its predicted pose (the scans of the map keyframes within ``radius``, at most
    ``max_scans``), within the matcher's window, unless less than ``min_view`` of its
    returns fall where the map's grid saw something (off the map: the odometry carries the
    pose); the last ``window``
    matched poses are smoothed with the wheel odometry between them; the pose is carried from
    scan to scan by ``motion`` (:class:`~fgslam.slam.keyframes.FusedMotion`). Lost after
    ``lost_after`` failed matches in a row, it searches near the pose the odometry carries
    on. Global localization (no initial pose, or lost for ``search_after`` m) searches around
    every place (map keyframes ``spacing`` apart) over +-``spacing`` and every heading
    (steps of ``global_step``), keeps up to ``hypotheses`` distinct answers that the grid
    does not contradict (at most ``max_see_through`` of the returns on free cells) and tracks
    them; it is localized when the best of them has passed ``confirm`` matches in a row and
    every other has failed or its mean score is ``confirm_margin`` lower."""

    spacing: float = param(2.0, "m", "between the places the global search starts from")
    radius: float = param(3.0, "m", "a local map's keyframes lie within this of its position")
    max_scans: int = param(12, "count", "map keyframes per local map, nearest per heading")
    every_distance: float = param(0.1, "m", "travel before the next scan is matched")
    every_angle: float = param(math.radians(3.0), "rad", "turn before the next scan is matched")
    window: int = param(10, "count", "matched poses smoothed together with the odometry")
    min_view: float = param(0.3, "1", "fewer returns where the map saw something: off the map")
    max_see_through: float = param(0.15, "1", "more returns on free map cells: a wrong answer")
    lost_after: int = param(8, "count", "failed matches in a row: lost")
    search_after: float = param(8.0, "m", "lost this much travel: search globally (kidnapped)")
    hypotheses: int = param(8, "count", "distinct answers of a global search tracked")
    confirm: int = param(5, "count", "matches in a row confirming a global answer")
    confirm_margin: float = param(0.1, "1", "... whose mean score beats every other's by this")
    global_step: float = param(math.radians(2.0), "rad", "heading step of the global search")
    cache_size: int = param(64, "count", "local maps kept, prepared for matching")
    motion: str = param(
        "wheels",
        "choice",
        "the motion between scans: wheels, fused (the scan odometry and the wheels by "
        "their covariances), scan (the scan odometry alone)",
    )

    def __post_init__(self) -> None:
        for name in ("spacing", "radius", "every_distance", "global_step"):
            if not getattr(self, name) > 0:
                raise ValueError(f"localize.{name} must be > 0, got {getattr(self, name)!r}")
        for name in ("max_scans", "window", "lost_after", "hypotheses", "confirm"):
            if getattr(self, name) < 1:
                raise ValueError(f"localize.{name} must be >= 1, got {getattr(self, name)!r}")
        if self.motion not in LOCALIZE_MOTION_CHOICES:
            raise ValueError(
                f"localize.motion must be one of {LOCALIZE_MOTION_CHOICES}, got {self.motion!r}"
            )

    @classmethod
    def from_config(cls, cfg: RobotConfig) -> LocalizeParams:
        """The ``[localize]`` section of ``cfg``."""
        return cfg.localize


@dataclass(frozen=True)
class RobotInfo:
    name: str = param(unit="text", doc="the robot's name")


# the components' sections of RobotConfig, in the order of the pipeline
COMPONENTS = (
    "features",
    "keyframes",
    "matcher",
    "loops",
    "association",
    "map",
    "graph",
    "localize",
)


@dataclass(frozen=True)
class RobotConfig:
    """Everything the system knows about the robot, and every parameter of every component.

    The components' sections (``features``, ``keyframes``, ``matcher``, ``loops``,
    ``association``, ``map``, ``graph``) are the components' parameter classes themselves;
    their linked fields are resolved here from the keys they name (also after
    ``dataclasses.replace``), so ``cfg.map`` is the map management's parameters as the
    configuration gives them."""

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
    graph: GraphParams = field(default_factory=GraphParams)
    localize: LocalizeParams = field(default_factory=LocalizeParams)
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
            line_ends=fe.line_ends,
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
MAP_RANGE_MARGIN = 2.0  # m: association candidates this much beyond the line range ...
MAP_RANGE_MIN = 10.0  # m: ... and at least this far (docs/readers.md, front-end thresholds)


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
    out["map_max_range"] = fe.map_max_range or max(
        out["max_line_range"] + MAP_RANGE_MARGIN, MAP_RANGE_MIN
    )
    out["residual_level"] = fe.residual_level or None
    return out
