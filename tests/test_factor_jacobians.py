"""Analytic Jacobians of every measurement model and factor against numerical ones."""

from __future__ import annotations

import math

import gtsam
import numpy as np
import pytest
from conftest import factor_analytic_jacobians, factor_numeric_jacobians, numeric_jacobian

from factors.corner import (
    corner_bearing_range_factor,
    corner_factor,
    corner_residual,
    corner_to_world,
    predict_corner,
)
from factors.geometry import wrap_angle
from factors.line import line_factor, line_residual, line_to_world, normalize_line, predict_line
from factors.point import point_factor, point_residual, point_to_world, predict_point

N_CONFIGS = 200
UNIT2 = gtsam.noiseModel.Unit.Create(2)
UNIT3 = gtsam.noiseModel.Unit.Create(3)


def random_pose(rng):
    return np.array([rng.uniform(-20, 20), rng.uniform(-20, 20), rng.uniform(-math.pi, math.pi)])


def random_mount(rng):
    if rng.random() < 0.2:
        return (0.0, 0.0, 0.0)
    return (rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3), rng.uniform(-math.pi, math.pi))


def wrapped_diff(a, b, angular):
    d = np.asarray(a, float) - np.asarray(b, float)
    return np.array([wrap_angle(v) if ang else v for v, ang in zip(d, angular, strict=True)])


def check_world_jacobians(residual, to_world, pose, landmark, meas, mount, angular):
    """A landmark model's plain functions (what the EKF uses) against central differences:
    ``residual``'s Jacobians w.r.t. the pose and the landmark, the inverse model's
    (``to_world``) w.r.t. the pose and the measurement (differences wrapped where
    ``angular``), and the inverse is exact (the residual at the world landmark is zero)."""
    _, H_x, H_l = residual(pose, landmark, meas, mount)
    Nx = numeric_jacobian(lambda p: residual(p, landmark, meas, mount)[0], pose)
    Nl = numeric_jacobian(lambda q: residual(pose, q, meas, mount)[0], landmark)
    np.testing.assert_allclose(H_x, Nx, atol=1e-5)
    np.testing.assert_allclose(H_l, Nl, atol=1e-5)
    w, Hwx, Hwz = to_world(pose, meas, mount)
    Nwx = numeric_jacobian(lambda p: wrapped_diff(to_world(p, meas, mount)[0], w, angular), pose)
    Nwz = numeric_jacobian(lambda m: wrapped_diff(to_world(pose, m, mount)[0], w, angular), meas)
    np.testing.assert_allclose(Hwx, Nwx, atol=1e-5)
    np.testing.assert_allclose(Hwz, Nwz, atol=1e-5)
    np.testing.assert_allclose(residual(pose, w, meas, mount)[0], 0.0, atol=1e-9)


def check_factor(factor, values):
    analytic = factor_analytic_jacobians(factor, values)
    numeric = factor_numeric_jacobians(factor, values)
    for A, N in zip(analytic, numeric, strict=True):
        np.testing.assert_allclose(A, N, atol=1e-5, rtol=1e-5)


# ---------------------------------------------------------------- lines


def line_case(rng, i):
    """Random pose, mount and world line; every 4th has alpha_w near +-pi, every 4th+1 a line
    passing close to the sensor (d near 0, both sides of the flip)."""
    pose, mount = random_pose(rng), random_mount(rng)
    if i % 4 == 0:
        aw = math.pi - rng.uniform(0, 1e-3) if i % 8 == 0 else -math.pi + rng.uniform(0, 1e-3)
    else:
        aw = rng.uniform(-math.pi, math.pi)
    # sensor position in world
    c, s = math.cos(pose[2]), math.sin(pose[2])
    xs = pose[0] + c * mount[0] - s * mount[1]
    ys = pose[1] + s * mount[0] + c * mount[1]
    through_sensor = xs * math.cos(aw) + ys * math.sin(aw)
    if i % 4 == 1:
        dw = through_sensor + rng.uniform(-0.02, 0.02)  # sensor within 2 cm of the line
    else:
        dw = through_sensor + rng.choice([-1, 1]) * rng.uniform(0.3, 8.0)
    aw, dw = normalize_line(aw, dw)
    return pose, mount, np.array([aw, dw])


