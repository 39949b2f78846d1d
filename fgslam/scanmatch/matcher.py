"""The public matcher: :func:`match` (the pipeline of :mod:`fgslam.scanmatch`: search,
ICP from each basin, covariance, rejection) and its result, :class:`Match`."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from factors.geometry import rot
from fgslam.scanmatch.params import MatchParams
from fgslam.scanmatch.points import _clean, _voxel, _wrap
from fgslam.scanmatch.reference import Reference
from fgslam.scanmatch.search import _Response, _search


def _expmap(pose: NDArray, xi: NDArray) -> NDArray:
    """pose * Exp(xi) for Pose2 (x, y, theta), xi in the body tangent."""
    w = float(xi[2])
    if abs(w) < 1e-9:
        v = xi[:2]
    else:
        s, c = math.sin(w), math.cos(w)
        v = np.array([s * xi[0] - (1 - c) * xi[1], (1 - c) * xi[0] + s * xi[1]]) / w
    t = pose[:2] + rot(float(pose[2])) @ v
    return np.array([t[0], t[1], _wrap(float(pose[2]) + w)])


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


# ---------------------------------------------------------------- ICP


@dataclass
class _Icp:
    pose: NDArray
    J: NDArray  # (m, 3) inlier Jacobians, body tangent
    r: NDArray  # (m,) inlier residuals (m)
    order: NDArray  # (m,) query index of each inlier (beam order)
    iterations: int
    converged: bool
    Jt: NDArray  # (m, 3) normal-noise part of J (1-sigma): E[J J^T] = J0 J0^T + Jt Jt^T


def _correspond(ref: Reference, q: NDArray, pose: NDArray, params: MatchParams) -> tuple:
    """Point-to-line correspondences of the query points (query frame) placed at ``pose``:
    the rotation R, the indices of the query points with a neighbour within
    ``corr_distance`` that has a normal, their neighbours ``jj`` (for every query point),
    the neighbours' normals (every query point) and the signed residuals (m) of ``idx``."""
    assert ref.tree is not None
    R = rot(float(pose[2]))
    p = q @ R.T + pose[:2]
    d, j = ref.tree.query(p, distance_upper_bound=params.corr_distance)
    ok = np.isfinite(d)
    jj = np.where(ok, j, 0)
    nrm = ref.normals[jj]
    ok &= np.isfinite(nrm[:, 0])
    idx = np.flatnonzero(ok)
    r = np.einsum("ij,ij->i", nrm[idx], p[idx] - ref.anchors[jj[idx]])
    return R, idx, jj, nrm, r


_DIAG3 = np.diag_indices(3)


def _median_abs(r: NDArray) -> float:
    """np.median(np.abs(r)) (the same value) without its overhead: a partial sort."""
    a = np.abs(r)
    n = len(a)
    lo, hi = (n - 1) // 2, n // 2
    part = np.partition(a, [lo, hi])
    return float(part[hi]) if lo == hi else 0.5 * float(part[lo] + part[hi])


