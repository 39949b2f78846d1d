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
:func:`fgslam.frontend.fits.tls_line` (the reference) takes the total-least-squares line. The
sums are numpy's pairwise summation written out (:func:`pairwise_sum`): the same bits.

:func:`line_fit`: the Gauss-Newton iterations and covariances of
:func:`fgslam.frontend.fits._fit_line_once` (the reference: ``_fit_line_once_numpy``). It
computes what the reference's numpy expressions compute, in the same order, through the same
LAPACK and BLAS routines: each step ``np.linalg.lstsq`` (gelsd, numpy's ``rcond``), ``H^T H``
and the products BLAS's matrix products, ``(H^T H)^-1`` gesv on the identity (numpy's
``inv``), the squared residuals' sum numpy's pairwise one. numba calls SciPy's LAPACK and BLAS,
numpy its own build of them: where the two builds agree (here both OpenBLAS, the same
kernels) the fits are the reference's bit for bit (the SLAM run downstream is chaotic: a
one-ulp change of a line's parameters changes which keyframes and loops it takes); else equal
to rounding (the tests' bound: 1e-9). Only the condition number is computed another way (the
eigenvalues of the 2x2 matrix; numpy's SVD where it is within 10x of the threshold), so the
same fits are refused. Non-finite values or a LAPACK failure hand the fit back to the
reference.

:func:`trim_bounds`: the end trimming of :func:`fgslam.frontend.fits.fit_line`: the
range residuals of the kept beams to the fitted line, their robust spread
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
def _pairwise_block(a, lo, n):  # pragma: no cover - compiled
    """numpy's pairwise sum of ``a[lo:lo + n]``, n <= 128: eight accumulators."""
    if n < 8:
        res = 0.0
        for i in range(lo, lo + n):
            res += a[i]
        return res
    r0, r1, r2, r3 = a[lo], a[lo + 1], a[lo + 2], a[lo + 3]
    r4, r5, r6, r7 = a[lo + 4], a[lo + 5], a[lo + 6], a[lo + 7]
    i = 8
    while i < n - n % 8:
        k = lo + i
        r0 += a[k]
        r1 += a[k + 1]
        r2 += a[k + 2]
        r3 += a[k + 3]
        r4 += a[k + 4]
        r5 += a[k + 5]
        r6 += a[k + 6]
        r7 += a[k + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[lo + i]
        i += 1
    return res


@numba.njit(cache=True, nogil=True)
def pairwise_sum(a, lo, n):  # pragma: no cover - compiled
    """``np.sum(a[lo:lo + n])`` of contiguous float64, bit for bit: numpy's pairwise
    summation (blocks of up to 128 values, halved above, the halves' lengths multiples of 8).
    numpy recurses; here a stack of halves does (numba's cache does not load recursive
    functions)."""
    if n <= 128:
        return _pairwise_block(a, lo, n)
    los = np.empty(64, dtype=np.int64)
    ns = np.empty(64, dtype=np.int64)
    stage = np.empty(64, dtype=np.int64)
    vals = np.empty(64)
    sp, vp = 0, 0
    los[0], ns[0], stage[0] = lo, n, 0
    while sp >= 0:
        l0, m = los[sp], ns[sp]
        if m <= 128:
            vals[vp] = _pairwise_block(a, l0, m)
            vp += 1
            sp -= 1
            continue
        n2 = m // 2
        n2 -= n2 % 8
        if stage[sp] == 0:  # the first half next
            stage[sp] = 1
            sp += 1
            los[sp], ns[sp], stage[sp] = l0, n2, 0
        elif stage[sp] == 1:  # then the second
            stage[sp] = 2
            sp += 1
            los[sp], ns[sp], stage[sp] = l0 + n2, m - n2, 0
        else:  # both summed: first + second
            vp -= 1
            vals[vp - 1] = vals[vp - 1] + vals[vp]
            sp -= 1
    return vals[0]


@numba.njit(cache=True, nogil=True)
def ok_sums(phi, r, ok):  # pragma: no cover - compiled
    """(mean x, mean y, sum (x - mx)^2, sum (y - my)^2, sum (x - mx)(y - my)) of the points
    ``r (cos phi, sin phi)`` of the beams ``ok`` (at least one), as
    :func:`fgslam.frontend.fits.tls_line` computes them with numpy, bit for bit; float64
    arrays and a bool mask of one length."""
    n = 0
    for i in range(phi.shape[0]):
        if ok[i]:
            n += 1
    x = np.empty(n)
    y = np.empty(n)
    k = 0
    for i in range(phi.shape[0]):
        if ok[i]:
            x[k] = r[i] * math.cos(phi[i])
            y[k] = r[i] * math.sin(phi[i])
            k += 1
    mx, my = pairwise_sum(x, 0, n) / n, pairwise_sum(y, 0, n) / n
    xx = np.empty(n)
    yy = np.empty(n)
    xy = np.empty(n)
    for k in range(n):
        dx, dy = x[k] - mx, y[k] - my
        xx[k], yy[k], xy[k] = dx * dx, dy * dy, dx * dy
    return mx, my, pairwise_sum(xx, 0, n), pairwise_sum(yy, 0, n), pairwise_sum(xy, 0, n)


# line_fit's outcomes: converged, a grazing beam, no convergence, a case the kernel does not
# take (non-finite values: the caller runs the reference)
FIT_OK, FIT_GRAZING, FIT_NO_CONVERGENCE, FIT_FALLBACK = 0, 1, 2, 3


@numba.njit(cache=True, nogil=True)
def _jacobian(p, rr, alpha, d, H, y):  # pragma: no cover - compiled
    """The fit's Jacobian ``H`` and range residuals ``y`` at (alpha, d), as the reference's
    numpy expressions; False if a beam grazes the line (cos <= 0.02)."""
    grazing = False
    for k in range(p.shape[0]):
        c = math.cos(alpha - p[k])
        if c <= 0.02:
            grazing = True
        H[k, 0] = d * math.sin(alpha - p[k]) / (c * c)
        H[k, 1] = 1.0 / c
        y[k] = rr[k] - d / c
    return not grazing


@numba.njit(cache=True, nogil=True)
def _line_fit(phi, r, ok, alpha, d, max_iter, S_all, E_all):  # pragma: no cover - compiled
    n = 0
    for i in range(ok.shape[0]):
        if ok[i]:
            n += 1
    p = np.empty(n)
    rr = np.empty(n)
    S = np.empty((S_all.shape[0], n))  # a row per source, as the reference's vectors
    E = np.empty((n, E_all.shape[0]))  # a column per source, as the reference's matrix
    k = 0
    for i in range(ok.shape[0]):
        if ok[i]:
            p[k], rr[k] = phi[i], r[i]
            S[:, k] = S_all[:, i]
            E[k, :] = E_all[:, i]
            k += 1
    H = np.empty((n, 2))
    y = np.empty(n)
    rcond = np.finfo(np.float64).eps * max(n, 2)  # numpy's lstsq with rcond=None
    none = np.zeros((2, 2))
    it = 0
    converged = False
    for it in range(1, max_iter + 1):
        if not _jacobian(p, rr, alpha, d, H, y):
            return FIT_GRAZING, alpha, d, it, n, 0.0, none, none, np.zeros(2), np.zeros((2, 0))
        if not (np.isfinite(H).all() and np.isfinite(y).all()):
            return FIT_FALLBACK, alpha, d, it, n, 0.0, none, none, np.zeros(2), np.zeros((2, 0))
        step = np.linalg.lstsq(H, y, rcond=rcond)[0]  # LAPACK's gelsd, as numpy's
        alpha, d = alpha + step[0], d + step[1]
        if abs(step[0]) < 1e-8 and abs(step[1]) < 1e-7:
            converged = True
            break
    if not converged:
        return FIT_NO_CONVERGENCE, alpha, d, it, n, 0.0, none, none, np.zeros(2), np.zeros((2, 0))
    if d <= 0:  # the caller rejects it before anything below
        return FIT_OK, alpha, d, it, n, 0.0, none, none, np.zeros(2), np.zeros((2, 0))
    _jacobian(p, rr, alpha, d, H, y)
    if not (np.isfinite(H).all() and np.isfinite(y).all()):
        return FIT_FALLBACK, alpha, d, it, n, 0.0, none, none, np.zeros(2), np.zeros((2, 0))
    for k in range(n):
        y[k] = y[k] * y[k]
    ssq = pairwise_sum(y, 0, n)
    HtH = H.T @ H
    # gesv on the identity, as numpy's inv, and in C order as numpy's (the products below
    # take another BLAS path for a Fortran-ordered matrix)
    inv = np.ascontiguousarray(np.linalg.solve(HtH, np.eye(2)))
    sys_sum = np.zeros(2)
    for s in range(S.shape[0]):
        # numpy's inv @ vector is BLAS's matrix product with a column
        sys_sum += np.abs((inv @ (H.T @ S[s]).reshape(2, 1))[:, 0])
    J = inv @ (H.T @ E)
    return FIT_OK, alpha, d, it, n, ssq, HtH, inv, sys_sum, J


def line_fit(phi, r, ok, alpha, d, max_iter, S, E):
    """Gauss-Newton from the line (alpha, d) over the beams ``ok`` (bearings ``phi``, ranges
    ``r``; float64 arrays and a bool mask of one length) minimising the squared range
    residuals, then, at the solution, the sum of the squared residuals, ``H^T H``, its
    inverse, the sum over the rows ``e`` of ``S`` of ``|(H^T H)^-1 H^T e|`` and the columns
    ``(H^T H)^-1 H^T e`` for the rows of ``E`` (both (k, len(phi)) float64, on every beam:
    the kernel takes those ``ok``). Returns (outcome, alpha, d, iterations, beams used, ssq,
    HtH, inv, sys_sum, J), the outcome one of FIT_OK, FIT_GRAZING, FIT_NO_CONVERGENCE,
    FIT_FALLBACK (the values after the beams used only for FIT_OK with d > 0; alpha not
    wrapped). Each step is ``np.linalg.lstsq`` (LAPACK's gelsd, as numpy calls it),
    ``(H^T H)^-1`` LAPACK's gesv on the identity (as ``np.linalg.inv``), products BLAS's and
    sums numpy's pairwise ones: the reference's numbers bit for bit."""
    return _line_fit(phi, r, ok, float(alpha), float(d), int(max_iter), S, E)


@numba.njit(cache=True, nogil=True)
def trim_bounds(phi, r, ok, a, d, trim):  # pragma: no cover - compiled
    """Of the beams ``ok`` (in order), those whose range residual
    ``r - d / cos(a - phi)`` is within ``trim`` times the residuals' spread ``1.4826 MAD`` (at
    least 1 mm; a beam at or beyond grazing, cos <= 0, is outside): the first and last of
    them (positions among the beams ``ok``; -1 when none is), how many they are, and how
    many beams ``ok`` has."""
    n = 0
    for i in range(phi.shape[0]):
        if ok[i]:
            n += 1
    e = np.empty(n)
    m = 0
    for i in range(phi.shape[0]):
        if ok[i]:
            c = math.cos(a - phi[i])
            e[m] = r[i] - d / c if c > 0.0 else math.inf
            m += 1
    med = np.median(e)
    spread = 1.4826 * np.median(np.abs(e - med))
    if not math.isfinite(spread):
        spread = 0.0
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
