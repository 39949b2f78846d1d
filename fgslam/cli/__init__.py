"""The ``fgslam`` command line. Each subcommand has its own ``--help`` and its own module here
(``register`` adds its parser, ``run`` runs it); what several share is in ``common``.

Bad input is reported as one line on stderr with exit status 2; no traceback reaches the user
for a problem with their files or options.
"""

from __future__ import annotations

import argparse
import os
import sys
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path

from fgslam import __version__
from fgslam.cli import (
    calibrate,
    compare,
    config,
    convert,
    demo,
    emulate,
    evaluate,
    export_reference,
    localize,
    online,
    plot_log,
    replay,
    run,
    simulate,
    sweep,
)
from fgslam.cli.common import WORLD_HELP
from fgslam.errors import OutputWarning, RunWarning, UserError

__all__ = ["WORLD_HELP", "build_parser", "main"]

EPILOG = """\
Typical use:
  fgslam config                         show the default robot configuration (TOML)
  fgslam config --config my_robot.toml  validate your robot file and show the merged result
  fgslam simulate --seed 1 --out run.log.gz     the paper's lab-and-corridor run, simulated
  fgslam plot-log run.log.gz --out run.png      look at it
  fgslam run run.log.gz --backend isam2 --out out/   SLAM on a log (native, CARMEN, ROS bag)
  fgslam compare run.log.gz --out cmp/          EKF, iSAM2, batch x fused, laser, sonar
  fgslam demo                                   simulate the built-in run and compare
  fgslam run run.log.gz --out out/ --save map/   ... and save the map (a session)
  fgslam localize run2.log.gz --map map/ --out loc/   localize another run on that map
  fgslam evaluate out/trajectory.tum --reference ref.tum   ATE, RPE, NEES
  fgslam export-reference run.log.gz --out ref.tum   truth/reference poses as TUM (for evo)
  fgslam emulate --speed 4 --link-dir /tmp/robot   emulated devices on pseudo-terminals
  fgslam online --laser PORT --sonar PORT --sonar PORT --odom PORT --out DIR   live SLAM
  fgslam sweep grid.toml --out sweep/   many runs on Dask (resumable); --report sweep/

Frames follow REP-103 (x forward, y left, yaw counter-clockwise); units are SI.
"""

# What each command writes with --out (a file or a folder), checked before any work starts,
# and the options naming its inputs (an input is never an output).
OUTPUT_KINDS = {
    "run": "dir",
    "compare": "dir",
    "demo": "dir",
    "online": "dir",
    "localize": "dir",
    "simulate": "file",
    "convert": "file",
    "replay": "file",
    "plot-log": "file",
    "evaluate": "file",
    "export-reference": "file",
    "calibrate": "file",
    "sweep": "dir",
}
INPUT_OPTIONS = (
    "log",
    "config",
    "world",
    "trajectory",
    "reference",
    "covariances",
    "map",
    "relations",
    "odometry_log",
    "spec",
    "report",
)

# The commands in the order `fgslam --help` lists them; each module's register(sub) adds its
# parser, whose default func is the module's run(args).
COMMANDS = (
    config,
    simulate,
    plot_log,
    run,
    localize,
    convert,
    evaluate,
    calibrate,
    compare,
    export_reference,
    demo,
    replay,
    emulate,
    online,
    sweep,
)


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
    for command in COMMANDS:
        command.register(sub)
    return parser


def _check_outputs(args: argparse.Namespace) -> None:
    """Refuse an --out that cannot be written or that is one of the inputs, before any work."""
    from fgslam.io.safeio import check_output_dir, check_output_file

    kind = OUTPUT_KINDS.get(args.command)
    out = getattr(args, "out", None)
    if kind is None or out is None:
        return
    log = getattr(args, "log", None)
    if log is not None and not Path(log).exists():
        return  # the command says so; no output folder is created for nothing
    inputs = [getattr(args, k, None) for k in INPUT_OPTIONS]
    inputs.append(getattr(args, "raw_dir", None))
    if args.command == "plot-log":
        args.out = out = plot_log.image_path(out, args.log)
    if kind == "dir":
        check_output_dir(out, inputs)
    else:
        check_output_file(out, inputs)


def main(argv: Sequence[str] | None = None) -> int:
    try:
        return _main(argv)
    except BrokenPipeError:
        # the reader of our output went away (`fgslam ... | head`): no traceback, and none
        # at exit either when Python flushes stdout
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 141


def _one_line_warning(command: str, show: Callable) -> Callable:
    """``warnings.showwarning`` that prints an OutputWarning (an output not written) or a
    RunWarning (something odd the run survived) as one line, ``fgslam COMMAND: warning:
    ...``, and leaves other warnings to ``show``."""

    def showwarning(message, category, filename, lineno, file=None, line=None) -> None:
        if issubclass(category, (OutputWarning, RunWarning)):
            print(f"fgslam {command}: warning: {message}", file=sys.stderr)
        else:
            show(message, category, filename, lineno, file, line)

    return showwarning


def _one_line(text: str) -> str:
    """An error message as one line: characters that are not printable (line breaks and
    other separators a file's bytes can put into a key or a name) escaped."""
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


def _main(argv: Sequence[str] | None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    func: Callable[[argparse.Namespace], int] | None = getattr(args, "func", None)
    if func is None:
        parser.print_help()
        sys.stdout.flush()
        return 0
    try:
        _check_outputs(args)
        with warnings.catch_warnings():
            warnings.simplefilter("always", OutputWarning)
            warnings.simplefilter("always", RunWarning)
            warnings.showwarning = _one_line_warning(args.command, warnings.showwarning)
            status = func(args)
        sys.stdout.flush()  # a closed pipe shows here, not at exit
        return status
    except UserError as exc:
        print(f"fgslam {args.command}: error: {_one_line(str(exc))}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"fgslam {args.command}: interrupted", file=sys.stderr)
        return 130
