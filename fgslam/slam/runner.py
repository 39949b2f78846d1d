"""The SLAM pipeline: events -> front end -> map management -> backend, and its result.

One keyframe per front-end output (a laser scan, after its 6 s sonar window), with the
odometry samples between keyframes preintegrated. The first keyframe is anchored at the
log's true pose when it has one (so errors and NEES need no alignment), else at the origin.
"""

from __future__ import annotations

import math
import time
from collections import Counter, deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from factors.odometry import OdometryParams, integrate_poses, preintegrate
from fgslam.config import RobotConfig
from fgslam.events import Event, OdometryEvent, TruthPose
from fgslam.frontend.pipeline import FrontEnd
from fgslam.slam import models
from fgslam.slam.backend import Backend
from fgslam.slam.ekf import EkfBackend
from fgslam.slam.graph import GraphBackend
from fgslam.slam.mapping import Landmark, MapManager, MapParams

BACKENDS = ("ekf", "isam2", "batch")
SENSORS = ("fused", "laser", "sonar")


def make_backend(name: str) -> Backend:
    if name == "ekf":
        return EkfBackend()
    if name in ("isam2", "batch"):  # batch: the iSAM2 graph, solved by LM at the end
        return GraphBackend()
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
    odometry: NDArray[np.float64]  # odometry alone at the keyframes, from the same start
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

    @property
    def has_truth(self) -> bool:
        return len(self.truth) > 1


class _Session:
    """One backend with its own map manager, fed the shared keyframes."""

    def __init__(self, backend: str, map_params: MapParams | None) -> None:
        self.be = make_backend(backend)
        self.mapper = MapManager(map_params)
        self.stats: Counter = Counter()
        self.latencies: list[float] = []
        self.filtered: list[NDArray[np.float64]] = []
        self.landmark_counts: list[int] = []
        self.started = False
        self.wall = 0.0

    def keyframe(self, sf, pre, pose0: NDArray[np.float64]) -> None:
        t0 = time.perf_counter()
        be, mapper = self.be, self.mapper
        if not self.started:
            be.start(sf.t, pose0, np.eye(3) * 1e-8)
            self.started = True
        else:
            be.predict(sf.t, pre)
        dec = mapper.associate(sf.t, sf.features, be.pose(), be.means(), be.estimate)
        for keep, drop in dec.merge:
            be.merge(keep, drop)
        for lid, f in dec.observe:
            be.observe(mapper.resolve(lid), f)
        for lid, f in dec.new:
            be.add_landmark(lid, f)
        be.commit()
        mapper.update_geometry(dec, be.pose(), be.means())
        self.stats.update(dec.stats)
        self.filtered.append(be.pose())
        dt = time.perf_counter() - t0
        self.landmark_counts.append(len(mapper.landmarks))
        self.latencies.append(dt)
        self.wall += dt


def run_slam(
    events: Iterable[Event],
    cfg: RobotConfig,
    backend: str = "isam2",
    sensors: str = "fused",
    progress: Callable[[float], None] | None = None,
    map_params: MapParams | None = None,
) -> SlamResult:
    """Run SLAM with one backend over an event stream; see :func:`run_backends`."""
    return run_backends(events, cfg, [backend], sensors, progress, map_params)[0]


