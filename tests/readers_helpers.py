"""Small synthetic logs for the reader tests: a robot in a rectangular room, written as a
corrected or raw CARMEN log, and ROS 1 / ROS 2 bags written with rosbags."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from factors.odometry import integrate_poses
from fgslam.events import LaserScan, OdometryEvent

ROOM = (-2.5, -1.5, 3.0, 2.5)  # x0, y0, x1, y1 (m)
DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"


def ray_rect(pose, bearings, room=ROOM) -> np.ndarray:
    """Ranges from pose (x, y, th) along bearings (robot frame) to the walls of the room."""
    x, y, th = pose
    x0, y0, x1, y1 = room
    a = th + np.asarray(bearings)
    c, s = np.cos(a), np.sin(a)
    with np.errstate(divide="ignore", invalid="ignore"):
        tx = np.where(c > 0, (x1 - x) / c, np.where(c < 0, (x0 - x) / c, np.inf))
        ty = np.where(s > 0, (y1 - y) / s, np.where(s < 0, (y0 - y) / s, np.inf))
    return np.minimum(tx, ty)


def path(n: int = 30) -> list[tuple[float, float, float]]:
    """A smooth drive through the room: forward, a turn, forward."""
    out = []
    for k in range(n):
        u = k / (n - 1)
        th = 1.2 * u
        out.append((-1.5 + 3.0 * u, -0.5 + 1.5 * u * u, th))
    return out


def compose(a, d):
    c, s = math.cos(a[2]), math.sin(a[2])
    return (a[0] + c * d[0] - s * d[1], a[1] + s * d[0] + c * d[1], a[2] + d[2])


def rel(a, b):
    c, s = math.cos(a[2]), math.sin(a[2])
    dx, dy = b[0] - a[0], b[1] - a[1]
    return (c * dx + s * dy, -s * dx + c * dy, b[2] - a[2])


def fmt(v) -> str:
    return " ".join(repr(float(x)) for x in v)


def carmen_text(
    corrected: bool = True,
    n: int = 30,
    beams: int = 180,
    odo_error=(0.02, 0.0, 0.01),
    extra: dict[int, str] | None = None,
    stamp=None,
) -> str:
    """A CARMEN log of the room run. ``corrected``: as a GMapping corrected log (ODOM lines
    restart from the corrected pose, the true pose here), with raw odometry = truth
    increments composed with ``odo_error`` per step; raw: cumulative odometry in ODOM lines.
    ``extra`` puts a line before scan k; ``stamp(k)`` overrides scan k's time."""
    truth = path(n)
    phi = -math.pi / 2 + np.arange(beams) * math.pi / (beams - 1)
    lines = [
        "# message formats defined: PARAM ODOM FLASER",
        "PARAM robot_frontlaser_offset 0.0 h 0",
    ]
    odo = (0.0, 0.0, 0.0)
    for k, p in enumerate(truth):
        t = 1.0 + k if stamp is None else stamp(k)
        inc = compose(rel(truth[k - 1], p), odo_error) if k else (0.0, 0.0, 0.0)
        odo = compose(odo, inc)
        if extra and k in extra:
            lines.append(extra[k])
        if corrected:
            before = compose(truth[k - 1], inc) if k else (0.0, 0.0, 0.0)
            lines.append(f"ODOM {fmt(before)} 0 0 0 {t!r} h {t!r}")
        else:
            lines.append(f"ODOM {fmt(odo)} 0 0 0 {t!r} h {t!r}")
        r = ray_rect(p, phi)
        r[5] = 81.91  # no return
        pose = p if corrected else odo
        lines.append(f"FLASER {beams} {fmt(r)} {fmt(pose)} {fmt(pose)} {t!r} h {t!r}")
        if corrected:
            lines.append(f"ODOM {fmt(p)} 0 0 0 0 h 0")
            lines.append("NEFF 12.5")
    return "\n".join(lines) + "\n"


def bag_drive(k: int) -> tuple[float, float, float]:
    """The pose (x m, y m, theta rad) of odometry message k (from 0) of :func:`write_bag`,
    at 1 + 0.1 k s: 5 cm chords turning 0.02 rad each."""
    x = sum(0.05 * math.cos(0.02 * j + 0.01) for j in range(k))
    y = sum(0.05 * math.sin(0.02 * j + 0.01) for j in range(k))
    return x, y, 0.02 * k


