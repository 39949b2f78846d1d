"""The front end as a stream processor: events in, per-scan features out (robot frame).

A scan is processed once the sonar readings of the 6 s after it have arrived (or at the end
of the data), so its features come out with that lag. Modes: ``fused`` (the paper: laser and
sonar), ``laser`` (no sonar at all) and ``sonar`` (sonar planes as lines, corner/edge
clusters as points; one output step per laser-scan period, or every ``sonar_step`` s when the
log has no laser). The same code runs all three, so comparisons use identical processing.

Each sonar reading is used as a measurement (fused into a feature, or a point feature) only by
the scan nearest to it in time, so that no reading is counted twice; the whole 12 s window
serves segmentation, clustering, phantom removal and support counts.
"""

from __future__ import annotations

import dataclasses
import math
from collections import Counter, deque
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from factors.corner import corner_to_world, predict_corner
from factors.geometry import wrap_angle
from factors.line import flips, line_residual, line_to_world, normalize_line
from factors.odometry import OdometryIntegrator
from factors.point import (
    bearing_range_in_frame,
    bearing_range_to_robot_frame,
    point_to_world,
    predict_point,
)
from factors.sensor_models import (
    LINE_ANGULAR,
    SonarErrorModel,
    laser_feature_time_inflation,
    quantum_common_sigma,
    time_registration_inflation,
)
from fgslam.config import FrontEndParams, RobotConfig, linked_from
from fgslam.events import Event, LaserScan, OdometryEvent, SonarReading, scan_bearings
from fgslam.frontend.features import SOURCES, End, Feature, OwnTime, ScanFeatures
from fgslam.frontend.fits import (
    FitRejected,
    corner_ranges,
    fit_corner,
    fit_line,
    with_common_error,
)
from fgslam.frontend.fusion import fuse, fused_jacobian
from fgslam.frontend.segmentation import Segment, segment_scan
from fgslam.frontend.sonar import (
    Cluster,
    PoseHistory,
    SonarBuffer,
    SonarPoints,
    cluster,
    mark_invisible,
    remove_phantoms,
    to_laser_frame,
)
from fgslam.scanmatch import scan_points

MODES = ("fused", "laser", "sonar")
CHI2_2_99 = 9.21


def frontend_params(cfg: RobotConfig, base: FrontEndParams | None = None) -> FrontEndParams:
    """The front end's parameters of ``cfg`` (its ``[features]`` section, the sensor-dependent
    thresholds configured or derived from the laser: :func:`fgslam.config.frontend_thresholds`;
    the paper's PLS gives exactly the defaults); given ``base``, ``base`` with those linked
    parameters of ``cfg``."""
    if base is None:
        return cfg.features
    return linked_from(base, cfg.features)


