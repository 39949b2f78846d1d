"""Segment geometry of the map (docs/design.md, 5): line segment ends and corner arms, kept in WORLD
coordinates (m), outside the estimator's state.

A line's (alpha, d) may be stored in either parametrisation ((alpha, d) or (alpha + pi, -d),
by :func:`factors.line.flips`); a position *along* the line measured from its foot point
changes sign with the parametrisation. Ends are therefore never stored as such positions:
they are world points, projected onto the current line estimate when a rule needs positions
along it, and put back as world points. No parametrisation flip can mirror them.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from fgslam.frontend.features import End, Feature


def line_frame(lm: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Foot point of a world line (alpha, d) and its unit direction (-sin a, cos a)."""
    a, d = float(lm[0]), float(lm[1])
    n = np.array([math.cos(a), math.sin(a)])
    return d * n, np.array([-n[1], n[0]])


def along(lm: NDArray[np.float64], pts: NDArray[np.float64]) -> NDArray[np.float64]:
    """Positions (m) of world points along the line ``lm`` from its foot point."""
    foot, u = line_frame(lm)
    return (np.asarray(pts, dtype=float).reshape(-1, 2) - foot) @ u


def on_line(lm: NDArray[np.float64], s: NDArray[np.float64]) -> NDArray[np.float64]:
    """World points of positions ``s`` along the line ``lm``: (n, 2)."""
    foot, u = line_frame(lm)
    return foot + np.asarray(s, dtype=float).reshape(-1, 1) * u


def to_world(pose: NDArray[np.float64], pts: NDArray[np.float64]) -> NDArray[np.float64]:
    """Robot-frame points (n, 2) to the world frame, robot at ``pose`` (x, y, theta)."""
    pts = np.asarray(pts, dtype=float).reshape(-1, 2)
    c, s = math.cos(pose[2]), math.sin(pose[2])
    out = np.empty_like(pts)
    out[:, 0] = pose[0] + c * pts[:, 0] - s * pts[:, 1]
    out[:, 1] = pose[1] + s * pts[:, 0] + c * pts[:, 1]
    return out


def foot_point(pose: NDArray[np.float64], z: NDArray[np.float64]) -> NDArray[np.float64]:
    """World foot point of a robot-frame line measurement (alpha, d) (a sonar plane)."""
    return to_world(pose, np.array([[z[1] * math.cos(z[0]), z[1] * math.sin(z[0])]]))[0]


def measured_ends(f: Feature, pose: NDArray[np.float64]) -> NDArray[np.float64]:
    """World ends of a line feature (2, 2); a sonar plane (no endpoints) gives its foot
    point twice."""
    if f.endpoints is None:
        p = foot_point(pose, f.z)
        return np.array([p, p])
    (x0, y0), (x1, y1) = f.endpoints  # to_world of two points, in scalars
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return np.array(
        [
            [pose[0] + c * x0 - s * y0, pose[1] + s * x0 + c * y0],
            [pose[0] + c * x1 - s * y1, pose[1] + s * x1 + c * y1],
        ]
    )


def overlap(
    lm: NDArray[np.float64], ends: NDArray[np.float64] | None, meas: NDArray[np.float64]
) -> float:
    """Overlap (m) along the line ``lm`` of the map segment ``ends`` and a measured segment
    ``meas`` (world ends); negative: the gap between them. A map line without ends: 0."""
    if ends is None:
        return 0.0
    fr = _frame(lm)  # in scalars: called for every line pairing the association tries
    a0, a1 = _along2(fr, ends)
    b0, b1 = _along2(fr, meas)
    return min(max(a0, a1), max(b0, b1)) - max(min(a0, a1), min(b0, b1))


# Scalar forms of line_frame / along / on_line for the two ends of a segment (the per-keyframe
# geometry updates call them thousands of times; numpy's per-call cost dominates there).
_Frame = tuple[float, float, float, float]


