"""The measurement models of the three landmark kinds, seen from SLAM: one place that maps a
feature kind to the shared prediction/residual/initialisation functions of ``factors`` and to
its GTSAM factor. Features are in the robot frame, so the sensor mount is the identity.

World parametrisations (what the EKF stores and the map reports): line (alpha, d); corner
(x, y, theta) with theta the bisector into free space; point (x, y). Angles rad, lengths m.
"""

from __future__ import annotations

import math

import gtsam
import numpy as np
from numpy.typing import NDArray

from factors.corner import (
    corner_bearing_range_factor,
    corner_factor,
    corner_residual,
    corner_to_world,
)
from factors.geometry import wrap_angle
from factors.line import flips, line_factor, line_residual, line_to_world, normalize_line
from factors.point import point_factor, point_residual, point_to_world
from fgslam.frontend.features import Feature

DIM = {"line": 2, "corner": 3, "point": 2}
ANGULAR = {"line": (True, False), "corner": (False, False, True), "point": (False, False)}


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
    x, y, th = (float(v) for v in pose)
    lms = np.asarray(lms, dtype=float).reshape(-1, DIM[kind])
    Z = np.asarray(Z, dtype=float)
    z0, z1 = Z[:, 0:1], Z[:, 1:2]
    if kind == "line":
        aw, dw = lms[:, 0], lms[:, 1]
        e0 = np.remainder(aw - th - z0 + math.pi, 2 * math.pi) - math.pi
        flip = flips(e0)  # the (alpha + pi, -d) form of the prediction
        e0 = np.where(flip, np.remainder(e0 + 2 * math.pi, 2 * math.pi) - math.pi, e0)
        d = dw - x * np.cos(aw) - y * np.sin(aw)
        return np.stack([e0, np.where(flip, -d, d) - z1], axis=-1)
    dx, dy = lms[:, 0] - x, lms[:, 1] - y
    cols = [
        np.remainder(np.arctan2(dy, dx) - th - z0 + math.pi, 2 * math.pi) - math.pi,
        np.hypot(dx, dy) - z1,
    ]
    if Z.shape[1] == 3:  # a laser corner: its bisector
        cols.append(np.remainder(lms[:, 2] - th - Z[:, 2:3] + math.pi, 2 * math.pi) - math.pi)
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


ROBUST_KERNELS = ("none", "huber", "cauchy", "dcs")


def m_estimator(kernel: str, dim: int) -> gtsam.noiseModel.mEstimator.Base | None:
    """The M-estimator of a robust noise model for ``dim``-dimensional residuals (None for
    "none"). GTSAM weighs by the norm of the whitened residual, which is chi-distributed
    with ``dim`` dof for a correct association: the threshold k is its 95 % quantile,
    sqrt(chi2_95(dim)), so correct sightings keep (nearly) full weight."""
    if kernel == "none":
        return None
    k = math.sqrt(CHI2_95[dim])
    if kernel == "huber":
        return gtsam.noiseModel.mEstimator.Huber.Create(k)
    if kernel == "cauchy":
        return gtsam.noiseModel.mEstimator.Cauchy.Create(k)
    if kernel == "dcs":
        return gtsam.noiseModel.mEstimator.DCS.Create(k * k)
    raise ValueError(f"unknown robust kernel {kernel!r}; expected one of {ROBUST_KERNELS}")


CHI2_95 = {1: 3.841, 2: 5.991, 3: 7.815}


def noise_model(cov: NDArray[np.float64], kernel: str = "none") -> gtsam.noiseModel.Base:
    """Gaussian noise of covariance ``cov``, robust with ``kernel`` (see :func:`m_estimator`)."""
    noise = gtsam.noiseModel.Gaussian.Covariance(np.asarray(cov, dtype=float))
    est = m_estimator(kernel, len(cov))
    return noise if est is None else gtsam.noiseModel.Robust.Create(est, noise)


def factor(
    kind: str, pose_key: int, lm_key: int, f: Feature, robust: str = "none"
) -> gtsam.NonlinearFactor:
    """The GTSAM factor of a feature measured from pose ``pose_key`` of landmark ``lm_key``,
    its noise robust with the kernel ``robust`` (:func:`m_estimator`)."""
    if kind == "point":
        return point_factor(pose_key, lm_key, f.z, f.cov, robust=m_estimator(robust, 2))
    noise = noise_model(f.cov, robust)
    if kind == "line":
        return line_factor(pose_key, lm_key, f.z, noise)
    if len(f.z) == 2:
        return corner_bearing_range_factor(pose_key, lm_key, f.z, noise)
    return corner_factor(pose_key, lm_key, f.z, noise)


def value(kind: str, lm: NDArray[np.float64]) -> object:
    """The GTSAM value of a landmark's world parameters."""
    if kind == "corner":
        return gtsam.Pose2(float(lm[0]), float(lm[1]), float(lm[2]))
    return np.asarray(lm, dtype=float)


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