class FrontEnd:
    """Feed events in time order with :meth:`add`; collect :class:`ScanFeatures` from its
    return value and from :meth:`finish` at the end of the data."""

    def __init__(
        self,
        cfg: RobotConfig,
        mode: str = "fused",
        params: FrontEndParams | None = None,
        select: Callable[..., bool] | None = None,
    ) -> None:
        """``select(t, points, odom, v, w)``, if given, is asked for every scan in time order
        (its robot-frame points and odometry pose, as in :class:`ScanFeatures`, and the
        robot's speed in m/s and turn rate in rad/s) whether its features are wanted (a
        keyframe); a scan it declines comes out without features."""
        if mode not in MODES:
            raise ValueError(f"unknown front-end mode {mode!r}; expected one of {MODES}")
        self.cfg, self.mode = cfg, mode
        self.select = select
        self.p = params or frontend_params(cfg)
        self.odo = OdometryIntegrator(cfg.odometry.params(), covariance=False)
        self.poses = PoseHistory(keep=4 * self.p.window)
        self.sonar = SonarBuffer(cfg)
        self._first_sonar_t: float | None = None
        self.pending: deque[tuple[LaserScan, float, float]] = deque()
        self.sonar_model = SonarErrorModel(cfg.sonar.sigma_bearing, cfg.sonar.sigma_sound_rel)
        self.phi = cfg.laser.bearings
        m = cfg.laser.mount
        self.mount = (m.x, m.y, math.radians(m.yaw_deg))
        self.half_slot = 0.5 * cfg.laser.scan_period
        self.mean_delay = 0.5 * (cfg.laser.delay_min + cfg.laser.delay_max)
        # m: the range quantum's error that a fit's beams share (docs/design.md, 3.2)
        self.quantum = quantum_common_sigma(cfg.laser.range_resolution, cfg.laser.sigma_range)
        self._echo_time = (0.0, 0.0, 0.0)  # (|v| m/s, |omega| rad/s, sigma_t s) of the scan
        self._next_sonar_step: float | None = None
        self._saw_laser = False
        self.now = -math.inf

    # ------------------------------------------------------------------ stream

    def add(self, ev: Event) -> list[ScanFeatures]:
        """Consume one event; returns the scans whose window is now complete."""
        self.now = max(self.now, ev.t)
        if isinstance(ev, OdometryEvent):
            self.odo.add(ev.t, *self.cfg.odometry.wheel_travel(ev.ticks_right, ev.ticks_left))
            self.poses.add(ev.t, self.odo.pose)
        elif isinstance(ev, LaserScan):
            self._saw_laser = True
            # time registration (docs/design.md, 3.4): the host stamp is late by the transmission
            # delay; take off its known mean, the spread is covered by the inflation
            ev = dataclasses.replace(ev, t=ev.t - self.mean_delay)
            if self.poses.last_time == -math.inf:
                self.poses.add(ev.t, self.odo.pose)
            v, w = self.poses.velocity(ev.t)
            self.pending.append((ev, v, w))
        elif isinstance(ev, SonarReading) and self.mode != "laser":
            self.sonar.add(ev)
            if self._first_sonar_t is None:
                self._first_sonar_t = ev.t
        return self._ready(final=False)

    def finish(self) -> list[ScanFeatures]:
        """Process every scan still waiting for its sonar window."""
        return self._ready(final=True)

    def _ready(self, final: bool) -> list[ScanFeatures]:
        out = []
        wait = 0.0 if self.mode == "laser" else self.p.window
        while self.pending and (final or self.pending[0][0].t + wait <= self.now):
            scan, v, w = self.pending.popleft()
            out.append(self.process_scan(scan, v, w))
        if self.mode == "sonar" and not self._saw_laser:
            out.extend(self._sonar_only_steps(final))
        oldest = self.pending[0][0].t if self.pending else self.now
        if self._next_sonar_step is not None:
            oldest = min(oldest, self._next_sonar_step)
        self.sonar.drop_before(oldest - self.p.window - 1.0)
        return out

    def _sonar_only_steps(self, final: bool) -> list[ScanFeatures]:
        if self._next_sonar_step is None:
            if self._first_sonar_t is None:
                return []
            self._next_sonar_step = self._first_sonar_t
        out = []
        while (final and self._next_sonar_step <= self.now) or (
            self._next_sonar_step + self.p.window <= self.now
        ):
            fake = LaserScan(self._next_sonar_step, np.full(len(self.phi), np.nan))
            out.append(self.process_scan(fake, *self.poses.velocity(fake.t)))
            self._next_sonar_step += self.p.sonar_step
        return out

    # ------------------------------------------------------------------ one scan

    def process_scan(self, scan: LaserScan, v: float, w: float) -> ScanFeatures:
        """Features of one scan (robot frame); ``v``, ``w`` the robot's speed (m/s) and turn
        rate (rad/s) at the scan for the time-registration inflation. The scan's own bearings
        (:func:`fgslam.events.scan_bearings`) if it has them, evenly spaced (the sonar phantom
        test looks beams up by their spacing); every other step takes them as they are."""
        stats: Counter = Counter()
        t = scan.t
        # the scan's time error, modelled per scan, is on the pose the laser features see;
        # the sonar, moved to the stamp by odometry, carries it per echo (docs/design.md, 3.4)
        self._echo_time = (abs(v), abs(w), self.cfg.laser.time_sigma("per-scan"))
        phi = scan_bearings(scan, self.cfg.laser)
        r = np.asarray(scan.ranges, dtype=float).copy()
        bad = ~np.isfinite(r) | (r <= 0)
        stats["beams_invalid"] = int(bad.sum())
        r[bad] = np.nan
        use_laser = self.mode != "sonar"
        use_sonar = self.mode != "laser"
        points = scan_points(r, phi, self.mount, self.cfg.laser.max_range) if use_laser else None
        odom = self.poses.at(t)
        if self.select is not None and not self.select(t, points, odom, v, w):
            return ScanFeatures(t, [], stats, points, odom)
        pts, clusters = self._sonar_points(t, phi, r, use_laser, stats) if use_sonar else (None, [])
        near = dist = None
        if use_laser and use_sonar:
            near, dist = self._near_clusters(phi, r, clusters)
        feats: list[Feature] = []
        segs: list[Segment] = []
        if use_laser:
            segs, rejected = segment_scan(phi, r, self.p.segment, near, dist)
            stats.update({f"segments_rejected_{k}": v for k, v in rejected.items()})
            lines = [self._line(s, phi, r, pts, stats) for s in segs]
            corners = []
            if self.p.corners != "off":  # (on the whole segments: the vertex's beams count)
                corners = self._corners(segs, lines, phi, r, clusters, pts, stats)
            if self.p.line_ends == "at-vertex":
                self._split_at_vertices(segs, lines, phi, r, pts, stats)
            if self.p.corners == "replace-lines":  # a corner's points count once, in it
                corners, used, dropped = points_once(corners)
                stats["corners_sharing_a_wall"] += dropped
                for k in used:
                    lines[k] = None
            for f in [f for f in lines if f is not None] + [c for _, c in corners]:
                f.cov = laser_feature_time_inflation(
                    f.cov, f.kind, v, w, self.cfg.laser.time_sigma("per-feature")
                )
                feats.append(f)
        if use_sonar and pts is not None:
            slot = np.abs(pts.t - t) <= self.half_slot
            if use_laser:
                used = self._fuse(feats, pts, slot, stats)
                if self.p.points_from == "unfused-echoes":  # an echo counts once
                    slot = slot & ~used
                feats.extend(self._points(segs, clusters, pts, slot, stats))
            else:
                feats.extend(self._sonar_only(clusters, pts, slot, stats))
        feats = [self._to_robot(f) for f in feats]
        for k in ("line", "corner", "point"):
            stats[f"{k}s"] = sum(f.kind == k for f in feats)
        return ScanFeatures(t, feats, stats, points, odom)

    # ------------------------------------------------------------------ sonar

    def _sonar_points(self, t, phi, r, use_laser, stats):
        pts = to_laser_frame(self.sonar, self.cfg, self.poses, t, self.p.window)
        stats["sonar_echoes"] = len(pts)
        if use_laser:
            pts, n_ph = remove_phantoms(pts, phi, r, self.p.phantom_margin)
            stats["sonar_phantoms_removed"] = n_ph
        clusters = cluster(pts, self.p.cluster_radius)
        if use_laser:
            ok = np.isfinite(r)
            mark_invisible(
                clusters,
                np.column_stack([r[ok] * np.cos(phi[ok]), r[ok] * np.sin(phi[ok])]),
                self.p.visible_dist,
            )
            stats["sonar_clusters_invisible"] = sum(not c.visible for c in clusters)
        stats["sonar_clusters"] = len(clusters)
        return pts, clusters

    def _near_clusters(self, phi, r, clusters: list[Cluster]):
        near = np.full(len(r), -1)
        dist = np.full(len(r), np.inf)
        vis = [i for i, c in enumerate(clusters) if c.visible and c.has_corner_or_edge]
        ok = np.isfinite(r)
        if not vis or not ok.any():
            return near, dist
        tree = cKDTree(np.array([clusters[i].centre for i in vis]))
        xy = np.column_stack([r[ok] * np.cos(phi[ok]), r[ok] * np.sin(phi[ok])])
        d, k = tree.query(xy, distance_upper_bound=self.p.segment.sonar_radius)
        hit = np.isfinite(d)
        idx = np.flatnonzero(ok)
        near[idx[hit]] = np.array(vis)[k[hit]]
        dist[idx[hit]] = d[hit]
        return near, dist

    # ------------------------------------------------------------------ laser features

    def _systematic(self, r):
        """The fits' worst-case systematic range errors (m) of the sources not estimated."""
        las = self.cfg.laser
        scale = [] if self.p.range_calibration == "range" else [las.systematic_per_metre * r]
        if self.p.range_calibration != "off":
            return scale
        return [np.full(r.shape, las.systematic_offset), *scale]

    @staticmethod
    def _sources(r):
        """Unit range-error sources: the offset (1 m per m) and the scale (r m per unit)."""
        return [np.ones(r.shape), r]

    def _line(self, seg: Segment, phi, r, pts: SonarPoints | None, stats) -> Feature | None:
        p, rr = phi[seg.first : seg.last + 1], r[seg.first : seg.last + 1]
        try:
            fit = fit_line(
                p,
                rr,
                self.cfg.laser.sigma_range,
                self._systematic(rr),
                residual_test=self.p.residual_level,
                sources=self._sources(rr),
                trim_ends=self.p.line_end_trim or None,
            )
        except FitRejected as exc:
            stats[f"lines_rejected_{exc.reason}"] += 1
            return None
        fit = with_common_error(fit, self.quantum)
        if fit.scale > 1:  # the residual exceeds the range model: covariance scaled
            stats["lines_residual_scaled"] += 1
        stats["line_end_beams_trimmed"] += int(np.isfinite(rr).sum() - fit.used.sum())
        a, d = fit.params
        kept = np.flatnonzero(fit.used)
        ends = []
        for k in (kept[0], kept[-1]):  # first and last point kept, projected on the line
            x, y = rr[k] * math.cos(p[k]), rr[k] * math.sin(p[k])
            off = x * math.cos(a) + y * math.sin(a) - d
            ends.append((x - off * math.cos(a), y - off * math.sin(a)))
        f = Feature(
            "line",
            fit.params,
            fit.cov,
            "laser",
            np.array(ends),
            seg.start,
            seg.end,
            laser_support=int(fit.used.sum()),
            Jc=_laser_sources(fit.source_jacobian),
        )
        if pts is not None and len(pts):
            f.sonar_support = int(np.sum(_seg_dist(pts.xy, f.endpoints) < self.p.support_dist))
        return f

    def _split_at_vertices(self, segs, lines, phi, r, pts, stats) -> None:
        """Consecutive segments whose lines meet (not within 20 deg of parallel) at a vertex
        where the segments meet (within a few beams of their junction, at the range measured
        there): each line is refitted on its segment's beams on its side of the vertex's
        bearing, half a beam step clear of it (``lines`` updated in place; ``segs`` kept).
        The segmentation splits where the points leave a line, so the beams next to the
        vertex go to the segment scanned first, and that line ends with a beam or two of
        the next wall: in a room with its walls 1 m away, 2 mrad and 4 mm of bias."""
        half_step = 0.5 * float(np.median(np.diff(phi)))
        bounds = [(sg.first, sg.last) for sg in segs]
        for k in range(len(segs) - 1):
            s1, s2, l1, l2 = segs[k], segs[k + 1], lines[k], lines[k + 1]
            if l1 is None or l2 is None or s2.first - s1.last > 2:
                continue
            (a1, d1), (a2, d2) = l1.z, l2.z
            det = math.sin(a2 - a1)
            if abs(det) < math.sin(math.radians(20.0)):
                continue
            vx = (d1 * math.sin(a2) - d2 * math.sin(a1)) / det
            vy = (d2 * math.cos(a1) - d1 * math.cos(a2)) / det
            pv = math.atan2(vy, vx)
            # a vertex where the segments meet: within a few beams of their junction and at
            # the range measured there (not two walls an occlusion separates)
            near = phi[max(s1.last - 3, s1.first)] <= pv <= phi[min(s2.first + 3, s2.last)]
            if not near or abs(math.hypot(vx, vy) - r[s1.last]) > self.p.segment.outlier:
                continue
            last = s1.first + int(np.searchsorted(phi[s1.first : s1.last + 1], pv - half_step)) - 1
            first = s2.first + int(np.searchsorted(phi[s2.first : s2.last + 1], pv + half_step))
            bounds[k] = (bounds[k][0], min(bounds[k][1], last))
            bounds[k + 1] = (max(bounds[k + 1][0], first), bounds[k + 1][1])
        for j, (sg, (first, last)) in enumerate(zip(segs, bounds, strict=True)):
            if (first, last) != (sg.first, sg.last) and lines[j] is not None:
                stats["lines_split_at_vertex"] += 1
                seg = dataclasses.replace(sg, first=first, last=last)
                lines[j] = self._line(seg, phi, r, pts, stats) if seg.n >= 3 else None

    def _corners(self, segs, lines, phi, r, clusters, pts, stats) -> list[tuple[int, Feature]]:
        """Right-angle corners of consecutive lines k, k + 1, as (k, corner)."""
        out = []
        for k in range(len(segs) - 1):
            s1, s2, l1, l2 = segs[k], segs[k + 1], lines[k], lines[k + 1]
            if l1 is None or l2 is None:
                continue
            if self.mode == "laser":
                if s1.end not in (End.OUTLIERS, End.SPREAD):
                    continue
            elif not (
                s1.end is End.SONAR
                and s1.end_cluster is not None
                and clusters[s1.end_cluster].counts[1] > 0
            ):
                continue
            a1, d1 = l1.z
            a2, d2 = l2.z
            if abs(abs(wrap_angle(a1 - a2)) - math.pi / 2) > self.p.right_angle_tol:
                continue
            stats["corners_tried"] += 1
            det = math.sin(a2 - a1)
            vx = (d1 * math.sin(a2) - d2 * math.sin(a1)) / det
            vy = (d2 * math.cos(a1) - d1 * math.cos(a2)) / det
            if self.mode == "laser":
                gap = min(
                    np.hypot(*(l1.endpoints[1] - (vx, vy))), np.hypot(*(l2.endpoints[0] - (vx, vy)))
                )
                if gap > self.p.corner_gap:
                    stats["corners_rejected_gap"] += 1
                    continue
            phi_c, r_c = math.atan2(vy, vx), math.hypot(vx, vy)
            # paper gamma: mean of the two normals; l2 lies at larger bearings
            g = a1 + 0.5 * wrap_angle(a2 - a1)
            if abs(wrap_angle(g - phi_c)) > math.pi / 2:
                g += math.pi
            convex = wrap_angle(a2 - g) < 0
            # the two lines' beams, and those between them that the corner of the two lines
            # explains (the vertex's own returns); not an occluder's or its shadow's
            between = np.arange(s1.last + 1, s2.first)
            if between.size:
                pred = corner_ranges((phi_c, r_c, g), phi[between], convex)[0]
                between = between[np.abs(r[between] - pred) <= self.p.segment.outlier]
            sl = np.r_[s1.first : s1.last + 1, between, s2.first : s2.last + 1]
            try:
                fit = fit_corner(
                    phi[sl],
                    r[sl],
                    (phi_c, r_c, g),
                    self.cfg.laser.sigma_range,
                    self._systematic(r[sl]),
                    convex=convex,
                    residual_test=self.p.residual_level,
                    sources=self._sources(r[sl]),
                )
            except FitRejected as exc:
                stats[f"corners_rejected_{exc.reason}"] += 1
                continue
            fit = with_common_error(fit, self.quantum)
            if fit.scale > 1:
                stats["corners_residual_scaled"] += 1
            f = Feature(
                "corner",
                fit.params,
                fit.cov,
                "laser",
                np.array([l1.endpoints[0], l2.endpoints[1]]),
                convex=convex,
                laser_support=int(fit.used.sum()),
                Jc=_laser_sources(fit.source_jacobian),
            )
            if pts is not None and len(pts):
                vx, vy = (
                    fit.params[1] * math.cos(fit.params[0]),
                    fit.params[1] * math.sin(fit.params[0]),
                )
                f.sonar_support = int(
                    np.sum(
                        (pts.kind == 1)
                        & (
                            np.hypot(pts.xy[:, 0] - vx, pts.xy[:, 1] - vy)
                            < 2 * self.p.cluster_radius
                        )
                    )
                )
            out.append((k, f))
        return out

    # ------------------------------------------------------------------ sonar features

    def _plane_cov(self, pts: SonarPoints, i: int) -> NDArray[np.float64]:
        C = self.sonar_model.covariance(pts.r[i])
        C = _plane(pts.sensor[i], pts.bearing[i], pts.r[i], C)[1]
        v, w, sig = self._echo_time
        return time_registration_inflation(C, LINE_ANGULAR, v, w, sig) if sig else C

    def _own(self, pts: SonarPoints, i: int, kind: str) -> OwnTime:
        """Echo ``i`` as a point (bearing, range) or plane (alpha, d) measurement from the
        robot at the reading's own time (its transducer's mount, no odometry)."""
        C = self.sonar_model.covariance(pts.r[i])
        if kind == "line":
            z, cov = _plane(pts.mount[i], pts.bearing[i], pts.r[i], C)
        else:
            z, cov = bearing_range_to_robot_frame((pts.bearing[i], pts.r[i]), C, pts.mount[i])
        Jc = _sound_source(_echo_range_jacobian(kind, pts.mount[i], pts.bearing[i], pts.r[i]))
        return OwnTime(float(pts.t[i]), z, cov, Jc)

    @staticmethod
    def _sound_jacobian(pts: SonarPoints, i: int) -> NDArray[np.float64]:
        """Echo ``i``'s measurement in the laser frame at the scan's time (a plane's (alpha, d)
        as ``pts.line[i]``, another's (bearing, range)) w.r.t. :data:`SOURCES`."""
        kind = "line" if pts.kind[i] == 0 else "point"
        return _sound_source(_echo_range_jacobian(kind, pts.sensor[i], pts.bearing[i], pts.r[i]))

    def _point_cov(self, pts: SonarPoints, i: int) -> NDArray[np.float64]:
        _, _, tth = pts.sensor[i]
        a, rr = tth + pts.bearing[i], pts.r[i]
        J = np.array([[-rr * math.sin(a), math.cos(a)], [rr * math.cos(a), math.sin(a)]])
        C = self.sonar_model.covariance(rr)
        v, w, sig = self._echo_time
        if sig:
            C = time_registration_inflation(C, (True, False), v, w, sig)
        return J @ C @ J.T

    def _fuse(self, feats: list[Feature], pts: SonarPoints, slot, stats) -> NDArray[np.bool_]:
        """Fuse the slot's sonar planes into the laser lines and its corner echoes into the
        laser corners they agree with; returns which echoes were fused."""
        used = np.zeros(len(pts.xy), dtype=bool)
        planes = np.flatnonzero(slot & (pts.kind == 0))
        corners = np.flatnonzero(slot & (pts.kind == 1))
        for f in feats:
            if f.kind == "line":
                for i in planes:
                    zs, Cs = pts.line[i], self._plane_cov(pts, i)
                    e = line_residual((0, 0, 0), zs, f.z)[0]  # sonar - laser, same form
                    S = f.cov + Cs
                    if e @ np.linalg.solve(S, e) > CHI2_2_99:
                        continue
                    if _seg_dist(pts.xy[i : i + 1], f.endpoints)[0] > 0.2:
                        continue
                    zs = f.z + e  # the sonar line in the laser line's (alpha, d) form
                    if f.Jc is not None:
                        Js = self._sound_jacobian(pts, i)
                        if flips(wrap_angle(zs[0] - pts.line[i, 0])):
                            Js = -Js  # that form is (alpha + pi, -d) of pts.line's
                        f.Jc = fused_jacobian(f.cov, Cs, f.Jc, J_s=Js)
                    f.z, f.cov = fuse(f.z, f.cov, zs, Cs, angular=(True, False))
                    f.source = "fused"
                    used[i] = True
                    stats["fused_lines"] += 1
            elif f.kind == "corner":
                for i in corners:
                    zs = np.array([math.atan2(pts.xy[i, 1], pts.xy[i, 0]), np.hypot(*pts.xy[i])])
                    Cs = _polar_cov(pts.xy[i], self._point_cov(pts, i))
                    e = np.array([wrap_angle(zs[0] - f.z[0]), zs[1] - f.z[1]])
                    if e @ np.linalg.solve(f.cov[:2, :2] + Cs, e) > CHI2_2_99:
                        continue
                    if f.Jc is not None:
                        Js = self._sound_jacobian(pts, i)
                        f.Jc = fused_jacobian(f.cov, Cs, f.Jc, dims=2, J_s=Js)
                    f.z, f.cov = fuse(f.z, f.cov, f.z[:2] + e, Cs, angular=(True, False), dims=2)
                    f.source = "fused"
                    used[i] = True
                    stats["fused_corners"] += 1
        return used

    def _point_from_cluster(self, c: Cluster, pts: SonarPoints, slot) -> Feature | None:
        members = c.members[slot[c.members]]
        if members.size == 0:
            return None
        i = members[np.argmin(np.hypot(*(pts.xy[members] - c.centre).T))]
        xy = pts.xy[i]
        z = np.array([math.atan2(xy[1], xy[0]), math.hypot(*xy)])
        f = Feature(
            "point",
            z,
            _polar_cov(xy, self._point_cov(pts, i)),
            "sonar",
            sonar_support=int(c.members.size),
            own=self._own(pts, i, "point"),
            Jc=self._sound_jacobian(pts, i),
        )
        f.sonar_readings = (pts.readings[int(pts.reading[i])],)
        return f

    def _points(self, segs, clusters, pts, slot, stats) -> list[Feature]:
        ending = {s.end_cluster for s in segs if s.end is End.SONAR}
        out = []
        for k in sorted(c for c in ending if c is not None):
            f = self._point_from_cluster(clusters[k], pts, slot)
            if f is not None:
                out.append(f)
        return out

    def _sonar_only(self, clusters, pts, slot, stats) -> list[Feature]:
        out = []
        for c in clusters:
            if c.members.size >= self.p.min_cluster:
                f = self._point_from_cluster(c, pts, slot)
                if f is not None:
                    out.append(f)
        for i in np.flatnonzero(slot & (pts.kind == 0)):
            out.append(
                Feature(
                    "line",
                    pts.line[i].copy(),
                    self._plane_cov(pts, i),
                    "sonar",
                    sonar_support=1,
                    own=self._own(pts, i, "line"),
                    Jc=self._sound_jacobian(pts, i),
                )
            )
        return out

    # ------------------------------------------------------------------ frames

    def _to_robot(self, f: Feature) -> Feature:
        """Laser frame -> robot frame (the laser's mount); sonar points were moved with it."""
        m = self.mount
        if f.kind == "line":
            z, _, J = line_to_world(m, f.z, (0.0, 0.0, 0.0))
        elif f.kind == "corner":
            c, _, Hz = corner_to_world(m, f.z)
            z, _, Hc = predict_corner((0.0, 0.0, 0.0), c)
            J = Hc @ Hz
        else:
            q, _, Hz = point_to_world(m, f.z)
            z, _, Hp = predict_point((0.0, 0.0, 0.0), q)
            J = Hp @ Hz
        f.z, f.cov = z, J @ f.cov @ J.T
        if f.Jc is not None:
            f.Jc = J @ f.Jc
        f.cov = 0.5 * (f.cov + f.cov.T)
        if f.endpoints is not None:
            c, s = math.cos(m[2]), math.sin(m[2])
            e = f.endpoints
            f.endpoints = np.column_stack(
                [m[0] + c * e[:, 0] - s * e[:, 1], m[1] + s * e[:, 0] + c * e[:, 1]]
            )
        return f