def _frame(lm: NDArray[np.float64]) -> _Frame:
    """(foot x, foot y, direction x, direction y) of a world line (alpha, d)."""
    a, d = float(lm[0]), float(lm[1])
    c, s = math.cos(a), math.sin(a)
    return d * c, d * s, -s, c


def _along2(fr: _Frame, pts: NDArray[np.float64]) -> tuple[float, float]:
    """:func:`along` of two points."""
    fx, fy, ux, uy = fr
    return (
        (float(pts[0][0]) - fx) * ux + (float(pts[0][1]) - fy) * uy,
        (float(pts[1][0]) - fx) * ux + (float(pts[1][1]) - fy) * uy,
    )


def _on_line2(fr: _Frame, s0: float, s1: float) -> NDArray[np.float64]:
    """:func:`on_line` of two positions."""
    fx, fy, ux, uy = fr
    return np.array([[fx + s0 * ux, fy + s0 * uy], [fx + s1 * ux, fy + s1 * uy]])


def union(
    lm: NDArray[np.float64], a: NDArray[np.float64] | None, b: NDArray[np.float64] | None
) -> NDArray[np.float64] | None:
    """The segment of ``lm`` spanning both world segments (ends projected onto ``lm``)."""
    pts = [p for p in (a, b) if p is not None]
    if not pts:
        return None
    s = along(lm, np.vstack(pts))
    return on_line(lm, np.array([s.min(), s.max()]))


def reproject(lm: NDArray[np.float64], ends: NDArray[np.float64]) -> NDArray[np.float64]:
    """World ends (2, 2) moved onto the current line estimate (orthogonal projection)."""
    fr = _frame(lm)
    return _on_line2(fr, *_along2(fr, ends))


def update_line_ends(
    ends: NDArray[np.float64] | None,
    lm: NDArray[np.float64],
    f: Feature,
    pose: NDArray[np.float64],
    big_step: float,
    small_step: float,
) -> NDArray[np.float64]:
    """Paper IV's endpoint rules for a line measurement of the map line ``lm`` (world, current
    estimate): a measured end beyond the map's extends it; inside, the map end moves
    ``big_step`` toward a reliable measured end (sonar, discontinuity), ``small_step`` toward
    a weak one, not at all toward an end that carries no information (field of view). A sonar
    plane (its foot point only) can only extend the segment. Returns the world ends (2, 2)."""
    meas = measured_ends(f, pose)
    fr = _frame(lm)
    s = _along2(fr, meas)
    if f.endpoints is None:
        if ends is None:
            return _on_line2(fr, *s)
        e = _along2(fr, ends)
        return _on_line2(fr, min(min(e), min(s)), max(max(e), max(s)))
    conds = [f.start, f.end]
    i0, i1 = (0, 1) if s[0] <= s[1] else (1, 0)
    (s0, c0), (s1, c1) = (s[i0], conds[i0]), (s[i1], conds[i1])
    if ends is None:
        return _on_line2(fr, s0, s1)
    e0, e1 = sorted(_along2(fr, ends))
    return _on_line2(
        fr,
        _move(e0, s0, c0, True, big_step, small_step),
        _move(e1, s1, c1, False, big_step, small_step),
    )


def _move(
    map_end: float, meas_end: float, cond: End | None, low: bool, big: float, small: float
) -> float:
    beyond = meas_end < map_end if low else meas_end > map_end
    if beyond:
        return meas_end  # the wall is at least this long
    if cond is None or cond is End.FIELD_OF_VIEW:
        return map_end  # the measured end carries no information
    step = big if cond.reliable else small
    return map_end + step * (meas_end - map_end)


def segment_distance(p: NDArray[np.float64], ends: NDArray[np.float64]) -> NDArray[np.float64]:
    """Distances of the point ``p`` (2,) to segments ``ends`` (n, 4): rows (ax, ay, bx, by)."""
    A, ab = ends[:, :2], ends[:, 2:] - ends[:, :2]
    t = np.clip(np.sum((p - A) * ab, axis=1) / np.maximum(np.sum(ab * ab, axis=1), 1e-12), 0, 1)
    return np.hypot(*(p - A - t[:, None] * ab).T)
