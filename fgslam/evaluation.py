"""Trajectory evaluation: SE(2) alignment, absolute trajectory error, NEES, TUM files.

Poses are (x, y, theta) in m and rad; times in s.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.stats import chi2

from factors.geometry import wrap_angles


def interpolate_poses(t_ref: ArrayLike, poses: ArrayLike, t: ArrayLike) -> NDArray[np.float64]:
    """Poses at times t, linearly interpolated (heading unwrapped), clamped at the ends."""
    t_ref = np.asarray(t_ref, dtype=float)
    poses = np.asarray(poses, dtype=float)
    t = np.asarray(t, dtype=float)
    th = np.unwrap(poses[:, 2])
    out = np.column_stack(
        [
            np.interp(t, t_ref, poses[:, 0]),
            np.interp(t, t_ref, poses[:, 1]),
            np.interp(t, t_ref, th),
        ]
    )
    out[:, 2] = wrap_angles(out[:, 2])
    return out


def align_se2(est: ArrayLike, ref: ArrayLike) -> tuple[float, NDArray[np.float64]]:
    """The rotation angle and translation that best map estimated positions onto reference
    positions in the least-squares sense (Umeyama/Horn in 2-D, no scale)."""
    P = np.asarray(est, dtype=float)[:, :2]
    Q = np.asarray(ref, dtype=float)[:, :2]
    mp, mq = P.mean(axis=0), Q.mean(axis=0)
    A, B = P - mp, Q - mq
    angle = math.atan2(float(np.sum(A[:, 0] * B[:, 1] - A[:, 1] * B[:, 0])), float(np.sum(A * B)))
    c, s = math.cos(angle), math.sin(angle)
    t = mq - np.array([c * mp[0] - s * mp[1], s * mp[0] + c * mp[1]])
    return angle, t


def apply_se2(angle: float, t: ArrayLike, poses: ArrayLike) -> NDArray[np.float64]:
    poses = np.asarray(poses, dtype=float)
    c, s = math.cos(angle), math.sin(angle)
    out = poses.copy()
    out[:, 0] = c * poses[:, 0] - s * poses[:, 1] + t[0]
    out[:, 1] = s * poses[:, 0] + c * poses[:, 1] + t[1]
    out[:, 2] = wrap_angles(poses[:, 2] + angle)
    return out


def ate(est: ArrayLike, ref: ArrayLike, align: bool = True) -> dict[str, float]:
    """Absolute trajectory error of positions (m), after SE(2) alignment by default."""
    est = np.asarray(est, dtype=float)
    ref = np.asarray(ref, dtype=float)
    if align:
        est = apply_se2(*align_se2(est, ref), est)
    err = np.hypot(est[:, 0] - ref[:, 0], est[:, 1] - ref[:, 1])
    return {
        "rmse": float(np.sqrt(np.mean(err**2))),
        "mean": float(err.mean()),
        "max": float(err.max()),
        "heading_rmse_deg": float(
            np.degrees(np.sqrt(np.mean(wrap_angles(est[:, 2] - ref[:, 2]) ** 2)))
        ),
    }


def position_errors(est: ArrayLike, ref: ArrayLike, align: bool = True) -> NDArray[np.float64]:
    est = np.asarray(est, dtype=float)
    ref = np.asarray(ref, dtype=float)
    if align:
        est = apply_se2(*align_se2(est, ref), est)
    return np.hypot(est[:, 0] - ref[:, 0], est[:, 1] - ref[:, 1])


def nees(est: ArrayLike, cov: ArrayLike, ref: ArrayLike) -> dict[str, float]:
    """Pose NEES e^T P^-1 e (e = estimate - reference, heading wrapped; 3 dof): its mean and
    the fraction of poses inside the two-sided 95 % chi-square interval."""
    est, cov, ref = (np.asarray(a, dtype=float) for a in (est, cov, ref))
    e = est - ref
    e[:, 2] = wrap_angles(e[:, 2])
    vals = np.einsum("ni,ni->n", e, np.linalg.solve(cov, e[..., None])[..., 0])
    lo, hi = chi2.ppf([0.025, 0.975], 3)
    return {
        "mean": float(vals.mean()),
        "median": float(np.median(vals)),
        "within_95": float(np.mean((vals >= lo) & (vals <= hi))),
        "dof": 3,
    }


def write_tum(path: str | Path, t: ArrayLike, poses: ArrayLike) -> None:
    """TUM trajectory: ``timestamp x y z qx qy qz qw`` with z = 0 and a yaw quaternion."""
    t = np.asarray(t, dtype=float)
    poses = np.asarray(poses, dtype=float)
    with open(path, "w", encoding="utf-8") as fh:
        for ti, (x, y, th) in zip(t, poses, strict=True):
            fh.write(
                f"{ti:.6f} {x:.6f} {y:.6f} 0.000000 0.000000 0.000000 "
                f"{math.sin(th / 2):.9f} {math.cos(th / 2):.9f}\n"
            )


def read_tum(path: str | Path) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Times and (x, y, yaw) of a TUM trajectory (yaw from the quaternion)."""
    data = np.loadtxt(path, comments="#", ndmin=2)
    if data.shape[1] != 8:
        raise ValueError(f"{path}: expected 8 columns (timestamp x y z qx qy qz qw)")
    qx, qy, qz, qw = data[:, 4], data[:, 5], data[:, 6], data[:, 7]
    yaw = np.arctan2(2 * (qw * qz + qx * qy), 1 - 2 * (qy**2 + qz**2))
    return data[:, 0], np.column_stack([data[:, 1], data[:, 2], yaw])