def _icp(
    ref: Reference,
    q: NDArray,
    pose0: NDArray,
    params: MatchParams,
    join: tuple[NDArray, float, float] | None = None,
) -> _Icp | None:
    """Point-to-line ICP from ``pose0``. ``join``: (poses (k, 3), xy and theta tolerances):
    stop and return None once an iterate, moving by less than the tolerances' tenth, lies
    within them of one of those poses (other runs' converged results): this run has reached
    that basin's fixed point (the caller drops runs that end in a basin already found)."""
    pose = pose0.astype(float).copy()
    sigma = max(params.sigma_range, 1e-4)
    scale = params.robust_scale
    jq = np.column_stack([-q[:, 1], q[:, 0]])
    converged = False
    it = 0
    assert ref.tree is not None
    for it in range(1, params.icp_iterations + 1):  # noqa: B007
        R, idx, jj, nrm, r = _correspond(ref, q, pose, params)
        if len(idx) < 3:
            break
        nb = nrm[idx] @ R  # normal in the query frame: n^T R
        J = np.column_stack([nb, np.einsum("ij,ij->i", nb, jq[idx])])
        # residual scale: robust (MAD), never below the sensor's
        sigma = max(params.sigma_range, 1.4826 * _median_abs(r))
        wts = 1.0 / (1.0 + (r / (scale * sigma)) ** 2)
        H = (J * wts[:, None]).T @ J
        g = (J * wts[:, None]).T @ r
        H_d = H.copy()
        H_d[_DIAG3] = H[_DIAG3] + H[_DIAG3] * 1e-6 + 1e-9
        try:
            delta = -np.linalg.solve(H_d, g)
        except np.linalg.LinAlgError:
            break
        if not np.isfinite(delta).all():
            break
        pose = _expmap(pose, delta)
        if (
            join is not None
            and np.hypot(delta[0], delta[1]) < 0.1 * join[1]
            and abs(delta[2]) < 0.1 * join[2]
        ):
            d = join[0] - pose
            d[:, 2] = (d[:, 2] + math.pi) % (2 * math.pi) - math.pi
            if ((np.hypot(d[:, 0], d[:, 1]) <= join[1]) & (np.abs(d[:, 2]) <= join[2])).any():
                return None
        if np.hypot(delta[0], delta[1]) < 3e-4 and abs(delta[2]) < 3e-5:
            converged = True
            break
    # final correspondences at the estimate: inliers
    R, idx, jj, nrm, r = _correspond(ref, q, pose, params)
    if len(r):
        sigma = max(params.sigma_range, 1.4826 * _median_abs(r))
    inl = np.abs(r) < params.inlier_sigmas * sigma
    idx, r = idx[inl], r[inl]
    nb = nrm[idx] @ R
    J = np.column_stack([nb, np.einsum("ij,ij->i", nb, jq[idx])])
    # the Jacobian's part that is the noise of the normal: its angle error times the tangent
    tb = np.column_stack([-nb[:, 1], nb[:, 0]])
    Jt = np.column_stack([tb, np.einsum("ij,ij->i", tb, jq[idx])])
    Jt *= np.sqrt(ref.normal_var[jj[idx]])[:, None]
    return _Icp(pose, J, r, idx, it, converged, Jt)


def _seeds(resp: _Response, res: float, most: int) -> list[int]:
    """Indices of up to ``most`` response poses, best first, each more than 3 cells or 3
    rotation steps from every one before it: one start per basin."""
    out: list[int] = []
    if most <= 0 or len(resp.scores) == 0:
        return out
    for k in np.argsort(-resp.scores, kind="stable"):
        p = resp.poses[k]
        far = True
        for j in out:
            d = p - resp.poses[j]
            if np.hypot(d[0], d[1]) <= 3 * res and abs(_wrap(float(d[2]))) <= 3 * resp.step:
                far = False
                break
        if far:
            out.append(int(k))
            if len(out) >= most:
                break
    return out


def _same(a: NDArray, b: NDArray, res: float, step: float) -> bool:
    """Whether two ICP results are one basin: within 2 cells and 2 rotation steps."""
    d = a - b
    return bool(np.hypot(d[0], d[1]) <= 2 * res and abs(_wrap(float(d[2]))) <= 2 * step)


def _inside(pose: NDArray, guess: NDArray, params: MatchParams, res: float, step: float) -> bool:
    """Whether ``pose`` lies in the search window around ``guess`` (a cell, a step of margin)."""
    d = pose - guess
    return bool(
        max(abs(d[0]), abs(d[1])) <= params.search_xy + res
        and abs(_wrap(float(d[2]))) <= params.search_theta + step
    )