@pytest.mark.parametrize("flip", [False, True])
def test_line_factor_jacobians(rng, flip):
    for i in range(N_CONFIGS):
        pose, mount, line = line_case(rng, i)
        zp, _, _ = predict_line(pose, line, mount)
        meas = np.array(normalize_line(zp[0], zp[1])) + rng.normal(0, [0.01, 0.01])
        if flip:  # same line, other parametrisation of the measurement
            meas = np.array([wrap_angle(meas[0] + math.pi), -meas[1]])
        values = gtsam.Values()
        values.insert(0, gtsam.Pose2(*pose))
        values.insert(1, line)
        f = line_factor(0, 1, meas, UNIT2, mount)
        e = f.unwhitenedError(values)
        assert np.all(np.abs(e) < 0.1), (e, pose, line, meas)  # residual small on both forms
        check_factor(f, values)


def test_line_world_jacobians(rng):
    """Jacobians of the plain functions (what the EKF uses) w.r.t. world coordinates."""
    for i in range(N_CONFIGS):
        pose, mount, line = line_case(rng, i)
        meas = np.array([rng.uniform(-math.pi, math.pi), rng.uniform(0.1, 8)])
        e, H_x, H_l = line_residual(pose, line, meas, mount)
        Nx = numeric_jacobian(lambda p: line_residual(p, line, meas, mount)[0], pose)
        Nl = numeric_jacobian(lambda l_: line_residual(pose, l_, meas, mount)[0], line)
        if abs(abs(e[0]) - math.pi / 2) < 1e-3:
            continue  # the parametrisation switch itself is not differentiable
        np.testing.assert_allclose(H_x, Nx, atol=1e-5)
        np.testing.assert_allclose(H_l, Nl, atol=1e-5)
        w, Hwx, Hwz = line_to_world(pose, meas, mount)
        if abs(w[1]) < 1e-4 or abs(abs(w[0]) - math.pi) < 1e-4:
            continue  # at the d = 0 flip or the angle wrap the inverse is not differentiable
        Nwx = numeric_jacobian(lambda p: line_to_world(p, meas, mount)[0], pose)
        Nwz = numeric_jacobian(lambda m: line_to_world(pose, m, mount)[0], meas)
        np.testing.assert_allclose(Hwx, Nwx, atol=1e-5)
        np.testing.assert_allclose(Hwz, Nwz, atol=1e-5)
        # the inverse is exact: predicting the world line gives back the measurement
        e_back, _, _ = line_residual(pose, w, meas, mount)
        np.testing.assert_allclose(e_back, 0.0, atol=1e-9)


def test_line_residual_same_for_both_parametrisations(rng):
    for i in range(N_CONFIGS):
        pose, mount, line = line_case(rng, i)
        meas = np.array([rng.uniform(-math.pi, math.pi), rng.uniform(0.0, 8)])
        other = np.array([line[0] + math.pi, -line[1]])
        e1 = line_residual(pose, line, meas, mount)[0]
        e2 = line_residual(pose, other, meas, mount)[0]
        np.testing.assert_allclose(e1, e2, atol=1e-9)


def test_line_prediction_geometry():
    """A wall x = 5 seen from (1, 0) facing +y through a laser mounted 0.5 m ahead."""
    e, _, _ = line_residual((1.0, 0.0, math.pi / 2), (0.0, 5.0), (0.0, 0.0), (0.5, 0.0, 0.0))
    # sensor at (1, 0.5) heading +y: wall normal is at -90 deg, distance 4
    np.testing.assert_allclose(e, [-math.pi / 2, 4.0], atol=1e-12)


# ---------------------------------------------------------------- corners


