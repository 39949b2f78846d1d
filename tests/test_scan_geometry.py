"""Laser geometry per scan: scans whose beams lie elsewhere than the configured laser's
(interlaced scans, another beam count) are read with their own bearings, never dropped; the
front end, the native log and a whole run use them; a bag's tf gives the laser's mount."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from readers_helpers import (
    ROOM,
    bag_writer,
    header_message,
    laser_scan_message,
    odometry_message,
    ray_rect,
)

from fgslam.events import LaserScan, OdometryEvent, scan_bearings
from fgslam.io.formats import open_log
from fgslam.scanmatch import scan_points

DEG = math.pi / 180
START = (-1.5, -0.5, 0.2)  # robot pose at t = 1 s (m, rad); it drives straight ahead
SPEED = 0.25  # m/s


def robot_pose(t: float) -> tuple[float, float, float]:
    """The robot's world pose at time t (s) of the synthetic bags."""
    x, y, th = START
    d = SPEED * (t - 1.0)
    return x + d * math.cos(th), y + d * math.sin(th), th


def compose(a, d):
    c, s = math.cos(a[2]), math.sin(a[2])
    return (a[0] + c * d[0] - s * d[1], a[1] + s * d[0] + c * d[1], a[2] + d[2])


def interlaced(k: int) -> tuple[int, float, float]:
    """Scan k of a laser that interlaces its scans: 181 and 180 beams in turn, 1 deg apart,
    starting at four angles a quarter degree apart (beam count, angle_min, increment; rad)."""
    return (181 if k % 2 == 0 else 180), (-90.0 + 0.25 * (k % 4)) * DEG, 1.0 * DEG


def wall_distance(points) -> float:
    """The largest distance (m) of world points from the walls of the room."""
    x0, y0, x1, y1 = ROOM
    p = np.asarray(points)
    d = np.min(np.abs([p[:, 0] - x0, p[:, 0] - x1, p[:, 1] - y0, p[:, 1] - y1]), axis=0)
    return float(d.max())


def world_points(scan: LaserScan, cfg, pose) -> np.ndarray:
    """A scan's returns in the world: its bearings, the configured mount, the robot's pose."""
    m = cfg.laser.mount
    p = scan_points(scan.ranges, scan_bearings(scan, cfg.laser), (m.x, m.y, m.yaw_deg * DEG))
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return np.column_stack(
        [pose[0] + c * p[:, 0] - s * p[:, 1], pose[1] + s * p[:, 0] + c * p[:, 1]]
    )


def _quaternion(T, yaw: float, roll: float = 0.0):
    """yaw about z after roll about x."""
    cy, sy, cr, sr = math.cos(yaw / 2), math.sin(yaw / 2), math.cos(roll / 2), math.sin(roll / 2)
    return T["geometry_msgs/msg/Quaternion"](x=cy * sr, y=sy * sr, z=sy * cr, w=cy * cr)


