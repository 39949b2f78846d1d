"""Compiled inner loops of the scan matcher (numba, cached on disk), each with the numpy
reference it must equal (tests/test_kernels.py checks them on random inputs and on simulated
scans).

The correlative search (:mod:`fgslam.scanmatch.search`): :func:`branch_and_bound` scores
candidate poses on max-pooled likelihood levels, splits the blocks in four, keeps a greedy
lower bound and caps the candidates, in one call; its reference is the whole numpy search
``search._search_numpy``, whose scoring is :func:`gather_sums_numpy`: ``flat`` a raveled
likelihood level (uint8, 255 = most likely), ``base[r]`` the flat cells of the query points
at rotation ``r``, ``off`` each candidate's translation as a flat offset, the score of
candidate ``k`` ``sum_j flat[base[r[k], j] + off[k]]``. Integer sums: both give the same
candidates, order and scores, not just close ones. (The max-pooled levels stay numpy's,
``search._pool``: a compiled loop was slower, ``experiments/bench_kernels.py``.)

The reference's preparation (:class:`fgslam.scanmatch.reference.Reference`): the points
binned in :class:`Cells` (:func:`cells`) for fixed-radius queries; :func:`local_lines` each
point's local line (reference ``reference._normals_numpy``, over scipy's cKDTree);
:func:`polyline_cells` the cells of the points joined to their nearest neighbours (reference
``reference._polyline_cells_numpy``); :func:`splat` the likelihood kernel stamped around
those cells (:func:`splat_numpy`, byte for byte).

:func:`icp_loop`: the point-to-line ICP's Gauss-Newton iterations
(:mod:`fgslam.scanmatch.icp`, whose ``_icp_numpy`` is the reference): correspondences to the
nearest reference point within ``corr_distance`` (:func:`correspond`, over :class:`Cells`
by :func:`nearest_within`, the reference being scipy's cKDTree: :func:`nearest_within_numpy`),
the Jacobian row ``J = (n^T R, n^T R J_q)`` in the query's body tangent, Cauchy weights
``w = 1 / (1 + (r / c)^2)``, ``H = sum w J J^T`` and ``g = sum w J r`` (the reference:
:func:`icp_system_numpy`), a 3x3 solve and GTSAM's Pose2 retract. Float sums in another
order than numpy's: equal to the reference to rounding, not bit for bit.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba
import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree


def gather_sums_numpy(
    flat: NDArray[np.uint8], base: NDArray[np.int64], r: NDArray[np.int64], off: NDArray[np.int64]
) -> NDArray[np.uint32]:
    """The reference scoring of :func:`fgslam.scanmatch.search._search_numpy` (what
    :func:`branch_and_bound` computes in its loop): ``flat[base[r] + off[:, None]].sum(axis=1)``
    as uint32, exact for any scan. An index past the end of ``flat`` raises IndexError."""
    idx = base[r]
    idx += off[:, None]
    return flat.take(idx).sum(axis=1, dtype=np.uint32)


def icp_system_numpy(
    nrm: NDArray[np.float64],
    idx: NDArray[np.int64],
    R: NDArray[np.float64],
    q: NDArray[np.float64],
    r: NDArray[np.float64],
    c: float,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The reference: ``nrm`` (N, 2) each query point's reference normal (world), ``idx`` the
    corresponded points, ``R`` the query's rotation, ``q`` (N, 2) the query points (query
    frame, m), ``r`` (len(idx),) their residuals (m), ``c`` the Cauchy scale (m)."""
    jq = np.column_stack([-q[idx, 1], q[idx, 0]])
    nb = nrm[idx] @ R
    J = np.column_stack([nb, np.einsum("ij,ij->i", nb, jq)])
    wts = 1.0 / (1.0 + (r / c) ** 2)
    return (J * wts[:, None]).T @ J, (J * wts[:, None]).T @ r


