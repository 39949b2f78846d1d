"""Small SE(2) helpers shared by the models. Angles in rad, wrapped to (-pi, pi]."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

TWO_PI = 2.0 * math.pi

# The one angle wrap (docs/design.md, 2). Every wrap of the project calls one of the three
# functions below; tests/test_one_rule.py finds any other (an inline ``remainder(x, 2 pi)``,
# ``(x + pi) % (2 pi) - pi``, ``arctan2(sin x, cos x)`` or a function of its own).
#
# wrap_angle / wrap_angles: (-pi, pi], exact. fmod(a, 2 pi) is exact in floating point, and
# so is the one subtraction or addition of 2 pi after it (Sterbenz: the operands are within
# a factor 2 of each other), so the result is a - 2 pi n without rounding: an angle already
# inside is returned unchanged, and scalar and vectorised give the same bits. (It equals
# math.remainder(a, 2 pi) except at -pi, which becomes pi.)
#
# wrap_angle_half_open: [-pi, pi), as (a + pi) mod 2 pi - pi, which rounds a + pi (the last
# bits differ from wrap_angle's, and an angle an ulp below -pi comes out as pi). The
# simulator and the scan matcher's reference fans were written with it and keep it bit for
# bit: their outputs (simulated logs, the bearings a covered direction is searched among)
# stay the same, and the scan match's response spread takes the sign of an angle difference
# of exactly pi from it.


def wrap_angle(a: float) -> float:
    """Wrap a scalar angle to (-pi, pi], exactly (module note above)."""
    w = math.fmod(a, TWO_PI)
    if w > math.pi:
        return w - TWO_PI
    if w <= -math.pi:
        return w + TWO_PI
    return w


def wrap_angles(a: ArrayLike) -> NDArray[np.float64]:
    """Vectorised :func:`wrap_angle` (the same bits, element for element)."""
    w = np.fmod(np.asarray(a, dtype=float), TWO_PI)
    w = np.where(w > math.pi, w - TWO_PI, w)
    return np.where(w <= -math.pi, w + TWO_PI, w)


def wrap_angle_half_open(a: ArrayLike) -> float | NDArray[np.float64]:
    """``a`` (a float or an array) wrapped to [-pi, pi) as (a + pi) mod 2 pi - pi: the
    simulator's and the scan matcher's reference fans' convention (module note above); every
    other wrap is :func:`wrap_angle`."""
    return (a + math.pi) % TWO_PI - math.pi


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
