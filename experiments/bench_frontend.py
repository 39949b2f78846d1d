"""Time per laser scan of the whole front end on the simulated corridor run, in each mode.

Run: python experiments/bench_frontend.py [--seed 0] [--duration 100] [--repeat 2]
       [--profile fused]
The run (seed 0, the first ``--duration`` s of the built-in corridor; 0 = the whole run) is
simulated into memory first; then every event is fed to ``FrontEnd.add`` and ``finish`` and
each call is timed. The time of the calls since the previous scan came out (odometry
integration, sonar buffering) is shared among the scans that a call returns, so the mean is
the total front-end time over the number of scans. The modes are run ``--repeat`` times,
interleaved, and each scan keeps its fastest time (the machine is shared: this strips most
of the other processes' interference). Prints mean, p95 and max per scan (ms) and the ratio
of the PLS scan period to the mean (how many times faster than real time).
``--profile MODE`` also prints the 20 most expensive functions of that mode (cProfile).
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import time

import numpy as np

from fgslam.config import load_config
from fgslam.events import LaserScan
from fgslam.frontend.pipeline import MODES, FrontEnd
from fgslam.sim.simulate import events, plan_run
from fgslam.sim.world import load_world


def time_mode(cfg, evs, mode: str) -> np.ndarray:
    """Milliseconds of front-end work per output scan."""
    fe = FrontEnd(cfg, mode)
    per_scan: list[float] = []
    acc = 0.0
    clock = time.perf_counter
    for ev in evs:
        t0 = clock()
        out = fe.add(ev)
        acc += clock() - t0
        if out:
            per_scan.extend([acc / len(out)] * len(out))
            acc = 0.0
    t0 = clock()
    out = fe.finish()
    acc += clock() - t0
    if out:
        per_scan.extend([acc / len(out)] * len(out))
    return 1e3 * np.array(per_scan)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--duration", type=float, default=100.0, help="simulated s of the run (0: all)")
    ap.add_argument("--repeat", type=int, default=2, help="rounds; each scan keeps its best")
    ap.add_argument("--profile", choices=MODES, help="also profile this mode with cProfile")
    args = ap.parse_args()
    cfg, world = load_config(), load_world("corridor")
    run = plan_run(world, cfg, args.seed, duration=args.duration or None)
    evs = list(events(world, cfg, run))
    n_scans = sum(isinstance(e, LaserScan) for e in evs)
    period = 1e3 * cfg.laser.scan_period
    print(
        f"corridor run, seed {args.seed}: {run.duration:.1f} s simulated, {len(evs)} events, "
        f"{n_scans} laser scans; PLS scan period {period:.1f} ms"
    )
    best: dict[str, np.ndarray] = {}
    for _ in range(max(args.repeat, 1)):  # interleave the modes so machine load hits all alike
        for mode in MODES:
            ms = time_mode(cfg, evs, mode)
            best[mode] = np.minimum(best[mode], ms) if mode in best else ms
    print(f"per-scan time, best of {max(args.repeat, 1)} interleaved rounds")
    print("| mode  | scans | mean (ms) | p95 (ms) | max (ms) | scan period / mean |")
    print("|-------|-------|-----------|----------|----------|--------------------|")
    for mode, ms in best.items():
        print(
            f"| {mode:5s} | {ms.size:5d} | {ms.mean():9.2f} | {np.percentile(ms, 95):8.2f} "
            f"| {ms.max():8.2f} | {period / ms.mean():18.1f} |"
        )
    if args.profile:
        prof = cProfile.Profile()
        prof.enable()
        time_mode(cfg, evs, args.profile)
        prof.disable()
        print(f"\ncProfile of mode {args.profile} (by own time):")
        pstats.Stats(prof).sort_stats("tottime").print_stats(20)


if __name__ == "__main__":
    main()
