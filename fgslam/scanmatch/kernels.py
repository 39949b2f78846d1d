"""Compiled inner loops of the scan matcher (numba, cached on disk), each with the numpy
reference it must equal (tests/test_kernels.py checks them on random inputs).

:func:`gather_sums`: the correlative search's score of candidate poses. ``flat`` is a raveled
likelihood level (uint8, 255 = most likely), ``base[r]`` the flat cells of the query points
at rotation ``r``, ``off`` each candidate's translation as a flat offset; the score of
candidate ``k`` is ``sum_j flat[base[r[k], j] + off[k]]``. Integer sums: the compiled loop and
the reference give the same numbers, not just close ones. The compiled loop reads the cells
in place instead of building the (candidates x points) index array of the reference.

:func:`icp_system`: one Gauss-Newton step's normal equations of the point-to-line ICP
(:mod:`fgslam.scanmatch.icp`): for the corresponded query points ``idx``, the Jacobian row
``J = (n^T R, n^T R J_q)`` in the query's body tangent, Cauchy weights
``w = 1 / (1 + (r / c)^2)``, ``H = sum w J J^T`` and ``g = sum w J r``. Float sums in another
order than numpy's: equal to the reference to rounding (1e-12 relative), not bit for bit.
"""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import NDArray


def gather_sums_numpy(
    flat: NDArray[np.uint8], base: NDArray[np.int64], r: NDArray[np.int64], off: NDArray[np.int64]
) -> NDArray[np.uint32]:
    """The reference: ``flat[base[r] + off[:, None]].sum(axis=1)`` as uint32."""
    idx = base[r]
    idx += off[:, None]
    return flat.take(idx).sum(axis=1, dtype=np.uint32)


@numba.njit(cache=True, nogil=True)
def _gather_sums(flat, base, r, off):  # pragma: no cover - compiled
    k_n = r.shape[0]
    n = base.shape[1]
    size = flat.shape[0]
    out = np.empty(k_n, dtype=np.uint32)
    for k in range(k_n):
        row = r[k]
        o = off[k]
        s = 0
        for j in range(n):
            i = base[row, j] + o
            if i < 0 or i >= size:
                raise IndexError("gather_sums: a cell index outside the likelihood level")
            s += flat[i]
        out[k] = s
    return out


def gather_sums(
    flat: NDArray[np.uint8], base: NDArray[np.int64], r: NDArray[np.int64], off: NDArray[np.int64]
) -> NDArray[np.uint32]:
    """:func:`gather_sums_numpy`, compiled. Every index must lie inside ``flat`` (the search's
    pyramid guarantees it: a point off the grid looks up a zero block); an index outside
    raises IndexError as the reference does."""
    r = np.ascontiguousarray(r, dtype=np.int64)
    off = np.ascontiguousarray(off, dtype=np.int64)
    return _gather_sums(flat, np.ascontiguousarray(base, dtype=np.int64), r, off)


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


@numba.njit(cache=True, nogil=True)
def _icp_system(nrm, idx, R, q, r, c):  # pragma: no cover - compiled
    H = np.zeros((3, 3))
    g = np.zeros(3)
    J = np.empty(3)
    for k in range(idx.shape[0]):
        i = idx[k]
        n0, n1 = nrm[i, 0], nrm[i, 1]
        J[0] = n0 * R[0, 0] + n1 * R[1, 0]
        J[1] = n0 * R[0, 1] + n1 * R[1, 1]
        J[2] = -J[0] * q[i, 1] + J[1] * q[i, 0]
        u = r[k] / c
        w = 1.0 / (1.0 + u * u)
        for a in range(3):
            wa = w * J[a]
            g[a] += wa * r[k]
            for b in range(3):
                H[a, b] += wa * J[b]
    return H, g


def icp_system(
    nrm: NDArray[np.float64],
    idx: NDArray[np.int64],
    R: NDArray[np.float64],
    q: NDArray[np.float64],
    r: NDArray[np.float64],
    c: float,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """:func:`icp_system_numpy`, compiled (the same arguments and results, to rounding)."""
    return _icp_system(
        np.ascontiguousarray(nrm, dtype=np.float64),
        np.ascontiguousarray(idx, dtype=np.int64),
        np.ascontiguousarray(R, dtype=np.float64),
        np.ascontiguousarray(q, dtype=np.float64),
        np.ascontiguousarray(r, dtype=np.float64),
        float(c),
    )