def _costs(ref: Reference, q: NDArray, pose: NDArray, s2: float, params: MatchParams) -> NDArray:
    """Per query point at ``pose``: its point-to-line r^2 / s2, capped at
    ``inlier_sigmas``^2; NaN where it has no correspondence."""
    _, idx, _, _, r = _correspond(ref, q, pose, params)
    out = np.full(len(q), np.nan)
    out[idx] = np.minimum(r**2 / s2, params.inlier_sigmas**2)
    return out


def _dcost(a: NDArray, b: NDArray) -> tuple[float, float]:
    """Cost of ``a`` minus that of ``b`` over the points both matched (a point matched at
    one pose only says as much about the sampling of far, grazing surfaces as about the
    pose), and the standard deviation of that sum from the spread of the per-point
    differences (paired: how much of it the residuals' own noise explains; NaN below 6
    common points)."""
    both = np.isfinite(a) & np.isfinite(b)
    d = a[both] - b[both]
    if len(d) < 6:
        return 0.0, math.nan
    return float(d.sum()), math.sqrt(len(d) * float(np.var(d, ddof=1)))


def _hac(J: NDArray, r: NDArray, order: NDArray, lags: int) -> NDArray:
    """Newey-West (Bartlett-weighted) covariance of the gradient sum_i J_i r_i, with the
    residuals correlated between beams up to ``lags`` apart (``order``: beam index of each
    residual, increasing). Lag 0 alone is the usual sum_i r_i^2 J_i J_i^T."""
    g = J * r[:, None]
    S = g.T @ g
    if len(r) < 2 or lags <= 0:
        return S
    pos = np.full(int(order.max()) + lags + 2, -1)
    pos[order] = np.arange(len(order))
    for k in range(1, lags + 1):
        j = pos[order + k]
        ok = j >= 0
        if not ok.any():
            continue
        c = g[ok].T @ g[j[ok]]
        S += (1.0 - k / (lags + 1.0)) * (c + c.T)
    return S


