"""``fgslam localize``: localization on a saved session (docs/sessions.md)."""

from __future__ import annotations

import argparse

from fgslam.cli.common import add_log_arguments, log_progress, parse_pose, reader_options
from fgslam.errors import UserError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "localize",
        help="track the robot's pose on a map saved by `fgslam run --save`",
        description=(
            "Localize a log on a saved session: the map stays fixed, each scan is matched "
            "against the map's scans near the pose the wheels predict, the last matched poses "
            "smoothed with the odometry between them. Without --initial-pose the pose is "
            "found by a global search over the whole map (every place, every heading), "
            "confirmed over several scans; a robot lost (matches failing in a row: kidnapped) "
            "is searched for again. Writes trajectory.tum (every localized scan), "
            "trajectory_bridged.tum (every scan: those not localized placed by the odometry "
            "between localized ones, an offline estimate), "
            "report.json (when it was localized and how confidently, lost spells, speed, the "
            "error against the log's truth if it has one) and map.png (the map's grid with "
            "the path) into --out. The [localize] section of the configuration sets the "
            "search (fgslam config --show)."
        ),
    )
    add_log_arguments(p, "DIR", "output directory", config=True, tolerant=True)
    p.add_argument("--map", required=True, metavar="SESSION", help="session folder to localize on")
    p.add_argument(
        "--initial-pose",
        metavar="X,Y,THETA",
        type=parse_pose,
        help="the start pose in the map's frame (m, m, rad); default: search the whole map",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from fgslam.cli.run import _run_config
    from fgslam.config import check_against_log
    from fgslam.io.formats import open_log
    from fgslam.session import load_session
    from fgslam.session.localize import Localizer
    from fgslam.session.outputs import summary, write_localization

    session = load_session(args.map)
    reader = open_log(args.log, **reader_options(args))
    cfg = _run_config(reader, args.config, args.log)
    saved = session.robot_config()
    try:
        check_against_log(saved, reader.config, str(args.log))
    except UserError as e:
        raise UserError(f"the map {args.map} was made by another robot: {e}") from None
    progress = log_progress(reader, "localize")
    loc = Localizer(session, cfg, args.initial_pose, progress=progress)
    try:
        for ev in reader:
            loc.add(ev)
        res = loc.finish()
    finally:
        progress.close()
    rep = write_localization(session, res, args.out, {"map": str(args.map), "log": str(args.log)})
    print(summary(rep))
    print(f"wrote {args.out}/trajectory.tum, trajectory_bridged.tum, report.json, map.png")
    return 0 if rep["localized_at"] is not None else 1
