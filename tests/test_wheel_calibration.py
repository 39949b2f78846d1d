"""Wheel calibration as estimated variables (issue 15, section 1): the preintegration's
Jacobian w.r.t. the calibration errors (e_r, e_l, e_b), the calibrated odometry factor, and
the estimate's recovery of a known bias."""

from __future__ import annotations

import dataclasses
import math

import gtsam
import numpy as np
import pytest
from conftest import factor_analytic_jacobians, factor_numeric_jacobians, numeric_jacobian

from factors.geometry import wrap_angle
from factors.odometry import (
    OdometryParams,
    calibrated_delta,
    calibrated_error,
    calibrated_odometry_factor,
    integrate_poses,
    preintegrate,
    propagate,
)
from fgslam.config import load_config, with_scanmatch
from fgslam.evaluation import metrics as evaluation
from fgslam.sim.scenes import NO_LASER_BIAS, PAPER, ROOM
from fgslam.sim.sensors import SimParams
from fgslam.sim.simulate import events, plan_run
from fgslam.sim.world import parse_world
from fgslam.slam.runner import run_backends

BACKENDS = ["ekf", "isam2", "batch"]
PARAMS = OdometryParams(0.5, 0.01, 0.01, 0.005, alpha3=1e-4, alpha5=1e-5)


def random_samples(rng, n: int = 40) -> tuple[np.ndarray, np.ndarray]:
    """Wheel distances of an arc with a changing turn rate (m per sample)."""
    v = rng.uniform(-0.02, 0.05)
    w = rng.uniform(-0.1, 0.1, n).cumsum() * 0.1
    return v + 0.25 * w * 0.5, v - 0.25 * w * 0.5


@pytest.mark.parametrize("seed", range(20))
def test_preintegration_calibration_jacobian_matches_finite_differences(seed):
    """d(x, y, theta)/d(e_r, e_l, e_b): integrating with the wheel distances and the
    wheelbase scaled by (1 + e) moves the end pose by the Jacobian times e."""
    rng = np.random.default_rng(seed)
    lr, ll = random_samples(rng)

    def end(c):
        p = OdometryParams(PARAMS.wheelbase * (1 + c[2]), PARAMS.k_r, PARAMS.k_l, PARAMS.k_d)
        return propagate(lr * (1 + c[0]), ll * (1 + c[1]), p)[0]

    _, _, Jc = propagate(lr, ll, PARAMS)
    np.testing.assert_allclose(Jc, numeric_jacobian(end, np.zeros(3)), atol=1e-7, rtol=1e-5)
    pre = preintegrate(lr, ll, PARAMS)
    np.testing.assert_allclose(pre.calibration_jacobian, Jc)
    c = rng.normal(0, 0.01, 3)  # first order: the error of the prediction is O(|c|^2)
    moved = end(c)
    assert np.abs(calibrated_delta(pre, c) - moved).max() < 50 * np.abs(c).max() ** 2


def test_calibration_jacobian_of_a_straight_line_and_a_turn_on_the_spot():
    """Closed forms: driving straight L metres, x grows by L (e_r + e_l) / 2 and the heading
    by L (e_r - e_l) / D; turning on the spot by phi, the heading grows by
    phi (e_r + e_l) / 2 - phi e_b, and a scale difference drives it along its heading
    (x, y depend on e_r - e_l only)."""
    n, step = 100, 0.01
    _, _, J = propagate(np.full(n, step), np.full(n, step), PARAMS)
    L, D = n * step, PARAMS.wheelbase
    np.testing.assert_allclose(J[0], [L / 2, L / 2, 0.0], atol=1e-12)
    np.testing.assert_allclose(J[2], [L / D, -L / D, 0.0], atol=1e-12)
    _, _, J = propagate(np.full(n, step), np.full(n, -step), PARAMS)
    phi = 2 * L / D
    np.testing.assert_allclose(J[2], [phi / 2, phi / 2, -phi], atol=1e-12)
    np.testing.assert_allclose(J[:2, 2], 0.0, atol=1e-12)
    np.testing.assert_allclose(J[:2, 0], -J[:2, 1], atol=1e-12)
    assert np.abs(J[:2, 0]).max() > 0.05


def _link_case(rng):
    """A random wheel motion and two world poses about that far apart (x, y, theta)."""
    pre = preintegrate(*random_samples(rng), PARAMS)
    pi = np.array([rng.uniform(-9, 9), rng.uniform(-9, 9), rng.uniform(-math.pi, math.pi)])
    rel = np.array([pre.delta.x(), pre.delta.y(), pre.delta.theta()]) + rng.normal(0, 0.05, 3)
    pj = gtsam.Pose2(*pi).compose(gtsam.Pose2(*rel))
    return pre, pi, np.array([pj.x(), pj.y(), pj.theta()])