# ---------------------------------------------------------------- match


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
    g = np.array([g[0], g[1], _wrap(float(g[2]))])
    q = _clean(query)
    q = q[np.hypot(q[:, 0], q[:, 1]) < params.max_range] if len(q) else q
    need = max(params.min_points, 6)
    if len(q) < need:
        return _failed(g, f"too few query points ({len(q)} < {need})", params)
    if ref.n_points < need or ref.tree is None:
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
    alts: list[tuple[_Icp, float, float]] = []
    owned = np.zeros(len(resp.poses), dtype=bool)
    if len(seeds) > 1 and len(icp.r) >= 6:
        qr = q @ rot(float(g[2])).T + g[:2]
        use = ref.covered(qr, params.search_theta, params.search_xy)
        qc = q[use] if use.sum() >= max(params.min_coverage * len(q), 3) else q
        s2_0 = max(params.sigma_range**2, float(icp.r @ icp.r) / max(len(icp.r) - 3, 1))
        runs = [(icp, _costs(ref, qc, icp.pose, s2_0, params), 0)]
        for k in range(1, len(seeds)):
            # a run that settles next to a basin already found is that basin: stopped there
            # (_same would drop it at the end)
            done = np.array([a.pose for a, _, _ in runs])
            alt = _icp(ref, q, seed_poses[k], params, (done, 0.5 * res, 0.5 * resp.step))
            # one run per basin (the first, by score), and only inside the window
            if (
                alt is not None
                and len(alt.r) >= 6
                and _inside(alt.pose, g, params, res, resp.step)
                and not any(_same(alt.pose, a.pose, res, resp.step) for a, _, _ in runs)
            ):
                runs.append((alt, _costs(ref, qc, alt.pose, s2_0, params), k))
        c0 = runs[0][1]
        for a, c, k in runs[1:]:
            dc, sd = _dcost(c, c0)
            if not math.isfinite(sd):
                continue  # too few common points: the response speaks for it
            alts.append((a, dc, sd))
            # the response's poses in this basin stand for it no more
            dd = resp.poses - seed_poses[k]
            dd[:, 2] = (dd[:, 2] + math.pi) % (2 * math.pi) - math.pi
            owned |= (np.hypot(dd[:, 0], dd[:, 1]) <= 3 * res) & (np.abs(dd[:, 2]) <= 3 * resp.step)
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
    dof = max(m - 3, 1)
    s2 = max(params.sigma_range**2, float(icp.r @ icp.r) / dof)
    rms = math.sqrt(float(np.mean(icp.r**2)))
    # information the noise of the reference normals fakes along featureless walls: removed
    w_, V = np.linalg.eigh(icp.J.T @ icp.J - icp.Jt.T @ icp.Jt)
    H0 = (V * np.maximum(w_, 0.0)) @ V.T
    # correlated beams: per-axis ratio of the gradient's HAC variance to the independent one
    S = _hac(icp.J, icp.r, icp.order, params.hac_lags)
    dH = np.maximum(np.diag(H0), 1e-12)
    kap = np.clip(np.diag(S) / (s2 * dH), 1.0, params.max_kappa) * params.cov_inflation
    kappa = float(kap.max())
    Ki = np.diag(1.0 / np.sqrt(kap))
    # window prior: uniform over the window, variance w^2 / 3 (body frame: isotropic in xy)
    wxy, wth = max(params.search_xy, res), max(params.search_theta, resp.step)
    prior = np.diag([3.0 / wxy**2, 3.0 / wxy**2, 3.0 / wth**2])
    H = Ki @ H0 @ Ki / s2 + prior
    cov_icp = np.linalg.inv(H)
    # response surface: other poses' spread about the estimate (reference axes)
    A = np.eye(3)
    A[:2, :2] = rot(float(pose[2]))
    d = resp.poses - pose
    d[:, 2] = (d[:, 2] + math.pi) % (2 * math.pi) - math.pi
    nats = resp.n / kappa * params.response_gain * (score - resp.scores)
    # poses that the local Gaussian (ICP covariance plus the grid's cell and rotation step)
    # explains are the best basin itself: only the others widen the covariance
    local = A @ cov_icp @ A.T + np.diag([res**2, res**2, resp.step**2])
    maha = np.einsum("ij,ij->i", d @ np.linalg.inv(local), d)
    far = (maha > params.basin_chi2) & ~owned
    wts = np.exp(-np.clip(nats, 0.0, 700.0)) * far
    total = 1.0 + wts.sum()  # the best basin counts with weight 1
    # other basins ICP converged to elsewhere, weighted by their likelihood ratio
    # (a paired test: the cost difference over its noise, correlated beams counted): a
    # basin as good as the best within the residuals' noise is a tie and weighs as much
    for alt, dc, sd in alts:
        da = alt.pose - pose
        da[2] = _wrap(float(da[2]))
        t = max(dc, 0.0) / max(sd * math.sqrt(kappa), 1e-9)
        wa = math.exp(-0.5 * min(t * t, 1400.0))
        d = np.vstack([d, da])
        wts = np.append(wts, wa)
        total += wa
    M_ref = (d * wts[:, None]).T @ d / total
    cov_ref = A @ cov_icp @ A.T + M_ref
    cov_ref = 0.5 * (cov_ref + cov_ref.T)
    ev = np.linalg.eigvalsh(cov_ref[:2, :2])
    amb = max(
        math.sqrt(max(float(ev[-1]), 0.0)) / wxy, math.sqrt(max(float(cov_ref[2, 2]), 0.0)) / wth
    )
    floor = np.diag([params.floor_xy**2, params.floor_xy**2, params.floor_theta**2])
    cov_ref = cov_ref + floor  # isotropic in xy: the same in either frame
    cov = A.T @ cov_ref @ A
    cov = 0.5 * (cov + cov.T)
    moved = pose - start
    moved[2] = _wrap(float(moved[2]))
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
