"""Small SE(2) helpers shared by the models. Angles in rad, wrapped to (-pi, pi]."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

TWO_PI = 2.0 * math.pi


def wrap_angle(a: float) -> float:
    """Wrap a scalar angle to (-pi, pi]."""
    w = math.fmod(a + math.pi, TWO_PI)
    if w <= 0.0:
        w += TWO_PI
    return w - math.pi


def wrap_angles(a: ArrayLike) -> NDArray[np.float64]:
    """Vectorised :func:`wrap_angle`."""
    a = np.asarray(a, dtype=float)
    w = np.mod(a + np.pi, TWO_PI)
    w = np.where(w <= 0.0, w + TWO_PI, w)
    return w - np.pi


def rot(theta: float) -> NDArray[np.float64]:
    """2x2 rotation matrix R(theta)."""
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, -s], [s, c]])


def sensor_pose(
    x: float, y: float, th: float, mount: tuple[float, float, float]
) -> tuple[float, float, float, NDArray[np.float64]]:
    """World pose (xs, ys, ths) of a sensor mounted at ``mount`` = (mx, my, mth) in the robot
    frame, and the 3x3 Jacobian of (xs, ys, ths) w.r.t. the robot's world (x, y, th)."""
    mx, my, mth = mount
    c, s = math.cos(th), math.sin(th)
    ox, oy = c * mx - s * my, s * mx + c * my  # mount offset in world axes
    J = np.array([[1.0, 0.0, -oy], [0.0, 1.0, ox], [0.0, 0.0, 1.0]])
    return x + ox, y + oy, th + mth, J


def to_body_jacobian(H_world: NDArray[np.float64], th: float) -> NDArray[np.float64]:
    """Convert a Jacobian w.r.t. a pose's world (x, y, th) into one w.r.t. GTSAM's body-frame
    tangent [dx, dy, dth]: H = H_w blockdiag(R(th), 1)."""
    c, s = math.cos(th), math.sin(th)
    H = H_world.copy()
    H[:, 0] = H_world[:, 0] * c + H_world[:, 1] * s
    H[:, 1] = -H_world[:, 0] * s + H_world[:, 1] * c
    return H


def bearing_range(
    xs: float, ys: float, ths: float, px: float, py: float
) -> tuple[float, float, NDArray[np.float64], NDArray[np.float64]]:
    """Bearing (rad) and range (m) of world point (px, py) from sensor pose (xs, ys, ths).

    Returns (phi, r, H_s, H_p): H_s (2x3) w.r.t. the sensor's world (xs, ys, ths), H_p (2x2)
    w.r.t. the point's world (px, py). The range is floored at 1e-9 m to stay finite.
    """
    dx, dy = px - xs, py - ys
    c, s = math.cos(ths), math.sin(ths)
    lx, ly = c * dx + s * dy, -s * dx + c * dy
    r2 = max(lx * lx + ly * ly, 1e-18)
    r = math.sqrt(r2)
    # d(phi)/d(world point) = [-dy, dx]/r^2 ; d(r)/d(world point) = [dx, dy]/r
    H_p = np.array([[-dy / r2, dx / r2], [dx / r, dy / r]])
    H_s = np.array([[dy / r2, -dx / r2, -1.0], [-dx / r, -dy / r, 0.0]])
    return math.atan2(ly, lx), r, H_s, H_p


def compose_poses(a: ArrayLike, b: ArrayLike) -> NDArray[np.float64]:
    """a * b for poses (x, y, theta), one (3,) or row by row (N, 3); theta wrapped."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    return np.stack(
        [
            a[..., 0] + c * b[..., 0] - s * b[..., 1],
            a[..., 1] + s * b[..., 0] + c * b[..., 1],
            wrap_angles(a[..., 2] + b[..., 2]),
        ],
        axis=-1,
    )


def between_poses(a: ArrayLike, b: ArrayLike) -> NDArray[np.float64]:
    """inverse(a) * b for poses (x, y, theta): b in the frame of a; (3,) or (N, 3)."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    dx, dy = b[..., 0] - a[..., 0], b[..., 1] - a[..., 1]
    return np.stack(
        [c * dx + s * dy, -s * dx + c * dy, wrap_angles(b[..., 2] - a[..., 2])], axis=-1
    )


def invert_pose(a: ArrayLike) -> NDArray[np.float64]:
    """inverse(a) for a pose (x, y, theta)."""
    return between_poses(a, np.zeros(3))


def transform_points(pose: ArrayLike, points: ArrayLike) -> NDArray[np.float64]:
    """Points (N, 2) given in the frame of ``pose``, in the frame the pose is expressed in."""
    x, y, th = (float(v) for v in np.asarray(pose, dtype=float).reshape(3))
    p = np.asarray(points, dtype=float).reshape(-1, 2)
    c, s = math.cos(th), math.sin(th)
    return np.column_stack([x + c * p[:, 0] - s * p[:, 1], y + s * p[:, 0] + c * p[:, 1]])
