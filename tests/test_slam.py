"""SLAM: map management rules, the three backends on a small simulated run with known
answers, robustness to bad logs, and the outputs."""

from __future__ import annotations

import dataclasses
import json
import math
from types import SimpleNamespace

import numpy as np
import pytest

from fgslam.config.robot import MapParams
from fgslam.evaluation import metrics as evaluation
from fgslam.events import LaserScan, OdometryEvent
from fgslam.frontend.features import End, Feature
from fgslam.sim.scenes import EXACT_WHEELS, NO_CLUTTER, NO_LASER_BIAS, room_events
from fgslam.slam import models
from fgslam.slam.ekf import EkfBackend
from fgslam.slam.outputs import write_outputs
from fgslam.slam.runner import run_backends
from fgslam.slam.step import SlamStep


@pytest.fixture(scope="module")
def room_results():
    evs, cfg, _ = room_events(0)
    return run_backends(list(evs), cfg, ["ekf", "isam2", "batch"], "fused")


def _truth(res):
    return evaluation.interpolate_poses(res.truth_t, res.truth, res.times)


def test_backends_track_the_truth_and_agree(room_results):
    ekf, isam, batch = room_results
    for res in room_results:
        a = evaluation.ate(res.poses, _truth(res))
        odo = evaluation.ate(res.odometry, _truth(res))
        assert a["rmse"] < 0.05 and a["max"] < 0.12, (res.backend, a)
        assert a["rmse"] < odo["rmse"]
        assert len(res.landmarks) >= 6
    # the three estimators agree (same front end, near-identical associations)
    for other in (isam, batch):
        d = np.hypot(*(other.poses[:, :2] - ekf.poses[:, :2]).T)
        assert np.percentile(d, 95) < 0.05
    d = np.hypot(*(batch.poses[:, :2] - isam.poses[:, :2]).T)
    assert d.max() < 0.05


def test_consistent_when_the_errors_match_the_models():
    """With only the random errors the models describe (no systematic laser, odometry or
    speed-of-sound errors, no mixed pixels, phantoms or misclassifications), every backend's
    pose NEES is near its 3 degrees of freedom; with the simulator's systematic errors the
    estimates are overconfident (experiments/README.md, consistency_sources.py)."""
    import dataclasses

    from fgslam.config import load_config
    from fgslam.sim.scenes import ROOM
    from fgslam.sim.sensors import SimParams
    from fgslam.sim.simulate import events, plan_run
    from fgslam.sim.world import parse_world

    cfg = load_config()
    # nor the scan matches' model-error floor (errors of real surfaces the simulator has not)
    sm = dataclasses.replace(cfg.scanmatch, model_error_xy=0.0, model_error_theta_deg=0.0)
    # nor a range offset to estimate: the paper's laser model (its worst-case term)
    las = dataclasses.replace(cfg.laser, calibration="off")
    cfg = dataclasses.replace(cfg, scanmatch=sm, laser=las)
    w = parse_world(ROOM, "room")
    p = SimParams(**EXACT_WHEELS, **NO_LASER_BIAS, **NO_CLUTTER, sound_speed_bias_sigma=0)
    evs = list(events(w, cfg, plan_run(w, cfg, 1, p), p))
    for res in run_backends(evs, cfg, ["ekf", "isam2", "batch"], "fused"):
        n = evaluation.nees(res.poses, np.array(res.covs), _truth(res))
        assert 1.5 < n["mean"] < 6.0 and n["within_95"] > 0.8, (res.backend, n)


def test_outputs(room_results, tmp_path):
    res = room_results[1]
    rep = write_outputs(res, tmp_path)
    _, poses = evaluation.read_tum(tmp_path / "trajectory.tum")
    np.testing.assert_allclose(poses[:, :2], res.poses[:, :2], atol=1e-5)
    np.testing.assert_allclose(np.cos(poses[:, 2] - res.poses[:, 2]), 1.0, atol=1e-8)
    lines = (tmp_path / "trajectory.tum").read_text().splitlines()
    assert len(lines[0].split()) == 8 and lines[0].split()[3] == "0.000000"
    m = json.loads((tmp_path / "map.json").read_text())
    kinds = {lm["kind"] for lm in m["landmarks"]}
    assert {"line", "corner"} <= kinds
    for lm in m["landmarks"]:
        assert lm["covariance"] is not None and "observations" in lm
        if lm["kind"] == "line":
            assert len(lm["endpoints"]) == 2
    r = json.loads((tmp_path / "report.json").read_text())
    for key in (
        "backend",
        "sensors",
        "poses",
        "landmarks",
        "wall_time_s",
        "log_duration_s",
        "keyframe_latency_ms",
        "ate",
        "final_pose_error",
        "nees",
    ):
        assert key in r
    assert r == json.loads(json.dumps(rep))
    assert (tmp_path / "map.png").stat().st_size > 10000


