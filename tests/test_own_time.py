"""Sonar measurements at their own time (issue 15, section 2): the interpolated pose, the
factor's Jacobians, and the equality with the paper's scheme when the robot stands still."""

from __future__ import annotations

import math

import gtsam
import numpy as np
import pytest
from conftest import factor_analytic_jacobians, factor_numeric_jacobians

from factors.line import line_residual
from factors.own_time import interpolate_pose, interpolated_factor
from factors.point import point_residual

UNIT2 = gtsam.noiseModel.Unit.Create(2)


def _pose(rng):
    return gtsam.Pose2(rng.uniform(-20, 20), rng.uniform(-20, 20), rng.uniform(-math.pi, math.pi))


def _unicycle(p0, v, w, t, steps=20000):
    """Pose after driving at speed v (m/s) and turn rate w (rad/s) for t s (Euler, fine)."""
    x, y, th = p0.x(), p0.y(), p0.theta()
    dt = t / steps
    for _ in range(steps):
        x += v * dt * math.cos(th + 0.5 * w * dt)
        y += v * dt * math.sin(th + 0.5 * w * dt)
        th += w * dt
    return gtsam.Pose2(x, y, th)


@pytest.mark.parametrize("v, w", [(0.6, 0.0), (0.5, 0.8), (0.3, -2.5), (0.0, 1.0)])
def test_interpolated_pose_is_the_constant_velocity_pose(v, w):
    a = gtsam.Pose2(1.0, -2.0, 2.9)
    b = _unicycle(a, v, w, 1.0)
    for s in (0.0, 0.25, 0.5, 1.0, 1.4):  # 1.4: a reading just after keyframe b
        p, _, _ = interpolate_pose(a, b, s)
        truth = _unicycle(a, v, w, s)
        assert np.allclose([p.x(), p.y()], [truth.x(), truth.y()], atol=1e-7), (
            f"s={s}: {p} vs {truth}"
        )
        assert abs(gtsam.Rot2(p.theta()).between(gtsam.Rot2(truth.theta())).theta()) < 1e-9


def _values(a, b, lm):
    v = gtsam.Values()
    v.insert(1, a)
    v.insert(2, b)
    v.insert(3, np.asarray(lm, dtype=float))
    return v


