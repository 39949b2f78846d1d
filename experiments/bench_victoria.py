"""Victoria Park through the project's iSAM2 pipeline against a plain loop over GTSAM's
built-in factors, on the same data in the same run.

Run: python experiments/bench_victoria.py [--repeat 2]
Both use given data association and one ISAM2 update per odometry step with the same ISAM2
parameters (relinearisation threshold 0.1, relinearise every 10 updates):
- fgslam: fgslam.slam.pointslam.run_points(backend="isam2") through GraphBackend (predict,
  add_landmark / observe, commit; its landmark-mean bookkeeping for association included);
- plain: BetweenFactorPose2 + BearingRangeFactor2D built in a Python loop, ISAM2.update and
  calculateEstimatePose2 of the new pose per step.
The best of ``--repeat`` runs of each is reported, with the ratio and the largest position
difference between the two final trajectories.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import gtsam
import numpy as np

from fgslam.io.readers.victoria import VictoriaPark, read_victoria, to_bearing_range
from fgslam.slam.pointslam import run_points

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "victoria_park.txt"


def plain_gtsam(data: VictoriaPark) -> tuple[np.ndarray, float]:
    params = gtsam.ISAM2Params()
    params.setRelinearizeThreshold(0.1)
    params.relinearizeSkip = 10
    isam = gtsam.ISAM2(params)
    X = lambda k: gtsam.symbol("x", k)  # noqa: E731
    L = lambda i: gtsam.symbol("l", i)  # noqa: E731
    t0 = time.perf_counter()
    known: set[int] = set()

    def sightings(graph, values, k, pose_index, pose):
        for s in data.sightings.get(pose_index, []):
            z, c = to_bearing_range(s.xy, s.cov)
            noise = gtsam.noiseModel.Gaussian.Covariance(c)
            graph.add(
                gtsam.BearingRangeFactor2D(X(k), L(s.landmark), gtsam.Rot2(z[0]), z[1], noise)
            )
            if s.landmark not in known:
                known.add(s.landmark)
                values.insert(L(s.landmark), pose.transformFrom(np.asarray(s.xy, dtype=float)))

    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    pose = gtsam.Pose2()
    graph.add(gtsam.PriorFactorPose2(X(0), pose, gtsam.noiseModel.Isotropic.Sigma(3, 1e-4)))
    values.insert(X(0), pose)
    sightings(graph, values, 0, data.steps[0].i, pose)
    isam.update(graph, values)
    for k, st in enumerate(data.steps, 1):
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        delta = gtsam.Pose2(*map(float, st.delta))
        graph.add(
            gtsam.BetweenFactorPose2(
                X(k - 1), X(k), delta, gtsam.noiseModel.Gaussian.Covariance(st.cov)
            )
        )
        pose = pose.compose(delta)
        values.insert(X(k), pose)
        sightings(graph, values, k, st.j, pose)
        isam.update(graph, values)
        pose = isam.calculateEstimatePose2(X(k))
    est = isam.calculateEstimate()
    wall = time.perf_counter() - t0
    poses = np.array(
        [[p.x(), p.y(), p.theta()] for p in (est.atPose2(X(k)) for k in range(len(data.steps) + 1))]
    )
    return poses, wall


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--data", type=Path, default=DATA)
    args = ap.parse_args()
    data = read_victoria(args.data)
    fg_t, plain_t = [], []
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        fg = run_points(data, "isam2", "given")
        fg_t.append(time.perf_counter() - t0)
        plain, wall = plain_gtsam(data)
        plain_t.append(wall)
    diff = np.hypot(*(fg.poses[:, :2] - plain[:, :2]).T)
    n = len(data.steps)
    print(f"Victoria Park: {n} steps, {data.n_sightings} sightings, given association")
    print("| pipeline | best time (s) | per step (ms) |")
    print("|---|---|---|")
    for name, ts in (
        ("fgslam iSAM2 (GraphBackend via pointslam)", fg_t),
        ("plain GTSAM loop (built-in factors)", plain_t),
    ):
        print(f"| {name} | {min(ts):.2f} | {1000 * min(ts) / n:.2f} |")
    print(f"ratio fgslam / plain: {min(fg_t) / min(plain_t):.2f}")
    print(f"largest position difference between the two final trajectories: {diff.max():.3f} m")


if __name__ == "__main__":
    main()