@pytest.mark.parametrize("sensors", ["laser", "sonar"])
def test_sensor_modes_run(sensors):
    evs, cfg, _ = room_events(0, 20.0)
    for res in run_backends(list(evs), cfg, ["ekf", "isam2"], sensors):
        assert len(res.every_scan[0]) > 50  # a pose at every scan (keyframes by motion)
        if sensors == "sonar":
            assert not any(lm.observations.get("laser") for lm in res.landmarks.values())


def test_landmarks_off_keeps_scan_matching_and_tracks_the_truth():
    """``[map] landmarks = false``: no landmark enters the graph, the keyframes come by motion
    alone (not one per scan for want of map support), and scan matching still beats the
    wheels against the truth."""
    evs, cfg, _ = room_events(0, 40.0)
    cfg = dataclasses.replace(cfg, map=dataclasses.replace(cfg.map, landmarks=False))
    on = run_backends(list(evs), room_events(0, 40.0)[1], ["isam2"], "laser")[0]
    (off,) = run_backends(list(evs), cfg, ["isam2"], "laser")
    assert len(on.landmarks) >= 4 and len(off.landmarks) == 0
    assert off.stats["keyframes_map_support"] == 0
    assert len(off.times) <= len(on.times) < len(off.every_scan[0]) / 2
    a = evaluation.ate(off.poses, _truth(off))
    odo = evaluation.ate(off.odometry, _truth(off))
    assert a["rmse"] < 0.05 and a["rmse"] < 0.8 * odo["rmse"], (a, odo)


def test_bad_logs_never_crash():
    evs, cfg, _ = room_events(0, 20.0)
    evs = list(evs)
    # a gap of 3 s, a few records out of order, a burst of empty and garbage scans
    bad = [e for e in evs if not (8.0 < e.t < 11.0)]
    late = [bad[100], bad[300]]  # each repeated far beyond the reorder window
    bad.insert(next(i for i, e in enumerate(bad) if e.t > late[0].t + 3.0), late[0])
    bad.insert(next(i for i, e in enumerate(bad) if e.t > late[1].t + 3.0), late[1])
    for k in range(len(bad)):
        if isinstance(bad[k], LaserScan) and 13.0 < bad[k].t < 15.0:
            r = np.full(361, np.nan) if k % 2 else np.random.default_rng(k).uniform(0, 90, 361)
            bad[k] = LaserScan(bad[k].t, r)
    for res in run_backends(bad, cfg, ["ekf", "isam2", "batch"], "fused"):
        assert res.stats["events_out_of_order"] == 2
        assert np.all(np.isfinite(res.poses))
    # a log with odometry only: no landmark, no crash
    only = [e for e in evs if isinstance(e, OdometryEvent | LaserScan) and e.t < 3]
    only = [
        e if isinstance(e, OdometryEvent) else LaserScan(e.t, np.full(361, np.nan)) for e in only
    ]
    for res in run_backends(only, cfg, ["ekf", "isam2", "batch"], "laser"):
        assert len(res.landmarks) == 0 and len(res.times) > 5


# ------------------------------------------------------------------ map management rules


def _line_feature(z, ends, start=End.OUTLIERS, end=End.OUTLIERS, cov=None):
    return Feature(
        "line",
        np.array(z, float),
        np.diag([1e-4, 1e-4]) if cov is None else cov,
        "laser",
        np.array(ends, float),
        start,
        end,
    )


def _still(n=1):
    """Preintegrated odometry of a robot standing still (tiny covariance)."""
    import gtsam

    from factors.odometry import Preintegrated

    c = np.eye(3) * 1e-8
    return Preintegrated(gtsam.Pose2(), c, c, n)


def test_new_lines_only_when_long_enough_confirmed_on_a_second_keyframe_and_gated():
    """A short line never starts a landmark; a long one is tentative (not in the EKF) until
    seen again on a second keyframe; a wall 0.3 m farther fails the gate: a new tentative."""
    step = SlamStep(EkfBackend())
    short = _line_feature((0.0, 2.0), [(2.0, -0.3), (2.0, 0.3)])
    long = _line_feature((0.0, 2.0), [(2.0, -1.0), (2.0, 1.0)])
    step.keyframe(0.0, [short, long], None, np.zeros(3))
    assert step.stats["lines_too_short"] == 1 and step.stats["lines_tentative"] == 1
    assert step.be.index == {}  # tentative: not in the state
    again = _line_feature((0.01, 2.005), [(2.0, -0.8), (2.0, 0.9)])
    step.keyframe(1.0, [again], _still(), None)
    (lid,) = step.be.index
    assert step.landmarks[lid].status == "confirmed" and step.stats["lines_new"] == 1
    np.testing.assert_allclose(step.landmarks[lid].extent, [-1.0, 1.0], atol=0.05)
    other = _line_feature((0.0, 2.3), [(2.3, -1.0), (2.3, 1.0)])
    again = _line_feature((0.0, 2.0), [(2.0, -0.8), (2.0, 0.9)])
    where = step.keyframe(2.0, [again, other], _still(), None)
    assert where[0] == lid and where[1] != lid
    assert step.landmarks[where[1]].status == "tentative"


