"""Measurement covariance models: sonar error model, mount conversion, time registration."""

from __future__ import annotations

import math

import numpy as np
import pytest

from factors.geometry import wrap_angles
from factors.point import bearing_range_to_robot_frame
from factors.sensor_models import (
    CORNER_ANGULAR,
    LINE_ANGULAR,
    LaserRangeModel,
    SonarErrorModel,
    time_registration_inflation,
)


def test_sonar_covariance_values():
    m = SonarErrorModel()
    C = m.covariance(3.0)
    np.testing.assert_allclose(C, np.diag([math.radians(2) ** 2, 0.06**2]))
    z, C2 = m.plane_to_line(0.4, 3.0)
    np.testing.assert_allclose(z, [0.4, 3.0])
    np.testing.assert_allclose(C2, C)
    for bad in (-1.0, math.nan, math.inf):
        with pytest.raises(ValueError):
            m.covariance(bad)


def test_sonar_model_monte_carlo():
    """Readings simulated as the model says (bearing noise, speed-of-sound noise scaling the
    range) have the model's covariance."""
    rng = np.random.default_rng(3)
    m = SonarErrorModel()
    r_true, b_true, n = 4.0, 0.3, 20000
    b = b_true + rng.normal(0, m.sigma_bearing, n)
    r = r_true * (1 + rng.normal(0, m.sigma_sound_rel, n))
    S = np.cov(np.vstack([b, r]))
    np.testing.assert_allclose(
        np.sqrt(np.diag(S)), np.sqrt(np.diag(m.covariance(r_true))), rtol=0.05
    )


def test_robot_frame_conversion_monte_carlo():
    """The sensor-to-robot conversion used with the built-in point factor carries the
    covariance correctly (Monte Carlo through the exact map)."""
    rng = np.random.default_rng(5)
    mount = (0.1, 0.2, math.radians(80))
    z = np.array([0.4, 3.0])
    C = SonarErrorModel().covariance(3.0) / 4  # a well-calibrated sonar: small noise
    zr, Cr = bearing_range_to_robot_frame(z, C, mount)
    samples = rng.multivariate_normal(z, C, 20000)
    conv = np.array([bearing_range_to_robot_frame(s, C, mount)[0] for s in samples])
    err = conv - zr
    err[:, 0] = wrap_angles(err[:, 0])
    S = np.cov(err.T)
    np.testing.assert_allclose(np.sqrt(np.diag(S)), np.sqrt(np.diag(Cr)), rtol=0.05)
    # mean map is exact: a point at the predicted robot-frame bearing/range
    a = z[0] + mount[2]
    p = np.array([mount[0] + 3 * math.cos(a), mount[1] + 3 * math.sin(a)])
    np.testing.assert_allclose(zr, [math.atan2(p[1], p[0]), np.hypot(*p)], atol=1e-12)
    # a pure-rotation mount is exact: bearing shifts, covariance unchanged
    zr2, Cr2 = bearing_range_to_robot_frame(z, C, (0.0, 0.0, 0.5))
    np.testing.assert_allclose(zr2, [0.9, 3.0], atol=1e-12)
    np.testing.assert_allclose(Cr2, C, atol=1e-15)


def test_laser_systematic_error():
    m = LaserRangeModel(sigma_range=0.02, systematic_offset=0.01, systematic_per_metre=0.002)
    np.testing.assert_allclose(m.systematic([0.0, 5.0]), [0.01, 0.02])


def test_time_registration_inflation():
    C = np.diag([1e-4, 4e-4])
    out = time_registration_inflation(C, LINE_ANGULAR, speed=0.5, turn_rate=0.2, sigma_t=0.05)
    np.testing.assert_allclose(out, np.diag([1e-4 + 0.01**2, 4e-4 + 0.025**2]))
    C3 = np.eye(3) * 1e-4
    out3 = time_registration_inflation(C3, CORNER_ANGULAR, 0.0, 1.0, 0.1)
    np.testing.assert_allclose(np.diag(out3), [1e-4 + 0.01, 1e-4, 1e-4 + 0.01])
    assert np.all(out3 - np.diag(np.diag(out3)) == 0)
    np.testing.assert_allclose(time_registration_inflation(C, LINE_ANGULAR, 0, 0, 0.05), C)
    with pytest.raises(ValueError):
        time_registration_inflation(C3, LINE_ANGULAR, 0.1, 0.1, 0.05)
    with pytest.raises(ValueError):
        time_registration_inflation(C, LINE_ANGULAR, math.nan, 0.1, 0.05)
