"""Map management shared by every backend (paper IV, DESIGN 5).

Association by a chi-square validation gate on the innovation (with the joint covariance of
pose and landmark that the backend provides) and, for lines, the overlap of segments; merging
of two map lines when a measurement covers at least 40 cm of both; endpoint updates by the end
conditions; new landmarks (lines only when longer than 70 cm). World frame, m, rad.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from fgslam.frontend.features import End, Feature
from fgslam.slam import models

CHI2_99 = {2: 9.21, 3: 11.34}
CHI2_9999 = {2: 18.42, 3: 21.11}


@dataclass(frozen=True)
class MapParams:
    """Map management thresholds (m)."""

    min_line_length: float = 0.7  # only longer lines enter the map
    merge_overlap: float = 0.4  # a measurement covering this much of two lines merges them
    max_gap: float = 0.5  # a line measurement may extend a map line by leaving this gap
    big_step: float = 0.5  # endpoint moved this fraction toward a reliable measured end
    small_step: float = 0.1  # ... toward an unreliable one
    max_range: float = 10.0  # landmarks farther than this are not association candidates
    sonar_line_gap: float = 1.0  # a sonar plane's foot point within this of a map line
    # residuals beyond these (rad or m, per component) cannot pass any sensible gate
    pregate: tuple[float, float, float] = (0.35, 1.0, 0.6)


@dataclass
class Landmark:
    """A map landmark: its kind, line extent along the line (s0, s1) or corner arms, and
    counts of the observations by source and of supporting sonar readings."""

    id: int
    kind: str
    created: float
    extent: NDArray[np.float64] | None = None  # lines: (s0, s1) along (-sin a, cos a)
    arms: NDArray[np.float64] | None = None  # corners: the arm ends (2, 2), world
    observations: Counter = field(default_factory=Counter)  # laser / sonar / fused
    sonar_readings: int = 0
    convex: bool = False
    merged_into: int | None = None

    @property
    def active(self) -> bool:
        return self.merged_into is None


@dataclass
class Decisions:
    """What to do with one scan's features."""

    observe: list[tuple[int, Feature]] = field(default_factory=list)
    new: list[tuple[int, Feature]] = field(default_factory=list)
    merge: list[tuple[int, int]] = field(default_factory=list)  # (keep, drop)
    stats: Counter = field(default_factory=Counter)


