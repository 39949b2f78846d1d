"""Compiled inner loops of the laser front end (numba, cached on disk), each with the numpy or
plain-Python reference it must equal (tests/test_frontend_kernels.py checks them on random
inputs).

:func:`grow_lines`: the line growing of :func:`fgslam.frontend.segmentation.segment_scan`
(its reference: ``segment_scan_reference``, a scalar loop over Python floats). Given the
scan's Cartesian points (computed by numpy before the call, as the reference does), its
ranges, the valid beams and the sonar hints, it returns every segment's first and last
index, start and end condition (codes of :data:`END_CODES`) and the sonar cluster that ended
it, plus how many were too short. The same scalar operations in the same order (IEEE double,
no fast-math; ``math.sqrt``, ``math.atan2``, ``math.cos``, ``math.sin`` are the C library's
in both), and ``max`` written out with Python's NaN behaviour: the same segments, decision
for decision, not just close ones.

:func:`ok_sums`: the centred moments (mean x, mean y, sum dx^2, sum dy^2, sum dx dy) of the
points ``r (cos phi, sin phi)`` of the beams ``ok``, from which
:func:`fgslam.frontend.fits.tls_line` (the reference) takes the total-least-squares line.
Sequential sums instead of numpy's pairwise ones: equal to rounding.

:func:`line_fit`: the Gauss-Newton iterations and covariances of
:func:`fgslam.frontend.fits._fit_line_once` (the reference: ``_fit_line_once_numpy``, with
``np.linalg.lstsq``, ``inv`` and ``cond``): each step solves the 2-column least-squares
problem by Givens rotations (a QR factorisation, as well conditioned as the reference's
SVD), then the sum of squared range residuals, ``(H^T H)^-1`` (2x2, by its adjugate) with its
condition number, ``(H^T H)^-1 H^T e`` for each systematic and each source column. Equal to
the reference to rounding (1e-9 relative on the tests' random lines), with the same
iterations and the same rejections; a case the kernel does not take (a non-finite or
rank-deficient step) is handed back to the reference.

:func:`trim_bounds`: the end trimming of :func:`fgslam.frontend.fits.fit_line`: the
perpendicular residuals of the kept beams to the fitted line, their robust spread
(1.4826 MAD) and the first and last beam within the bound. The same operations as numpy's
elementwise ones and exact medians: the same beams kept.
"""

from __future__ import annotations

import math

import numba
import numpy as np

# End conditions of grow_lines, in the order of fgslam.frontend.features.End's members
END_CODES = ("discontinuity", "spread", "outliers", "max_range", "field_of_view", "sonar")
_DISCONTINUITY, _SPREAD, _OUTLIERS, _MAX_RANGE, _FIELD_OF_VIEW, _SONAR = range(6)


@numba.njit(cache=True, nogil=True)
def _pymax(a, b):  # pragma: no cover - compiled
    """Python's ``max(a, b)`` for floats, NaN included (the first unless the second is
    greater)."""
    return b if b > a else a


@numba.njit(cache=True, nogil=True)
def _grow_lines(
    xs, ys, rs, valid, near, ndist, jump, jump_rel, outlier, spread2, min_points
):  # pragma: no cover - compiled
    n = rs.shape[0]
    first = np.empty(n, dtype=np.int64)
    last = np.empty(n, dtype=np.int64)
    start = np.empty(n, dtype=np.int64)
    ends = np.empty(n, dtype=np.int64)
    clus = np.empty(n, dtype=np.int64)
    m = 0
    too_few = 0
    prev_end = _FIELD_OF_VIEW
    i = 0
    while i < n:
        if not valid[i]:
            prev_end = _MAX_RANGE
            i += 1
            continue
        cnt = 1
        sx, sy = xs[i], ys[i]
        sxx, syy, sxy = sx * sx, sy * sy, sx * sy
        have_line = False
        lc = ls = ld = 0.0
        j = i + 1
        end, cl = _FIELD_OF_VIEW, -1
        stop_at = -1
        while j < n:
            if j == stop_at:
                end, cl = _SONAR, near[j]
                break
            if not valid[j]:
                end = _MAX_RANGE
                break
            if abs(rs[j] - rs[j - 1]) > jump + jump_rel * rs[j - 1]:
                end = _DISCONTINUITY
                break
            if stop_at < 0 and near[j] >= 0 and near[j] != near[i]:
                stop_at = k = j
                while k + 1 < n and near[k + 1] == near[j]:
                    k += 1
                    if ndist[k] < ndist[stop_at]:
                        stop_at = k
                if stop_at == j:
                    end, cl = _SONAR, near[j]
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
                end = _OUTLIERS
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
                tr, det = cxx + cyy, cxx * cyy - cxy * cxy
                var = _pymax(0.5 * tr - math.sqrt(_pymax(0.25 * tr * tr - det, 0.0)), 0.0)
                if var > spread2:
                    end = _SPREAD
                    break
                alpha = 0.5 * math.atan2(-2 * cxy, cyy - cxx)
                lc, ls = math.cos(alpha), math.sin(alpha)
                ld = mx * lc + my * ls
                have_line = True
            j += 1
        if j - i > min_points:  # the segment's points i..j-1
            first[m], last[m], start[m], ends[m], clus[m] = i, j - 1, prev_end, end, cl
            m += 1
        else:
            too_few += 1
        prev_end = end
        if end == _SONAR:
            i = j + 1
        elif end != _FIELD_OF_VIEW:
            i = j
        else:
            i = n
    return first[:m], last[:m], start[:m], ends[:m], clus[:m], too_few


