"""``fgslam convert``: a CARMEN log or a ROS bag into the native log."""

from __future__ import annotations

import argparse
from collections import Counter

from fgslam.cli.common import add_log_arguments, reader_options, reader_warnings
from fgslam.errors import UserError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "convert",
        help="convert a CARMEN log or a ROS bag into the native log",
        description=(
            "Read a CARMEN log (FLASER/ROBOTLASER1/ODOM, gzipped or not) or a ROS 1/2 bag "
            "(LaserScan, Odometry, Range topics) and write the native log (docs/log-format.md; "
            "'.gz' to compress) with the robot configuration derived from the data: the "
            "laser's beams and field of view, odometry as ticks of a virtual differential "
            "drive (0.1 mm per tick), reference poses as truth records. See docs/readers.md."
        ),
    )
    add_log_arguments(
        p,
        "FILE.log",
        "log file to write",
        log_help="CARMEN log or ROS bag (or a native log, copied)",
        tolerant=True,
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:

    from fgslam.io.formats import open_log
    from fgslam.io.logwriter import LogWriter

    reader = open_log(args.log, **reader_options(args))
    counts: Counter = Counter()
    try:  # the log appears at --out only when complete (LogWriter writes a temporary file)
        with reader, LogWriter(args.out, reader.config, reader.world, meta=reader.meta) as w:
            for ev in reader:
                w.write(ev)
                counts[type(ev).__name__] += 1
    except OSError as exc:
        raise UserError(f"cannot write {args.out}: {exc.strerror or exc}") from None
    kinds = ", ".join(f"{n} {k}" for k, n in sorted(counts.items())) or "no events"
    print(f"wrote {args.out}: {kinds}")
    summary = reader.problems.summary()
    if summary["skipped"]:
        print(f"skipped {summary['skipped']} bad records: {summary['skipped_by_reason']}")
    if summary["timestamps_backwards"]:
        print(f"timestamps going backwards (kept as they are): {summary['timestamps_backwards']}")
    for w in reader_warnings(reader):
        print(f"warning: {w}")
    if reader.reference_kind == "reference":
        print("truth records hold the log's reference poses (not ground truth)")
    return 0
