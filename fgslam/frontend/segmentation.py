"""Sonar-aided laser segmentation by line growing (paper III-A).

Each point not yet in a line starts one; the line grows point by point until one of the
paper's conditions ends it (see :class:`~fgslam.frontend.features.End`). Laser frame, m, rad.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from fgslam.frontend.features import End


@dataclass(frozen=True)
class SegmentParams:
    """Thresholds of the line growing (m unless stated)."""

    min_points: int = 8  # a line needs more points than this to be kept
    max_range: float = 8.0  # points farther than this end lines (and start none)
    jump: float = 0.3  # range discontinuity: |r_i - r_{i-1}| > jump + jump_rel * r
    jump_rel: float = 0.05
    spread: float = 0.025  # std of point-to-line distances
    outlier: float = 0.07  # range-model threshold for the next-3-points test
    sonar_radius: float = 0.2  # a corner/edge cluster this close to a point ends the line


@dataclass
class Segment:
    """Points first..last (inclusive, scan indices) and why the segment started and ended."""

    first: int
    last: int
    start: End
    end: End
    end_cluster: int | None = None  # index of the sonar cluster that ended it

    @property
    def n(self) -> int:
        return self.last - self.first + 1


class _Tls:
    """Running sums for the total-least-squares line through a growing set of points."""

    def __init__(self) -> None:
        self.n = 0
        self.sx = self.sy = self.sxx = self.syy = self.sxy = 0.0

    def add(self, x: float, y: float) -> None:
        self.n += 1
        self.sx += x
        self.sy += y
        self.sxx += x * x
        self.syy += y * y
        self.sxy += x * y

    def line(self) -> tuple[float, float, float]:
        """(alpha, d, variance of the perpendicular distances)."""
        n = self.n
        mx, my = self.sx / n, self.sy / n
        cxx = self.sxx / n - mx * mx
        cyy = self.syy / n - my * my
        cxy = self.sxy / n - mx * my
        alpha = 0.5 * math.atan2(-2 * cxy, cyy - cxx)
        # smallest eigenvalue of the covariance: the mean squared perpendicular distance
        tr, det = cxx + cyy, cxx * cyy - cxy * cxy
        var = max(0.5 * tr - math.sqrt(max(0.25 * tr * tr - det, 0.0)), 0.0)
        return alpha, mx * math.cos(alpha) + my * math.sin(alpha), var


def segment_scan(
    phi: NDArray[np.float64],
    r: NDArray[np.float64],
    params: SegmentParams,
    sonar_near: NDArray[np.int64] | None = None,
    sonar_dist: NDArray[np.float64] | None = None,
) -> tuple[list[Segment], dict[str, int]]:
    """Grow lines along a scan. ``sonar_near[i]`` is the index of a visible sonar cluster with
    corners or edges within ``sonar_radius`` of point i, or -1 (None: laser only), and
    ``sonar_dist[i]`` the distance to it. A line reaching such a cluster ends just before the
    point nearest to the cluster (the jamb or corner itself), and the next line starts after it.

    Returns the accepted segments and counts of rejected ones by reason.
    """
    n = len(r)
    # plain Python floats: the growing loop is scalar work, and numpy scalars are slow
    xs, ys = (r * np.cos(phi)).tolist(), (r * np.sin(phi)).tolist()
    rs = r.tolist()
    valid = (np.isfinite(r) & (r > 0) & (r <= params.max_range)).tolist()
    near = (sonar_near if sonar_near is not None else np.full(n, -1)).tolist()
    ndist = (sonar_dist if sonar_dist is not None else np.zeros(n)).tolist()
    jump, jump_rel, outlier = params.jump, params.jump_rel, params.outlier
    spread2 = params.spread**2
    segments: list[Segment] = []
    rejected = {"too_few_points": 0}
    prev_end = End.FIELD_OF_VIEW
    i = 0
    while i < n:
        if not valid[i]:
            prev_end = End.MAX_RANGE
            i += 1
            continue
        tls = _Tls()
        tls.add(xs[i], ys[i])
        line = None  # (cos, sin, d) of the line through the points so far (3 or more)
        j = i + 1
        end, cl = End.FIELD_OF_VIEW, None
        stop_at = -1  # index of the point nearest to the sonar cluster ahead
        while j < n:
            if j == stop_at:
                end, cl = End.SONAR, near[j]
                break
            if not valid[j]:
                end = End.MAX_RANGE
                break
            if abs(rs[j] - rs[j - 1]) > jump + jump_rel * rs[j - 1]:
                end = End.DISCONTINUITY
                break
            if stop_at < 0 and near[j] >= 0 and near[j] != near[i]:
                stop_at = j
                while (
                    stop_at + 1 < n
                    and near[stop_at + 1] == near[j]
                    and (ndist[stop_at + 1] < ndist[stop_at])
                ):
                    stop_at += 1
                if stop_at == j:
                    end, cl = End.SONAR, near[j]
                    break
            if line is not None and j + 3 <= n:
                c, s_, d = line
                if all(
                    valid[k] and abs(xs[k] * c + ys[k] * s_ - d) > outlier
                    for k in (j, j + 1, j + 2)
                ):
                    end = End.OUTLIERS
                    break
            tls.add(xs[j], ys[j])
            if tls.n >= 3:
                alpha, d, var = tls.line()
                if var > spread2:
                    end = End.SPREAD
                    break
                line = (math.cos(alpha), math.sin(alpha), d)
            j += 1
        seg = Segment(i, j - 1, prev_end, end, cl)
        if seg.n > params.min_points:
            segments.append(seg)
        else:
            rejected["too_few_points"] += 1
        prev_end = end
        i = j + 1 if end is End.SONAR else (j if end is not End.FIELD_OF_VIEW else n)
    return segments, rejected
