"""Point-landmark SLAM on odometry steps and (x, y) sightings (Victoria Park), through the
project's backends (:class:`~fgslam.slam.backend.Backend`): the paper's EKF, iSAM2 and batch.

Every odometry step is a keyframe: :meth:`Backend.predict` with the step as a
:class:`~factors.odometry.Preintegrated` (its covariance taken as the between factor's; the
steps turn by milliradians, so the frame it is given in hardly matters), then each sighting
as a point :class:`~fgslam.frontend.features.Feature` with z = (bearing, range) and the
covariance carried through the Jacobian of the polar conversion, then :meth:`commit`.
Association is either the file's (``"given"``: the landmark index) or the project's own
(``"own"``: the association and landmark lifecycle of a laser run, with the backend's
joint covariance). Both go through :class:`~fgslam.slam.step.SlamStep`, the SLAM step of
every run. The keyframe "time" is the pose index.

Odometry noise: the file's step covariances, their variances scaled by ``odometry_scale``;
``"self"`` scales them by the self-calibration (:func:`self_calibrate`,
:mod:`~fgslam.slam.point_calibration`: maximum likelihood of the sightings' innovations on
the own association, alternated with it; nothing of the given association).
Not the default: on Victoria Park it measured worse than the hand factor 100
(experiments/README.md, real_victoria_park.py; CHANGELOG.md, issue 12).
"""

from __future__ import annotations

import time
from collections import Counter
from dataclasses import dataclass, field, replace

import gtsam
import numpy as np
from numpy.typing import NDArray

from factors.geometry import compose_poses
from factors.odometry import Preintegrated
from fgslam.config.robot import MapParams
from fgslam.frontend.features import Feature
from fgslam.io.readers.victoria import VictoriaPark, to_bearing_range
from fgslam.slam.backend import Backend
from fgslam.slam.ekf import EkfBackend
from fgslam.slam.graph import GraphBackend
from fgslam.slam.graph_solve import BatchSmoother
from fgslam.slam.point_calibration import (
    Scales,
    association_of,
    fit_scale,
    scaled_covariance,
    sighting_nll,
)
from fgslam.slam.step import SlamStep

BACKENDS = ("ekf", "isam2", "batch")
ASSOCIATIONS = ("given", "own")
# Own association: trees are seen up to ~80 m away, so the candidate radius is wide; the
# residual pre-gate is loose (the chi-square gate decides). The file's sighting covariances
# (sigma 0.63 m) and the drift between trees make the 99 % gate reject true matches and the
# 1-unit ambiguity margin accept close calls: a 99.9 % gate and a margin of 4 (measured,
# CHANGELOG.md, issue 12).
POINT_MAP_PARAMS = MapParams(
    max_range=100.0, pregate=(0.5, 5.0, 0.6), gate_p=0.999, ambiguity_margin=4.0
)


@dataclass
class PointSlamResult:
    backend: str
    association: str
    index: NDArray[np.int64]  # pose index per keyframe
    poses: NDArray[np.float64]  # final estimate (smoothed for graphs), (N, 3)
    filtered: NDArray[np.float64]  # the estimate available at each keyframe
    odometry: NDArray[np.float64]  # the odometry chain alone
    landmarks: dict[int, NDArray[np.float64]]
    wall_time: float
    latencies: list[float]
    stats: Counter = field(default_factory=Counter)
    # own association: the landmark id each sighting went to (-1: none), in file order
    assigned: list[tuple[int, int]] = field(default_factory=list)  # (given index, own id)
    # own association: (pose index, position in that pose's sightings, own id or -1)
    sighting_ids: list[tuple[int, int, int]] = field(default_factory=list)
    odometry_scale: NDArray[np.float64] = field(default_factory=lambda: np.ones(3))


def _pre(delta: NDArray[np.float64], cov: NDArray[np.float64]) -> Preintegrated:
    """A step as preintegrated odometry: the file's covariance serves as the between
    factor's (tangent at the end of the step); ``covariance_start`` (the first pose's axes,
    for the EKF and the association's prediction) is it rotated back by the step's turn."""
    c = np.asarray(cov, dtype=float)
    R = np.eye(3)
    th = float(delta[2])
    R[:2, :2] = [[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]]
    start = R @ c @ R.T
    return Preintegrated(gtsam.Pose2(*map(float, delta)), c, 0.5 * (start + start.T), 1)


