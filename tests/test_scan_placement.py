"""Every scan's pose (runner.place_scans): the scans between keyframes follow the graph's
correction of the scan odometry instead of jumping at the next keyframe."""

import numpy as np

from factors.geometry import between_poses, compose_poses
from fgslam.slam.runner import place_scans


def _scene(seed: int, drift_xy: float = 0.03, drift_theta: float = 0.01):
    """A curved true path of keyframes 0.5 m apart with 9 scans between each pair; the scan
    odometry drifts linearly within each interval (its own error per interval) and the
    keyframe estimates are the truth (the graph corrected them)."""
    rng = np.random.default_rng(seed)
    n_kf, per = 12, 9
    truth_kf = [np.zeros(3)]
    steps = []
    for _ in range(n_kf - 1):
        step = np.array([0.5, rng.normal(0, 0.05), rng.normal(0, 0.2)])
        steps.append(step)
        truth_kf.append(compose_poses(truth_kf[-1], step))
    truth_kf = np.array(truth_kf)
    times = np.arange(n_kf, dtype=float)
    between, truth_scans = [], []
    kf_rel = [np.zeros(3)]
    for k, step in enumerate(steps):
        err = np.array(
            [rng.normal(0, drift_xy), rng.normal(0, drift_xy), rng.normal(0, drift_theta)]
        )
        for j in range(1, per + 1):
            a = j / (per + 1)
            true_rel = a * step  # a point along the (constant-curvature) step
            seen = compose_poses(true_rel, a * err)  # the drift so far
            between.append((k + a, k, seen))
            truth_scans.append(compose_poses(truth_kf[k], true_rel))
        kf_rel.append(compose_poses(step, err))
    return times, truth_kf, between, kf_rel, np.array(truth_scans)


def _scan_errors(times, t, p, truth_scans):
    scans = ~np.isin(t, times)
    d = between_poses(p[scans], truth_scans)
    return np.hypot(d[:, 0], d[:, 1]), np.abs(d[:, 2])


def test_scans_follow_the_correction_to_the_next_keyframe():
    for seed in range(5):
        times, kf, between, kf_rel, truth_scans = _scene(seed)
        t0, p0 = place_scans(times, kf, between)  # the scan odometry alone
        t1, p1 = place_scans(times, kf, between, kf_rel)
        assert np.array_equal(t0, t1) and len(t1) == len(times) + len(between)
        assert np.all(np.diff(t1) > 0)
        # the keyframes stay where the estimate put them
        at_kf = np.isin(t1, times)
        np.testing.assert_allclose(p1[at_kf], kf)
        e0, r0 = _scan_errors(times, t0, p0, truth_scans)
        e1, r1 = _scan_errors(times, t1, p1, truth_scans)
        assert e1.mean() < 0.2 * e0.mean(), (seed, e0.mean(), e1.mean())
        assert r1.mean() < 0.2 * r0.mean(), (seed, r0.mean(), r1.mean())
        assert e1.max() < 0.01 and r1.max() < 0.003


def test_no_next_keyframe_or_no_chain_keeps_the_scan_odometry():
    times, kf, between, kf_rel, _ = _scene(7)
    # a backend that stopped early: only the first 4 keyframes estimated
    t, p = place_scans(times[:4], kf[:4], between, kf_rel)
    _, p0 = place_scans(times[:4], kf[:4], between)
    last = t > times[3]  # the scans after the last estimated keyframe
    assert last.any()
    np.testing.assert_allclose(p[last], p0[last])
    assert not np.allclose(p[~last], p0[~last])
    # nothing between: the keyframes alone
    t, p = place_scans(times, kf, [], kf_rel)
    np.testing.assert_allclose(p, kf)
