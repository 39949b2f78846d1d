"""Line landmark model (DESIGN 3.2, 3.7).

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

import math

import gtsam
import numpy as np
from numpy.typing import ArrayLike, NDArray

from factors.geometry import sensor_pose, to_body_jacobian, wrap_angle

Mount = tuple[float, float, float]
IDENTITY_MOUNT: Mount = (0.0, 0.0, 0.0)


def normalize_line(alpha: float, d: float) -> tuple[float, float]:
    """The (alpha, d) with d >= 0 and alpha in (-pi, pi] for the same line."""
    if d < 0:
        return wrap_angle(alpha + math.pi), -d
    return wrap_angle(alpha), d


def predict_line(
    pose: ArrayLike, line: ArrayLike, mount: Mount = IDENTITY_MOUNT
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Predicted (alpha, d) in the sensor frame, not normalised, with the Jacobians w.r.t.
    the robot's world (x, y, th) (2x3) and the world line (alpha_w, d_w) (2x2)."""
    x, y, th = pose
    aw, dw = line
    xs, ys, ths, Js = sensor_pose(x, y, th, mount)
    c, s = math.cos(aw), math.sin(aw)
    z = np.array([aw - ths, dw - xs * c - ys * s])
    H_s = np.array([[0.0, 0.0, -1.0], [-c, -s, 0.0]])
    H_l = np.array([[1.0, 0.0], [xs * s - ys * c, 1.0]])
    return z, H_s @ Js, H_l


def line_residual(
    pose: ArrayLike, line: ArrayLike, measured: ArrayLike, mount: Mount = IDENTITY_MOUNT
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Residual prediction - measurement [angle wrapped, distance] and its Jacobians w.r.t.
    the robot's world pose (2x3) and the world line (2x2). The EKF innovation is its negative."""
    z, H_x, H_l = predict_line(pose, line, mount)
    e_a = wrap_angle(z[0] - measured[0])
    if abs(e_a) > 0.5 * math.pi:  # use the (alpha + pi, -d) form of the prediction
        e_a = wrap_angle(e_a + math.pi)
        z[1] = -z[1]
        H_x[1] *= -1.0
        H_l[1] *= -1.0
    return np.array([e_a, z[1] - measured[1]]), H_x, H_l


def line_to_world(
    pose: ArrayLike, measured: ArrayLike, mount: Mount = IDENTITY_MOUNT
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """World line (alpha_w, d_w >= 0) of a sensor-frame measurement (alpha, d), with the
    Jacobians w.r.t. the robot's world pose (2x3) and the measurement (2x2)."""
    x, y, th = pose
    a, d = measured
    xs, ys, ths, Js = sensor_pose(x, y, th, mount)
    aw = a + ths
    c, s = math.cos(aw), math.sin(aw)
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
) -> gtsam.CustomFactor:
    """A factor between a robot ``Pose2`` and a world line ``Vector2`` (alpha_w, d_w) for a
    sensor-frame line measurement (alpha, d) with the given noise model."""
    meas = (float(measured[0]), float(measured[1]))
    mount = tuple(float(v) for v in mount)

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list | None) -> np.ndarray:
        p = values.atPose2(pose_key)
        th = p.theta()
        e, H_x, H_l = line_residual((p.x(), p.y(), th), values.atVector(line_key), meas, mount)
        if H is not None:
            H[0] = to_body_jacobian(H_x, th)
            H[1] = H_l
        return e

    return gtsam.CustomFactor(noise, [pose_key, line_key], error)
