"""The compiled kernels equal their numpy references (fgslam.scanmatch.kernels), on random
inputs and on a real search, and refuse an index outside the grid as the reference does."""

from __future__ import annotations

import numpy as np
import pytest

from fgslam.scanmatch.kernels import branch_and_bound, gather_sums_numpy


def _all_candidates(flat, base, n, ny):
    """branch_and_bound on one level (top 1) keeping every candidate: each rotation x each
    translation -n .. n cells, in the reference's order, with its score."""
    nrot, npts = base.shape
    return branch_and_bound(flat[None], base, nrot, n, 1, ny, npts, 2.0, 10**9)


@pytest.mark.parametrize("seed", range(20))
def test_branch_and_bound_scores_are_the_reference_sums(seed):
    """On one level keeping everything, the compiled search scores every candidate with
    gather_sums_numpy (the numpy search's scoring) over 255 x points, exactly."""
    rng = np.random.default_rng(seed)
    ny = int(rng.integers(5, 60))
    n = int(rng.integers(0, 4))
    size = ny * int(rng.integers(2 * n + 3, 80))
    flat = rng.integers(0, 256, size, dtype=np.uint8)
    reach = n * (ny + 1)
    base = rng.integers(reach, size - reach, (int(rng.integers(1, 8)), int(rng.integers(1, 400))))
    cr, cx, cy, score = _all_candidates(flat, base, n, ny)
    assert len(score) == base.shape[0] * (2 * n + 1) ** 2
    want = gather_sums_numpy(flat, base.copy(), cr, cx * ny + cy)
    assert want.dtype == np.uint32
    np.testing.assert_array_equal(score, want / (255.0 * base.shape[1]))


def test_all_255_sums_do_not_overflow():
    """The largest score: every point on a 255 cell, 16 000 points, sums exactly (the
    reference's uint32 sums and the compiled search's score 1)."""
    flat = np.full(100, 255, dtype=np.uint8)
    base = np.full((1, 16_000), 50, dtype=np.int64)
    r, off = np.zeros(3, dtype=np.int64), np.array([-50, 0, 49])
    np.testing.assert_array_equal(gather_sums_numpy(flat, base, r, off), [255 * 16_000] * 3)
    *_, score = _all_candidates(flat, base, 4, 10)
    np.testing.assert_array_equal(score, np.ones(81))


@pytest.mark.parametrize("cell", [0, 9])
def test_a_cell_outside_the_level_is_refused(cell):
    """A query point whose cell plus a translation leaves the level: the compiled search
    raises IndexError, before the start as past the end; the reference's take past the end
    (a negative index would wrap there)."""
    flat = np.zeros(10, dtype=np.uint8)
    base = np.array([[cell]], dtype=np.int64)
    with pytest.raises(IndexError):
        _all_candidates(flat, base, 1, 1)  # translations -2 .. 2 cells
    if cell == 9:
        with pytest.raises(IndexError):
            gather_sums_numpy(flat, base.copy(), np.zeros(1, dtype=np.int64), np.array([1]))


@pytest.mark.parametrize("seed", range(12))
def test_the_search_responds_as_the_reference(seed):
    """The compiled branch and bound keeps the numpy reference's candidates, in its order,
    with its scores, also when the candidate cap truncates them; the best is near the truth."""
    from dataclasses import replace

    from factors.geometry import wrap_angle
    from fgslam.scanmatch import search as search_mod

    ref, q, truth, params, rng = _box_scans(700 + seed)
    if seed % 3 == 2:
        params = replace(params, max_candidates=int(rng.integers(1, 20)))
    guess = truth + np.array([*rng.uniform(-0.1, 0.1, 2), rng.uniform(-0.05, 0.05)])
    got = search_mod._search(ref, q, guess, params)
    want = search_mod._search_numpy(ref, q, guess, params)
    np.testing.assert_array_equal(got.poses, want.poses)
    np.testing.assert_array_equal(got.scores, want.scores)
    assert (got.best, got.n, got.step) == (want.best, want.n, want.step)
    assert len(got.scores) > 0
    best = got.poses[got.best]
    assert np.hypot(*(best[:2] - truth[:2])) < 0.06
    assert abs(wrap_angle(best[2] - truth[2])) < 0.03


