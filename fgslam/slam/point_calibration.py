"""Odometry noise of a point-landmark run estimated from the run itself (self-calibration).

The odometry covariances a file gives may be far off (Victoria Park's: one constant
covariance for steps of 0.1 to 1.5 m, its heading sigma 0.1 deg per step). Model: the step
covariance is the given one with each component's variance scaled, ``D C D`` with
``D = diag(sqrt(s_x), sqrt(s_y), sqrt(s_theta))`` (``s`` one number: all three alike).

The scales are fitted by maximum likelihood of the sightings under a fixed association, by
the prediction error decomposition of an EKF over pose and point landmarks:
``-2 log L(s) = sum_t log det S_t(s) + nu_t^T S_t(s)^-1 nu_t`` with ``nu_t`` the innovation
of sighting t (robot-frame x, y, m) and ``S_t`` its covariance (:func:`sighting_nll`). The
innovations are predictions, not residuals of a smoothed solution: a smoother's odometry
residuals are shrunk (most odometry degrees of freedom are constrained by nothing else), so
their normalised squares say little about the noise.

:func:`fgslam.slam.pointslam.self_calibrate` alternates: associate with the current scales
(the project's own association, :func:`fgslam.slam.pointslam.run_points`, EKF), fit the
scales on that association (:func:`fit_scale`), repeat until the scales settle. Nothing of
the file's own association is used.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import minimize, minimize_scalar

from factors.geometry import wrap_angle
from fgslam.io.readers.victoria import VictoriaPark

Scales = float | Sequence[float] | NDArray[np.float64]


def scaled_covariance(cov: NDArray[np.float64], scale: Scales) -> NDArray[np.float64]:
    """``cov`` (x, y, theta of a step) with the variances scaled by ``scale`` (one number or
    three), correlations kept: ``D cov D``, ``D = diag(sqrt(scale))``."""
    s = np.broadcast_to(np.asarray(scale, dtype=float), (3,))
    d = np.sqrt(s)
    return cov * np.outer(d, d)


def sighting_nll(
    data: VictoriaPark,
    association: dict[tuple[int, int], int],
    scale: Scales,
    limit: int | None = None,
) -> tuple[float, int]:
    """``-2 log`` likelihood (without the constant) of the associated sightings under the
    odometry covariances scaled by ``scale``, and the number of innovations in it.

    ``association``: (pose index, position of the sighting in that pose's list) -> landmark
    id (negative or missing: the sighting is not used). An EKF over the pose (world x, y,
    theta; m, rad) and the landmarks (world x, y, m), started exactly at the origin: a
    landmark's first sighting initialises it (no likelihood term), every later one is an
    update whose innovation enters the sum."""
    steps = data.steps[:limit] if limit is not None else data.steps
    ids = sorted({lid for lid in association.values() if lid >= 0})
    n_max = 3 + 2 * len(ids)
    x = np.zeros(n_max)
    P = np.zeros((n_max, n_max))
    n = 3  # active state size (pose + initialised landmarks)
    slot: dict[int, int] = {}
    nll, count = 0.0, 0

    def sight(pose_index: int) -> None:
        nonlocal n, nll, count
        for q, s in enumerate(data.sightings.get(pose_index, [])):
            lid = association.get((pose_index, q), -1)
            if lid < 0:
                continue
            th = x[2]
            c, si = math.cos(th), math.sin(th)
            R = np.array([[c, -si], [si, c]])
            if lid not in slot:  # initialise: l = p + R z
                k = slot[lid] = n
                n += 2
                x[k : k + 2] = x[:2] + R @ s.xy
                Jp = np.array([[1.0, 0.0, -si * s.xy[0] - c * s.xy[1]]])
                Jp = np.vstack([Jp, [0.0, 1.0, c * s.xy[0] - si * s.xy[1]]])
                P[k : k + 2, :k] = Jp @ P[:3, :k]
                P[:k, k : k + 2] = P[k : k + 2, :k].T
                P[k : k + 2, k : k + 2] = Jp @ P[:3, :3] @ Jp.T + R @ s.cov @ R.T
                continue
            k = slot[lid]
            d = x[k : k + 2] - x[:2]
            z_hat = R.T @ d
            Hp = np.array([[-c, -si, -si * d[0] + c * d[1]], [si, -c, -c * d[0] - si * d[1]]])
            Hl = R.T
            idx = np.r_[0:3, k : k + 2]
            H = np.hstack([Hp, Hl])
            PHt = P[:n, idx] @ H.T  # (n, 2)
            S = H @ PHt[idx] + s.cov
            nu = s.xy - z_hat
            Si = np.linalg.inv(S)
            nll += math.log(np.linalg.det(S)) + float(nu @ Si @ nu)
            count += 1
            K = PHt @ Si
            x[:n] += K @ nu
            x[2] = wrap_angle(float(x[2]))
            P[:n, :n] -= K @ PHt.T
            P[:n, :n] = 0.5 * (P[:n, :n] + P[:n, :n].T)

    sight(steps[0].i)
    for st in steps:
        th = x[2]
        c, si = math.cos(th), math.sin(th)
        dx, dy, dth = st.delta
        F = np.array([[1.0, 0.0, -si * dx - c * dy], [0.0, 1.0, c * dx - si * dy], [0, 0, 1.0]])
        G = np.array([[c, -si, 0.0], [si, c, 0.0], [0.0, 0.0, 1.0]])
        x[0] += c * dx - si * dy
        x[1] += si * dx + c * dy
        x[2] = wrap_angle(float(th + dth))
        P[:3, :n] = F @ P[:3, :n]
        P[:n, :3] = P[:n, :3] @ F.T
        P[:3, :3] += G @ scaled_covariance(st.cov, scale) @ G.T
        sight(st.j)
    return nll, count


def fit_scale(
    data: VictoriaPark,
    association: dict[tuple[int, int], int],
    per_component: bool = False,
    limit: int | None = None,
    bounds: tuple[float, float] = (1e-2, 1e5),
) -> NDArray[np.float64]:
    """Maximum-likelihood variance scales (:func:`sighting_nll`): one for all components
    (bounded Brent on log s within ``bounds``), or, ``per_component``, x, y and theta
    (L-BFGS-B on log s from the common one). Returns three scales."""
    lo, hi = math.log(bounds[0]), math.log(bounds[1])

    def f1(u: float) -> float:
        return sighting_nll(data, association, math.exp(u), limit)[0]

    r = minimize_scalar(f1, bounds=(lo, hi), method="bounded", options={"xatol": 0.02})
    u0 = float(r.x)
    if not per_component:
        return np.full(3, math.exp(u0))

    def f3(u: NDArray[np.float64]) -> float:
        u = np.clip(u, lo, hi)
        return sighting_nll(data, association, np.exp(u), limit)[0]

    r3 = minimize(f3, np.full(3, u0), method="L-BFGS-B", bounds=[(lo, hi)] * 3)
    return np.exp(np.clip(r3.x, lo, hi))


def association_of(assigned: Iterable[tuple[int, int, int]]) -> dict[tuple[int, int], int]:
    """(pose index, position in the pose's sightings, landmark id) rows as the mapping
    :func:`sighting_nll` takes."""
    return {(i, q): lid for i, q, lid in assigned}
