"""Measurements at their own time (docs/design.md, 6): a sonar reading taken between (or just after)
two keyframes is measured from the pose at its own time, which the graph expresses through
the two keyframe poses instead of moving the reading with odometry into a scan's frame.

The pose at fraction ``s`` of the way from keyframe pose ``a`` (s = 0) to ``b`` (s = 1) is
``a * Exp(s Log(a^-1 b))``: constant velocity and turn rate (one twist) between them;
``s`` a little beyond 1 extrapolates that twist (a reading shortly after the last keyframe).
Jacobians are w.r.t. GTSAM's body-frame tangents of the poses.
"""

from __future__ import annotations

from collections.abc import Callable

import gtsam
import numpy as np
from numpy.typing import ArrayLike, NDArray

from factors.calibrated import calibrated
from factors.geometry import to_body_jacobian

# residual(pose_world, landmark, z) -> (e, H_pose_world (k x 3), H_landmark (k x dim))
Residual = Callable[..., tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]]


def interpolate_pose(
    a: gtsam.Pose2, b: gtsam.Pose2, s: float
) -> tuple[gtsam.Pose2, NDArray[np.float64], NDArray[np.float64]]:
    """The pose ``a * Exp(s Log(a^-1 b))`` and its 3x3 Jacobians w.r.t. the body tangents of
    ``a`` and ``b`` (the result's body tangent)."""
    d = a.between(b)
    xi = gtsam.Pose2.Logmap(d)
    e = gtsam.Pose2.Expmap(s * xi)
    # d xi = LogD(d) [d_b - Ad(d^-1) d_a];  P = a e:  dP = Ad(e^-1) d_a + ExpD(s xi) s d xi
    G = s * gtsam.Pose2.ExpmapDerivative(s * xi) @ gtsam.Pose2.LogmapDerivative(d)
    Ha = e.inverse().AdjointMap() - G @ d.inverse().AdjointMap()
    return a.compose(e), Ha, G


def interpolated_factor(
    residual: Residual,
    key_a: int,
    key_b: int,
    key_l: int,
    s: float,
    z: ArrayLike,
    noise: gtsam.noiseModel.Base,
    cal_key: int | None = None,
    cal_jacobian: ArrayLike | None = None,
    cal_gain: ArrayLike | None = None,
) -> gtsam.CustomFactor:
    """A factor on keyframe poses ``key_a``, ``key_b`` and a vector landmark ``key_l``: the
    measurement ``z`` (robot frame at its own time) taken from the pose at fraction ``s``
    between them (:func:`interpolate_pose`); ``residual`` is the kind's prediction -
    measurement with world-frame Jacobians (e.g. :func:`factors.point.point_residual`). With
    ``cal_key`` the measurement reads z + ``cal_jacobian`` c
    (:func:`factors.calibrated.calibrated`, with its ``cal_gain``)."""
    z = np.asarray(z, dtype=float)

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list | None) -> np.ndarray:
        p, Ha, Hb = interpolate_pose(values.atPose2(key_a), values.atPose2(key_b), s)
        th = p.theta()
        e, Hx, Hl = residual((p.x(), p.y(), th), values.atVector(key_l), z)
        if H is not None:
            Hp = to_body_jacobian(Hx, th)
            H[0], H[1], H[2] = Hp @ Ha, Hp @ Hb, Hl
        return e

    if cal_key is not None:
        return calibrated(noise, [key_a, key_b, key_l], cal_key, cal_jacobian, error, cal_gain)
    return gtsam.CustomFactor(noise, [key_a, key_b, key_l], error)
