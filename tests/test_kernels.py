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
