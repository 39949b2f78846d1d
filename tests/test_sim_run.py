"""The simulated run: the paper's route without collisions, joystick speeds, and odometry whose
drift from the truth matches the configured error model (Monte Carlo over seeds)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from factors.odometry import OdometryParams, integrate_poses, propagate, ticks_to_distances
from fgslam.config import load_config
from fgslam.events import LaserScan, OdometryEvent, SonarReading, TruthPose
from fgslam.sim.scenes import EXACT_WHEELS
from fgslam.sim.sensors import SimParams
from fgslam.sim.simulate import Run, events, plan_run
from fgslam.sim.world import load_world, parse_world

CFG = load_config()


@pytest.fixture(scope="module")
def corridor_run():
    w = load_world("corridor")
    return w, plan_run(w, CFG, seed=3)


def test_corridor_run_is_the_papers_run(corridor_run):
    w, run = corridor_run
    assert run.distance > 150.0
    assert w.clearance(run.poses[:, :2]).min() > 0.3  # robot radius 0.25 m: no collision
    v = np.hypot(*np.diff(run.poses[:, :2], axis=0).T) / CFG.odometry.sample_period
    assert v.max() <= 0.5 + 1e-6
    # it reaches both ends of the corridor and comes back into the lab
    assert run.poses[:, 0].min() < -20 and run.poses[:, 0].max() > 30
    assert 0 < run.poses[-1, 0] < 10 and 0 < run.poses[-1, 1] < 7
    # turns on the spot: heading changes while standing still
    dth = np.abs(np.diff(np.unwrap(run.poses[:, 2])))
    assert np.any((dth > 1e-3) & (v < 1e-3))


def test_pose_at_is_the_pose_at_that_time_between_samples():
    # a scan's pose is the robot's at the scan's own time, not at the nearest encoder sample
    # (half a sample off: 3 mrad at 0.6 rad/s, beyond a corner's modelled bearing error)
    dt = 0.01
    t = dt * np.arange(1, 5)
    poses = np.array(
        [[0.0, 0.0, 3.1], [0.01, 0.0, -3.13], [0.02, 0.01, -3.11], [0.03, 0.01, -3.09]]
    )
    run = Run(t=t, poses=poses, ticks=np.zeros((4, 2), dtype=np.int64), seed=0)
    np.testing.assert_allclose(run.pose_at(0.02), poses[1], atol=1e-12)
    # a quarter of the way from sample 1 to sample 2, and across the +-pi cut the short way
    got = run.pose_at(0.0125)
    turn = (-3.13 + 2 * math.pi) - 3.1
    np.testing.assert_allclose(got[:2], [0.0025, 0.0], atol=1e-12)
    assert got[2] == pytest.approx(3.1 + 0.25 * turn, abs=1e-12)
    np.testing.assert_allclose(run.pose_at(0.0275)[:2], [0.0175, 0.0075], atol=1e-12)
    np.testing.assert_allclose(run.pose_at(-1.0), poses[0])  # clamped at the ends
    np.testing.assert_allclose(run.pose_at(1.0), poses[-1])


def test_duration_limit_and_event_order():
    w = load_world("corridor")
    run = plan_run(w, CFG, seed=1, duration=12.0)
    assert run.duration == pytest.approx(12.0, abs=0.011)
    evs = list(events(w, CFG, run))
    ts = [e.t for e in evs]
    assert ts == sorted(ts)
    kinds = {type(e) for e in evs}
    assert kinds == {OdometryEvent, TruthPose, SonarReading, LaserScan}
    scans = [e for e in evs if isinstance(e, LaserScan)]
    assert len(scans) == pytest.approx(12.0 / CFG.laser.scan_period, abs=2)
    assert all(e.ranges.shape == (361,) for e in scans)
    sonar = [e for e in evs if isinstance(e, SonarReading)]
    assert len(sonar) == pytest.approx(2 * 25 * 12, abs=4)
    pans = np.array([e.pan for e in sonar if e.array == 0])
    assert pans.min() < math.radians(-80) or pans.max() > math.radians(80)  # sweeping
    assert any(e.echoes for e in sonar)


def test_same_seed_same_events():
    w = load_world("corridor")
    a = list(events(w, CFG, plan_run(w, CFG, seed=5, duration=4.0)))
    b = list(events(w, CFG, plan_run(w, CFG, seed=5, duration=4.0)))
    c = list(events(w, CFG, plan_run(w, CFG, seed=6, duration=4.0)))
    assert a == b and a != c


def test_odometry_drift_matches_error_model():
    """Without systematic errors, the drift of odometry from the truth over 100 seeds has the
    covariance that eq 4 propagates (mean NEES ~ 3); with them, odometry is biased."""
    room = {
        "name": "room",
        "walls": [{"id": "r", "points": [[-2, -2], [8, -2], [8, 6], [-2, 6]], "closed": True}],
        "route": [[0, 0], [3, 0], [3, 2.5], [1, 3]],
    }
    w = parse_world(room, "room")
    odo = CFG.odometry
    params = OdometryParams(odo.wheelbase, odo.k_r, odo.k_l, odo.k_d)
    exact = SimParams(**EXACT_WHEELS)

    def drift(seed, sim):
        run = plan_run(w, CFG, seed=seed, params=sim, duration=25.0)
        lr, ll = ticks_to_distances(
            run.ticks[:, 0], run.ticks[:, 1], odo.metres_per_tick_right, odo.metres_per_tick_left
        )
        start = (0.0, 0.0, 0.0)
        end, P, _ = propagate(lr, ll, params, start=start)
        np.testing.assert_allclose(end, integrate_poses(lr, ll, odo.wheelbase, start)[-1])
        e = run.poses[-1] - end
        e[2] = (e[2] + math.pi) % (2 * math.pi) - math.pi
        return e, P

    nees = []
    for seed in range(100):
        e, P = drift(seed, exact)
        nees.append(e @ np.linalg.solve(P, e))
    assert 2.25 < np.mean(nees) < 3.75, np.mean(nees)
    # systematic errors (wheel radii, wheelbase) add a bias that the random model lacks
    biased = [drift(seed, SimParams(wheelbase_error=0.05)) for seed in range(30)]
    nees_b = [e @ np.linalg.solve(P, e) for e, P in biased]
    assert np.mean(nees_b) > 2 * np.mean(nees)
