"""Odometry model (paper eqs 1-5): integration, covariance propagation, preintegration."""

from __future__ import annotations

import math

import gtsam
import numpy as np
import pytest

from factors.geometry import wrap_angles
from factors.odometry import (
    OdometryIntegrator,
    OdometryParams,
    integrate_poses,
    preintegrate,
    propagate,
    sample_wheel_noise,
    step_jacobians,
    ticks_to_distances,
)

PARAMS = OdometryParams(wheelbase=0.42, k_r=0.1, k_l=0.1, k_d=0.1)
N_PATHS = 4000


def nominal_path() -> tuple[np.ndarray, np.ndarray]:
    """5 s at 100 Hz: straight, an arc to the left, a turn on the spot, an arc right."""
    v = np.concatenate([np.full(150, 0.4), np.full(150, 0.3), np.zeros(100), np.full(100, 0.35)])
    w = np.concatenate([np.zeros(150), np.full(150, 0.6), np.full(100, 1.2), np.full(100, -0.5)])
    dt, D = 0.01, PARAMS.wheelbase
    return (v + w * D / 2) * dt, (v - w * D / 2) * dt


def test_straight_and_spot_turn_geometry():
    x, y, th = integrate_poses([0.01] * 100, [0.01] * 100, 0.42)[-1]
    np.testing.assert_allclose([x, y, th], [1.0, 0.0, 0.0], atol=1e-12)
    # a quarter turn on the spot: each wheel travels D*pi/8 in opposite directions
    arc = 0.42 * math.pi / 8 / 50
    x, y, th = integrate_poses([arc] * 50, [-arc] * 50, 0.42)[-1]
    np.testing.assert_allclose([x, y, th], [0.0, 0.0, math.pi / 4], atol=1e-12)
    # REP-103: driving forward after turning left moves the robot toward +y
    p = integrate_poses([0.01] * 100, [0.01] * 100, 0.42, start=(0, 0, math.pi / 2))[-1]
    np.testing.assert_allclose(p, [0.0, 1.0, math.pi / 2], atol=1e-12)


def test_step_jacobians_numeric(rng):
    from conftest import numeric_jacobian

    for _ in range(50):
        th, lr, ll, D = rng.uniform(-3, 3), rng.uniform(-0.01, 0.01), rng.uniform(-0.01, 0.01), 0.42

        def step(state, u):
            return integrate_poses([u[0]], [u[1]], u[2], start=state)[-1]

        F, G = step_jacobians(th, lr, ll, D)
        np.testing.assert_allclose(
            F,
            numeric_jacobian(lambda s: step(s, (lr, ll, D)), np.array([1.0, 2.0, th])),
            atol=1e-8,
        )
        np.testing.assert_allclose(
            G,
            numeric_jacobian(lambda u: step((1.0, 2.0, th), u), np.array([lr, ll, D])),
            atol=1e-8,
        )


@pytest.fixture(scope="module")
def monte_carlo():
    rng = np.random.default_rng(2024)
    lr, ll = nominal_path()
    nr, nl, nd = sample_wheel_noise(lr, ll, PARAMS, N_PATHS, rng)
    ends = integrate_poses(nr, nl, nd)[:, -1, :]
    return lr, ll, ends


def test_monte_carlo_pose_covariance(monte_carlo):
    """Sample covariance of the end pose against eq 4 propagation: every std within 10 %."""
    lr, ll, ends = monte_carlo
    mean, P = propagate(lr, ll, PARAMS)
    nominal = integrate_poses(lr, ll, PARAMS.wheelbase)[-1]
    np.testing.assert_allclose(mean, nominal, atol=1e-12)
    assert abs(mean[2]) > 1.0  # the path turns: the test exercises the heading coupling
    err = ends - nominal
    S = np.cov(err.T)
    np.testing.assert_allclose(np.sqrt(np.diag(S)), np.sqrt(np.diag(P)), rtol=0.10)
    assert np.all(np.abs(np.linalg.eigvals(np.linalg.solve(P, S)).real - 1.0) < 0.15)