def run_points(
    data: VictoriaPark,
    backend: str = "isam2",
    association: str = "given",
    map_params: MapParams | None = None,
    limit: int | None = None,
    odometry_scale: Scales | str = 1.0,
    robust: str | None = None,
    resolve_scale: Scales | None = None,
) -> PointSlamResult:
    """Run one backend over the steps (the first ``limit`` of them, if given), the odometry
    covariances' variances multiplied by ``odometry_scale`` (one factor, or x, y, theta:
    :func:`~fgslam.slam.point_calibration.scaled_covariance`; ``"self"``: the
    self-calibration's, on the own association);
    ``robust``: the graph's kernel (default :class:`GraphBackend`'s). The scales used are
    in the result's ``odometry_scale``.

    ``resolve_scale`` (own association only; offline): a second pass of the same backend
    over the same data with the first pass's association taken as given (sightings it left
    out dropped) and the odometry variances scaled by ``resolve_scale`` (e.g. 1: the file's
    own). Gates need a generous odometry model after long stretches without landmarks,
    the estimate an honest one; the result holds the second pass's trajectory and
    landmarks, the first pass's association (``assigned``, ``sighting_ids``), and both
    passes' times in ``wall_time`` (the second's in ``stats["resolve_seconds"]``)."""
    if resolve_scale is not None:
        if association != "own":
            raise ValueError("resolve_scale needs the own association (a given one is final)")
        first = run_points(data, backend, "own", map_params, limit, odometry_scale, robust)
        second = run_points(
            relabelled(data, first.sighting_ids),
            backend,
            "given",
            map_params,
            limit,
            resolve_scale,
            robust,
        )
        first.stats["resolve_seconds"] = round(second.wall_time, 3)
        return replace(
            first,
            poses=second.poses,
            filtered=second.filtered,
            landmarks=second.landmarks,
            wall_time=first.wall_time + second.wall_time,
            latencies=first.latencies + second.latencies,
            odometry_scale=second.odometry_scale,
        )
    if backend not in BACKENDS:
        raise ValueError(f"unknown backend {backend!r}; expected one of {BACKENDS}")
    if association not in ASSOCIATIONS:
        raise ValueError(f"unknown association {association!r}; expected one of {ASSOCIATIONS}")
    if isinstance(odometry_scale, str):
        if odometry_scale != "self":
            raise ValueError(f"odometry_scale: a number, three or 'self', not {odometry_scale!r}")
        odometry_scale = self_calibrate(data, limit=limit, map_params=map_params).scale
    scale = np.broadcast_to(np.asarray(odometry_scale, dtype=float), (3,)).copy()
    if backend == "ekf":  # a given association is trusted: the EKF's gate is for its own
        be: Backend = EkfBackend(gate_p=None if association == "given" else 0.9999)
    else:
        kw = {} if robust is None else {"robust": robust}
        be = GraphBackend(covariances=False, **kw)
    step = SlamStep(be, map_params or POINT_MAP_PARAMS)
    steps = data.steps[:limit] if limit is not None else data.steps
    index = [steps[0].i]
    odo = [np.zeros(3)]
    assigned: list[tuple[int, int]] = []
    where_of: list[tuple[int, int, int]] = []  # (pose index, position, own id)
    t_start = time.perf_counter()

    def keyframe(k: int, pose_index: int, pre: Preintegrated | None) -> None:
        sights = data.sightings.get(pose_index, [])
        feats = []
        for s in sights:
            z, c = to_bearing_range(s.xy, s.cov)
            feats.append(Feature("point", z, c, source="laser", laser_support=1))
        given = [s.landmark for s in sights] if association == "given" else None
        where = step.keyframe(float(k), feats, pre, np.zeros(3), given)
        if given is None:  # resolved at the end (a tentative's sightings count if confirmed)
            for q, (s, lid) in enumerate(zip(sights, where, strict=True)):
                assigned.append((s.landmark, -1 if lid is None else lid))
                where_of.append((pose_index, q, -1 if lid is None else lid))

    keyframe(0, steps[0].i, None)
    for k, st in enumerate(steps, 1):
        keyframe(k, st.j, _pre(st.delta, scaled_covariance(st.cov, scale)))
        index.append(st.j)
        odo.append(compose_poses(odo[-1], st.delta))
    stats = step.stats
    lms = step.landmarks  # discarded tentatives are forgotten: their sightings count as -1

    def final(o: int) -> int:
        if o < 0 or o not in lms:
            return -1
        o = step.map.resolve(o)
        return o if lms[o].active else -1

    assigned = [(g, final(o)) for g, o in assigned]
    where_of = [(i, q, final(o)) for i, q, o in where_of]
    results: Backend | BatchSmoother = be
    if backend == "batch":
        results = BatchSmoother(be)  # type: ignore[arg-type]
        stats["batch_seconds"] = round(results.seconds, 3)
    traj = results.finish()
    wall = time.perf_counter() - t_start
    means = results.means()
    return PointSlamResult(
        backend=backend,
        association=association,
        index=np.array(index),
        poses=np.array([p[1] for p in traj]).reshape(-1, 3),
        filtered=np.array(step.filtered).reshape(-1, 3),
        odometry=np.array(odo),
        landmarks={lid: np.asarray(m) for lid, m in means.items()},
        wall_time=wall,
        latencies=step.latencies,
        stats=stats,
        assigned=assigned,
        sighting_ids=where_of,
        odometry_scale=scale,
    )


