"""Covariance of a match (body tangent at the estimate, GTSAM's BetweenFactorPose2
convention): ICP's information with the normals' noise removed, inflated for correlated
beams (Newey-West), a uniform prior over the window, widened by the response's and the
other basins' poses; and the ambiguity of the rejection rule."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from factors.geometry import rot, wrap_angle, wrap_angle_half_open
from fgslam.config.robot import MatchParams
from fgslam.scanmatch.icp import _Icp
from fgslam.scanmatch.search import _Response


def _covariance(
    icp: _Icp,
    resp: _Response,
    alts: list[tuple[_Icp, float, float]],
    owned: NDArray[np.bool_],
    score: float,
    params: MatchParams,
) -> tuple[NDArray, NDArray, float, float]:
    """Covariance of the match at ``icp``'s pose (:mod:`fgslam.scanmatch`, 3.): ``resp`` the
    response's poses within ``mode_nats`` (``score`` the best's), ``alts`` and ``owned`` the
    other basins (:func:`fgslam.scanmatch.basins._other_basins`). Returns the covariance in
    the body tangent and in the reference's axes (both with the floor), kappa (the largest
    per-axis inflation) and the ambiguity (1-sigma extent over the window's half-width,
    before the floor)."""
    pose = icp.pose
    res = params.resolution
    dof = max(len(icp.r) - 3, 1)
    s2 = max(params.sigma_range**2, float(icp.r @ icp.r) / dof)
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
    # to [-pi, pi), not wrap_angles' (-pi, pi]: the sign of d enters the moment M_ref
    d[:, 2] = wrap_angle_half_open(d[:, 2])
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
        da[2] = wrap_angle(float(da[2]))
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
    return cov, cov_ref, kappa, amb


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
