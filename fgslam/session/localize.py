"""Localization on a saved session (``fgslam localize``; docs/sessions.md): the map fixed,
the robot's pose tracked by scan matching against it, found by a global search when unknown
or lost.

Local maps (:class:`Places`): at a position, the scans of the map keyframes within
``radius`` of it (at most ``max_scans``, nearest first from each eighth of the headings in
turn, so that a place passed both ways keeps the scans that looked each way) in the world
frame, thinned to one point per matcher cell, prepared for matching
(:class:`~fgslam.scanmatch.Reference`, with the laser origins) and kept (``cache_size``)
while the same keyframes make it. Places: map keyframes at least ``spacing`` apart; every
map keyframe lies within ``spacing`` of one. The map's occupancy grid (:class:`MapCheck`)
says where the map saw something and what it saw free.

Motion (``motion``): the wheel odometry carries the pose from scan to scan ("wheels"), or
the scan odometry of the mapping (:class:`~fgslam.slam.keyframes.ScanOdometry`, each scan
matched against the ones just before it) fused with the wheels by their covariances
("fused"), or alone ("scan"); :class:`~fgslam.slam.keyframes.FusedMotion`.

Tracking: a scan is matched when the robot has moved ``every_distance`` or turned
``every_angle`` since the last matched scan; the motion since then predicts its pose, the
matcher searches its window around it against the local map there. The last ``window``
matched poses, each with its match as a prior (the map is fixed, so a match is an absolute
measurement of the pose: the match's covariance, body tangent) and the wheel odometry between
consecutive ones (:func:`factors.odometry.preintegrate`), are solved together
(Levenberg-Marquardt); the oldest carries the information of the poses before it. A scan not
matched is placed by the motion from the last matched one; offline,
:meth:`LocalizationResult.bridged` places the scans not localized too. Where less than
``min_view`` of the scan's returns at the prediction fall where the map saw something (the
robot has left the mapped part), the scan is not matched: the odometry carries the pose on,
and nothing counts as failed. ``lost_after`` matches in a row that failed or that the map
contradicts (more than ``max_see_through`` of the returns on cells the map saw free) and the
robot is lost. Lost, a scan every ``RECOVER_EVERY`` of travel is searched for around the
pose the odometry carried on (a window growing with the travel since, up to ``spacing``:
the robot came back into the mapped part), and once it has travelled ``search_after`` also
by the global search. When the map contradicted most of the failures (at the match, or at
the prediction where the match failed), the robot was carried away (kidnapped): the global
search alone, at once. The tracking thresholds are the scan odometry's; a weak score or
overlap is no sign of being lost: where the robot sees much the map did not, they are low at
the right pose.

Global search (no ``initial_pose``, or lost): the scan is matched against every place with a
window of +-``spacing`` and every heading (steps of ``global_step``). The answers that pass
(the loop closures' score threshold) and that the map does not contradict (at least
``min_view`` of their returns where the map saw something, at most ``max_see_through`` on
cells it saw free), best score first, at most ``hypotheses`` of them at least 0.5 m or
10 deg apart, are the candidates. When the best does not score ``confirm_margin`` above the
next, or above an answer rejected as ambiguous only (the scan also fits a featureless
stretch, where the matcher cannot pin the pose down), none stands out (a corridor's doors, a
symmetric room seen from its middle: the truth may not even be among them) and the search is
made again further on. Otherwise the answers
are tracked like the pose; one dies after ``lost_after`` failed matches in a row. Localized:
the one whose last ``confirm`` matches score best on average has passed ``confirm`` matches
in a row, and no other is left, or every other's average is ``confirm_margin`` lower and the
robot has travelled ``CONFIRM_TRAVEL`` spacings since the search (a room symmetric under a
half turn fits both ways until something that breaks the symmetry comes into view; a
corridor's doors make a lead that does not last). All dead, or none decided after
``EXPIRE_TRAVEL`` spacings: a new search at once; a search that found nothing: again once
the robot moved ``spacing`` / 2 (doubling each time, up to ``RETRY_MAX`` spacings) or turned
30 deg.

Frames: world = the saved session's; scan points in the robot frame; (x, y, theta) m, rad."""

from __future__ import annotations

import dataclasses
import math
import time
from collections import OrderedDict, deque
from collections.abc import Callable
from dataclasses import dataclass, field

import gtsam
import numpy as np
from numpy.typing import NDArray

from factors.geometry import (
    between_poses,
    compose_poses,
    transform_points,
    wrap_angle,
    wrap_angles,
)
from factors.odometry import preintegrate
from fgslam.config import LocalizeParams, MatchParams, RobotConfig
from fgslam.config.robot import KeyframeParams
from fgslam.evaluation.metrics import interpolate_poses
from fgslam.events import Event, OdometryEvent, TruthPose
from fgslam.frontend.pipeline import FrontEnd
from fgslam.io.ordering import REORDER_WINDOW, ReorderBuffer
from fgslam.scanmatch import Match, Reference, match
from fgslam.scanmatch.points import voxel_index
from fgslam.session.store import Session, SessionError
from fgslam.slam.keyframes import FusedMotion, ScanOdometry

