"""Right-angle corner landmark model (docs/design.md, 3.3, 3.7).

A corner landmark is a world pose (cx, cy, c_theta): the vertex and the direction of its
bisector, pointing from the vertex into free space (toward the sensor for a concave corner
seen from inside, and for a convex corner seen from outside). Measured in the sensor frame as
b = (phi_c, r_c, gamma): bearing and range of the vertex and the bisector's direction.
Sonar corners measure (phi_c, r_c) only.

Jacobians of the plain functions are w.r.t. the robot's world (x, y, th) and the corner's
world (cx, cy, c_theta): what the EKF uses. The factors convert both to GTSAM's body tangent.
"""

from __future__ import annotations

import math
from math import atan2, cos, sin, sqrt

import gtsam
import numpy as np
from numpy.typing import ArrayLike, NDArray

from factors.calibrated import calibrated
from factors.geometry import sensor_pose, wrap_angle
from factors.line import IDENTITY_MOUNT, Mount


def _corner_terms(
    x: float, y: float, th: float, cx: float, cy: float, ct: float, mount: Mount
) -> tuple[float, float, float, float, float, float, float, float]:
    """Scalar core shared by every user of the model (lean: the factor callbacks call it).

    Returns (phi, r, gamma, a, b, u, v, w): the prediction (phi, gamma unwrapped) and the
    world Jacobians H_x = [[a, b, -1 - w], [-u, -v, ...]] written out in ``_corner_jacobians``.
    """
    mx, my, mth = mount
    c, s = cos(th), sin(th)
    ox, oy = c * mx - s * my, s * mx + c * my
    dx, dy = cx - x - ox, cy - y - oy
    ths = th + mth
    r2 = dx * dx + dy * dy
    if r2 < 1e-18:
        r2 = 1e-18
    r = sqrt(r2)
    return atan2(dy, dx) - ths, r, ct - ths, dx, dy, r2, ox, oy


def _corner_jacobians(
    dx: float, dy: float, r2: float, r: float, ox: float, oy: float
) -> tuple[tuple[float, ...], tuple[float, ...], tuple[float, ...], tuple[float, ...]]:
    """World Jacobian rows of (phi, r) w.r.t. the robot's (x, y, th) and the vertex (cx, cy)."""
    px, py = -dy / r2, dx / r2  # d(phi)/d(cx, cy)
    qx, qy = dx / r, dy / r  # d(r)/d(cx, cy)
    return (
        (-px, -py, -1.0 + px * oy - py * ox),
        (-qx, -qy, qx * oy - qy * ox),
        (px, py),
        (qx, qy),
    )


