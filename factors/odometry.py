"""Differential-drive odometry: the paper's eqs 1-5 in REP-103 convention (docs/design.md, 3.1).

Per encoder sample with wheel distances L_r, L_l (m) and wheelbase D (m):
``ds = (L_r + L_l)/2``, ``dth = (L_r - L_l)/D``, ``x += ds cos(th + dth/2)``,
``y += ds sin(th + dth/2)``, ``th += dth``; covariance by eq 4 with u = [L_r, L_l, D] and
Q = diag(K_R^2 L_r^2, K_L^2 L_l^2, K_D^2 D^2) (eq 5), per sample.

:func:`preintegrate` turns the samples between two keyframes into a relative pose and the
covariance of a ``gtsam.BetweenFactorPose2`` (tangent space at the end of the motion).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import gtsam
import numpy as np
from numpy.typing import ArrayLike, NDArray

from factors.geometry import rot, wrap_angle
from factors.noise import noise_model


@dataclass(frozen=True)
class OdometryParams:
    """Wheelbase D (m), the eq 5 error parameters K_R, K_L, K_D (dimensionless), the motion
    error model and the odometry-hole model.

    Motion error model (added to eq 5; all 0 by default, the paper's model alone), per
    sample of travel ``ds`` (m) and turn ``dth`` (rad), in the frame of the sample's mean
    heading: along-track variance ``alpha3 |ds| + alpha4 |dth|`` (m^2), lateral variance
    ``alpha5 |ds|`` (m^2), turn variance ``alpha1 |dth| + alpha2 |ds|`` (rad^2). These are
    the four parameters of Probabilistic Robotics' odometry model (rotation from rotation,
    rotation from translation, translation from translation, translation from rotation)
    plus a lateral term, with variances proportional to the motion (a random walk) instead
    of its square, so that the covariance does not depend on how finely the motion is
    sampled.

    Odometry holes: a gap between consecutive samples (or the interval's ends) longer than
    ``hole_tolerance`` s gets the covariance of a motion that could have happened in it,
    ``diag((hole_speed g)^2, (hole_speed g)^2, (hole_turn_rate g)^2)`` for a gap of g s,
    added where the gap lies in the sequence (so that its heading error spreads into later
    positions).

    Encoder resolution: ``resolution_right``, ``resolution_left`` (m) are the smallest wheel
    distances the encoders tell apart (one tick). Every preintegrated interval, however short
    and even with the robot standing still, gets :func:`resolution_floor`: eq 5 is exactly 0
    for zero wheel motion, and a between factor without noise makes the factor graph
    singular. 0: no such floor (only :data:`COVARIANCE_FLOOR`).
    """

    wheelbase: float
    k_r: float
    k_l: float
    k_d: float
    alpha1: float = 0.0  # rad^2 per rad turned
    alpha2: float = 0.0  # rad^2 per m travelled
    alpha3: float = 0.0  # m^2 per m travelled
    alpha4: float = 0.0  # m^2 per rad turned
    alpha5: float = 0.0  # m^2 (lateral) per m travelled
    hole_tolerance: float = math.inf  # s
    hole_speed: float = 1.0  # m/s
    hole_turn_rate: float = 1.0  # rad/s
    resolution_right: float = 0.0  # m, one encoder tick of the right wheel
    resolution_left: float = 0.0  # m, of the left wheel

    def __post_init__(self) -> None:
        vals = (self.wheelbase, self.k_r, self.k_l, self.k_d, *self.alphas)
        vals += (self.hole_speed, self.hole_turn_rate, self.resolution_right)
        vals += (self.resolution_left,)
        if not all(math.isfinite(v) for v in vals) or self.wheelbase <= 0:
            raise ValueError(f"invalid odometry parameters {self}")
        if min(vals[1:]) < 0 or not self.hole_tolerance > 0:
            raise ValueError(f"odometry error parameters must be >= 0: {self}")

    @property
    def alphas(self) -> tuple[float, float, float, float, float]:
        return (self.alpha1, self.alpha2, self.alpha3, self.alpha4, self.alpha5)

    @property
    def has_motion_model(self) -> bool:
        return any(a > 0 for a in self.alphas)


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


def motion_jacobian(th: float, lr: float, ll: float, wheelbase: float) -> NDArray[np.float64]:
    """Jacobian of one step (eqs 1-3) from heading ``th`` w.r.t. the motion errors [along
    track (m), lateral (m), turn (rad)] of the motion error model, in world (x, y, th)."""
    ds = 0.5 * (lr + ll)
    a = th + 0.5 * (lr - ll) / wheelbase
    ca, sa = math.cos(a), math.sin(a)
    return np.array([[ca, -sa, -0.5 * ds * sa], [sa, ca, 0.5 * ds * ca], [0.0, 0.0, 1.0]])


def motion_noise(lr: float, ll: float, params: OdometryParams) -> NDArray[np.float64]:
    """Variances (along track m^2, lateral m^2, turn rad^2) of one sample under the motion
    error model of :class:`OdometryParams`."""
    a1, a2, a3, a4, a5 = params.alphas
    ds = abs(0.5 * (lr + ll))
    dth = abs((lr - ll) / params.wheelbase)
    return np.array([a3 * ds + a4 * dth, a5 * ds, a1 * dth + a2 * ds])


def step_noise(
    th: float, lr: float, ll: float, params: OdometryParams
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Covariance added by one sample from heading ``th`` (world axes): eq 4-5 and the motion
    error model. Returns (F, Q) with the step's pose Jacobian F: P <- F P F^T + Q."""
    F, Q, _ = _step_noise(th, lr, ll, params)
    return F, Q


def _step_noise(th: float, lr: float, ll: float, params: OdometryParams) -> tuple:
    """:func:`step_noise` and the step's Jacobian G w.r.t. [L_r, L_l, D]."""
    D = params.wheelbase
    F, G = step_jacobians(th, lr, ll, D)
    Qw = np.array((params.k_r**2 * lr * lr, params.k_l**2 * ll * ll, (params.k_d * D) ** 2))
    Q = (G * Qw) @ G.T
    if params.has_motion_model:
        M = motion_jacobian(th, lr, ll, D)
        Q = Q + (M * motion_noise(lr, ll, params)) @ M.T
    return F, Q, G


def hole_noise(gap: float, params: OdometryParams) -> NDArray[np.float64]:
    """Covariance of the motion that could have happened in an odometry hole of ``gap`` s."""
    v, w = params.hole_speed * gap, params.hole_turn_rate * gap
    return np.diag((v * v, v * v, w * w))


def _gaps(
    times: ArrayLike | None,
    span: tuple[float, float] | None,
    n: int,
    tol: float,
    last_sample: float | None = None,
) -> NDArray[np.float64]:
    """Hole time (s) to add before each of the n samples (only the first can get any) and
    after the last (index n), for the keyframe interval ``span`` = (t0, t1).

    A hole is a gap between two odometry samples longer than ``tol`` with a keyframe inside
    it (scans kept coming); a gap inside one keyframe interval is none. The part of a hole
    in an interval is counted there, and the part before the first keyframe that could know
    of it (the gap's elapsed time exceeding ``tol``) there too: so each second of a hole is
    counted once. ``last_sample``: the time of the last sample at or before t0 (None: t0).
    """
    out = np.zeros(n + 1)
    if times is None or span is None or not math.isfinite(tol):
        return out
    t = np.asarray(times, dtype=float)
    if t.shape != (n,):
        raise ValueError(f"{t.shape} sample times for {n} samples")
    t0, t1 = span
    last = t0 if last_sample is None else min(float(last_sample), t0)
    known = t0 - last > tol  # the gap was already a hole at t0 (counted up to t0)
    if n == 0:
        if t1 - last > tol:
            out[0] = t1 - t0 if known else t1 - last
        return out
    if last < t0 and t[0] - last > tol:  # a gap with the keyframe t0 inside it
        out[0] = t[0] - t0 if known else t[0] - last
    if t1 - t[-1] > tol:  # the keyframe t1 lies in a gap already longer than tol
        out[n] = t1 - t[-1]
    return out


def propagate(
    lr: ArrayLike,
    ll: ArrayLike,
    params: OdometryParams,
    start: ArrayLike = (0.0, 0.0, 0.0),
    P0: ArrayLike | None = None,
    times: ArrayLike | None = None,
    span: tuple[float, float] | None = None,
    last_sample: float | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Integrate samples from ``start`` (x, y, th) with covariance ``P0`` (world axes) and
    propagate the covariance by eq 4 (and the motion error model). With the samples'
    ``times``, the interval's ``span`` (t0, t1) and the ``last_sample`` time before it,
    odometry holes (:func:`_gaps`) add :func:`hole_noise` where they lie. Returns the final
    (x, y, th), its 3x3 covariance and the 3x3 Jacobian of (x, y, th) w.r.t. the calibration
    errors c = (e_r, e_l, e_b) at c = 0: the relative errors of the right and left wheel
    distances and of the wheelbase (true L_r = (1 + e_r) L_r, etc.)."""
    lr = np.atleast_1d(np.asarray(lr, dtype=float))
    ll = np.atleast_1d(np.asarray(ll, dtype=float))
    _check_distances(lr, ll)
    x, y, th = (float(v) for v in start)
    P = np.zeros((3, 3)) if P0 is None else np.array(P0, dtype=float)
    if P.shape != (3, 3) or not np.all(np.isfinite(P)):
        raise ValueError("initial covariance must be a finite 3x3 matrix")
    D = params.wheelbase
    gaps = _gaps(times, span, lr.size, params.hole_tolerance, last_sample)
    Jc = np.zeros((3, 3))
    for i, (r, l) in enumerate(zip(lr.tolist(), ll.tolist(), strict=True)):
        if gaps[i]:
            P = P + hole_noise(gaps[i], params)
        F, Q, G = _step_noise(th, r, l, params)
        P = F @ P @ F.T + Q
        Jc = F @ Jc + G * (r, l, D)  # d(step)/d(e_r, e_l, e_b) = d(step)/d(L_r, L_l, D) scaled
        ds = 0.5 * (r + l)
        dth = (r - l) / D
        a = th + 0.5 * dth
        x += ds * math.cos(a)
        y += ds * math.sin(a)
        th += dth
    if gaps[-1]:
        P = P + hole_noise(gaps[-1], params)
    return np.array([x, y, th]), 0.5 * (P + P.T), Jc


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
    hole_seconds: float = 0.0  # odometry holes in the interval (s), see OdometryParams
    # wheel odometry: d(x, y, theta)/d(e_r, e_l, e_b) in keyframe 1's axes at zero calibration
    # error (:func:`propagate`); None for a motion not measured by the wheels
    calibration_jacobian: NDArray[np.float64] | None = None

    def factor(self, key1: int, key2: int) -> gtsam.BetweenFactorPose2:
        """The between factor for keys ``key1`` -> ``key2``."""
        return gtsam.BetweenFactorPose2(key1, key2, self.delta, noise_model(self.covariance))


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
# A numerical guard, on top of the physical floor of the encoders (resolution_floor).
COVARIANCE_FLOOR = 1e-8


def resolution_floor(params: OdometryParams) -> NDArray[np.float64]:
    """The covariance (3x3, [x m, y m, theta rad], in the frame of the interval's end) that the
    encoders' resolution gives any preintegrated interval: each wheel's distance over it is
    the difference of two quantised readings, off by the difference of two errors uniform
    over one tick r (variance r^2 / 6). Hence along track ``(q_r + q_l) / 4``, heading
    ``(q_r + q_l) / D^2``, their covariance ``(q_r - q_l) / (2 D)`` (q = r^2 / 6). Wheels do
    not sense sideways motion at all; the lateral variance is taken equal to the along-track
    one, so that the floor has full rank (a robot standing still is placed no better
    sideways than along its track)."""
    q_r, q_l = params.resolution_right**2 / 6.0, params.resolution_left**2 / 6.0
    D = params.wheelbase
    along = 0.25 * (q_r + q_l)
    cross = 0.5 * (q_r - q_l) / D
    return np.array([[along, 0.0, cross], [0.0, along, 0.0], [cross, 0.0, (q_r + q_l) / D**2]])


def _floor_start(params: OdometryParams, dth: float) -> NDArray[np.float64]:
    """:data:`COVARIANCE_FLOOR` and :func:`resolution_floor` in the axes of the interval's
    start, for a motion turning ``dth`` rad (the floor lies in the end's axes)."""
    floor = to_between_covariance(resolution_floor(params), -dth)
    return floor + np.eye(3) * COVARIANCE_FLOOR


def preintegrate(
    lr: ArrayLike,
    ll: ArrayLike,
    params: OdometryParams,
    times: ArrayLike | None = None,
    span: tuple[float, float] | None = None,
    last_sample: float | None = None,
) -> Preintegrated:
    """Integrate the samples between two keyframes in the first keyframe's frame, from the
    identity with zero covariance (plus the floors: :func:`resolution_floor` of the
    encoders, :data:`COVARIANCE_FLOOR`); an empty interval gives the identity with them.
    With the samples' ``times``, the keyframes' times ``span`` and the time of the
    ``last_sample`` before the interval, odometry holes (:func:`_gaps`: gaps longer than the
    tolerance with a keyframe in them) get the covariance of :func:`hole_noise`."""
    lr = np.atleast_1d(np.asarray(lr, dtype=float))
    gaps = _gaps(times, span, lr.size, params.hole_tolerance, last_sample)
    hole = float(gaps.sum())
    if lr.size == 0:
        P = _floor_start(params, 0.0) + (hole_noise(hole, params) if hole else 0.0)
        return Preintegrated(gtsam.Pose2(), P, P, 0, hole, np.zeros((3, 3)))
    (x, y, th), P, Jc = propagate(lr, ll, params, times=times, span=span, last_sample=last_sample)
    P = P + _floor_start(params, th)
    return Preintegrated(
        gtsam.Pose2(x, y, wrap_angle(th)),
        to_between_covariance(P, th),
        P,
        int(lr.size),
        hole,
        Jc,
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


def sample_paths(
    lr: ArrayLike, ll: ArrayLike, params: OdometryParams, n: int, rng: np.random.Generator
) -> NDArray[np.float64]:
    """Final poses (n, 3) of ``n`` noisy runs of the samples: eq 5 wheel noise and the motion
    error model (along-track, lateral and turn errors per sample, variances from the nominal
    sample), integrated from the origin. For Monte Carlo checks of :func:`propagate`."""
    lr = np.asarray(lr, dtype=float)
    ll = np.asarray(ll, dtype=float)
    nr, nl, nd = sample_wheel_noise(lr, ll, params, n, rng)
    ds = 0.5 * (nr + nl)
    dth = (nr - nl) / nd
    var = np.array([motion_noise(r, l, params) for r, l in zip(lr, ll, strict=True)])
    var = var.reshape(-1, 3)
    e = rng.standard_normal((3, n, lr.size)) * np.sqrt(var.T)[:, None, :]
    dth = dth + e[2]
    th_after = np.cumsum(dth, axis=1)
    a = th_after - 0.5 * dth
    step = ds + e[0]
    x = np.sum(step * np.cos(a) - e[1] * np.sin(a), axis=1)
    y = np.sum(step * np.sin(a) + e[1] * np.cos(a), axis=1)
    return np.column_stack([x, y, th_after[:, -1]])


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
            F, Q = step_noise(self._rel[2], lr, ll, p)
            self._P = F @ self._P @ F.T + Q
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
            eps = _floor_start(self.params, 0.0)
            out = Preintegrated(gtsam.Pose2(), eps, eps, 0)
        else:
            x, y, th = self._rel
            P = 0.5 * (self._P + self._P.T) + _floor_start(self.params, th)
            out = Preintegrated(
                gtsam.Pose2(x, y, wrap_angle(th)), to_between_covariance(P, th), P, self._n
            )
        self._rel = np.zeros(3)
        self._P = np.zeros((3, 3))
        self._n = 0
        return out


def calibrated_delta(pre: Preintegrated, c: ArrayLike) -> NDArray[np.float64]:
    """The wheel motion ``pre`` (x, y, theta in keyframe 1's frame) under calibration errors
    ``c`` = (e_r, e_l, e_b), to first order: delta + J_c c."""
    d = np.array([pre.delta.x(), pre.delta.y(), pre.delta.theta()])
    if pre.calibration_jacobian is None:
        raise ValueError("this motion has no calibration Jacobian (not wheel odometry)")
    return d + pre.calibration_jacobian @ np.asarray(c, dtype=float)


def with_calibration(pre: Preintegrated, c: ArrayLike) -> Preintegrated:
    """``pre`` with its motion corrected for calibration errors ``c``
    (:func:`calibrated_delta`), the same covariances and Jacobian."""
    x, y, th = calibrated_delta(pre, c)
    th = wrap_angle(th)
    return dataclasses.replace(
        pre,
        delta=gtsam.Pose2(x, y, th),
        covariance=to_between_covariance(pre.covariance_start, th),
    )


def time_registration_jacobians(
    delta: ArrayLike, twist_start: ArrayLike, twist_end: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """d(delta)/d(t_start), d(delta)/d(t_end): how the relative pose ``delta`` (x, y, theta of
    keyframe 2 in keyframe 1's frame) moves when either keyframe's scan was taken 1 s later
    than its stamp says, the robot moving at ``twist`` = (v m/s forward, omega rad/s) then
    (docs/design.md, 3.4). Keyframe 1 later: its frame moves on by (v, 0, omega), so
    delta moves by -(v - omega y, omega x, omega); keyframe 2 later: delta moves by its own
    heading's (v cos theta, v sin theta, omega)."""
    x, y, th = (float(u) for u in delta)
    v0, w0 = (float(u) for u in twist_start)
    v1, w1 = (float(u) for u in twist_end)
    a = np.array([-v0 + w0 * y, -w0 * x, -w0])
    b = np.array([v1 * math.cos(th), v1 * math.sin(th), w1])
    return a, b


def with_time_registration(
    pre: Preintegrated, twist_start: ArrayLike, twist_end: ArrayLike, sigma_t: float
) -> Preintegrated:
    """``pre``, measured between two scans' stamps, as the motion between the robot's poses
    at the scans' true times, each scan's time off its stamp by an independent error of
    sigma ``sigma_t`` (s): its covariance gains sigma_t^2 (a a^T + b b^T)
    (:func:`time_registration_jacobians`). For one link only (e.g. to gate the next
    keyframe's features): along a chain the errors cancel, each keyframe's entering two
    links with opposite signs, and the graph models them once per scan (docs/design.md, 3.4)."""
    if not (math.isfinite(sigma_t) and sigma_t >= 0):
        raise ValueError("sigma_t must be finite and >= 0")
    d = (pre.delta.x(), pre.delta.y(), pre.delta.theta())
    a, b = time_registration_jacobians(d, twist_start, twist_end)
    P = np.asarray(pre.covariance_start, dtype=float) + sigma_t**2 * (
        np.outer(a, a) + np.outer(b, b)
    )
    return dataclasses.replace(
        pre, covariance_start=P, covariance=to_between_covariance(P, pre.delta.theta())
    )


def calibrated_error(
    pose_i: ArrayLike, pose_j: ArrayLike, c: ArrayLike, pre: Preintegrated
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Error of the wheel motion ``pre`` between world poses i and j under calibration
    errors ``c``: pose j in pose i's frame minus :func:`calibrated_delta`, as (x, y, theta)
    in keyframe i's axes (the heading wrapped); its covariance is ``pre.covariance_start``.
    Returns the error and its Jacobians w.r.t. GTSAM's body tangents of poses i and j (3x3
    each) and w.r.t. c (3x3).

    The error is in the wheels' own units, where their noise (``pre``'s covariance, computed
    from the measured distances) lives: the position's is the poses' motion minus
    :func:`calibrated_delta`'s, the heading's the poses' turn (1 + e_b) minus the measured turn
    and its e_r, e_l terms, each divided by the wheels' mean scale 1 + (e_r + e_l) / 2, so
    that a world scaled with the wheels and the wheelbase alike leaves it as it is; to first
    order it is the poses' motion minus :func:`calibrated_delta`. Scaling the measured turn
    by (1 - e_b) instead would make the wheels' noise a regressor's error: on a straight run
    the measured turn is that noise alone, and the fit shrinks the turn's scale towards it
    (e_b read 5e-3 high on the simulated corridor; docs/design.md, 6)."""
    xi, yi, ti = (float(v) for v in pose_i)
    xj, yj, tj = (float(v) for v in pose_j)
    co, si = math.cos(ti), math.sin(ti)
    dx, dy = xj - xi, yj - yi
    qx, qy = co * dx + si * dy, -si * dx + co * dy
    c = np.asarray(c, dtype=float)
    m = calibrated_delta(pre, c)
    Hc = -pre.calibration_jacobian.copy()
    measured = Hc[2, 2]  # the measured turn (d theta / d e_b = -turn)
    off = wrap_angle(tj - ti - measured)  # the poses' turn minus the measured one
    e_b = float(c[2])
    k = 1.0 / (1.0 + 0.5 * (float(c[0]) + float(c[1])))  # 1 / the wheels' mean scale
    e = k * np.array([qx - m[0], qy - m[1], wrap_angle(tj - ti - m[2]) + off * e_b])
    Hc[2, 2] = measured + off  # the poses' turn
    Hc = k * Hc - np.outer(e, [0.5 * k, 0.5 * k, 0.0])
    Hi = k * np.array([[-1.0, 0.0, qy], [0.0, -1.0, -qx], [0.0, 0.0, -1.0 - e_b]])
    cd, sd = math.cos(tj - ti), math.sin(tj - ti)
    Hj = k * np.array([[cd, -sd, 0.0], [sd, cd, 0.0], [0.0, 0.0, 1.0 + e_b]])
    return e, Hi, Hj, Hc


def calibrated_odometry_factor(
    key_i: int,
    key_j: int,
    key_c: int,
    pre: Preintegrated,
    noise: gtsam.noiseModel.Base,
    columns: slice = slice(0, 3),
    dim: int = 3,
) -> gtsam.CustomFactor:
    """A factor between poses i, j (``Pose2``) and the calibration errors (a ``Vector`` of
    ``dim``, the wheels' (e_r, e_l, e_b) at ``columns``) for the wheel motion ``pre``:
    :func:`calibrated_error`, with a noise model of ``pre.covariance_start`` (keyframe i's
    axes)."""
    Hfull = np.zeros((3, dim))

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list | None) -> np.ndarray:
        a, b = values.atPose2(key_i), values.atPose2(key_j)
        c = values.atVector(key_c)[columns]
        pa, pb = (a.x(), a.y(), a.theta()), (b.x(), b.y(), b.theta())
        e, Hi, Hj, Hc = calibrated_error(pa, pb, c, pre)
        if H is not None:
            Hfull[:, columns] = Hc
            H[0], H[1], H[2] = Hi, Hj, Hfull
        return e

    return gtsam.CustomFactor(noise, [key_i, key_j, key_c], error)


def relative_pose(delta: ArrayLike, covariance: ArrayLike) -> Preintegrated:
    """A measured relative pose (e.g. a scan match) as a :class:`Preintegrated`: ``delta`` =
    (x, y, theta) of keyframe 2 in keyframe 1's frame (m, rad), ``covariance`` in GTSAM's
    between convention (tangent at ``delta``); ``covariance_start`` is rotated back into
    keyframe 1's axes (the inverse of :func:`to_between_covariance`)."""
    x, y, th = (float(v) for v in np.asarray(delta, dtype=float).reshape(3))
    C = np.asarray(covariance, dtype=float).reshape(3, 3)
    C = 0.5 * (C + C.T)
    J = np.eye(3)
    J[:2, :2] = rot(th)
    P = J @ C @ J.T
    return Preintegrated(gtsam.Pose2(x, y, wrap_angle(th)), C, 0.5 * (P + P.T), 0)


def motion_mahalanobis(a: Preintegrated, b: Preintegrated) -> float:
    """Squared Mahalanobis distance between two measurements of one relative motion (the
    difference in the tangent at ``b``; both covariances there, to first order)."""
    xi = b.delta.localCoordinates(a.delta)
    S = a.covariance + b.covariance
    return float(xi @ np.linalg.solve(S, xi))


def fuse_motions(a: Preintegrated, b: Preintegrated) -> Preintegrated:
    """The information-weighted fusion of two independent measurements of one relative
    motion (e.g. wheel odometry and a scan match), linearised in the tangent at ``b``:
    C = (Ca^-1 + Cb^-1)^-1, xi = C Ca^-1 (a - b), delta = b retracted by xi; the same as the
    two between factors of the factor graph solved together, to first order. A calibration
    Jacobian of ``a`` (wheel odometry) is carried into the fusion's, through the chain
    a (start axes -> a's tangent) -> xi (Log's derivative) -> C Ca^-1 xi -> delta (Exp's
    derivative, then delta's tangent -> start axes)."""
    xi = b.delta.localCoordinates(a.delta)
    Ia = np.linalg.inv(a.covariance)
    C = np.linalg.inv(Ia + np.linalg.inv(b.covariance))
    C = 0.5 * (C + C.T)
    xf = C @ Ia @ xi
    d = b.delta.retract(xf)
    out = relative_pose([d.x(), d.y(), d.theta()], C)
    if a.calibration_jacobian is None:
        return out
    Ra, Rd = np.eye(3), np.eye(3)
    Ra[:2, :2] = rot(a.delta.theta()).T
    Rd[:2, :2] = rot(d.theta())
    J = Rd @ gtsam.Pose2.ExpmapDerivative(xf) @ C @ Ia
    J = J @ gtsam.Pose2.LogmapDerivative(b.delta.between(a.delta)) @ Ra
    return dataclasses.replace(out, calibration_jacobian=J @ a.calibration_jacobian)


def link_motions(
    wheels: Preintegrated, scan: Preintegrated, gate: float
) -> tuple[Preintegrated | None, Preintegrated]:
    """What a filter predicts with, given wheel odometry and a scan match of one keyframe
    link: both (to be fused) when their squared Mahalanobis distance
    (:func:`motion_mahalanobis`) is within ``gate``, else the scan match alone (``None`` for
    the wheels). The scan match already passed its own checks (score, overlap, ambiguity);
    wheels slip. On the real logs, of the links where the two disagreed at p = 0.999 the
    scan match was the nearer to the reference poses in 3 of 3 (Intel) and 61 of 62
    (Freiburg 079); in the simulated corridor the wheels were right in every case (the
    matcher's tail along bare walls and behind people walking): CHANGELOG.md (issue 14). The
    EKF's rule only: the factor graph keeps both as robust factors, and the landmarks and
    loops decide (given to the graph too, the rule took the corridor from 7 cm to 2.6 m)."""
    if motion_mahalanobis(wheels, scan) <= gate:
        return wheels, scan
    return None, scan