def corner_case(rng):
    pose, mount = random_pose(rng), random_mount(rng)
    rel = rng.uniform(0.2, 8.0)
    ang = rng.uniform(-math.pi, math.pi)
    corner = np.array(
        [pose[0] + rel * math.cos(ang), pose[1] + rel * math.sin(ang), rng.uniform(-4, 4)]
    )
    corner[2] = wrap_angle(corner[2])
    if rng.random() < 0.25:  # bisector or bearing right at the wrap
        corner[2] = math.pi - 1e-4
    return pose, mount, corner


def corner_values(pose, corner, c=None) -> gtsam.Values:
    """Values with the pose at key 0, the corner at 1 and, if given, calibration c at 9."""
    values = gtsam.Values()
    values.insert(0, gtsam.Pose2(*pose))
    values.insert(1, gtsam.Pose2(*corner))
    if c is not None:
        values.insert(9, c)
    return values


def test_corner_factor_jacobians(rng):
    for _ in range(N_CONFIGS):
        pose, mount, corner = corner_case(rng)
        z, _, _ = predict_corner(pose, corner, mount)
        meas = z + rng.normal(0, [0.01, 0.01, 0.01])
        values = corner_values(pose, corner)
        check_factor(corner_factor(0, 1, meas, UNIT3, mount), values)
        check_factor(corner_bearing_range_factor(0, 1, meas[:2], UNIT2, mount), values)


def test_corner_world_jacobians(rng):
    for _ in range(N_CONFIGS):
        pose, mount, corner = corner_case(rng)
        meas = predict_corner(pose, corner, mount)[0] + rng.normal(0, 0.01, 3)
        check_world_jacobians(
            corner_residual, corner_to_world, pose, corner, meas, mount, (False, False, True)
        )


def test_corner_prediction_geometry():
    # robot at origin facing +x, corner vertex at (3, 4) whose bisector points to -x (world)
    e, _, _ = corner_residual((0, 0, 0), (3.0, 4.0, math.pi), (0, 0, 0))
    np.testing.assert_allclose(e, [math.atan2(4, 3), 5.0, math.pi], atol=1e-12)


# ---------------------------------------------------------------- points


def test_point_world_jacobians(rng):
    for _ in range(N_CONFIGS):
        pose, mount, corner = corner_case(rng)
        point = corner[:2]
        meas = predict_point(pose, point, mount)[0] + rng.normal(0, 0.01, 2)
        check_world_jacobians(
            point_residual, point_to_world, pose, point, meas, mount, (False, False)
        )


def test_point_factor_matches_model(rng):
    """The built-in factor with the mount handled gives zero error at the truth and the same
    error as the plain model (to first order) near it; its Jacobians are checked too."""
    for _ in range(N_CONFIGS):
        pose, mount, corner = corner_case(rng)
        point = corner[:2]
        z = predict_point(pose, point, mount)[0]
        values = gtsam.Values()
        values.insert(0, gtsam.Pose2(*pose))
        values.insert(1, point)
        f = point_factor(0, 1, z, np.eye(2), mount)
        np.testing.assert_allclose(f.unwhitenedError(values), 0.0, atol=1e-9)
        check_factor(point_factor(0, 1, z + rng.normal(0, 0.01, 2), np.eye(2), mount), values)


# ---------------------------------------------------------------- calibrated measurements


