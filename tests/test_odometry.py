"""Odometry model (paper eqs 1-5): integration, covariance propagation, preintegration."""

from __future__ import annotations

import itertools
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
    mean, P, _ = propagate(lr, ll, PARAMS)
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


# ------------------------------------------------------------------ motion error model, holes

ALPHA = OdometryParams(
    wheelbase=0.42,
    k_r=0.02,
    k_l=0.02,
    k_d=0.02,
    alpha1=0.01,
    alpha2=0.004,
    alpha3=0.002,
    alpha4=0.001,
    alpha5=0.001,
)


def test_motion_jacobian_numeric(rng):
    """The motion Jacobian against finite differences of one step with along-track, lateral
    and turn errors (e_t, e_l, e_r): ds + e_t along th + (dth + e_r)/2, e_l across it."""
    from conftest import numeric_jacobian

    from factors.odometry import motion_jacobian

    for _ in range(30):
        th, lr, ll, D = rng.uniform(-3, 3), rng.uniform(-0.05, 0.05), rng.uniform(-0.05, 0.05), 0.42
        ds, dth = 0.5 * (lr + ll), (lr - ll) / D

        def step(e):
            a = th + 0.5 * (dth + e[2])
            return np.array(
                [
                    (ds + e[0]) * math.cos(a) - e[1] * math.sin(a),
                    (ds + e[0]) * math.sin(a) + e[1] * math.cos(a),
                    th + dth + e[2],
                ]
            )

        np.testing.assert_allclose(
            motion_jacobian(th, lr, ll, D), numeric_jacobian(step, np.zeros(3)), atol=1e-8
        )


def test_monte_carlo_motion_error_model():
    """Sample covariance of noisy runs (wheel noise and the motion error model) against the
    propagated covariance, on the turning path: stds within 10 %, eigenvalues of P^-1 S
    within 15 % of 1; the model's lateral and turn terms make it much larger than eq 5's."""
    from factors.odometry import sample_paths

    rng = np.random.default_rng(77)
    lr, ll = nominal_path()
    ends = sample_paths(lr, ll, ALPHA, N_PATHS, rng)
    mean, P, _ = propagate(lr, ll, ALPHA)
    S = np.cov((ends - mean).T)
    np.testing.assert_allclose(np.sqrt(np.diag(S)), np.sqrt(np.diag(P)), rtol=0.10)
    assert np.all(np.abs(np.linalg.eigvals(np.linalg.solve(P, S)).real - 1.0) < 0.15)
    base = OdometryParams(0.42, 0.02, 0.02, 0.02)
    assert np.trace(propagate(lr, ll, base)[1]) < 0.5 * np.trace(P)


def test_motion_error_model_does_not_depend_on_the_sampling():
    """The same motion cut into 10 or 1000 samples: the same covariance (to 2 %) with the
    motion error model alone (eq 5's per-sample noise would shrink 100 times)."""
    only = OdometryParams(
        0.42, 0.0, 0.0, 0.0, alpha1=0.01, alpha2=0.004, alpha3=0.002, alpha4=0.001, alpha5=0.001
    )
    P = [propagate(np.full(n, 1.2 / n), np.full(n, 0.8 / n), only)[1] for n in (10, 1000)]
    np.testing.assert_allclose(np.diag(P[0]), np.diag(P[1]), rtol=0.02, atol=1e-12)


def test_integrator_uses_the_same_model():
    lr, ll = nominal_path()
    integ = OdometryIntegrator(ALPHA)
    for i, (r, l) in enumerate(zip(lr, ll, strict=True)):
        integ.add(0.01 * (i + 1), r, l)
    np.testing.assert_allclose(
        integ.keyframe().covariance, preintegrate(lr, ll, ALPHA).covariance, rtol=1e-9
    )


def test_odometry_hole_covariance():
    """Samples every 0.01 s up to 1.0 s, then none until 4.1 s while keyframes come every
    0.3 s: each second of the 3.1 s hole is counted once over the keyframe intervals (the
    first keyframe that sees the gap longer than the 0.5 s tolerance takes what came
    before), each with the covariance of (1 m/s, 1 rad/s) over its part; the interval where
    the samples resume takes the rest, its heading error moving the motion after it
    sideways. A gap between two samples inside one keyframe interval (no keyframe in it: a
    pause of everything, not an odometry hole) adds nothing."""
    p = OdometryParams(
        0.42, 0.05, 0.05, 0.1, hole_tolerance=0.5, hole_speed=1.0, hole_turn_rate=1.0
    )
    t_all = np.concatenate([0.01 * np.arange(1, 101), 4.1 + 0.01 * np.arange(20)])
    kf = np.concatenate([[0.0, 1.0], 1.0 + 0.3 * np.arange(1, 11), [4.3]])
    last, total, pres = None, 0.0, []
    for t0, t1 in itertools.pairwise(kf):
        sel = (t_all > t0) & (t_all <= t1)
        n = int(sel.sum())
        pre = preintegrate(np.full(n, 0.004), np.full(n, 0.004), p, t_all[sel], (t0, t1), last)
        if n:
            last = t_all[sel][-1]
        total += pre.hole_seconds
        pres.append(pre)
    assert total == pytest.approx(3.1)
    assert pres[0].hole_seconds == 0.0 and pres[1].hole_seconds == 0.0  # 0.3 s: not yet
    assert pres[2].hole_seconds == pytest.approx(0.6)  # 1.6 - 1.0, first seen at 1.6 s
    assert pres[3].hole_seconds == pytest.approx(0.3)
    assert np.diag(pres[3].covariance) == pytest.approx([0.09, 0.09, 0.09], rel=1e-5)
    resume = pres[-1]  # (4.0, 4.3]: 0.1 s of hole, then 4 cm driven straight
    plain = preintegrate(np.full(20, 0.004), np.full(20, 0.004), p)
    d = np.diag(resume.covariance_start - plain.covariance_start)
    assert resume.hole_seconds == pytest.approx(0.1)
    assert d[0] == pytest.approx(0.01, rel=1e-3) and d[2] == pytest.approx(0.01, rel=1e-3)
    assert d[1] > 0.01  # the hole's heading error, carried through the 8 cm after it
    inner = np.concatenate([0.01 * np.arange(1, 11), 3.1 + 0.01 * np.arange(10)])
    lr = ll = np.full(20, 0.004)
    pause = preintegrate(lr, ll, p, times=inner, span=(0.0, 3.2), last_sample=0.0)
    assert pause.hole_seconds == 0.0
    np.testing.assert_allclose(pause.covariance, preintegrate(lr, ll, p).covariance)


def test_default_configuration_params_unchanged():
    """The paper robot's configuration gives eq 5 alone: no motion error model terms (and
    the floor of one encoder tick, 2 pi 0.075 / 2000 m, per wheel)."""
    from fgslam.config import load_config

    p = load_config().odometry.params()
    tick = 2 * np.pi * 0.075 / 2000
    assert p == OdometryParams(
        0.42,
        0.05,
        0.05,
        0.1,
        hole_tolerance=p.hole_tolerance,
        resolution_right=tick,
        resolution_left=tick,
    )
    assert not p.has_motion_model