class Cells(NamedTuple):
    """Points binned on a square grid for fixed-radius nearest-neighbour queries in compiled
    code: cell ``(cx, cy) = floor((p - lo) / size)``, key ``cx * ny + cy``; ``keys`` the
    occupied cells' keys (sorted), the points of ``keys[t]`` are
    ``order[starts[t]:starts[t + 1]]``. Build with :func:`cells`."""

    points: NDArray[np.float64]  # (n, 2), m
    lo: NDArray[np.float64]  # (2,) corner of cell (0, 0), m
    size: float  # cell side, m
    ny: int  # cells along y
    nx: int  # cells along x
    keys: NDArray[np.int64]
    starts: NDArray[np.int64]  # (len(keys) + 1,)
    order: NDArray[np.int64]


def cells(points: NDArray[np.float64], size: float) -> Cells:
    """Bin ``points`` ((n, 2) finite, m) in cells of ``size`` (m, > 0)."""
    p = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 2)
    if len(p) == 0:
        z = np.zeros(0, dtype=np.int64)
        return Cells(p, np.zeros(2), float(size), 1, 1, z, np.zeros(1, dtype=np.int64), z)
    lo = p.min(axis=0)
    ij = np.floor((p - lo) / size).astype(np.int64)
    nx, ny = int(ij[:, 0].max()) + 1, int(ij[:, 1].max()) + 1
    key = ij[:, 0] * ny + ij[:, 1]
    order = np.argsort(key, kind="stable")
    keys, first = np.unique(key[order], return_index=True)
    starts = np.append(first, len(p)).astype(np.int64)
    return Cells(p, lo, float(size), ny, nx, keys.astype(np.int64), starts, order)


def nearest_within_numpy(
    tree: cKDTree, x: NDArray[np.float64], dmax: float
) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """The reference: each row of ``x``'s nearest point closer than ``dmax`` (m): its
    distance (inf where none) and index (``n`` where none), as ``cKDTree.query`` gives."""
    return tree.query(x, distance_upper_bound=dmax)


@numba.njit(cache=True, nogil=True)
def _nearest(pts, lo, size, ny, nx, keys, starts, order, x, y, dmax, bd, bj):  # pragma: no cover
    """Index of the point nearest to (x, y) closer than dmax (-1 if none), and its squared
    distance: :func:`_k_nearest` with k = 1 (``bd``, ``bj`` its one-element buffers)."""
    if _k_nearest(pts, lo, size, ny, nx, keys, starts, order, x, y, dmax, 1, bd, bj):
        return bj[0], bd[0]
    return -1, dmax * dmax


@numba.njit(cache=True, nogil=True)
def _nearest_all(pts, lo, size, ny, nx, keys, starts, order, x, dmax):  # pragma: no cover
    n = x.shape[0]
    d = np.empty(n)
    j = np.empty(n, dtype=np.int64)
    buf_d, buf_j = np.empty(1), np.empty(1, dtype=np.int64)
    for i in range(n):
        b, bd = _nearest(
            pts, lo, size, ny, nx, keys, starts, order, x[i, 0], x[i, 1], dmax, buf_d, buf_j
        )
        if b < 0:
            d[i], j[i] = np.inf, pts.shape[0]
        else:
            d[i], j[i] = math.sqrt(bd), b
    return d, j


def nearest_within(
    c: Cells, x: NDArray[np.float64], dmax: float
) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """:func:`nearest_within_numpy`, compiled over :class:`Cells` (the same results except
    between points at exactly equal distance: the lower index here)."""
    x = np.ascontiguousarray(x, dtype=np.float64).reshape(-1, 2)
    return _nearest_all(c.points, c.lo, c.size, c.ny, c.nx, c.keys, c.starts, c.order, x, dmax)