def run_backends(
    events: Iterable[Event],
    cfg: RobotConfig,
    backends: list[str],
    sensors: str = "fused",
    progress: Callable[[float], None] | None = None,
    map_params: MapParams | None = None,
) -> list[SlamResult]:
    """Run several backends on one pass of the front end over an event stream (in time order;
    out-of-order events are dropped and counted). Each backend has its own map manager, so
    associations follow its own estimates. ``batch`` shares the iSAM2 run's graph when both
    are asked for: it is that graph solved by Levenberg-Marquardt at the end. ``progress`` is
    called with each event's time. Results come in the order of ``backends``."""
    if sensors not in SENSORS:
        raise ValueError(f"unknown sensor mode {sensors!r}; expected one of {SENSORS}")
    for b in backends:
        if b not in BACKENDS:
            raise ValueError(f"unknown backend {b!r}; expected one of {BACKENDS}")
    t_start = time.perf_counter()
    graph_names = [b for b in backends if b in ("isam2", "batch")]
    sessions: dict[str, _Session] = {}
    for b in backends:
        if b == "ekf":
            sessions[b] = _Session("ekf", map_params)
        elif b in graph_names and "graph" not in sessions:
            sessions["graph"] = _Session("isam2", map_params)
    fe = FrontEnd(cfg, sensors)
    o = cfg.odometry
    odo_params = OdometryParams(o.wheelbase, o.k_r, o.k_l, o.k_d)
    samples: deque[tuple[float, float, float]] = deque()
    truth_t: list[float] = []
    truth: list[tuple[float, float, float]] = []
    stats: Counter = Counter()
    kf_times: list[float] = []
    kf_odo: list[NDArray[np.float64]] = []
    last_t = -math.inf
    first_t = None
    odo_pose = np.zeros(3)
    fe_wall = 0.0

    def keyframe(sf) -> None:
        nonlocal odo_pose
        lr, ll = [], []
        while samples and samples[0][0] <= sf.t:
            _, r, l = samples.popleft()
            lr.append(r)
            ll.append(l)
        pre = preintegrate(lr, ll, odo_params)
        if not kf_times:
            odo_pose = _truth_at(truth_t, truth, sf.t)
        elif lr:
            odo_pose = integrate_poses(lr, ll, o.wheelbase, odo_pose)[-1]
        for sess in sessions.values():
            sess.keyframe(sf, pre, odo_pose if not kf_times else None)
        stats.update({f"frontend_{k}": v for k, v in sf.stats.items()})
        kf_times.append(sf.t)
        kf_odo.append(odo_pose.copy())

    for ev in events:
        if ev.t < last_t:
            stats["events_out_of_order"] += 1
            continue
        last_t = ev.t
        if first_t is None:
            first_t = ev.t
        if isinstance(ev, TruthPose):
            truth_t.append(ev.t)
            truth.append((ev.x, ev.y, ev.theta))
            continue
        if isinstance(ev, OdometryEvent):
            samples.append(
                (
                    ev.t,
                    ev.ticks_right * o.metres_per_tick_right,
                    ev.ticks_left * o.metres_per_tick_left,
                )
            )
        t0 = time.perf_counter()
        out = fe.add(ev)
        fe_wall += time.perf_counter() - t0
        for sf in out:
            keyframe(sf)
        if progress is not None:
            progress(ev.t)
    t0 = time.perf_counter()
    out = fe.finish()
    fe_wall += time.perf_counter() - t0
    for sf in out:
        keyframe(sf)
    total = time.perf_counter() - t_start
    # the shared work (reading, front end) is charged to every backend
    shared = total - sum(s.wall for s in sessions.values())
    common = dict(
        kf_odo=kf_odo,
        truth_t=truth_t,
        truth=truth,
        stats=stats,
        shared=shared,
        first_t=first_t,
        last_t=last_t,
        sensors=sensors,
    )
    # (session, name) in the order to finish them: iSAM2's estimate before the batch solve
    order = [("ekf", "ekf"), ("graph", "isam2"), ("graph", "batch")]
    results: dict[str, SlamResult] = {}
    for key, name in order:
        if key not in sessions or name not in backends:
            continue
        sess = sessions[key]
        if name == "batch":
            sess.be.run_batch()
        results[name] = _result(sess, name, **common)
    for r in results.values():
        r.stats["frontend_seconds"] = round(fe_wall, 3)
    return [results[b] for b in backends]


def _result(
    sess, name, *, kf_odo, truth_t, truth, stats, shared, first_t, last_t, sensors
) -> SlamResult:
    """Finish one session's backend and package its result; ``shared`` (s) is the reading
    and front-end time that every backend of the pass is charged with."""
    t0 = time.perf_counter()
    traj = sess.be.finish()
    means = {
        lid: models.normalize(sess.mapper.landmarks[lid].kind, m)
        for lid, m in sess.be.means().items()
    }
    covs = sess.be.landmark_covariances()
    finish = time.perf_counter() - t0
    st = Counter(stats)
    st.update(sess.stats)
    if name == "batch":
        sess_wall = sess.wall + getattr(sess.be, "batch_seconds", 0.0)
    else:
        sess_wall = sess.wall
    return SlamResult(
        backend=name,
        sensors=sensors,
        times=np.array([p[0] for p in traj]),
        poses=np.array([p[1] for p in traj]).reshape(-1, 3),
        covs=[p[2] for p in traj],
        filtered=np.array(sess.filtered).reshape(-1, 3),
        odometry=np.array(kf_odo).reshape(-1, 3),
        landmarks={lid: lm for lid, lm in sess.mapper.landmarks.items() if lm.active},
        means=means,
        landmark_covs=covs,
        truth_t=np.array(truth_t),
        truth=np.array(truth).reshape(-1, 3),
        latencies=list(sess.latencies),
        wall_time=shared + sess_wall + finish,
        log_duration=(last_t - first_t) if first_t is not None else 0.0,
        stats=st,
        batch_seconds=getattr(sess.be, "batch_seconds", 0.0) if name == "batch" else 0.0,
        landmark_counts=list(sess.landmark_counts),
    )


def _truth_at(
    t_ref: list[float], poses: list[tuple[float, float, float]], t: float
) -> NDArray[np.float64]:
    if not t_ref:
        return np.zeros(3)
    from fgslam.evaluation import interpolate_poses

    return interpolate_poses(t_ref, poses, [t])[0]
