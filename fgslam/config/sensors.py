"""The robot's sensors and drive as configuration sections: mounts, ``[odometry]``,
``[laser]``, ``[sonar]`` (SI units; ``_deg`` keys in degrees with radian properties)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import gtsam

from fgslam.config.fields import _meta, param


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

    def wheel_travel(self, ticks_right: float, ticks_left: float) -> tuple[float, float]:
        """The right and left wheels' travel (m) of an odometry sample's encoder ticks."""
        return ticks_right * self.metres_per_tick_right, ticks_left * self.metres_per_tick_left


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
    # how a scan's time error (sigma_time) is modelled (docs/design.md, 3.4): "per-feature"
    # (each laser feature's covariance inflated on its own, the paper's way) or "per-scan"
    # (once per scan: the graph's keyframe poses are the robot's at the scans' true times,
    # tied to its poses at the stamps, which the wheel odometry links; the EKF, which has no
    # such pose, inflates the features itself)
    time_registration: str = param(
        "per-feature", "choice", "a scan's time error: per-feature or per-scan"
    )

    def time_sigma(self, model: str) -> float:
        """``sigma_time`` (s) where the time error is modelled as ``model`` (one of
        ``time_registration``'s choices) and that is the configured one, else 0."""
        return self.sigma_time if model == self.time_registration else 0.0

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
