"""The paper's Fig. 4: a wall with a recessed door and a table leg, segmented without and with
sonar.

Run: python experiments/frontend_segmentation.py [--seed 0] [--quiet-sensors]
The scene of tests/test_frontend.py (``FIG4``): a wall 2.5 m ahead of a standing robot, a
door 0.9 m wide recessed by 4 cm, and a table leg (3 cm radius) 0.5 m in front of the wall.
The robot stands still for 13 s while both sonar arrays sweep; one laser scan at 6.5 s is
segmented by the front end in "laser" mode and in "fused" mode (sonar readings from 6 s
before to 6 s after it). The simulator's default sensor errors are used unless
``--quiet-sensors`` (the test's small errors). Prints, for both modes, every segment with its
start and end conditions and its fitted line, and draws frontend_segmentation.png next to this
file: laser points coloured per segment (grey: in no line), fitted lines, end conditions, and
the sonar readings of the window moved into the laser frame by class.
Coordinates in the figure are the world's (the robot at the origin facing +y).
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from fgslam.config import load_config
from fgslam.events import LaserScan
from fgslam.frontend import pipeline
from fgslam.frontend.features import End
from fgslam.sim.scenes import QUIET, standing_scene
from fgslam.sim.sensors import SimParams
from fgslam.sim.world import parse_world

# the scene of tests/test_frontend.py::FIG4
FIG4 = {
    "walls": [{"id": "w", "points": [[-5.0, 2.5], [5.0, 2.5]]}],
    "doors": [{"wall": "w", "at": 5.3, "width": 0.9, "recess": 0.04, "side": "left"}],
    "legs": [{"x": -1.2, "y": 2.0, "radius": 0.03}],
}
POSE = (0.0, 0.0, math.pi / 2)  # the robot faces the wall
T_SCAN = 6.5
END_CODE = {
    End.DISCONTINUITY: "D",
    End.SPREAD: "P",
    End.OUTLIERS: "O",
    End.MAX_RANGE: "R",
    End.FIELD_OF_VIEW: "F",
    End.SONAR: "S",
}
SONAR_STYLE = {
    0: ("s", "tab:blue", "plane"),
    1: ("^", "tab:red", "corner"),
    2: ("o", "tab:green", "edge"),
}


def scene_events(cfg, params, seed):
    """A robot standing at POSE for 13 s in FIG4 (:func:`fgslam.sim.scenes.standing_scene`):
    odometry without motion, both sonar arrays sweeping, one laser scan at T_SCAN."""
    evs, _ = standing_scene(FIG4, POSE, seed, params, cfg, T_SCAN)
    return evs, parse_world({"name": "fig4", **FIG4}, "<fig4>")


def run(cfg, evs, mode):
    """The front end on the scene, capturing what it segmented and the sonar points it used."""
    seen = {}
    seg_fn, cl_fn = pipeline.segment_scan, pipeline.cluster

    def segment_scan(*a, **kw):
        seen["segments"], seen["rejected"] = out = seg_fn(*a, **kw)
        return out

    def cluster(pts, *a, **kw):
        seen["pts"] = pts
        seen["clusters"] = out = cl_fn(pts, *a, **kw)
        return out

    pipeline.segment_scan, pipeline.cluster = segment_scan, cluster
    try:
        fe = pipeline.FrontEnd(cfg, mode)
        out = [sf for ev in evs for sf in fe.add(ev)] + fe.finish()
    finally:
        pipeline.segment_scan, pipeline.cluster = seg_fn, cl_fn
    (sf,) = out
    return sf, seen


def to_world(xy_laser, cfg):
    """Laser frame -> world (robot at the origin facing +y)."""
    m = cfg.laser.mount
    xr, yr = xy_laser[..., 0] + m.x, xy_laser[..., 1] + m.y
    return np.stack([-yr, xr], axis=-1)


def segment_ends(seg, r, phi, cfg):
    """World positions of a segment's first and last points."""
    idx = [seg.first, seg.last]
    return to_world(np.column_stack([r[idx] * np.cos(phi[idx]), r[idx] * np.sin(phi[idx])]), cfg)


