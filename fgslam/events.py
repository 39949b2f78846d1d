"""Timestamped events: what every source (simulator, log file, devices) produces and every
consumer (front end, backends, evaluation) reads. Times in s, lengths in m, angles in rad.

Frames: odometry is wheel motion; a laser scan is in the laser frame (REP-103, beam bearings
from the robot configuration); a sonar echo's bearing is in the transducer frame, whose pose in
the robot frame is the array's mount rotated by the pan angle; truth is the robot's world pose.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

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

    ``ranges`` (m) has one entry per beam of the configured laser, first beam at -fov/2;
    NaN means no usable return (beyond maximum range, dazzled, invalid).
    """

    t: float
    ranges: np.ndarray = field(repr=False)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, LaserScan):
            return NotImplemented
        return self.t == other.t and np.array_equal(self.ranges, other.ranges, equal_nan=True)

    __hash__ = None  # type: ignore[assignment]


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