@pytest.mark.parametrize("seed", range(20))
def test_nearest_within_equals_the_kdtree(seed):
    """The binned nearest-neighbour query gives cKDTree's distances and indices, also with a
    radius of several cells, queries far outside the points and non-finite ones."""
    from scipy.spatial import cKDTree

    from fgslam.scanmatch.kernels import cells, nearest_within, nearest_within_numpy

    rng = np.random.default_rng(200 + seed)
    n = int(rng.integers(1, 800))
    p = rng.uniform(-5, 5, (n, 2)) * rng.uniform(0.1, 10)
    x = np.vstack([rng.uniform(-12, 12, (300, 2)), p[:20] + rng.normal(0, 0.01, (min(n, 20), 2))])
    x[:3] = [[np.nan, 0.0], [np.inf, 1.0], [1e12, -1e12]]
    size = float(rng.uniform(0.05, 2.0))
    dmax = float(rng.uniform(0.01, 3.0) * size * rng.choice([1, 4]))
    d, j = nearest_within(cells(p, size), x, dmax)
    assert np.isinf(d[:2]).all() and (j[:2] == n).all()  # no neighbour (the tree refuses them)
    d, j = d[2:], j[2:]
    d0, j0 = nearest_within_numpy(cKDTree(p), x[2:], dmax)
    np.testing.assert_array_equal(j, j0)
    np.testing.assert_allclose(d, d0, rtol=1e-12, atol=0)
    assert np.isfinite(d).sum() > 0 or n < 5


def test_nearest_within_on_no_points():
    from fgslam.scanmatch.kernels import cells, nearest_within

    d, j = nearest_within(cells(np.zeros((0, 2)), 0.3), np.array([[0.0, 0.0]]), 0.3)
    assert np.isinf(d).all() and (j == 0).all()


@pytest.mark.parametrize("seed", range(20))
def test_solve3_equals_numpy(seed):
    from fgslam.scanmatch.kernels import _solve3

    rng = np.random.default_rng(300 + seed)
    A = rng.normal(size=(3, 3)) * rng.uniform(1e-3, 1e3, 3)
    b = rng.normal(size=3)
    np.testing.assert_allclose(_solve3(A, b), np.linalg.solve(A, b), rtol=1e-9, atol=1e-12)
    assert np.isnan(_solve3(np.zeros((3, 3)), b)).all()


def _box_scans(seed):
    """A Reference of the box room's first scan (fgslam.sim.scenes.box_room_scans), the
    query scan, the query's true pose in the reference's frame, the MatchParams and the
    random generator."""
    from fgslam.config import load_config
    from fgslam.scanmatch import MatchParams, Reference
    from fgslam.sim.scenes import box_room_scans

    ref_points, query, truth, rng = box_room_scans(seed)
    params = MatchParams.from_config(load_config())
    return Reference.build(ref_points, params), query, truth, params, rng


@pytest.mark.parametrize("seed", range(10))
def test_correspond_equals_the_reference(seed):
    from fgslam.scanmatch import icp as icp_mod

    ref, q, truth, params, rng = _box_scans(seed)
    pose = truth + rng.normal(0, 0.05, 3)
    _, idx, jj, nrm, r = icp_mod._correspond(ref, q, pose, params)
    _, idx0, jj0, nrm0, r0 = icp_mod._correspond_numpy(ref, q, pose, params)
    np.testing.assert_array_equal(idx, idx0)
    np.testing.assert_array_equal(jj[idx], jj0[idx0])
    np.testing.assert_array_equal(nrm[idx], nrm0[idx0])
    np.testing.assert_allclose(r, r0, rtol=0, atol=1e-12)
    assert len(idx) > 0.5 * len(q)


