"""What the front end produces: features with covariances, per scan (robot frame, m, rad)."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np
from numpy.typing import NDArray

from fgslam.events import SonarReading


class End(StrEnum):
    """Why a line segment started or ended (paper III-A). The next segment's start condition
    is the previous segment's end condition."""

    DISCONTINUITY = "discontinuity"  # a range jump in the scan
    SPREAD = "spread"  # std of point-to-line distances above the threshold
    OUTLIERS = "outliers"  # the next 3 points all beyond the range-model threshold
    MAX_RANGE = "max_range"  # a point beyond the maximum line range (or no return)
    FIELD_OF_VIEW = "field_of_view"  # the end of the 180 deg scan
    SONAR = "sonar"  # a sonar cluster with corners or edges close by

    @property
    def reliable(self) -> bool:
        """The object really ends here (the map moves its endpoint a big step)."""
        return self in (End.SONAR, End.DISCONTINUITY)


# the range error sources a feature's Jc is taken against, in its column order: a laser range
# reads r (1 + laser_scale) + laser_offset, a sonar range r (1 + sound)
SOURCES = ("laser_offset", "laser_scale", "sound")


@dataclass(frozen=True)
class OwnTime:
    """A sonar feature's measurement from the robot at the reading's own time ``t`` (s):
    ``z`` and ``cov`` like :attr:`Feature.z`, in the robot frame then, not moved by odometry
    into the scan's frame (docs/design.md, 6; used by the graph backends with ``[sonar] timing =
    "own-time"``)."""

    t: float
    z: NDArray[np.float64]
    cov: NDArray[np.float64]
    Jc: NDArray[np.float64] | None = field(default=None, repr=False)  # as Feature.Jc


@dataclass
class Feature:
    """One measured feature in the robot frame at the scan's time.

    kind ``line``: z = (alpha, d), d >= 0; ``corner``: z = (phi_c, r_c, gamma) with gamma the
    bisector pointing into free space, or (phi_c, r_c) for a sonar-only corner; ``point``:
    z = (bearing, range). ``cov`` is ordered like z. ``endpoints`` (2, 2) for lines (first
    and last point projected on the line, in scan order) and corners (the ends of both arms).
    ``support`` counts laser points and sonar readings; ``sources`` says which sensors
    measured z ("laser", "sonar" or "fused"). ``own``: a sonar-only point or plane feature's
    measurement at the reading's own time (None for the others). ``Jc`` (len(z), 3): dz / d
    (:data:`SOURCES`: laser range offset in m, laser range scale in m per m, relative error
    of the speed of sound), through the fit, the fusion and the mount (None: no range in z);
    where the laser's calibration is estimated (:mod:`fgslam.slam.calibration`) ``cov``
    leaves out the fits' worst-case systematic term.
    """

    kind: str
    z: NDArray[np.float64]
    cov: NDArray[np.float64]
    source: str = "laser"
    endpoints: NDArray[np.float64] | None = None
    start: End | None = None
    end: End | None = None
    convex: bool = False
    laser_support: int = 0
    sonar_support: int = 0
    sonar_readings: tuple[SonarReading, ...] = field(default=(), repr=False)
    own: OwnTime | None = field(default=None, repr=False)
    Jc: NDArray[np.float64] | None = field(default=None, repr=False)


@dataclass
class ScanFeatures:
    """The front end's output for one laser scan (or one sonar-only step) at time ``t``."""

    t: float
    features: list[Feature]
    stats: Counter = field(default_factory=Counter)
    # the scan's valid returns as points (N, 2) in the robot frame, m (None: no laser)
    points: NDArray[np.float64] | None = field(default=None, repr=False)
    # the wheel-odometry pose (x, y, theta) at ``t`` in the odometry frame, m, rad
    odom: NDArray[np.float64] | None = field(default=None, repr=False)

    def count(self, kind: str) -> int:
        return sum(f.kind == kind for f in self.features)
