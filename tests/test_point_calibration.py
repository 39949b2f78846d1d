"""Self-calibration of the odometry noise of a point-landmark run
(fgslam.slam.point_calibration): the maximum-likelihood scales recover the true ones on
synthetic runs whose odometry is noisier than its stated covariance."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fgslam.io.readers.odometry import relative
from fgslam.io.readers.victoria import Sighting, Step, VictoriaPark
from fgslam.slam.point_calibration import fit_scale, scaled_covariance, sighting_nll
from fgslam.slam.pointslam import association_agreement, run_points, self_calibrate

STATED = np.diag([0.02, 0.01, 0.002]) ** 2  # the covariance every step claims


def park(true_scale, seed: int = 0, laps: int = 2, per_lap: int = 200) -> VictoriaPark:
    """A robot circling (radius 18 m) among 20 trees, odometry noise of variance
    ``true_scale`` times the stated one (per component), sightings (sigma 0.1 m, as stated)
    of the trees ahead within 15 m; the given landmark index is the tree."""
    rng = np.random.default_rng(seed)
    trees = np.array(
        [[r * math.cos(a), r * math.sin(a)] for r in (12, 24) for a in np.linspace(0, 6.28, 10)]
    )
    n = laps * per_lap
    truth = park_truth(laps, per_lap)
    sig = np.sqrt(np.broadcast_to(np.asarray(true_scale, float), (3,)) * np.diag(STATED))
    data = VictoriaPark()
    for k in range(n + 1):
        if k:
            d = relative(truth[k - 1], truth[k])
            data.steps.append(Step(k - 1, k, d + sig * rng.standard_normal(3), STATED))
        p = truth[k]
        c, s = math.cos(p[2]), math.sin(p[2])
        for j, t in enumerate(trees):
            dx, dy = t - p[:2]
            xy = np.array([c * dx + s * dy, -s * dx + c * dy])
            if np.hypot(*xy) < 15 and xy[0] > 0:
                z = xy + 0.1 * rng.standard_normal(2)
                data.sightings.setdefault(k, []).append(Sighting(k, 100 + j, z, np.eye(2) * 0.01))
    return data


def park_truth(laps: int = 2, per_lap: int = 200) -> np.ndarray:
    """The true poses of :func:`park` (world frame; the first is (18, 0, pi/2))."""
    a = np.linspace(0, 2 * math.pi * laps, laps * per_lap + 1)
    return np.column_stack([18 * np.cos(a), 18 * np.sin(a), a + math.pi / 2])


def given(data: VictoriaPark) -> dict[tuple[int, int], int]:
    return {(i, q): s.landmark for i, v in data.sightings.items() for q, s in enumerate(v)}


def test_scaled_covariance_keeps_correlations():
    c = np.array([[4.0, 1.0, 0.2], [1.0, 1.0, 0.1], [0.2, 0.1, 0.01]])
    s = scaled_covariance(c, (9.0, 4.0, 100.0))
    assert np.allclose(np.diag(s), [36.0, 4.0, 1.0])
    corr = lambda m: m / np.sqrt(np.outer(np.diag(m), np.diag(m)))
    assert np.allclose(corr(s), corr(c))
    assert np.allclose(scaled_covariance(c, 2.0), 2 * c)


def test_likelihood_counts_every_sighting_after_the_first_of_its_landmark():
    data = park(1.0)
    nll, m = sighting_nll(data, given(data), 1.0)
    n = sum(len(v) for v in data.sightings.values())
    assert m == n - 20 and math.isfinite(nll)
    # an unused sighting (id -1) drops out
    a = given(data)
    a[next(iter(a))] = -1
    assert sighting_nll(data, a, 1.0)[1] in (m - 1, m)


@pytest.mark.parametrize("true_scale", [1.0, 25.0])
def test_fit_recovers_a_common_scale(true_scale):
    data = park(true_scale, seed=1)
    s = fit_scale(data, given(data))
    assert s[0] == s[1] == s[2]
    assert abs(math.log(s[0] / true_scale)) < math.log(1.3)


def test_fit_recovers_per_component_scales():
    true = np.array([25.0, 1.0, 100.0])
    data = park(true, seed=2)
    s = fit_scale(data, given(data), per_component=True)
    assert np.all(np.abs(np.log(s / true)) < math.log(1.6)), s
    # one common scale explains these data worse
    s1 = fit_scale(data, given(data))
    assert sighting_nll(data, given(data), s)[0] < sighting_nll(data, given(data), s1)[0]


def test_self_calibration_with_own_association():
    """From the stated (25x too small) covariance, own association and refits settle near
    the true scale; the point path runs with it on request ("self")."""
    data = park(25.0, seed=3)
    cal = self_calibrate(data, rounds=4)
    assert abs(math.log(cal.scale[0] / 25.0)) < math.log(1.5), cal.history
    assert cal.history[0]["scale_used"] == [1.0, 1.0, 1.0]
    r = run_points(data, "ekf", "own", odometry_scale="self", limit=100)
    assert r.odometry_scale[0] > 3.0  # calibrated on the first 100 steps, not the stated 1
    assert association_agreement(r.assigned)["purity"] == 1.0
    assert np.all(run_points(data, "ekf", "given", limit=10).odometry_scale == 1.0)
    with pytest.raises(ValueError, match="odometry_scale"):
        run_points(data, "ekf", "own", odometry_scale="hand", limit=10)