def test_calibrated_factors_read_the_measurement_moved_by_the_calibration(rng):
    """A line or corner factor with a calibration variable c (z = h + J c): its error is the
    plain factor's for the measurement z - J c, and its Jacobians (c's too) are checked
    numerically."""
    for i in range(60):
        c = rng.normal(0, 0.01, 5)
        pose, mount, line = line_case(rng, i)
        zp, _, _ = predict_line(pose, line, mount)
        meas = np.array(normalize_line(zp[0], zp[1])) + rng.normal(0, [0.01, 0.01])
        J = rng.normal(size=(2, 5))
        values = gtsam.Values()
        values.insert(0, gtsam.Pose2(*pose))
        values.insert(1, line)
        values.insert(9, c)
        f = line_factor(0, 1, meas, UNIT2, mount, cal_key=9, cal_jacobian=J)
        plain = line_factor(0, 1, meas - J @ c, UNIT2, mount)
        np.testing.assert_allclose(f.unwhitenedError(values), plain.unwhitenedError(values))
        check_factor(f, values)
        pose, mount, corner = corner_case(rng)
        z, _, _ = predict_corner(pose, corner, mount)
        meas = z + rng.normal(0, [0.01, 0.01, 0.01])
        J = rng.normal(size=(3, 5))
        values = corner_values(pose, corner, c)
        for dim, make in ((3, corner_factor), (2, corner_bearing_range_factor)):
            unit = UNIT3 if dim == 3 else UNIT2
            f = make(0, 1, meas[:dim], unit, mount, cal_key=9, cal_jacobian=J[:dim])
            plain = make(0, 1, meas[:dim] - J[:dim] @ c, unit, mount)
            e, e0 = f.unwhitenedError(values), plain.unwhitenedError(values)
            np.testing.assert_allclose(wrapped_diff(e, e0, [True, False, True][:dim]), 0, atol=1e-9)
            check_factor(f, values)


def test_scale_columns_are_taken_at_the_prediction(rng):
    """With a gain (factors.calibrated.scale_gain) for c's scale column, a line's, corner's and
    point's error is e (1 + G c) + J c: a world scaled by (1 + s) seen with the scale error s
    gives the same error as the true world with none (the measurement's noise is not shrunk
    with the world), which J taken at the measurement alone does not; Jacobians checked
    numerically, c's included."""
    from factors.calibrated import scale_gain

    s = 0.01
    no_mount = (0.0, 0.0, 0.0)  # (a mount would not scale with the world)
    for i in range(20):
        pose, _, line = line_case(rng, i)
        zp, _, _ = predict_line(pose, line, no_mount)
        meas = np.array(normalize_line(zp[0], zp[1])) + rng.normal(0, [0.01, 0.01])
        J = np.zeros((2, 2))
        J[1] = [1.0, meas[1]]  # an offset's and a scale's Jacobian on d
        G = scale_gain(J, meas, [1])
        # the true world read with the scale error s, and the world (1 + s) times larger
        # read without: the same ranges; the error must not tell them apart
        true_w, scaled_w = gtsam.Values(), gtsam.Values()
        for vals, k, c in ((true_w, 1.0, s), (scaled_w, 1.0 + s, 0.0)):
            vals.insert(0, gtsam.Pose2(pose[0] * k, pose[1] * k, pose[2]))
            vals.insert(1, np.array([line[0], line[1] * k]))
            vals.insert(9, np.array([0.0, c]))
        f = line_factor(0, 1, meas, UNIT2, no_mount, cal_key=9, cal_jacobian=J, cal_gain=G)
        plain = line_factor(0, 1, meas, UNIT2, no_mount, cal_key=9, cal_jacobian=J)
        e_scaled = f.unwhitenedError(scaled_w)
        np.testing.assert_allclose(f.unwhitenedError(true_w), e_scaled, atol=1e-12)
        noise = normalize_line(zp[0], zp[1])[1] - meas[1]  # the reading's error on d
        gap = abs(plain.unwhitenedError(true_w)[1] - e_scaled[1])
        assert gap == pytest.approx(s * abs(noise), rel=0.05)  # the noise shrunk with s
        check_factor(f, true_w)
    pose, mount, corner = corner_case(rng)
    z, _, _ = predict_corner(pose, corner, mount)
    meas = z + rng.normal(0, [0.01, 0.01, 0.01])
    J = rng.normal(size=(3, 2))
    values = corner_values(pose, corner, np.array([0.003, 0.02]))
    check_factor(corner_factor(0, 1, meas, UNIT3, mount, 9, J, scale_gain(J, meas, [1])), values)
    assert scale_gain(J, meas, []) is None and scale_gain(J, [0.1, -1.0, 0.0], [1]) is None
