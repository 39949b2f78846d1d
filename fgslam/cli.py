"""The ``fgslam`` command line. Each subcommand has its own ``--help``.

Bad input is reported as one line on stderr with exit status 2; no traceback reaches the user
for a problem with their files or options.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable, Sequence

from fgslam import __version__
from fgslam.errors import UserError

EPILOG = """\
Typical use:
  fgslam config                         show the default robot configuration (TOML)
  fgslam config --config my_robot.toml  validate your robot file and show the merged result
  fgslam simulate --seed 1 --out run.log.gz     the paper's lab-and-corridor run, simulated
  fgslam plot-log run.log.gz --out run.png      look at it

Frames follow REP-103 (x forward, y left, yaw counter-clockwise); units are SI.
"""


def _cmd_config(args: argparse.Namespace) -> int:
    import tomli_w

    from fgslam.config import load_config

    cfg = load_config(args.config)
    data = cfg.to_dict()
    if args.json:
        print(json.dumps(data, indent=2))
    else:
        print(f"# robot configuration from {cfg.source}")
        print(tomli_w.dumps(data), end="")
    return 0


def _progress_bar(desc: str, unit: str = "s"):
    """A tqdm bar driven by (value, total) calls; silent when stderr is not a terminal."""
    from tqdm import tqdm

    state: dict = {}

    def update(value: float, total: float) -> None:
        bar = state.get("bar")
        if bar is None:
            bar = state["bar"] = tqdm(
                total=round(total, 1), desc=desc, unit=unit, disable=None, leave=False
            )
        step = round(value, 1) - bar.n
        if step >= 1.0 or value >= total:
            bar.update(step)

    def close() -> None:
        if "bar" in state:
            state["bar"].close()

    update.close = close  # type: ignore[attr-defined]
    return update


def _cmd_simulate(args: argparse.Namespace) -> int:
    import time

    from fgslam.config import load_config
    from fgslam.sim import simulate_to_log
    from fgslam.sim.world import load_world

    cfg = load_config(args.config)
    world = load_world(args.world)
    if args.duration is not None and args.duration <= 0:
        raise UserError(f"--duration must be positive, got {args.duration}")
    t0 = time.perf_counter()
    bar = _progress_bar("simulating")
    try:
        run = simulate_to_log(world, cfg, args.out, args.seed, args.duration, progress=bar)
    except ValueError as exc:
        raise UserError(str(exc)) from None
    finally:
        bar.close()
    wall = time.perf_counter() - t0
    print(
        f"wrote {args.out}: world '{world.name}', seed {args.seed}, {run.duration:.1f} s "
        f"simulated, {run.distance:.1f} m travelled, in {wall:.1f} s "
        f"({run.duration / wall:.0f}x real time)"
    )
    return 0


def _cmd_plot_log(args: argparse.Namespace) -> int:
    from fgslam.logfile import LogReader
    from fgslam.plotting import plot_log
    from fgslam.sim.world import BUILTIN_WORLDS, load_world

    world = None
    if args.world:
        world = load_world(args.world)
    else:
        with LogReader(args.log) as reader:
            name = reader.world
        if name in BUILTIN_WORLDS:
            world = load_world(name)
    info = plot_log(args.log, args.out, world, args.scan_time)
    extra = ""
    if "odometry_final_error_m" in info:
        extra = f"; odometry-only final position error {info['odometry_final_error_m']:.2f} m"
    print(
        f"wrote {args.out}: {info['scans']} laser scans, {info['sonar_readings']} sonar cycles"
        f"{extra}"
    )
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="fgslam",
        description=(
            "Laser + advanced sonar SLAM (lines, right-angle corners, points) as a GTSAM "
            "factor graph (iSAM2 or batch), with the paper's EKF kept for comparison."
        ),
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"fgslam {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    p = sub.add_parser(
        "config",
        help="show or validate a robot configuration",
        description=(
            "Print the effective robot configuration: the shipped default (the paper's "
            "SLAMbot) overridden by --config FILE. Any subset of keys may be overridden; an "
            "unknown key, a missing value or a wrong type is reported with file and key. "
            "Redirect the output to a file to start your own robot configuration."
        ),
    )
    p.add_argument("--config", metavar="ROBOT.toml", help="TOML file overriding the default")
    p.add_argument("--json", action="store_true", help="print JSON instead of TOML")
    p.set_defaults(func=_cmd_config)

    p = sub.add_parser(
        "simulate",
        help="simulate a run of the robot in a world and write a log",
        description=(
            "Simulate SLAMbot driving a world's route (the built-in 'corridor' is the paper's "
            "experiment: loops in a lab, out along a 60 m corridor to both ends and back) with "
            "odometry, the SICK PLS and two panning advanced sonar arrays, and write the native "
            "log (docs/log-format.md; '.gz' to compress) with ground truth. Deterministic for a "
            "given seed."
        ),
    )
    p.add_argument("--world", default="corridor", help="built-in world name or world JSON file")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument(
        "--duration", type=float, help="stop after this many seconds (default: whole route)"
    )
    p.add_argument(
        "--config", metavar="ROBOT.toml", help="robot configuration overriding the default"
    )
    p.add_argument("--out", required=True, metavar="FILE.log", help="log file to write")
    p.set_defaults(func=_cmd_simulate)

    p = sub.add_parser(
        "plot-log",
        help="draw a log: world, true and odometry paths, a scan with sonar",
        description=(
            "Draw a log as a PNG: the world (when the log's world is built in, or --world), the "
            "true path, the odometry-only path, and one laser scan with the sonar readings of "
            "the 6 s around it, placed with the true poses."
        ),
    )
    p.add_argument("log", help="native log file (.log or .log.gz)")
    p.add_argument("--out", required=True, metavar="FILE.png", help="image to write")
    p.add_argument("--world", help="world JSON file, when the log's world is not built in")
    p.add_argument("--scan-time", type=float, help="time (s) of the scan to draw (default: middle)")
    p.set_defaults(func=_cmd_plot_log)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    func: Callable[[argparse.Namespace], int] | None = getattr(args, "func", None)
    if func is None:
        parser.print_help()
        return 0
    try:
        return func(args)
    except UserError as exc:
        print(f"fgslam {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"fgslam {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
