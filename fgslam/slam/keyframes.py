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
import itertools
import math
from collections import Counter, deque
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.stats import chi2

from factors.geometry import between_poses, compose_poses, transform_points
from factors.odometry import (
    Preintegrated,
    fuse_motions,
    link_motions,
    preintegrate,
    relative_pose,
)
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

    @property
    def pose(self) -> NDArray[np.float64]:
        """The last scan's pose along the scan-odometry chain (the frame of the first scan;
        m, rad): the chain of keyframes composed with the scan's pose in the last one."""
        return compose_poses(self._chain, self._rel)

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


class FusedMotion:
    """The robot's motion from scan to scan, for a tracker that keeps no graph (the
    localizer): between the scan odometry's keyframes its match to the last (the wheels where
    that failed), and at each keyframe the wheels since the last fused with its scan match
    (:func:`factors.odometry.fuse_motions`; the scan match alone where the two disagree
    beyond ``motion_gate_p``, as the EKF commits: :func:`factors.odometry.link_motions`).
    Each source weighs by its covariance: along a bare corridor, where the match is
    ambiguous, the wheels; in a fast turn, where the wheels slip, the match. Feed wheel
    samples (:meth:`sample`) and scans (:meth:`add`) in time order; :attr:`pose` is the last
    scan's pose in the frame of the first (m, rad)."""

    def __init__(
        self, odometry: ScanOdometry, odo_params, motion_gate_p: float, fuse: bool = True
    ) -> None:
        """``fuse`` False: the scan odometry alone (:attr:`ScanOdometry.pose`; the wheels
        only where its matches failed)."""
        self.scan = odometry
        self.fuse = fuse
        self._params = odo_params
        self._gate = float(chi2.ppf(motion_gate_p, 3))
        self._samples: deque[tuple[float, float, float]] = deque()
        self._last_sample_t: float | None = None
        self._kf_t: float | None = None
        self._kf_pose = np.zeros(3)  # the last keyframe's fused pose
        self.pose = np.zeros(3)
        self.stats: Counter = Counter()

    def sample(self, t: float, right: float, left: float) -> None:
        """One wheel odometry sample: time (s), wheel travel right and left (m)."""
        self._samples.append((t, right, left))

    def add(
        self, t: float, points, odom: NDArray[np.float64], speed: tuple[float, float]
    ) -> NDArray[np.float64]:
        """One scan at ``t`` (robot-frame points, the wheel odometry pose, the speed); returns
        its pose (:attr:`pose`)."""
        step = self.scan.add(points, np.asarray(odom, dtype=float), speed)
        if not self.fuse:
            self.pose = self.scan.pose
            return self.pose
        m = step.match
        scan = step.scan
        if not step.keyframe and m is not None and m.ok:
            scan = relative_pose(m.pose, m.cov)
        due = list(itertools.takewhile(lambda s: s[0] <= t, self._samples))
        n = len(due)
        ts, lr, ll = (list(c) for c in zip(*due, strict=True)) if due else ([], [], [])
        if self._kf_t is None:  # the first scan
            rel = np.zeros(3)
        else:
            pre = preintegrate(lr, ll, self._params, ts, (self._kf_t, t), self._last_sample_t)
            motion = pre
            if scan is not None:
                wheels, scan = link_motions(pre, scan, self._gate)
                self.stats["motion_disagreements"] += wheels is None
                motion = scan if wheels is None else fuse_motions(wheels, scan)
            d = motion.delta
            rel = np.array([d.x(), d.y(), d.theta()])
        self.pose = compose_poses(self._kf_pose, rel)
        if step.keyframe or self._kf_t is None:
            for _ in range(n):
                self._samples.popleft()
            if ts:
                self._last_sample_t = ts[-1]
            self._kf_t, self._kf_pose = t, self.pose.copy()
        return self.pose
