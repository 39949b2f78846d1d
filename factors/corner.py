"""Right-angle corner landmark model (DESIGN 3.3, 3.7).

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

import gtsam
import numpy as np
from numpy.typing import ArrayLike, NDArray

from factors.geometry import bearing_range, sensor_pose, to_body_jacobian, wrap_angle
from factors.line import IDENTITY_MOUNT, Mount


def predict_corner(
    pose: ArrayLike, corner: ArrayLike, mount: Mount = IDENTITY_MOUNT
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Predicted (phi_c, r_c, gamma) in the sensor frame (angles wrapped), with Jacobians
    w.r.t. the robot's world pose (3x3) and the corner's world (cx, cy, c_theta) (3x3)."""
    x, y, th = pose
    cx, cy, ct = corner
    xs, ys, ths, Js = sensor_pose(x, y, th, mount)
    phi, r, H_s2, H_p = bearing_range(xs, ys, ths, cx, cy)
    z = np.array([phi, r, wrap_angle(ct - ths)])
    H_s = np.zeros((3, 3))
    H_s[:2] = H_s2
    H_s[2, 2] = -1.0
    H_c = np.zeros((3, 3))
    H_c[:2, :2] = H_p
    H_c[2, 2] = 1.0
    return z, H_s @ Js, H_c


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
) -> gtsam.CustomFactor:
    """Factor between a robot ``Pose2`` and a corner ``Pose2`` for a measured
    (phi_c, r_c, gamma) with a 3x3 noise model (full covariance allowed)."""
    meas = tuple(float(v) for v in measured)
    mount = tuple(float(v) for v in mount)

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list | None) -> np.ndarray:
        p = values.atPose2(pose_key)
        c = values.atPose2(corner_key)
        th, ct = p.theta(), c.theta()
        e, H_x, H_c = corner_residual((p.x(), p.y(), th), (c.x(), c.y(), ct), meas, mount)
        if H is not None:
            H[0] = to_body_jacobian(H_x, th)
            H[1] = to_body_jacobian(H_c, ct)
        return e

    return gtsam.CustomFactor(noise, [pose_key, corner_key], error)


def corner_bearing_range_factor(
    pose_key: int,
    corner_key: int,
    measured: ArrayLike,
    noise: gtsam.noiseModel.Base,
    mount: Mount = IDENTITY_MOUNT,
) -> gtsam.CustomFactor:
    """Factor between a robot ``Pose2`` and a corner ``Pose2`` for a sonar corner: measured
    (phi_c, r_c) only, 2x2 noise model; the corner's orientation is left unconstrained."""
    meas = (float(measured[0]), float(measured[1]))
    mount = tuple(float(v) for v in mount)

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list | None) -> np.ndarray:
        p = values.atPose2(pose_key)
        c = values.atPose2(corner_key)
        th, ct = p.theta(), c.theta()
        xs, ys, ths, Js = sensor_pose(p.x(), p.y(), th, mount)
        phi, r, H_s, H_p = bearing_range(xs, ys, ths, c.x(), c.y())
        if H is not None:
            H[0] = to_body_jacobian(H_s @ Js, th)
            H_c = np.zeros((2, 3))
            H_c[:, :2] = H_p
            H[1] = to_body_jacobian(H_c, ct)
        return np.array([wrap_angle(phi - meas[0]), r - meas[1]])

    return gtsam.CustomFactor(noise, [pose_key, corner_key], error)
