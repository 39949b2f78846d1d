"""The front end's compiled kernels (fgslam.frontend.kernels) equal their references: the
segmentation makes the same decisions as the plain-Python line growing on random scans
(invalid ranges, jumps, noise, sonar hints), the line fits equal the numpy fits to 1e-9 with
the same iterations, beams and rejections (and bit for bit where numba's LAPACK rounds as
numpy's), and the pieces (pairwise sums, moments, end trimming) equal numpy's."""

from __future__ import annotations

import math

import numba
import numpy as np
import pytest

from fgslam.config import SegmentParams
from fgslam.frontend import fits, kernels
from fgslam.frontend.fits import FitRejected, fit_line, line_ranges
from fgslam.frontend.segmentation import segment_scan, segment_scan_reference

# ------------------------------------------------------------------ segmentation


def random_scan(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A scan of walls (a few straight pieces, noisy, some rounded to the mm so that ranges
    and distances tie) with NaN, inf, zero, negative and far ranges sprinkled in."""
    n = int(rng.integers(1, 400))
    fov = rng.uniform(math.pi / 2, 2 * math.pi)
    phi = np.linspace(-fov / 2, fov / 2, n)
    r = np.empty(n)
    cuts = np.sort(rng.choice(n + 1, size=min(n, int(rng.integers(1, 12))), replace=False))
    for a, b in zip(np.r_[0, cuts], np.r_[cuts, n], strict=True):
        if b <= a:
            continue
        mid = 0.5 * (phi[a] + phi[b - 1])
        alpha = mid + rng.uniform(-1.2, 1.2)
        c = np.maximum(np.cos(alpha - phi[a:b]), 0.05)
        r[a:b] = rng.uniform(0.2, 10.0) * c.min() / c  # ranges within ~0.2-200 m
    r += rng.normal(0.0, rng.choice([0.0, 0.003, 0.01, 0.05]), n)
    if rng.random() < 0.5:
        r = np.round(r, 3)
    for bad in (np.nan, np.inf, -np.inf, 0.0, -1.0, 50.0):
        r[rng.random(n) < rng.uniform(0.0, 0.08)] = bad
    return phi, r


def random_hints(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Sonar hints: runs of points near a cluster (ids 0..5, -1 elsewhere) and distances,
    some equal, some inf."""
    near = np.full(n, -1, dtype=np.int64)
    dist = np.full(n, np.inf)
    for _ in range(int(rng.integers(0, 8))):
        a = int(rng.integers(0, max(n, 1)))
        b = min(n, a + int(rng.integers(1, 15)))
        near[a:b] = rng.integers(0, 6)
        dist[a:b] = np.round(rng.uniform(0.0, 0.2, b - a), int(rng.integers(1, 4)))
    dist[rng.random(n) < 0.03] = np.inf
    return near, dist


def random_params(rng: np.random.Generator) -> SegmentParams:
    return SegmentParams(
        min_points=int(rng.integers(0, 12)),
        max_range=float(rng.uniform(3.0, 30.0)),
        jump=float(rng.uniform(0.05, 0.5)),
        jump_rel=float(rng.uniform(0.0, 0.1)),
        spread=float(rng.choice([0.005, 0.025, 0.1])),
        outlier=float(rng.uniform(0.01, 0.2)),
    )


def _same_segments(phi, r, params, near=None, dist=None):
    got, got_rej = segment_scan(phi, r, params, near, dist)
    want, want_rej = segment_scan_reference(phi, r, params, near, dist)
    assert got == want  # first, last, start, end and cluster of every segment
    assert got_rej == want_rej
    return want


@pytest.mark.parametrize("seed", range(40))
def test_segmentation_decides_as_the_reference(seed):
    rng = np.random.default_rng(seed)
    found = 0
    for _ in range(25):
        phi, r = random_scan(rng)
        params = random_params(rng) if rng.random() < 0.7 else SegmentParams()
        found += len(_same_segments(phi, r, params))
        near, dist = random_hints(rng, len(r))
        found += len(_same_segments(phi, r, params, near, dist))
    assert found > 0  # the scans do have lines


def test_segmentation_ends_of_every_kind_as_the_reference():
    """Over the random scans every end condition occurs, each decided as the reference."""
    rng = np.random.default_rng(123)
    ends = set()
    for _ in range(300):
        phi, r = random_scan(rng)
        near, dist = random_hints(rng, len(r))
        for seg in _same_segments(phi, r, random_params(rng), near, dist):
            ends |= {seg.start, seg.end}
    assert {e.value for e in ends} == set(kernels.END_CODES)


def test_segmentation_of_degenerate_scans():
    params = SegmentParams()
    for r in ([], [1.0], [np.nan] * 5, [0.0] * 20, [2.0] * 30, [np.inf, 2.0, 2.0, np.nan]):
        r = np.asarray(r, dtype=float)
        phi = np.linspace(-1.0, 1.0, len(r))
        _same_segments(phi, r, params)
        _same_segments(phi, r, params, np.zeros(len(r), dtype=np.int64), np.zeros(len(r)))
    # bearings that are not numbers: NaN points, NaN spreads (Python's max keeps a NaN first)
    rng = np.random.default_rng(7)
    for _ in range(50):
        phi, r = random_scan(rng)
        phi[rng.random(len(phi)) < 0.05] = np.nan
        _same_segments(phi, r, params)


# ------------------------------------------------------------------ line fits


@numba.njit(cache=True)
def numba_lstsq(H, y, rcond):  # pragma: no cover - compiled
    return np.linalg.lstsq(H, y, rcond=rcond)[0]


@numba.njit(cache=True)
def numba_inv(A):  # pragma: no cover - compiled
    return np.ascontiguousarray(np.linalg.solve(A, np.eye(2)))


def random_line(rng: np.random.Generator):
    """Bearings and ranges of a wall (noisy, maybe with NaN beams and a grazing beam of the
    next wall at an end), and fit_line's keyword arguments as the front end passes them."""
    n = int(rng.integers(3, 200))
    alpha = rng.uniform(-math.pi, math.pi)
    span = rng.uniform(0.02, 1.6)
    centre = alpha + rng.uniform(-0.6, 0.6)
    phi = np.sort(centre + rng.uniform(-span / 2, span / 2, n))
    d = rng.uniform(0.2, 8.0)
    r = line_ranges(alpha, d, phi) + rng.normal(0.0, rng.choice([0.0, 0.002, 0.01, 0.05]), n)
    if rng.random() < 0.3:
        r[rng.random(n) < 0.1] = np.nan
    if rng.random() < 0.3:
        r[-1] *= rng.uniform(0.7, 1.3)  # the next wall's beam
    kw = {}
    if rng.random() < 0.8:
        kw["systematic"] = [rng.uniform(0.0, 0.02), rng.uniform(0.0, 0.02) * np.abs(r)][
            : int(rng.integers(0, 3))
        ]
    if rng.random() < 0.8:
        kw["sources"] = [np.ones(n), r]
    if rng.random() < 0.5:
        kw["residual_test"] = fits.RESIDUAL_TEST
    if rng.random() < 0.6:
        kw["trim_ends"] = float(rng.choice([2.0, 3.0, 5.0]))
    return phi, r, float(rng.uniform(0.005, 0.05)), kw


def _reference(monkeypatch):
    """Make fit_line run the numpy reference throughout (the fit and the end trimming)."""

    def trim(phi, r, ok, a, d, t):
        return fits._trim_bounds_numpy(phi, r, ok, a, d, t)

    monkeypatch.setattr(fits, "_fit_line_once", fits._fit_line_once_numpy)
    monkeypatch.setattr(fits.kernels, "trim_bounds", trim)


def _outcome(phi, r, sigma, kw):
    try:
        return fit_line(phi, r, sigma, **kw)
    except FitRejected as exc:
        return exc.reason


def assert_same_fit(got, want):
    if isinstance(want, str) or isinstance(got, str):
        assert got == want
        return
    assert got.iterations == want.iterations
    np.testing.assert_array_equal(got.used, want.used)
    np.testing.assert_allclose(got.scale, want.scale, rtol=1e-9)
    np.testing.assert_allclose(got.rms, want.rms, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(got.params, want.params, rtol=0, atol=1e-9 * (1 + want.params[1]))
    for a, b in [
        (got.cov, want.cov),
        (got.cov_random, want.cov_random),
        (got.source_jacobian, want.source_jacobian),
    ]:
        if b is None:
            assert a is None
            continue
        # entries that are zero in exact arithmetic (d alpha / d scale) are rounding noise:
        # compare against the matrix's size
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-9 * np.abs(b).max())


@pytest.mark.parametrize("seed", range(20))
def test_line_fits_equal_the_reference(seed, monkeypatch):
    rng = np.random.default_rng(seed)
    cases = [random_line(rng) for _ in range(40)]
    got = [_outcome(*c) for c in cases]
    _reference(monkeypatch)
    want = [_outcome(*c) for c in cases]
    for g, w in zip(got, want, strict=True):
        assert_same_fit(g, w)
    assert sum(not isinstance(w, str) for w in want) > 10  # most lines fit


def test_line_fit_rejections_as_the_reference(monkeypatch):
    """Through the sensor, grazing beams, no convergence, too few beams, ill-conditioned:
    the same reasons."""
    phi = np.linspace(0.2, 0.6, 30)
    tiny = np.linspace(0.4, 0.4 + 1e-6, 5)
    cases = [
        (phi, line_ranges(0.4, 1e-4, phi), 0.01, {}),  # d ~ 0: through the sensor
        (phi, line_ranges(0.4 + 1.55, 2.0, phi) * 0 + np.linspace(1, 60, 30), 0.01, {}),
        (phi, line_ranges(0.4 + 1.2, 2.0, phi), 0.01, {}),  # beams nearly along the wall
        (phi, line_ranges(0.4, 2.0, phi) + 0.05 * np.sin(9 * phi), 0.01, {"max_iter": 1}),
        (phi[:2], line_ranges(0.4, 2.0, phi[:2]), 0.01, {}),
        (tiny, line_ranges(0.5, 3.0, tiny), 0.01, {}),  # 5 beams over 1e-6 rad
        (tiny * 10, line_ranges(0.5, 3.0, tiny * 10), 0.01, {}),  # still fits
    ]
    got = [_outcome(*c) for c in cases]
    _reference(monkeypatch)
    want = [_outcome(*c) for c in cases]
    reasons = {"through_sensor", "grazing", "no_convergence", "too_few_points", "ill_conditioned"}
    assert reasons <= set(w for w in want if isinstance(w, str))
    for g, w in zip(got, want, strict=True):
        assert_same_fit(g, w)


@pytest.mark.parametrize("how", ["handed back", "LAPACK failed"])
def test_a_fit_the_kernel_hands_back_runs_the_reference(how, monkeypatch):
    rng = np.random.default_rng(5)
    phi, r, sigma, kw = random_line(rng)
    kw.pop("trim_ends", None)
    want = _outcome(phi, r, sigma, kw)

    def handed_back(*a):
        if how == "LAPACK failed":
            raise np.linalg.LinAlgError("SVD did not converge")
        return (kernels.FIT_FALLBACK,) + (None,) * 9

    monkeypatch.setattr(kernels, "line_fit", handed_back)
    got = _outcome(phi, r, sigma, kw)
    _reference(monkeypatch)
    assert_same_fit(got, _outcome(phi, r, sigma, kw))
    assert_same_fit(got, want)


@pytest.mark.parametrize("seed", range(10))
def test_pairwise_sums_are_numpys_bit_for_bit(seed):
    rng = np.random.default_rng(seed)
    for n in [0, 1, 7, 8, 9, 127, 128, 129, 255, 256, 257, int(rng.integers(1, 5000))]:
        a = rng.normal(size=n) * 10.0 ** rng.uniform(-6, 6, n)
        assert kernels.pairwise_sum(a, 0, n) == np.sum(a)
        lo = n // 3
        assert kernels.pairwise_sum(a, lo, n - lo) == np.sum(a[lo:])


def _same_lapack() -> bool:
    """numba's LAPACK (SciPy's) gives numpy's lstsq and inv bits on a few probes."""
    rng = np.random.default_rng(0)
    for n in (3, 20, 150):
        H, y = rng.normal(size=(n, 2)), rng.normal(size=n)
        want = np.linalg.lstsq(H, y, rcond=None)[0]
        if not np.array_equal(numba_lstsq(H, y, np.finfo(float).eps * n), want):
            return False
        if not np.array_equal(numba_inv(H.T @ H), np.linalg.inv(H.T @ H)):
            return False
    return True


@pytest.mark.parametrize("seed", range(5))
def test_line_fits_are_the_reference_bit_for_bit(seed, monkeypatch):
    """Where numba's LAPACK and BLAS are numpy's (here), the fits are the same bits (the SLAM
    run downstream changes with a one-ulp change of a line)."""
    if not _same_lapack():
        pytest.skip("numpy and SciPy use LAPACK builds that round differently")
    rng = np.random.default_rng(100 + seed)
    cases = [random_line(rng) for _ in range(40)]
    got = [_outcome(*c) for c in cases]
    _reference(monkeypatch)
    want = [_outcome(*c) for c in cases]
    for g, w in zip(got, want, strict=True):
        if isinstance(w, str) or isinstance(g, str):
            assert g == w
            continue
        for name in ("params", "cov", "cov_random", "source_jacobian", "rms", "scale", "used"):
            np.testing.assert_array_equal(getattr(g, name), getattr(w, name), err_msg=name)
        assert g.iterations == w.iterations


@pytest.mark.parametrize("seed", range(10))
def test_moments_equal_numpy(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 300))
    phi, r = rng.uniform(-3, 3, n), rng.uniform(0.1, 20, n)
    ok = rng.random(n) < 0.8
    ok[int(rng.integers(0, n))] = True
    x, y = r[ok] * np.cos(phi[ok]), r[ok] * np.sin(phi[ok])
    mx, my = x.mean(), y.mean()
    want = [mx, my, ((x - mx) ** 2).sum(), ((y - my) ** 2).sum(), ((x - mx) * (y - my)).sum()]
    got = kernels.ok_sums(phi, r, ok)
    assert got == tuple(want)  # numpy's pairwise sums, bit for bit
    assert fits._tls_of_moments(*got) == fits.tls_line(x, y)


@pytest.mark.parametrize("seed", range(20))
def test_end_trimming_keeps_the_beams_of_the_reference(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(3, 200))
    phi = np.sort(rng.uniform(-1.0, 1.0, n))
    a, d = rng.uniform(-0.3, 0.3), rng.uniform(0.5, 6.0)
    r = line_ranges(a, d, phi) + rng.normal(0.0, 0.01, n)
    r[rng.random(n) < 0.1] += rng.normal(0.0, 0.5)  # outliers anywhere
    ok = np.isfinite(r) & (r > 0) & (rng.random(n) < 0.95)
    if ok.sum() == 0:
        ok[0] = True
    for t in (0.5, 2.0, 3.0, 50.0):
        got = kernels.trim_bounds(phi, r, ok, a, d, t)
        assert tuple(got) == fits._trim_bounds_numpy(phi, r, ok, a, d, t)