@numba.njit(cache=True, nogil=True)
def _correspond(
    pts, lo, size, ny, nx, keys, starts, order, normals, anchors, q, pose, dmax
):  # pragma: no cover
    """Point-to-line correspondences of the query points ``q`` (query frame) at ``pose``:
    the corresponded points' indices, their neighbours and signed residuals (m)."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    n = q.shape[0]
    idx = np.empty(n, dtype=np.int64)
    jj = np.empty(n, dtype=np.int64)
    r = np.empty(n)
    buf_d, buf_j = np.empty(1), np.empty(1, dtype=np.int64)
    m = 0
    for i in range(n):
        x = c * q[i, 0] - s * q[i, 1] + pose[0]
        y = s * q[i, 0] + c * q[i, 1] + pose[1]
        j, _ = _nearest(pts, lo, size, ny, nx, keys, starts, order, x, y, dmax, buf_d, buf_j)
        if j < 0 or not np.isfinite(normals[j, 0]):
            continue
        idx[m], jj[m] = i, j
        r[m] = normals[j, 0] * (x - anchors[j, 0]) + normals[j, 1] * (y - anchors[j, 1])
        m += 1
    return idx[:m], jj[:m], r[:m]


def correspond(
    c: Cells,
    normals: NDArray[np.float64],
    anchors: NDArray[np.float64],
    q: NDArray[np.float64],
    pose: NDArray[np.float64],
    dmax: float,
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.float64]]:
    """Point-to-line correspondences of ``q`` ((N, 2), query frame, m) placed at ``pose``
    (x, y, theta) in the reference frame: the query points with a reference point closer
    than ``dmax`` that has a normal, those neighbours, and the signed residuals (m)."""
    return _correspond(
        c.points,
        c.lo,
        c.size,
        c.ny,
        c.nx,
        c.keys,
        c.starts,
        c.order,
        normals,
        anchors,
        np.ascontiguousarray(q, dtype=np.float64),
        np.asarray(pose, dtype=np.float64),
        dmax,
    )


@numba.njit(cache=True, nogil=True)
def _solve3(A, b):  # pragma: no cover - compiled
    """A x = b for 3x3 A by Gaussian elimination with partial pivoting; NaNs if singular."""
    M = A.copy()
    x = b.copy()
    for k in range(3):
        p = k
        for i in range(k + 1, 3):
            if abs(M[i, k]) > abs(M[p, k]):
                p = i
        if M[p, k] == 0.0:
            return np.full(3, np.nan)
        if p != k:
            for col in range(3):
                M[k, col], M[p, col] = M[p, col], M[k, col]
            x[k], x[p] = x[p], x[k]
        for i in range(k + 1, 3):
            f = M[i, k] / M[k, k]
            for col in range(k, 3):
                M[i, col] -= f * M[k, col]
            x[i] -= f * x[k]
    for k in range(2, -1, -1):
        acc = x[k]
        for col in range(k + 1, 3):
            acc -= M[k, col] * x[col]
        x[k] = acc / M[k, k]
    return x


@numba.njit(cache=True, nogil=True)
def _icp_loop(  # pragma: no cover - compiled
    pts,
    lo,
    size,
    ny,
    nx,
    keys,
    starts,
    order,
    normals,
    anchors,
    q,
    pose0,
    sigma_range,
    scale,
    dmax,
    iterations,
    join,
    jxy,
    jth,
):
    pose = pose0.copy()
    converged, joined, it = False, False, 0
    H = np.zeros((3, 3))
    g = np.zeros(3)
    J = np.empty(3)
    for it in range(1, iterations + 1):
        idx, jj, r = _correspond(
            pts, lo, size, ny, nx, keys, starts, order, normals, anchors, q, pose, dmax
        )
        m = idx.shape[0]
        if m < 3:
            break
        sigma = max(sigma_range, 1.4826 * np.median(np.abs(r)))
        cc = scale * sigma
        c, s = math.cos(pose[2]), math.sin(pose[2])
        H[:] = 0.0
        g[:] = 0.0
        for k in range(m):
            i, j = idx[k], jj[k]
            n0, n1 = normals[j, 0], normals[j, 1]
            J[0] = n0 * c + n1 * s
            J[1] = -n0 * s + n1 * c
            J[2] = -J[0] * q[i, 1] + J[1] * q[i, 0]
            u = r[k] / cc
            w = 1.0 / (1.0 + u * u)
            for a in range(3):
                wa = w * J[a]
                g[a] += wa * r[k]
                for b in range(3):
                    H[a, b] += wa * J[b]
        Hd = H.copy()
        for a in range(3):
            Hd[a, a] = H[a, a] + H[a, a] * 1e-6 + 1e-9
        delta = -_solve3(Hd, g)
        if not np.isfinite(delta).all():
            break
        # pose * Exp(delta) (GTSAM's Pose2 retract); the angle is wrapped by the caller
        w = delta[2]
        if abs(w) < 1e-9:
            v0, v1 = delta[0], delta[1]
        else:
            sw, cw = math.sin(w), math.cos(w)
            v0 = (sw * delta[0] - (1 - cw) * delta[1]) / w
            v1 = ((1 - cw) * delta[0] + sw * delta[1]) / w
        pose = np.array([pose[0] + c * v0 - s * v1, pose[1] + s * v0 + c * v1, pose[2] + w])
        step_xy = math.hypot(delta[0], delta[1])
        if join.shape[0] and step_xy < 0.1 * jxy and abs(w) < 0.1 * jth:
            cj = math.cos(jth)  # |wrapped angle difference| <= jth  <=>  cos(difference) >= cj
            for k in range(join.shape[0]):
                if math.hypot(join[k, 0] - pose[0], join[k, 1] - pose[1]) <= jxy:
                    if math.cos(join[k, 2] - pose[2]) >= cj:
                        joined = True
                        return pose, it, converged, joined
        if step_xy < 3e-4 and abs(w) < 3e-5:
            converged = True
            break
    return pose, it, converged, joined


def icp_loop(
    c: Cells,
    normals: NDArray[np.float64],
    anchors: NDArray[np.float64],
    q: NDArray[np.float64],
    pose0: NDArray[np.float64],
    sigma_range: float,
    robust_scale: float,
    dmax: float,
    iterations: int,
    join: tuple[NDArray[np.float64], float, float] | None = None,
) -> tuple[NDArray[np.float64], int, bool, bool]:
    """The Gauss-Newton iterations of :func:`fgslam.scanmatch.icp._icp_numpy` (its numpy
    reference), compiled: the pose reached (angle not wrapped), the iterations run, whether
    they converged, and whether they joined one of ``join``'s poses (then stopped)."""
    jp, jxy, jth = (np.zeros((0, 3)), 0.0, 0.0) if join is None else join
    return _icp_loop(
        c.points,
        c.lo,
        c.size,
        c.ny,
        c.nx,
        c.keys,
        c.starts,
        c.order,
        normals,
        anchors,
        np.ascontiguousarray(q, dtype=np.float64),
        np.asarray(pose0, dtype=np.float64),
        float(sigma_range),
        float(robust_scale),
        float(dmax),
        int(iterations),
        np.ascontiguousarray(jp, dtype=np.float64).reshape(-1, 3),
        float(jxy),
        float(jth),
    )


