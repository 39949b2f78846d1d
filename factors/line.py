"""Line landmark model (docs/design.md, 3.2, 3.7).

A line is (alpha, d): the points p with p . (cos alpha, sin alpha) = d. A world line
``(alpha_w, d_w)`` seen from a sensor at world pose (xs, ys, ths) is predicted in the sensor
frame as ``alpha = alpha_w - ths``, ``d = d_w - xs cos alpha_w - ys sin alpha_w``.
A line has two parametrisations, (alpha, d) and (alpha + pi, -d). The residual picks the one
of the prediction whose normal agrees with the measurement's (angle residual within pi/2), so
it is smooth through d = 0 and across alpha = +-pi; measurements are fitted with d >= 0.

Jacobians of the plain functions are w.r.t. the robot's world (x, y, th) and the line's
(alpha_w, d_w): what the EKF uses. :func:`line_factor` converts to GTSAM's body tangent.
"""

from __future__ import annotations

from math import cos, pi, sin

import gtsam
import numpy as np
from numpy.typing import ArrayLike, NDArray

from factors.calibrated import calibrated
from factors.geometry import sensor_pose, wrap_angle, wrap_angles

Mount = tuple[float, float, float]
IDENTITY_MOUNT: Mount = (0.0, 0.0, 0.0)
HALF_PI = 0.5 * pi


def flips(angle_residual: float | NDArray[np.float64]) -> bool | NDArray[np.bool_]:
    """THE rule for the two parametrisations of a line, (alpha, d) and (alpha + pi, -d): two
    descriptions of a line are compared in the form whose angles differ by at most pi/2;
    ``angle_residual`` (wrapped) beyond that means "compare against (alpha + pi, -d)". Every
    residual, merge and association of lines uses this function (vectorised on arrays)."""
    return abs(angle_residual) > HALF_PI