# a place's overlapping scans thinned to one point per matcher cell: else the local lines of
# ICP are fitted to a few centimetres of stacked returns (overlap 0.07 instead of 0.48)
VOXEL = 1.0
CHECK_RESOLUTION = 0.1  # m, the cells of :class:`MapCheck` (a return within a cell agrees)
HYP_XY, HYP_THETA = 0.5, math.radians(10.0)  # global answers nearer than this: one
RECOVER_XY, RECOVER_THETA, RECOVER_GROWTH = 0.5, 0.25, 0.2  # m, rad, per metre travelled
RECOVER_EVERY = 0.3  # m of travel between the searches near the dead-reckoned pose
RETRY_XY, RETRY_THETA = 0.5, math.radians(30.0)  # of spacing (x), absolute (theta)
RETRY_MAX = 8.0  # spacings
CONFIRM_TRAVEL = 1.0  # spacings of travel before one of several answers is taken
EXPIRE_TRAVEL = 10.0  # spacings of travel after which undecided answers are searched anew


class Places:
    """The map cut into places (module doc)."""

    def __init__(self, session: Session, params: LocalizeParams, mp: MatchParams) -> None:
        self.s, self.p, self.mp = session, params, mp
        have = np.array([p is not None and len(p) > 0 for p in session.scans], dtype=bool)
        self.kf = np.nonzero(have & np.isfinite(session.poses).all(axis=1))[0]
        xy = session.poses[self.kf, :2]
        chosen: list[int] = []
        for i in range(len(self.kf)):
            if not chosen or np.hypot(*(xy[chosen] - xy[i]).T).min() >= params.spacing:
                chosen.append(i)
        self.anchors = self.kf[chosen]
        self.xy = session.poses[self.anchors, :2].reshape(-1, 2)
        self._refs: OrderedDict[tuple, Reference] = OrderedDict()
        self.built = 0  # local maps built

    def __len__(self) -> int:
        return len(self.anchors)

    def near(self, xy: NDArray[np.float64]) -> NDArray[np.int64]:
        """The map keyframes (indices into the session) that make the local map at the world
        position ``xy``: those within ``radius``, nearest first, taken in turn from each
        eighth of the headings (so that a place passed one way and the other keeps the
        scans that looked each way), at most ``max_scans``."""
        poses = self.s.poses[self.kf]
        d = np.hypot(*(poses[:, :2] - np.asarray(xy, dtype=float)[:2]).T)
        near = np.argsort(d, kind="stable")
        near = near[d[near] <= self.p.radius]
        if len(near) == 0:  # off the map: the nearest keyframe's scans all the same
            near = np.argsort(d, kind="stable")[:1]
        octant = np.floor((wrap_angles(poses[near, 2]) + np.pi) / (np.pi / 4)).astype(int) % 8
        rank = np.zeros(len(near), dtype=int)  # rank within its octant: round robin
        seen = np.zeros(8, dtype=int)
        for i, o in enumerate(octant):
            rank[i] = seen[o]
            seen[o] += 1
        order = np.lexsort((np.arange(len(near)), rank))
        return np.sort(self.kf[near[order[: self.p.max_scans]]])

    def reference(self, xy: NDArray[np.float64]) -> Reference:
        """The local map at ``xy`` (:meth:`near`) in the world frame, prepared for matching
        (one built before for the same keyframes is reused)."""
        keys = tuple(self.near(xy).tolist())
        ref = self._refs.get(keys)
        if ref is not None:
            self._refs.move_to_end(keys)
            return ref
        pts, org = [], []
        o = np.array([self.s.laser_xy])
        for k in keys:
            pose, scan = self.s.poses[k], self.s.scans[k]
            pts.append(transform_points(pose, scan))
            org.append(np.repeat(transform_points(pose, o), len(scan), axis=0))
        pts, org = np.vstack(pts), np.vstack(org)
        keep = voxel_index(pts, VOXEL * self.mp.resolution)  # overlapping scans: one density
        ref = Reference.build(pts[keep], self.mp, org[keep])
        self._refs[keys] = ref
        self.built += 1
        while len(self._refs) > self.p.cache_size:
            self._refs.popitem(last=False)
        return ref