def grow_lines(xs, ys, rs, valid, near, ndist, jump, jump_rel, outlier, spread2, min_points):
    """The segments of ``segment_scan_reference``'s line growing: arrays of each accepted
    segment's first and last point, start and end code (:data:`END_CODES`) and ending sonar
    cluster (-1: none), and the count of segments with ``min_points`` points or fewer.
    ``xs``, ``ys``, ``rs`` float64, ``valid`` bool, ``near`` int64, ``ndist`` float64, all of
    the scan's length."""
    return _grow_lines(
        np.ascontiguousarray(xs, dtype=np.float64),
        np.ascontiguousarray(ys, dtype=np.float64),
        np.ascontiguousarray(rs, dtype=np.float64),
        np.ascontiguousarray(valid, dtype=np.bool_),
        np.ascontiguousarray(near, dtype=np.int64),
        np.ascontiguousarray(ndist, dtype=np.float64),
        float(jump),
        float(jump_rel),
        float(outlier),
        float(spread2),
        int(min_points),
    )


@numba.njit(cache=True, nogil=True)
def ok_sums(phi, r, ok):  # pragma: no cover - compiled
    """(mean x, mean y, sum (x - mx)^2, sum (y - my)^2, sum (x - mx)(y - my)) of the points
    ``r (cos phi, sin phi)`` of the beams ``ok`` (at least one); float64 arrays and a bool
    mask of one length."""
    n = 0
    sx = sy = 0.0
    for i in range(phi.shape[0]):
        if ok[i]:
            sx += r[i] * math.cos(phi[i])
            sy += r[i] * math.sin(phi[i])
            n += 1
    mx, my = sx / n, sy / n
    sxx = syy = sxy = 0.0
    for i in range(phi.shape[0]):
        if ok[i]:
            dx = r[i] * math.cos(phi[i]) - mx
            dy = r[i] * math.sin(phi[i]) - my
            sxx += dx * dx
            syy += dy * dy
            sxy += dx * dy
    return mx, my, sxx, syy, sxy


# line_fit's outcomes: converged, a grazing beam, no convergence, a step the kernel does not
# take (the caller runs the reference)
FIT_OK, FIT_GRAZING, FIT_NO_CONVERGENCE, FIT_FALLBACK = 0, 1, 2, 3


@numba.njit(cache=True, nogil=True)
def _lsq2(h0, h1, y):  # pragma: no cover - compiled
    """Least squares ``min |[h0 h1] x - y|`` by Givens rotations: x, or NaNs when the
    columns are (numerically) dependent."""
    r00 = r01 = r11 = 0.0
    b0 = b1 = 0.0
    for k in range(h0.shape[0]):
        a0, a1, yk = h0[k], h1[k], y[k]
        # rotate the row into R's first row
        if a0 != 0.0:
            rho = math.hypot(r00, a0)
            c, s = r00 / rho, a0 / rho
            r00 = rho
            r01, a1 = c * r01 + s * a1, -s * r01 + c * a1
            b0, yk = c * b0 + s * yk, -s * b0 + c * yk
        # then its remainder into the second
        if a1 != 0.0:
            rho = math.hypot(r11, a1)
            c, s = r11 / rho, a1 / rho
            r11 = rho
            b1 = c * b1 + s * yk
    if r00 == 0.0 or abs(r11) <= 1e-14 * abs(r00):
        return math.nan, math.nan
    x1 = b1 / r11
    return (b0 - r01 * x1) / r00, x1


