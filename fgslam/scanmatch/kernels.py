"""Compiled inner loops of the scan matcher (numba, cached on disk), each with the numpy
reference it must equal (tests/test_kernels.py checks them on random inputs).

:func:`gather_sums`: the correlative search's score of candidate poses. ``flat`` is a raveled
likelihood level (uint8, 255 = most likely), ``base[r]`` the flat cells of the query points
at rotation ``r``, ``off`` each candidate's translation as a flat offset; the score of
candidate ``k`` is ``sum_j flat[base[r[k], j] + off[k]]``. Integer sums: the compiled loop and
the reference give the same numbers, not just close ones. The compiled loop reads the cells
in place instead of building the (candidates x points) index array of the reference.
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