def splat_numpy(
    occ: NDArray[np.int64], off: NDArray[np.int64], val: NDArray[np.uint8], size: int
) -> NDArray[np.uint8]:
    """The reference: a flat uint8 grid of ``size`` cells, each cell ``occ[i] + off[t]`` set to
    the largest ``val[t]`` that reaches it (0 elsewhere): the kernel ``(off, val)`` stamped
    around every occupied cell, written in order of increasing value."""
    g = np.zeros(size, dtype=np.uint8)
    order = np.argsort(val, kind="stable")
    for o, v in zip(off[order], val[order], strict=True):
        g[occ + o] = v
    return g


@numba.njit(cache=True, nogil=True)
def _splat(occ, off, val, size):  # pragma: no cover - compiled
    g = np.zeros(size, dtype=np.uint8)
    for c in occ:
        for t in range(off.shape[0]):
            i = c + off[t]
            if i < 0 or i >= size:
                raise IndexError("splat: a cell outside the grid")
            if g[i] < val[t]:
                g[i] = val[t]
    return g


def splat(
    occ: NDArray[np.int64], off: NDArray[np.int64], val: NDArray[np.uint8], size: int
) -> NDArray[np.uint8]:
    """:func:`splat_numpy`, compiled (the same grid, byte for byte; a cell outside raises
    IndexError)."""
    return _splat(
        np.ascontiguousarray(occ, dtype=np.int64),
        np.ascontiguousarray(off, dtype=np.int64),
        np.ascontiguousarray(val, dtype=np.uint8),
        int(size),
    )


