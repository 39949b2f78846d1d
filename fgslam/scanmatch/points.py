"""Points and angles: a scan's robot-frame points (:func:`scan_points`), the cleaning and
voxel filter of point sets."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

# the one angle wrap (docs/design.md, 2), under the name fgslam.scanmatch.matcher imports


def scan_points(
    ranges: ArrayLike,
    bearings: ArrayLike,
    mount: ArrayLike = (0.0, 0.0, 0.0),
    max_range: float = math.inf,
) -> NDArray[np.float64]:
    """(N, 2) robot-frame points (m) of the finite, positive ranges below ``max_range``, in
    beam order. ``bearings`` (rad) are in the laser frame; ``mount`` is the laser's pose in
    the robot frame (x, y, yaw)."""
    r = np.asarray(ranges, dtype=float).ravel()
    b = np.asarray(bearings, dtype=float).ravel()
    n = min(r.size, b.size)
    r, b = r[:n], b[:n]
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(r) & np.isfinite(b) & (r > 0) & (r < max_range)
    r, b = r[ok], b[ok]
    mx, my, myaw = (float(v) for v in np.asarray(mount, dtype=float).ravel()[:3])
    a = b + myaw
    return np.column_stack([mx + r * np.cos(a), my + r * np.sin(a)])


def _clean(points: ArrayLike) -> NDArray[np.float64]:
    p = np.asarray(points, dtype=float)
    if p.size == 0:
        return np.zeros((0, 2))
    p = p.reshape(-1, 2) if p.ndim != 2 or p.shape[1] != 2 else p
    p = p[np.isfinite(p).all(axis=1)]
    return p[np.abs(p).max(axis=1) < 1e6] if len(p) else p


def _voxel(points: NDArray, size: float) -> NDArray:
    """One point per ``size`` cell (the first in order), order kept."""
    return points[voxel_index(points, size)]


def voxel_index(points: NDArray, size: float) -> NDArray[np.int64]:
    """The indices of one point per ``size`` (m) cell of ``points`` ((N, 2), finite): the
    first in order, ascending; every index when ``size`` <= 0."""
    if len(points) == 0 or size <= 0:
        return np.arange(len(points))
    key = np.floor(points / size).astype(np.int64)
    _, first = np.unique(key[:, 0] * 3_000_017 + key[:, 1], return_index=True)
    return np.sort(first)