def write_bag(
    path,
    scans,
    *,
    ros1: bool = True,
    mount=(0.0, 0.0, 0.0),
    frame: str = "laser",
    child: str = "base_link",
    tf_static=(),
    tf_dynamic=(),
    noise: float = 0.0,
) -> None:
    """A bag of the robot driving through the room (:func:`robot_pose`): ``/odom`` (child
    frame ``child``) every 0.1 s from 1 s, and ``/scan`` (frame ``frame``) 0.05 s after
    every other odometry message, scan k with the geometry ``scans[k]`` (beam count,
    angle_min, increment), seen by a laser at ``mount`` (x, y, yaw) on the robot, ranges
    float32 with seeded Gaussian ``noise`` (m); its first three beams read inf, range_max (no
    return) and NaN. ``tf_static`` / ``tf_dynamic``: transforms (parent, child, x, y, z, yaw,
    roll) on ``/tf_static`` once and on ``/tf`` with every odometry message."""
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    if "tf2_msgs/msg/TFMessage" not in ts.types:  # not in rosbags' ROS 1 store
        from rosbags.typesys import get_types_from_msg

        msg = "geometry_msgs/TransformStamped[] transforms"
        ts.register(get_types_from_msg(msg, "tf2_msgs/msg/TFMessage"))
    T = ts.types
    g = {k.split("/")[-1]: T[k] for k in T if k.startswith("geometry_msgs/msg/")}
    ser = ts.serialize_ros1 if ros1 else ts.serialize_cdr
    rng = np.random.default_rng(5)

    def header(t, frame_id):
        return header_message(T, t, frame_id, ros1)

    def tf_message(t, transforms):
        out = [
            T["geometry_msgs/msg/TransformStamped"](
                header=header(t, parent),
                child_frame_id=kid,
                transform=g["Transform"](
                    translation=g["Vector3"](x=x, y=y, z=z), rotation=_quaternion(T, yaw, roll)
                ),
            )
            for parent, kid, x, y, z, yaw, roll in transforms
        ]
        return ser(T["tf2_msgs/msg/TFMessage"](transforms=out), "tf2_msgs/msg/TFMessage")

    writer = bag_writer(path, ros1)
    with writer:
        cs = writer.add_connection("/scan", "sensor_msgs/msg/LaserScan", typestore=ts)
        co = writer.add_connection("/odom", "nav_msgs/msg/Odometry", typestore=ts)
        if tf_static:
            c = writer.add_connection("/tf_static", "tf2_msgs/msg/TFMessage", typestore=ts)
            writer.write(c, round(0.9e9), tf_message(0.9, tf_static))
        ct = writer.add_connection("/tf", "tf2_msgs/msg/TFMessage", typestore=ts)
        for j in range(2 * len(scans)):
            t = 1.0 + 0.1 * j
            x, y, th = robot_pose(t)
            pose = g["Pose"](position=g["Point"](x=x, y=y, z=0.0), orientation=_quaternion(T, th))
            odom = odometry_message(T, header(t, "odom"), child, pose)
            writer.write(co, round(t * 1e9), ser(odom, "nav_msgs/msg/Odometry"))
            odom_tf = [("odom", child, x, y, 0.0, th, 0.0)]
            writer.write(ct, round(t * 1e9), tf_message(t, [*odom_tf, *tf_dynamic]))
            if j % 2:
                continue
            ts_ = t + 0.05
            n, a0, inc = scans[j // 2]
            angles = np.float32(a0) + np.float32(inc) * np.arange(n)  # as a driver has them
            r = ray_rect(compose(robot_pose(ts_), mount), angles)
            r = (r + noise * rng.standard_normal(n)).astype(np.float32)
            r[0], r[1], r[2] = np.inf, 30.0, np.nan  # no return, a max-range reading, NaN
            scan = laser_scan_message(T, header(ts_, frame), r, a0, a0 + (n - 1) * inc, inc, 0.2)
            writer.write(cs, round(ts_ * 1e9), ser(scan, "sensor_msgs/msg/LaserScan"))


# ------------------------------------------------------------------ ROS bags


@pytest.mark.parametrize("ros1", [True, False])
def test_interlaced_bag_keeps_every_scan_with_its_bearings(tmp_path, ros1):
    """181 and 180 beams in turn at four start angles: every scan is read, the first one's
    geometry is the configured laser's, the others carry their own bearings (angle_min + k
    increment in the laser frame), and every return lands on the walls."""
    pytest.importorskip("rosbags")
    bag = tmp_path / ("i.bag" if ros1 else "i")
    geoms = [interlaced(k) for k in range(8)]
    write_bag(bag, geoms, ros1=ros1)
    log = open_log(bag)
    cfg = log.config
    assert cfg.laser.n_beams == 181 and cfg.laser.fov_deg == pytest.approx(180.0)
    scans = [e for e in log if isinstance(e, LaserScan)]
    assert len(scans) == 8 and log.problems.summary()["skipped"] == 0
    assert [s.ranges.size for s in scans] == [g[0] for g in geoms]
    assert scans[0].bearings is None and scans[4].bearings is None  # the first one's geometry
    for k, (scan, (n, a0, inc)) in enumerate(zip(scans, geoms, strict=True)):
        expect = np.float32(a0) + np.float64(np.float32(inc)) * np.arange(n)
        np.testing.assert_allclose(scan_bearings(scan, cfg.laser), expect, atol=1e-6)
        assert np.isnan(scan.ranges[:3]).all() and np.isfinite(scan.ranges[3:]).all()
        assert wall_distance(world_points(scan, cfg, robot_pose(scan.t))) < 1e-4, k


def test_negative_increment_scans_are_turned_around(tmp_path):
    """A laser sweeping clockwise (negative angle_increment) after an anticlockwise first
    scan: its ranges are reversed so that its bearings increase."""
    pytest.importorskip("rosbags")
    bag = tmp_path / "cw.bag"
    geoms = [interlaced(0), (180, 89.5 * DEG, -1.0 * DEG), (181, 90.0 * DEG, -1.0 * DEG)]
    write_bag(bag, geoms)
    log = open_log(bag)
    scans = [e for e in log if isinstance(e, LaserScan)]
    assert len(scans) == 3 and all(np.isnan(s.ranges[-3:]).all() for s in scans[1:])
    assert scans[1].bearings is not None and np.all(np.diff(scans[1].bearings) > 0)
    assert scans[2].bearings is None  # the configured geometry, turned around
    for scan in scans:
        assert wall_distance(world_points(scan, log.config, robot_pose(scan.t))) < 1e-4


@pytest.mark.parametrize("where", ["tf_static", "tf"])
def test_laser_mount_from_tf(tmp_path, where):
    """The laser's pose on the robot from tf: base_footprint (the odometry's child frame) ->
    base_link -> laser, composed; static or among the dynamic transforms."""
    pytest.importorskip("rosbags")
    bag = tmp_path / "tf.bag"
    chain = [
        ("base_footprint", "base_link", 0.1, 0.0, 0.2, 0.0, 0.0),
        ("/base_link", "/laser", 0.15, -0.05, 0.3, 0.3, 0.0),  # ROS 1 style leading slashes
    ]
    mount = (0.25, -0.05, 0.3)
    kw = {"tf_static": chain} if where == "tf_static" else {"tf_dynamic": chain}
    write_bag(bag, [interlaced(k) for k in range(4)], mount=mount, child="base_footprint", **kw)
    log = open_log(bag)
    m = log.config.laser.mount
    assert (m.x, m.y, m.yaw_deg * DEG) == pytest.approx(mount, abs=1e-6)
    assert log.meta["laser_mount"]["source"] == "tf"
    assert log.meta["laser_mount"]["tf"] == "base_footprint -> laser"
    for scan in (e for e in log if isinstance(e, LaserScan)):
        assert wall_distance(world_points(scan, log.config, robot_pose(scan.t))) < 1e-4
    # laser_mount given: it wins over tf
    m = open_log(bag, laser_mount=(0.0, 0.0, 0.0)).config.laser.mount
    assert (m.x, m.y, m.yaw_deg) == pytest.approx((0.0, 0.0, 0.0), abs=1e-6)


def test_upside_down_laser_in_tf_keeps_the_configured_mount(tmp_path):
    pytest.importorskip("rosbags")
    bag = tmp_path / "flip.bag"
    flip = [("base_link", "laser", 0.2, 0.0, 0.3, 0.0, math.pi)]
    write_bag(bag, [interlaced(0)] * 2, tf_static=flip)
    log = open_log(bag)
    m = log.config.laser.mount
    assert (m.x, m.y) == (0.0, 0.0) and log.meta["laser_mount"]["source"] == "robot origin"
    assert "tilted 180 deg" in log.meta["laser_mount"]["tf"]


def test_bag_without_tf_keeps_the_robot_origin(tmp_path):
    pytest.importorskip("rosbags")
    bag = tmp_path / "notf.bag"
    write_bag(bag, [interlaced(0)] * 2, child="chassis")
    log = open_log(bag)
    m = log.config.laser.mount
    assert (m.x, m.y) == (0.0, 0.0) and log.meta["laser_mount"]["source"] == "robot origin"


# ------------------------------------------------------------------ CARMEN


def _carmen_pose(k: int) -> tuple[float, float, float]:
    return robot_pose(1.0 + 0.2 * k)


def test_carmen_flaser_beam_counts_vary(tmp_path):
    """FLASER lines of 180, 181 and 361 beams (each over 180 deg), with NaN, inf and 81.91
    (no return) among the ranges: every scan read, with its own bearings where its beam
    count is not the first scan's, and every return on the walls."""
    counts = [180, 181, 361, 180, 361]
    lines = []
    for k, n in enumerate(counts):
        p, t = _carmen_pose(k), 1.0 + 0.2 * k
        r = [repr(float(v)) for v in ray_rect(p, np.linspace(-math.pi / 2, math.pi / 2, n))]
        r[0], r[1], r[2] = "nan", "inf", "81.91"
        pose = " ".join(map(repr, p))
        lines.append(f"FLASER {n} {' '.join(r)} {pose} {pose} {t!r} h {t!r}")
    f = tmp_path / "beams.clf"
    f.write_text("\n".join(lines) + "\n")
    log = open_log(f)
    scans = [e for e in log if isinstance(e, LaserScan)]
    assert [s.ranges.size for s in scans] == counts and log.problems.summary()["skipped"] == 0
    assert [s.bearings is None for s in scans] == [True, False, False, True, False]
    for k, scan in enumerate(scans):
        b = np.linspace(-math.pi / 2, math.pi / 2, counts[k])
        np.testing.assert_allclose(scan_bearings(scan, log.config.laser), b, atol=1e-12)
        assert np.isnan(scan.ranges[:3]).all() and np.isfinite(scan.ranges[3:]).all()
        assert wall_distance(world_points(scan, log.config, _carmen_pose(k))) < 1e-6


def test_carmen_robotlaser1_interlaced(tmp_path):
    """ROBOTLASER1 lines of an interlacing laser (start angle and beam count per line; beam
    k at start + k resolution) mounted 0.2 m ahead: every scan read with its bearings."""
    lines = []
    for k in range(6):
        n, a0, inc = interlaced(k)
        p, t = _carmen_pose(k), 1.0 + 0.2 * k
        lp = compose(p, (0.2, 0.0, 0.0))
        r = " ".join(repr(float(v)) for v in ray_rect(lp, a0 + inc * np.arange(n)))
        head = f"0 {a0!r} {(n - 1) * inc!r} {inc!r} 30.0 0.01 0"
        pose, lpose = " ".join(map(repr, p)), " ".join(map(repr, lp))
        lines.append(f"ROBOTLASER1 {head} {n} {r} 0 {lpose} {pose} 0 0 0.5 0.3 1e6 {t!r} h {t!r}")
    f = tmp_path / "rl.clf"
    f.write_text("\n".join(lines) + "\n")
    log = open_log(f)
    cfg = log.config
    assert cfg.laser.n_beams == 181 and cfg.laser.mount.x == pytest.approx(0.2)
    scans = [e for e in log if isinstance(e, LaserScan)]
    assert len(scans) == 6 and log.problems.summary()["skipped"] == 0
    assert [s.bearings is None for s in scans] == [True, False, False, False, True, False]
    for k, scan in enumerate(scans):
        n, a0, inc = interlaced(k)
        np.testing.assert_allclose(
            scan_bearings(scan, cfg.laser), a0 + inc * np.arange(n), atol=1e-9
        )
        assert wall_distance(world_points(scan, cfg, _carmen_pose(k))) < 1e-6


# ------------------------------------------------------------------ front end


def test_front_end_fits_the_same_wall_on_an_interlaced_scan():
    """A wall seen by the configured laser and by a scan interlaced with it (half a beam
    further on, one beam fewer): the two line fits agree within their covariances, and with
    the wall."""
    from fgslam.config import load_config
    from fgslam.frontend.fits import line_ranges
    from fgslam.frontend.pipeline import FrontEnd

    cfg = load_config()
    phi = cfg.laser.bearings
    shifted = phi[:-1] + 0.5 * (phi[1] - phi[0])
    alpha, d = 0.3, 2.5  # the wall, laser frame
    rng = np.random.default_rng(11)
    lines = []
    for b, own in ((phi, None), (shifted, shifted)):
        r = line_ranges(alpha, d, b) + cfg.laser.sigma_range * rng.standard_normal(b.size)
        r[(b < -0.6) | (b > 1.1)] = np.nan
        fe = FrontEnd(cfg, "laser")
        feats = fe.process_scan(LaserScan(1.0, r, own), 0.0, 0.0).features
        (line,) = [f for f in feats if f.kind == "line"]
        lines.append(line)
    a, b = lines
    e = np.array([math.remainder(a.z[0] - b.z[0], 2 * math.pi), a.z[1] - b.z[1]])
    assert e @ np.linalg.solve(a.cov + b.cov, e) < 9.21  # chi-square 2 dof, 99 %
    m = cfg.laser.mount  # the wall in the robot frame
    yaw = math.radians(m.yaw_deg)
    true_d = d + m.x * math.cos(alpha + yaw) + m.y * math.sin(alpha + yaw)
    for f in lines:
        assert math.remainder(f.z[0] - alpha - yaw, 2 * math.pi) == pytest.approx(0, abs=0.01)
        assert f.z[1] == pytest.approx(true_d, abs=0.02)


# ------------------------------------------------------------------ native log


def test_native_log_round_trip_keeps_per_scan_bearings(tmp_path):
    import dataclasses

    from fgslam.config import load_config
    from fgslam.io.logfile import read_log
    from fgslam.io.logrecords import LogFormatError
    from fgslam.io.logwriter import LogWriter

    cfg = load_config()
    cfg = dataclasses.replace(cfg, laser=dataclasses.replace(cfg.laser, n_beams=5))
    events = [
        OdometryEvent(0.1, 3, 2),
        LaserScan(0.2, np.array([1.0, np.nan, 2.0, 2.5, 3.0])),
        LaserScan(0.4, np.array([1.5, 2.0, np.nan, 2.5]), np.array([-0.3, -0.1, 0.1, 0.3])),
        LaserScan(0.6, np.full(6, 2.0), np.linspace(-1.0, 1.0, 6) + 1e-3 / 3),
    ]
    for name in ("g.log", "g.log.gz"):
        with LogWriter(tmp_path / name, cfg, "w") as w:
            for ev in events:
                w.write(ev)
        header, out = read_log(tmp_path / name)
        assert header.version == 2 and out == events
        assert out[1].bearings is None
        assert out[3].bearings.tolist() == events[3].bearings.tolist()  # exact
    text = (tmp_path / "g.log").read_text().splitlines()
    assert text[0] == "FGSLAM-LOG 2" and text[-2].startswith("L 0.4 4 1.5 2.0 nan 2.5 B -0.3 ")
    # a version 1 log still reads: its scans take the header's laser
    old = tmp_path / "old.log"
    head = [ln for ln in text if ln.startswith(("CONFIG", "WORLD"))]
    old.write_text("\n".join(["FGSLAM-LOG 1", *head, "L 0.2 5 1.0 nan 2.0 2.5 3.0"]) + "\n")
    header, out = read_log(old)
    assert header.version == 1 and out == [events[1]]
    # bearings that do not increase, or a beam count that differs without bearings
    for bad in ("L 0.2 2 1.0 2.0 B 0.1 0.1", "L 0.2 2 1.0 2.0", "L 0.2 2 1.0 2.0 B 0.1 inf"):
        old.write_text("\n".join(["FGSLAM-LOG 2", *head, bad]) + "\n")
        with pytest.raises(LogFormatError, match="laser record"):
            read_log(old)
    with pytest.raises(ValueError, match="n_beams=5"):
        LogWriter(tmp_path / "x.log", cfg, "w").write(LaserScan(0.1, np.ones(4)))


# ------------------------------------------------------------------ end to end


def test_convert_and_run_an_interlaced_bag(tmp_path, capsys):
    """fgslam convert writes the interlaced scans with their bearings into the native log,
    and fgslam run (iSAM2, laser) uses every one of them."""
    pytest.importorskip("rosbags")
    from fgslam.cli import main
    from fgslam.io.logfile import read_log

    bag = tmp_path / "i.bag"
    write_bag(bag, [interlaced(k) for k in range(24)], noise=0.005)
    log = tmp_path / "i.log.gz"
    assert main(["convert", str(bag), "--out", str(log)]) == 0
    assert "24 LaserScan" in capsys.readouterr().out
    _, events = read_log(log)
    scans = [e for e in events if isinstance(e, LaserScan)]
    assert len(scans) == 24 and sum(s.bearings is not None for s in scans) == 18
    out = tmp_path / "run"
    argv = ["run", str(log), "--backend", "isam2", "--sensors", "laser", "--out", str(out)]
    assert main(argv) == 0
    rep = json.loads((out / "report.json").read_text())
    assert rep["backend"] == "isam2" and rep["sensors"] == "laser"
    assert rep["scans_placed"] == 24 and rep["statistics"]["scan_matches"] == 23
    traj = np.loadtxt(out / "trajectory.tum", ndmin=2)
    assert len(traj) >= 2
    # the estimate follows the straight drive (0.25 m/s along 0.2 rad)
    end = robot_pose(traj[-1, 0])
    assert math.hypot(traj[-1, 1] - traj[0, 1], traj[-1, 2] - traj[0, 2]) == pytest.approx(
        math.hypot(end[0] - robot_pose(traj[0, 0])[0], end[1] - robot_pose(traj[0, 0])[1]),
        abs=0.1,
    )
