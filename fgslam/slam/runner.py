"""The SLAM pipeline: events -> front end -> scan odometry and keyframes -> map management ->
backend, and its result.

Each front-end output (a laser scan, after its 6 s sonar window) goes to the scan odometry
(:mod:`fgslam.slam.keyframes`), which matches it against the last keyframe's scan and decides
whether it is a keyframe (policy ``motion`` by default, ``every-scan`` the paper's); the
odometry samples between keyframes are preintegrated, and a keyframe is linked to the last by
the wheel odometry, the scan match or both (``odometry``). Scans between keyframes keep their
pose relative to their keyframe, so the result has a pose at every scan. The first keyframe
is anchored at the log's true pose when it has one (so errors and NEES need no alignment),
else at the origin.

:class:`SlamPipeline` takes events one at a time (``fgslam online`` feeds it as data arrives;
:func:`run_backends` loops over a log with it); a :class:`ReorderBuffer` in front of it puts
events that arrive slightly out of time order (laser scans stamped at their first byte) back
in order.
"""

from __future__ import annotations

import math
import time
from collections import Counter, deque
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from factors.geometry import between_poses, compose_poses
from factors.odometry import integrate_poses, preintegrate
from fgslam.config import RobotConfig
from fgslam.config.robot import KeyframeParams, LoopParams, MapParams
from fgslam.events import Event, OdometryEvent, TruthPose
from fgslam.frontend.pipeline import FrontEnd
from fgslam.io.ordering import REORDER_WINDOW, ReorderBuffer
from fgslam.scanmatch import MatchParams
from fgslam.slam import models
from fgslam.slam.association import METHODS
from fgslam.slam.backend import Backend
from fgslam.slam.calibration import Calibration
from fgslam.slam.ekf import EkfBackend
from fgslam.slam.graph import GraphBackend
from fgslam.slam.graph_solve import BackendError, BatchSmoother
from fgslam.slam.keyframes import ScanOdometry
from fgslam.slam.lifecycle import Landmark
from fgslam.slam.loops import LoopCloser
from fgslam.slam.step import SlamStep

BACKENDS = ("ekf", "isam2", "batch")
SENSORS = ("fused", "laser", "sonar")


def make_backend(
    name: str,
    cfg: RobotConfig,
    keyframes: KeyframeParams | None = None,
    calibration: Calibration | NDArray[np.float64] | None = None,
) -> Backend:
    """A backend by name, built from ``cfg``: the EKF's gate between wheel odometry and a scan
    match of one link (``keyframes.motion_gate_p``, default ``cfg.keyframes``;
    :meth:`EkfBackend.predict`), the graph's solver settings (``cfg.graph``) and sonar timing
    (``cfg.sonar.timing``; the EKF has only the scan frame), the scan's time error where it
    is modelled per scan (``cfg.laser``); ``calibration``: the calibration errors to estimate
    (:meth:`Calibration.from_config`; None: off)."""
    if name == "ekf":
        gate = (keyframes or KeyframeParams.from_config(cfg)).motion_gate_p
        return EkfBackend(
            motion_gate_p=gate,
            calibration=calibration,
            time_sigma=cfg.laser.time_sigma("per-scan"),
        )
    if name in ("isam2", "batch"):  # batch: the iSAM2 graph, solved by LM at the end
        g = cfg.graph
        return GraphBackend(
            robust=g.robust,
            merge_sigma=g.merge_sigma,
            relinearize_threshold=g.relinearize_threshold,
            relinearize_skip=g.relinearize_skip,
            refresh_every=g.refresh_every,
            max_final_updates=g.max_final_updates,
            converge_tol=g.converge_tol,
            loop_updates=g.loop_updates,
            calibration=calibration,
            sonar_timing=cfg.sonar.timing,
            factorization=g.factorization,
            time_sigma=cfg.laser.time_sigma("per-scan"),
        )
    raise ValueError(f"unknown backend {name!r}; expected one of {BACKENDS}")


