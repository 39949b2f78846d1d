"""``fgslam emulate``: the robot's devices emulated on pseudo-terminals, fed by a simulated run."""

from __future__ import annotations

import argparse

from fgslam.cli.common import add_simulation_arguments, add_speed_argument


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "emulate",
        help="emulate the robot's devices on pseudo-terminals, fed by a simulated run",
        description=(
            "Start emulators of the SICK PLS, the two advanced sonar arrays and the odometry "
            "board on pseudo-terminals, byte for byte in their protocols (docs/devices.md), "
            "print their ports and the `fgslam online` command to use, and play a simulated "
            "run of the world into them once a host streams from every port. Stops at the "
            "end of the run or on Ctrl-C. Faults (noise, dropped bytes, bit flips, cable "
            "pulls) can be injected."
        ),
    )
    add_simulation_arguments(p)
    add_speed_argument(p)
    p.add_argument(
        "--link-dir",
        metavar="DIR",
        help="put the port links (laser, sonar0, sonar1, odometry) here (default: a temp dir)",
    )
    p.add_argument(
        "--noise",
        type=float,
        default=0.0,
        metavar="P",
        help="fault: probability of random bytes before a frame",
    )
    p.add_argument(
        "--drop",
        type=float,
        default=0.0,
        metavar="P",
        help="fault: probability of losing bytes of a frame",
    )
    p.add_argument(
        "--flip",
        type=float,
        default=0.0,
        metavar="P",
        help="fault: probability of a flipped bit in a frame",
    )
    p.add_argument(
        "--disconnect",
        action="append",
        metavar="DEVICE:AT:DOWN",
        help="fault: pull DEVICE's cable (laser, sonar0, sonar1, odometry) at AT s of the run "
        "for DOWN s; repeatable",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from fgslam.config import load_config
    from fgslam.online.loop import StopSignal, emulate_main, emulation_faults

    cfg = load_config(args.config)
    faults = emulation_faults(
        cfg,
        noise=args.noise,
        drop=args.drop,
        flip=args.flip,
        disconnects=args.disconnect or [],
        seed=args.seed,
    )
    with StopSignal() as sig:
        return emulate_main(
            cfg,
            args.world,
            seed=args.seed,
            speed=args.speed,
            duration=args.duration,
            link_dir=args.link_dir,
            faults=faults,
            stop=sig.event,
        )
