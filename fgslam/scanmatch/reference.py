"""The reference side of a match: :class:`Reference`, a scan or local map prepared once
(the likelihood grid of the correlative search, the cKDTree and local lines of ICP, the
sensor origins' fans of view)."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from factors.geometry import wrap_angle_half_open
from fgslam.config.robot import MatchParams
from fgslam.scanmatch.kernels import Cells, cells, local_lines, polyline_cells, splat
from fgslam.scanmatch.points import _clean


def _blur(params: MatchParams) -> float:
    return params.blur or max(params.resolution, 2.0 * params.sigma_range)


class Reference:
    """A reference scan (or a local map: points already in one frame) prepared once for
    matching many queries against it: likelihood grid(s) for the correlative search, a
    cKDTree and per-point normals for point-to-line ICP. Build with :meth:`build`."""

    points: NDArray[np.float64]  # (n, 2) reference frame, m
    normals: NDArray[np.float64]  # (n, 2) unit normals (NaN where no line fits)
    anchors: NDArray[np.float64]  # (n, 2) a point of each local line (neighbours' centroid)
    normal_var: NDArray[np.float64]  # (n,) variance of each normal's angle (rad^2)
    n_points: int
    _tree: cKDTree | None = None
    cells: Cells  # the points binned for ICP's compiled nearest-neighbour queries
    resolution: float
    origin: NDArray[np.float64]  # reference-frame position of cell (0, 0)'s corner
    grid: NDArray[np.uint8]  # likelihood in [0, 1] x 255 over the points' bounding box

    @classmethod
    def build(
        cls, points: ArrayLike, params: MatchParams, origins: ArrayLike | None = None
    ) -> Reference:
        """Prepare ``points`` ((n, 2), reference frame, m; non-finite rows dropped).

        ``origins``: where the sensor was when it saw the points (reference frame, m): one
        (x, y) for a scan (for :func:`scan_points`' robot-frame points, the mount's x, y), or
        one per point (a local map of several scans). With them, the correlative search
        scores only the query points that fall, at every pose of the window, in directions
        some origin's beams covered (if at least ``min_coverage`` of the points do): a query
        point where the reference could not have seen anything (behind the sensor, outside
        its field of view, no return) neither scores nor costs. Without them every point
        counts, which biases the search towards poses that overlap the reference more (along
        a corridor: a confident wrong answer)."""
        self = cls()
        raw = np.asarray(points, dtype=float)
        p = _clean(points)
        self.points = p
        self.n_points = len(p)
        self.resolution = params.resolution
        if len(p):
            area = float(np.prod(np.ptp(p, axis=0) + 2.0))
            # an absurd extent (a map of kilometres) gets coarser cells, not a huge grid
            self.resolution = max(self.resolution, math.sqrt(area / params.max_cells))
        self._blur = max(_blur(params), self.resolution)
        self.normals = np.full((len(p), 2), np.nan)
        self.cells = cells(p, max(params.corr_distance, 0.05))
        self.anchors = p.copy()
        self.normal_var = np.zeros(len(p))
        if len(p) >= 3:
            self.normals, self.anchors, self.normal_var = local_lines(
                self.cells, params.normal_k, params.normal_radius, params.sigma_range**2
            )
        self._rasterise(p, params)
        self._fans = _fans(raw, origins, len(p), params)
        return self

    def _rasterise(self, p: NDArray, params: MatchParams) -> None:
        res = self.resolution
        reach = math.ceil(3.0 * self._blur / res) + 1
        if len(p) == 0:
            self.origin = np.zeros(2)
            self.grid = np.zeros((1, 1), dtype=np.uint8)
            return
        lo = p.min(axis=0)
        self.origin = lo - reach * res
        shape = tuple(np.floor((p.max(axis=0) - lo) / res).astype(int) + 2 * reach + 1)
        # the reference as a polyline: points joined to their two nearest neighbours
        occ = polyline_cells(self.cells, params.link_distance, self.origin, res, shape)
        # likelihood exp(-d^2 / 2 s^2) of the distance d (m) from each cell centre to the
        # nearest occupied cell's, cut at 3 s: a kernel splatted around each occupied cell,
        # each cell keeping the largest value that reaches it
        k = np.arange(-reach, reach + 1)
        kx, ky = np.meshgrid(k, k, indexing="ij")
        kd = np.hypot(kx, ky).ravel() * res
        val = np.exp(-0.5 * (kd / self._blur) ** 2)
        use = kd <= 3.0 * self._blur
        off = (kx.ravel() * shape[1] + ky.ravel())[use]
        val = val[use]
        q8 = np.round(255.0 * val).astype(np.uint8)
        self.grid = splat(occ, off, q8, shape[0] * shape[1]).reshape(shape)

    @property
    def tree(self) -> cKDTree | None:
        """A cKDTree of the points (None without points), built on first use: the numpy
        references of the compiled kernels query it; the matcher itself does not."""
        if self._tree is None and self.n_points:
            self._tree = cKDTree(self.points)
        return self._tree

    def covered(
        self, points: ArrayLike, margin_theta: float = 0.0, margin_xy: float = 0.0
    ) -> NDArray[np.bool_]:
        """Which ``points`` ((N, 2), reference frame, m) lie in directions that the beams
        from some origin given to :meth:`build` covered, still when the points turn by up to
        ``margin_theta`` (rad) and move by up to ``margin_xy`` (m); all True without
        origins."""
        p = np.asarray(points, dtype=float).reshape(-1, 2)
        if not self._fans:
            return np.ones(len(p), dtype=bool)
        out = np.zeros(len(p), dtype=bool)
        for o, ang, ok in self._fans:
            v = p - o
            dist = np.maximum(np.hypot(v[:, 0], v[:, 1]), 0.3)
            mg = margin_theta + np.arcsin(np.minimum(margin_xy / dist, 1.0))
            phi = np.arctan2(v[:, 1], v[:, 0])
            phi = wrap_angle_half_open(phi - ang[0]) + ang[0]  # within [-pi, pi) of ang[0]
            good = np.ones(len(p), dtype=bool)
            for f in (phi - mg, phi, phi + mg):
                k = np.searchsorted(ang, f)
                inside = (k > 0) & (k < len(ang))
                good &= inside & ok[np.clip(k - 1, 0, len(ok) - 1)]
            out |= good
        return out


def _fans(
    raw: NDArray, origins: ArrayLike | None, n_clean: int, params: MatchParams
) -> list[tuple[NDArray, NDArray, NDArray]]:
    """Per sensor origin: its (x, y), the sorted bearings (rad) of the points it saw, and
    whether the gap after each bearing is covered by beams (at most 4 median gaps, 2 deg)."""
    if origins is None or n_clean == 0:
        return []
    o = np.asarray(origins, dtype=float)
    p = raw.reshape(-1, 2) if raw.size else np.zeros((0, 2))
    if o.size in (2, 3) and o.ndim <= 1:
        o = np.broadcast_to(o.ravel()[:2], p.shape)
    o = o.reshape(len(p), -1)[:, :2] if o.size >= 2 * len(p) else None
    if o is None:
        return []
    good = np.isfinite(p).all(axis=1) & np.isfinite(o).all(axis=1)
    good &= np.abs(p).max(axis=1) < 1e6
    out = []
    og = o[good]
    if len(og) and (og == og[0]).all():  # one origin (a scan): np.unique's row sort is slow
        keys, inv = og[:1], np.zeros(len(og), dtype=np.int64)
    else:
        keys, inv = np.unique(og, axis=0, return_inverse=True)
    for i, c in enumerate(keys):
        v = p[good][inv.ravel() == i] - c
        ang = np.arctan2(v[:, 1], v[:, 0])
        ref = math.atan2(float(np.sin(ang).mean()), float(np.cos(ang).mean()))
        ang = np.sort(wrap_angle_half_open(ang - ref) + ref)
        if len(ang) < 2:
            continue
        gap = np.diff(ang)
        thr = max(4.0 * float(np.median(gap)), math.radians(2.0))
        out.append((c, ang, gap <= thr))
    return out


def _normals_numpy(
    p: NDArray, tree: cKDTree, params: MatchParams
) -> tuple[NDArray, NDArray, NDArray]:
    """The reference of :func:`fgslam.scanmatch.kernels.local_lines` (which the build uses).
    Local lines: unit normals from the PCA of each point's neighbours (NaN where they are
    not a line), the neighbours' centroids (a point of the line) and the variance of the
    normal's angle (rad^2: scatter across the line / (k - 2) over the spread along it)."""
    k = min(params.normal_k, len(p))
    d, j = tree.query(p, k=k, distance_upper_bound=params.normal_radius)
    valid = np.isfinite(d)
    jj = np.where(valid, j, 0)
    nb = p[jj]  # (n, k, 2)
    cnt = valid.sum(axis=1)
    w = valid[..., None].astype(float)
    mean = (nb * w).sum(axis=1) / np.maximum(cnt, 1)[:, None]
    c = (nb - mean[:, None, :]) * w
    sxx = (c[..., 0] ** 2).sum(1)
    syy = (c[..., 1] ** 2).sum(1)
    sxy = (c[..., 0] * c[..., 1]).sum(1)
    # eigenvector of the smallest eigenvalue of [[sxx, sxy], [sxy, syy]]
    ang = 0.5 * np.arctan2(2 * sxy, sxx - syy)  # direction of the line
    tr, det = sxx + syy, sxx * syy - sxy**2
    disc = np.sqrt(np.maximum(tr**2 / 4 - det, 0.0))
    lmin, lmax = tr / 2 - disc, tr / 2 + disc
    n = np.column_stack([-np.sin(ang), np.cos(ang)])
    line = (cnt >= 3) & (lmin <= 0.04 * lmax) & (lmax > 0)
    n[~line] = np.nan
    # scatter across the line: the observed one, never below the sensor's range noise (5 cm
    # quantisation fits a staircase that looks straighter, and tilted, than it is)
    s2 = np.maximum(np.maximum(lmin, 0.0) / np.maximum(cnt - 2, 1), params.sigma_range**2)
    var = np.where(line, s2 / np.maximum(lmax, 1e-12), 0)
    return n, mean, var


def _polyline_cells_numpy(
    p: NDArray, tree: cKDTree, link: float, origin: NDArray, res: float, shape: tuple[int, int]
) -> NDArray:
    """The reference of :func:`fgslam.scanmatch.kernels.polyline_cells`."""
    dense = [p]
    if len(p) > 1:
        d, j = tree.query(p, k=min(3, len(p)))
        steps = math.ceil(link / (0.5 * res))
        f = np.linspace(0.0, 1.0, steps + 1)[1:-1]
        for c in range(1, d.shape[1]):
            ok = d[:, c] < link
            a, b = p[ok], p[j[ok, c]]
            if len(a) and len(f):
                seg = a[:, None, :] + f[None, :, None] * (b - a)[:, None, :]
                dense.append(seg.reshape(-1, 2))
    q = np.vstack(dense)
    ij = np.floor((q - origin) / res).astype(np.int64)
    return np.unique(ij[:, 0] * shape[1] + ij[:, 1])
