"""One SLAM step: the per-keyframe protocol, the same for every backend and every caller (the
event pipeline :class:`fgslam.slam.runner.SlamPipeline`, hence ``fgslam online``, and the
point-landmark path :mod:`fgslam.slam.pointslam`).

Per keyframe: predict (or start; wheel odometry and/or a scan match); apply the duplicate
merges found after the last keyframe; associate (:mod:`fgslam.slam.association`, with the
backend's fresh estimate); merge the map lines a measurement covers; observe; fuse the
unassociated features into tentative landmarks and add the ones confirmed now
(:mod:`fgslam.slam.lifecycle`); commit; update the segment geometry
(:mod:`fgslam.slam.geometry`, world coordinates) with the updated estimate; look for
duplicates among the landmarks seen; count misses of landmarks predicted in view. With a
:class:`fgslam.slam.loops.LoopCloser` and a backend that keeps past poses, verified loop
closures of the keyframe's scan enter before the commit.
"""

from __future__ import annotations

import time
from collections import Counter

import numpy as np
from numpy.typing import NDArray

from factors.odometry import Preintegrated, relative_pose
from fgslam.config.robot import MapParams
from fgslam.frontend.features import Feature
from fgslam.slam import geometry
from fgslam.slam.association import associate
from fgslam.slam.backend import Backend
from fgslam.slam.lifecycle import CONFIRMED, Lifecycle
from fgslam.slam.loops import LoopCloser


