"""The association (one joint covariance product for all pairs, batched individual gates)
decides exactly as the per-pair reference (``reference_association``, the module as of
d4a6cdb) on seeded random scenes: walls seen as one or two segments, sonar planes, corners
(laser and sonar-only), points, clutter, near misses, correlated covariances."""

from __future__ import annotations

import math
from collections import Counter

import numpy as np
import pytest
import reference_association as ref

from fgslam.config.robot import AssociationParams
from fgslam.frontend.features import End, Feature
from fgslam.slam import association, models
from fgslam.slam.association import Candidate


def _spd(rng: np.random.Generator, n: int, scale: float) -> np.ndarray:
    B = rng.normal(size=(n, n)) * scale
    return B @ B.T + np.eye(n) * scale**2 * 0.1


def _line_feature(rng, pose, lm, s0, s1, noise, endpoints=True) -> Feature:
    """A laser line (or, without endpoints, a sonar plane) of the world line ``lm`` between
    positions s0 < s1 along it, seen from ``pose``."""
    z = models.residual("line", pose, lm, np.zeros(2))[0]  # predicted (alpha, d) - 0
    z = np.array([z[0], z[1]]) + rng.normal(size=2) * noise
    if z[1] < 0:
        z = np.array([math.remainder(z[0] + math.pi, 2 * math.pi), -z[1]])
    cov = np.diag([(noise + 1e-3) ** 2, (noise + 1e-3) ** 2])
    if not endpoints:
        return Feature("line", z, cov, "sonar")
    a, d = lm
    foot, u = d * np.array([math.cos(a), math.sin(a)]), np.array([-math.sin(a), math.cos(a)])
    w = np.array([foot + s0 * u, foot + s1 * u])
    c, s = math.cos(pose[2]), math.sin(pose[2])
    rel = (w - pose[:2]) @ np.array([[c, -s], [s, c]])
    return Feature("line", z, cov, "laser", rel, End.DISCONTINUITY, End.OUTLIERS)


def _scene(seed: int):
    rng = np.random.default_rng(seed)
    pose = np.array([rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(-math.pi, math.pi)])
    means: dict[int, np.ndarray] = {}
    cands: list[Candidate] = []
    feats: list[Feature] = []
    lid = 0
    noise = rng.choice([0.01, 0.05, 0.15])
    for _ in range(rng.integers(1, 5)):  # walls
        a, d = rng.uniform(-math.pi, math.pi), rng.uniform(1.0, 6.0)
        lm = np.array([a, d])
        s0, s1 = sorted(rng.uniform(-6, 6, size=2))
        foot, u = d * np.array([math.cos(a), math.sin(a)]), np.array([-math.sin(a), math.cos(a)])
        ends = np.array([foot + s0 * u, foot + s1 * u]) if rng.random() < 0.9 else None
        means[lid] = lm
        cands.append(Candidate(lid, "line", ends))
        if rng.random() < 0.3:  # a near twin (duplicate-like): two candidates for one wall
            means[lid + 1] = lm + rng.normal(size=2) * 0.03
            cands.append(Candidate(lid + 1, "line", ends))
        r = rng.random()
        if r < 0.4:  # seen as two segments (a door)
            m = 0.5 * (s0 + s1)
            feats.append(_line_feature(rng, pose, lm, s0, m - 0.4, noise))
            feats.append(_line_feature(rng, pose, lm, m + 0.4, s1, noise))
        elif r < 0.8:
            feats.append(_line_feature(rng, pose, lm, s0 + 0.5, s1 + 0.3, noise))
        elif r < 0.9:
            feats.append(_line_feature(rng, pose, lm, s0, s1, noise, endpoints=False))
        lid += 2
    for _ in range(rng.integers(0, 5)):  # corners and points
        kind = rng.choice(["corner", "point"])
        xy = pose[:2] + rng.uniform(-5, 5, size=2)
        lm = np.append(xy, rng.uniform(-math.pi, math.pi)) if kind == "corner" else xy
        means[lid] = lm
        cands.append(Candidate(lid, kind))
        if rng.random() < 0.8:
            z = -models.residual(kind, pose, lm, np.zeros(len(lm)))[0] * -1
            if kind == "corner" and rng.random() < 0.3:  # a sonar-only corner
                z = z[:2]
            z = z + rng.normal(size=len(z)) * noise
            feats.append(Feature(kind, z, np.eye(len(z)) * (noise + 1e-3) ** 2, "laser"))
        if rng.random() < 0.3:  # a rival nearby
            means[lid + 1] = lm + np.append(rng.normal(size=2) * 0.2, [0.0] * (len(lm) - 2))
            cands.append(Candidate(lid + 1, kind))
        lid += 2
    for _ in range(rng.integers(0, 3)):  # clutter
        xy = rng.uniform(-4, 4, size=2)
        feats.append(
            Feature(
                "point", np.array([math.atan2(xy[1], xy[0]), math.hypot(*xy)]), np.eye(2) * 1e-3
            )
        )
    rng.shuffle(feats)
    dims = {i: len(m) for i, m in means.items()}
    order = sorted(means)
    off, o = {}, 3
    for i in order:
        off[i] = o
        o += dims[i]
    P_all = _spd(rng, o, rng.choice([0.02, 0.1]))
    fresh = {i: m + rng.normal(size=len(m)) * 0.01 for i, m in means.items()}

    def estimate(lids):
        idx = [0, 1, 2] + [j for i in lids for j in range(off[i], off[i] + dims[i])]
        return {i: fresh[i] for i in lids}, P_all[np.ix_(idx, idx)].copy()

    return feats, pose, cands, means, estimate