@numba.njit(cache=True, nogil=True)
def _k_nearest(
    pts, lo, size, ny, nx, keys, starts, order, x, y, radius, k, bd, bj
):  # pragma: no cover
    """The ``k`` points nearest to (x, y) closer than ``radius``, nearest first (equal
    distances: the lower index first), into ``bd`` (squared distances) and ``bj`` (indices);
    returns how many."""
    rings = math.ceil(radius / size)
    r2 = radius * radius
    fx, fy = (x - lo[0]) / size, (y - lo[1]) / size
    if not (fx > -rings - 1.0 and fx < nx + rings + 1.0 and fy > -rings - 1.0):
        return 0
    if not fy < ny + rings + 1.0:
        return 0
    ix, iy = math.floor(fx), math.floor(fy)
    c = 0
    for cx in range(max(ix - rings, 0), min(ix + rings, nx - 1) + 1):
        for cy in range(max(iy - rings, 0), min(iy + rings, ny - 1) + 1):
            key = cx * ny + cy
            t = np.searchsorted(keys, key)
            if t == keys.shape[0] or keys[t] != key:
                continue
            for u in range(starts[t], starts[t + 1]):
                j = order[u]
                dx, dy = pts[j, 0] - x, pts[j, 1] - y
                d2 = dx * dx + dy * dy
                if d2 >= r2:
                    continue
                if c == k and (d2 > bd[c - 1] or (d2 == bd[c - 1] and j > bj[c - 1])):
                    continue
                # insertion into the sorted buffer, dropping its last when full
                pos = c if c < k else k - 1
                while pos > 0 and (d2 < bd[pos - 1] or (d2 == bd[pos - 1] and j < bj[pos - 1])):
                    if pos < k:
                        bd[pos], bj[pos] = bd[pos - 1], bj[pos - 1]
                    pos -= 1
                bd[pos], bj[pos] = d2, j
                if c < k:
                    c += 1
    return c


@numba.njit(cache=True, nogil=True)
def _local_lines(
    pts, lo, size, ny, nx, keys, starts, order, k, radius, var_floor
):  # pragma: no cover
    n = pts.shape[0]
    nrm = np.full((n, 2), np.nan)
    mean = np.empty((n, 2))
    var = np.zeros(n)
    bd = np.empty(max(k, 1))
    bj = np.empty(max(k, 1), dtype=np.int64)
    for i in range(n):
        cnt = _k_nearest(
            pts, lo, size, ny, nx, keys, starts, order, pts[i, 0], pts[i, 1], radius, k, bd, bj
        )
        mx = my = 0.0
        for a in range(cnt):
            mx += pts[bj[a], 0]
            my += pts[bj[a], 1]
        mx /= max(cnt, 1)
        my /= max(cnt, 1)
        mean[i, 0], mean[i, 1] = mx, my
        sxx = syy = sxy = 0.0
        for a in range(cnt):
            cx_, cy_ = pts[bj[a], 0] - mx, pts[bj[a], 1] - my
            sxx += cx_ * cx_
            syy += cy_ * cy_
            sxy += cx_ * cy_
        ang = 0.5 * math.atan2(2 * sxy, sxx - syy)  # direction of the line
        tr, det = sxx + syy, sxx * syy - sxy * sxy
        disc = math.sqrt(max(tr * tr / 4 - det, 0.0))
        lmin, lmax = tr / 2 - disc, tr / 2 + disc
        if cnt >= 3 and lmin <= 0.04 * lmax and lmax > 0:
            nrm[i, 0], nrm[i, 1] = -math.sin(ang), math.cos(ang)
            s2 = max(max(lmin, 0.0) / max(cnt - 2, 1), var_floor)
            var[i] = s2 / max(lmax, 1e-12)
    return nrm, mean, var


