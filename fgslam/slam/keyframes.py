"""Scan odometry and the keyframe policy (docs/design.md, 5b; beyond the paper).

Every laser scan is matched (:mod:`fgslam.scanmatch`) against the last keyframe's scan (or a
local map of the last ``local_map`` keyframes' scans in its frame), the match started from the
wheel odometry since the previous scan; that carries the pose forward between keyframes. A
scan becomes a keyframe when the robot has moved ``distance`` or turned ``angle`` since the
last keyframe, when its overlap with the keyframe's scan falls below ``min_overlap``, or when
the last keyframe tracked too few of its features in the map (the SLAM step reports that
through :meth:`ScanOdometry.map_support`). With the policy ``every-scan`` (the paper's) every
scan is a keyframe. At a keyframe the match against the previous keyframe is the scan
constraint between the two (relative pose and covariance, GTSAM's between convention), the
wheel odometry the other.

Frames: points in the robot frame (m); poses (x, y, theta) in m, rad; ``rel`` is the scan's
pose in the frame of the last keyframe.
"""

from __future__ import annotations

import dataclasses
import math
from collections import Counter, deque
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from factors.geometry import between_poses, compose_poses, transform_points
from factors.odometry import Preintegrated, relative_pose
from factors.sensor_models import time_registration_inflation
from fgslam.config import KeyframeParams
from fgslam.scanmatch import Match, MatchParams, Reference, match


@dataclass
class ScanStep:
    """What :meth:`ScanOdometry.add` decided for one scan: ``keyframe``; ``rel`` the scan's
    pose in the frame of the keyframe before it (for a keyframe: of the previous keyframe);
    ``scan`` the scan constraint from the previous keyframe (keyframes only; None when the
    match was rejected or there is none); ``match`` the raw match (None if not matched)."""

    keyframe: bool
    rel: NDArray[np.float64]
    scan: Preintegrated | None = None
    match: Match | None = None
    speed: tuple[float, float] = (0.0, 0.0)  # the robot's (m/s, rad/s) at the scan
    points: NDArray[np.float64] | None = None  # the scan's points (robot frame, m)


def timing_inflation(
    cov: NDArray[np.float64],
    speed_a: tuple[float, float],
    speed_b: tuple[float, float],
    sigma_time: float,
) -> NDArray[np.float64]:
    """A scan match's covariance (x, y, theta) with the time registration of both scans
    (docs/design.md, 3.4): (v sigma_t)^2 and (omega sigma_t)^2 of each, (v, omega) in m/s, rad/s."""
    (v0, w0), (v1, w1) = speed_a, speed_b
    return time_registration_inflation(
        cov, (False, False, True), math.hypot(v0, v1), math.hypot(w0, w1), sigma_time
    )


def _key(reason: str) -> str:
    """A rejection reason as a statistics key: its words, without the numbers in brackets."""
    return reason.split(" (")[0].strip().replace(" ", "_")


