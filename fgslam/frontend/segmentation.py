"""Sonar-aided laser segmentation by line growing (paper III-A).

Each point not yet in a line starts one; the line grows point by point until one of the
paper's conditions ends it (see :class:`~fgslam.frontend.features.End`). Laser frame, m, rad.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from fgslam.config import SegmentParams
from fgslam.frontend import kernels
from fgslam.frontend.features import End


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


_ENDS = tuple(End(v) for v in kernels.END_CODES)  # the kernel's end codes
_SONAR = kernels.END_CODES.index(End.SONAR.value)


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

    Returns the accepted segments and counts of rejected ones by reason. The line growing is
    compiled (:func:`fgslam.frontend.kernels.grow_lines`); :func:`segment_scan_reference` is
    the same in plain Python, and makes the same decisions.
    """
    n = len(r)
    with np.errstate(invalid="ignore"):  # an infinite range at a zero sine: invalid anyway
        xs, ys = r * np.cos(phi), r * np.sin(phi)  # the reference's points, bit for bit
    valid = np.isfinite(r) & (r > 0) & (r <= params.max_range)
    near = sonar_near if sonar_near is not None else np.full(n, -1)
    ndist = sonar_dist if sonar_dist is not None else np.zeros(n)
    first, last, start, end, cl, too_few = kernels.grow_lines(
        xs,
        ys,
        r,
        valid,
        near,
        ndist,
        params.jump,
        params.jump_rel,
        params.outlier,
        params.spread**2,
        params.min_points,
    )
    segments = [
        Segment(a, b, _ENDS[s], _ENDS[e], c if e == _SONAR else None)
        for a, b, s, e, c in zip(
            first.tolist(), last.tolist(), start.tolist(), end.tolist(), cl.tolist(), strict=True
        )
    ]
    return segments, {"too_few_points": too_few}


def segment_scan_reference(
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

    Returns the accepted segments and counts of rejected ones by reason. The reference of
    :func:`segment_scan` (and of the compiled :func:`fgslam.frontend.kernels.grow_lines`).
    """
    n = len(r)
    # plain Python floats: the growing loop is scalar work, and numpy scalars are slow
    with np.errstate(invalid="ignore"):  # an infinite range at a zero sine: invalid anyway
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
        # running sums of the total-least-squares line through the points so far
        cnt, sx, sy = 1, xs[i], ys[i]
        sxx, syy, sxy = sx * sx, sy * sy, sx * sy
        have_line = False  # a line (lc, ls, ld) through 3 or more points exists
        lc = ls = ld = 0.0
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
                # the point nearest to the cluster among the run of points near it (not the
                # first local minimum: range noise and quantisation make the distances bumpy)
                stop_at = k = j
                while k + 1 < n and near[k + 1] == near[j]:
                    k += 1
                    if ndist[k] < ndist[stop_at]:
                        stop_at = k
                if stop_at == j:
                    end, cl = End.SONAR, near[j]
                    break
            x, y = xs[j], ys[j]
            if (
                have_line
                and j + 3 <= n
                and valid[j]
                and abs(x * lc + y * ls - ld) > outlier
                and valid[j + 1]
                and abs(xs[j + 1] * lc + ys[j + 1] * ls - ld) > outlier
                and valid[j + 2]
                and abs(xs[j + 2] * lc + ys[j + 2] * ls - ld) > outlier
            ):
                end = End.OUTLIERS
                break
            cnt += 1
            sx += x
            sy += y
            sxx += x * x
            syy += y * y
            sxy += x * y
            if cnt >= 3:
                mx, my = sx / cnt, sy / cnt
                cxx = sxx / cnt - mx * mx
                cyy = syy / cnt - my * my
                cxy = sxy / cnt - mx * my
                # smallest eigenvalue of the covariance: the mean squared perpendicular distance
                tr, det = cxx + cyy, cxx * cyy - cxy * cxy
                var = max(0.5 * tr - math.sqrt(max(0.25 * tr * tr - det, 0.0)), 0.0)
                if var > spread2:
                    end = End.SPREAD
                    break
                alpha = 0.5 * math.atan2(-2 * cxy, cyy - cxx)
                lc, ls = math.cos(alpha), math.sin(alpha)
                ld = mx * lc + my * ls
                have_line = True
            j += 1
        seg = Segment(i, j - 1, prev_end, end, cl)
        if seg.n > params.min_points:
            segments.append(seg)
        else:
            rejected["too_few_points"] += 1
        prev_end = end
        i = j + 1 if end is End.SONAR else (j if end is not End.FIELD_OF_VIEW else n)
    return segments, rejected
