"""Offline point SLAM in two passes (fgslam.slam.pointslam ``resolve_scale``): associate with a
generous odometry model, then smooth again with the data's own, the association fixed."""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_point_calibration import park, park_truth

from fgslam.io.readers.victoria import Sighting, Step, VictoriaPark
from fgslam.slam.pointslam import relabelled, run_points


def _error(poses: np.ndarray) -> float:
    """RMS position error (m) against the park's truth, in the frame of the first pose."""
    truth = park_truth()
    c, s = math.cos(truth[0, 2]), math.sin(truth[0, 2])
    d = truth[:, :2] - truth[0, :2]
    local = np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]])
    return float(np.sqrt(np.mean(np.sum((poses[:, :2] - local) ** 2, axis=1))))


def test_relabelled_takes_the_own_ids_and_drops_the_rest():
    cov = np.eye(2)
    data = VictoriaPark(
        steps=[Step(0, 1, np.array([1.0, 0.0, 0.0]), np.eye(3))],
        sightings={
            0: [Sighting(0, 7, np.array([1.0, 2.0]), cov), Sighting(0, 8, np.zeros(2), cov)],
            1: [Sighting(1, 7, np.array([0.0, 2.0]), cov)],
        },
    )
    out = relabelled(data, [(0, 0, 3), (0, 1, -1), (1, 0, -1)])
    assert out.steps is data.steps
    assert list(out.sightings) == [0]
    (s,) = out.sightings[0]
    assert s.landmark == 3 and np.array_equal(s.xy, [1.0, 2.0])
    assert [x.landmark for x in data.sightings[0]] == [7, 8]  # the input is not changed


@pytest.mark.parametrize(("backend", "seed"), [("ekf", 0), ("ekf", 1), ("isam2", 0)])
def test_second_pass_with_the_honest_model_is_more_accurate(backend, seed):
    """Odometry exactly as noisy as stated: associating with 100x its variances works, but
    the estimate then under-weights the odometry; the second pass with the stated model,
    the same association, is more accurate, within reach of the given association."""
    data = park(1.0, seed=seed)
    one = run_points(data, backend, "own", odometry_scale=100.0)
    two = run_points(data, backend, "own", odometry_scale=100.0, resolve_scale=1.0)
    best = run_points(data, backend, "given")
    assert two.assigned == one.assigned and two.sighting_ids == one.sighting_ids
    assert np.all(two.odometry_scale == 1.0) and two.stats["resolve_seconds"] > 0
    e_one, e_two, e_best = _error(one.poses), _error(two.poses), _error(best.poses)
    assert e_two < 0.75 * e_one, (e_one, e_two)
    assert e_two < 2.5 * e_best, (e_two, e_best)


def test_resolve_needs_the_own_association():
    with pytest.raises(ValueError, match="own association"):
        run_points(park(1.0), "ekf", "given", resolve_scale=1.0)
