"""Linearisation cost of the custom landmark factors against GTSAM's built-in
BearingRangeFactor2D, measured side by side in one run.

Run: python experiments/bench_factors.py [--n 20000] [--repeat 5]
Prints a table of microseconds per linearize() call and the ratio to the built-in factor.
"""

from __future__ import annotations

import argparse
import math
import time

import gtsam
import numpy as np

from factors.corner import corner_bearing_range_factor, corner_factor
from factors.line import line_factor
from factors.point import point_factor


def build(n: int, seed: int = 0) -> dict[str, tuple[gtsam.NonlinearFactorGraph, gtsam.Values]]:
    rng = np.random.default_rng(seed)
    mount = (0.12, 0.0, 0.0)
    n2, n3 = (
        gtsam.noiseModel.Diagonal.Sigmas([0.01, 0.02]),
        gtsam.noiseModel.Diagonal.Sigmas([0.01, 0.02, 0.03]),
    )
    cases = {}
    zero_e, zero_hx, zero_hl = np.zeros(2), np.zeros((2, 3)), np.zeros((2, 2))

    def empty(this, values, H):  # the floor: a CustomFactor callback doing no work at all
        if H is not None:
            H[0], H[1] = zero_hx, zero_hl
        return zero_e

    makers = {
        "BearingRangeFactor2D (built-in)": lambda i: gtsam.BearingRangeFactor2D(
            2 * i, 2 * i + 1, gtsam.Rot2(0.3), 4.0, n2
        ),
        "point_factor (built-in, mount)": lambda i: point_factor(
            2 * i, 2 * i + 1, (0.3, 4.0), np.diag([1e-4, 4e-4]), mount
        ),
        "line_factor (CustomFactor)": lambda i: line_factor(
            2 * i, 2 * i + 1, (0.3, 4.0), n2, mount
        ),
        "corner_factor (CustomFactor)": lambda i: corner_factor(
            2 * i, 2 * i + 1, (0.3, 4.0, 2.5), n3, mount
        ),
        "corner bearing-range (CustomFactor)": lambda i: corner_bearing_range_factor(
            2 * i, 2 * i + 1, (0.3, 4.0), n2, mount
        ),
        "empty CustomFactor (floor)": lambda i: gtsam.CustomFactor(n2, [2 * i, 2 * i + 1], empty),
    }
    for name, make in makers.items():
        g, v = gtsam.NonlinearFactorGraph(), gtsam.Values()
        for i in range(n):
            g.add(make(i))
            v.insert(2 * i, gtsam.Pose2(*rng.uniform(-5, 5, 2), rng.uniform(-math.pi, math.pi)))
            if name.startswith("corner"):
                v.insert(2 * i + 1, gtsam.Pose2(*rng.uniform(-5, 5, 3)))
            else:
                v.insert(2 * i + 1, rng.uniform(-5, 5, 2))
        cases[name] = (g, v)
    return cases


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=20000, help="factors per graph")
    ap.add_argument("--repeat", type=int, default=5, help="timed rounds (best is kept)")
    args = ap.parse_args()
    cases = build(args.n)
    best = {name: math.inf for name in cases}
    for _ in range(args.repeat):  # interleave the cases so machine load hits all alike
        for name, (g, v) in cases.items():
            t0 = time.perf_counter()
            g.linearize(v)
            best[name] = min(best[name], time.perf_counter() - t0)
    base = best["BearingRangeFactor2D (built-in)"]
    print(f"linearize(), {args.n} factors per graph, best of {args.repeat} interleaved rounds")
    print(f"| {'factor':38s} | us/factor | ratio to built-in |")
    print(f"|{'-' * 40}|-----------|-------------------|")
    for name, t in best.items():
        print(f"| {name:38s} | {1e6 * t / args.n:9.2f} | {t / base:17.1f} |")


if __name__ == "__main__":
    main()
