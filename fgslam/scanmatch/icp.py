"""Point-to-line ICP: correspondences to the reference's local lines, Cauchy-weighted
Gauss-Newton in the query's body tangent (GTSAM's Pose2 retract), the inliers' Jacobians."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from factors.geometry import rot, wrap_angle, wrap_angles
from fgslam.config.robot import MatchParams
from fgslam.scanmatch.kernels import correspond, icp_loop, icp_system_numpy
from fgslam.scanmatch.reference import Reference


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
    """:func:`_correspond_numpy`, compiled (:func:`fgslam.scanmatch.kernels.correspond`)."""
    R = rot(float(pose[2]))
    idx, jj, r = correspond(ref.cells, ref.normals, ref.anchors, q, pose, params.corr_distance)
    nrm = np.full((len(q), 2), np.nan)
    nrm[idx] = ref.normals[jj]
    full = np.zeros(len(q), dtype=np.int64)
    full[idx] = jj
    return R, idx, full, nrm, r


def _correspond_numpy(ref: Reference, q: NDArray, pose: NDArray, params: MatchParams) -> tuple:
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
    """:func:`_icp_numpy`, its iterations compiled (:func:`fgslam.scanmatch.kernels.icp_loop`)."""
    pose, it, converged, joined = icp_loop(
        ref.cells,
        ref.normals,
        ref.anchors,
        q,
        pose0.astype(float),
        params.sigma_range,
        params.robust_scale,
        params.corr_distance,
        params.icp_iterations,
        join,
    )
    if joined:
        return None
    pose[2] = wrap_angle(float(pose[2]))
    return _inliers(ref, q, pose, params, it, converged, _correspond)


def _icp_numpy(
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
    scale = params.robust_scale
    converged = False
    it = 0
    assert ref.tree is not None
    for it in range(1, params.icp_iterations + 1):  # noqa: B007
        R, idx, _, nrm, r = _correspond_numpy(ref, q, pose, params)
        if len(idx) < 3:
            break
        # residual scale: robust (MAD), never below the sensor's
        sigma = max(params.sigma_range, 1.4826 * _median_abs(r))
        # the Cauchy-weighted normal equations
        H, g = icp_system_numpy(nrm, idx, R, q, r, scale * sigma)
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
            d[:, 2] = wrap_angles(d[:, 2])
            if ((np.hypot(d[:, 0], d[:, 1]) <= join[1]) & (np.abs(d[:, 2]) <= join[2])).any():
                return None
        if np.hypot(delta[0], delta[1]) < 3e-4 and abs(delta[2]) < 3e-5:
            converged = True
            break
    return _inliers(ref, q, pose, params, it, converged, _correspond_numpy)


def _inliers(
    ref: Reference,
    q: NDArray,
    pose: NDArray,
    params: MatchParams,
    it: int,
    converged: bool,
    correspond_: Callable,
) -> _Icp:
    """The final correspondences at the estimate ``pose``: the inliers and their Jacobians."""
    jq = np.column_stack([-q[:, 1], q[:, 0]])
    R, idx, jj, nrm, r = correspond_(ref, q, pose, params)
    sigma = max(params.sigma_range, 1.4826 * _median_abs(r)) if len(r) else params.sigma_range
    inl = np.abs(r) < params.inlier_sigmas * sigma
    idx, r = idx[inl], r[inl]
    nb = nrm[idx] @ R
    J = np.column_stack([nb, np.einsum("ij,ij->i", nb, jq[idx])])
    # the Jacobian's part that is the noise of the normal: its angle error times the tangent
    tb = np.column_stack([-nb[:, 1], nb[:, 0]])
    Jt = np.column_stack([tb, np.einsum("ij,ij->i", tb, jq[idx])])
    Jt *= np.sqrt(ref.normal_var[jj[idx]])[:, None]
    return _Icp(pose, J, r, idx, it, converged, Jt)


def _expmap(pose: NDArray, xi: NDArray) -> NDArray:
    """pose * Exp(xi) for Pose2 (x, y, theta), xi in the body tangent."""
    w = float(xi[2])
    if abs(w) < 1e-9:
        v = xi[:2]
    else:
        s, c = math.sin(w), math.cos(w)
        v = np.array([s * xi[0] - (1 - c) * xi[1], (1 - c) * xi[0] + s * xi[1]]) / w
    t = pose[:2] + rot(float(pose[2])) @ v
    return np.array([t[0], t[1], wrap_angle(float(pose[2]) + w)])
