"""The EKF's update by the nonzero columns of H equals the textbook dense update."""

from __future__ import annotations

import math

import numpy as np
import pytest

from factors.geometry import wrap_angle
from fgslam.frontend.features import Feature
from fgslam.slam import models
from fgslam.slam.ekf import EkfBackend


def _filled(rng, calibration):
    be = EkfBackend(gate_p=None, calibration=np.eye(3) * 1e-4 if calibration else None)
    be.start(0.0, np.array([0.3, -0.2, 0.4]), np.diag([1e-3, 1e-3, 1e-4]))
    for lid in range(12):
        kind = ("line", "corner", "point")[lid % 3]
        if kind == "line":
            z = np.array([rng.uniform(-math.pi, math.pi), rng.uniform(0.5, 5)])
        elif kind == "corner":
            z = np.array([rng.uniform(-1.5, 1.5), rng.uniform(1, 5), rng.uniform(-3, 3)])
        else:
            z = np.array([rng.uniform(-1.5, 1.5), rng.uniform(1, 5)])
        be.add_landmark(lid, Feature(kind, z, np.eye(len(z)) * 1e-3))
    A = rng.normal(size=(be.x.size, be.x.size)) * 0.03
    be.P = be.P + A @ A.T  # correlated, positive definite
    return be


def _dense(be, cols, Hc, e, R):
    H = np.zeros((len(e), be.x.size))
    H[:, cols] = Hc
    S = H @ be.P @ H.T + R
    K = be.P @ H.T @ np.linalg.inv(S)
    x = be.x - K @ e
    P = be.P - K @ S @ K.T
    return x, P


def _same_state(be, x, P):
    d = be.x - x
    d[be._angles] = [wrap_angle(v) for v in d[be._angles]]
    np.testing.assert_allclose(d, 0, atol=1e-12)
    np.testing.assert_allclose(be.P, 0.5 * (P + P.T), atol=1e-12)


@pytest.mark.parametrize("calibration", [False, True])
def test_observe_equals_the_dense_update(rng, calibration):
    be = _filled(rng, calibration)
    for lid in (0, 1, 2, 7):
        o, kind = be.index[lid]
        n = models.DIM[kind]
        z = models.residual(kind, be.x[:3], be.x[o : o + n], np.zeros(n))[0]  # predicted
        z = z + rng.normal(size=n) * 0.05
        f = Feature(kind, z, np.eye(n) * 2e-3)
        e, Hx, Hl = models.residual(kind, be.x[:3], be.x[o : o + n], f.z)
        cols = np.r_[0:3, o : o + n]
        x, P = _dense(be, cols, np.hstack([Hx, Hl]), e, f.cov)
        be.observe(lid, f)
        _same_state(be, x, P)


def test_merge_equals_the_dense_update(rng):
    be = _filled(rng, False)
    ok, kind = be.index[2]
    od, _ = be.index[5]
    e, Hb = models.difference(kind, be.x[ok : ok + 2], be.x[od : od + 2])
    H = np.zeros((2, be.x.size))
    H[:, ok : ok + 2], H[:, od : od + 2] = np.eye(2), Hb
    R = np.eye(2) * 1e-10
    S = H @ be.P @ H.T + R
    K = be.P @ H.T @ np.linalg.inv(S)
    IKH = np.eye(be.x.size) - K @ H
    x = be.x - K @ e
    P = IKH @ be.P @ IKH.T + K @ R @ K.T  # Joseph form
    keep = np.ones(be.x.size, dtype=bool)
    keep[od : od + 2] = False
    be.merge(2, 5)
    d = be.x - x[keep]
    d[be._angles] = [wrap_angle(v) for v in d[be._angles]]
    np.testing.assert_allclose(d, 0, atol=1e-9)
    np.testing.assert_allclose(be.P, P[np.ix_(keep, keep)], atol=1e-9)
    # the angles index follows the removal: every line's alpha and corner's theta, and the pose
    ang = [2] + [o + i for o, k in be.index.values() for i, a in enumerate(models.ANGULAR[k]) if a]
    assert sorted(ang) == be._angles.tolist()
