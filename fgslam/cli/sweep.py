"""``fgslam sweep``: many runs on Dask, resumable, and their report (docs/sweeps.md)."""

from __future__ import annotations

import argparse
import math
import sys

from fgslam.errors import UserError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "sweep",
        help="run a grid of logs, seeds and settings on Dask (resumable); report on it",
        description=(
            "Run every cell of SPEC.toml (a grid or list over logs or simulated seeds, "
            "backends, sensor modes and any configuration key: docs/sweeps.md) on a Dask "
            "cluster, each into its own folder under --out/cells/ with the outputs of "
            "`fgslam run` and result.json. A finished cell is never run again: start the same "
            "command again after an interruption and only what is missing runs. Without "
            "--scheduler a local cluster of --workers processes; with it, an existing "
            "cluster (`dask scheduler` and `dask worker` started by you). With --report DIR: "
            "no run, but the sweep in DIR summarized per setting (mean, median, spread of "
            "ATE, relations error, NEES, real-time factor): summary.md, summary.csv, "
            "cells.csv and boxplots.png."
        ),
    )
    p.add_argument("spec", nargs="?", metavar="SPEC.toml", help="the sweep's specification")
    p.add_argument(
        "--out",
        metavar="DIR",
        help="the sweep's folder (or, with --report, where "
        "the report goes; default the sweep's folder)",
    )
    p.add_argument("--report", metavar="DIR", help="report on the sweep in DIR instead of running")
    p.add_argument("--workers", type=_positive, help="local workers (default: one per core)")
    p.add_argument(
        "--memory-limit",
        default="auto",
        help="memory per local worker, e.g. 4GB (default: the machine's divided among them)",
    )
    p.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        help="an existing Dask scheduler, e.g. tcp://host:8786, instead of a local cluster",
    )
    p.add_argument(
        "--retries",
        type=int,
        default=2,
        help="times a cell whose worker died is run again (default 2)",
    )
    p.set_defaults(func=run)


def _positive(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if n < 1:
        raise argparse.ArgumentTypeError(f"expected at least 1, got {n}")
    return n


def run(args: argparse.Namespace) -> int:
    from fgslam.sweep import load_spec, run_sweep, write_report

    if args.report:
        if args.spec:
            raise UserError("give SPEC.toml to run a sweep or --report DIR, not both")
        done = write_report(args.report, args.out)
        print(
            f"{done['cells']} cells, {done['settings']} settings: wrote summary.md, "
            f"summary.csv, cells.csv, boxplots.png into {done['folder']}"
        )
        print(open(f"{done['folder']}/summary.md").read())
        return 0
    if not args.spec or not args.out:
        raise UserError("give SPEC.toml and --out DIR (or --report DIR)")
    spec = load_spec(args.spec)
    print(f"sweep {spec.name!r}: {len(spec.cells)} cells into {args.out}")
    from tqdm import tqdm

    bar = tqdm(total=len(spec.cells), unit="cell", file=sys.stderr, dynamic_ncols=True)

    def progress(p: dict) -> None:
        if "dashboard" in p:
            bar.write(f"Dask dashboard: {p['dashboard']}")
        bar.n = p["done"] + p["failed"]
        eta = p["eta_s"]
        bar.set_postfix_str(
            f"done {p['done']} failed {p['failed']} running {p['running']}"
            + ("" if eta is None or math.isnan(eta) else f" eta {eta / 60:.1f} min")
        )

    try:
        res = run_sweep(
            spec,
            args.out,
            scheduler=args.scheduler,
            workers=args.workers,
            memory_limit=args.memory_limit,
            retries=args.retries,
            progress=progress,
        )
    finally:
        bar.close()
    print(
        f"{res.skipped} cells finished before, {len(res.ran)} run now, "
        f"{len(res.failed)} failed ({res.wall_s:.0f} s)"
    )
    for cid, why in res.failed.items():
        print(f"  failed: {cid}: {why}")
    if res.failed:
        print(f"failed cells: {args.out}/failed.json; start the sweep again to retry them")
    return 1 if res.failed else 0