def test_endpoint_rules():
    """Paper IV's endpoint rules, on world ends (geometry.update_line_ends)."""
    from fgslam.slam import geometry

    line = np.array([0.0, 2.0])
    ends = geometry.on_line(line, np.array([-1.0, 1.0]))

    def observe(y0, y1, c0, c1):
        nonlocal ends
        f = _line_feature((0.0, 2.0), [(2.0, y0), (2.0, y1)], c0, c1)
        ends = geometry.update_line_ends(ends, line, f, np.zeros(3), 0.5, 0.1)
        return np.sort(geometry.along(line, ends))

    # beyond the map's ends: extended, whatever the condition
    np.testing.assert_allclose(observe(-1.5, 1.2, End.FIELD_OF_VIEW, End.OUTLIERS), [-1.5, 1.2])
    # inside: reliable (sonar) -> big step; weak -> small step; field of view -> unchanged
    e = observe(-1.0, 0.2, End.FIELD_OF_VIEW, End.SONAR)
    np.testing.assert_allclose(e, [-1.5, 1.2 + 0.5 * (0.2 - 1.2)])
    e = observe(-0.5, 0.7, End.SPREAD, End.FIELD_OF_VIEW)
    np.testing.assert_allclose(e, [-1.5 + 0.1 * 1.0, 0.7])
    np.testing.assert_allclose(ends[:, 0], [2.0, 2.0])


def _two_line_map(step):
    """An EKF map with two collinear lines x = 2, y in [-2, -0.5] and [0.3, 2] (confirmed
    over keyframes 0-1), the robot still at the origin."""
    a = _line_feature((0.0, 2.0), [(2.0, -2.0), (2.0, -0.5)], End.SONAR, End.SONAR)
    b = _line_feature((0.0, 2.0), [(2.0, 0.3), (2.0, 2.0)], End.SONAR, End.SONAR)
    step.keyframe(0.0, [a, b], None, np.zeros(3))
    step.keyframe(1.0, [a, b], _still(), None)
    assert len(step.be.index) == 2
    return sorted(step.be.index)


def test_merge_when_measurement_covers_both_keeps_the_dropped_extent():
    """A measurement covering 0.5 m of only one line merges nothing; one covering 0.5 m of
    both merges them into the older; with a real EKF (the dropped line leaves the state) the
    merged segment still spans both: [-2, 2] (before the fix: the dropped extent was lost).
    Duplicate detection is off here (it would merge the touching lines after keyframe 2)."""
    step = SlamStep(EkfBackend(), MapParams(duplicate_p=0.0))
    l0, l1 = _two_line_map(step)
    f = _line_feature((0.0, 2.0), [(2.0, -1.0), (2.0, 0.5)], End.FIELD_OF_VIEW, End.FIELD_OF_VIEW)
    step.keyframe(2.0, [f], _still(), None)
    assert step.stats["line_merges"] == 0
    f = _line_feature((0.0, 2.0), [(2.0, -1.0), (2.0, 0.8)], End.FIELD_OF_VIEW, End.FIELD_OF_VIEW)
    where = step.keyframe(3.0, [f], _still(), None)
    assert step.stats["line_merges"] == 1 and where == [l0]
    assert step.landmarks[l1].merged_into == l0 and step.map.resolve(l1) == l0
    assert list(step.be.index) == [l0]
    np.testing.assert_allclose(step.landmarks[l0].extent, [-2.0, 2.0], atol=0.01)


def test_observations_are_credited_to_the_landmark_kept_by_a_merge_in_the_same_scan():
    """Feature 1 of a scan observes line l1; feature 2 covers both lines and merges l1 into
    l0: feature 1's sighting counts for l0 (before the fix it went to the merged-away l1)."""
    step = SlamStep(EkfBackend(), MapParams(duplicate_p=0.0))
    l0, l1 = _two_line_map(step)
    before = sum(step.landmarks[l0].observations.values()) + sum(
        step.landmarks[l1].observations.values()
    )
    f1 = _line_feature((0.0, 2.0), [(2.0, 1.0), (2.0, 1.9)])
    f2 = _line_feature((0.0, 2.0), [(2.0, -1.0), (2.0, 0.8)], End.FIELD_OF_VIEW, End.FIELD_OF_VIEW)
    step.keyframe(2.0, [f1, f2], _still(), None)
    assert step.stats["line_merges"] == 1
    assert sum(step.landmarks[l0].observations.values()) == before + 2


