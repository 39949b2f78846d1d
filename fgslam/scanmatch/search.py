"""Correlative search (Olson 2009, Hess et al. 2016): every rotation of the window, the
translations by branch and bound over max-pooled likelihood grids; the response surface
(:class:`_Response`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from factors.geometry import rot
from fgslam.config.robot import MatchParams
from fgslam.scanmatch.kernels import branch_and_bound, gather_sums_numpy
from fgslam.scanmatch.reference import Reference


@dataclass
class _Response:
    poses: NDArray  # (K, 3) reference frame
    scores: NDArray  # (K,)
    best: int
    n: int  # search points
    step: float  # rotation step (rad)


@dataclass
class _Window:
    """A search prepared: the rotations (rad), every query point's cell at every rotation
    (``base``, (R, N) flat indices into the pooled levels, translation = the guess), the
    levels (L, cells) max-pooled over 1, 2, .. ``top`` cells, the crop's row length ``ny``,
    the half-width ``n`` of the translation window (cells) and the rotation step (rad)."""

    rots: NDArray
    base: NDArray
    levels: NDArray
    ny: int
    npts: int
    n: int
    top: int
    step: float


def _window(ref: Reference, q: NDArray, guess: NDArray, params: MatchParams) -> _Window:
    res = ref.resolution
    n = math.ceil(params.search_xy / res)
    top = _top_block(params, n)
    # the points the reference could have seen at every pose of the window (with a margin)
    qr = q @ rot(float(guess[2])).T + guess[:2]
    use = ref.covered(qr, params.search_theta, params.search_xy)
    if use.sum() >= max(params.min_coverage * len(q), 3):
        q = q[use]
    far = float(np.quantile(np.hypot(q[:, 0], q[:, 1]), 0.9)) if len(q) else 1.0
    step = params.angular_step or res / float(np.clip(far, 1.0, 10.0))
    m = math.ceil(params.search_theta / step) if params.search_theta > 0 else 0
    rots = guess[2] + step * np.arange(-m, m + 1)
    c, s = np.cos(rots), np.sin(rots)
    # (R, N) cells of every query point at every rotation, translation = guess
    px = c[:, None] * q[None, :, 0] - s[:, None] * q[None, :, 1] + guess[0]
    py = s[:, None] * q[None, :, 0] + c[:, None] * q[None, :, 1] + guess[1]
    ix = np.floor((px - ref.origin[0]) / res).astype(np.int64)
    iy = np.floor((py - ref.origin[1]) / res).astype(np.int64)
    levels, base, ny = _pyramid(ref, ix, iy, n, top)
    return _Window(rots, base, levels, ny, q.shape[0], n, top, step)


def _margin(params: MatchParams, npts: int) -> float:
    """Candidates kept: within mode_nats (the response) or basin_nats (ICP starts) of the
    best, at gain 1, as a score difference."""
    nats = max(params.mode_nats, params.basin_nats if params.max_basins > 1 else 0.0)
    return nats / max(npts, 1)


def _response(win: _Window, guess: NDArray, res: float, cand: tuple, bound: NDArray) -> _Response:
    r, x, y = cand
    poses = np.column_stack([guess[0] + x * res, guess[1] + y * res, win.rots[r]])
    best = int(np.argmax(bound)) if len(bound) else -1
    return _Response(poses, bound, best, win.npts, win.step)


def _search(ref: Reference, q: NDArray, guess: NDArray, params: MatchParams) -> _Response:
    """The correlative search of ``q`` ((N, 2), query frame, m) around ``guess`` (T_ref_query)
    with its branch and bound compiled (:func:`fgslam.scanmatch.kernels.branch_and_bound`;
    the same response as :func:`_search_numpy`)."""
    win = _window(ref, q, guess, params)
    *cand, bound = branch_and_bound(
        win.levels,
        win.base,
        len(win.rots),
        win.n,
        win.top,
        win.ny,
        win.npts,
        _margin(params, win.npts),
        params.max_candidates,
    )
    return _response(win, guess, ref.resolution, tuple(cand), bound)


def _search_numpy(ref: Reference, q: NDArray, guess: NDArray, params: MatchParams) -> _Response:
    """The reference of :func:`_search`: the branch and bound in numpy. Every rotation of the
    window; the translations by blocks of ``top`` cells, each block's bound its best cell's
    score on the max-pooled level; a lower bound from a greedy descent of the best four
    blocks; blocks split in four while their bound reaches the lower bound less the margin
    (at most ``max_candidates`` kept). Sorts are stable: ties keep the candidates' order."""
    win = _window(ref, q, guess, params)
    base, ny, npts, n = win.base, win.ny, win.npts, win.n
    flats = win.levels

    def evaluate(level: int, r: NDArray, dx: NDArray, dy: NDArray) -> NDArray:
        # sums of uint8 fit uint32 for any scan (exact)
        return gather_sums_numpy(flats[level], base, r, dx * ny + dy) / (255.0 * npts)

    # top level: every rotation x every block
    nlev = len(flats) - 1
    w = win.top
    starts = np.arange(-n, n + 1, w)
    rr, bx, by = np.meshgrid(np.arange(len(win.rots)), starts, starts, indexing="ij")
    cand = [rr.ravel(), bx.ravel(), by.ravel()]
    bound = evaluate(nlev, *cand)
    # a lower bound: greedy descent from the best few blocks
    lower = 0.0
    for k in np.argsort(-bound, kind="stable")[:4]:
        r, x, y = cand[0][k : k + 1], cand[1][k : k + 1], cand[2][k : k + 1]
        lev, ww = nlev, w
        while lev > 0:
            ww //= 2
            lev -= 1
            cx = np.concatenate([x, x + ww, x, x + ww])
            cy = np.concatenate([y, y, y + ww, y + ww])
            cr = np.repeat(r, 4)
            keep = (cx <= n) & (cy <= n)
            cx, cy, cr = cx[keep], cy[keep], cr[keep]
            b = evaluate(lev, cr, cx, cy)
            j = int(np.argmax(b))
            r, x, y = cr[j : j + 1], cx[j : j + 1], cy[j : j + 1]
        lower = max(lower, float(evaluate(0, r, x, y)[0]))
    margin_score = _margin(params, npts)
    lev = nlev
    while True:
        thr = lower - margin_score
        keep = bound >= thr
        if keep.sum() > params.max_candidates:
            keep = np.zeros_like(keep)
            keep[np.argsort(-bound, kind="stable")[: params.max_candidates]] = True
        cand = [c_[keep] for c_ in cand]
        bound = bound[keep]
        if lev == 0:
            break
        w //= 2
        lev -= 1
        r, x, y = cand
        cx = np.concatenate([x, x + w, x, x + w])
        cy = np.concatenate([y, y, y + w, y + w])
        cr = np.concatenate([r, r, r, r])
        ok = (cx <= n) & (cy <= n)
        cand = [cr[ok], cx[ok], cy[ok]]
        bound = evaluate(lev, *cand)
        if lev == 0 and len(bound):
            lower = max(lower, float(bound.max()))
    return _response(win, guess, ref.resolution, tuple(cand), bound)