class ScanOdometry:
    """Feed scans in time order with :meth:`add` (robot-frame points and the wheel-odometry
    pose at the scan's time); see the module doc. ``stats`` counts matches, rejections and
    the reasons of keyframes."""

    def __init__(
        self,
        params: KeyframeParams,
        match_params: MatchParams,
        origin: tuple[float, float] = (0.0, 0.0),
        sigma_time: float = 0.0,
    ) -> None:
        """``origin``: the laser's position on the robot (m, robot frame), whence the
        scans' points were seen; ``sigma_time`` (s): the uncertainty of a scan's time
        (docs/design.md, 3.4), which inflates a keyframe-to-keyframe match by the robot's motion at
        both scans."""
        self.p = params
        # ambiguous matches are rejected here too: kept with their covariance (the wheels to
        # fill in) they took Intel from 0.23 to 1.8 m (CHANGELOG.md, issue 14)
        self.mp = dataclasses.replace(
            match_params, min_score=params.match_min_score, min_overlap=params.match_min_overlap
        )
        self.origin = origin
        self.sigma_time = sigma_time
        self._ref_speed = (0.0, 0.0)
        self.stats: Counter = Counter()
        self._ref: Reference | None = None
        self._rel = np.zeros(3)  # the last scan's pose in the keyframe's frame
        self._odom_prev: NDArray[np.float64] | None = None
        self._motion = np.zeros(3)  # the last scan-to-scan motion (robot frame)
        self._low_support = False
        self._started = False
        self._chain = np.zeros(3)  # the keyframe's pose along the scan-odometry chain
        self._recent: deque = deque(maxlen=params.local_map)  # (chain pose, points)

    def map_support(self, features: int, tracked: int) -> None:
        """How many features the last keyframe had and how many of them went to landmarks
        already in the map."""
        self._low_support = features >= self.p.min_features and tracked < self.p.min_tracked

    def add(
        self,
        points: NDArray[np.float64] | None,
        odom: NDArray[np.float64],
        speed: tuple[float, float] = (0.0, 0.0),
    ) -> ScanStep:
        """One scan: its points (N, 2, robot frame; None or empty: no laser), the wheel
        odometry pose at its time (odometry frame) and the robot's (speed m/s, turn rate
        rad/s) then."""
        odom = np.asarray(odom, dtype=float)
        wheel = np.zeros(3) if self._odom_prev is None else between_poses(self._odom_prev, odom)
        self._odom_prev = odom
        first = not self._started
        self._started = True
        guess = compose_poses(self._rel, wheel)
        m = None
        usable = points is not None and len(points) > 0
        if self.p.matching and usable and self._ref is not None:
            m = match(self._ref, points, guess, self.mp)
            self.stats["scan_matches"] += 1
            if not m.ok and self.p.retry_window > 1 and not m.reason.startswith("ambiguous"):
                # the wheels may be off by more than the window (a slip, a coarse log)
                wide = dataclasses.replace(
                    self.mp,
                    search_xy=self.mp.search_xy * self.p.retry_window,
                    search_theta=self.mp.search_theta * self.p.retry_window,
                )
                m2 = match(self._ref, points, guess, wide)
                self.stats["scan_matches_retried"] += 1
                if m2.ok:
                    m = m2
                    self.stats["scan_matches_recovered"] += 1
            if not m.ok:
                # the wheels may have frozen and caught up (logs do): the motion of the last
                # scan carried on is the other guess (its match passes every check itself)
                steady = compose_poses(self._rel, self._motion)
                if np.abs(between_poses(guess, steady)).max() > 0.5 * self.mp.resolution:
                    m2 = match(self._ref, points, steady, self.mp)
                    self.stats["scan_matches_steady_guess"] += 1
                    if m2.ok:
                        m = m2
                        self.stats["scan_matches_recovered"] += 1
            if m.ok:
                guess = np.asarray(m.pose, dtype=float)
            else:
                self.stats["scan_matches_rejected"] += 1
                self.stats[f"scan_rejected_{_key(m.reason)}"] += 1
        self._motion = between_poses(self._rel, guess)
        self._rel = guess
        reason = self._keyframe_reason(first, m)
        if reason is None:
            return ScanStep(False, guess.copy(), None, m, speed, points)
        self.stats[f"keyframes_{reason}"] += 1
        scan = None
        if m is not None and m.ok:
            cov = timing_inflation(m.cov, self._ref_speed, speed, self.sigma_time)
            scan = relative_pose(m.pose, cov)
        self._ref_speed = speed
        self._ref = None
        self._chain = compose_poses(self._chain, guess)
        if usable:
            self._recent.append((self._chain, points))
        if self.p.matching and self._recent:
            self._ref = self._local_map()
        self._rel = np.zeros(3)
        self._low_support = False
        return ScanStep(True, guess.copy(), scan, m, speed, points)

    def _local_map(self) -> Reference:
        """The last ``local_map`` keyframes' points in the newest keyframe's frame, placed by
        the scan-odometry chain, with the laser position each was seen from."""
        here = self._chain
        pts, origins = [], []
        o = np.array([[self.origin[0], self.origin[1]]])
        for pose, p in self._recent:
            rel = between_poses(here, pose)
            pts.append(transform_points(rel, p))
            origins.append(np.repeat(transform_points(rel, o), len(p), axis=0))
        if len(pts) == 1:
            return Reference.build(pts[0], self.mp, self.origin)
        return Reference.build(np.vstack(pts), self.mp, np.vstack(origins))

    def _keyframe_reason(self, first: bool, m: Match | None) -> str | None:
        p = self.p
        if first:
            return "first"
        if p.policy == "every-scan":
            return "every_scan"
        if self._ref is None:
            return "no_reference"
        if self._low_support:
            return "map_support"
        if math.hypot(self._rel[0], self._rel[1]) >= p.distance:
            return "distance"
        if abs(self._rel[2]) >= p.angle:
            return "angle"
        if m is not None and (not m.ok or m.overlap < p.min_overlap):
            return "overlap"
        return None
