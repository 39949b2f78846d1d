"""``fgslam simulate``: simulate a run of the robot in a world and write a log."""

from __future__ import annotations

import argparse

from fgslam.cli.common import add_simulation_arguments, progress_bar
from fgslam.errors import UserError


def register(sub: argparse._SubParsersAction) -> None:
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
    add_simulation_arguments(p)
    p.add_argument("--out", required=True, metavar="FILE.log", help="log file to write")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import time

    from fgslam.config import load_config
    from fgslam.sim import simulate_to_log
    from fgslam.sim.world import load_world

    cfg = load_config(args.config)
    world = load_world(args.world)
    if args.duration is not None and args.duration <= 0:
        raise UserError(f"--duration must be positive, got {args.duration}")
    t0 = time.perf_counter()
    bar = progress_bar("simulating")
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