@dataclass
class Calibration:
    """The fitted scales (x, y, theta variance factors on the given step covariance) and
    the history of the alternation: scales used, landmarks found, -2 log L per round."""

    scale: NDArray[np.float64]
    history: list[dict] = field(default_factory=list)


def self_calibrate(
    data: VictoriaPark,
    start: Scales = 1.0,
    per_component: bool = False,
    rounds: int = 6,
    tol: float = 0.1,
    limit: int | None = None,
    map_params=None,
) -> Calibration:
    """Alternate own association (EKF, :func:`run_points`) and the maximum-likelihood scales
    on it, from ``start``, until every scale changes by less than a factor ``exp(tol)`` or
    after ``rounds`` rounds (see :mod:`fgslam.slam.point_calibration`)."""
    s = np.broadcast_to(np.asarray(start, dtype=float), (3,)).copy()
    cal = Calibration(s)
    for _ in range(rounds):
        r = run_points(data, "ekf", "own", map_params, limit=limit, odometry_scale=s.copy())
        assoc = association_of(r.sighting_ids)
        new = fit_scale(data, assoc, per_component, limit)
        nll, m = sighting_nll(data, assoc, new, limit)
        cal.history.append(
            {
                "scale_used": s.tolist(),
                "landmarks": len(r.landmarks),
                "scale_fitted": new.tolist(),
                "nll": nll,
                "innovations": m,
            }
        )
        done = bool(np.all(np.abs(np.log(new / s)) < tol))
        s = new
        if done:
            break
    cal.scale = s
    return cal


def relabelled(data: VictoriaPark, sighting_ids: list[tuple[int, int, int]]) -> VictoriaPark:
    """``data`` with each sighting's landmark index replaced by the id an own association
    gave it (``sighting_ids``: pose index, position in that pose's sightings, id or -1);
    sightings without an id are dropped."""
    ids = {(i, q): o for i, q, o in sighting_ids}
    sightings = {}
    for pose, ss in data.sightings.items():
        kept = [
            replace(s, landmark=ids[(pose, q)])
            for q, s in enumerate(ss)
            if ids.get((pose, q), -1) >= 0
        ]
        if kept:
            sightings[pose] = kept
    return VictoriaPark(steps=data.steps, sightings=sightings, problems=data.problems)


def association_agreement(assigned: list[tuple[int, int]]) -> dict[str, float]:
    """How the own association compares with the given one: ``purity`` (share of the
    associated sightings whose landmark's majority given index is theirs), ``split`` (own
    landmarks per given landmark), ``unassigned`` (share of sightings left out)."""
    by_own: dict[int, Counter] = {}
    by_given: dict[int, set[int]] = {}
    n_unassigned = 0
    for given, own in assigned:
        if own < 0:
            n_unassigned += 1
            continue
        by_own.setdefault(own, Counter())[given] += 1
        by_given.setdefault(given, set()).add(own)
    n = sum(sum(c.values()) for c in by_own.values())
    pure = sum(max(c.values()) for c in by_own.values())
    return {
        "purity": pure / n if n else float("nan"),
        "own_landmarks": len(by_own),
        "given_landmarks": len(by_given),
        "split": float(np.mean([len(v) for v in by_given.values()])) if by_given else 0.0,
        "unassigned": n_unassigned / len(assigned) if assigned else 0.0,
    }
