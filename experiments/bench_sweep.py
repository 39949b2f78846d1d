"""A 40-cell sweep on the corridor on a local Dask cluster of 1 and of 2 workers, side by
side (issue 36's target: 2 workers in about half the time of one).

The cells: seeds 1-20 x backends isam2 and ekf, laser, the first ``--duration`` s of the
simulated run each; each cluster starts with an empty folder. Prints the wall time of each
and the ratio, and, for the ceiling of this workload on this machine (memory and caches are
shared too), the same cells in a plain process pool of the most workers.

    python experiments/bench_sweep.py [--duration 30] [--workers 1,2]
"""

from __future__ import annotations

import argparse
import tempfile
import time

from fgslam.sweep import run_sweep, spec_from_dict


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--duration", type=float, default=30.0)
    ap.add_argument("--workers", default="1,2")
    args = ap.parse_args()
    spec = spec_from_dict(
        {
            "name": "bench",
            "run": {"duration": args.duration, "sensors": "laser"},
            "grid": {"seed": list(range(1, 21)), "backend": ["isam2", "ekf"]},
        }
    )
    rows = []
    for n in (int(w) for w in args.workers.split(",")):
        with tempfile.TemporaryDirectory() as out:
            t0 = time.perf_counter()
            run = run_sweep(spec, out, workers=n)
            wall = time.perf_counter() - t0
        assert not run.failed, run.failed
        rows.append((n, len(run.ran), wall))
    # the ceiling of this workload on this machine: the same cells in a plain process pool
    from concurrent.futures import ProcessPoolExecutor

    from fgslam.sweep.cell import run_cell
    from fgslam.sweep.engine import cell_folder

    n = max(int(w) for w in args.workers.split(","))
    with tempfile.TemporaryDirectory() as out, ProcessPoolExecutor(n) as pool:
        t0 = time.perf_counter()
        folders = [str(cell_folder(out, c.id)) for c in spec.cells]
        list(pool.map(run_cell, [c.settings for c in spec.cells], folders))
        rows.append((f"{n} (a process pool, no Dask)", len(spec.cells), time.perf_counter() - t0))
    base = rows[0][2]
    print(f"{len(spec.cells)} cells, {args.duration:.0f} s of the corridor each\n")
    print("| workers | cells run | wall (s) | time / one worker's |")
    print("|---|---|---|---|")
    for n, ran, wall in rows:
        print(f"| {n} | {ran} | {wall:.1f} | {wall / base:.2f} |")


if __name__ == "__main__":
    main()