def bag_writer(path, ros1: bool):
    """A rosbags writer of a ROS 1 bag, or of a ROS 2 bag (storage version 8)."""
    if ros1:
        from rosbags.rosbag1 import Writer

        return Writer(path)
    from rosbags.rosbag2 import Writer

    return Writer(path, version=8)


def header_message(T, t: float, frame: str, ros1: bool):
    """A std_msgs/Header stamped ``t`` (s) in ``frame`` (``T``: a typestore's types)."""
    sec = math.floor(t)
    kw = {"stamp": T["builtin_interfaces/msg/Time"](sec=sec, nanosec=round((t - sec) * 1e9))}
    kw["frame_id"] = frame
    if ros1:
        kw["seq"] = 0
    return T["std_msgs/msg/Header"](**kw)


def odometry_message(T, header, child: str, pose):
    """A nav_msgs/Odometry of ``pose`` (a geometry_msgs/Pose), zero twist and covariances."""
    zero3 = T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
    return T["nav_msgs/msg/Odometry"](
        header=header,
        child_frame_id=child,
        pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
        twist=T["geometry_msgs/msg/TwistWithCovariance"](
            twist=T["geometry_msgs/msg/Twist"](linear=zero3, angular=zero3),
            covariance=np.zeros(36),
        ),
    )


def laser_scan_message(T, header, ranges, angle_min, angle_max, increment, scan_time):
    """A sensor_msgs/LaserScan of ``ranges`` (float32; 0.05 to 30 m), no intensities."""
    return T["sensor_msgs/msg/LaserScan"](
        header=header,
        angle_min=angle_min,
        angle_max=angle_max,
        angle_increment=increment,
        time_increment=0.0,
        scan_time=scan_time,
        range_min=0.05,
        range_max=30.0,
        ranges=ranges,
        intensities=np.zeros(0, dtype=np.float32),
    )


def write_bag(
    path,
    ros1: bool,
    n: int = 10,
    backwards_scan: int | None = None,
    with_range: bool = True,
    zero_stamps: bool = False,
    jump: int | None = None,
    header=None,
    record=None,
    frozen: range = range(0),
    shift: tuple[int, float] | None = None,
    paused: range = range(0),
) -> None:
    """A bag with /scan (181 beams over 180 deg), /odom (two messages per scan, the robot
    advancing 5 cm and turning 0.02 rad per message, :func:`bag_drive`) and /sonar
    (sensor_msgs/Range, one out-of-range reading). ``zero_stamps``: every header stamp 0
    (the record times stay); ``jump``: odometry message ``jump`` 1e6 m off; ``frozen``: the
    odometry messages in it repeat the pose of message ``frozen.start - 1`` (the stream froze
    while the robot drove on); ``shift`` = (k, dx): odometry messages k and after dx m off in
    x (the odometry jumped and continued from there); ``header(topic, k, t)`` / ``record(topic,
    k, t)``: the header stamp / record time of the k-th message (from 0) of a topic instead of
    ``t``; ``paused``: the odometry messages in it are left out (the stream paused while the
    robot drove on)."""
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    T = ts.types
    count = {"/scan": 0, "/odom": 0, "/sonar": 0}

    def hdr(t, frame):
        topic = {"odom": "/odom", "laser": "/scan", "sonar": "/sonar"}[frame]
        if header is not None:
            t = header(topic, count[topic], t)
        if zero_stamps:  # an unset header: the bag's record time is the only clock
            t = 0.0
        return header_message(T, t, frame, ros1)

    writer = bag_writer(path, ros1)
    g = {k.split("/")[-1]: T[k] for k in T if k.startswith("geometry_msgs/msg/")}
    ser = ts.serialize_ros1 if ros1 else ts.serialize_cdr

    def put(conn, topic, t, data):
        ns = round(1e9 * (record(topic, count[topic], t) if record else t))
        count[topic] += 1
        writer.write(conn, ns, data)

    with writer:
        cs = writer.add_connection("/scan", "sensor_msgs/msg/LaserScan", typestore=ts)
        co = writer.add_connection("/odom", "nav_msgs/msg/Odometry", typestore=ts)
        cr = None
        if with_range:
            cr = writer.add_connection("/sonar", "sensor_msgs/msg/Range", typestore=ts)
        for k in range(2 * n):
            t = 1.0 + 0.1 * k
            x, y, th = bag_drive(frozen.start - 1 if k in frozen else k)
            q = g["Quaternion"](x=0.0, y=0.0, z=math.sin(th / 2), w=math.cos(th / 2))
            if jump is not None and k == jump:
                x += 1e6  # a corrupt odometry message
            if shift is not None and k >= shift[0]:
                x += shift[1]  # the odometry jumped and stayed
            pose = g["Pose"](position=g["Point"](x=x, y=y, z=0.0), orientation=q)
            if k not in paused:
                odom = odometry_message(T, hdr(t, "odom"), "base_link", pose)
                put(co, "/odom", t, ser(odom, "nav_msgs/msg/Odometry"))
            if k % 2 == 0:
                continue
            stamp = t - 0.5 if k == backwards_scan else t
            r = np.full(181, 2.0, dtype=np.float32)
            r[0], r[1], r[2] = np.inf, 0.01, 40.0  # no return, below range_min, beyond max
            scan = laser_scan_message(
                T, hdr(stamp, "laser"), r, -math.pi / 2, math.pi / 2, math.pi / 180, 0.1
            )
            put(cs, "/scan", t, ser(scan, "sensor_msgs/msg/LaserScan"))
            if cr is not None:
                rng = T["sensor_msgs/msg/Range"](
                    header=hdr(t, "sonar"),
                    radiation_type=0,
                    field_of_view=0.3,
                    min_range=0.1,
                    max_range=5.0,
                    range=9.0 if k == 3 else 1.5,
                )
                put(cr, "/sonar", t, ser(rng, "sensor_msgs/msg/Range"))


