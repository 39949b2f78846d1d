"""CPU cost of the corridor run, to compare two versions of the code side by side on a shared
machine (process CPU time is far less sensitive to other jobs than wall time).

Run: PYTHONPATH=<tree> python experiments/bench_side_by_side.py [--duration S] [--seed N]
[--calibration off wheels]
(once with PYTHONPATH at the previous commit's tree, once at this one, interleaved). Prints,
for one pass of EKF and iSAM2 over the simulated corridor (fused): the process CPU seconds of
the whole run (front end included), each backend's summed per-keyframe time (wall), its ATE,
and the landmark count. ``--calibration off wheels``: one pass per wheel-calibration setting
in this tree, side by side, with each one's CPU time over the first's.

Like with like: the run is pinned to the paper's scheme (wheel odometry, every scan a
keyframe, no loop closures: ``PAPER``), the only scheme of a tree older than scan matching
(a6e0f28); a tree without :func:`fgslam.config.with_scanmatch` runs its configuration as is.
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time
from pathlib import Path

import numpy as np

from fgslam.config import load_config
from fgslam.evaluation import metrics as evaluation
from fgslam.io.logfile import LogReader
from fgslam.sim import simulate_to_log
from fgslam.sim.world import load_world
from fgslam.slam.runner import run_backends

try:  # trees with scan matching: pin the paper's scheme
    from fgslam.config import with_scanmatch
    from fgslam.sim.scenes import PAPER
except ImportError:  # older trees (e.g. a6e0f28): the paper's scheme is the only one
    with_scanmatch, PAPER = None, None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, help="s of the run (default: the whole run)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument(
        "--calibration",
        nargs="+",
        choices=["off", "wheels"],
        help="one pass per setting of [odometry] calibration (default: the configuration's)",
    )
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as d:
        log = Path(d) / "run.log.gz"
        simulate_to_log(load_world("corridor"), load_config(), log, args.seed, args.duration)
        evs = list(LogReader(log))
        cfg = LogReader(log).config
    if with_scanmatch is not None:
        cfg = with_scanmatch(cfg, PAPER)
    first = None
    for cal in args.calibration or [None]:
        if cal is not None:
            cfg = dataclasses.replace(
                cfg, odometry=dataclasses.replace(cfg.odometry, calibration=cal)
            )
        t0 = time.process_time()
        res = run_backends(evs, cfg, ["ekf", "isam2"], "fused")
        cpu = time.process_time() - t0
        first = first or cpu
        label = "" if cal is None else f", calibration {cal}"
        print(
            f"corridor seed {args.seed}{label}, {res[0].log_duration:.0f} s of log: CPU "
            f"{cpu:.1f} s ({cpu / first:.2f}x the first)"
        )
        for r in res:
            ref = evaluation.interpolate_poses(r.truth_t, r.truth, r.times)
            print(
                f"  {r.backend}: per-keyframe time {np.sum(r.latencies):.1f} s, "
                f"ATE {evaluation.ate(r.poses, ref)['rmse']:.4f} m, {len(r.landmarks)} landmarks"
            )


if __name__ == "__main__":
    main()