def predict_corner(
    pose: ArrayLike, corner: ArrayLike, mount: Mount = IDENTITY_MOUNT
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Predicted (phi_c, r_c, gamma) in the sensor frame (angles wrapped), with Jacobians
    w.r.t. the robot's world pose (3x3) and the corner's world (cx, cy, c_theta) (3x3)."""
    x, y, th = (float(v) for v in pose)
    phi, r, gamma, dx, dy, r2, ox, oy = _corner_terms(
        x, y, th, float(corner[0]), float(corner[1]), float(corner[2]), mount
    )
    hp, hr, cp, cr = _corner_jacobians(dx, dy, r2, r, ox, oy)
    H_x = np.array([hp, hr, (0.0, 0.0, -1.0)])
    H_c = np.array([(*cp, 0.0), (*cr, 0.0), (0.0, 0.0, 1.0)])
    return np.array([wrap_angle(phi), r, wrap_angle(gamma)]), H_x, H_c


def corner_residual(
    pose: ArrayLike, corner: ArrayLike, measured: ArrayLike, mount: Mount = IDENTITY_MOUNT
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Residual prediction - measurement (angles wrapped) and its Jacobians (3x3, 3x3)."""
    z, H_x, H_c = predict_corner(pose, corner, mount)
    e = np.array(
        [wrap_angle(z[0] - measured[0]), z[1] - measured[1], wrap_angle(z[2] - measured[2])]
    )
    return e, H_x, H_c


def corner_to_world(
    pose: ArrayLike, measured: ArrayLike, mount: Mount = IDENTITY_MOUNT
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """World corner (cx, cy, c_theta) of a sensor-frame (phi_c, r_c, gamma), with Jacobians
    w.r.t. the robot's world pose (3x3) and the measurement (3x3)."""
    x, y, th = pose
    phi, r, gamma = measured
    xs, ys, ths, Js = sensor_pose(x, y, th, mount)
    a = ths + phi
    ca, sa = math.cos(a), math.sin(a)
    corner = np.array([xs + r * ca, ys + r * sa, wrap_angle(gamma + ths)])
    H_s = np.array([[1.0, 0.0, -r * sa], [0.0, 1.0, r * ca], [0.0, 0.0, 1.0]])
    H_z = np.array([[-r * sa, ca, 0.0], [r * ca, sa, 0.0], [0.0, 0.0, 1.0]])
    return corner, H_s @ Js, H_z


def corner_factor(
    pose_key: int,
    corner_key: int,
    measured: ArrayLike,
    noise: gtsam.noiseModel.Base,
    mount: Mount = IDENTITY_MOUNT,
    cal_key: int | None = None,
    cal_jacobian: ArrayLike | None = None,
    cal_gain: ArrayLike | None = None,
) -> gtsam.CustomFactor:
    """Factor between a robot ``Pose2`` and a corner ``Pose2`` for a measured
    (phi_c, r_c, gamma) with a 3x3 noise model (full covariance allowed). With ``cal_key``
    (a calibration ``Vector``) the measurement reads z + ``cal_jacobian`` c
    (:func:`factors.calibrated.calibrated`, with its ``cal_gain``)."""
    return _make_corner_factor(
        pose_key, corner_key, measured, noise, mount, 3, cal_key, cal_jacobian, cal_gain
    )


def corner_bearing_range_factor(
    pose_key: int,
    corner_key: int,
    measured: ArrayLike,
    noise: gtsam.noiseModel.Base,
    mount: Mount = IDENTITY_MOUNT,
    cal_key: int | None = None,
    cal_jacobian: ArrayLike | None = None,
    cal_gain: ArrayLike | None = None,
) -> gtsam.CustomFactor:
    """Factor between a robot ``Pose2`` and a corner ``Pose2`` for a sonar corner: measured
    (phi_c, r_c) only, 2x2 noise model; the corner's orientation is left unconstrained.
    ``cal_key``, ``cal_jacobian``, ``cal_gain``: as :func:`corner_factor`."""
    return _make_corner_factor(
        pose_key, corner_key, measured, noise, mount, 2, cal_key, cal_jacobian, cal_gain
    )


def _make_corner_factor(
    pose_key: int,
    corner_key: int,
    measured: ArrayLike,
    noise: gtsam.noiseModel.Base,
    mount: Mount,
    dim: int,
    cal_key: int | None = None,
    cal_jacobian: ArrayLike | None = None,
    cal_gain: ArrayLike | None = None,
) -> gtsam.CustomFactor:
    pm, rm = float(measured[0]), float(measured[1])
    gm = float(measured[2]) if dim == 3 else 0.0
    mount = (float(mount[0]), float(mount[1]), float(mount[2]))
    # Per-factor Jacobian buffers (GTSAM copies on assignment); the gamma rows are constant.
    Hx = np.zeros((dim, 3))
    Hc = np.zeros((dim, 3))
    if dim == 3:
        Hx[2, 2] = -1.0
        Hc[2, 2] = 1.0
    array = np.array

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list | None) -> np.ndarray:
        p = values.atPose2(pose_key)
        q = values.atPose2(corner_key)
        th, ct = p.theta(), q.theta()
        phi, r, gamma, dx, dy, r2, ox, oy = _corner_terms(p.x(), p.y(), th, q.x(), q.y(), ct, mount)
        if H is not None:  # _corner_jacobians inlined: this callback is the hot path
            px, py, qx, qy = -dy / r2, dx / r2, dx / r, dy / r
            c, s = cos(th), sin(th)  # world -> body columns of the robot pose
            Hx[0, 0], Hx[0, 1], Hx[0, 2] = -px * c - py * s, px * s - py * c, px * oy - py * ox - 1
            Hx[1, 0], Hx[1, 1], Hx[1, 2] = -qx * c - qy * s, qx * s - qy * c, qx * oy - qy * ox
            c, s = cos(ct), sin(ct)  # and of the corner pose
            Hc[0, 0], Hc[0, 1] = px * c + py * s, py * c - px * s
            Hc[1, 0], Hc[1, 1] = qx * c + qy * s, qy * c - qx * s
            H[0] = Hx
            H[1] = Hc
        if dim == 3:
            return array((wrap_angle(phi - pm), r - rm, wrap_angle(gamma - gm)))
        return array((wrap_angle(phi - pm), r - rm))

    if cal_key is not None:
        return calibrated(noise, [pose_key, corner_key], cal_key, cal_jacobian, error, cal_gain)
    return gtsam.CustomFactor(noise, [pose_key, corner_key], error)
