"""The EKF's cost per landmark update against the map size, for this tree and (``--compare``)
other trees side by side: an EKF filled with N random landmarks (lines, corners, points) and
a correlated covariance, timed over 40 updates of existing landmarks (process CPU time, the
median of 3 repeats). The covariance update P - K S K^T is O(n^2) for n states whatever H's
sparsity; the part that H's sparsity saves is P H^T.

Run: python experiments/bench_ekf_update.py [--sizes 100 200 400 800] [--compare TREE ...]
(each tree in a child process with ``PYTHONPATH`` = the tree, one BLAS thread; this tree
first). The last column's ratio is that tree's time over this tree's.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def measure(sizes: list[int]) -> dict[int, float]:
    """ms per update at each number of landmarks (in this process's fgslam)."""
    from fgslam.frontend.features import Feature
    from fgslam.slam import models
    from fgslam.slam.ekf import EkfBackend

    out = {}
    for n_lm in sizes:
        rng = np.random.default_rng(0)
        be = EkfBackend(gate_p=None)
        be.start(0.0, np.zeros(3), np.eye(3) * 1e-3)
        for lid in range(n_lm):
            kind = ("line", "corner", "point")[lid % 3]
            z = [rng.uniform(-math.pi, math.pi), rng.uniform(0.5, 5.0), rng.uniform(-3, 3)]
            z = np.array(z[: models.DIM[kind]])
            be.add_landmark(lid, Feature(kind, z, np.eye(len(z)) * 1e-3))
        be.P = be.P + np.eye(be.x.size) * 1e-4
        feats = []
        for lid in rng.integers(0, n_lm, 40).tolist():
            o, kind = be.index[lid]
            k = models.DIM[kind]
            z = models.residual(kind, be.x[:3], be.x[o : o + k], np.zeros(k))[0]
            feats.append((lid, Feature(kind, z + rng.normal(size=k) * 0.01, np.eye(k) * 1e-3)))
        runs = []
        for _ in range(3):
            P0, x0 = be.P.copy(), be.x.copy()
            t0 = time.process_time()
            for lid, f in feats:
                be.observe(lid, f)
            runs.append((time.process_time() - t0) / len(feats) * 1e3)
            be.P, be.x = P0, x0
        out[n_lm] = float(np.median(runs))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[100, 200, 400, 800])
    ap.add_argument("--compare", nargs="*", default=[], help="other source trees")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(measure(args.sizes)))
        return
    trees = [ROOT, *map(Path, args.compare)]
    rows = {}
    for tree in trees:
        env = {**os.environ, "PYTHONPATH": str(tree), "OPENBLAS_NUM_THREADS": "1"}
        cmd = [sys.executable, __file__, "--child", "--sizes", *map(str, args.sizes)]
        res = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True)
        rows[tree] = {int(k): v for k, v in json.loads(res.stdout).items()}
    heads = [str(t) for t in trees]
    print("| landmarks | states | " + " | ".join(f"{h} (ms/update)" for h in heads) + " |")
    print("|---|---|" + "---|" * len(heads))
    for n in args.sizes:
        cells = [f"{rows[t][n]:.2f}" for t in trees]
        if len(trees) > 1:
            cells[1:] = [
                f"{c} ({rows[t][n] / rows[ROOT][n]:.2f}x)"
                for c, t in zip(cells[1:], trees[1:], strict=True)
            ]
        states = 3 + round(n * 7 / 3)
        print(f"| {n} | {states} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