@pytest.mark.parametrize("seed", range(10))
def test_icp_equals_the_reference_and_finds_the_truth(seed):
    """The compiled ICP ends at the numpy reference's pose (1e-9) after as many iterations,
    with the same inliers, and near the true pose."""
    from factors.geometry import wrap_angle
    from fgslam.scanmatch import icp as icp_mod

    ref, q, truth, params, rng = _box_scans(seed)
    start = truth + np.array([*rng.uniform(-0.06, 0.06, 2), rng.uniform(-0.02, 0.02)])
    got = icp_mod._icp(ref, q, start, params)
    want = icp_mod._icp_numpy(ref, q, start, params)
    assert got is not None and want is not None
    np.testing.assert_allclose(got.pose, want.pose, rtol=0, atol=1e-9)
    assert (got.iterations, got.converged) == (want.iterations, want.converged)
    np.testing.assert_array_equal(got.order, want.order)
    np.testing.assert_allclose(got.J, want.J, rtol=0, atol=1e-9)
    assert np.hypot(*(got.pose[:2] - truth[:2])) < 0.02
    assert abs(wrap_angle(got.pose[2] - truth[2])) < 0.005


@pytest.mark.parametrize("seed", range(5))
def test_icp_joins_a_basin_already_found_as_the_reference_does(seed):
    """Given the converged pose as a basin already found (its angle shifted by a full turn
    and back: the comparison wraps), both ICPs stop and return None; given a pose far away,
    both run to the end."""
    from fgslam.scanmatch import icp as icp_mod

    ref, q, truth, params, _ = _box_scans(seed)
    start = truth + np.array([0.04, -0.03, 0.01])
    done = icp_mod._icp_numpy(ref, q, start, params).pose
    for shift in (2 * np.pi, 0.0):
        join = ((done + np.array([0, 0, shift]))[None], 0.02, 0.01)
        if shift == 0.0:
            assert icp_mod._icp_numpy(ref, q, start, params, join) is None
        assert icp_mod._icp(ref, q, start, params, join) is None
    far = ((done + np.array([3.0, 0, 0]))[None], 0.02, 0.01)
    assert icp_mod._icp(ref, q, start, params, far) is not None
    assert icp_mod._icp_numpy(ref, q, start, params, far) is not None


@pytest.mark.parametrize("seed", range(20))
def test_splat_equals_the_reference(seed):
    from fgslam.scanmatch.kernels import splat, splat_numpy

    rng = np.random.default_rng(400 + seed)
    size = int(rng.integers(100, 20_000))
    reach = int(rng.integers(0, 30))
    occ = np.unique(rng.integers(reach, size - reach, int(rng.integers(0, 300))))
    off = np.arange(-reach, reach + 1)
    val = rng.integers(0, 256, len(off)).astype(np.uint8)
    np.testing.assert_array_equal(splat(occ, off, val, size), splat_numpy(occ, off, val, size))
    with pytest.raises(IndexError):
        splat(np.array([size - 1]), np.array([0, 1]), np.array([1, 2], np.uint8), size)


def _lines_and_clutter(rng):
    """Points on a few noisy lines (walls) and a cloud of clutter, m."""
    parts = []
    for _ in range(int(rng.integers(1, 6))):
        a, b = rng.uniform(-8, 8, 2), rng.uniform(-8, 8, 2)
        t = rng.uniform(0, 1, int(rng.integers(5, 200)))[:, None]
        parts.append(a + t * (b - a) + rng.normal(0, rng.uniform(0.001, 0.03), (len(t), 2)))
    parts.append(rng.uniform(-8, 8, (int(rng.integers(0, 100)), 2)))
    return np.vstack(parts)