@pytest.mark.parametrize("seed", range(30))
def test_calibrated_error_jacobians(seed):
    """The error's Jacobians w.r.t. both poses' body tangents and the calibration errors,
    directly and through the GTSAM factor (whitening undone)."""
    rng = np.random.default_rng(100 + seed)
    pre, pi, pj = _link_case(rng)
    c = rng.normal(0, 0.01, 3)
    e, Hi, Hj, Hc = calibrated_error(pi, pj, c, pre)
    # in the wheels' units: of the position, pose j in pose i's frame minus the calibrated
    # motion; of the heading, the poses' turn scaled by the wheelbase error minus the
    # measured turn and its wheel terms; both over the wheels' mean scale
    q = gtsam.Pose2(*pi).between(gtsam.Pose2(*pj))
    want = np.array([q.x(), q.y(), q.theta()]) - calibrated_delta(pre, c)
    Jc = pre.calibration_jacobian
    want[2] = wrap_angle(q.theta() * (1 + c[2]) - pre.delta.theta() - Jc[2, :2] @ c[:2])
    want /= 1 + (c[0] + c[1]) / 2
    np.testing.assert_allclose(e, want, atol=1e-12)

    def at(which, xi):
        poses = [gtsam.Pose2(*pi), gtsam.Pose2(*pj)]
        poses[which] = poses[which].retract(xi)
        a, b = ([p.x(), p.y(), p.theta()] for p in poses)
        return calibrated_error(a, b, c, pre)[0]

    np.testing.assert_allclose(Hi, numeric_jacobian(lambda x: at(0, x), np.zeros(3)), atol=1e-6)
    np.testing.assert_allclose(Hj, numeric_jacobian(lambda x: at(1, x), np.zeros(3)), atol=1e-6)
    Hc_num = numeric_jacobian(lambda x: calibrated_error(pi, pj, x, pre)[0], c)
    np.testing.assert_allclose(Hc, Hc_num, atol=1e-6)
    keys = gtsam.symbol("x", 0), gtsam.symbol("x", 1), gtsam.symbol("c", 0)
    f = calibrated_odometry_factor(
        *keys, pre, gtsam.noiseModel.Gaussian.Covariance(pre.covariance_start)
    )
    values = gtsam.Values()
    values.insert(keys[0], gtsam.Pose2(*pi))
    values.insert(keys[1], gtsam.Pose2(*pj))
    values.insert(keys[2], c)
    np.testing.assert_allclose(f.unwhitenedError(values), e, atol=1e-12)
    for A, N in zip(
        factor_analytic_jacobians(f, values), factor_numeric_jacobians(f, values), strict=True
    ):
        np.testing.assert_allclose(A, N, atol=1e-5, rtol=1e-5)


def test_calibrated_odometry_factor_with_the_wheels_inside_a_longer_calibration(rng):
    """The wheels' (e_r, e_l, e_b) at columns 1:4 of a 5-vector c: the same error as the
    3-vector factor, zero Jacobian in the other columns, checked numerically."""
    pre = preintegrate(*random_samples(rng), PARAMS)
    c5 = rng.normal(0, 0.01, 5)
    values = gtsam.Values()
    values.insert(0, gtsam.Pose2(0.1, -0.2, 0.3))
    values.insert(1, gtsam.Pose2(0.9, 0.1, 0.5))
    values.insert(2, c5)
    noise = gtsam.noiseModel.Gaussian.Covariance(pre.covariance_start)
    f = calibrated_odometry_factor(0, 1, 2, pre, noise, slice(1, 4), 5)
    e, *_ = calibrated_error((0.1, -0.2, 0.3), (0.9, 0.1, 0.5), c5[1:4], pre)
    np.testing.assert_allclose(f.unwhitenedError(values), e, atol=1e-12)
    A = factor_analytic_jacobians(f, values)
    for a, n in zip(A, factor_numeric_jacobians(f, values), strict=True):
        np.testing.assert_allclose(a, n, atol=1e-5, rtol=1e-5)
    np.testing.assert_allclose(A[2][:, [0, 4]], 0)


@pytest.fixture(scope="module")
def biased_room():
    """The room run with wheel radii and wheelbase 2 %, -1.5 % and 2.5 % off their nominal
    values (the laser and sonar without systematic errors: the wheels' alone to find)."""
    cfg = load_config()
    w = parse_world(ROOM, "room")
    p = SimParams(
        radius_error_right=0.02,
        radius_error_left=-0.015,
        wheelbase_error=0.025,
        **NO_LASER_BIAS,
        sound_speed_bias_sigma=0,
    )
    evs = list(events(w, cfg, plan_run(w, cfg, 2, p), p))
    truth = np.array([p.radius_error_right, p.radius_error_left, p.wheelbase_error])
    return evs, cfg, truth