@numba.njit(cache=True, nogil=True)
def _mark(occ, x, y, origin, res, shape):  # pragma: no cover - compiled
    fx, fy = (x - origin[0]) / res, (y - origin[1]) / res
    if not (fx >= 0.0 and fx < shape[0] and fy >= 0.0 and fy < shape[1]):
        raise IndexError("polyline_cells: a point outside the grid")
    occ[math.floor(fx) * shape[1] + math.floor(fy)] = True


@numba.njit(cache=True, nogil=True)
def _polyline_cells(
    pts, lo, size, ny, nx, keys, starts, order, link, steps, origin, res, shape
):  # pragma: no cover
    occ = np.zeros(shape[0] * shape[1], dtype=np.bool_)
    bd = np.empty(3)
    bj = np.empty(3, dtype=np.int64)
    n = pts.shape[0]
    df = 1.0 / steps  # numpy's linspace: f = s * (1 / steps)
    for i in range(n):
        ax, ay = pts[i, 0], pts[i, 1]
        _mark(occ, ax, ay, origin, res, shape)
        if n < 2 or steps < 2:
            continue
        c = _k_nearest(pts, lo, size, ny, nx, keys, starts, order, ax, ay, link, min(3, n), bd, bj)
        for t in range(1, c):
            bx, by = pts[bj[t], 0], pts[bj[t], 1]
            for s in range(1, steps):
                f = s * df
                _mark(occ, ax + f * (bx - ax), ay + f * (by - ay), origin, res, shape)
    return occ