def test_map_json_endpoints_of_a_line_stored_with_negative_d_are_not_mirrored(tmp_path):
    """A line whose estimate is stored as (alpha + pi, -d) (d < 0: a line seen across the
    origin, or a graph variable that crossed it) is reported normalised; its endpoints in
    map.json must still be the measured wall's, not mirrored about the foot point."""
    from fgslam.slam.outputs import map_dict

    step = SlamStep(EkfBackend())
    c, s = math.cos(0.3), math.sin(0.3)
    want = np.array([(2 * c + 0.4 * s, 2 * s - 0.4 * c), (2 * c - 1.5 * s, 2 * s + 1.5 * c)])
    f = _line_feature((0.3, 2.0), want)
    pose = np.zeros(3)
    step.keyframe(0.0, [f], None, pose)
    step.keyframe(1.0, [f], _still(), None)
    (lid,) = step.be.index
    o, _ = step.be.index[lid]
    a, d = step.be.x[o : o + 2]
    step.be.x[o : o + 2] = (a + math.pi, -d)  # the same line, the other parametrisation
    f2 = _line_feature((0.3, 2.0), want, End.SONAR, End.SONAR)
    step.keyframe(2.0, [f2], _still(), None)

    res = SimpleNamespace(
        landmarks={lid: step.landmarks[lid]},
        means={lid: models.normalize("line", step.be.x[o : o + 2])},
        landmark_covs={},
    )
    (entry,) = map_dict(res)["landmarks"]
    assert entry["d"] > 0
    got = np.array(entry["endpoints"])
    # the measured ends (not their mirror images about the foot point, 2 m apart)
    assert np.abs(np.sort(got, axis=0) - np.sort(want, axis=0)).max() < 0.01, got


# ------------------------------------------------------------------ evaluation by hand


def test_alignment_and_ate_by_hand():
    ref = np.array([[0, 0, 0], [1, 0, 0], [1, 1, math.pi / 2], [0, 1, math.pi]], float)
    est = evaluation.apply_se2(0.3, [1.0, -2.0], ref)
    angle, _ = evaluation.align_se2(est, ref)
    assert math.isclose(angle, -0.3, abs_tol=1e-12)
    a = evaluation.ate(est, ref)
    assert a["rmse"] < 1e-12 and a["heading_rmse_deg"] < 1e-9
    # a 10 cm offset on one of four points, no alignment: rmse = sqrt(0.01 / 4)
    est2 = ref.copy()
    est2[2, 0] += 0.1
    a = evaluation.ate(est2, ref, align=False)
    assert math.isclose(a["rmse"], 0.05) and math.isclose(a["max"], 0.1)
    n = evaluation.nees(ref + np.array([0.1, 0, 0]), np.array([np.eye(3) * 0.01] * 4), ref)
    assert math.isclose(n["mean"], 1.0)


@pytest.mark.parametrize("kind,dimz", [("line", 2), ("corner", 3), ("corner", 2), ("point", 2)])
def test_vectorised_residuals_match_the_model(kind, dimz):
    """The association's vectorised pre-gate residuals equal the model's residual, including
    lines seen from behind (the flipped form), wrap-around angles and sonar-only corners."""
    from fgslam.slam import models

    rng = np.random.default_rng(7)
    for _ in range(50):
        pose = rng.uniform([-5, -5, -math.pi], [5, 5, math.pi])
        n = 20
        if kind == "line":
            lms = np.column_stack([rng.uniform(-math.pi, math.pi, n), rng.uniform(0, 8, n)])
        else:
            lms = rng.uniform([-8, -8, -math.pi], [8, 8, math.pi], (n, 3))[:, : models.DIM[kind]]
        z = rng.uniform([-math.pi, 0.1, -math.pi], [math.pi, 6, math.pi])[:dimz]
        got = models.residuals(kind, pose, lms, z)
        want = np.array([models.residual(kind, pose, lm, z)[0] for lm in lms])
        diff = got - want
        # angles may differ by 2 pi only exactly at +-pi
        for j in (0, 2)[: 1 + (dimz == 3)]:  # bearing, and a corner's bisector
            diff[:, j] = np.remainder(diff[:, j] + math.pi, 2 * math.pi) - math.pi
        np.testing.assert_allclose(diff, 0.0, atol=1e-9)
