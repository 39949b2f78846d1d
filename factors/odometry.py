"""Differential-drive odometry: the paper's eqs 1-5 in REP-103 convention (DESIGN 3.1).

Per encoder sample with wheel distances L_r, L_l (m) and wheelbase D (m):
``ds = (L_r + L_l)/2``, ``dth = (L_r - L_l)/D``, ``x += ds cos(th + dth/2)``,
``y += ds sin(th + dth/2)``, ``th += dth``; covariance by eq 4 with u = [L_r, L_l, D] and
Q = diag(K_R^2 L_r^2, K_L^2 L_l^2, K_D^2 D^2) (eq 5), per sample.

:func:`preintegrate` turns the samples between two keyframes into a relative pose and the
covariance of a ``gtsam.BetweenFactorPose2`` (tangent space at the end of the motion).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import gtsam
import numpy as np
from numpy.typing import ArrayLike, NDArray

from factors.geometry import rot, wrap_angle


@dataclass(frozen=True)
class OdometryParams:
    """Wheelbase D (m) and the eq 5 error parameters K_R, K_L, K_D (dimensionless)."""

    wheelbase: float
    k_r: float
    k_l: float
    k_d: float

    def __post_init__(self) -> None:
        vals = (self.wheelbase, self.k_r, self.k_l, self.k_d)
        if not all(math.isfinite(v) for v in vals) or self.wheelbase <= 0:
            raise ValueError(f"invalid odometry parameters {self}")
        if min(self.k_r, self.k_l, self.k_d) < 0:
            raise ValueError(f"odometry error parameters must be >= 0: {self}")


def ticks_to_distances(
    ticks_right: ArrayLike,
    ticks_left: ArrayLike,
    metres_per_tick_right: float,
    metres_per_tick_left: float,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Encoder tick increments per sample to wheel distances L_r, L_l in m."""
    tr = np.asarray(ticks_right, dtype=float)
    tl = np.asarray(ticks_left, dtype=float)
    if tr.shape != tl.shape:
        raise ValueError(f"tick arrays differ in shape: {tr.shape} vs {tl.shape}")
    if not (np.all(np.isfinite(tr)) and np.all(np.isfinite(tl))):
        raise ValueError("encoder ticks must be finite")
    return tr * metres_per_tick_right, tl * metres_per_tick_left


def _check_distances(lr: NDArray[np.float64], ll: NDArray[np.float64]) -> None:
    if lr.shape != ll.shape:
        raise ValueError(f"wheel distance arrays differ in shape: {lr.shape} vs {ll.shape}")
    if not (np.all(np.isfinite(lr)) and np.all(np.isfinite(ll))):
        raise ValueError("wheel distances must be finite (got NaN or inf)")


def integrate_poses(
    lr: ArrayLike, ll: ArrayLike, wheelbase: float | ArrayLike, start: ArrayLike = (0, 0, 0)
) -> NDArray[np.float64]:
    """Integrate wheel distances (eqs 1-3) along the last axis, vectorised over leading axes.

    ``lr``, ``ll`` have shape (..., N); ``wheelbase`` is a scalar or broadcasts to (..., N)
    (per-sample wheelbase, as in Monte Carlo runs). Returns the poses after each sample,
    shape (..., N, 3) as (x, y, th) with th unwrapped (cumulative).
    """
    lr = np.asarray(lr, dtype=float)
    ll = np.asarray(ll, dtype=float)
    _check_distances(lr, ll)
    d = np.asarray(wheelbase, dtype=float)
    if not np.all(np.isfinite(d)) or np.any(d <= 0):
        raise ValueError("wheelbase must be finite and positive")
    x0, y0, th0 = (float(v) for v in start)
    ds = 0.5 * (lr + ll)
    dth = (lr - ll) / d
    th_after = th0 + np.cumsum(dth, axis=-1)
    th_mid = th_after - 0.5 * dth
    x = x0 + np.cumsum(ds * np.cos(th_mid), axis=-1)
    y = y0 + np.cumsum(ds * np.sin(th_mid), axis=-1)
    return np.stack([x, y, th_after], axis=-1)