def local_lines(
    c: Cells, k: int, radius: float, var_floor: float
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Each point's local line from the PCA of its ``k`` nearest points closer than
    ``radius`` (m, itself included) among ``c``'s points: unit normals (NaN where they are
    not a line: fewer than 3 points, or the smaller eigenvalue above 4 % of the larger), the
    neighbours' centroids and the normal angle's variance (rad^2; the scatter across the line
    per degree of freedom, never below ``var_floor`` (m^2), over the spread along it). The
    reference: :func:`fgslam.scanmatch.reference._normals_numpy` (cKDTree's k nearest)."""
    return _local_lines(
        c.points,
        c.lo,
        c.size,
        c.ny,
        c.nx,
        c.keys,
        c.starts,
        c.order,
        int(k),
        float(radius),
        float(var_floor),
    )


def polyline_cells(
    c: Cells, link: float, origin: NDArray[np.float64], res: float, shape: tuple[int, int]
) -> NDArray[np.int64]:
    """The cells (flat indices, sorted, of a grid of ``shape`` with cell ``(0, 0)``'s corner at
    ``origin`` and cells of ``res`` m) of ``c``'s points and of the segments joining each point
    to its two nearest points closer than ``link`` (m), sampled every ``res / 2`` or finer.
    The reference: :func:`fgslam.scanmatch.reference._polyline_cells_numpy`."""
    steps = math.ceil(link / (0.5 * res))
    occ = _polyline_cells(
        c.points,
        c.lo,
        c.size,
        c.ny,
        c.nx,
        c.keys,
        c.starts,
        c.order,
        float(link),
        int(steps),
        np.asarray(origin, dtype=np.float64),
        float(res),
        np.array(shape, dtype=np.int64),
    )
    return np.flatnonzero(occ)


@numba.njit(cache=True, nogil=True)
def _scores(flat, base, cr, cx, cy, ny, denom):  # pragma: no cover - compiled
    out = np.empty(cr.shape[0])
    size = flat.shape[0]
    n = base.shape[1]
    for k in range(cr.shape[0]):
        o = cx[k] * ny + cy[k]
        row = cr[k]
        s = 0
        for j in range(n):
            i = base[row, j] + o
            if i < 0 or i >= size:
                raise IndexError("branch_and_bound: a cell index outside the likelihood level")
            s += flat[i]
        out[k] = np.uint32(s) / denom
    return out


@numba.njit(cache=True, nogil=True)
def _children(cr, cx, cy, w, n):  # pragma: no cover - compiled
    """The four sub-blocks of each block, in the reference's order (all first quarters,
    then all second ...), those starting beyond the window (> n) left out."""
    m = cr.shape[0]
    rr = np.empty(4 * m, dtype=np.int64)
    xx = np.empty(4 * m, dtype=np.int64)
    yy = np.empty(4 * m, dtype=np.int64)
    c = 0
    for part in range(4):
        ox = w if part in (1, 3) else 0
        oy = w if part >= 2 else 0
        for k in range(m):
            x, y = cx[k] + ox, cy[k] + oy
            if x <= n and y <= n:
                rr[c], xx[c], yy[c] = cr[k], x, y
                c += 1
    return rr[:c], xx[:c], yy[:c]


@numba.njit(cache=True, nogil=True)
def _branch_and_bound(levels, base, nrot, n, top, ny, npts, margin, max_cand):  # pragma: no cover
    denom = 255.0 * npts
    nlev = levels.shape[0] - 1
    w = top
    starts = np.arange(-n, n + 1, w)
    ns = starts.shape[0]
    cr = np.empty(nrot * ns * ns, dtype=np.int64)
    cx = np.empty(nrot * ns * ns, dtype=np.int64)
    cy = np.empty(nrot * ns * ns, dtype=np.int64)
    k = 0
    for r in range(nrot):
        for a in range(ns):
            for b in range(ns):
                cr[k], cx[k], cy[k] = r, starts[a], starts[b]
                k += 1
    bound = _scores(levels[nlev], base, cr, cx, cy, ny, denom)
    lower = 0.0
    order = np.argsort(-bound, kind="mergesort")
    for t in range(min(4, order.shape[0])):
        i = order[t]
        r1, x1, y1 = cr[i : i + 1].copy(), cx[i : i + 1].copy(), cy[i : i + 1].copy()
        lev, ww = nlev, w
        while lev > 0:
            ww //= 2
            lev -= 1
            rr, xx, yy = _children(r1, x1, y1, ww, n)
            b = _scores(levels[lev], base, rr, xx, yy, ny, denom)
            j = np.argmax(b)
            r1, x1, y1 = rr[j : j + 1], xx[j : j + 1], yy[j : j + 1]
        lower = max(lower, _scores(levels[0], base, r1, x1, y1, ny, denom)[0])
    lev = nlev
    while True:
        keep = bound >= lower - margin
        if keep.sum() > max_cand:
            keep[:] = False
            order = np.argsort(-bound, kind="mergesort")
            for t in range(max_cand):
                keep[order[t]] = True
        cr, cx, cy, bound = cr[keep], cx[keep], cy[keep], bound[keep]
        if lev == 0:
            break
        w //= 2
        lev -= 1
        cr, cx, cy = _children(cr, cx, cy, w, n)
        bound = _scores(levels[lev], base, cr, cx, cy, ny, denom)
        if lev == 0 and bound.shape[0]:
            lower = max(lower, bound.max())
    return cr, cx, cy, bound


def branch_and_bound(
    levels: NDArray[np.uint8],
    base: NDArray[np.int64],
    nrot: int,
    n: int,
    top: int,
    ny: int,
    npts: int,
    margin: float,
    max_candidates: int,
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64], NDArray[np.float64]]:
    """The correlative search's branch and bound (:func:`fgslam.scanmatch.search._search_numpy`
    is the reference; the same candidates in the same order and the same scores): ``levels``
    (L, cells) the likelihood max-pooled over 1, 2, .., ``top`` cells, raveled with rows of
    ``ny``; ``base`` (R, N) each query point's cell at each of the ``nrot`` rotations;
    translations -n .. n cells. Returns the kept candidates' rotation index, x and y offsets
    (cells) and scores (mean likelihood in [0, 1])."""
    return _branch_and_bound(
        np.ascontiguousarray(levels, dtype=np.uint8),
        np.ascontiguousarray(base, dtype=np.int64),
        int(nrot),
        int(n),
        int(top),
        int(ny),
        int(npts),
        float(margin),
        int(max_candidates),
    )
