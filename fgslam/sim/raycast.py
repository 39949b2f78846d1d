"""Vectorised 2-D ray casting against line segments and circles (world frame, m, rad)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


def raycast(
    origin: tuple[float, float],
    angles: NDArray[np.float64],
    segments: NDArray[np.float64],
    circles: NDArray[np.float64] | None = None,
) -> NDArray[np.float64]:
    """Distance from ``origin`` along each world ``angle`` to the first segment (M, 4: x1 y1 x2
    y2) or circle (K, 3: x y radius) hit; ``inf`` where nothing is hit. An origin inside a
    circle does not see that circle."""
    ox, oy = origin
    dx, dy = np.cos(angles)[:, None], np.sin(angles)[:, None]
    best = np.full(len(angles), np.inf)
    if len(segments):
        ax, ay = segments[None, :, 0] - ox, segments[None, :, 1] - oy
        ex, ey = (
            segments[None, :, 2] - segments[None, :, 0],
            segments[None, :, 3] - segments[None, :, 1],
        )
        denom = dx * ey - dy * ex  # cross(d, e)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (ax * ey - ay * ex) / denom  # along the ray
            s = (ax * dy - ay * dx) / denom  # along the segment
        ok = (np.abs(denom) > 1e-12) & (t > 1e-9) & (s >= 0.0) & (s <= 1.0)
        best = np.minimum(best, np.where(ok, t, np.inf).min(axis=1))
    if circles is not None and len(circles):
        cx, cy, r = circles[None, :, 0] - ox, circles[None, :, 1] - oy, circles[None, :, 2]
        b = dx * cx + dy * cy
        disc = b * b - (cx * cx + cy * cy - r * r)
        outside = (cx * cx + cy * cy) > r * r
        with np.errstate(invalid="ignore"):
            t = b - np.sqrt(disc)
        ok = (disc >= 0) & (t > 1e-9) & outside
        best = np.minimum(best, np.where(ok, t, np.inf).min(axis=1))
    return best


def blocked(
    origin: tuple[float, float],
    targets: NDArray[np.float64],
    segments: NDArray[np.float64],
    circles: NDArray[np.float64] | None = None,
    margin: float = 1e-3,
) -> NDArray[np.bool_]:
    """For each target point (N, 2): is the straight path from ``origin`` interrupted before
    reaching it (by more than ``margin`` m)? Points lying on a segment are not blocked by it."""
    targets = np.asarray(targets, dtype=float).reshape(-1, 2)
    if len(targets) == 0:
        return np.zeros(0, dtype=bool)
    vx, vy = targets[:, 0] - origin[0], targets[:, 1] - origin[1]
    dist = np.hypot(vx, vy)
    hit = raycast(origin, np.arctan2(vy, vx), segments, circles)
    return hit < dist - margin
