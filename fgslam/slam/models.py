"""The three landmark kinds, seen from SLAM: one registry (:data:`KINDS`, a :class:`Kind`
each) that maps a kind to the shared prediction/residual/initialisation functions of
``factors``, its GTSAM value and factors, the difference of two landmarks (one line-flip
rule) and the rotation of its tangent covariance into the world; the EKF, the graph, the
association and the lifecycle ask it instead of branching on the kind. Features are in the
robot frame, so the sensor mount is the identity.

World parametrisations (what the EKF stores and the map reports): line (alpha, d); corner
(x, y, theta) with theta the bisector into free space; point (x, y). Angles rad, lengths m.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import gtsam
import numpy as np
from numpy.typing import NDArray

from factors.corner import (
    corner_bearing_range_factor,
    corner_factor,
    corner_residual,
    corner_to_world,
)
from factors.geometry import wrap_angle, wrap_angles
from factors.line import (
    line_difference,
    line_differences,
    line_factor,
    line_residual,
    line_residuals,
    line_to_world,
    normalize_line,
)
from factors.noise import ROBUST_KERNELS as ROBUST_KERNELS
from factors.noise import noise_model
from factors.own_time import interpolated_factor
from factors.point import point_factor, point_residual, point_to_world
from fgslam.frontend.features import Feature, OwnTime


def rot_block(th: float) -> NDArray[np.float64]:
    """blockdiag(R(th), 1): a ``Pose2``'s body tangent at heading ``th`` into world axes."""
    c, s = math.cos(th), math.sin(th)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _line_equality(k1: int, k2: int, noise: gtsam.noiseModel.Base) -> gtsam.CustomFactor:
    """Two line variables describe the same line (either parametrisation, by the one rule
    :func:`factors.line.line_difference`)."""

    def error(this, values, H):
        e, Hb = line_difference(values.atVector(k1), values.atVector(k2))
        if H is not None:
            H[0], H[1] = np.eye(2), Hb
        return e

    return gtsam.CustomFactor(noise, [k1, k2], error)


def _vector_difference(angular: tuple[bool, ...]):
    def difference(a, b):
        e = np.asarray(a, dtype=float) - np.asarray(b, dtype=float)
        for i, ang in enumerate(angular):
            if ang:
                e[i] = wrap_angle(e[i])
        return e, -np.eye(len(e))

    return difference


@dataclass(frozen=True)
class Kind:
    """One landmark kind: its world parameters' dimension and which are angles; the GTSAM
    variable is a ``Pose2`` (``pose``) or a vector; ``difference(a, b)``: a - b of two world
    landmarks and its Jacobian w.r.t. b; ``equality(k1, k2, noise)``: the factor tying two
    variables of one landmark; ``tangent_to_world(mean)``: the rotation taking a tangent-space
    covariance (GTSAM's) into world parameters."""

    name: str
    dim: int
    angular: tuple[bool, ...]
    pose: bool
    difference: Callable
    equality: Callable

    def tangent_to_world(self, mean: NDArray[np.float64]) -> NDArray[np.float64]:
        return rot_block(float(mean[2])) if self.pose else np.eye(self.dim)

    def value(self, lm: NDArray[np.float64]) -> object:
        """The GTSAM value of world parameters ``lm``."""
        if self.pose:
            return gtsam.Pose2(float(lm[0]), float(lm[1]), float(lm[2]))
        return np.asarray(lm, dtype=float)

    def read(self, values: gtsam.Values, key: int) -> NDArray[np.float64]:
        """World parameters of variable ``key`` in ``values``."""
        if self.pose:
            p = values.atPose2(key)
            return np.array([p.x(), p.y(), p.theta()])
        return np.array(values.atVector(key))

    def read_isam(self, isam: gtsam.ISAM2, key: int) -> NDArray[np.float64]:
        """World parameters of variable ``key`` solved by ``isam`` for now."""
        if self.pose:
            p = isam.calculateEstimatePose2(key)
            return np.array([p.x(), p.y(), p.theta()])
        return np.array(isam.calculateEstimateVector(key))


