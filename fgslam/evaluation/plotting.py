"""Figures people would rather look at than read: logs, worlds and trajectories (world frame,
metres). Uses matplotlib's non-interactive Agg backend."""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from factors.odometry import integrate_poses, ticks_to_distances
from fgslam.events import LaserScan, OdometryEvent, SonarReading, TruthPose, scan_bearings
from fgslam.io.safeio import atomic_path
from fgslam.sim.world import World

SONAR_STYLE = {"plane": ("s", "tab:blue"), "corner": ("^", "tab:red"), "edge": ("o", "tab:green")}


def draw_world(ax: plt.Axes, world: World) -> None:
    """Walls (black), glass (cyan), legs (grey dots), mouldings (small ticks)."""
    for pl in world.polylines:
        ax.plot(pl[:, 0], pl[:, 1], "k-", lw=1.0)
    for g in world.glass:
        ax.plot(g[:, 0], g[:, 1], "c-", lw=2.0, label="glass")
    if len(world.legs):
        ax.plot(world.legs[:, 0], world.legs[:, 1], ".", color="0.4", ms=3)
    if len(world.mouldings):
        ax.plot(world.mouldings[:, 0], world.mouldings[:, 1], "|", color="0.3", ms=4)


def plot_log(
    path: str | Path,
    out: str | Path,
    world: World | None,
    scan_time: float | None,
    options: dict | None = None,
) -> dict:
    """Draw a log (any format :func:`fgslam.io.formats.open_log` reads, with reader ``options``):
    the world (``world``, or the log's when it is built in), the true or reference path, the
    odometry-only path, and one laser scan with the sonar readings of the 6 s before and
    after it (placed with the true poses when the log has them, else with odometry). The
    image is written atomically. Returns a few numbers about the log, and the reader's
    warnings (``"warnings"``: ``problems.warnings()``, for the console)."""
    from fgslam.io.formats import open_log
    from fgslam.sim.world import BUILTIN_WORLDS, load_world

    reader = open_log(path, **(options or {}))
    cfg = reader.config
    if world is None and reader.world in BUILTIN_WORLDS:
        world = load_world(reader.world)
    t_truth, truth, t_odo, ticks = [], [], [], []
    scans: list[LaserScan] = []
    sonar: list[SonarReading] = []
    for ev in reader:
        if isinstance(ev, OdometryEvent):
            t_odo.append(ev.t)
            ticks.append((ev.ticks_right, ev.ticks_left))
        elif isinstance(ev, TruthPose):
            t_truth.append(ev.t)
            truth.append((ev.x, ev.y, ev.theta))
        elif isinstance(ev, LaserScan):
            scans.append(ev)
        elif isinstance(ev, SonarReading):
            sonar.append(ev)
    truth_a = np.array(truth).reshape(-1, 3)
    start = tuple(truth_a[0]) if len(truth_a) else (0.0, 0.0, 0.0)
    odo_path = np.zeros((0, 3))
    if ticks:
        tk = np.array(ticks, dtype=float)
        o = cfg.odometry
        lr, ll = ticks_to_distances(
            tk[:, 0], tk[:, 1], o.metres_per_tick_right, o.metres_per_tick_left
        )
        odo_path = integrate_poses(lr, ll, o.wheelbase, start)
    # pose lookup for drawing sensor data: truth if present, else odometry
    ref_t, ref = (np.array(t_truth), truth_a) if len(truth_a) else (np.array(t_odo), odo_path)

    def pose_at(t: float) -> np.ndarray:
        if len(ref) == 0:
            return np.zeros(3)
        return ref[int(np.clip(np.searchsorted(ref_t, t), 0, len(ref) - 1))]

    fig, ax = plt.subplots(
        figsize=(14, 6) if world and np.ptp(world.sonar_segments[:, [0, 2]]) > 30 else (8, 7)
    )
    if world is not None:
        draw_world(ax, world)
    if len(truth_a):
        ax.plot(truth_a[:, 0], truth_a[:, 1], "-", color="tab:green", lw=1.2, label="true path")
    if len(odo_path):
        ax.plot(
            odo_path[:, 0], odo_path[:, 1], "--", color="tab:orange", lw=1.0, label="odometry only"
        )
    info = {"scans": len(scans), "sonar_readings": len(sonar), "odometry_samples": len(t_odo)}
    info["warnings"] = reader.problems.warnings()
    if scans:
        if scan_time is None:
            scan_time = scans[len(scans) // 2].t
        scan = min(scans, key=lambda s: abs(s.t - scan_time))
        m = cfg.laser.mount
        x, y, th = pose_at(scan.t)
        c, s_ = math.cos(th), math.sin(th)
        lx, ly, lth = x + c * m.x - s_ * m.y, y + s_ * m.x + c * m.y, th + math.radians(m.yaw_deg)
        b = scan_bearings(scan, cfg.laser) + lth
        ok = np.isfinite(scan.ranges)
        ax.plot(
            lx + scan.ranges[ok] * np.cos(b[ok]),
            ly + scan.ranges[ok] * np.sin(b[ok]),
            ".",
            color="tab:purple",
            ms=2.5,
            label=f"laser scan at t = {scan.t:.1f} s",
        )
        pts: dict[str, list] = {k: [] for k in SONAR_STYLE}
        for rd in sonar:
            if abs(rd.t - scan.t) > 6.0:
                continue
            arr = cfg.sonar.arrays[rd.array]
            px, py, pth = pose_at(rd.t)
            c, s_ = math.cos(pth), math.sin(pth)
            mx, my = arr.mount.x, arr.mount.y
            sx, sy = px + c * mx - s_ * my, py + s_ * mx + c * my
            sth = pth + math.radians(arr.mount.yaw_deg) + rd.pan
            for e in rd.echoes:
                pts[e.kind].append(
                    (
                        sx + e.range * math.cos(sth + e.bearing),
                        sy + e.range * math.sin(sth + e.bearing),
                    )
                )
        for kind, p in pts.items():
            if p:
                a = np.array(p)
                mk, col = SONAR_STYLE[kind]
                ax.plot(
                    a[:, 0], a[:, 1], mk, color=col, ms=3, mfc="none", label=f"sonar {kind} (+-6 s)"
                )
        info["scan_time"] = scan.t
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(f"{Path(path).name}: world '{reader.world}'")
    handles, labels = ax.get_legend_handles_labels()
    uniq = dict(zip(labels, handles, strict=True))
    ax.legend(uniq.values(), uniq.keys(), loc="best", fontsize=7)
    fig.tight_layout()
    with atomic_path(out) as tmp:
        fig.savefig(tmp, dpi=130, format=Path(out).suffix.lstrip(".").lower() or "png")
    plt.close(fig)
    if len(truth_a) and len(odo_path):
        info["odometry_final_error_m"] = float(np.hypot(*(odo_path[-1, :2] - truth_a[-1, :2])))
    return info
