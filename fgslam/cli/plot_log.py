"""``fgslam plot-log``: draw a log: world, true and odometry paths, a scan with sonar."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from fgslam.cli.common import add_log_arguments, reader_options
from fgslam.errors import UserError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "plot-log",
        help="draw a log: world, true and odometry paths, a scan with sonar",
        description=(
            "Draw a log as a PNG: the world (when the log's world is built in, or --world), the "
            "true (or reference) path, the odometry-only path, and one laser scan with the "
            "sonar readings of the 6 s around it, placed with the true poses. Any log `run` "
            "reads."
        ),
    )
    add_log_arguments(
        p, "FILE.png", "image to write ('.png' added without a suffix; a folder: FOLDER/<log>.png)"
    )
    p.add_argument("--world", help="world JSON file, when the log's world is not built in")
    p.add_argument("--scan-time", type=float, help="time (s) of the scan to draw (default: middle)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from fgslam.evaluation.plotting import plot_log
    from fgslam.sim.world import load_world

    world = load_world(args.world) if args.world else None
    info = plot_log(args.log, args.out, world, args.scan_time, reader_options(args))
    extra = ""
    if "odometry_final_error_m" in info:
        extra = f"; odometry-only final position error {info['odometry_final_error_m']:.2f} m"
    print(
        f"wrote {args.out}: {info['scans']} laser scans, {info['sonar_readings']} sonar cycles"
        f"{extra}"
    )
    for w in info["warnings"]:  # the reader's, as every command prints them
        print(f"warning: {w}")
    return 0


def image_path(out: str, log: str) -> str:
    """The file ``plot-log --out`` writes: OUT/<log name>.png for a folder, OUT.png without a
    known image suffix; an unknown image format is refused."""
    from matplotlib.backend_bases import FigureCanvasBase

    from fgslam.io.safeio import is_special

    p = Path(out)
    if is_special(p):
        return out  # /dev/null: written as PNG in place
    if p.is_dir() or out.endswith(("/", os.sep)):
        name = Path(log).name.split(".")[0] or "log"
        return str(p / f"{name}.png")
    suffix = p.suffix.lower().lstrip(".")
    if not suffix:
        return f"{out}.png"
    if suffix not in FigureCanvasBase.get_supported_filetypes():
        known = ", ".join(sorted(FigureCanvasBase.get_supported_filetypes()))
        raise UserError(f"--out {out}: unknown image format '.{suffix}' (known: {known})")
    return out