@numba.njit(cache=True, nogil=True)
def _line_fit(phi, r, ok, alpha, d, max_iter, S_all, E_all):  # pragma: no cover - compiled
    n = 0
    for i in range(ok.shape[0]):
        if ok[i]:
            n += 1
    p = np.empty(n)
    rr = np.empty(n)
    S = np.empty((S_all.shape[0], n))
    E = np.empty((E_all.shape[0], n))
    k = 0
    for i in range(ok.shape[0]):
        if ok[i]:
            p[k], rr[k] = phi[i], r[i]
            S[:, k] = S_all[:, i]
            E[:, k] = E_all[:, i]
            k += 1
    h0 = np.empty(n)
    h1 = np.empty(n)
    y = np.empty(n)
    it = 0
    converged = False
    for it in range(1, max_iter + 1):
        for k in range(n):
            c = math.cos(alpha - p[k])
            if c <= 0.02:
                return (
                    FIT_GRAZING,
                    alpha,
                    d,
                    it,
                    n,
                    0.0,
                    np.zeros((2, 2)),
                    0.0,
                    np.zeros(2),
                    np.zeros((2, 0)),
                )
            h0[k] = d * math.sin(alpha - p[k]) / (c * c)
            h1[k] = 1.0 / c
            y[k] = rr[k] - d / c
        s0, s1 = _lsq2(h0, h1, y)
        if not (math.isfinite(s0) and math.isfinite(s1)):
            return (
                FIT_FALLBACK,
                alpha,
                d,
                it,
                n,
                0.0,
                np.zeros((2, 2)),
                0.0,
                np.zeros(2),
                np.zeros((2, 0)),
            )
        alpha, d = alpha + s0, d + s1
        if abs(s0) < 1e-8 and abs(s1) < 1e-7:
            converged = True
            break
    if not converged:
        return (
            FIT_NO_CONVERGENCE,
            alpha,
            d,
            it,
            n,
            0.0,
            np.zeros((2, 2)),
            0.0,
            np.zeros(2),
            np.zeros((2, 0)),
        )
    # the Jacobian and residuals at the solution, H^T H and the squared residuals
    a00 = a01 = a11 = ssq = 0.0
    for k in range(n):
        c = math.cos(alpha - p[k])
        h0[k] = d * math.sin(alpha - p[k]) / (c * c)
        h1[k] = 1.0 / c
        e = rr[k] - d / c
        ssq += e * e
        a00 += h0[k] * h0[k]
        a01 += h0[k] * h1[k]
        a11 += h1[k] * h1[k]
    inv = np.empty((2, 2))
    det = a00 * a11 - a01 * a01
    inv[0, 0], inv[0, 1], inv[1, 0], inv[1, 1] = a11 / det, -a01 / det, -a01 / det, a00 / det
    # the 2-norm condition number of the symmetric H^T H: its eigenvalues' ratio
    half = 0.5 * (a00 + a11)
    root = math.hypot(0.5 * (a00 - a11), a01)
    lmax = half + root
    lmin = det / lmax if lmax > 0.0 else 0.0
    cond = lmax / lmin if lmin > 0.0 else math.inf
    sys_sum = np.zeros(2)
    for s in range(S.shape[0]):
        g0 = g1 = 0.0
        for k in range(n):
            g0 += h0[k] * S[s, k]
            g1 += h1[k] * S[s, k]
        sys_sum[0] += abs(inv[0, 0] * g0 + inv[0, 1] * g1)
        sys_sum[1] += abs(inv[1, 0] * g0 + inv[1, 1] * g1)
    J = np.empty((2, E.shape[0]))
    for s in range(E.shape[0]):
        g0 = g1 = 0.0
        for k in range(n):
            g0 += h0[k] * E[s, k]
            g1 += h1[k] * E[s, k]
        J[0, s] = inv[0, 0] * g0 + inv[0, 1] * g1
        J[1, s] = inv[1, 0] * g0 + inv[1, 1] * g1
    return FIT_OK, alpha, d, it, n, ssq, inv, cond, sys_sum, J


def line_fit(phi, r, ok, alpha, d, max_iter, S, E):
    """Gauss-Newton from the line (alpha, d) over the beams ``ok`` (bearings ``phi``, ranges
    ``r``; float64 arrays and a bool mask of one length) minimising the squared range
    residuals, then, at the solution, the sum of the squared residuals, ``(H^T H)^-1``, its
    condition number, the sum over the rows ``e`` of ``S`` of ``|(H^T H)^-1 H^T e|`` and the
    columns ``(H^T H)^-1 H^T e`` for the rows of ``E`` (both (k, len(phi)) float64, on every
    beam: the kernel takes those ``ok``). Returns (outcome, alpha, d, iterations, beams used,
    ssq, inv, cond, sys_sum, J), the outcome one of FIT_OK, FIT_GRAZING,
    FIT_NO_CONVERGENCE, FIT_FALLBACK (the values after the beams used only for FIT_OK;
    alpha not wrapped)."""
    return _line_fit(phi, r, ok, float(alpha), float(d), int(max_iter), S, E)


@numba.njit(cache=True, nogil=True)
def trim_bounds(phi, r, ok, a, d, trim):  # pragma: no cover - compiled
    """Of the beams ``ok`` (in order), those whose perpendicular residual
    ``r cos(a - phi) - d`` is within ``trim`` times the residuals' spread ``1.4826 MAD`` (at
    least 1 mm): the first and last of them (positions among the beams ``ok``; -1 when none
    is), how many they are, and how many beams ``ok`` has."""
    n = 0
    for i in range(phi.shape[0]):
        if ok[i]:
            n += 1
    e = np.empty(n)
    m = 0
    for i in range(phi.shape[0]):
        if ok[i]:
            e[m] = r[i] * math.cos(a - phi[i]) - d
            m += 1
    med = np.median(e)
    spread = 1.4826 * np.median(np.abs(e - med))
    bound = trim * _pymax(spread, 1e-3)
    lo = hi = -1
    inside = 0
    for k in range(n):
        if abs(e[k]) <= bound:
            if lo < 0:
                lo = k
            hi = k
            inside += 1
    return lo, hi, inside, n