def to_world_robot(xy_robot):
    """Robot frame -> world (robot at the origin facing +y)."""
    xy_robot = np.asarray(xy_robot, dtype=float)
    return np.stack([-xy_robot[..., 1], xy_robot[..., 0]], axis=-1)


def near_leg(f) -> bool:
    """The line's segment passes within 0.2 m of the table leg."""
    e = to_world_robot(f.endpoints)
    leg = np.array([FIG4["legs"][0]["x"], FIG4["legs"][0]["y"]])
    ab = e[1] - e[0]
    t = np.clip((leg - e[0]) @ ab / max(ab @ ab, 1e-12), 0, 1)
    return bool(np.hypot(*(e[0] + t * ab - leg)) < 0.2)


def door_line(sf) -> tuple[float, float] | None:
    """World x of the ends of a line lying on the door only (x 0.3..1.2, at least 0.5 m)."""
    for f in sf.features:
        if f.kind == "line":
            x0, x1 = np.sort(to_world_robot(f.endpoints)[:, 0])
            if 0.25 < x0 and x1 < 1.25 and x1 - x0 >= 0.5:
                return float(x0), float(x1)
    return None


def across_jamb(sf) -> bool:
    """A line running more than 5 cm past a door jamb on both sides of it."""
    for f in sf.features:
        if f.kind == "line":
            x0, x1 = np.sort(to_world_robot(f.endpoints)[:, 0])
            if any(x0 < xj - 0.05 and x1 > xj + 0.05 for xj in (0.3, 1.2)):
                return True
    return False


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0, help="seed of the scene drawn")
    ap.add_argument("--seeds", type=int, default=10, help="seeds in the summary")
    ap.add_argument("--quiet-sensors", action="store_true", help="the test's small errors")
    args = ap.parse_args()
    cfg = load_config()
    params = QUIET if args.quiet_sensors else SimParams()
    evs, _ = scene_events(cfg, params, args.seed)
    phi = cfg.laser.bearings
    r = next(e for e in evs if isinstance(e, LaserScan)).ranges
    xy = to_world(np.column_stack([r * np.cos(phi), r * np.sin(phi)]), cfg)
    fig, axes = plt.subplots(2, 1, figsize=(14, 8.4), sharex=True)
    print(
        f"scene FIG4, seed {args.seed}, {'quiet' if args.quiet_sensors else 'default'} sensor "
        "errors; world x (m): door 0.30..1.20 (recessed 4 cm), table leg at -1.20 (y 2.0); "
        "the scan runs from world x +5 (first beam) to -5"
    )
    for ax, mode in zip(axes, ("laser", "fused"), strict=True):
        sf, seen = run(cfg, evs, mode)
        segs = seen["segments"]
        lines = [f for f in sf.features if f.kind == "line"]
        print(f"\n{mode}: {len(segs)} segments, {seen['rejected']['too_few_points']} too short")
        print(
            "| segment | beams   | points | world x from .. to (m) | start         | end  "
            "         | line d (m) | sonar support |"
        )
        print(
            "|---------|---------|--------|------------------------|---------------|------"
            "---------|------------|---------------|"
        )
        ax.plot(xy[:, 0], xy[:, 1], ".", color="0.6", ms=4, label="laser points in no line")
        colours = plt.get_cmap("tab10")
        for k, s in enumerate(segs):
            col = colours(k % 10)
            pts = xy[s.first : s.last + 1]
            ax.plot(pts[:, 0], pts[:, 1], ".", color=col, ms=5)
            a, b = segment_ends(s, r, phi, cfg)
            # the line fitted to this segment (features are in the robot frame, in scan order)
            line = min(
                lines,
                key=lambda f: (
                    np.hypot(*(to_world_robot(f.endpoints[0]) - a))
                    + np.hypot(*(to_world_robot(f.endpoints[1]) - b))
                ),
                default=None,
            )
            d_txt, sup = "-", "-"
            if line is not None:
                e = to_world_robot(line.endpoints)
                ax.plot(e[:, 0], e[:, 1], "-", color=col, lw=2.5)
                d_txt, sup = f"{line.z[1]:.3f}", str(line.sonar_support)
            ax.plot([b[0], b[0]], [b[1] - 0.06, b[1] - 0.02], "-", color=col, lw=1.5)
            ax.annotate(
                END_CODE[s.end],
                (b[0], b[1] - 0.06),
                xytext=(0, -10),
                textcoords="offset points",
                ha="center",
                fontsize=10,
                color=col,
                fontweight="bold",
            )
            x0, x1 = sorted((a[0], b[0]))
            print(
                f"| {k:7d} | {s.first:3d}-{s.last:3d} | {s.n:6d} | {x0:+9.2f} .. {x1:+9.2f} "
                f"| {s.start.value:13s} | {s.end.value:13s} | {d_txt:>10s} | {sup:>13s} |"
            )
        others = [f for f in sf.features if f.kind != "line"]
        for f in others:
            q = to_world_robot(np.array([f.z[1] * math.cos(f.z[0]), f.z[1] * math.sin(f.z[0])]))
            ax.plot(*q, "kx", ms=9, mew=2)
        if others:
            ax.plot([], [], "kx", ms=9, mew=2, label="point / corner features")
        print(
            "features: "
            + ", ".join(f"{sf.count(k)} {k}s" for k in ("line", "corner", "point"))
            + f"; lines within 0.2 m of the leg: {sum(1 for f in lines if near_leg(f))}"
        )
        if mode == "fused":
            pts = seen["pts"]
            w = to_world(pts.xy, cfg)
            for code, (marker, col, name) in SONAR_STYLE.items():
                sel = pts.kind == code
                ax.plot(
                    w[sel, 0],
                    w[sel, 1],
                    marker,
                    color=col,
                    ms=4,
                    alpha=0.6,
                    mfc="none",
                    label=f"sonar {name} echoes ({int(sel.sum())}, laser frame)",
                )
        leg = FIG4["legs"][0]
        ax.add_patch(
            plt.Rectangle((leg["x"] - 0.03, leg["y"] - 0.03), 0.06, 0.06, fill=False, ec="k")
        )
        ax.set(
            title=f"{mode}: {len(lines)} lines"
            + (" (laser and sonar)" if mode == "fused" else " (laser only)"),
            ylabel="world y (m)",
            xlim=(-5.3, 5.3),
            ylim=(1.8, 2.72),
        )
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="lower right", ncol=2)
    axes[1].set_xlabel("world x (m); the robot stands at (0, 0) facing +y")
    fig.text(
        0.5,
        0.005,
        "end conditions (below each segment's last point): S sonar cluster, D discontinuity, "
        "O next 3 points off the line, P spread, R max range, F field of view; "
        "square: the table leg",
        ha="center",
        fontsize=9,
    )
    fig.tight_layout(rect=(0, 0.025, 1, 1))
    fig.savefig(Path(__file__).with_suffix(".png"), dpi=75)

    # the same scene over several seeds
    rows = {m: {"door": [], "across": 0, "leg": 0} for m in ("laser", "fused")}
    for seed in range(args.seeds):
        evs_s, _ = scene_events(cfg, params, seed)
        for mode in ("laser", "fused"):
            sf, _ = run(cfg, evs_s, mode)
            row = rows[mode]
            d = door_line(sf)
            if d is not None:
                row["door"].append(d)
            row["across"] += across_jamb(sf)
            row["leg"] += any(near_leg(f) for f in sf.features if f.kind == "line")
    n = args.seeds
    print(f"\nseeds 0..{n - 1} (door x 0.30..1.20):")
    print(
        "| mode  | a line on the door only | its ends, mean x (m) | a line across a jamb "
        "| a line at the leg |"
    )
    print(
        "|-------|-------------------------|----------------------|----------------------"
        "|-------------------|"
    )
    for mode, row in rows.items():
        ends = np.mean(row["door"], axis=0) if row["door"] else None
        e = f"{ends[0]:.2f} .. {ends[1]:.2f}" if ends is not None else "-"
        print(
            f"| {mode:5s} | {len(row['door']):17d} / {n:<3d} | {e:>20s} "
            f"| {row['across']:14d} / {n:<3d} | {row['leg']:11d} / {n:<3d} |"
        )


if __name__ == "__main__":
    main()
