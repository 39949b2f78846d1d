"""Relative-pose measurements besides wheel odometry (scan matches, loop closures): their
covariance conventions, their fusion for the EKF, and the graph's relative-pose covariance,
each against Monte Carlo or GTSAM's own solution."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from factors.odometry import (
    fuse_motions,
    link_motions,
    motion_mahalanobis,
    relative_pose,
)
from fgslam.slam.graph import GraphBackend


def _spd(rng, scale):
    A = rng.standard_normal((3, 3)) * scale
    return A @ A.T + np.eye(3) * scale**2 * 0.1


def _sample(m, rng, n):
    """Poses m.delta * exp(xi), xi ~ N(0, m.covariance) (GTSAM's between convention)."""
    L = np.linalg.cholesky(m.covariance)
    xi = rng.standard_normal((n, 3)) @ L.T
    return [m.delta.retract(x) for x in xi]


def test_relative_pose_start_covariance_by_monte_carlo():
    rng = np.random.default_rng(1)
    C = np.diag([0.02, 0.005, 0.01]) ** 2
    C[0, 2] = C[2, 0] = 0.5 * 0.02 * 0.01
    m = relative_pose([1.0, 0.4, 1.1], C)
    poses = _sample(m, rng, 40000)
    xy = np.array([[p.x(), p.y(), p.theta()] for p in poses])
    emp = np.cov(xy.T)
    # covariance_start: the same uncertainty in keyframe 1's axes
    assert np.allclose(emp, m.covariance_start, rtol=0.05, atol=0.03 * np.abs(emp).max())
    # and not the between-convention matrix (they differ by the rotation)
    assert not np.allclose(emp, m.covariance, rtol=0.05, atol=0.03 * np.abs(emp).max())


def test_fusion_equals_the_two_factor_graph():
    """Two between factors solved by GTSAM (X0 fixed) give the fused mean and covariance."""
    rng = np.random.default_rng(2)
    for _ in range(5):
        a = relative_pose([0.5, 0.05, 0.2], _spd(rng, 0.03))
        b = relative_pose(
            [0.5 + 0.02 * rng.standard_normal(), 0.05, 0.2 + 0.01 * rng.standard_normal()],
            _spd(rng, 0.02),
        )
        f = fuse_motions(a, b)
        g = gtsam.NonlinearFactorGraph()
        g.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(), gtsam.noiseModel.Isotropic.Sigma(3, 1e-9)))
        for m in (a, b):
            g.add(m.factor(0, 1))
        v = gtsam.Values()
        v.insert(0, gtsam.Pose2())
        v.insert(1, b.delta)
        sol = gtsam.LevenbergMarquardtOptimizer(g, v).optimize()
        x1 = sol.atPose2(1)
        assert np.allclose(
            [x1.x(), x1.y(), x1.theta()], [f.delta.x(), f.delta.y(), f.delta.theta()], atol=2e-4
        )
        cov = gtsam.Marginals(g, sol).marginalCovariance(1)
        assert np.allclose(cov, f.covariance, rtol=0.02, atol=0.01 * np.abs(cov).max())


def test_a_link_keeps_the_scan_alone_when_they_disagree():
    """link_motions: wheels 30 sigma from the scan match (slipped, or frozen) leave the link
    to the scan; within the gate both stay, and the EKF's fusion of them lies between."""
    C = np.diag([0.01, 0.01, 0.005]) ** 2
    wheels = relative_pose([0.5, 0.0, 0.0], C)
    scan = relative_pose([0.8, 0.0, 0.3], C)
    assert motion_mahalanobis(wheels, scan) > 100
    w, s = link_motions(wheels, scan, 7.8)
    assert w is None and s is scan
    near = relative_pose([0.505, 0.0, 0.002], C)
    w, s = link_motions(wheels, near, 7.8)
    assert w is wheels and s is near
    m = fuse_motions(wheels, near)
    assert 0.5 < m.delta.x() < 0.505  # between the two, halfway for equal covariances
    assert np.allclose(m.covariance, C / 2, rtol=0.05)
    # frozen wheels: no motion with (almost) no uncertainty against a turn the scans saw
    frozen = relative_pose([0.0, 0.0, 0.0], np.eye(3) * 1e-12)
    assert link_motions(frozen, scan, 16.27)[0] is None


@pytest.mark.parametrize("j", [0, 1])
def test_graph_relative_covariance_by_monte_carlo(j):
    """GraphBackend.relative: the current (predicted) pose in keyframe j's frame and its
    covariance, checked by sampling the joint marginal and the new odometry."""
    rng = np.random.default_rng(3 + j)
    be = GraphBackend()
    be.start(0.0, np.array([1.0, -2.0, 0.7]), np.diag([0.01, 0.02, 0.01]) ** 2)
    be.commit()
    motions = [
        relative_pose([1.0, 0.1, 0.3], np.diag([0.05, 0.02, 0.03]) ** 2),
        relative_pose([0.8, -0.2, 0.6], np.diag([0.04, 0.03, 0.02]) ** 2),
        relative_pose([0.5, 0.0, -0.4], np.diag([0.03, 0.02, 0.04]) ** 2),
    ]
    for i, m in enumerate(motions[:-1]):
        be.predict(float(i + 1), m)
        be.commit()
    last = motions[-1]
    be.predict(9.0, last)
    r, C = be.relative(j)
    kp = be.k - 1
    from fgslam.slam.graph_keys import X

    A = be.isam.calculateEstimatePose2(X(j))
    B = be.isam.calculateEstimatePose2(X(kp))
    J = be.isam.jointMarginalCovariance([X(j), X(kp)]).fullMatrix()
    n = 20000
    xi = rng.multivariate_normal(np.zeros(6), J, n)
    e = rng.multivariate_normal(np.zeros(3), last.covariance, n)
    samples = np.empty((n, 3))
    for s in range(n):
        a, b = A.retract(xi[s, :3]), B.retract(xi[s, 3:])
        rs = a.between(b).compose(last.delta.retract(e[s]))
        samples[s] = r.localCoordinates(rs)
    emp = np.cov(samples.T)
    assert np.allclose(samples.mean(axis=0), 0.0, atol=4 * np.sqrt(np.diag(C) / n) + 1e-4)
    assert np.allclose(emp, C, atol=0.06 * np.abs(C).max())


