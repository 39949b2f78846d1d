"""Is iSAM2's final estimate at the optimum? Cost per degree of freedom of iSAM2's estimate
after the last keyframe against batch Levenberg-Marquardt on the same graph.

Run: python experiments/isam2_convergence.py [--limit N]
Victoria Park with the given association (a real point-landmark log, robust Cauchy factors),
through fgslam.slam.pointslam. For each relinearisation policy: iSAM2 as it stands after the
last keyframe ("as run"), after the final Gauss-Newton steps on the whole graph of
GraphBackend.finish ("converged"), and batch LM from there; the cost is 2 x graph error /
(measurement dof - variable dof) (robust costs: not exactly chi-square), and the largest
position difference to batch.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from fgslam.io.readers.victoria import read_victoria
from fgslam.slam import pointslam
from fgslam.slam.graph import GraphBackend
from fgslam.slam.graph_keys import X
from fgslam.slam.graph_solve import BatchSmoother

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "victoria_park.txt"


def positions(values, n: int) -> np.ndarray:
    return np.array([[values.atPose2(X(k)).x(), values.atPose2(X(k)).y()] for k in range(n)])


def hooks(thr: float, skip: int, holder: dict, orig, orig_finish):
    """GraphBackend.__init__ with this policy (remembering the backend) and finish (keeping
    the estimate as run and timing the final convergence)."""

    def init(self, *a, **kw):
        orig(self, *a, **{**kw, "relinearize_threshold": thr, "relinearize_skip": skip})
        holder["be"] = self

    def finish(self):
        holder["as_run"] = self.isam.calculateEstimate()
        t0 = time.perf_counter()
        out = orig_finish(self)
        holder["finish_s"] = time.perf_counter() - t0
        return out

    return init, finish


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--limit", type=int)
    ap.add_argument("--data", type=Path, default=DATA)
    args = ap.parse_args()
    data = read_victoria(args.data)
    print(
        "| relinearisation | iSAM2 run (s) | cost/dof as run | cost/dof converged | final "
        "updates | finish (s) | cost/dof batch | max diff as run / converged to batch (m) |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for thr, skip in ((0.1, 10), (0.01, 10), (0.1, 1)):
        holder: dict = {}
        orig, orig_finish = GraphBackend.__init__, GraphBackend.finish
        init, finish = hooks(thr, skip, holder, orig, orig_finish)
        GraphBackend.__init__, GraphBackend.finish = init, finish
        try:
            t0 = time.perf_counter()
            pointslam.run_points(data, "isam2", "given", limit=args.limit)
            run_s = time.perf_counter() - t0 - holder["finish_s"]
        finally:
            GraphBackend.__init__, GraphBackend.finish = orig, orig_finish
        be = holder["be"]
        n = len(be.times)
        c_run = be.chi2_per_dof(holder["as_run"])
        c_conv = be.chi2_per_dof()
        conv = positions(be._est, n)
        run = positions(holder["as_run"], n)
        batch = BatchSmoother(be)
        b = positions(batch.values, n)
        c_b = batch.chi2_per_dof()
        d_run = np.hypot(*(run - b).T).max()
        d_conv = np.hypot(*(conv - b).T).max()
        print(
            f"| threshold {thr}, every {skip} | {run_s:.1f} | {c_run:.4f} | {c_conv:.4f} | "
            f"{be.final_updates} | {holder['finish_s']:.1f} | {c_b:.4f} | "
            f"{d_run:.3f} / {d_conv:.4f} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