def _run(biased_room, calibration: str, scheme: dict | None = PAPER, backends=None):
    evs, cfg, _ = biased_room
    cfg = with_scanmatch(cfg, scheme)
    odo = dataclasses.replace(cfg.odometry, calibration=calibration, calibration_sigma=(0.05,) * 3)
    out = {}
    las = dataclasses.replace(cfg.laser, calibration="off")  # the wheels' alone to find
    cfg = dataclasses.replace(cfg, odometry=odo, laser=las)
    for res in run_backends(evs, cfg, backends or BACKENDS, "fused"):
        ref = evaluation.interpolate_poses(res.truth_t, res.truth, res.times)
        out[res.backend] = (res, evaluation.ate(res.poses, ref, align=False)["rmse"])
    return out


def test_every_backend_recovers_a_known_wheel_bias(biased_room):
    """Estimated with a prior of 5 % each, the three errors come out within 3 sigma of the
    truth (and within 1 % absolute), and the trajectory is more accurate than with the
    nominal calibration taken as exact."""
    off = _run(biased_room, "off")
    on = _run(biased_room, "wheels")
    truth = biased_room[2]
    for b in BACKENDS:
        res, ate = on[b]
        assert off[b][0].calibration is None
        est = np.array(res.calibration["estimate"])
        sig = np.array(res.calibration["sigma"])
        assert np.all(np.abs(est - truth) < 3 * sig), (b, est, sig)
        assert np.all(np.abs(est - truth) < 0.01), (b, est)
        assert np.all(sig < 0.02), (b, sig)  # learned from the data, not the 5 % prior
        assert ate < 0.7 * off[b][1], (b, ate, off[b][1])


def test_calibration_uncertainty_spreads_the_motion_as_the_jacobian_says():
    """Monte Carlo: wheel distances and wheelbase scaled by (1 + c) with c drawn from a
    prior of 1 % each; the spread of the end poses matches J_c Sigma_c J_c^T."""
    rng = np.random.default_rng(7)
    lr, ll = random_samples(rng, 80)
    _, _, Jc = propagate(lr, ll, PARAMS)
    S = np.diag([0.01, 0.01, 0.01]) ** 2
    ends = []
    for c in rng.multivariate_normal(np.zeros(3), S, 4000):
        p = OdometryParams(PARAMS.wheelbase * (1 + c[2]), 0.0, 0.0, 0.0)
        ends.append(propagate(lr * (1 + c[0]), ll * (1 + c[1]), p)[0])
    C = np.cov(np.array(ends).T)
    want = Jc @ S @ Jc.T
    np.testing.assert_allclose(np.sqrt(np.diag(C)), np.sqrt(np.diag(want)), rtol=0.06)


@pytest.mark.parametrize("seed", range(10))
def test_fusion_with_a_scan_match_carries_the_calibration_jacobian(seed):
    """Fusing calibrated wheels with a scan match: the fused motion moves with the
    calibration errors as its Jacobian says (finite differences through the fusion)."""
    from factors.odometry import fuse_motions, relative_pose, with_calibration

    rng = np.random.default_rng(200 + seed)
    wheels = preintegrate(*random_samples(rng), PARAMS)
    d = np.array([wheels.delta.x(), wheels.delta.y(), wheels.delta.theta()])
    scan = relative_pose(d + rng.normal(0, 0.02, 3), np.diag(rng.uniform(1e-4, 1e-3, 3)))
    fused = fuse_motions(wheels, scan)

    def f(c):  # covariances held at the linearisation point, as every Jacobian here does
        moved = dataclasses.replace(with_calibration(wheels, c), covariance=wheels.covariance)
        m = fuse_motions(moved, scan).delta
        return np.array([m.x(), m.y(), m.theta()])

    J = fused.calibration_jacobian
    np.testing.assert_allclose(J, numeric_jacobian(f, np.zeros(3)), atol=1e-6 * np.abs(J).max())


