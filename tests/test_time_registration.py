"""A scan's time error modelled once per scan (``[laser] time_registration = "per-scan"``):
the motion's Jacobians numerically, its covariance by Monte Carlo, the graph's poses at the
scans' true times against the simulator's truth, the filter's per-feature stand-in against
the front end's."""

from __future__ import annotations

import math

import gtsam
import numpy as np
import pytest

from factors.geometry import between_poses, compose_poses
from factors.odometry import (
    OdometryParams,
    preintegrate,
    time_registration_jacobians,
    with_time_registration,
)
from fgslam.config import load_config, with_options, with_scanmatch
from fgslam.evaluation import metrics as evaluation
from fgslam.frontend.pipeline import FrontEnd
from fgslam.frontend.sonar import PoseHistory
from fgslam.sim.scenes import PAPER
from fgslam.sim.sensors import SimParams
from fgslam.sim.simulate import events, plan_run, true_scan_time
from fgslam.sim.world import load_world
from fgslam.slam.ekf import EkfBackend
from fgslam.slam.graph_keys import X
from fgslam.slam.graph_solve import GraphSolution
from fgslam.slam.runner import run_backends


def _later(pose, twist, dt):
    """``pose`` moved on by ``dt`` s at the body twist (v, omega) (an arc)."""
    v, w = twist
    th = w * dt
    if abs(w) < 1e-12:
        step = (v * dt, 0.0, 0.0)
    else:
        r = v / w
        step = (r * math.sin(th), r * (1 - math.cos(th)), th)
    return compose_poses(pose, np.array(step))


def test_time_registration_jacobians_numerically(rng):
    for _ in range(50):
        a, b = rng.uniform(-3, 3, 3), rng.uniform(-3, 3, 3)
        ta, tb = rng.uniform(-1.5, 1.5, 2), rng.uniform(-1.5, 1.5, 2)
        d0 = between_poses(a, b)
        ja, jb = time_registration_jacobians(d0, ta, tb)
        h = 1e-6
        for twist_end, jac in ((False, ja), (True, jb)):
            moved = [
                between_poses(a, _later(b, tb, s))
                if twist_end
                else between_poses(_later(a, ta, s), b)
                for s in (h, -h)
            ]
            num = (moved[0] - moved[1]) / (2 * h)
            num[2] = (math.remainder(moved[0][2] - moved[1][2], 2 * math.pi)) / (2 * h)
            np.testing.assert_allclose(jac, num, atol=1e-6)


def test_time_registered_motion_covariance_by_monte_carlo(rng):
    """The wheel motion between two stamps as the motion between the scans' true times: its
    covariance against the spread of the relative pose with both scans' times drawn."""
    params = OdometryParams(wheelbase=0.5, k_r=0.01, k_l=0.01, k_d=0.01)
    lr, ll = np.full(20, 0.01), np.full(20, 0.012)
    pre = preintegrate(lr, ll, params)
    d = np.array([pre.delta.x(), pre.delta.y(), pre.delta.theta()])
    ta, tb, sig = (0.8, 0.6), (1.1, -0.9), 0.03
    out = with_time_registration(pre, ta, tb, sig)
    n = 20000
    da, db = rng.normal(0, sig, n), rng.normal(0, sig, n)
    wheel = rng.multivariate_normal(np.zeros(3), pre.covariance_start, n)
    samples = np.array(
        [
            between_poses(_later(np.zeros(3), ta, x), _later(d + e, tb, y))
            for x, y, e in zip(da, db, wheel, strict=True)
        ]
    )
    emp = np.cov(samples.T)
    se = np.sqrt((emp**2 + np.outer(np.diag(emp), np.diag(emp))) / n)  # sampling error
    assert np.all(np.abs(emp - out.covariance_start) < 5 * se + 1e-9), (emp, out.covariance_start)
    assert np.linalg.norm(out.covariance_start - pre.covariance_start) > 10 * np.abs(se).max()


def test_velocity_is_signed():
    h = PoseHistory()
    for k in range(30):  # backing up while turning clockwise, heading 0.3 rad
        t = 0.01 * k
        th = 0.3 - 0.5 * t
        h.add(t, np.array([-0.4 * t * math.cos(0.3), -0.4 * t * math.sin(0.3), th]))
    v, w = h.velocity(0.29)
    assert v == pytest.approx(-0.4, rel=0.01) and w == pytest.approx(-0.5, rel=1e-6)


