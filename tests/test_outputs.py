"""Run outputs (issue 16): laser points placed with the estimate, the bounded scan sample,
figures sized to what they show, comparison.md that explains itself, atomic writes."""

from __future__ import annotations

import dataclasses
import math
from collections import Counter

import numpy as np
import pytest
from matplotlib.image import imread
from readers_helpers import ray_rect

from fgslam.config import Mount, load_config
from fgslam.events import LaserScan, OdometryEvent
from fgslam.io import safeio
from fgslam.slam.compare import describe_run, markdown_table, plot_comparison
from fgslam.slam.outputs import ScanSample, laser_points, plot_map, write_outputs
from fgslam.slam.runner import SlamResult

ROOM = (-4.0, -2.0, 5.0, 3.0)


def _cfg(yaw_deg: float = 10.0):
    cfg = load_config()
    mount = Mount(0.3, -0.1, yaw_deg)
    return dataclasses.replace(cfg, laser=dataclasses.replace(cfg.laser, mount=mount))


def _fake(times, poses, backend="isam2", truth=True, stats=None) -> SlamResult:
    poses = np.asarray(poses, dtype=float)
    return SlamResult(
        backend=backend,
        sensors="fused",
        times=np.asarray(times, dtype=float),
        poses=poses,
        covs=[None] * len(poses),
        filtered=poses,
        odometry=poses + 0.05,
        landmarks={},
        means={},
        landmark_covs={},
        truth_t=np.asarray(times, dtype=float) if truth else np.zeros(0),
        truth=poses if truth else np.zeros((0, 3)),
        latencies=[0.01] * len(poses),
        wall_time=1.0,
        log_duration=float(times[-1] - times[0]),
        stats=Counter(stats or {}),
    )


def _wall_distance(p: np.ndarray) -> np.ndarray:
    x0, y0, x1, y1 = ROOM
    return np.min(np.abs([p[:, 0] - x0, p[:, 0] - x1, p[:, 1] - y0, p[:, 1] - y1]), axis=0)


def test_laser_points_lie_on_the_walls():
    """Scans simulated from the laser's true pose (robot pose, mount, yaw) and placed back
    with the trajectory land on the room's walls, between keyframes as well (interpolation
    of a straight drive is exact)."""
    cfg = _cfg()
    m = cfg.laser.mount
    times = np.array([0.0, 1.0, 2.0])
    poses = np.array([(-1.0, 0.0, 0.4), (0.0, 0.5, 0.4), (1.0, 1.0, 0.4)])
    scans = []
    for t in (0.0, 0.5, 1.0, 1.75, 2.0, 2.5):  # 2.5: after the trajectory, left out
        x, y, th = -1.0 + t, 0.5 * t, 0.4
        lp = (
            x + math.cos(th) * m.x - math.sin(th) * m.y,
            y + math.sin(th) * m.x + math.cos(th) * m.y,
            th + math.radians(m.yaw_deg),
        )
        r = ray_rect(lp, cfg.laser.bearings, ROOM)
        r[::7] = np.nan  # no return
        r[3] = cfg.laser.max_range  # no return, as CARMEN writes it
        scans.append((t, r))
    pts = laser_points(scans, times, poses, cfg)
    per_scan = int(np.sum(np.isfinite(scans[0][1]))) - 1
    assert len(pts) == 5 * per_scan
    assert _wall_distance(pts).max() < 1e-9
    thin = laser_points(scans, times, poses, cfg, max_points=100)
    assert 50 <= len(thin) <= 100 and _wall_distance(thin).max() < 1e-9


def test_scan_sample_is_bounded_and_even():
    s = ScanSample(max_scans=100)
    for k in range(10_000):
        s.add(LaserScan(0.1 * k, np.zeros(3)))
        s.add(OdometryEvent(0.1 * k, 0, 0))
    t = np.array([x[0] for x in s.scans])
    assert 50 <= len(t) <= 100
    assert np.allclose(np.diff(t), t[1] - t[0]) and t[0] == 0.0 and t[-1] > 900