@pytest.mark.parametrize("method", ["jcbb", "nn"])
def test_association_decides_as_the_per_pair_reference(method):
    seen: Counter = Counter()
    for seed in range(300):
        feats, pose, cands, hint, estimate = _scene(seed)
        a = association.associate(
            feats, pose, cands, hint, estimate, AssociationParams(method=method)
        )
        b = ref.associate(feats, pose, cands, hint, estimate, ref.AssociationParams(method=method))
        assert (a.pairs, a.ambiguous, a.merges) == (b.pairs, b.ambiguous, b.merges), seed
        assert a.compatible == b.compatible and a.stats == b.stats, seed
        np.testing.assert_allclose(a.d2, b.d2, rtol=1e-9, atol=1e-12)
        assert a.joint_d2 == pytest.approx(b.joint_d2, rel=1e-9, abs=1e-12)
        seen.update(b.stats)
        seen["paired"] += sum(p is not None for p in b.pairs)
        seen["ambiguous"] += sum(b.ambiguous)
        seen["merges"] += sum(bool(m) for m in b.merges)
        pairs = [q for q in b.pairs if q is not None]
        seen["shared"] += len(pairs) - len(set(pairs))  # a wall seen as two segments
    # the scenes exercise every path
    assert seen["paired"] > 300 and seen["ambiguous"] > 10 and seen["merges"] > 10
    if method == "jcbb":
        assert seen["jcbb_nearest_compatible"] > 20 and seen["jcbb_nodes"] > 100
        assert seen["shared"] > 10


@pytest.mark.parametrize("kind,dimz", [("line", 2), ("corner", 3), ("corner", 2), ("point", 2)])
def test_pregate_residuals_of_many_measurements_equal_those_one_at_a_time(kind, dimz):
    """The pre-gate's residuals of a scan's features at once are, bit for bit, those of each
    feature alone (:func:`models.residuals`, itself checked against the model in test_slam)."""
    rng = np.random.default_rng(3)
    for _ in range(30):
        pose = rng.uniform([-5, -5, -math.pi], [5, 5, math.pi])
        n, m = 15, 6
        if kind == "line":
            lms = np.column_stack([rng.uniform(-math.pi, math.pi, n), rng.uniform(0, 8, n)])
        else:
            lms = rng.uniform([-8, -8, -math.pi], [8, 8, math.pi], (n, 3))[:, : models.DIM[kind]]
        Z = rng.uniform([-math.pi, 0.1, -math.pi], [math.pi, 6, math.pi], (m, 3))[:, :dimz]
        Z[0, 0] = math.pi  # on the wrap-around
        got = models.residuals_grid(kind, pose, lms, Z)
        assert got.shape == (m, n, dimz)
        for z, g in zip(Z, got, strict=True):
            np.testing.assert_array_equal(g, models.residuals(kind, pose, lms, z))