class MapCheck:
    """The saved map's occupancy grid (``CHECK_RESOLUTION`` cells) asked where a scan's
    returns fall at a pose: on or next to an occupied cell (the map agrees), on a free cell
    (the map saw through there: it contradicts the pose, unless something moved), or where
    the map saw nothing."""

    def __init__(self, session: Session) -> None:
        from scipy.ndimage import binary_dilation

        g = session.grid(CHECK_RESOLUTION)
        self.grid = g
        occ = binary_dilation(g.occupied(), iterations=1)
        self.occupied = occ
        self.free = g.free() & ~occ

    def check(self, pose: NDArray[np.float64], points) -> tuple[float, float]:
        """(view, contradiction): the fraction of the returns (robot-frame points, m) at
        ``pose`` (world) that fall where the map saw something, and of those the fraction on
        free cells."""
        w = transform_points(np.asarray(pose, dtype=float), np.asarray(points, dtype=float))
        row, col = self.grid.cell_of(w)
        rows, cols = self.occupied.shape
        inside = (row >= 0) & (row < rows) & (col >= 0) & (col < cols)
        r, c = row[inside], col[inside]
        occ = self.occupied[r, c]
        free = self.free[r, c]
        known = int(occ.sum() + free.sum())
        view = known / max(len(w), 1)
        return view, (float(free.sum()) / known if known else 0.0)


@dataclass
class _Track:
    """A pose being tracked (the localized one, or a hypothesis of the global search)."""

    pose: NDArray[np.float64]
    passes: int = 0
    fails: int = 0
    score: float = 0.0  # the last match's
    contradicted: int = 0  # of the failures in a row, those the map contradicted
    scores: list[float] = field(default_factory=list)  # its matches' since the global search

    def recent(self, n: int) -> float:
        """The mean score of its last ``n`` matches."""
        return float(np.mean(self.scores[-n:])) if self.scores else 0.0


@dataclass
class LocalizationResult:
    """What :class:`Localizer` produced. ``times``, ``poses``: every scan's pose (world;
    NaN while not localized); ``matched``: whether that scan's pose comes from a match
    (else from the odometry since the last matched one); ``odometry``: each scan's pose
    along the odometry that carried the pose (the scan odometry's chain or the wheels';
    its own frame); ``events``: what happened when (localized, lost, with their evidence);
    ``stats`` counts. :meth:`bridged` fills the gaps."""

    times: NDArray[np.float64]
    poses: NDArray[np.float64]
    matched: NDArray[np.bool_]
    odometry: NDArray[np.float64]
    events: list[dict]
    stats: dict
    truth_t: NDArray[np.float64]
    truth: NDArray[np.float64]
    wall_time: float
    log_duration: float
    places: int

    def bridged(self) -> NDArray[np.float64]:
        """Every scan's pose, the scans not localized (before the first localization, lost,
        after the last) placed by the odometry from the localized scans on either side, the
        difference of the two spread over the gap by time (one side: carried from it). An
        offline estimate: right where the odometry holds (the scan odometry across a stretch
        the map does not show), wrong across a kidnapping. NaN when nothing was localized."""
        ok = np.isfinite(self.poses).all(axis=1)
        out = self.poses.copy()
        idx, gap = np.flatnonzero(ok), np.flatnonzero(~ok)
        if not len(idx) or not len(gap):
            return out
        k = np.searchsorted(idx, gap)
        a = idx[np.maximum(k - 1, 0)]
        b = idx[np.minimum(k, len(idx) - 1)]
        o, p, t = self.odometry, self.poses, self.times
        pa = compose_poses(p[a], between_poses(o[a], o[gap]))
        pb = compose_poses(p[b], between_poses(o[b], o[gap]))
        span = np.maximum(t[b] - t[a], 1e-9)
        w = np.where(k == 0, 1.0, np.where(k == len(idx), 0.0, (t[gap] - t[a]) / span))
        out[gap] = compose_poses(pa, np.clip(w, 0.0, 1.0)[:, None] * between_poses(pa, pb))
        return out

    def report(self) -> dict:
        """report.json's content: when it was localized and how confidently, lost spells,
        the share of scans matched, the speed, and the error against the truth if the log
        has it (after the first localization)."""
        loc = [e for e in self.events if e["event"] == "localized"]
        ok = np.isfinite(self.poses).all(axis=1)
        rep: dict = {
            "scans": len(self.times),
            "scans_localized": int(ok.sum()),
            "scans_matched": int(self.matched.sum()),
            "scans_bridged": int((~ok).sum()) if ok.any() else 0,
            "places": self.places,
            "localized": bool(loc),
            "localized_at": loc[0]["t"] if loc else None,
            "first_localization": loc[0] if loc else None,
            "relocalizations": max(len(loc) - 1, 0),
            "lost": [e for e in self.events if e["event"] == "lost"],
            "events": self.events,
            "wall_time_s": round(self.wall_time, 3),
            "log_duration_s": round(self.log_duration, 3),
            "real_time_factor": round(self.log_duration / self.wall_time, 2)
            if self.wall_time > 0
            else None,
            "stats": dict(self.stats),
        }
        err = self.errors()
        if err is not None:
            rep["error_vs_truth"] = err
        return rep

    def write_trajectory(self, path, bridged: bool = False) -> int:
        """The localized scans' poses (``bridged``: every scan's, :meth:`bridged`) as a TUM
        trajectory (atomically); returns how many."""
        from fgslam.evaluation import metrics as evaluation
        from fgslam.io import safeio

        poses = self.bridged() if bridged else self.poses
        ok = np.isfinite(poses).all(axis=1)
        with safeio.atomic_path(path) as tmp:
            evaluation.write_tum(tmp, self.times[ok], poses[ok])
        return int(ok.sum())

    def errors(self) -> dict | None:
        """Position (m) and heading (deg) error of the localized scans against the truth
        interpolated at their times (None without truth)."""
        if len(self.truth_t) < 2:
            return None
        ok = np.isfinite(self.poses).all(axis=1)
        t = self.times[ok]
        inside = (t >= self.truth_t[0]) & (t <= self.truth_t[-1])
        if not inside.any():
            return None
        t, p = t[inside], self.poses[ok][inside]
        truth = interpolate_poses(self.truth_t, self.truth, t)
        dxy = np.hypot(p[:, 0] - truth[:, 0], p[:, 1] - truth[:, 1])
        dth = np.degrees(np.abs(wrap_angles(p[:, 2] - truth[:, 2])))
        return {
            "scans": len(t),
            "position_rmse_m": round(float(np.sqrt(np.mean(dxy**2))), 4),
            "position_max_m": round(float(dxy.max()), 4),
            "heading_rmse_deg": round(float(np.sqrt(np.mean(dth**2))), 3),
            "heading_max_deg": round(float(dth.max()), 3),
        }


