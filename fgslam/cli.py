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