def test_map_is_sized_to_the_map(tmp_path):
    """A 40 m x 4 m run gives a wide figure, a 4 m x 40 m one a tall figure."""
    cfg = _cfg(0.0)
    for wide in (True, False):
        xs = np.linspace(0, 40, 50)
        poses = np.column_stack([xs, np.zeros(50), np.zeros(50)])
        if not wide:
            poses = np.column_stack([np.zeros(50), xs, np.full(50, math.pi / 2)])
        res = _fake(np.arange(50.0), poses)
        scans = [(float(k), np.full(cfg.laser.n_beams, 2.0)) for k in range(50)]
        write_outputs(res, tmp_path / str(wide), scans=scans, cfg=cfg)
        h, w = imread(tmp_path / str(wide) / "map.png").shape[:2]
        assert (w > 2 * h) if wide else (h > 1.5 * w)


def test_map_draws_the_world_outline(tmp_path):
    from fgslam.sim.world import load_world

    world = load_world("corridor")
    res = _fake([0.0, 1.0], [(1.0, 1.0, 0.0), (9.0, 6.0, 0.0)])  # in the lab
    plot_map(res, tmp_path / "with.png", world=world)
    plot_map(res, tmp_path / "without.png")
    a, b = imread(tmp_path / "with.png"), imread(tmp_path / "without.png")
    assert a.shape == b.shape and np.sum(a[..., :3] < 0.2) > np.sum(b[..., :3] < 0.2) + 500


def test_comparison_png_equal_axes_sized_to_the_path_linear_errors(tmp_path):
    xs = np.linspace(0, 60, 100)
    poses = np.column_stack([xs, 2.0 + 0.1 * np.sin(xs), np.zeros(100)])
    good = _fake(np.arange(100.0), poses)
    bad = dataclasses.replace(good, backend="ekf", poses=poses + np.array([0.0, 0.5, 0.0]))
    info = plot_comparison([good, bad], tmp_path / "c.png")
    assert info["aspect"] == 1.0 and info["error_yscale"] == "linear"
    (x0, x1), (y0, y1) = info["xlim"], info["ylim"]
    assert x0 < 0 < 60 < x1 and x1 - x0 < 75
    assert (y1 - y0) == pytest.approx((x1 - x0) / 4)  # no thinner than 1:4
    assert info["error_ylim"] == pytest.approx((0.0, 1.15 * 0.5))


def _row(backend, nees=None, partial=None):
    r = {
        "backend": backend,
        "sensors": "fused",
        "ate": {"rmse": 0.1, "max": 0.2},
        "landmarks": {"line": 3},
        "keyframe_latency_ms": {"p95": 5.0},
        "realtime_factor": 10.0,
        "ate_odometry": {"rmse": 0.5, "max": 1.0},
    }
    if nees is not None:
        r["nees"] = {"mean": nees, "dof": 3}
    if partial:
        r["partial"] = partial
    return r


def test_comparison_md_explains_itself():
    res = _fake(np.arange(11.0), [(k, 0.0, 0.0) for k in range(11)])
    head = describe_run(
        "logs/run.log", [res], load_config(), {"LaserScan": 40, "SonarReading": 9}, "reference"
    )
    assert head.startswith("# fgslam compare: run.log\n")
    assert "10.0 s, 10.0 m travelled (along the reference)" in head
    assert "40 scans of 361 beams over 180 deg" in head and "9 readings from 2 arrays" in head
    assert "Columns: ATE RMSE" in head and "NEES mean" in head and "overconfident" in head
    assert "- records:" not in head
    res.stats["events_out_of_order"] = 50
    head = describe_run("run.log", [res], load_config(), {}, reader={"skipped": 0})
    assert "- records: 50 events dropped as too late to put back in order\n" in head
    md = markdown_table(
        [
            _row("ekf", 30.0),
            _row("isam2", 3.2),
            _row("batch", partial={"keyframe": 4, "t": 2.0, "error": "x"}),
        ]
    )
    assert "| ekf | fused | 0.100 | 0.200 | - | 30.0 (!) |" in md
    assert "| isam2 | fused | 0.100 | 0.200 | - | 3.2 |" in md
    assert "ekf/fused: NEES 30.0 is 10x its 3 dof: the covariances are overconfident" in md
    assert "isam2/fused: NEES" not in md
    assert "| batch (PARTIAL) |" in md and "failed at keyframe 4" in md


def test_atomic_path_keeps_the_old_file_on_failure(tmp_path):
    target = tmp_path / "a.json"
    safeio.write_json(target, {"v": 1})
    with pytest.raises(RuntimeError):
        with safeio.atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("disk full")
    assert target.read_text() == '{\n  "v": 1\n}\n'
    assert [p.name for p in tmp_path.iterdir()] == ["a.json"]


