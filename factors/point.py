"""Point landmark model: range and bearing to a world ``Point2`` (docs/design.md, 3.5, 3.7).

Sonar corners and edges chosen as point features are measured as (phi, r) in the sonar's
frame. The plain functions give Jacobians w.r.t. the robot's world (x, y, th) and the point's
world (px, py) for the EKF. In the factor graph the built-in C++ ``BearingRangeFactor2D``
is used: the measurement is moved from the sensor frame into the robot frame (an exact map of
the mean; the covariance is carried by its Jacobian, exact when the mount is a pure rotation).
A measurement that moves with a calibration variable (the speed of sound) is a Python factor
of the same error.
"""

from __future__ import annotations

import math

import gtsam
import numpy as np
from numpy.typing import ArrayLike, NDArray

from factors.calibrated import calibrated
from factors.geometry import bearing_range, sensor_pose, to_body_jacobian, wrap_angle
from factors.line import IDENTITY_MOUNT, Mount
from factors.noise import noise_model


def predict_point(
    pose: ArrayLike, point: ArrayLike, mount: Mount = IDENTITY_MOUNT
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Predicted (phi, r) in the sensor frame with Jacobians w.r.t. the robot's world pose
    (2x3) and the world point (2x2)."""
    x, y, th = pose
    xs, ys, ths, Js = sensor_pose(x, y, th, mount)
    phi, r, H_s, H_p = bearing_range(xs, ys, ths, point[0], point[1])
    return np.array([phi, r]), H_s @ Js, H_p


def point_residual(
    pose: ArrayLike, point: ArrayLike, measured: ArrayLike, mount: Mount = IDENTITY_MOUNT
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Residual prediction - measurement [bearing wrapped, range] and its Jacobians."""
    z, H_x, H_p = predict_point(pose, point, mount)
    return np.array([wrap_angle(z[0] - measured[0]), z[1] - measured[1]]), H_x, H_p


def point_to_world(
    pose: ArrayLike, measured: ArrayLike, mount: Mount = IDENTITY_MOUNT
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """World point of a sensor-frame (phi, r), with Jacobians w.r.t. the robot's world pose
    (2x3) and the measurement (2x2)."""
    x, y, th = pose
    phi, r = measured[0], measured[1]
    xs, ys, ths, Js = sensor_pose(x, y, th, mount)
    a = ths + phi
    ca, sa = math.cos(a), math.sin(a)
    H_s = np.array([[1.0, 0.0, -r * sa], [0.0, 1.0, r * ca]])
    H_z = np.array([[-r * sa, ca], [r * ca, sa]])
    return np.array([xs + r * ca, ys + r * sa]), H_s @ Js, H_z


def bearing_range_in_frame(
    measured: ArrayLike, mount: Mount
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """A sensor-frame (phi, r) as (bearing, range) in the frame the sensor's ``mount`` is
    given in, and its Jacobian w.r.t. (phi, r) (2x2)."""
    phi, r = float(measured[0]), float(measured[1])
    mx, my, mth = mount
    a = phi + mth
    px, py = mx + r * math.cos(a), my + r * math.sin(a)
    rr2 = px * px + py * py
    rr = math.sqrt(rr2)
    # d(px, py)/d(phi, r)
    Jp = np.array([[-r * math.sin(a), math.cos(a)], [r * math.cos(a), math.sin(a)]])
    Jbr = np.array([[-py / rr2, px / rr2], [px / rr, py / rr]])
    return np.array([math.atan2(py, px), rr]), Jbr @ Jp


def bearing_range_to_robot_frame(
    measured: ArrayLike, covariance: ArrayLike, mount: Mount
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Move a sensor-frame (phi, r) and its 2x2 covariance into the robot frame."""
    z, J = bearing_range_in_frame(measured, mount)
    C = J @ np.asarray(covariance, dtype=float) @ J.T
    return z, 0.5 * (C + C.T)


def point_factor(
    pose_key: int,
    point_key: int,
    measured: ArrayLike,
    covariance: ArrayLike,
    mount: Mount = IDENTITY_MOUNT,
    robust: str = "none",
    cal_key: int | None = None,
    cal_jacobian: ArrayLike | None = None,
    cal_gain: ArrayLike | None = None,
) -> gtsam.NonlinearFactor:
    """Built-in ``BearingRangeFactor2D`` for a sensor-frame (phi, r) with 2x2 covariance
    (order [bearing, range], as GTSAM's error); ``robust``: the robust kernel of its noise
    model (:func:`factors.noise.noise_model`). With ``cal_key`` (a calibration ``Vector``)
    the robot-frame measurement reads z + ``cal_jacobian`` c
    (:func:`factors.calibrated.calibrated`, with its ``cal_gain``; a Python factor of the
    same error)."""
    z, C = bearing_range_to_robot_frame(measured, covariance, mount)
    noise = noise_model(C, robust)
    if cal_key is None:
        return gtsam.BearingRangeFactor2D(pose_key, point_key, gtsam.Rot2(z[0]), z[1], noise)

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list | None) -> np.ndarray:
        p = values.atPose2(pose_key)
        th = p.theta()
        e, Hx, Hp = point_residual((p.x(), p.y(), th), values.atVector(point_key), z)
        if H is not None:
            H[0], H[1] = to_body_jacobian(Hx, th), Hp
        return e

    return calibrated(noise, [pose_key, point_key], cal_key, cal_jacobian, error, cal_gain)