def test_calibration_is_learned_through_links_fused_with_scan_matches(biased_room):
    """The default scheme (wheels and scan match on every link, keyframes by motion): the
    EKF predicts with their fusion, whose calibration Jacobian carries the wheels' share;
    it and iSAM2 recover the bias within 3 sigma, the EKF tracks far better than without (it
    commits to the biased prediction: 7 -> 1.2 cm), iSAM2 no worse (1.06 -> 1.04 cm: it keeps
    wheels and scan match as two factors, and the scan matches already hold the motion), both
    within 2 cm of the truth."""
    off = _run(biased_room, "off", None, ["ekf", "isam2"])
    on = _run(biased_room, "wheels", None, ["ekf", "isam2"])
    truth = biased_room[2]
    for b in ("ekf", "isam2"):
        res, ate = on[b]
        assert res.stats["keyframes_scan_linked"] > 20
        est = np.array(res.calibration["estimate"])
        sig = np.array(res.calibration["sigma"])
        assert np.all(np.abs(est - truth) < 3 * sig) and np.all(sig < 0.01), (b, est, sig)
        assert ate < (0.5 if b == "ekf" else 1.0) * off[b][1] and ate < 0.02, (b, ate, off[b])


def _straight_and_turns(rng, params: OdometryParams, noise: float, straight: int, turns: int):
    """Keyframes of 21 encoder samples: ``straight`` runs at 0.4 m/s between turns on the spot
    at 0.8 rad/s, the wheelbase and radii exact; returns the true poses (the turns' noise-free
    integration) and each keyframe's preintegration of the wheel distances with relative
    noise ``noise`` per sample."""
    n, dt, D = 21, 0.01, params.wheelbase
    drive = np.full(n, 0.4 * dt), np.full(n, 0.4 * dt)
    turn = np.full(n, 0.4 * D * dt), np.full(n, -0.4 * D * dt)
    true_lr, true_ll, pres = [], [], []
    for k in range(turns * (straight + 1)):
        lr, ll = turn if k % (straight + 1) == straight else drive
        true_lr.append(lr)
        true_ll.append(ll)
        meas = [w * (1 + noise * rng.standard_normal(n)) for w in (lr, ll)]
        pres.append(preintegrate(*meas, params))
    poses = integrate_poses(np.concatenate(true_lr), np.concatenate(true_ll), D)[n - 1 :: n]
    return np.vstack([np.zeros(3), poses]), pres


def test_wheelbase_estimate_is_not_pulled_by_the_wheels_noise():
    """Errors in variables: the poses known (a perfect laser), the wheels exact, only their
    random noise (5 % per sample, forty straight keyframes per turn on the spot): the
    wheelbase error's estimate stays at its true zero over 20 runs (mean within 3 standard
    errors and 1e-3). With the wheelbase term scaling the measured turn, the straight
    keyframes' noise-only turns pulled it to +2.7e-3 (9 standard errors: the fit shrinks the
    turn's scale towards the noise)."""
    rng = np.random.default_rng(11)
    params = OdometryParams(0.42, 0.05, 0.05, 1e-4)
    C = gtsam.symbol("c", 0)
    est = []
    for _ in range(20):
        poses, pres = _straight_and_turns(rng, params, 0.05, straight=40, turns=20)
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        tight = gtsam.noiseModel.Isotropic.Sigma(3, 1e-6)
        for k, p in enumerate(poses):
            graph.add(gtsam.PriorFactorPose2(k, gtsam.Pose2(*p), tight))
            values.insert(k, gtsam.Pose2(*p))
        graph.add(gtsam.PriorFactorVector(C, np.zeros(3), gtsam.noiseModel.Isotropic.Sigma(3, 0.1)))
        values.insert(C, np.zeros(3))
        for k, pre in enumerate(pres):
            noise = gtsam.noiseModel.Gaussian.Covariance(pre.covariance_start)
            graph.add(calibrated_odometry_factor(k, k + 1, C, pre, noise))
        result = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
        est.append(result.atVector(C)[2])
    mean, se = np.mean(est), np.std(est) / math.sqrt(len(est))
    assert abs(mean) < 3 * se and abs(mean) < 1e-3, (mean, se)


@pytest.mark.parametrize("seed", range(10))
def test_a_world_scaled_with_the_wheels_leaves_the_odometry_error_as_it_is(seed):
    """Poses 0.2 % farther apart with the wheels' three errors at +0.2 % read the same wheel
    motion: the error (in the wheels' units) is the unscaled one's to second order (within
    2 % of the difference the poses' units gave, the noise shrunk with the world)."""
    rng = np.random.default_rng(200 + seed)
    pre, pi, pj = _link_case(rng)
    s = 2e-3
    scale = np.array([1 + s, 1 + s, 1.0])
    e0 = calibrated_error(pi, pj, np.zeros(3), pre)[0]
    e1 = calibrated_error(pi * scale, pj * scale, np.full(3, s), pre)[0]
    poses_units = np.array([*(e0[:2] * (1 + s)), e0[2]])  # what the old error gave, to first order
    assert np.abs(e1 - e0).max() < 0.02 * np.abs(poses_units - e0).max() + 1e-9, e1 - e0