def step_jacobians(
    th: float, lr: float, ll: float, wheelbase: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Jacobians of one odometry step (eqs 1-3) w.r.t. the pose (F, 3x3) and u = [L_r, L_l, D]
    (G, 3x3), in world (x, y, th) coordinates."""
    D = wheelbase
    ds = 0.5 * (lr + ll)
    dth = (lr - ll) / D
    a = th + 0.5 * dth
    ca, sa = math.cos(a), math.sin(a)
    F = np.array([[1.0, 0.0, -ds * sa], [0.0, 1.0, ds * ca], [0.0, 0.0, 1.0]])
    # d(dth)/du = [1/D, -1/D, -(lr-ll)/D^2]; d(a)/du = half of that
    ddth = (1.0 / D, -1.0 / D, -(lr - ll) / (D * D))
    G = np.empty((3, 3))
    for j, dds in enumerate((0.5, 0.5, 0.0)):
        da = 0.5 * ddth[j]
        G[0, j] = dds * ca - ds * sa * da
        G[1, j] = dds * sa + ds * ca * da
        G[2, j] = ddth[j]
    return F, G


def propagate(
    lr: ArrayLike,
    ll: ArrayLike,
    params: OdometryParams,
    start: ArrayLike = (0.0, 0.0, 0.0),
    P0: ArrayLike | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Integrate samples from ``start`` (x, y, th) with covariance ``P0`` (world axes) and
    propagate the covariance by eq 4. Returns the final (x, y, th) and its 3x3 covariance."""
    lr = np.atleast_1d(np.asarray(lr, dtype=float))
    ll = np.atleast_1d(np.asarray(ll, dtype=float))
    _check_distances(lr, ll)
    x, y, th = (float(v) for v in start)
    P = np.zeros((3, 3)) if P0 is None else np.array(P0, dtype=float)
    if P.shape != (3, 3) or not np.all(np.isfinite(P)):
        raise ValueError("initial covariance must be a finite 3x3 matrix")
    D = params.wheelbase
    kr2, kl2, kd2D2 = params.k_r**2, params.k_l**2, (params.k_d * D) ** 2
    for r, l in zip(lr.tolist(), ll.tolist(), strict=True):
        F, G = step_jacobians(th, r, l, D)
        Q = np.diag((kr2 * r * r, kl2 * l * l, kd2D2))
        P = F @ P @ F.T + G @ Q @ G.T
        ds = 0.5 * (r + l)
        dth = (r - l) / D
        a = th + 0.5 * dth
        x += ds * math.cos(a)
        y += ds * math.sin(a)
        th += dth
    return np.array([x, y, th]), 0.5 * (P + P.T)


@dataclass(frozen=True)
class Preintegrated:
    """Relative motion between two keyframes, ready for a ``BetweenFactorPose2``.

    ``delta`` is the pose of keyframe 2 in the frame of keyframe 1; ``covariance`` is its
    3x3 covariance in GTSAM's convention (tangent space at ``delta``: body frame of
    keyframe 2, order [x, y, theta]); ``covariance_start`` the same in keyframe 1's axes.
    """

    delta: gtsam.Pose2
    covariance: NDArray[np.float64]
    covariance_start: NDArray[np.float64]
    n_samples: int

    def factor(self, key1: int, key2: int) -> gtsam.BetweenFactorPose2:
        """The between factor for keys ``key1`` -> ``key2``."""
        return gtsam.BetweenFactorPose2(
            key1, key2, self.delta, gtsam.noiseModel.Gaussian.Covariance(self.covariance)
        )


def to_between_covariance(P_start: ArrayLike, dth: float) -> NDArray[np.float64]:
    """Rotate a relative-pose covariance from keyframe 1's axes into the tangent space at the
    end of the motion (GTSAM's between error): J P J^T with J = blockdiag(R(dth)^T, 1)."""
    J = np.eye(3)
    J[:2, :2] = rot(dth).T
    P = J @ np.asarray(P_start, dtype=float) @ J.T
    return 0.5 * (P + P.T)


# Variance floor added to every preintegrated covariance (0.1 mm, 0.1 mrad standard deviation):
# a robot standing still has zero odometry uncertainty in eq 4, and a between factor that
# strong makes the factor graph ill conditioned (iSAM2 then reports an indeterminate system).
COVARIANCE_FLOOR = 1e-8


def preintegrate(lr: ArrayLike, ll: ArrayLike, params: OdometryParams) -> Preintegrated:
    """Integrate the samples between two keyframes in the first keyframe's frame, from the
    identity with zero covariance (plus :data:`COVARIANCE_FLOOR`); an empty interval gives
    the identity."""
    lr = np.atleast_1d(np.asarray(lr, dtype=float))
    if lr.size == 0:
        eps = np.eye(3) * COVARIANCE_FLOOR
        return Preintegrated(gtsam.Pose2(), eps, eps, 0)
    (x, y, th), P = propagate(lr, ll, params)
    P = P + np.eye(3) * COVARIANCE_FLOOR
    return Preintegrated(
        gtsam.Pose2(x, y, wrap_angle(th)), to_between_covariance(P, th), P, int(lr.size)
    )


def sample_wheel_noise(
    lr: ArrayLike, ll: ArrayLike, params: OdometryParams, n: int, rng: np.random.Generator
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Draw ``n`` noisy copies of nominal per-sample wheel distances and wheelbases from the
    eq 5 model. Returns arrays of shape (n, N): L_r, L_l and D per sample."""
    lr = np.asarray(lr, dtype=float)
    ll = np.asarray(ll, dtype=float)
    _check_distances(lr, ll)
    shape = (n, lr.size)
    D = params.wheelbase
    nr = lr + rng.standard_normal(shape) * params.k_r * np.abs(lr)
    nl = ll + rng.standard_normal(shape) * params.k_l * np.abs(ll)
    nd = D + rng.standard_normal(shape) * params.k_d * D
    return nr, nl, nd


class OdometryIntegrator:
    """Incremental eq 1-5 integration of timestamped encoder samples.

    Keeps the world pose (from odometry alone) and, since the last keyframe, the relative
    motion and its covariance. :meth:`keyframe` returns the :class:`Preintegrated` motion since
    the previous keyframe and restarts it. Timestamps (s) must not go backwards: a negative
    sample period, a NaN or an infinite distance raises ``ValueError`` and leaves the state
    unchanged.
    """

    def __init__(
        self, params: OdometryParams, t0: float | None = None, covariance: bool = True
    ) -> None:
        self.params = params
        self.track_covariance = covariance  # False: pose and velocity only (cheaper)
        self.t: float | None = t0
        self.pose = np.zeros(3)  # world (x, y, th), th unwrapped
        self._rel = np.zeros(3)  # since the last keyframe, keyframe axes
        self._P = np.zeros((3, 3))
        self._n = 0
        self.velocity = (0.0, 0.0)  # (v m/s, omega rad/s) over the last sample

    def add(self, t: float, lr: float, ll: float) -> None:
        """Add one sample: wheel distances lr, ll (m) travelled up to time t (s)."""
        if not (math.isfinite(t) and math.isfinite(lr) and math.isfinite(ll)):
            raise ValueError(f"odometry sample at t={t!r} is not finite: lr={lr!r}, ll={ll!r}")
        dt = None if self.t is None else t - self.t
        if dt is not None and dt < 0:
            raise ValueError(f"negative odometry sample period: t={t} after t={self.t}")
        p = self.params
        D = p.wheelbase
        if self.track_covariance:
            F, G = step_jacobians(self._rel[2], lr, ll, D)
            Q = np.diag((p.k_r**2 * lr * lr, p.k_l**2 * ll * ll, (p.k_d * D) ** 2))
            self._P = F @ self._P @ F.T + G @ Q @ G.T
        ds, dth = 0.5 * (lr + ll), (lr - ll) / D
        for state in (self._rel, self.pose):
            a = state[2] + 0.5 * dth
            state += (ds * math.cos(a), ds * math.sin(a), dth)
        self._n += 1
        if dt:
            self.velocity = (ds / dt, dth / dt)
        self.t = t

    def keyframe(self) -> Preintegrated:
        """Relative motion since the previous keyframe (GTSAM between convention); restart."""
        if self._n == 0:
            eps = np.eye(3) * COVARIANCE_FLOOR
            out = Preintegrated(gtsam.Pose2(), eps, eps, 0)
        else:
            P = 0.5 * (self._P + self._P.T) + np.eye(3) * COVARIANCE_FLOOR
            x, y, th = self._rel
            out = Preintegrated(
                gtsam.Pose2(x, y, wrap_angle(th)), to_between_covariance(P, th), P, self._n
            )
        self._rel = np.zeros(3)
        self._P = np.zeros((3, 3))
        self._n = 0
        return out
