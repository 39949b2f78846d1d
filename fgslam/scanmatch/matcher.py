"""The public matcher: :func:`match` (the pipeline of :mod:`fgslam.scanmatch`: search,
ICP from each basin, covariance, rejection) and its result, :class:`Match`."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from factors.geometry import wrap_angle
from fgslam.config.robot import MatchParams
from fgslam.scanmatch.basins import _other_basins, _seeds
from fgslam.scanmatch.covariance import _covariance
from fgslam.scanmatch.icp import _icp
from fgslam.scanmatch.points import _clean, _voxel
from fgslam.scanmatch.reference import Reference
from fgslam.scanmatch.search import _search


@dataclass(frozen=True)
class Match:
    """Result of :func:`match`. ``pose``: the query's pose in the reference frame, T_ref_query
    (x, y, theta; m, rad). ``cov``: its covariance in GTSAM's BetweenFactorPose2 convention
    (tangent at ``pose``, i.e. the query's body frame; order x, y, theta); ``cov_ref``: the
    same in the reference frame's axes (``cov = J cov_ref J^T``, J = blockdiag(R(theta)^T,
    1)). ``score``: correlative score in [0, 1]; ``overlap``: fraction of query points with an
    inlier correspondence after ICP; ``rms``: point-to-line rms of the inliers (m); ``ok``:
    passed the rejection rule, else ``reason`` says why."""

    pose: NDArray[np.float64]
    cov: NDArray[np.float64]
    cov_ref: NDArray[np.float64]
    score: float
    overlap: float
    rms: float
    ok: bool
    reason: str
    ambiguity: float = math.nan  # 1-sigma extent / window half-width (largest of xy, theta)
    kappa: float = math.nan  # covariance inflation used (correlated beams)
    n_inliers: int = 0
    iterations: int = 0
    search_pose: NDArray[np.float64] = field(default_factory=lambda: np.full(3, np.nan))


def _failed(guess: NDArray, reason: str, params: MatchParams) -> Match:
    g = np.asarray(guess, dtype=float).ravel()
    pose = g[:3] if g.size >= 3 and np.isfinite(g[:3]).all() else np.zeros(3)
    cov = np.diag([params.search_xy**2, params.search_xy**2, params.search_theta**2]) / 3.0
    return Match(pose.copy(), cov, cov.copy(), 0.0, 0.0, math.nan, False, reason)


def match(
    ref: Reference, query: ArrayLike, guess: ArrayLike, params: MatchParams | None = None
) -> Match:
    """Pose of the query points ((N, 2), query frame, m) in the reference frame, searched
    within the window around ``guess`` ((3,), T_ref_query guess: x, y, theta) and refined by
    point-to-line ICP. Never raises on bad input: a failed match has ``ok`` False."""
    params = params or MatchParams()
    g = np.asarray(guess, dtype=float).ravel()
    if g.size < 3 or not np.isfinite(g[:3]).all() or np.abs(g[:2]).max() > 1e6:
        return _failed(np.zeros(3), "invalid guess", params)
    g = np.array([g[0], g[1], wrap_angle(float(g[2]))])
    q = _clean(query)
    q = q[np.hypot(q[:, 0], q[:, 1]) < params.max_range] if len(q) else q
    need = max(params.min_points, 6)
    if len(q) < need:
        return _failed(g, f"too few query points ({len(q)} < {need})", params)
    if ref.n_points < need:
        return _failed(g, f"too few reference points ({ref.n_points})", params)
    if abs(ref.resolution - params.resolution) > 1e-12:
        params = replace(params, resolution=ref.resolution)
    res = params.resolution
    qs = _voxel(q, params.voxel or params.resolution)
    resp = _search(ref, qs, g, params)
    if resp.best < 0:
        return _failed(g, "no candidate in the window", params)
    start = resp.poses[resp.best]
    score = float(resp.scores[resp.best])
    icp = _icp(ref, q, start, params)
    assert icp is not None
    # ICP from the other basins of the response too (up to max_basins starts, reaching
    # basin_nats below the best): the correlative score on its grid is only a proxy, and a
    # periodic scene (doors along a corridor) has several basins of similar score
    seeds = _seeds(resp, res, params.max_basins)
    seed_poses = resp.poses[seeds]
    near = resp.scores >= score - params.mode_nats / max(resp.n, 1)
    best = int(np.argmax(resp.scores[near]))
    resp = replace(resp, poses=resp.poses[near], scores=resp.scores[near], best=best)
    alts, owned = _other_basins(ref, q, g, icp, resp, seed_poses, params)
    pose = icp.pose
    m = len(icp.r)
    overlap = m / len(q)
    if m < 6:
        return replace(
            _failed(pose, "too few correspondences after ICP", params),
            score=score,
            overlap=overlap,
            search_pose=start,
        )
    rms = math.sqrt(float(np.mean(icp.r**2)))
    cov, cov_ref, kappa, amb = _covariance(icp, resp, alts, owned, score, params)
    moved = pose - start
    moved[2] = wrap_angle(float(moved[2]))
    reason = ""
    if not np.isfinite(pose).all() or not np.isfinite(cov).all():
        reason = "diverged (non-finite)"
    elif np.hypot(moved[0], moved[1]) > max(params.search_xy, 4 * res) or abs(moved[2]) > max(
        params.search_theta, 4 * resp.step
    ):
        reason = "diverged (ICP left the search result)"
    elif score < params.min_score:
        reason = f"low score ({score:.2f} < {params.min_score})"
    elif overlap < params.min_overlap:
        reason = f"low overlap ({overlap:.2f} < {params.min_overlap})"
    elif amb > params.max_ambiguity:
        reason = f"ambiguous ({amb:.2f} > {params.max_ambiguity})"
    return Match(
        pose=pose,
        cov=cov,
        cov_ref=cov_ref,
        score=score,
        overlap=overlap,
        rms=rms,
        ok=reason == "",
        reason=reason,
        ambiguity=amb,
        kappa=kappa,
        n_inliers=m,
        iterations=icp.iterations,
        search_pose=start,
    )
