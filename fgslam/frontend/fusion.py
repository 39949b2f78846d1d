"""Laser-sonar fusion in information form (paper III-B, docs/design.md, 3.6).

C_f = (C_l^-1 + C_s^-1)^-1, z_f = C_f (C_l^-1 z_l + C_s^-1 z_s), written as the equivalent
Kalman update so that the sonar may measure only the leading components (corners: range and
bearing, not orientation; the fused orientation still moves through its correlations).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from factors.geometry import wrap_angle


def fuse(
    z_l: ArrayLike,
    C_l: ArrayLike,
    z_s: ArrayLike,
    C_s: ArrayLike,
    angular: Sequence[bool],
    dims: int | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Fuse laser estimate (z_l, C_l) with a sonar measurement (z_s, C_s) of its first ``dims``
    components (all by default). ``angular`` flags the angle components of z_s (residuals
    wrapped). Returns the fused vector and covariance."""
    z_l = np.asarray(z_l, dtype=float)
    C_l = np.asarray(C_l, dtype=float)
    z_s = np.asarray(z_s, dtype=float)
    C_s = np.asarray(C_s, dtype=float)
    n = z_l.size
    m = n if dims is None else dims
    if z_s.shape != (m,) or C_s.shape != (m, m) or C_l.shape != (n, n):
        raise ValueError("fusion: inconsistent shapes")
    H = np.eye(m, n)
    innov = z_s - z_l[:m]
    for k, ang in enumerate(angular[:m]):
        if ang:
            innov[k] = wrap_angle(innov[k])
    K = _gain(C_l, C_s, m)
    z = z_l + K @ innov
    C = C_l - K @ H @ C_l
    return z, 0.5 * (C + C.T)


def fused_jacobian(
    C_l: ArrayLike,
    C_s: ArrayLike,
    J_l: ArrayLike,
    dims: int | None = None,
    J_s: ArrayLike | None = None,
) -> NDArray[np.float64]:
    """The fused vector's Jacobian J_l + K (J_s - H J_l) w.r.t. what the laser estimate's
    Jacobian ``J_l`` and the sonar measurement's ``J_s`` (None: zero) are taken against
    (e.g. the laser's range calibration, which the sonar does not involve, and the speed of
    sound, which the laser does not), with the gain of :func:`fuse` for the same
    covariances."""
    C_l = np.asarray(C_l, dtype=float)
    J_l = np.asarray(J_l, dtype=float)
    m = C_l.shape[0] if dims is None else dims
    K = _gain(C_l, np.asarray(C_s, dtype=float), m)
    if J_s is None:
        return J_l - K @ J_l[:m]
    return J_l + K @ (np.asarray(J_s, dtype=float) - J_l[:m])


def _gain(C_l: NDArray[np.float64], C_s: NDArray[np.float64], m: int) -> NDArray[np.float64]:
    """K = C_l H^T (H C_l H^T + C_s)^-1 with H the first ``m`` rows of the identity."""
    S = C_l[:m, :m] + C_s
    return np.linalg.solve(S, C_l[:m, :]).T  # S and C_l symmetric