@pytest.mark.parametrize("seed", range(20))
def test_local_lines_equal_the_reference(seed):
    """The compiled local lines give the normals, centroids and angle variances of the numpy
    reference (cKDTree's k nearest) to 1e-9, and the same points have a line."""
    from scipy.spatial import cKDTree

    from fgslam.scanmatch import MatchParams
    from fgslam.scanmatch.kernels import cells, local_lines
    from fgslam.scanmatch.reference import _normals_numpy

    rng = np.random.default_rng(500 + seed)
    p = _lines_and_clutter(rng)
    params = MatchParams(
        normal_k=int(rng.integers(3, 40)), normal_radius=float(rng.uniform(0.05, 0.8))
    )
    size = float(rng.uniform(0.05, 1.0))
    n, mean, var = local_lines(
        cells(p, size), params.normal_k, params.normal_radius, params.sigma_range**2
    )
    n0, mean0, var0 = _normals_numpy(p, cKDTree(p), params)
    np.testing.assert_array_equal(np.isnan(n[:, 0]), np.isnan(n0[:, 0]))
    line = ~np.isnan(n[:, 0])
    assert line.sum() >= 10  # not a vacuous comparison
    # a normal's sign is the arctan2's: compare as the same direction
    np.testing.assert_allclose(n[line], n0[line], rtol=0, atol=1e-9)
    np.testing.assert_allclose(mean, mean0, rtol=0, atol=1e-9)
    np.testing.assert_allclose(var, var0, rtol=1e-9, atol=1e-15)


@pytest.mark.parametrize("seed", range(20))
def test_polyline_cells_equal_the_reference(seed):
    """The cells of the reference's polyline (points joined to their two nearest within the
    link distance) are the numpy reference's, on walls with clutter and on a tiny cloud."""
    from scipy.spatial import cKDTree

    from fgslam.scanmatch.kernels import cells, polyline_cells
    from fgslam.scanmatch.reference import _polyline_cells_numpy

    rng = np.random.default_rng(600 + seed)
    p = _lines_and_clutter(rng) if seed % 5 else rng.uniform(0, 0.2, (int(rng.integers(1, 4)), 2))
    res = float(rng.uniform(0.01, 0.1))
    link = float(rng.uniform(0.0, 0.6))
    reach = 3
    origin = p.min(axis=0) - reach * res
    shape = tuple(np.floor((p.max(axis=0) - p.min(axis=0)) / res).astype(int) + 2 * reach + 1)
    got = polyline_cells(cells(p, float(rng.uniform(0.05, 0.5))), link, origin, res, shape)
    want = _polyline_cells_numpy(p, cKDTree(p), link, origin, res, shape)
    np.testing.assert_array_equal(got, want)
    assert len(got) >= 1


def test_a_point_outside_the_polyline_grid_is_refused():
    from fgslam.scanmatch.kernels import cells, polyline_cells

    p = np.array([[0.0, 0.0], [1.0, 0.0]])
    with pytest.raises(IndexError):
        polyline_cells(cells(p, 0.3), 0.3, np.array([0.5, 0.0]), 0.1, (20, 5))


@pytest.mark.parametrize("seed", range(10))
def test_pooled_levels_are_block_maxima(seed):
    """Each pooled level holds, at every cell, the largest value of the 2^l x 2^l block
    starting there (cut at the grid's edge): checked cell by cell against a plain loop."""
    from fgslam.scanmatch.search import _pool

    rng = np.random.default_rng(800 + seed)
    a = rng.integers(0, 256, (int(rng.integers(1, 30)), int(rng.integers(1, 30)))).astype(np.uint8)
    top = int(2 ** rng.integers(0, 5))
    levels = _pool(a, top)
    assert len(levels) == 1 + int(np.log2(top))
    for lev, got in enumerate(levels):
        w = 2**lev
        want = np.array(
            [[a[i : i + w, j : j + w].max() for j in range(a.shape[1])] for i in range(a.shape[0])]
        )
        np.testing.assert_array_equal(got, want)