def test_pose_helpers_agree_with_gtsam():
    """factors.geometry's vectorised SE(2) helpers against gtsam.Pose2, across the wrap."""
    from factors.geometry import between_poses, compose_poses, invert_pose, transform_points

    rng = np.random.default_rng(9)
    a = rng.uniform([-5, -5, -np.pi], [5, 5, np.pi], (50, 3))
    b = rng.uniform([-5, -5, -np.pi], [5, 5, np.pi], (50, 3))
    c, d = compose_poses(a, b), between_poses(a, b)
    for i in range(50):
        A, B = gtsam.Pose2(*a[i]), gtsam.Pose2(*b[i])
        for got, want in ((c[i], A.compose(B)), (d[i], A.between(B))):
            assert np.allclose(got[:2], [want.x(), want.y()], atol=1e-12)
            assert abs(np.remainder(got[2] - want.theta() + np.pi, 2 * np.pi) - np.pi) < 1e-12
            assert -np.pi <= got[2] <= np.pi
        inv = A.inverse()
        assert np.allclose(invert_pose(a[i])[:2], [inv.x(), inv.y()], atol=1e-12)
        p = rng.normal(size=(4, 2))
        want = np.array([A.transformFrom(q) for q in p])
        assert np.allclose(transform_points(a[i], p), want, atol=1e-12)


def test_the_ekf_predicts_with_the_scan_alone_where_the_two_disagree():
    """The filter's rule (link_motions inside EkfBackend.predict): agreeing wheels and scan
    are fused; disagreeing ones leave the prediction to the scan match, counted."""
    from fgslam.slam.ekf import EkfBackend

    C = np.diag([0.01, 0.01, 0.005]) ** 2
    wheels = relative_pose([0.5, 0.0, 0.0], C)
    for scan, expect, counted in (
        (relative_pose([0.505, 0.0, 0.002], C), None, 0),
        (relative_pose([0.8, 0.0, 0.3], C), [0.8, 0.0, 0.3], 1),
    ):
        be = EkfBackend()
        be.start(0.0, np.zeros(3), np.zeros((3, 3)))
        be.predict(1.0, wheels, scan)
        want = expect or [
            (f := fuse_motions(wheels, scan)).delta.x(),
            f.delta.y(),
            f.delta.theta(),
        ]
        assert np.allclose(be.x[:3], want, atol=1e-9)
        assert be.stats["motion_disagreements"] == counted


def test_the_graph_keeps_both_and_the_landmarks_decide():
    """A wrong scan match (a person walking ahead, a bare corridor: 0.4 m short, with a
    confident covariance) against right wheels, with two point landmarks seen from every
    keyframe: the graph keeps both as robust factors and ends near the truth, where the
    EKF, which must commit to the scan match, ends 0.4 m off."""
    from fgslam.frontend.features import Feature
    from fgslam.slam.ekf import EkfBackend

    truth = [np.array([0.5 * k, 0.0, 0.0]) for k in range(6)]
    marks = {1: np.array([1.5, 2.0]), 2: np.array([1.0, -2.0])}
    Cw = np.diag([0.01, 0.005, 0.005]) ** 2
    Cs = np.diag([0.01, 0.005, 0.003]) ** 2
    R = np.diag([0.01, 0.02]) ** 2  # (bearing rad, range m)

    def point(pose, lm) -> Feature:
        d = lm - pose[:2]
        z = np.array([np.arctan2(d[1], d[0]) - pose[2], np.hypot(*d)])
        return Feature("point", z, R, "laser")

    final = {}
    for be in (GraphBackend(), EkfBackend()):
        be.start(0.0, truth[0], np.eye(3) * 1e-8)
        for lid, lm in marks.items():
            be.add_landmark(lid, point(truth[0], lm))
        be.commit()
        for k in range(1, 6):
            wheels = relative_pose([0.5, 0.0, 0.0], Cw)
            step = 0.1 if k == 3 else 0.5  # one wrong scan match
            be.predict(float(k), wheels, relative_pose([step, 0.0, 0.0], Cs))
            for lid, lm in marks.items():
                be.observe(lid, point(truth[k], lm))
            be.commit()
        final[be.name] = be.pose()
    assert np.linalg.norm(final["isam2"][:2] - truth[-1][:2]) < 0.05, final
    assert np.linalg.norm(final["ekf"][:2] - truth[-1][:2]) > 0.1, final
