"""``fgslam online``: SLAM online on the robot's devices (or emulators) over serial ports."""

from __future__ import annotations

import argparse
import sys

from fgslam.cli.common import (
    add_backend_arguments,
    add_robot_config_argument,
    add_scanmatch_arguments,
    add_speed_argument,
    config_options,
    print_summary,
)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "online",
        help="run SLAM online on the robot's devices (or emulators) over serial ports",
        description=(
            "Open the SICK PLS, the sonar arrays and the odometry board on their serial "
            "ports, run the front end and iSAM2 (or the EKF) incrementally as data arrives, "
            "with a live status line on stderr (pose, landmarks, keyframe latency, per-device "
            "disconnects, CRC errors, dropped frames). A device that disconnects is reopened "
            "while the others go on. On Ctrl-C, or when no data came for --idle-timeout s, "
            "write the outputs of `fgslam run` into --out. With --record every byte received "
            "is also recorded (`fgslam replay` decodes it into a log)."
        ),
        epilog=(
            "With emulated devices: run `fgslam emulate --speed 4` in one terminal and the "
            "command it prints in another."
        ),
    )
    p.add_argument("--laser", metavar="PORT", help="SICK PLS serial port")
    p.add_argument(
        "--sonar",
        action="append",
        metavar="PORT",
        help="sonar array port, once per array in the configuration's order",
    )
    p.add_argument("--odom", metavar="PORT", help="odometry board serial port")
    p.add_argument("--out", required=True, metavar="DIR", help="output directory")
    p.add_argument("--record", metavar="RAW_DIR", help="record every byte received here")
    add_backend_arguments(
        p, ["isam2", "ekf"], "incremental smoothing or the paper's EKF (default isam2)"
    )
    add_robot_config_argument(p)
    add_speed_argument(p)
    p.add_argument(
        "--idle-timeout",
        type=float,
        default=5.0,
        metavar="S",
        help="end of data: stop after S wall s without any data, once data flowed (default 5)",
    )
    p.add_argument(
        "--connect-timeout",
        type=float,
        default=30.0,
        metavar="S",
        help="give up if a device has not answered after S s (default 30)",
    )
    add_scanmatch_arguments(p)
    p.add_argument(
        "--map",
        metavar="SESSION",
        help="localize on this saved session (`fgslam run --save`) instead of mapping: the "
        "outputs of `fgslam localize` (docs/sessions.md)",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from fgslam.config import load_config, with_options
    from fgslam.online.loop import StopSignal, device_summary, online_main

    cfg = with_options(load_config(args.config), config_options(args))
    session = None
    if args.map:
        from fgslam.config import check_against_log
        from fgslam.session import load_session

        session = load_session(args.map)  # refused before any device is opened
        check_against_log(session.robot_config(), cfg, f"the map {args.map}")
    with StopSignal("stopping: processing what has arrived, writing outputs") as sig:
        run, rep = online_main(
            cfg,
            laser=args.laser,
            sonar=args.sonar or [],
            odometry=args.odom,
            out=args.out,
            record=args.record,
            backend=args.backend,
            sensors=args.sensors,
            speed=args.speed,
            idle_timeout=args.idle_timeout,
            connect_timeout=args.connect_timeout,
            stop=sig.event,
            meta={"command": " ".join(sys.argv)},
            session=session,
        )
    print(f"stopped ({run.reason}); events: {dict(sorted(run.events.items()))}")
    print("devices: " + " | ".join(device_summary(n, s) for n, s in run.status.items()))
    if args.record:
        print(f"recorded every byte received into {args.record} (fgslam replay to decode)")
    if session is not None:
        from fgslam.session.outputs import summary

        print(summary(rep))
        print(f"wrote {args.out}/trajectory.tum, trajectory_bridged.tum, report.json, map.png")
        return 0
    print_summary(rep, args.out)
    return 0