@pytest.mark.parametrize("kind", ["point", "line"])
def test_interpolated_factor_jacobians(rng, kind):
    residual = point_residual if kind == "point" else line_residual
    for _ in range(60):
        a = _pose(rng)
        b = a.compose(gtsam.Pose2(rng.uniform(-1, 1), rng.uniform(-0.3, 0.3), rng.uniform(-1, 1)))
        s = rng.uniform(-0.2, 1.6)
        if kind == "point":
            lm = np.array([a.x(), a.y()]) + rng.uniform(-5, 5, 2)
            z = np.array([rng.uniform(-math.pi, math.pi), rng.uniform(0.5, 5)])
        else:
            lm = np.array([rng.uniform(-math.pi, math.pi), rng.uniform(0, 25)])
            z = np.array([rng.uniform(-math.pi, math.pi), rng.uniform(0.1, 5)])
        f = interpolated_factor(residual, 1, 2, 3, s, z, UNIT2)
        values = _values(a, b, lm)
        for A, N in zip(
            factor_analytic_jacobians(f, values),
            factor_numeric_jacobians(f, values),
            strict=True,
        ):
            np.testing.assert_allclose(A, N, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("kind", ["point", "line"])
def test_standing_still_equals_the_scan_frame_factor(rng, kind):
    """With both keyframe poses equal, the reading's own-time pose is the keyframe's for any
    s: the factor's error is the plain (paper's scheme) residual at that pose."""
    residual = point_residual if kind == "point" else line_residual
    for _ in range(20):
        a = _pose(rng)
        lm = np.array([a.x(), a.y()]) + rng.uniform(-5, 5, 2)
        z = np.array([rng.uniform(-math.pi, math.pi), rng.uniform(0.5, 5)])
        pose = np.array([a.x(), a.y(), a.theta()])
        for s in (0.0, 0.3, 1.0, 1.5):
            f = interpolated_factor(residual, 1, 2, 3, s, z, UNIT2)
            e = f.unwhitenedError(_values(a, a, lm))
            np.testing.assert_allclose(e, residual(pose, lm, z)[0], atol=1e-12)


# ------------------------------------------------------------------ the front end's own-time data

ROOM_BOX = {
    "walls": [
        {"id": "r", "points": [[-3, -2], [4, -2], [4, 3], [-3, 3]], "closed": True},
        {"id": "b", "points": [[1.5, 0.8], [2.2, 0.8], [2.2, 1.4], [1.5, 1.4]], "closed": True},
    ]
}


def _same(a, b, atol):
    d = np.asarray(a, float) - np.asarray(b, float)
    d[0] = (d[0] + math.pi) % (2 * math.pi) - math.pi
    return np.all(np.abs(d) < atol)


def test_own_time_equals_the_scan_frame_when_standing_still():
    """A robot standing still (sonar only: planes and points): each sonar feature's own-time
    measurement (built from its transducer mount alone) is the scan-frame one (moved
    through the laser frame); laser features have none."""
    from frontend_scenes import run_frontend, scene_events

    evs, _ = scene_events(ROOM_BOX, (0.5, -0.3, 0.4), seed=3)
    feats = [f for sf in run_frontend(evs, "sonar") for f in sf.features]
    assert {f.kind for f in feats} == {"point", "line"}
    for f in feats:
        assert f.own is not None
        assert _same(f.own.z, f.z, 1e-9), (f.kind, f.own.z, f.z)
        np.testing.assert_allclose(f.own.cov, f.cov, rtol=1e-9, atol=1e-15)
    laser = [f for sf in run_frontend(evs, "fused") for f in sf.features]
    assert laser and all(f.own is None for f in laser if f.source != "sonar")


def test_own_time_is_the_reading_before_the_odometry_move():
    """A moving robot (the simulated corridor): each sonar point's own-time measurement, moved
    with the odometry from its reading's time to the scan's, is its scan-frame measurement;
    the reading lies within half a scan period of the scan."""
    from factors.point import point_to_world
    from fgslam.config import load_config
    from fgslam.events import OdometryEvent
    from fgslam.frontend.pipeline import FrontEnd
    from fgslam.frontend.sonar import PoseHistory
    from fgslam.sim.simulate import events, plan_run
    from fgslam.sim.world import load_world

    cfg, w = load_config(), load_world("corridor")
    evs = list(events(w, cfg, plan_run(w, cfg, seed=1, duration=30.0)))
    fe = FrontEnd(cfg, "fused")
    odo = PoseHistory(keep=1e9)
    out = []
    for ev in evs:
        out.extend(fe.add(ev))
        if isinstance(ev, OdometryEvent):
            odo.add(ev.t, fe.odo.pose)
    out.extend(fe.finish())
    moved = 0
    for sf in out:
        for f in sf.features:
            if f.kind != "point":
                continue
            assert abs(f.own.t - sf.t) <= 0.5 * cfg.laser.scan_period + 1e-9
            a, b = odo.at(f.own.t), odo.at(sf.t)
            q, _, _ = point_to_world(a, f.own.z)  # odometry frame
            c, s = math.cos(b[2]), math.sin(b[2])
            dx, dy = q[0] - b[0], q[1] - b[1]
            lx, ly = c * dx + s * dy, -s * dx + c * dy
            assert _same([math.atan2(ly, lx), math.hypot(lx, ly)], f.z, 1e-9)
            moved += np.hypot(*(a[:2] - b[:2])) > 0.01
    assert moved > 20  # the robot moved between many readings and their scans


# ------------------------------------------------------------------ SLAM with own-time sonar


@pytest.mark.parametrize("sensors", ["fused", "sonar"])
def test_slam_with_sonar_at_its_own_time_tracks_the_truth(sensors):
    """iSAM2 on the simulated room with every sonar point (and, sonar only, plane) attached
    at its reading's time: as accurate against the truth as the paper's scan-frame scheme
    (the readings lie within half a scan period of their scan, so the two nearly agree)."""
    from fgslam.config import with_options
    from fgslam.evaluation import metrics as evaluation
    from fgslam.sim.scenes import room_events
    from fgslam.slam.runner import run_backends

    evs, cfg, _ = room_events(0)
    ate, used = {}, {}
    for timing in ("scan-frame", "own-time"):
        c = with_options(cfg, {"sonar": {"timing": timing}})
        (res,) = run_backends(list(evs), c, ["isam2"], sensors)
        ref = evaluation.interpolate_poses(res.truth_t, res.truth, res.times)
        ate[timing] = evaluation.ate(res.poses, ref)["rmse"]
        used[timing] = res.stats.get("sonar_own_time", 0)
    assert used["scan-frame"] == 0 and used["own-time"] > (10 if sensors == "fused" else 300)
    bound = 0.02 if sensors == "fused" else 0.04
    assert ate["own-time"] < bound, ate
    assert ate["own-time"] < 1.2 * ate["scan-frame"] + 0.002, ate


def test_sonar_timing_is_checked():
    from fgslam.config import ConfigError, from_dict, load_config

    d = load_config().to_dict()
    d["sonar"]["timing"] = "later"
    with pytest.raises(ConfigError, match=r"sonar\.timing"):
        from_dict(d)