def test_reported_covariance_gains_the_motion_over_the_time_error():
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    cov = np.diag([1e-4, 4e-4, 1e-5])
    th = 0.7
    graph.add(
        gtsam.PriorFactorPose2(
            X(0), gtsam.Pose2(1, 2, th), gtsam.noiseModel.Gaussian.Covariance(cov)
        )
    )
    values.insert(X(0), gtsam.Pose2(1, 2, th))
    u = np.array([0.02, 0.0, 0.01])  # sigma_t (v, 0, omega)
    plain = GraphSolution(graph, values, [0.0], {}).trajectory()[0][2]
    spread = GraphSolution(graph, values, [0.0], {}, time_spread={0: u}).trajectory()[0][2]
    w = np.array([0.02 * math.cos(th), 0.02 * math.sin(th), 0.01])
    np.testing.assert_allclose(spread - plain, np.outer(w, w), atol=1e-12)


@pytest.fixture(scope="module")
def late_scans():
    """60 s of the corridor with a laser whose stamps are late by 0-0.2 s (sigma 58 ms about
    the mean the front end takes off), its sigma_time configured to match."""
    cfg = with_options(load_config(), {"laser": {"delay_min": 0.0, "delay_max": 0.2}})
    w = load_world("corridor")
    sim = SimParams()
    evs = list(events(w, cfg, plan_run(w, cfg, 1, sim, 60.0), sim))
    est = with_options(cfg, {"laser": {"sigma_time": 0.2 / math.sqrt(12)}})
    return evs, est


def test_per_scan_graph_poses_are_the_robots_at_the_scans_true_times(late_scans):
    evs, cfg = late_scans
    cfg = with_options(cfg, {"laser": {"time_registration": "per-scan"}})
    (res,) = run_backends(evs, with_scanmatch(cfg, PAPER), ["isam2"], "fused")
    true_t = np.array([true_scan_time(cfg, t) for t in res.times])
    at_true = evaluation.interpolate_poses(res.truth_t, res.truth, true_t)
    at_stamp = evaluation.interpolate_poses(res.truth_t, res.truth, res.times)
    e_true = evaluation.ate(res.poses, at_true, align=False)["rmse"]
    e_stamp = evaluation.ate(res.poses, at_stamp, align=False)["rmse"]
    assert e_true < 0.02 and e_true < 0.7 * e_stamp, (e_true, e_stamp)
    # the reported covariance is the pose's at the keyframe's time t: with the time term,
    # the truth at the stamp is inside its 99 % bound about as often as it should be
    nees = evaluation.nees(res.poses, np.array(res.covs), at_stamp)
    assert nees["mean"] < 6.0, nees


def test_filter_inflates_the_features_as_the_front_end_does(late_scans):
    evs, cfg = late_scans
    # the laser at the robot's centre: the front end inflates in the laser's frame, the filter
    # in the robot's (where the time error turns the robot); so the two frames are one
    cfg = with_options(cfg, {"laser": {"mount": {"x": 0.0, "y": 0.0, "yaw_deg": 0.0}}})
    fe_feature = FrontEnd(cfg, "laser")
    fe_scan = FrontEnd(with_options(cfg, {"laser": {"time_registration": "per-scan"}}), "laser")
    ekf = EkfBackend(time_sigma=cfg.laser.sigma_time)
    speeds = []
    real = fe_scan.process_scan

    def spy(scan, v, w):
        speeds.append((v, w))
        return real(scan, v, w)

    fe_scan.process_scan = spy
    a = [sf for ev in evs[: len(evs) // 3] for sf in fe_feature.add(ev)]
    b = [sf for ev in evs[: len(evs) // 3] for sf in fe_scan.add(ev)]
    checked = inflated = 0
    for sa, sb, speed in zip(a, b, speeds, strict=True):
        fb = ekf.time_registered(sb.features, speed)
        assert [f.kind for f in sa.features] == [f.kind for f in fb]
        for f1, f2, f0 in zip(sa.features, fb, sb.features, strict=True):
            s2 = np.sqrt(np.diag(f2.cov))
            np.testing.assert_allclose(f2.cov, f1.cov, rtol=1e-9, atol=1e-15)
            checked += 1
            inflated += bool(np.any(s2 > 1.05 * np.sqrt(np.diag(f0.cov))))
    assert checked > 200 and inflated > 50, (checked, inflated)