def points_once(
    corners: list[tuple[int, Feature]],
) -> tuple[list[tuple[int, Feature]], set[int], int]:
    """Corners ``(k, corner of lines k and k + 1)`` in scan order such that no line's points
    are in two of them: a corner whose line an earlier kept corner took is dropped (three
    walls of a room: the first corner, and the third wall as a line). Returns the kept
    corners, the lines they took, and how many corners were dropped."""
    kept: list[tuple[int, Feature]] = []
    used: set[int] = set()
    for k, c in corners:
        if k not in used and k + 1 not in used:
            kept.append((k, c))
            used.update((k, k + 1))
    return kept, used, len(corners) - len(kept)


def _plane(
    sensor: NDArray[np.float64], bearing: float, r: float, C: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """A sonar plane echo (``bearing``, range ``r``, covariance ``C`` in that order) of a
    transducer at ``sensor`` = (x, y, theta) as a line (alpha, d >= 0) in the frame the
    transducer pose is given in, and its covariance."""
    tx, ty, tth = (float(v) for v in sensor)
    a = tth + bearing
    d = r + tx * math.cos(a) + ty * math.sin(a)
    alpha, d = normalize_line(a, d)
    J = np.array([[1.0, 0.0], [-tx * math.sin(alpha) + ty * math.cos(alpha), 1.0]])
    return np.array([alpha, d]), J @ C @ J.T


def _echo_range_jacobian(
    kind: str, sensor: NDArray[np.float64], bearing: float, r: float
) -> NDArray[np.float64]:
    """r dz/dr of a sonar echo (``bearing``, range ``r``) of a transducer at ``sensor`` = (x,
    y, theta) as a ``line`` (plane: (alpha, d >= 0) as :func:`_plane`) or ``point`` ((bearing,
    range)) in the frame ``sensor`` is given in: its Jacobian w.r.t. the relative error of the
    speed of sound (a range reads r (1 + sound), to first order)."""
    tx, ty, tth = (float(v) for v in sensor)
    if kind == "line":
        a = tth + bearing
        d = r + tx * math.cos(a) + ty * math.sin(a)
        return np.array([0.0, r if d >= 0 else -r])  # d < 0: the form (a + pi, -d)
    return r * bearing_range_in_frame((bearing, r), (tx, ty, tth))[1][:, 1]


def _sound_source(j: NDArray[np.float64]) -> NDArray[np.float64]:
    """A Jacobian w.r.t. the speed of sound alone (len(z),) as one w.r.t. :data:`SOURCES`."""
    out = np.zeros((len(j), len(SOURCES)))
    out[:, SOURCES.index("sound")] = j
    return out


def _laser_sources(J: NDArray[np.float64]) -> NDArray[np.float64]:
    """A laser fit's Jacobian w.r.t. its range (offset, scale) as one w.r.t. :data:`SOURCES`."""
    return np.column_stack([J, np.zeros(len(J))])


def _polar_cov(xy: NDArray[np.float64], C: NDArray[np.float64]) -> NDArray[np.float64]:
    """Covariance of (bearing, range) of a point at xy with Cartesian covariance C."""
    x, y = xy
    r2 = x * x + y * y
    r = math.sqrt(r2)
    J = np.array([[-y / r2, x / r2], [x / r, y / r]])
    return J @ C @ J.T


def _seg_dist(xy: NDArray[np.float64], ends: NDArray[np.float64]) -> NDArray[np.float64]:
    """Distances from points (N, 2) to the segment between ends[0] and ends[1]."""
    a, b = ends[0], ends[1]
    ab = b - a
    t = np.clip(((xy - a) @ ab) / max(ab @ ab, 1e-12), 0.0, 1.0)
    return np.hypot(*(xy - (a + t[:, None] * ab)).T)