def write_native(path, n: int = 30, stamp=None, t0: float = 0.0) -> None:
    """A native fgslam log of ``n`` scan periods of 0.2 s from ``t0``, in time order: per
    period four odometry records (3 ticks right, 2 left each), a sonar and a truth record
    between them, then a 5-beam scan. ``stamp(kind, k, t)`` (kind ``odometry``, ``sonar``,
    ``truth`` or ``laser``; k counts that kind from 0) gives a record's stamp instead of
    ``t``; the first odometry record is at ``t0`` itself (a clock may start at 0)."""
    import dataclasses

    from fgslam.config import load_config
    from fgslam.events import LaserScan, OdometryEvent, SonarReading, TruthPose
    from fgslam.io.logwriter import LogWriter

    cfg = load_config()
    cfg = dataclasses.replace(cfg, laser=dataclasses.replace(cfg.laser, n_beams=5))
    stamp = stamp or (lambda kind, k, t: t)
    count = {"odometry": 0, "sonar": 0, "truth": 0, "laser": 0}

    def at(kind: str, t: float) -> float:
        k = count[kind]
        count[kind] += 1
        return float(stamp(kind, k, t))

    with LogWriter(path, cfg, "synthetic") as w:
        for p in range(n):
            base = t0 + 0.2 * p
            for j in range(4):
                w.write(OdometryEvent(at("odometry", base + 0.05 * j), 3, 2))
                if j == 1:
                    w.write(SonarReading(at("sonar", base + 0.07), 0, 0.0, ()))
                if j == 2:
                    w.write(TruthPose(at("truth", base + 0.1), 0.01 * p, 0.0, 0.0))
            w.write(LaserScan(at("laser", base + 0.15), np.full(5, 2.0)))


def odometry_at(events, odometry, kind=LaserScan) -> np.ndarray:
    """The odometry pose integrated (``odometry``: the configuration's section) from the
    delivered samples at each event of ``kind``."""
    o = odometry
    pose, out = np.zeros(3), []
    for e in events:
        if isinstance(e, OdometryEvent):
            lr, ll = e.ticks_right * o.metres_per_tick_right, e.ticks_left * o.metres_per_tick_left
            pose = integrate_poses([lr], [ll], o.wheelbase, pose)[-1]
        elif isinstance(e, kind):
            out.append(pose.copy())
    return np.array(out)