def _top_block(params: MatchParams, n: int) -> int:
    if params.levels > 0:
        return 2 ** (params.levels - 1)
    # coarsest block about half the window: 2-4 blocks per axis at the top
    return int(2 ** max(0, math.ceil(math.log2(max(1, (2 * n + 1) / 3)))))


def _pyramid(
    ref: Reference, ix: NDArray[np.int64], iy: NDArray[np.int64], n: int, top: int
) -> tuple[NDArray[np.uint8], NDArray[np.int64], int]:
    """``ref``'s grid max-pooled over 1, 2, 4, .., ``top`` cells (level l: max of
    grid[i:i+2^l, j:j+2^l]), raveled, over the part of the grid that query points (grid
    cells ``ix``, ``iy``) reach at offsets -n .. n + top, and each point's index into them.
    A point that reaches no cell of the grid looks up the middle of a zero block after it.
    Returns the levels, the indices and the crop's row length."""
    gx, gy = ref.grid.shape
    reach = n + top + 1
    x0 = max(int(ix.min()) - n - 1, -2 * reach)
    y0 = max(int(iy.min()) - n - 1, -2 * reach)
    x1 = min(int(ix.max()) + n + 2 * top + 2, gx + 2 * reach)
    y1 = min(int(iy.max()) + n + 2 * top + 2, gy + 2 * reach)
    x1, y1 = max(x1, x0 + 1), max(y1, y0 + 1)
    tail = 2 * reach + 3  # zero rows after the crop
    crop = np.zeros((x1 - x0 + tail, y1 - y0), dtype=np.uint8)
    a0, a1, b0, b1 = max(x0, 0), min(x1, gx), max(y0, 0), min(y1, gy)
    if a0 < a1 and b0 < b1:
        crop[a0 - x0 : a1 - x0, b0 - y0 : b1 - y0] = ref.grid[a0:a1, b0:b1]
    ny = crop.shape[1]
    hits = (ix >= -reach) & (ix <= gx + reach) & (iy >= -reach) & (iy <= gy + reach)
    hits &= (ix - n > x0) & (ix + n + 2 * top < x1) & (iy - n > y0) & (iy + n + 2 * top < y1)
    nowhere = (x1 - x0 + tail // 2) * ny + ny // 2
    base = np.where(hits, (ix - x0) * ny + (iy - y0), nowhere)
    return np.stack(_pool(crop, top)).reshape(-1, crop.size), base, ny


def _pool(a: NDArray, top: int) -> list[NDArray]:
    """Level l: the max over a[i:i+2^l, j:j+2^l] (cells beyond the edge left out), up to
    ``top`` cells (numpy's vectorised maximum: faster here than a compiled loop)."""
    levels = [a]
    w = 1
    while w < top:
        m = levels[-1]
        nxt = m.copy()
        nxt[:-w, :] = np.maximum(m[:-w, :], m[w:, :])
        nxt[:, :-w] = np.maximum(nxt[:, :-w], nxt[:, w:])
        levels.append(nxt)
        w *= 2
    return levels