def line_difference(a: ArrayLike, b: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Difference a - b of two world lines as the same line (either parametrisation, by
    :func:`flips`): [angle wrapped, distance], and its Jacobian w.r.t. b (w.r.t. a: identity)."""
    da = wrap_angle(float(a[0]) - float(b[0]))
    if flips(da):
        return np.array([wrap_angle(da - pi), float(a[1]) + float(b[1])]), np.array(
            [[-1.0, 0.0], [0.0, 1.0]]
        )
    return np.array([da, float(a[1]) - float(b[1])]), -np.eye(2)


def line_differences(a: ArrayLike, M: ArrayLike) -> NDArray[np.float64]:
    """:func:`line_difference` without Jacobians, vectorised: ``a`` (2,) or each row of ``a``
    (q, 2) against each row of ``M`` (n, 2): (n, 2) or (q, n, 2), the same arithmetic."""
    a, M = np.asarray(a, dtype=float), np.asarray(M, dtype=float)
    E = a[..., None, :] - M
    da = wrap_angles(E[..., 0])
    f = flips(da)
    E[..., 0] = np.where(f, wrap_angles(da - pi), da)
    E[..., 1] = np.where(f, a[..., None, 1] + M[:, 1], E[..., 1])
    return E


def normalize_line(alpha: float, d: float) -> tuple[float, float]:
    """The (alpha, d) with d >= 0 and alpha in (-pi, pi] for the same line."""
    if d < 0:
        return wrap_angle(alpha + pi), -d
    return wrap_angle(alpha), d


def normalize_lines(
    alpha: ArrayLike, d: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Vectorised :func:`normalize_line`: (alpha in (-pi, pi], d >= 0) element for element."""
    alpha, d = np.asarray(alpha, dtype=float), np.asarray(d, dtype=float)
    return wrap_angles(np.where(d < 0, alpha + pi, alpha)), np.abs(d)


def _line_terms(
    x: float, y: float, th: float, aw: float, dw: float, am: float, dm: float, mount: Mount
) -> tuple[float, float, float, float, float, float, float]:
    """Scalar core shared by every user of the model (lean: the factor callback calls it).

    Returns (e_alpha, e_d, g0, g1, g2, q, sg): the residual, and the world Jacobians
    H_x = [[0, 0, -1], [g0, g1, g2]] and H_l = [[1, 0], [q, sg]].
    """
    mx, my, mth = mount
    c, s = cos(th), sin(th)
    ox, oy = c * mx - s * my, s * mx + c * my
    xs, ys = x + ox, y + oy
    ca, sa = cos(aw), sin(aw)
    d = dw - xs * ca - ys * sa
    e0 = wrap_angle(aw - th - mth - am)
    sg = 1.0
    if flips(e0):  # use the (alpha + pi, -d) form of the prediction
        e0 = wrap_angle(e0 + pi)
        sg = -1.0
    return (
        e0,
        sg * d - dm,
        -sg * ca,
        -sg * sa,
        sg * (ca * oy - sa * ox),
        sg * (xs * sa - ys * ca),
        sg,
    )


def predict_line(
    pose: ArrayLike, line: ArrayLike, mount: Mount = IDENTITY_MOUNT
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Predicted (alpha, d) in the sensor frame, not normalised (alpha = alpha_w - ths may
    leave (-pi, pi]), with the Jacobians w.r.t. the robot's world (x, y, th) (2x3) and the
    world line (alpha_w, d_w) (2x2)."""
    x, y, th = (float(v) for v in pose)
    aw, dw = float(line[0]), float(line[1])
    # measuring against the prediction's own angle keeps the (alpha, d) form
    a = aw - th - mount[2]
    _, e1, g0, g1, g2, q, _ = _line_terms(x, y, th, aw, dw, a, 0.0, mount)
    return (
        np.array([a, e1]),
        np.array([[0.0, 0.0, -1.0], [g0, g1, g2]]),
        np.array([[1.0, 0.0], [q, 1.0]]),
    )


def line_residual(
    pose: ArrayLike, line: ArrayLike, measured: ArrayLike, mount: Mount = IDENTITY_MOUNT
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Residual prediction - measurement [angle wrapped, distance] and its Jacobians w.r.t.
    the robot's world pose (2x3) and the world line (2x2). The EKF innovation is its negative."""
    x, y, th = (float(v) for v in pose)
    e0, e1, g0, g1, g2, q, sg = _line_terms(
        x, y, th, float(line[0]), float(line[1]), float(measured[0]), float(measured[1]), mount
    )
    return (
        np.array([e0, e1]),
        np.array([[0.0, 0.0, -1.0], [g0, g1, g2]]),
        np.array([[1.0, 0.0], [q, sg]]),
    )


def line_residuals(pose: ArrayLike, lines: ArrayLike, Z: ArrayLike) -> NDArray[np.float64]:
    """:func:`line_residual` without Jacobians (identity mount), vectorised: each measurement
    row of ``Z`` (m, 2) against each world line of ``lines`` (n, 2): (m, n, 2), by the same
    formulas and flip rule as :func:`_line_terms`."""
    x, y, th = (float(v) for v in pose)
    lines, Z = np.asarray(lines, dtype=float).reshape(-1, 2), np.asarray(Z, dtype=float)
    aw, dw = lines[:, 0], lines[:, 1]
    e0 = wrap_angles(aw - th - Z[:, 0:1])
    flip = flips(e0)  # the (alpha + pi, -d) form of the prediction
    e0 = np.where(flip, wrap_angles(e0 + pi), e0)
    d = dw - x * np.cos(aw) - y * np.sin(aw)
    return np.stack([e0, np.where(flip, -d, d) - Z[:, 1:2]], axis=-1)


def line_to_world(
    pose: ArrayLike, measured: ArrayLike, mount: Mount = IDENTITY_MOUNT
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """World line (alpha_w, d_w >= 0) of a sensor-frame measurement (alpha, d), with the
    Jacobians w.r.t. the robot's world pose (2x3) and the measurement (2x2)."""
    x, y, th = pose
    a, d = measured
    xs, ys, ths, Js = sensor_pose(x, y, th, mount)
    aw = a + ths
    c, s = cos(aw), sin(aw)
    dw = d + xs * c + ys * s
    t = -xs * s + ys * c  # d(dw)/d(aw)
    H_s = np.array([[0.0, 0.0, 1.0], [c, s, t]])
    H_z = np.array([[1.0, 0.0], [t, 1.0]])
    if dw < 0:
        H_s[1] *= -1.0
        H_z[1] *= -1.0
    return np.array(normalize_line(aw, dw)), H_s @ Js, H_z


def line_factor(
    pose_key: int,
    line_key: int,
    measured: ArrayLike,
    noise: gtsam.noiseModel.Base,
    mount: Mount = IDENTITY_MOUNT,
    cal_key: int | None = None,
    cal_jacobian: ArrayLike | None = None,
    cal_gain: ArrayLike | None = None,
) -> gtsam.CustomFactor:
    """A factor between a robot ``Pose2`` and a world line ``Vector2`` (alpha_w, d_w) for a
    sensor-frame line measurement (alpha, d) with the given noise model. The pose Jacobian is
    w.r.t. GTSAM's body tangent: world columns rotated by the robot's heading. With
    ``cal_key`` (a calibration ``Vector``) the measurement reads z + ``cal_jacobian`` c
    (:func:`factors.calibrated.calibrated`, with its ``cal_gain``)."""
    am, dm = float(measured[0]), float(measured[1])
    mount = (float(mount[0]), float(mount[1]), float(mount[2]))
    # Per-factor Jacobian buffers: GTSAM copies them on assignment, and filling a few
    # entries is far cheaper than building arrays (the callback is the hot path).
    Hx = np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 0.0]])
    Hl = np.array([[1.0, 0.0], [0.0, 0.0]])
    array = np.array

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list | None) -> np.ndarray:
        p = values.atPose2(pose_key)
        aw, dw = values.atVector(line_key).tolist()
        th = p.theta()
        e0, e1, g0, g1, g2, q, sg = _line_terms(p.x(), p.y(), th, aw, dw, am, dm, mount)
        if H is not None:
            c, s = cos(th), sin(th)
            Hx[1, 0] = g0 * c + g1 * s
            Hx[1, 1] = g1 * c - g0 * s
            Hx[1, 2] = g2
            Hl[1, 0] = q
            Hl[1, 1] = sg
            H[0] = Hx
            H[1] = Hl
        return array((e0, e1))

    if cal_key is not None:
        return calibrated(noise, [pose_key, line_key], cal_key, cal_jacobian, error, cal_gain)
    return gtsam.CustomFactor(noise, [pose_key, line_key], error)