def test_monte_carlo_between_factor_covariance(monte_carlo):
    """The preintegrated covariance is the covariance of GTSAM's between-factor residual."""
    lr, ll, ends = monte_carlo
    pre = preintegrate(lr, ll, PARAMS)
    delta = pre.delta
    # residual of a BetweenFactorPose2(measured=true motion) at each noisy relative pose
    errs = np.array([delta.localCoordinates(gtsam.Pose2(*e)) for e in ends])
    S = np.cov(errs.T)
    np.testing.assert_allclose(np.sqrt(np.diag(S)), np.sqrt(np.diag(pre.covariance)), rtol=0.10)
    # and a factor built from it evaluates exactly that residual
    f = pre.factor(0, 1)
    v = gtsam.Values()
    v.insert(0, gtsam.Pose2())
    v.insert(1, gtsam.Pose2(*ends[0]))
    np.testing.assert_allclose(f.unwhitenedError(v), errs[0], atol=1e-12)

    # full-matrix check: the eigenvalues of P^-1 S are all near 1 with the factor's
    # covariance, and far from 1 with the unrotated covariance in keyframe-1 axes
    def ratio_eigs(P):
        return np.linalg.eigvals(np.linalg.solve(P, S)).real

    assert np.all(np.abs(ratio_eigs(pre.covariance) - 1.0) < 0.15)
    assert np.any(np.abs(ratio_eigs(pre.covariance_start) - 1.0) > 1.0)


def test_integrator_matches_batch(rng):
    lr, ll = nominal_path()
    integ = OdometryIntegrator(PARAMS, t0=0.0)
    for k, (r, l) in enumerate(zip(lr, ll, strict=True)):
        integ.add(0.01 * (k + 1), r, l)
    pre = integ.keyframe()
    ref = preintegrate(lr, ll, PARAMS)
    np.testing.assert_allclose(pre.delta.matrix(), ref.delta.matrix(), atol=1e-12)
    np.testing.assert_allclose(pre.covariance, ref.covariance, atol=1e-15)
    np.testing.assert_allclose(
        integ.pose, integrate_poses(lr, ll, PARAMS.wheelbase)[-1], atol=1e-12
    )
    v, w = integ.velocity
    assert v == pytest.approx(0.35, rel=1e-9) and w == pytest.approx(-0.5, rel=1e-9)
    # chaining keyframes composes to the whole motion
    integ2 = OdometryIntegrator(PARAMS)
    total = gtsam.Pose2()
    for k, (r, l) in enumerate(zip(lr, ll, strict=True)):
        integ2.add(0.01 * k, r, l)
        if k % 97 == 96:
            total = total.compose(integ2.keyframe().delta)
    total = total.compose(integ2.keyframe().delta)
    np.testing.assert_allclose(total.matrix(), ref.delta.matrix(), atol=1e-9)
    empty = integ2.keyframe()
    assert empty.n_samples == 0 and np.all(np.linalg.eigvalsh(empty.covariance) > 0)


@pytest.mark.parametrize(
    "t, lr, ll",
    [(0.5, 0.01, 0.01), (1.0, math.nan, 0.0), (1.0, 0.0, math.inf), (math.nan, 0.0, 0.0)],
)
def test_integrator_rejects_bad_samples(t, lr, ll):
    integ = OdometryIntegrator(PARAMS, t0=0.9)
    integ.add(0.9, 0.0, 0.0)  # zero period is allowed (duplicate timestamp)
    with pytest.raises(ValueError):
        integ.add(t, lr, ll)
    assert np.all(np.isfinite(integ.pose)) and integ.t == 0.9  # state untouched


def test_batch_functions_reject_nonfinite():
    with pytest.raises(ValueError):
        propagate([0.01, math.nan], [0.01, 0.01], PARAMS)
    with pytest.raises(ValueError):
        integrate_poses([0.01, math.inf], [0.01, 0.01], 0.42)
    with pytest.raises(ValueError):
        preintegrate([0.01], [-math.inf], PARAMS)
    with pytest.raises(ValueError):
        ticks_to_distances([1, 2], [1, math.nan], 1e-4, 1e-4)
    with pytest.raises(ValueError):
        integrate_poses([0.01], [0.01], 0.0)
    with pytest.raises(ValueError):
        OdometryParams(wheelbase=-1, k_r=0.1, k_l=0.1, k_d=0.1)


def test_ticks_to_distances():
    mpt = 2 * math.pi * 0.075 / 2000
    lr, ll = ticks_to_distances([2000, -10], [1000, 0], mpt, mpt)
    np.testing.assert_allclose(lr, [2 * math.pi * 0.075, -10 * mpt])
    np.testing.assert_allclose(ll, [math.pi * 0.075, 0.0])


def test_heading_is_wrapped_in_preintegration():
    arc = 0.42 * math.pi / 2 / 100  # 1.5 turns in total
    pre = preintegrate([arc] * 300, [-arc] * 300, PARAMS)
    # 3 pi of turning wraps to pi
    assert abs(wrap_angles(pre.delta.theta() - 3 * math.pi)) < 1e-9
    assert -math.pi < pre.delta.theta() <= math.pi
