"""``fgslam compare``: every backend and sensor mode on one log, compared."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from fgslam.cli.common import (
    add_association_argument,
    add_log_arguments,
    config_options,
    reader_options,
)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "compare",
        help="every backend and sensor mode on one log, compared",
        description=(
            "Run EKF, iSAM2 and batch smoothing in fused, laser-only and sonar-only modes on the "
            "same log (the front end runs once per mode), write each run's outputs into "
            "DIR/<backend>-<sensors>/, and comparison.json, comparison.md and comparison.png "
            "(trajectories and errors over time) into DIR. Any log `run` reads."
        ),
    )
    add_log_arguments(p, "DIR", "output directory", config=True)
    add_association_argument(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    rows = compare_all(
        args.log,
        args.out,
        args.config,
        reader_options(args),
        args.association,
        config_options(args),
    )
    names = ("comparison.json", "comparison.md", "comparison.png")
    written = [n for n in names if (Path(args.out) / n).exists()]  # a failed one is removed
    if "comparison.md" in written:
        print((Path(args.out) / "comparison.md").read_text(), end="")
    print(f"wrote {args.out}/{', '.join(written)} and one folder per run")
    failed = [n for n in names if n not in written] + [
        f"{r['backend']}-{r['sensors']}/{e['output']}"
        for r in rows
        for e in r.get("output_errors", [])
    ]
    if failed:
        print(f"fgslam compare: error: not written: {', '.join(failed)}", file=sys.stderr)
    partial = [f"{r['backend']}/{r['sensors']}" for r in rows if r.get("partial")]
    if partial:
        print(
            f"fgslam compare: error: {', '.join(partial)} failed mid-run: their outputs hold "
            "the run up to the last good keyframe (report.json: partial)",
            file=sys.stderr,
        )
    return 0 if rows and not failed and not partial else 1


def compare_all(
    log: str,
    out: str,
    config: str | None,
    options: dict | None = None,
    association: str = "jcbb",
    sections: dict | None = None,
) -> list:
    """:func:`fgslam.slam.compare.compare` with a progress bar over its runs (backends x
    sensors); the rows of the comparison."""
    from tqdm import tqdm

    from fgslam.slam.compare import compare
    from fgslam.slam.runner import BACKENDS, SENSORS

    with tqdm(
        total=len(BACKENDS) * len(SENSORS),
        desc="backends x sensors",
        unit="run",
        disable=None,
        leave=False,
    ) as bar:
        return compare(
            log,
            out,
            config,
            on_done=lambda _res: bar.update(1),
            options=options,
            association=association,
            sections=sections,
        )