@dataclass
class SlamResult:
    """Everything a run produced; see :mod:`fgslam.slam.outputs` for the files."""

    backend: str
    sensors: str
    times: NDArray[np.float64]
    poses: NDArray[np.float64]  # final estimate per keyframe (smoothed for graphs)
    covs: list[NDArray[np.float64] | None]
    filtered: NDArray[np.float64]  # the estimate available at each keyframe's time
    # odometry alone at the keyframes of the pass, from the same start: every keyframe the
    # front end made, so more than ``times`` when this backend failed mid-run (partial)
    odometry: NDArray[np.float64]
    landmarks: dict[int, Landmark]
    means: dict[int, NDArray[np.float64]]
    landmark_covs: dict[int, NDArray[np.float64]]
    truth_t: NDArray[np.float64]
    truth: NDArray[np.float64]
    latencies: list[float]
    wall_time: float
    log_duration: float
    stats: Counter = field(default_factory=Counter)
    batch_seconds: float = 0.0
    landmark_counts: list[int] = field(default_factory=list)  # landmarks after each keyframe
    # every odometry sample (t, L_r, L_l) in m, for the trajectory between keyframes
    odometry_samples: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 3)))
    # the pose at every scan (keyframes and the scans between them, placed with their scan
    # odometry relative to their keyframe's final estimate), time order
    scan_times: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    scan_poses: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 3)))
    loop_closures: list[dict] = field(default_factory=list)  # every attempt (loops.Closure)
    # each keyframe's laser points (robot frame, m; None: no laser), as ``times``
    keyframe_scans: list[NDArray[np.float64] | None] = field(default_factory=list)
    # each keyframe's link from the keyframe before ((x, y, theta) in its frame, covariance
    # in the between convention, "scan" (the scan match) or "odometry" (the wheels alone);
    # None: none), one fewer than ``times``
    keyframe_links: list = field(default_factory=list)
    # a continued session (fgslam.session.join): what was continued, its keyframes (first
    # in ``times``, their times shifted by time_offset s), the anchor; None: a new map
    continued: dict | None = None
    # the calibration errors estimated: {"parameters": names (Calibration), "estimate": [...],
    # "sigma": [...] or None}; None when not estimated
    calibration: dict | None = None
    # the times (s) of ``filtered`` and of ``odometry``; None: ``times``
    filtered_times: NDArray[np.float64] | None = None
    odometry_times: NDArray[np.float64] | None = None

    @property
    def has_truth(self) -> bool:
        return len(self.truth) > 1

    def tracks(self) -> dict[str, tuple[NDArray[np.float64], NDArray[np.float64]]]:
        """The run's trajectories, each with its own times: (times in s, (n, 3) world poses in
        m, rad) of the final estimate ("estimate"), the estimate as available at each
        keyframe ("online") and odometry alone ("odometry"). Their lengths may differ (a
        backend that failed mid-run has fewer keyframes than the odometry track)."""
        return {
            "estimate": (self.times, self.poses),
            "online": (
                self.times if self.filtered_times is None else self.filtered_times,
                self.filtered,
            ),
            "odometry": (
                self.times if self.odometry_times is None else self.odometry_times,
                self.odometry,
            ),
        }

    @property
    def every_scan(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """(times, poses) at every scan: keyframes and the scans between them."""
        if len(self.scan_times) >= len(self.times):
            return self.scan_times, self.scan_poses
        return self.times, self.poses


class _Session(SlamStep):
    """One backend with its own map, fed the shared keyframes; stops at a backend failure
    (``failed``: keyframe, time and the backend's message)."""

    def __init__(
        self,
        backend: str,
        cfg: RobotConfig,
        map_params: MapParams,
        keyframes: KeyframeParams,
        loops: LoopCloser | None = None,
        calibration: Calibration | None = None,
    ) -> None:
        super().__init__(make_backend(backend, cfg, keyframes, calibration), map_params, loops)
        self.failed: dict | None = None
        self.filtered_times: list[float] = []  # s, one per entry of ``filtered``

    def feed(
        self, sf, pre, pose0: NDArray[np.float64] | None, scan=None, speed=(0.0, 0.0), anchor=None
    ):
        if self.failed is not None:
            return
        try:
            self.keyframe(
                sf.t,
                sf.features,
                pre,
                pose0,
                scan=scan,
                points=sf.points,
                speed=speed,
                anchor=anchor,
            )
        except BackendError as exc:
            self.failed = {"keyframe": self.k, "t": float(sf.t), "error": str(exc)}
        else:  # a keyframe that completed added its pose to ``filtered``
            self.filtered_times.append(float(sf.t))


def run_slam(
    events: Iterable[Event],
    cfg: RobotConfig,
    backend: str = "isam2",
    sensors: str = "fused",
    progress: Callable[[float], None] | None = None,
    association: str | None = None,
    continuation=None,
) -> SlamResult:
    """Run SLAM with one backend over an event stream; see :func:`run_backends`."""
    return run_backends(
        events,
        cfg,
        [backend],
        sensors,
        progress,
        association=association,
        continuation=continuation,
    )[0]


class SlamPipeline:
    """The incremental pipeline: events in, one at a time, as they come; results at the end.

    Events pass a :class:`ReorderBuffer` (``reorder_window`` s of log time; events later
    than that are dropped and counted as ``events_out_of_order``), then the front end; each
    keyframe it completes goes to every backend's session (each with its own map manager).
    :meth:`add` returns how many keyframes the event completed; :meth:`pose`,
    :meth:`landmark_counts`, :attr:`last_latency` and :attr:`keyframes` describe the current
    state; :meth:`finish` processes what is still waiting and returns one
    :class:`SlamResult` per backend, in the order of ``backends``.

    ``association`` ("jcbb" default, or "nn") overrides ``map_params.association``.

    ``keyframes`` (default: from the configuration's ``[scanmatch]``) sets the keyframe
    policy and which odometry links keyframes; ``loops`` the loop-closure search (graph
    backends only). Sonar-only runs keep the paper's scheme: every step a keyframe, wheels.

    A backend failure (:class:`fgslam.slam.graph.BackendError`, e.g. an indeterminate
    system) during a keyframe stops feeding that backend only; the others go on. Its
    :class:`SlamResult` from :meth:`finish` then holds the estimate up to the last good
    keyframe, with ``result.stats["partial"] = {"keyframe": k, "t": t, "error": message}``
    (a JSON-serialisable dict; k the failed keyframe's index, t its time in s, the message
    naming the variable GTSAM reported).

    ``wall_time`` of the results: with ``count_idle`` (running over a log) the time since
    the pipeline was created, reading included; without (online, where the pipeline waits
    for data) only the time spent in :meth:`add` and :meth:`finish`.
    """

    def __init__(
        self,
        cfg: RobotConfig,
        backends: Sequence[str] = ("isam2",),
        sensors: str = "fused",
        map_params: MapParams | None = None,
        *,
        progress: Callable[[float], None] | None = None,
        reorder_window: float = REORDER_WINDOW,
        count_idle: bool = True,
        association: str | None = None,
        keyframes: KeyframeParams | None = None,
        loops: LoopParams | None = None,
        continuation=None,
    ) -> None:
        if sensors not in SENSORS:
            raise ValueError(f"unknown sensor mode {sensors!r}; expected one of {SENSORS}")
        backends = list(backends)
        for b in backends:
            if b not in BACKENDS:
                raise ValueError(f"unknown backend {b!r}; expected one of {BACKENDS}")
        self._t_start = time.perf_counter()
        self.cfg = cfg
        self.backends = backends
        self.sensors = sensors
        self.progress = progress
        self.count_idle = count_idle
        map_params = map_params or MapParams.from_config(cfg)
        if association is not None:
            if association not in METHODS:
                raise ValueError(f"unknown association {association!r}; expected one of {METHODS}")
            map_params = replace(map_params, association=association)
        self.sessions: dict[str, _Session] = {}
        kp = keyframes or KeyframeParams.from_config(cfg)
        lp = loops or LoopParams.from_config(cfg)
        if sensors == "sonar":  # the paper's scheme: no laser to match
            kp = replace(kp, policy="every-scan", odometry="wheels")
            lp = replace(lp, enabled=False)
        self.keyframe_params = kp
        mp = MatchParams.from_config(cfg)
        origin = (cfg.laser.mount.x, cfg.laser.mount.y)
        self.scan_odometry = ScanOdometry(kp, mp, origin, cfg.laser.sigma_time)
        self._between: list[tuple[float, int, NDArray[np.float64]]] = []  # non-keyframes
        self._kf_rel: list[NDArray[np.float64]] = []  # each keyframe's scan-odometry motion
        self._kf_points: list[NDArray[np.float64] | None] = []  # each keyframe's scan
        self._kf_links: list = []  # each keyframe's scan match to the one before (or None)
        cal = Calibration.from_config(cfg)
        for b in backends:
            if b == "ekf":
                self.sessions[b] = _Session("ekf", cfg, map_params, kp, None, cal)
            elif b in ("isam2", "batch") and "graph" not in self.sessions:
                loop = LoopCloser(lp, mp, origin, cfg.laser.sigma_time) if lp.enabled else None
                self.sessions["graph"] = _Session("isam2", cfg, map_params, kp, loop, cal)
        self.continuation = continuation
        self.reorder = ReorderBuffer(reorder_window)
        self.frontend = FrontEnd(cfg, sensors, select=self._select)
        self._steps: deque = deque()  # the scan odometry's decisions, in scan order
        o = cfg.odometry
        self._odo_params = o.params()
        self._samples: deque[tuple[float, float, float]] = deque()
        self._all_samples: list[tuple[float, float, float]] = []
        self._last_sample_t: float | None = None  # of the samples already preintegrated
        self.truth_t: list[float] = []
        self.truth: list[tuple[float, float, float]] = []
        self.stats: Counter = Counter()
        self.kf_times: list[float] = []
        self._kf_odo: list[NDArray[np.float64]] = []
        self.first_t: float | None = None
        self.last_t = -math.inf  # time of the last event processed
        self._odo_pose = np.zeros(3)
        self._fe_wall = 0.0
        self._busy = 0.0
        self._finished: list[SlamResult] | None = None
        if continuation is not None:
            self._restore(continuation)

    def _restore(self, c) -> None:
        """A continued session (:mod:`fgslam.session.join`): the graph starts from its
        keyframes; the log is mapped from the anchor's scan on."""
        if "ekf" in self.sessions or "graph" not in self.sessions:
            raise ValueError("the EKF keeps no past keyframes: continue a session with isam2")
        links, loops, missing = c.replay()
        s = c.session
        self.sessions["graph"].restore(c.times(), s.poses, s.scans, links, loops)
        if missing:
            self.stats["continued_links_missing"] = missing

    # -- feeding

    def add(self, ev: Event) -> int:
        """Take one event (any order within the reorder window); returns the number of
        keyframes processed because of it."""
        if self._finished is not None:
            raise RuntimeError("the pipeline has finished")
        t0 = time.perf_counter()
        n = 0
        dropped = self.reorder.dropped
        for e in self.reorder.push(ev):
            n += self._process(e)
        if self.reorder.dropped > dropped:
            self.stats["events_out_of_order"] += 1
        self._busy += time.perf_counter() - t0
        return n

    def _process(self, ev: Event) -> int:
        self.last_t = ev.t
        if self.first_t is None:
            self.first_t = ev.t
        if self.continuation is not None and ev.t < self.continuation.anchor.t:
            self.stats["events_before_anchor"] += 1  # not on the map yet
            return 0
        if isinstance(ev, TruthPose):
            self.truth_t.append(ev.t)
            self.truth.append((ev.x, ev.y, ev.theta))
            return 0
        if isinstance(ev, OdometryEvent):
            sample = (ev.t, *self.cfg.odometry.wheel_travel(ev.ticks_right, ev.ticks_left))
            self._samples.append(sample)
            self._all_samples.append(sample)
        t0 = time.perf_counter()
        out = self.frontend.add(ev)
        self._fe_wall += time.perf_counter() - t0
        n = sum(self._scan(sf) for sf in out)
        if self.progress is not None:
            self.progress(ev.t)
        return n

    def _select(self, t: float, points, odom, v: float = 0.0, w: float = 0.0) -> bool:
        """The front end asks, scan by scan in time order, whether to extract features: the
        scan odometry decides whether the scan is a keyframe (in fused mode a few scans may
        be decided before the last keyframe's map support is known)."""
        step = self.scan_odometry.add(points, odom, (v, w))
        self._steps.append(step)
        return step.keyframe

    def _scan(self, sf) -> bool:
        """One front-end output: a keyframe (True), or a scan carried by its keyframe."""
        step = self._steps.popleft()
        if not step.keyframe:
            self._between.append((sf.t, len(self.kf_times) - 1, step.rel))
            self.stats["scans_between_keyframes"] += 1
            return False
        scan = step.scan if self.keyframe_params.odometry != "wheels" else None
        self._kf_rel.append(step.rel)
        self._kf_points.append(step.points)
        self._keyframe(sf, scan, step.speed)
        sess = next(iter(self.sessions.values()))
        self.scan_odometry.map_support(len(sf.features) if sess.p.landmarks else 0, sess.tracked)
        return True

    def _keyframe(self, sf, scan=None, speed=(0.0, 0.0)) -> None:
        o = self.cfg.odometry
        samples = self._samples
        ts, lr, ll = [], [], []
        while samples and samples[0][0] <= sf.t:
            t, r, l = samples.popleft()
            ts.append(t)
            lr.append(r)
            ll.append(l)
        first = not self.kf_times
        span = None if first else (self.kf_times[-1], sf.t)
        pre = preintegrate(lr, ll, self._odo_params, ts, span, self._last_sample_t)
        if ts:
            self._last_sample_t = ts[-1]
        if pre.hole_seconds:  # odometry hole: its covariance covers the possible motion
            self.stats["odometry_hole_intervals"] += 1
            self.stats["odometry_hole_seconds"] += round(pre.hole_seconds, 3)
        anchor = None
        if first and self.continuation is not None:
            self._odo_pose, cov = self._anchor_pose(sf.t, ts, lr, ll)
            anchor = self.continuation.first_link(self._odo_pose, cov)
        elif first:
            self._odo_pose = _truth_at(self.truth_t, self.truth, sf.t)
        elif lr:
            self._odo_pose = integrate_poses(lr, ll, o.wheelbase, self._odo_pose)[-1]
        if not first:
            self.stats[
                "keyframes_scan_linked" if scan is not None else "keyframes_wheels_only"
            ] += 1
        wheels = pre
        if scan is not None and self.keyframe_params.odometry == "scan":
            wheels = None  # the scan match alone (wheels only where it was rejected)
        if not first:  # the link into this keyframe, from the one before
            m, kind = (scan, "scan") if scan is not None else (wheels, "odometry")
            self._kf_links.append((_xyt(m.delta), m.covariance, kind) if m is not None else None)
        if anchor is not None:
            wheels = scan = None
        for sess in self.sessions.values():
            sess.feed(sf, wheels, self._odo_pose if first else None, scan, speed, anchor)
        self.stats.update({f"frontend_{k}": v for k, v in sf.stats.items()})
        self.kf_times.append(sf.t)
        self._kf_odo.append(self._odo_pose.copy())

    def _anchor_pose(self, t: float, ts, lr, ll) -> tuple[NDArray[np.float64], NDArray]:
        """A continued run's first keyframe (at ``t``): the anchor's pose and covariance
        (body frame) carried to ``t`` by the wheel samples between them."""
        a = self.continuation.anchor
        pose, cov = np.asarray(a.pose, float), np.asarray(a.cov, float)
        if not lr or t <= a.t:
            return pose.copy(), cov.copy()
        pre = preintegrate(lr, ll, self._odo_params, ts, (a.t, t), None)
        Ad = pre.delta.inverse().AdjointMap()
        return compose_poses(pose, _xyt(pre.delta)), Ad @ cov @ Ad.T + pre.covariance

    # -- state

    def _session(self, backend: str | None) -> _Session:
        name = backend or self.backends[0]
        if name not in self.backends:
            raise ValueError(f"backend {name!r} is not part of this pipeline")
        return self.sessions["ekf" if name == "ekf" else "graph"]

    @property
    def keyframes(self) -> int:
        """Keyframes processed so far."""
        return len(self.kf_times)

    @property
    def pending(self) -> int:
        """Events held by the reorder buffer."""
        return len(self.reorder)

    def pose(self, backend: str | None = None) -> NDArray[np.float64] | None:
        """Current pose estimate (x, y, theta) of ``backend`` (default: the first), None
        before the first keyframe."""
        sess = self._session(backend)
        return sess.be.pose() if sess.started else None

    def landmark_counts(self, backend: str | None = None) -> dict[str, int]:
        """Landmarks in the map by kind (line, corner, point), merged ones left out."""
        counts = Counter(lm.kind for lm in self._session(backend).landmarks.values() if lm.active)
        return dict(counts)

    def last_latency(self, backend: str | None = None) -> float | None:
        """Wall seconds the last keyframe took in ``backend``'s session (map management
        and update), None before the first keyframe."""
        lat = self._session(backend).latencies
        return lat[-1] if lat else None

    @property
    def busy_seconds(self) -> float:
        """Wall seconds spent in :meth:`add` so far (front end and backends)."""
        return self._busy

    def status_text(self) -> str:
        """The estimate in one line: keyframes, pose, landmarks by kind, the last keyframe's
        latency (``fgslam online``'s status)."""
        pose = self.pose()
        if pose is None:
            where = "no keyframe yet"
        else:
            where = f"x {pose[0]:7.2f} y {pose[1]:7.2f} th {math.degrees(pose[2]):6.1f} deg"
        lm = self.landmark_counts()
        kinds = " ".join(f"{lm.get(k, 0)} {k}s" for k in ("line", "corner", "point"))
        lat = self.last_latency()
        lat_s = f"{lat * 1e3:4.0f} ms" if lat is not None else "  - ms"
        return f"kf {self.keyframes:4d} | {where} | {kinds} | kf {lat_s}"

    # -- the end

    def snapshot(self) -> SlamResult:
        """The first backend's estimate so far, finishing nothing (no event is flushed, no
        backend finished): a checkpoint of a long online run. Trajectory: each keyframe's
        pose as estimated at its time; landmarks: their current means."""
        if self._finished is not None:
            return self._finished[0]
        name = self.backends[0]
        sess = self.sessions["ekf" if name == "ekf" else "graph"]
        return _result(
            sess,
            name,
            kf_odo=self._kf_odo,
            kf_times=self.kf_times,
            truth_t=self.truth_t,
            truth=self.truth,
            stats=self.stats,
            shared=0.0,
            first_t=self.first_t,
            last_t=self.last_t,
            sensors=self.sensors,
            final=False,
            between=self._between,
            kf_rel=self._kf_rel,
            kf_points=self._kf_points,
            kf_links=self._kf_links,
            prefix=self.continuation,
        )

    def finish(self) -> list[SlamResult]:
        """Process everything still waiting (held events, scans waiting for their sonar
        window) and return the results, in the order of ``backends``. Idempotent."""
        if self._finished is not None:
            return self._finished
        t_busy = time.perf_counter()
        for e in self.reorder.flush():
            self._process(e)
        if self.reorder.reordered:
            self.stats["events_reordered"] = self.reorder.reordered
        t0 = time.perf_counter()
        out = self.frontend.finish()
        self._fe_wall += time.perf_counter() - t0
        for sf in out:
            self._scan(sf)
        self.stats.update(self.scan_odometry.stats)
        now = time.perf_counter()
        total = now - self._t_start if self.count_idle else self._busy + now - t_busy
        # the shared work (reading, front end) is charged to every backend
        shared = total - sum(s.wall for s in self.sessions.values())
        common = dict(
            kf_odo=self._kf_odo,
            kf_times=self.kf_times,
            truth_t=self.truth_t,
            truth=self.truth,
            stats=self.stats,
            shared=shared,
            first_t=self.first_t,
            last_t=self.last_t,
            sensors=self.sensors,
            between=self._between,
            kf_rel=self._kf_rel,
            kf_points=self._kf_points,
            kf_links=self._kf_links,
            prefix=self.continuation,
        )
        # (session, name) in the order to finish them: iSAM2's estimate before the batch solve
        order = [("ekf", "ekf"), ("graph", "isam2"), ("graph", "batch")]
        results: dict[str, SlamResult] = {}
        for key, name in order:
            if key not in self.sessions or name not in self.backends:
                continue
            sess = self.sessions[key]
            be = BatchSmoother(sess.be) if name == "batch" else sess.be
            results[name] = _result(sess, name, be, **common)
        samples = np.array(self._all_samples, dtype=float).reshape(-1, 3)
        for r in results.values():
            r.stats["frontend_seconds"] = round(self._fe_wall, 3)
            r.odometry_samples = samples
        self._finished = [results[b] for b in self.backends]
        return self._finished


def run_backends(
    events: Iterable[Event],
    cfg: RobotConfig,
    backends: list[str],
    sensors: str = "fused",
    progress: Callable[[float], None] | None = None,
    map_params: MapParams | None = None,
    association: str | None = None,
    keyframes: KeyframeParams | None = None,
    loops: LoopParams | None = None,
    continuation=None,
) -> list[SlamResult]:
    """Run several backends on one pass of the front end over an event stream (in time order
    up to a :class:`ReorderBuffer` window of ``REORDER_WINDOW`` s; later events are dropped
    and counted).
    Each backend has its own map manager, so associations follow its own estimates.
    ``batch`` shares the iSAM2 run's graph when both are asked for: it is that graph solved
    by Levenberg-Marquardt at the end. ``progress`` is called with each event's time.
    Results come in the order of ``backends``. ``association``: "jcbb" (default) or "nn".
    ``continuation``: a saved session to continue (:mod:`fgslam.session.join`).
    See :class:`SlamPipeline`."""
    pipe = SlamPipeline(
        cfg,
        backends,
        sensors,
        map_params,
        progress=progress,
        association=association,
        keyframes=keyframes,
        loops=loops,
        continuation=continuation,
    )
    for ev in events:
        pipe.add(ev)
    return pipe.finish()


def _result(
    sess,
    name,
    be=None,
    *,
    kf_odo,
    kf_times,
    truth_t,
    truth,
    stats,
    shared,
    first_t,
    last_t,
    sensors,
    final=True,
    between=(),
    kf_rel=(),
    kf_points=(),
    kf_links=(),
    prefix=None,
) -> SlamResult:
    """Finish one session's backend and package its result; ``shared`` (s) is the reading
    and front-end time that every backend of the pass is charged with. Not ``final``: the
    estimate so far, finishing nothing (the trajectory as estimated at each keyframe, no
    landmark covariances). ``be``: what gives the results (default the session's backend;
    a :class:`~fgslam.slam.graph.BatchSmoother` of it for "batch"). ``prefix``: the
    continued session (:class:`fgslam.session.join.Continuation`) whose keyframes come first
    in the graph."""
    be = sess.be if be is None else be
    t0 = time.perf_counter()
    traj = be.finish() if final else list(sess.be.trajectory)
    means = {
        lid: models.normalize(sess.map.landmarks[lid].kind, m) for lid, m in be.means().items()
    }
    covs = be.landmark_covariances() if final else {}
    cal = be.calibration_estimate()
    finish = time.perf_counter() - t0
    st = Counter(stats)
    st.update(sess.stats)
    st.update(getattr(sess.be, "stats", {}))  # e.g. the EKF's rejected innovations
    if sess.loops is not None:
        st.update(sess.loops.stats)
    if sess.failed is not None:  # after the updates: Counter cannot add a dict
        st["partial"] = dict(sess.failed)
    if getattr(sess.be, "repairs", None):  # what the graph's guard did, one line each
        st["graph_repair_log"] = list(sess.be.repairs)
    batch_seconds = be.seconds if isinstance(be, BatchSmoother) else 0.0
    sess_wall = sess.wall + batch_seconds
    times = np.array([p[0] for p in traj])
    poses = np.array([p[1] for p in traj]).reshape(-1, 3)
    continued = None
    if prefix is not None:  # the saved keyframes first, then this log's
        kf_rel_new = kf_rel
        n0, saved = prefix.keyframes, prefix.session.poses
        off = prefix.time_offset
        saved_between = [(t + off, int(k), rel) for t, k, *rel in prefix.session.between]
        between = saved_between + [(t, k + n0, rel) for t, k, rel in between if k >= 0]
        # (the saved scans after the last saved keyframe keep their odometry: no link on)
        kf_rel = [np.zeros(3), *between_poses(saved[:-1], saved[1:]), np.full(3, np.nan)]
        kf_rel += list(kf_rel_new[1:])
        kf_points = list(prefix.session.scans) + list(kf_points)
        kf_links = [*prefix.links(), None, *kf_links]
        continued = prefix.to_json()
    scan_t, scan_p = place_scans(times, poses, between, kf_rel)
    return SlamResult(
        keyframe_scans=list(kf_points[: len(times)]),
        keyframe_links=list(kf_links[: max(len(times) - 1, 0)]),
        continued=continued,
        scan_times=scan_t,
        scan_poses=scan_p,
        loop_closures=[c.to_json() for c in sess.loops.closures] if sess.loops else [],
        backend=name,
        sensors=sensors,
        times=times,
        poses=poses,
        covs=[p[2] for p in traj],
        filtered=np.array(sess.filtered).reshape(-1, 3),
        filtered_times=np.array(sess.filtered_times, dtype=float),
        odometry=np.array(kf_odo).reshape(-1, 3),
        odometry_times=np.array(kf_times, dtype=float),
        landmarks={lid: lm for lid, lm in sess.map.landmarks.items() if lm.active},
        means=means,
        landmark_covs=covs,
        truth_t=np.array(truth_t),
        truth=np.array(truth).reshape(-1, 3),
        latencies=list(sess.latencies),
        wall_time=shared + sess_wall + finish,
        log_duration=(last_t - first_t) if first_t is not None else 0.0,
        stats=st,
        batch_seconds=batch_seconds,
        landmark_counts=list(sess.landmark_counts),
        calibration=None
        if cal is None
        else {
            "parameters": list(sess.be.cal.names),
            "estimate": cal[0].tolist(),
            "sigma": None if cal[1] is None else np.sqrt(np.diag(cal[1])).tolist(),
        },
    )


def place_scans(
    times: NDArray[np.float64],
    poses: NDArray[np.float64],
    between: Sequence[tuple[float, int, NDArray[np.float64]]],
    kf_rel: Sequence[NDArray[np.float64]] = (),
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Every scan's world pose (m, rad), in time order: the keyframes' estimates ``poses`` at
    ``times`` and the scans ``between`` them, each (t, keyframe index k, its scan-odometry
    pose in keyframe k's frame).

    A scan between keyframes k and k + 1 is keyframe k's estimate composed with its scan
    odometry, then moved by its share of the correction the estimate made to the scan
    odometry's motion to keyframe k + 1 (``kf_rel[k + 1]``, in keyframe k's frame): E =
    (X_k R_k+1)^-1 X_k+1, applied as a * E (tangent, scaled) with a the scan's progress
    along R_k+1 (travel + 0.5 m/rad x turn, in [0, 1]). The scans then meet keyframe k + 1
    instead of jumping to it; the scans after the last keyframe, or before a keyframe whose
    ``kf_rel`` is NaN (not reached by odometry: a continued session's first), keep their
    odometry."""
    rows = [(t, k, rel) for t, k, rel in between if 0 <= k < len(poses)]
    if not rows:
        return times.copy(), poses.copy()
    k = np.array([r[1] for r in rows])
    rel = np.array([r[2] for r in rows], dtype=float).reshape(-1, 3)
    placed = compose_poses(poses[k], rel)
    n = min(len(poses), len(kf_rel))
    ok = k + 1 < n
    R_all = np.asarray(kf_rel[:n], dtype=float).reshape(-1, 3)
    ok[ok] &= np.isfinite(R_all[k[ok] + 1]).all(axis=1)
    if ok.any():
        kk = k[ok]
        R = R_all[kk + 1]
        E = between_poses(compose_poses(poses[kk], R), poses[kk + 1])
        progress = np.hypot(rel[ok, 0], rel[ok, 1]) + 0.5 * np.abs(rel[ok, 2])
        total = np.hypot(R[:, 0], R[:, 1]) + 0.5 * np.abs(R[:, 2])
        a = np.clip(progress / np.maximum(total, 1e-9), 0.0, 1.0)
        placed[ok] = compose_poses(placed[ok], a[:, None] * E)
    t = np.concatenate([times, [r[0] for r in rows]])
    p = np.vstack([poses, placed])
    order = np.argsort(t, kind="stable")
    return t[order], p[order]


def _xyt(p) -> NDArray[np.float64]:
    return np.array([p.x(), p.y(), p.theta()])


def _truth_at(
    t_ref: list[float], poses: list[tuple[float, float, float]], t: float
) -> NDArray[np.float64]:
    if not t_ref:
        return np.zeros(3)
    from fgslam.evaluation.metrics import interpolate_poses

    return interpolate_poses(t_ref, poses, [t])[0]
