"""Simulating the whole built-in corridor run against the time the run lasts.

Run: python experiments/bench_simulator.py [--seed 0]
Prints simulated time, wall time per stage and the ratio (simulated s per wall s).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from fgslam.config import load_config
from fgslam.io.logwriter import LogWriter
from fgslam.sim.simulate import events, plan_run
from fgslam.sim.world import load_world


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    cfg, world = load_config(), load_world("corridor")
    t0 = time.perf_counter()
    run = plan_run(world, cfg, args.seed)
    t1 = time.perf_counter()
    n = 0
    for _ in events(world, cfg, run):
        n += 1
    t2 = time.perf_counter()
    with tempfile.TemporaryDirectory() as d:
        with LogWriter(Path(d) / "run.log.gz", cfg, world.name) as log:
            for ev in events(world, cfg, run):
                log.write(ev)
        t3 = time.perf_counter()
    sim = run.duration
    print(
        f"corridor run, seed {args.seed}: {sim:.1f} s simulated, {run.distance:.1f} m, {n} events"
    )
    print("| stage | wall time (s) | simulated s per wall s |")
    print("|---|---|---|")
    print(f"| plan the drive (100 Hz truth, ticks) | {t1 - t0:.2f} | {sim / (t1 - t0):.0f} |")
    print(f"| sensor events (laser, sonar) | {t2 - t1:.2f} | {sim / (t2 - t1):.0f} |")
    print(f"| events written to .log.gz | {t3 - t2:.2f} | {sim / (t3 - t2):.0f} |")
    total = (t1 - t0) + (t3 - t2)
    print(f"| whole `fgslam simulate` (plan + write) | {total:.2f} | {sim / total:.0f} |")


if __name__ == "__main__":
    main()