def line_frame(lm: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Foot point of a world line and its unit direction."""
    a, d = lm
    n = np.array([math.cos(a), math.sin(a)])
    return d * n, np.array([-n[1], n[0]])


def line_endpoints(lm: NDArray[np.float64], extent: NDArray[np.float64]) -> NDArray[np.float64]:
    foot, u = line_frame(lm)
    return np.array([foot + extent[0] * u, foot + extent[1] * u])


def _to_world_points(pose: NDArray[np.float64], pts: NDArray[np.float64]) -> NDArray[np.float64]:
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return np.column_stack(
        [pose[0] + c * pts[:, 0] - s * pts[:, 1], pose[1] + s * pts[:, 0] + c * pts[:, 1]]
    )


# A backend's view of the estimate: means of the landmarks and the joint covariance of
# [pose, landmark ids...] in world coordinates (pose x, y, theta first).
EstimateFn = Callable[[list[int]], tuple[dict[int, NDArray[np.float64]], NDArray[np.float64]]]


class MapManager:
    """Associates features with landmarks, decides merges and new landmarks, keeps extents."""

    def __init__(self, params: MapParams | None = None) -> None:
        self.p = params or MapParams()
        self.landmarks: dict[int, Landmark] = {}
        self._next = 0

    def resolve(self, lid: int) -> int:
        while self.landmarks[lid].merged_into is not None:
            lid = self.landmarks[lid].merged_into  # type: ignore[assignment]
        return lid

    # -------------------------------------------------------------- association

    def _candidates(self, pose, means_hint: dict[int, NDArray[np.float64]]) -> list[int]:
        """Active landmarks within ``max_range`` of the robot (lines: of their segment)."""
        ids = [lid for lid, lm in self.landmarks.items() if lm.active and lid in means_hint]
        if not ids:
            return []
        ends = np.empty((len(ids), 4))  # segment ends a, b (a point: a = b)
        for i, lid in enumerate(ids):
            lm, m = self.landmarks[lid], means_hint[lid]
            if lm.kind == "line":
                c, s = math.cos(m[0]), math.sin(m[0])
                e0, e1 = lm.extent if lm.extent is not None else (0.0, 0.0)
                fx, fy = m[1] * c, m[1] * s
                ends[i] = (fx - e0 * s, fy + e0 * c, fx - e1 * s, fy + e1 * c)
            else:
                ends[i] = (m[0], m[1], m[0], m[1])
        A, ab = ends[:, :2], ends[:, 2:] - ends[:, :2]
        t = np.clip(
            np.sum((pose[:2] - A) * ab, axis=1) / np.maximum(np.sum(ab * ab, axis=1), 1e-12), 0, 1
        )
        d = np.hypot(*(pose[:2] - A - t[:, None] * ab).T)
        return [lid for lid, di in zip(ids, d, strict=True) if di < self.p.max_range]

    def associate(
        self,
        t: float,
        features: list[Feature],
        pose: NDArray[np.float64],
        means_hint: dict[int, NDArray[np.float64]],
        estimate: EstimateFn,
    ) -> Decisions:
        """Decide, for the features of the scan at time t seen from ``pose`` (world), which
        landmark each observes, which are new, and which map lines merge."""
        dec = Decisions()
        cands = self._candidates(pose, means_hint)
        # cheap pre-gate on the residual alone, so that the joint covariance is asked for the
        # few landmarks that may match (the backend's covariance query is the costly part)
        pre: list[
            list[tuple[int, NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]]
        ] = []
        needed: set[int] = set()
        by_kind: dict[str, tuple[list[int], NDArray[np.float64]]] = {}
        for kind in {f.kind for f in features}:
            lids = [lid for lid in cands if self.landmarks[lid].kind == kind]
            by_kind[kind] = (lids, np.array([means_hint[lid] for lid in lids]))
        for f in features:
            rows = []
            lids, M = by_kind[f.kind]
            if lids:
                E = models.residuals(f.kind, pose, M, f.z)
                ok = np.all(np.abs(E) < self.p.pregate[: len(f.z)], axis=1)
                for i in np.flatnonzero(ok):
                    lid = lids[i]
                    e, Hx, Hl = models.residual(f.kind, pose, means_hint[lid], f.z)
                    rows.append((lid, e, Hx, Hl))
                    needed.add(lid)
            pre.append(rows)
        ids = sorted(needed)
        means, P = estimate(ids) if ids else ({}, np.zeros((3, 3)))
        offs, o = {}, 3
        for lid in ids:
            offs[lid] = o
            o += models.DIM[self.landmarks[lid].kind]
        Pxx = P[:3, :3]
        for f, rows in zip(features, pre, strict=True):
            dim = len(f.z)
            gate, amb = CHI2_99[dim], CHI2_9999[dim]
            hits: list[tuple[float, int, float]] = []  # (d2, lid, overlap)
            near_miss = False
            for lid, e, Hx, Hl in rows:
                lm = self.landmarks[lid]
                if lm.merged_into is not None:
                    continue
                m = means[lid]
                k = offs[lid]
                n = models.DIM[lm.kind]
                Pxl = P[:3, k : k + n]
                Pll = P[k : k + n, k : k + n]
                HxPxl = Hx @ Pxl @ Hl.T
                S = Hx @ Pxx @ Hx.T + Hl @ Pll @ Hl.T + HxPxl + HxPxl.T + f.cov
                try:
                    d2 = float(e @ np.linalg.solve(S, e))
                except np.linalg.LinAlgError:
                    continue
                if d2 > gate:
                    near_miss |= d2 < amb
                    continue
                overlap = math.inf
                if f.kind == "line":
                    overlap = self._overlap(f, pose, m, lm)
                    if overlap is None:
                        continue
                hits.append((d2, lid, overlap))
            if not hits:
                if near_miss:
                    dec.stats[f"{f.kind}s_ambiguous"] += 1
                    continue
                if f.kind == "line" and f.endpoints is not None:
                    length = float(np.hypot(*(f.endpoints[1] - f.endpoints[0])))
                    if length < self.p.min_line_length:
                        dec.stats["lines_too_short"] += 1
                        continue
                if f.kind == "corner" and dim != 3:
                    continue  # a sonar-only corner cannot start a corner landmark
                lid = self._new_landmark(t, f)
                dec.new.append((lid, f))
                dec.stats[f"{f.kind}s_new"] += 1
                continue
            hits.sort()
            best = hits[0][1]
            if f.kind == "line" and len(hits) > 1:
                big = [h for h in hits if h[2] >= self.p.merge_overlap]
                if len(big) >= 2:
                    keep = min((h[1] for h in big), key=lambda i: self.landmarks[i].created)
                    for h in big:
                        if h[1] != keep and self.landmarks[h[1]].active:
                            dec.merge.append((keep, h[1]))
                            self.landmarks[h[1]].merged_into = keep
                            dec.stats["line_merges"] += 1
                    best = keep
            dec.observe.append((best, f))
            dec.stats[f"{f.kind}s_associated"] += 1
        return dec

    def _overlap(self, f: Feature, pose, m, lm: Landmark) -> float | None:
        """Overlap (m) of a measured line with the map line along it; None if too far apart."""
        foot, u = line_frame(m)
        if f.endpoints is None or lm.extent is None:  # a sonar plane: its foot point
            z_pt = _to_world_points(
                pose, np.array([[f.z[1] * math.cos(f.z[0]), f.z[1] * math.sin(f.z[0])]])
            )
            s = float((z_pt[0] - foot) @ u)
            if lm.extent is None:
                return 0.0
            gap = max(lm.extent[0] - s, s - lm.extent[1], 0.0)
            return None if gap > self.p.sonar_line_gap else 0.0
        w = _to_world_points(pose, f.endpoints)
        s = np.sort((w - foot) @ u)
        ov = min(s[1], lm.extent[1]) - max(s[0], lm.extent[0])
        return None if ov < -self.p.max_gap else float(ov)

    def _new_landmark(self, t: float, f: Feature) -> int:
        lid = self._next
        self._next += 1
        self.landmarks[lid] = Landmark(lid, f.kind, t, convex=f.convex)
        return lid

    # -------------------------------------------------------------- after the update

    def update_geometry(
        self,
        dec: Decisions,
        pose: NDArray[np.float64],
        means: dict[int, NDArray[np.float64]],
    ) -> None:
        """Extents, arms and counts after the backend took the scan in (updated estimates)."""
        for keep, drop in dec.merge:
            a, b = self.landmarks[keep], self.landmarks[drop]
            if a.extent is not None and b.extent is not None and drop in means:
                ends = line_endpoints(means[drop], b.extent)
                foot, u = line_frame(means[keep])
                s = (ends - foot) @ u
                a.extent = np.array([min(a.extent[0], s.min()), max(a.extent[1], s.max())])
            a.observations.update(b.observations)
            a.sonar_readings += b.sonar_readings
        for lid, f in dec.new + dec.observe:
            lm = self.landmarks[lid]
            lm.observations[f.source] += 1
            lm.sonar_readings += f.sonar_support
            if lid not in means:
                continue
            m = means[lid]
            if lm.kind == "line":
                self._update_extent(lm, f, pose, m)
            elif lm.kind == "corner" and f.endpoints is not None:
                w = _to_world_points(pose, f.endpoints)
                lm.arms = w if lm.arms is None else lm.arms + self.p.small_step * (w - lm.arms)

    def _update_extent(self, lm: Landmark, f: Feature, pose, m) -> None:
        foot, u = line_frame(m)
        if f.endpoints is None:  # sonar plane: the foot point of its normal
            z = f.z
            w = _to_world_points(pose, np.array([[z[1] * math.cos(z[0]), z[1] * math.sin(z[0])]]))
            s = float((w[0] - foot) @ u)
            lm.extent = (
                np.array([s, s])
                if lm.extent is None
                else np.array([min(lm.extent[0], s), max(lm.extent[1], s)])
            )
            return
        w = _to_world_points(pose, f.endpoints)
        s = (w - foot) @ u
        conds = [f.start, f.end]
        order = np.argsort(s)
        (s0, c0), (s1, c1) = (s[order[0]], conds[order[0]]), (s[order[1]], conds[order[1]])
        if lm.extent is None:
            lm.extent = np.array([s0, s1])
            return
        e0, e1 = lm.extent
        lm.extent = np.array([self._move(e0, s0, c0, low=True), self._move(e1, s1, c1, low=False)])

    def _move(self, map_end: float, meas_end: float, cond: End | None, low: bool) -> float:
        beyond = meas_end < map_end if low else meas_end > map_end
        if beyond:
            return meas_end  # the wall is at least this long
        if cond is None or cond is End.FIELD_OF_VIEW:
            return map_end  # the measured end carries no information
        step = self.p.big_step if cond.reliable else self.p.small_step
        return map_end + step * (meas_end - map_end)


def _point_segment(p: NDArray[np.float64], ends: NDArray[np.float64]) -> float:
    a, b = ends
    ab = b - a
    t = float(np.clip((p - a) @ ab / max(ab @ ab, 1e-12), 0.0, 1.0))
    return float(np.hypot(*(p - a - t * ab)))