def test_partial_result_without_a_single_pose_is_written(tmp_path):
    """A backend that failed at its first keyframe still leaves readable outputs."""
    res = dataclasses.replace(
        _fake([0.0, 1.0], [(0, 0, 0), (1, 0, 0)]),
        times=np.zeros(0),
        poses=np.zeros((0, 3)),
        covs=[],
        filtered=np.zeros((0, 3)),
        odometry=np.zeros((0, 3)),
        latencies=[],
        stats=Counter({"partial": {"keyframe": 0, "t": 0.0, "error": "boom"}}),
    )
    rep = write_outputs(res, tmp_path, scans=[(0.5, np.ones(361))], cfg=load_config())
    assert rep["partial"]["error"] == "boom" and rep["poses"] == 0
    assert (tmp_path / "map.png").stat().st_size > 0
    assert (tmp_path / "trajectory.tum").read_text() == ""


def test_report_states_the_scale_aligned_nees_beside_the_raw():
    """A map right but for its absolute scale (1 % too large about the start) with tight
    covariances: the raw NEES is far over its 3 dof, the scale-aligned one is zero (the
    estimate is the truth once scaled), the scale error -1/101; the demo's table shows both
    and its overconfidence flag names the aligned value."""
    from fgslam.slam.outputs import report_dict

    t = np.linspace(0.0, 60.0, 61)
    truth = np.column_stack([np.cos(t / 10) * 5, np.sin(t / 10) * 3, t / 10])
    est = truth.copy()
    est[:, :2] = truth[0, :2] + 1.01 * (truth[:, :2] - truth[0, :2])
    res = _fake(t, est)
    res.truth = truth
    res.covs = [np.diag([1e-4, 1e-4, 1e-4])] * len(t)
    rep = report_dict(res)
    assert rep["nees"]["mean"] > 30  # (3 dof)
    aligned = rep["nees_scale_aligned"]
    assert aligned["mean"] == pytest.approx(0.0, abs=1e-9)
    assert aligned["scale_error"] == pytest.approx(1 / 1.01 - 1, rel=1e-9)
    table = markdown_table([{**rep, "landmarks": {}}])
    assert "NEES scale-aligned" in table and "| 0.0 |" in table
    assert "with the map's absolute scale taken out" in table and "laser) 0.0" in table


def test_calibration_against_the_simulated_truth(tmp_path):
    """A simulated log's header gives its true calibration (the simulator's parameters and the
    seed's speed-of-sound draw); a log that is not simulated, or whose parameters are another
    simulator's, gives none. report.json's calibration states the truth and the error in
    sigmas, the comparison's table shows both (1e-3) and a truth row."""
    from fgslam.sim import true_calibration
    from fgslam.sim.sensors import SimParams
    from fgslam.sim.simulate import sound_speed_bias
    from fgslam.slam.outputs import calibration_against_truth

    meta = {"seed": 3, "sim_params": dataclasses.asdict(SimParams(wheelbase_error=-0.002))}
    truth = true_calibration(meta)
    assert truth["e_b"] == -0.002 and truth["laser_offset"] == 0.008
    assert truth["sound"] == sound_speed_bias(3) != sound_speed_bias(4)
    bad_meta = [{}, {"seed": 3}, {"seed": "3", "sim_params": {}}, {"seed": True, "sim_params": {}}]
    bad_meta += [{"seed": 3, "sim_params": {"warp_drive": 1.0}}, {"seed": 3, "sim_params": []}]
    bad_meta += [{"seed": 3, "sim_params": {"wheelbase_error": v}} for v in ("x", math.inf, None)]
    for bad in bad_meta:
        assert true_calibration(bad) is None, bad
    cal = {"parameters": ["e_r", "e_b", "glue"], "estimate": [0.007, -0.001, 0.1],
           "sigma": [0.0005, 0.002, 0.01]}  # fmt: skip
    out = calibration_against_truth(cal, truth)
    assert out["truth"] == [0.006, -0.002, None]
    assert out["error_sigmas"] == pytest.approx([2.0, 0.5, None])
    assert calibration_against_truth(cal, None) == cal
    table = markdown_table([{**_row("isam2"), "calibration": out}])
    assert "| e_r | e_b | glue |" in table
    assert (
        "| isam2 | fused | 7.00 +- 0.50 (+2.0) | -1.00 +- 2.00 (+0.5) | 100.00 +- 10.00 |" in table
    )
    assert "| truth | | 6.00 | -2.00 | - |" in table
    assert "Calibration" not in markdown_table([_row("isam2")])