def _pose2_equality(k1: int, k2: int, noise: gtsam.noiseModel.Base) -> gtsam.NonlinearFactor:
    return gtsam.BetweenFactorPose2(k1, k2, gtsam.Pose2(), noise)


def _point2_equality(k1: int, k2: int, noise: gtsam.noiseModel.Base) -> gtsam.NonlinearFactor:
    return gtsam.BetweenFactorPoint2(k1, k2, np.zeros(2), noise)


KINDS = {
    "line": Kind("line", 2, (True, False), False, line_difference, _line_equality),
    "corner": Kind(
        "corner",
        3,
        (False, False, True),
        True,
        _vector_difference((False, False, True)),
        _pose2_equality,
    ),
    "point": Kind(
        "point", 2, (False, False), False, _vector_difference((False, False)), _point2_equality
    ),
}
DIM = {k: v.dim for k, v in KINDS.items()}
ANGULAR = {k: v.angular for k, v in KINDS.items()}


def difference(
    kind: str, a: NDArray[np.float64], b: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """a - b for two world landmarks of one kind, and its Jacobian w.r.t. b (lines: the one
    line-flip rule, :func:`factors.line.line_difference`)."""
    return KINDS[kind].difference(a, b)


def differences(kind: str, a: NDArray[np.float64], M: NDArray[np.float64]) -> NDArray[np.float64]:
    """:func:`difference` of ``a`` (dim,) or of each row of ``a`` (q, dim) against each row
    of ``M`` (no Jacobians), vectorised: (n, dim) or (q, n, dim)."""
    if kind == "line":
        return line_differences(a, M)
    a = np.asarray(a, dtype=float)
    E = a[..., None, :] - M
    for i, ang in enumerate(KINDS[kind].angular):
        if ang:
            E[..., i] = wrap_angles(E[..., i])
    return E


def residual(
    kind: str, pose: NDArray[np.float64], lm: NDArray[np.float64], z: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Prediction - measurement, and its Jacobians w.r.t. the robot's world (x, y, theta) and
    the landmark's world parameters. A 2-vector z for a corner is a sonar (bearing, range)."""
    if kind == "line":
        return line_residual(pose, lm, z)
    if kind == "corner":
        if len(z) == 2:
            e, Hx, Hl = corner_residual(pose, lm, (z[0], z[1], 0.0))
            return e[:2], Hx[:2], Hl[:2]
        return corner_residual(pose, lm, z)
    return point_residual(pose, lm, z)


def residuals(
    kind: str, pose: NDArray[np.float64], lms: NDArray[np.float64], z: NDArray[np.float64]
) -> NDArray[np.float64]:
    """:func:`residual` without Jacobians for many landmarks at once: ``lms`` (n, dim) world
    parameters, one measurement ``z``; returns (n, len(z)). Vectorised for the association's
    pre-gate, which tries every nearby landmark against every feature of a scan."""
    return residuals_grid(kind, pose, lms, np.asarray(z, dtype=float)[None, :])[0]


def residuals_grid(
    kind: str, pose: NDArray[np.float64], lms: NDArray[np.float64], Z: NDArray[np.float64]
) -> NDArray[np.float64]:
    """:func:`residuals` of several measurements ``Z`` (m, k) of one kind and length k against
    every landmark: (m, n, k), element for element the same arithmetic."""
    if kind == "line":
        return line_residuals(pose, lms, Z)
    x, y, th = (float(v) for v in pose)
    lms = np.asarray(lms, dtype=float).reshape(-1, DIM[kind])
    Z = np.asarray(Z, dtype=float)
    dx, dy = lms[:, 0] - x, lms[:, 1] - y
    cols = [wrap_angles(np.arctan2(dy, dx) - th - Z[:, 0:1]), np.hypot(dx, dy) - Z[:, 1:2]]
    if Z.shape[1] == 3:  # a laser corner: its bisector
        cols.append(wrap_angles(lms[:, 2] - th - Z[:, 2:3]))
    return np.stack(cols, axis=-1)


def to_world(
    kind: str, pose: NDArray[np.float64], z: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Landmark world parameters from a measurement at a pose, with Jacobians w.r.t. the
    pose (world) and the measurement."""
    if kind == "line":
        return line_to_world(pose, z)
    if kind == "corner":
        return corner_to_world(pose, z)
    return point_to_world(pose, z)


def factor(
    kind: str,
    pose_key: int,
    lm_key: int,
    f: Feature,
    robust: str = "none",
    cal_key: int | None = None,
    cal_jacobian: NDArray[np.float64] | None = None,
    cal_gain: NDArray[np.float64] | None = None,
) -> gtsam.NonlinearFactor:
    """The GTSAM factor of a feature measured from pose ``pose_key`` of landmark ``lm_key``,
    its noise robust with the kernel ``robust`` (:func:`factors.noise.noise_model`); with a
    ``cal_jacobian`` (dz/dc, :class:`fgslam.slam.calibration.Calibration`) also of the
    calibration variable ``cal_key`` (``cal_gain``: its scale columns taken at the
    prediction, :func:`factors.calibrated.calibrated`)."""
    if cal_jacobian is None:
        cal_key = None
    cal = {"cal_key": cal_key, "cal_jacobian": cal_jacobian, "cal_gain": cal_gain}
    if kind == "point":
        return point_factor(pose_key, lm_key, f.z, f.cov, robust=robust, **cal)
    noise = noise_model(f.cov, robust)
    if kind == "line":
        return line_factor(pose_key, lm_key, f.z, noise, **cal)
    if len(f.z) == 2:
        return corner_bearing_range_factor(pose_key, lm_key, f.z, noise, **cal)
    return corner_factor(pose_key, lm_key, f.z, noise, **cal)


OWN_TIME_KINDS = {"point": point_residual, "line": line_residual}  # vector landmarks


def own_time_factor(
    kind: str,
    key_a: int,
    key_b: int,
    lm_key: int,
    s: float,
    own: OwnTime,
    robust: str = "none",
    cal_key: int | None = None,
    cal_jacobian: NDArray[np.float64] | None = None,
    cal_gain: NDArray[np.float64] | None = None,
) -> gtsam.NonlinearFactor:
    """The factor of a sonar point or plane measured at its own time (``own``, robot frame
    then) from the pose at fraction ``s`` between keyframe poses ``key_a`` and ``key_b``
    (:func:`factors.own_time.interpolated_factor`), robust with ``robust``; with a
    ``cal_jacobian`` (dz/dc of ``own``) also of the calibration variable ``cal_key``
    (``cal_gain``: as :func:`factor`'s)."""
    if kind not in OWN_TIME_KINDS:
        raise ValueError(f"no own-time factor for {kind!r} landmarks")
    noise = noise_model(own.cov, robust)
    if cal_jacobian is None:
        cal_key = None
    return interpolated_factor(
        OWN_TIME_KINDS[kind], key_a, key_b, lm_key, s, own.z, noise, cal_key, cal_jacobian,
        cal_gain,
    )  # fmt: skip


def value(kind: str, lm: NDArray[np.float64]) -> object:
    """The GTSAM value of a landmark's world parameters."""
    return KINDS[kind].value(lm)


def position(kind: str, lm: NDArray[np.float64]) -> NDArray[np.float64]:
    """A representative world point of a landmark (lines: the foot of the normal)."""
    if kind == "line":
        return np.array([lm[1] * math.cos(lm[0]), lm[1] * math.sin(lm[0])])
    return np.asarray(lm[:2], dtype=float)


def normalize(kind: str, lm: NDArray[np.float64]) -> NDArray[np.float64]:
    """Canonical world parameters (line d >= 0, angles wrapped)."""
    lm = np.array(lm, dtype=float)
    if kind == "line":
        lm = np.array(normalize_line(float(lm[0]), float(lm[1])))
    elif kind == "corner":
        lm[2] = wrap_angle(lm[2])
    return lm