class Localizer:
    """Events in with :meth:`add` (any order within the reorder window), the result from
    :meth:`finish`; :meth:`pose` is the current estimate (None while not localized). See
    the module doc. ``initial_pose``: the start pose in the map's world frame (skips the
    global search; it is checked by the first matches like any pose)."""

    def __init__(
        self,
        session: Session,
        cfg: RobotConfig,
        initial_pose: tuple[float, float, float] | None = None,
        params: LocalizeParams | None = None,
        progress: Callable[[float], None] | None = None,
        count_idle: bool = True,
    ) -> None:
        """``count_idle``: the wall time of the result is the time since the localizer was
        made (a log); without (online, waiting for data), only the time spent working."""
        self.t0 = time.perf_counter()
        self.count_idle = count_idle
        self.busy_seconds = 0.0
        self.cfg = cfg
        self.p = params or LocalizeParams.from_config(cfg)
        # tracking: a small window around a good prediction, the scan odometry's thresholds;
        # a corridor's match is kept with its covariance (long along it): the odometry
        # carries the pose along, the match holds it across
        kp = cfg.keyframes
        self.mp = dataclasses.replace(
            cfg.matcher,
            min_score=kp.match_min_score,
            min_overlap=kp.match_min_overlap,
            max_ambiguity=math.inf,
        )
        # the global search and its answers' confirmation: a place told from others by the
        # score, as a loop closure is (the overlap is low at the right pose where the robot
        # sees beyond the local map: the tracking threshold)
        self.mp_confirm = dataclasses.replace(self.mp, min_score=cfg.loops.min_score)
        self.mp_global = dataclasses.replace(
            self.mp_confirm,
            max_ambiguity=cfg.matcher.max_ambiguity,
            search_xy=self.p.spacing,
            search_theta=math.pi,
            angular_step=self.p.global_step,
        )
        self.places = Places(session, self.p, self.mp)
        if not len(self.places):
            raise SessionError(
                "the session holds no keyframe with a laser scan: no map to localize on"
            )
        self.map_check = MapCheck(session)
        self.progress = progress
        self.reorder = ReorderBuffer(REORDER_WINDOW)
        self.frontend = FrontEnd(cfg, "laser", select=self._select)
        self._odo = cfg.odometry.params()
        self._samples: deque[tuple[float, float, float]] = deque()
        self._last_sample_t: float | None = None
        self.stats: dict = {"matches": 0, "matches_failed": 0, "global_searches": 0}
        self.events: list[dict] = []
        self.times: list[float] = []
        self.poses: list[NDArray[np.float64]] = []
        self.odometry: list[NDArray[np.float64]] = []  # each scan's, the motion's frame
        self.matched: list[bool] = []
        self.truth_t: list[float] = []
        self.truth: list[tuple[float, float, float]] = []
        self.first_t: float | None = None
        self.last_t = -math.inf
        self._odom_prev: NDArray[np.float64] | None = None
        # the motion between scans other than the wheels' (module doc)
        kp = KeyframeParams.from_config(cfg)
        origin = (cfg.laser.mount.x, cfg.laser.mount.y)
        self.motion = (
            FusedMotion(
                ScanOdometry(kp, MatchParams.from_config(cfg), origin, cfg.laser.sigma_time),
                self._odo,
                kp.motion_gate_p,
                fuse=self.p.motion == "fused",
            )
            if self.p.motion != "wheels"
            else None
        )
        self._moved = np.zeros(3)  # since the last matched scan (odometry, robot frame)
        self._since_search = np.zeros(3)
        self._search_travel = 0.0  # m of path since the last global search
        self._search_now = True
        self._anchor = -1  # the scan index of the last matched scan
        self._rel = np.zeros(3)  # odometry since it
        self._placed: list[tuple[int, NDArray[np.float64]]] = []  # per scan (anchor, rel)
        self._track: _Track | None = None
        self._hyps: list[_Track] = []
        self._rival = 0.0
        self._lost_pose: NDArray[np.float64] | None = None  # dead reckoning since lost
        self._lost_travel = 0.0  # m since lost
        self._next_recover = 0.0  # m of travel since lost at which to search near it next
        self._retry = RETRY_XY  # spacings of travel before the next global search
        self._window: deque = deque()  # (scan index, t, match pose, match cov, odometry in)
        # the past's information on the window's oldest pose: (its scan index, mean, cov)
        self._carry: tuple[int, NDArray[np.float64], NDArray[np.float64]] | None = None
        self._last_t_matched: float | None = None  # the last scan matched (or tried)
        self._last_t_window: float | None = None  # the window's newest pose's time
        # the first tracked match: (scan time s, pose world, covariance body frame) (a
        # continued run's anchor on the map, :mod:`fgslam.session.join`)
        self.first_fix: tuple[float, NDArray[np.float64], NDArray[np.float64]] | None = None
        if initial_pose is not None:
            self._track = _Track(np.asarray(initial_pose, dtype=float).reshape(3))
            self._pending_initial = True
        else:
            self._pending_initial = False

    # -- feeding

    def add(self, ev: Event) -> None:
        """Take one event (any order within the reorder window)."""
        t0 = time.perf_counter()
        for e in self.reorder.push(ev):
            self._process(e)
        self.busy_seconds += time.perf_counter() - t0

    def status_text(self) -> str:
        """The state in one line (``fgslam online --map``'s status)."""
        pose = self.pose()
        if pose is not None:
            where = f"x {pose[0]:7.2f} y {pose[1]:7.2f} th {math.degrees(pose[2]):6.1f} deg"
            return f"localized | {where} | matched {sum(self.matched)} of {len(self.times)}"
        if self._hyps:
            return f"confirming {len(self._hyps)} answers of the global search"
        return f"searching the map ({self.stats['global_searches']} global searches)"

    def _process(self, ev: Event) -> None:
        self.last_t = ev.t
        if self.first_t is None:
            self.first_t = ev.t
        if isinstance(ev, TruthPose):
            self.truth_t.append(ev.t)
            self.truth.append((ev.x, ev.y, ev.theta))
            return
        if isinstance(ev, OdometryEvent):
            sample = (ev.t, *self.cfg.odometry.wheel_travel(ev.ticks_right, ev.ticks_left))
            self._samples.append(sample)
            if self.motion is not None:
                self.motion.sample(*sample)
        self.frontend.add(ev)
        if self.progress is not None:
            self.progress(ev.t)

    def pose(self) -> NDArray[np.float64] | None:
        """The current pose (world), None while not localized."""
        return None if self._track is None or self._pending_initial else self._track.pose.copy()

    # -- one scan

    def _select(self, t: float, points, odom, v: float = 0.0, w: float = 0.0) -> bool:
        odom = np.asarray(odom, dtype=float)
        if self.motion is not None:
            odom = self.motion.add(t, points, odom, (v, w))
        step = np.zeros(3) if self._odom_prev is None else between_poses(self._odom_prev, odom)
        self._odom_prev = odom
        self._moved = compose_poses(self._moved, step)
        self._rel = compose_poses(self._rel, step)
        self._since_search = compose_poses(self._since_search, step)
        self._search_travel += math.hypot(step[0], step[1])
        for h in self._hyps:
            h.pose = compose_poses(h.pose, step)
        if self._lost_pose is not None:
            self._lost_pose = compose_poses(self._lost_pose, step)
            self._lost_travel += math.hypot(step[0], step[1])
        if self._track is not None:
            self._track.pose = compose_poses(self._track.pose, step)
        due = (
            math.hypot(self._moved[0], self._moved[1]) >= self.p.every_distance
            or abs(self._moved[2]) >= self.p.every_angle
            or self._last_t_matched is None
        )
        usable = points is not None and len(points) >= self.mp.min_points
        matched = False
        if usable and due:
            if self._track is not None:
                matched = self._track_step(t, points)
            else:
                matched = self._search_step(t, points)
        if matched:
            self._anchor, self._rel = len(self.times), np.zeros(3)
        located = self._track is not None and not self._pending_initial
        self._placed.append((self._anchor if located else -1, self._rel.copy()))
        self.times.append(t)
        self.poses.append(self._track.pose.copy() if located else np.full(3, np.nan))
        self.odometry.append(odom)
        self.matched.append(matched)
        return False

    def _odometry_to(self, t: float):
        """The wheels' motion and covariance from the window's newest pose to ``t``."""
        ts, lr, ll = [], [], []
        while self._samples and self._samples[0][0] <= t:
            a, r, l = self._samples.popleft()
            ts.append(a)
            lr.append(r)
            ll.append(l)
        span = None if self._last_t_window is None else (self._last_t_window, t)
        pre = preintegrate(lr, ll, self._odo, ts, span, self._last_sample_t)
        if ts:
            self._last_sample_t = ts[-1]
        return pre

    def _drop_samples(self, t: float) -> None:
        """No window: the odometry up to ``t`` is not needed."""
        while self._samples and self._samples[0][0] <= t:
            self._last_sample_t = self._samples.popleft()[0]
        self._last_t_window = t

    def _local(self, pose: NDArray[np.float64], points, confirm: bool = False) -> Match | None:
        """The scan matched against the local map at ``pose``; None when the local map's
        scans looked at less than ``min_view`` of the scan placed there (off the map)."""
        view, _ = self.map_check.check(pose, points)
        if view < self.p.min_view:
            self.stats["off_map"] = self.stats.get("off_map", 0) + 1
            return None
        ref = self.places.reference(pose[:2])
        m = match(ref, points, pose, self.mp_confirm if confirm else self.mp)
        if confirm and m.ok and self._contradicted(m.pose, points):
            m = dataclasses.replace(m, ok=False, reason="the map saw through its returns")
        self.stats["matches"] += 1
        if not m.ok:
            self.stats["matches_failed"] += 1
        return m

    def _track_step(self, t: float, points) -> bool:
        tr = self._track
        assert tr is not None
        m = self._local(tr.pose, points)
        self._last_t_matched = t
        self._moved = np.zeros(3)
        if m is None:  # off the map: the odometry carries the pose, nothing is wrong
            return False
        # a match the map contradicts (its returns on cells the map saw free) still places
        # the pose, but a run of them, or of failed matches, says the map is not where the
        # pose is: a kidnapped robot. A weak match where the robot sees much the map did not
        # (a partly mapped room) is no sign of it.
        # (a failed match: the map asked at the prediction)
        through = self.map_check.check(m.pose if m.ok else tr.pose, points)[1]
        good = m.ok and through <= self.p.max_see_through
        tr.fails = 0 if good else tr.fails + 1
        seen_through = through > self.p.max_see_through
        tr.contradicted = 0 if good else tr.contradicted + seen_through
        if tr.fails >= self.p.lost_after:
            why = m.reason or f"{100 * through:.0f} % of the returns on free map cells"
            # most of the run contradicted: the map says the pose is wrong (carried away),
            # not that the robot sees what it does not know: no search near it
            moved = tr.contradicted > tr.fails // 2
            self._lose(t, f"{tr.fails} failed or contradicted matches in a row (the last: {why})")
            if moved:
                self._lost_pose, self._search_now = None, True
            return False
        if not m.ok:
            tr.passes = 0
            return False
        tr.passes += 1
        if self._pending_initial:
            self._pending_initial = False
            self._localized(t, tr, "initial pose", [tr])
        pre = self._odometry_to(t)
        self._last_t_window = t
        self._window.append((len(self.times), t, np.asarray(m.pose, float), m.cov, pre))
        if self.first_fix is None:
            self.first_fix = (t, np.asarray(m.pose, float).copy(), np.asarray(m.cov, float))
        tr.pose = self._smooth()
        return True

    def _smooth(self) -> NDArray[np.float64]:
        """Solve the window (module doc); returns its newest pose, updates the kept poses."""
        win = self._window
        while len(win) > self.p.window:
            self._carry_forward()
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        for i, (_, _, pose, cov, pre) in enumerate(win):
            values.insert(i, gtsam.Pose2(*pose))
            graph.add(gtsam.PriorFactorPose2(i, gtsam.Pose2(*pose), _gauss(cov)))
            if i > 0:
                graph.add(gtsam.BetweenFactorPose2(i - 1, i, pre.delta, _gauss(pre.covariance)))
        if self._carry is not None and self._carry[0] == win[0][0]:
            graph.add(
                gtsam.PriorFactorPose2(0, gtsam.Pose2(*self._carry[1]), _gauss(self._carry[2]))
            )
        try:
            est = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
        except RuntimeError:
            self.stats["window_solve_failures"] = self.stats.get("window_solve_failures", 0) + 1
            return win[-1][2].copy()
        out = np.array([_xyt(est.atPose2(i)) for i in range(len(win))])
        for (scan_i, *_), p in zip(win, out, strict=True):
            if scan_i < len(self.poses):  # (the newest is this scan, recorded after)
                self.poses[scan_i] = p.copy()
        return out[-1].copy()

    def _carry_forward(self) -> None:
        """Drop the window's oldest pose, its information (its match and what it carried)
        passed to the next by the odometry between them."""
        (i0, _, pose0, cov0, _), (i1, _, _, _, pre1) = self._window[0], self._window[1]
        g = gtsam.NonlinearFactorGraph()
        g.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(*pose0), _gauss(cov0)))
        if self._carry is not None and self._carry[0] == i0:
            g.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(*self._carry[1]), _gauss(self._carry[2])))
        g.add(gtsam.BetweenFactorPose2(0, 1, pre1.delta, _gauss(pre1.covariance)))
        v = gtsam.Values()
        v.insert(0, gtsam.Pose2(*self.poses[i0]))
        v.insert(1, gtsam.Pose2(*self.poses[i1]))
        try:
            est = gtsam.LevenbergMarquardtOptimizer(g, v).optimize()
            cov = gtsam.Marginals(g, est).marginalCovariance(1)
            self._carry = (i1, _xyt(est.atPose2(1)), cov)
        except RuntimeError:
            self._carry = None
        self._window.popleft()

    def _lose(self, t: float, why: str) -> None:
        self.events.append({"event": "lost", "t": round(t, 3), "why": why})
        assert self._track is not None
        self._lost_pose, self._lost_travel = self._track.pose.copy(), 0.0
        self._next_recover = 0.0
        self._track = None
        self._pending_initial = False
        self._window.clear()
        self._carry = None
        self._hyps = []
        self._search_now = False  # the search near the dead-reckoned pose first
        self._since_search = np.zeros(3)
        self._last_t_window = None

    def _search_step(self, t: float, points) -> bool:
        if self._lost_pose is not None and self._recover(t, points):
            return True
        if self._hyps:
            return self._confirm_step(t, points)
        moved = math.hypot(self._since_search[0], self._since_search[1])
        if not self._search_now and (
            moved < self._retry * self.p.spacing and abs(self._since_search[2]) < RETRY_THETA
        ):
            return False
        if self._lost_pose is not None and self._lost_travel < self.p.search_after:
            return False  # the search near the dead-reckoned pose alone, for now
        self._since_search = np.zeros(3)
        self._search_travel = 0.0
        self._search_now = False
        hyps = self._global(points)
        rivals = [h.score for h in hyps[1:2]] + [self._rival]
        if hyps and hyps[0].score - max(rivals) < self.p.confirm_margin:
            # no answer stands out (a corridor's doors, a symmetric room seen from its
            # middle): the truth may not even be among them; search again further on
            self.stats["global_ambiguous"] = self.stats.get("global_ambiguous", 0) + 1
            hyps = []
        # nothing found: the robot is somewhere the map does not show; search less often
        self._retry = RETRY_XY if hyps else min(2 * self._retry, RETRY_MAX)
        self._hyps = hyps
        self._drop_samples(t)
        self._last_t_matched = t
        self._moved = np.zeros(3)
        return False

    def _recover(self, t: float, points) -> bool:
        """Lost: the scan searched for around the pose the odometry carried on since, in a
        window growing with the travel (``RECOVER_XY`` + ``RECOVER_GROWTH`` per metre, at most
        ``spacing``; the heading's ``RECOVER_THETA`` likewise, at most doubled: a half turn
        away, a symmetric room's twin would fit), with the global answers' tests."""
        assert self._lost_pose is not None
        d = self._lost_travel
        if d < self._next_recover:
            return False
        self._next_recover = d + RECOVER_EVERY
        wide = dataclasses.replace(
            self.mp_global,
            search_xy=min(RECOVER_XY + RECOVER_GROWTH * d, self.p.spacing),
            search_theta=min(RECOVER_THETA * (1.0 + RECOVER_GROWTH * d), 2 * RECOVER_THETA),
            angular_step=0.0,
        )
        if self.map_check.check(self._lost_pose, points)[0] < self.p.min_view:
            return False  # off the map: nothing to recover on
        m = match(self.places.reference(self._lost_pose[:2]), points, self._lost_pose, wide)
        self.stats["recovery_matches"] = self.stats.get("recovery_matches", 0) + 1
        if not m.ok or self._contradicted(m.pose, points):
            return False
        tr = _Track(np.asarray(m.pose, float), passes=1, score=m.score, scores=[m.score])
        self._track, self._lost_pose, self._hyps = tr, None, []
        self._localized(t, tr, "search near the dead-reckoned pose", [tr])
        self._drop_samples(t)
        self._last_t_matched = t
        self._moved = np.zeros(3)
        return True

    def _contradicted(self, pose: NDArray[np.float64], points) -> bool:
        """A global answer the map contradicts: its returns fall where the map saw little
        (less than ``min_view``) or, more than ``max_see_through`` of them, on free cells."""
        view, through = self.map_check.check(pose, points)
        bad = view < self.p.min_view or through > self.p.max_see_through
        if bad:
            self.stats["answers_contradicted"] = self.stats.get("answers_contradicted", 0) + 1
        return bad

    def _global(self, points) -> list[_Track]:
        """Every place searched over +-spacing and every heading: the distinct passing
        answers, best first."""
        self.stats["global_searches"] += 1
        wide = self.mp_global
        found: list[Match] = []
        self._rival = 0.0  # the best answer too ambiguous to take (a featureless stretch)
        for a in range(len(self.places)):
            x, y = self.places.xy[a]
            m = match(self.places.reference((x, y)), points, (x, y, 0.0), wide)
            vague = not m.ok and m.reason.startswith("ambiguous")
            if (m.ok or vague) and not self._contradicted(m.pose, points):
                if m.ok:
                    found.append(m)
                else:
                    self._rival = max(self._rival, m.score)
        found.sort(key=lambda m: -m.score)
        hyps: list[_Track] = []
        for m in found:
            p = np.asarray(m.pose, float)
            if all(
                math.hypot(*(p[:2] - h.pose[:2])) > HYP_XY
                or abs(wrap_angle(float(p[2] - h.pose[2]))) > HYP_THETA
                for h in hyps
            ):
                hyps.append(_Track(p, passes=1, score=m.score, scores=[m.score]))
            if len(hyps) >= self.p.hypotheses:
                break
        self.stats["global_answers"] = self.stats.get("global_answers", 0) + len(hyps)
        return hyps

    def _confirm_step(self, t: float, points) -> bool:
        self._drop_samples(t)
        self._last_t_matched = t
        self._moved = np.zeros(3)
        for h in self._hyps:
            m = self._local(h.pose, points, confirm=True)
            if m is None:  # off the map: no evidence either way
                continue
            h.scores.append(m.score)
            if m.ok:
                h.pose = np.asarray(m.pose, float)
                h.passes += 1
                h.fails = 0
                h.score = m.score
            else:
                h.fails += 1
                h.passes = 0
        n_found = len(self._hyps)
        c = self.p.confirm
        alive = [h for h in self._hyps if h.fails < self.p.lost_after]
        alive.sort(key=lambda h: -h.recent(c))
        self._hyps = alive
        if not alive or self._search_travel > EXPIRE_TRAVEL * self.p.spacing:
            self._hyps = []  # all dead, or none stood out for long: search again
            self._search_now = True
            return False
        best = alive[0]
        clear = len(alive) == 1 or best.recent(c) - alive[1].recent(c) >= self.p.confirm_margin
        far = self._search_travel >= CONFIRM_TRAVEL * self.p.spacing
        if best.passes >= c and clear and (far or len(alive) == 1):
            self._hyps = []
            self._track = _Track(best.pose.copy(), passes=best.passes)
            self._localized(t, best, "global search", alive, n_found)
            self._window.clear()
            self._carry = None
            return True
        return False

    def _localized(
        self, t: float, tr: _Track, how: str, hyps: list[_Track], found: int = 1
    ) -> None:
        self.events.append(
            {
                "event": "localized",
                "t": round(t, 3),
                "how": how,
                "pose": [round(float(v), 4) for v in tr.pose],
                "confirming_matches": int(tr.passes),
                "answers_found": int(found),
                "answers_left": len(hyps),
                "score": round(float(tr.score), 3),
                "recent_score": round(tr.recent(self.p.confirm), 3),
                "next_recent_score": round(hyps[1].recent(self.p.confirm), 3)
                if len(hyps) > 1
                else None,
            }
        )

    # -- the end

    def finish(self) -> LocalizationResult:
        """Process what the reorder buffer holds and return the result."""
        t0 = time.perf_counter()
        for e in self.reorder.flush():
            self._process(e)
        self.frontend.finish()
        self.busy_seconds += time.perf_counter() - t0
        n = len(self.times)
        poses = np.array(self.poses).reshape(n, 3)
        for i, (anchor, rel) in enumerate(self._placed):  # scans between matched ones
            if anchor >= 0 and anchor != i and np.isfinite(poses[anchor]).all():
                poses[i] = compose_poses(poses[anchor], rel)
        return LocalizationResult(
            times=np.array(self.times),
            poses=poses,
            matched=np.array(self.matched, dtype=bool),
            odometry=np.array(self.odometry).reshape(n, 3),
            events=self.events,
            stats=dict(self.stats),
            truth_t=np.array(self.truth_t),
            truth=np.array(self.truth).reshape(-1, 3),
            wall_time=time.perf_counter() - self.t0 if self.count_idle else self.busy_seconds,
            log_duration=(self.last_t - self.first_t) if self.first_t is not None else 0.0,
            places=len(self.places),
        )


def _gauss(cov: NDArray[np.float64]) -> gtsam.noiseModel.Base:
    return gtsam.noiseModel.Gaussian.Covariance(np.asarray(cov, dtype=float))


def _xyt(p: gtsam.Pose2) -> NDArray[np.float64]:
    return np.array([p.x(), p.y(), p.theta()])
