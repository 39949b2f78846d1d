"""Timestamped events: what every source (simulator, log file, devices) produces and every
consumer (front end, backends, evaluation) reads. Times in s, lengths in m, angles in rad.

Frames: odometry is wheel motion; a laser scan is in the laser frame (REP-103, beam bearings
from the robot configuration, or the scan's own: :func:`scan_bearings`); a sonar echo's
bearing is in the transducer frame, whose pose in the robot frame is the array's mount rotated
by the pan angle; truth is the robot's world pose.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from fgslam.config import LaserConfig

SONAR_KINDS = ("plane", "corner", "edge")


@dataclass(frozen=True, slots=True)
class OdometryEvent:
    """Encoder tick increments of the right and left wheels over the sample ending at ``t``."""

    t: float
    ticks_right: int
    ticks_left: int


@dataclass(frozen=True, slots=True)
class LaserScan:
    """One laser scan stamped at host time ``t`` (late by the transmission delay).

    ``ranges`` (m): one entry per beam; NaN means no usable return (beyond maximum range,
    dazzled, invalid). ``bearings``: the scan's own beam bearings (rad, laser frame, strictly
    increasing, evenly spaced as a laser gives them, one per range) where its geometry differs
    from the configured laser's (a scanner that interlaces its scans, another beam count);
    None: the configured laser's, ``cfg.laser.bearings`` (n_beams beams, first at -fov/2).
    Use :func:`scan_bearings` for the bearings of a scan.
    """

    t: float
    ranges: np.ndarray = field(repr=False)
    bearings: np.ndarray | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        if self.bearings is None:
            return
        b = np.asarray(self.bearings, dtype=float)
        if b.ndim != 1 or b.size != np.size(self.ranges):
            raise ValueError(
                f"a scan's bearings must be 1-D, one per range: {b.shape} for "
                f"{np.size(self.ranges)} ranges"
            )
        if not (np.isfinite(b).all() and (np.diff(b) > 0).all()):
            raise ValueError("a scan's bearings must be finite and strictly increasing")

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, LaserScan):
            return NotImplemented
        if (self.bearings is None) != (other.bearings is None):
            return False
        return (
            self.t == other.t
            and np.array_equal(self.ranges, other.ranges, equal_nan=True)
            and (self.bearings is None or np.array_equal(self.bearings, other.bearings))
        )

    __hash__ = None  # type: ignore[assignment]


# A scan's own bearings within this of the configured laser's (rad, every beam) are the
# configured ones: far below a beam's width, above float32 angles' rounding (ROS messages)
BEARING_TOLERANCE = 1e-5


def scan_bearings(scan: LaserScan, laser: LaserConfig) -> np.ndarray:
    """The beam bearings of ``scan`` (rad, laser frame, one per range): its own, else those of
    the configured ``laser`` (ValueError when the scan then has another beam count)."""
    if scan.bearings is not None:
        return np.asarray(scan.bearings, dtype=float)
    if np.size(scan.ranges) != laser.n_beams:
        raise ValueError(
            f"a scan of {np.size(scan.ranges)} ranges without its own bearings; the "
            f"configured laser has {laser.n_beams} beams"
        )
    return laser.bearings


def own_bearings(bearings: np.ndarray, laser: LaserConfig) -> np.ndarray | None:
    """``bearings`` (rad, laser frame) as a scan's own, read-only: None when they are the
    configured ``laser``'s within :data:`BEARING_TOLERANCE` (the scan then uses those)."""
    b = np.array(bearings, dtype=float)
    if b.size == laser.n_beams and np.abs(b - laser.bearings).max(initial=0.0) <= BEARING_TOLERANCE:
        return None
    b.flags.writeable = False
    return b


@dataclass(frozen=True, slots=True)
class SonarEcho:
    """One classified echo: kind in ``SONAR_KINDS``, range (m), bearing in the transducer frame."""

    kind: str
    range: float
    bearing: float


@dataclass(frozen=True, slots=True)
class SonarReading:
    """One measurement cycle of sonar array ``array`` (its index in the robot configuration)
    at pan angle ``pan`` (rad, about the array's mount), with zero or more echoes."""

    t: float
    array: int
    pan: float
    echoes: tuple[SonarEcho, ...]


@dataclass(frozen=True, slots=True)
class TruthPose:
    """Ground-truth world pose of the robot at time ``t`` (simulator logs only)."""

    t: float
    x: float
    y: float
    theta: float


Event = OdometryEvent | LaserScan | SonarReading | TruthPose
