"""The compiled kernels equal their numpy references (fgslam.scanmatch.kernels), on random
inputs and on a real search, and refuse an index outside the grid as the reference does."""

from __future__ import annotations

import numpy as np
import pytest

from fgslam.scanmatch.kernels import gather_sums, gather_sums_numpy


@pytest.mark.parametrize("seed", range(20))
def test_gather_sums_equal_the_reference(seed):
    rng = np.random.default_rng(seed)
    size = int(rng.integers(50, 5000))
    flat = rng.integers(0, 256, size, dtype=np.uint8)
    n_rot, n_pts = int(rng.integers(1, 30)), int(rng.integers(0, 400))
    spread = size // 3
    base = rng.integers(spread, size - spread, (n_rot, n_pts), dtype=np.int64)
    k = int(rng.integers(0, 500))
    r = rng.integers(0, n_rot, k, dtype=np.int64)
    off = rng.integers(-spread, spread, k, dtype=np.int64)
    got = gather_sums(flat, base, r, off)
    want = gather_sums_numpy(flat, base.copy(), r, off)
    assert got.dtype == np.uint32 and want.dtype == np.uint32
    np.testing.assert_array_equal(got, want)


def test_all_255_sums_do_not_overflow():
    """The largest score: every point on a 255 cell, 16 000 points, sums exactly."""
    flat = np.full(100, 255, dtype=np.uint8)
    base = np.full((1, 16_000), 50, dtype=np.int64)
    r, off = np.zeros(3, dtype=np.int64), np.array([-50, 0, 49])
    np.testing.assert_array_equal(gather_sums(flat, base, r, off), [255 * 16_000] * 3)


@pytest.mark.parametrize("shift", [-11, 1])
def test_an_index_outside_the_grid_is_refused(shift):
    flat = np.zeros(10, dtype=np.uint8)
    base = np.array([[0, 5, 9]], dtype=np.int64)
    off = np.array([shift])
    r = np.zeros(1, dtype=np.int64)
    with pytest.raises(IndexError):
        gather_sums(flat, base, r, off)
    if shift > 0:  # numpy's take refuses past the end; a negative index would wrap there
        with pytest.raises(IndexError):
            gather_sums_numpy(flat, base.copy(), r, off)


def test_a_search_scores_the_same_with_the_reference(monkeypatch):
    """A correlative search over a simulated corridor scan gives the same response surface
    with the compiled kernel and with the numpy reference."""
    from fgslam.config import load_config
    from fgslam.scanmatch import MatchParams, Reference, scan_points
    from fgslam.scanmatch import search as search_mod
    from fgslam.sim.raycast import raycast

    box = [(0, 0, 8, 0), (8, 0, 8, 5), (8, 5, 0, 5), (0, 5, 0, 0), (3, 2.5, 3.5, 3.0)]
    segs = np.asarray(box, dtype=float)
    cfg = load_config()
    bearings = cfg.laser.bearings
    rng = np.random.default_rng(0)

    def scan(pose):
        r = raycast(pose[:2], pose[2] + bearings, segs)
        return scan_points(r + rng.normal(0, 0.01, r.shape), bearings, max_range=20.0)

    params = MatchParams.from_config(cfg)
    ref = Reference.build(scan((2.0, 2.0, 0.1)), params)
    q = scan((2.2, 2.1, 0.15))
    guess = np.array([0.15, 0.05, 0.04])
    compiled = search_mod._search(ref, q, guess, params)
    monkeypatch.setattr(search_mod, "gather_sums", gather_sums_numpy)
    reference = search_mod._search(ref, q, guess, params)
    np.testing.assert_array_equal(compiled.poses, reference.poses)
    np.testing.assert_array_equal(compiled.scores, reference.scores)
    assert compiled.best == reference.best and len(compiled.scores) > 0


@pytest.mark.parametrize("seed", range(20))
def test_icp_system_equals_the_reference(seed):
    from fgslam.scanmatch.kernels import icp_system, icp_system_numpy

    rng = np.random.default_rng(100 + seed)
    n = int(rng.integers(3, 600))
    q = rng.uniform(-20, 20, (n, 2))
    a = rng.uniform(-np.pi, np.pi, n)
    nrm = np.column_stack([np.cos(a), np.sin(a)])
    idx = np.sort(rng.choice(n, int(rng.integers(1, n + 1)), replace=False))
    th = rng.uniform(-np.pi, np.pi)
    R = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    r = rng.normal(0, 0.05, len(idx)) * rng.choice([1, 20], len(idx))
    c = float(rng.uniform(0.01, 0.2))
    H, g = icp_system(nrm, idx, R, q, r, c)
    H0, g0 = icp_system_numpy(nrm, idx, R, q, r, c)
    np.testing.assert_allclose(H, H0, rtol=1e-9, atol=1e-9 * np.abs(H0).max())
    np.testing.assert_allclose(g, g0, rtol=1e-9, atol=1e-9 * np.abs(g0).max())
    assert np.allclose(H, H.T, rtol=0, atol=1e-12 * np.abs(H).max())


def test_icp_converges_to_the_same_pose_with_the_reference(monkeypatch):
    """Point-to-line ICP on a simulated box scan ends at the same pose (1e-9) with the
    compiled normal equations and with the numpy reference, and near the truth."""
    from fgslam.config import load_config
    from fgslam.scanmatch import MatchParams, Reference, scan_points
    from fgslam.scanmatch import icp as icp_mod
    from fgslam.scanmatch.kernels import icp_system_numpy
    from fgslam.sim.raycast import raycast

    box = [(0, 0, 8, 0), (8, 0, 8, 5), (8, 5, 0, 5), (0, 5, 0, 0), (3, 2.5, 3.5, 3.0)]
    segs = np.asarray(box, dtype=float)
    bearings = load_config().laser.bearings
    rng = np.random.default_rng(1)

    def scan(pose):
        r = raycast(pose[:2], pose[2] + bearings, segs)
        return scan_points(r + rng.normal(0, 0.01, r.shape), bearings, max_range=20.0)

    params = MatchParams.from_config(load_config())
    ref = Reference.build(scan((2.0, 2.0, 0.1)), params)
    q = scan((2.2, 2.1, 0.15))
    truth = np.array(
        [0.2 * np.cos(0.1) + 0.1 * np.sin(0.1), -0.2 * np.sin(0.1) + 0.1 * np.cos(0.1), 0.05]
    )
    start = truth + np.array([0.05, -0.04, 0.02])
    compiled = icp_mod._icp(ref, q, start, params)
    monkeypatch.setattr(icp_mod, "icp_system", icp_system_numpy)
    reference = icp_mod._icp(ref, q, start, params)
    assert compiled is not None and reference is not None
    np.testing.assert_allclose(compiled.pose, reference.pose, rtol=0, atol=1e-9)
    assert compiled.iterations == reference.iterations
    assert np.hypot(*(compiled.pose[:2] - truth[:2])) < 0.02
    assert abs(compiled.pose[2] - truth[2]) < 0.005