class SlamStep:
    """One backend and its map, fed keyframes (see module doc). ``stats`` counts decisions;
    ``latencies``, ``filtered`` (the pose estimate after each keyframe) and
    ``landmark_counts`` (active landmarks after each keyframe) grow by one per keyframe."""

    def __init__(
        self,
        backend: Backend,
        params: MapParams | None = None,
        loops: LoopCloser | None = None,
    ) -> None:
        self.be = backend
        self.loops = loops if backend.supports_loops else None
        # how many of the last keyframe's features went to landmarks (confirmed or tentative)
        # older than that keyframe: how well the map tracks the scan
        self.tracked = 0
        self.p = params or MapParams()
        self.assoc = self.p.association_params()
        self.map = Lifecycle(self.p)
        self.stats: Counter = Counter()
        self.latencies: list[float] = []
        self.filtered: list[NDArray[np.float64]] = []
        self.landmark_counts: list[int] = []
        self.started = False
        self.wall = 0.0
        self.k = -1
        self._start_cov = np.eye(3) * 1e-8
        self._pending_merges: list[tuple[int, int]] = []
        self._given: dict[int, int] = {}  # given association: the caller's id -> ours

    @property
    def landmarks(self):
        return self.map.landmarks

    def restore(
        self,
        times: NDArray[np.float64],
        poses: NDArray[np.float64],
        scans: list[NDArray[np.float64] | None],
        links: list[Preintegrated],
        loops: list[tuple[int, int, Preintegrated]],
    ) -> None:
        """Start from saved keyframes instead of a first pose (a continued session;
        :meth:`Backend.restore`): the backend holds them, the loop closer their scans
        (robot frame) at their poses (world); the next keyframe is number ``len(times)``."""
        self.be.restore(times, poses, links, loops, self._start_cov)
        if self.loops is not None:
            for i, (pose, points) in enumerate(zip(poses, scans, strict=True)):
                self.loops.add_keyframe(i, points, pose, (0.0, 0.0))
        self.started = True
        self.k = self.map.k = len(times) - 1

    def keyframe(
        self,
        t: float,
        features: list[Feature],
        pre: Preintegrated | None,
        pose0: NDArray[np.float64] | None = None,
        given: list[int] | None = None,
        scan: Preintegrated | None = None,
        points: NDArray[np.float64] | None = None,
        speed: tuple[float, float] = (0.0, 0.0),
        anchor: tuple[int, Preintegrated] | None = None,
    ) -> list[int | None]:
        """Process one keyframe at time ``t`` (the first: ``pose0``, world; later: ``pre``, the
        odometry since the last one, and/or ``scan``, the scan match from the last keyframe).
        ``given``: the caller's landmark id per feature (data association given, e.g.
        Victoria Park's file), skipping association and lifecycle. ``points``: the keyframe's
        laser scan (robot frame) for loop closures, ``speed`` the robot's (m/s, rad/s) then.
        ``anchor``: (j, relative pose from keyframe j): this keyframe linked to the
        restored keyframe j (:meth:`restore`) by that alone, not to the last one; no loop
        search at it.
        Returns the landmark id each feature went to (None: not used). Raises the backend's
        error (e.g. :class:`fgslam.slam.graph.BackendError`) unchanged."""
        t0 = time.perf_counter()
        be, lc = self.be, self.map
        n_features = len(features)
        if not self.p.landmarks:  # scan matching and loop closures alone
            features, given = [], None if given is None else []
        self.k += 1
        lc.k = self.k
        if not self.started:
            be.start(t, np.zeros(3) if pose0 is None else pose0, self._start_cov, twist=speed)
            self.started = True
        elif anchor is not None:
            be.predict(t, None, anchor[1], origin=anchor[0], twist=speed)
        else:
            be.predict(t, pre, scan, twist=speed)
        features = be.time_registered(features, speed)
        for keep, drop in self._pending_merges:
            keep, drop = lc.resolve(keep), lc.resolve(drop)
            if keep != drop:
                be.merge(keep, drop)
                self._merge_geometry(keep, drop, be.means())
                lc.merge(keep, drop)
        self._pending_merges = []
        pose = be.pose()
        self._compatible: set[int] = set()
        known = set(lc.landmarks)
        if given is not None:
            where = self._keyframe_given(t, features, given)
        else:
            where = self._keyframe_own(t, features, pose)
        if self.loops is not None:
            self.loops.add_keyframe(self.k, points, pose, speed)
            if self.k > 0 and anchor is None:
                for c in self.loops.try_close(self.k, be, pose):
                    be.add_loop(c.j, c.k, relative_pose(c.pose, c.cov))
        be.commit()
        for lid in be.take_removed():  # a repaired graph dropped them
            lc.remove(lid)
        means = be.means()
        pose = be.pose()
        seen: set[int] = set()
        for f, lid in zip(features, where, strict=True):
            if lid is None:
                continue
            lid = lc.resolve(lid)  # a landmark merged away in this scan: credit the kept one
            lm = lc.landmarks[lid]
            lm.observations[f.source] += 1
            lm.sonar_readings += f.sonar_support
            if lm.active:
                seen.add(lid)
                self._update_geometry(lid, f, pose, means.get(lid))
            else:  # tentative: geometry on its own estimate
                self._update_geometry(lid, f, pose, lm.mean)
        self.tracked = sum(1 for lid in where if lid is not None and lid in known)
        if given is None:
            lc.expire(self.k)
            query = seen | {lc.resolve(i) for i in self._compatible}
            if self.p.duplicate_p > 0 and query:
                self._pending_merges = lc.duplicates(sorted(query), means, be.estimate)
            lc.visibility(pose, means, seen)
            self.stats.update(lc.stats)
            lc.stats.clear()
        self.filtered.append(be.pose())
        self.landmark_counts.append(sum(1 for lm in lc.landmarks.values() if lm.active))
        dt = time.perf_counter() - t0
        self.latencies.append(dt)
        self.wall += dt
        return where if self.p.landmarks else [None] * n_features

    # ------------------------------------------------------------------ decisions

    def _keyframe_given(self, t: float, features, given: list[int]) -> list[int | None]:
        be, lc = self.be, self.map
        where: list[int | None] = []
        for f, g in zip(features, given, strict=True):
            lid = self._given.get(g)
            if lid is None:
                lid = self._given[g] = lc.new_id(t, f, CONFIRMED)
                be.add_landmark(lid, f)
                self.stats[f"{f.kind}s_new"] += 1
            else:
                be.observe(lid, f)
                self.stats[f"{f.kind}s_associated"] += 1
            where.append(lid)
        return where

    def _keyframe_own(self, t: float, features, pose) -> list[int | None]:
        be, lc, p = self.be, self.map, self.p
        means = be.means()
        # the features as association and the tentative map weigh them (Backend.for_association)
        weighed = [be.for_association(f) for f in features]
        a = associate(weighed, pose, lc.candidates(pose, means), means, be.estimate, self.assoc)
        self.stats.update(a.stats)
        self._compatible = a.compatible
        # line merges decided by a measurement covering two map lines (paper IV)
        for group in a.merges:
            group = sorted({lc.resolve(g) for g in group}, key=lambda i: lc.landmarks[i].created)
            for drop in group[1:]:
                be.merge(group[0], drop)
                self._merge_geometry(group[0], drop, means)
                lc.merge(group[0], drop)
                self.stats["line_merges"] += 1
        where: list[int | None] = [None] * len(features)
        for i, (f, lid) in enumerate(zip(features, a.pairs, strict=True)):
            if lid is None:
                continue
            lid = lc.resolve(lid)
            be.observe(lid, f)
            where[i] = lid
            self.stats[f"{f.kind}s_associated"] += 1
        Pxx = a.pose_cov
        for i, f in enumerate(features):
            if where[i] is not None or a.ambiguous[i]:
                continue
            if f.kind == "line" and f.endpoints is not None:
                length = float(np.hypot(*(f.endpoints[1] - f.endpoints[0])))
                if length < p.min_line_length:
                    self.stats["lines_too_short"] += 1
                    continue
            if f.kind == "corner" and len(f.z) != 3:
                continue  # a sonar-only corner cannot start a corner landmark
            if Pxx is None:
                Pxx = self._pose_cov()
            lid, confirmed = lc.sight_tentative(t, self.k, weighed[i], pose, Pxx)
            where[i] = lid
            if confirmed:
                lc.confirm(lid)
                be.add_landmark(lid, f)
                self.stats[f"{f.kind}s_new"] += 1
        return where

    def _pose_cov(self) -> NDArray[np.float64]:
        if self.k == 0:
            return self._start_cov
        return self.be.estimate([])[1][:3, :3]

    # ------------------------------------------------------------------ geometry

    def _update_geometry(self, lid: int, f: Feature, pose, m) -> None:
        if m is None:
            return
        lm = self.map.landmarks[lid]
        if lm.kind == "line":
            lm.ends = geometry.update_line_ends(
                None if lm.ends is None else geometry.reproject(m, lm.ends),
                m,
                f,
                pose,
                self.p.big_step,
                self.p.small_step,
            )
            lm.line = np.array(m, dtype=float)
        elif lm.kind == "corner" and f.endpoints is not None:
            w = geometry.to_world(pose, f.endpoints)
            lm.arms = w if lm.arms is None else lm.arms + self.p.small_step * (w - lm.arms)

    def _merge_geometry(self, keep: int, drop: int, means) -> None:
        a, b = self.map.landmarks[keep], self.map.landmarks[drop]
        if a.kind == "line" and keep in means:
            a.ends = geometry.union(means[keep], a.ends, b.ends)
            a.line = np.array(means[keep], dtype=float)