def test_segment_overlap_equals_the_projection_along_the_line():
    """geometry.overlap in scalars equals the overlap of the sorted projections
    (:func:`geometry.along`) to rounding, lines in either parametrisation."""
    from fgslam.slam import geometry

    rng = np.random.default_rng(5)
    for _ in range(2000):
        lm = rng.uniform([-math.pi, -8], [math.pi, 8])
        ends, meas = rng.uniform(-8, 8, (2, 2, 2))
        a, b = np.sort(geometry.along(lm, ends)), np.sort(geometry.along(lm, meas))
        want = min(a[1], b[1]) - max(a[0], b[0])
        assert geometry.overlap(lm, ends, meas) == pytest.approx(want, abs=1e-12)
    assert geometry.overlap(lm, None, meas) == 0.0


@pytest.mark.parametrize("kind", ["line", "corner", "point"])
def test_duplicate_pregate_differences_of_many_landmarks_at_once(kind):
    """The duplicate pre-gate's differences of several landmarks at once equal, bit for bit,
    those of each alone, and the scalar difference (either line parametrisation) to
    rounding."""
    _difference, _differences = models.difference, models.differences

    rng = np.random.default_rng(11)
    dim = models.DIM[kind]
    for _ in range(30):
        A = rng.uniform([-math.pi, -8, -math.pi], [math.pi, 8, math.pi], (5, 3))[:, :dim]
        M = rng.uniform([-math.pi, -8, -math.pi], [math.pi, 8, math.pi], (12, 3))[:, :dim]
        M[0] = A[0]
        got = _differences(kind, A, M)
        assert got.shape == (5, 12, dim)
        for a, g in zip(A, got, strict=True):
            np.testing.assert_array_equal(g, _differences(kind, a, M))
            want = np.array([_difference(kind, a, m)[0] for m in M])
            np.testing.assert_allclose(g, want, atol=1e-9)


def _update_line_ends_reference(ends, lm, f, pose, big, small):
    """geometry.update_line_ends as of d4a6cdb (numpy projections), the reference."""
    from fgslam.slam import geometry as g

    meas = g.measured_ends(f, pose)
    s = g.along(lm, meas)
    if f.endpoints is None:
        if ends is None:
            return g.on_line(lm, s)
        e = g.along(lm, ends)
        return g.on_line(lm, np.array([min(e.min(), s.min()), max(e.max(), s.max())]))
    conds = [f.start, f.end]
    order = np.argsort(s)
    (s0, c0), (s1, c1) = (s[order[0]], conds[order[0]]), (s[order[1]], conds[order[1]])
    if ends is None:
        return g.on_line(lm, np.array([s0, s1]))
    e0, e1 = np.sort(g.along(lm, ends))
    return g.on_line(
        lm,
        np.array([g._move(e0, s0, c0, True, big, small), g._move(e1, s1, c1, False, big, small)]),
    )


def test_segment_end_updates_equal_the_numpy_projections():
    """The scalar end rules (update_line_ends, reproject) equal the numpy reference to
    rounding: laser segments with every end condition, sonar planes, no map ends yet."""
    from fgslam.slam import geometry

    rng = np.random.default_rng(13)
    conds = [None, *End]
    for _ in range(3000):
        lm = rng.uniform([-math.pi, 0.0], [math.pi, 8])
        pose = rng.uniform([-3, -3, -math.pi], [3, 3, math.pi])
        ends = None if rng.random() < 0.2 else rng.uniform(-8, 8, (2, 2))
        z = rng.uniform([-math.pi, 0.5], [math.pi, 6])
        if rng.random() < 0.2:
            f = Feature("line", z, np.eye(2), "sonar")
        else:
            c0, c1 = rng.choice(len(conds), 2)
            f = Feature(
                "line", z, np.eye(2), "laser", rng.uniform(-6, 6, (2, 2)), conds[c0], conds[c1]
            )
        if ends is not None:
            np.testing.assert_allclose(
                geometry.reproject(lm, ends),
                geometry.on_line(lm, geometry.along(lm, ends)),
                atol=1e-12,
            )
            ends = geometry.reproject(lm, ends)
        got = geometry.update_line_ends(ends, lm, f, pose, 0.5, 0.1)
        want = _update_line_ends_reference(ends, lm, f, pose, 0.5, 0.1)
        np.testing.assert_allclose(got, want, atol=1e-12)
