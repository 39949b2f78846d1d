"""Backend speed: iSAM2 and the EKF on the whole simulated corridor run (real-time factor and
per-keyframe latency, measured side by side in one run), and the cost of a step against the
number of landmarks on a corridor ten times as long (600 m), plotted.

Run: python experiments/bench_backends.py [--long-duration 900]
Writes experiments/bench_backends.png.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from fgslam.config import load_config
from fgslam.sim.simulate import events, plan_run
from fgslam.sim.world import load_world, parse_world
from fgslam.slam.runner import run_backends

HERE = Path(__file__).resolve().parent


def long_corridor(length: float = 600.0) -> dict:
    """A 2 m wide corridor ``length`` m long with doors every 5 m (recessed, flush)."""
    pts = [[0.0, 0.0], [length, 0.0], [length, 2.0], [0.0, 2.0]]
    doors, mould = [], []
    for k, x in enumerate(np.arange(3.0, length - 3.0, 5.0)):
        doors.append(
            {
                "wall": "c",
                "segment": 0,
                "at": float(x),
                "width": 0.9,
                "side": "right",
                **({"recess": 0.15} if k % 2 == 0 else {}),
            }
        )
        doors.append(
            {
                "wall": "c",
                "segment": 2,
                "at": float(x + 1.5),
                "width": 0.9,
                "side": "right",
                **({"recess": 0.2} if k % 3 == 0 else {}),
            }
        )
        mould.append({"wall": "c", "segment": 0, "at": float(x + 2.5), "side": "left"})
    return {
        "name": "long-corridor",
        "walls": [{"id": "c", "points": pts, "closed": True}],
        "doors": doors,
        "mouldings": mould,
        "route": [[1.0, 1.0], [length - 1.0, 1.0]],
    }


def table(results, label: str) -> None:
    for r in results:
        lat = np.array(r.latencies) * 1000
        backend_s = float(np.sum(r.latencies))
        print(
            f"| {label} | {r.backend} | {r.log_duration:.0f} | {r.wall_time:.1f} | "
            f"{r.log_duration / r.wall_time:.1f} | {backend_s:.1f} | "
            f"{r.log_duration / backend_s:.1f} | "
            f"{np.percentile(lat, 50):.1f} / {np.percentile(lat, 95):.1f} / {lat.max():.0f} | "
            f"{len(r.landmarks)} |"
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--long-duration", type=float, default=900.0, help="s of driving in the long corridor"
    )
    args = ap.parse_args()
    cfg = load_config()
    print(
        "| run | backend | log (s) | wall, all (s) | real-time factor, all | backend only (s) | "
        "real-time factor, backend | latency p50 / p95 / max (ms) | landmarks |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    w = load_world("corridor")
    evs = list(events(w, cfg, plan_run(w, cfg, 0)))
    table(run_backends(evs, cfg, ["ekf", "isam2"], "fused"), "corridor, fused")
    lw = parse_world(long_corridor(), "long")
    t0 = time.perf_counter()
    evs = list(events(lw, cfg, plan_run(lw, cfg, 0, duration=args.long_duration)))
    sim = time.perf_counter() - t0
    res = run_backends(evs, cfg, ["ekf", "isam2"], "fused")
    table(res, "600 m corridor, fused")
    print(
        f"\n(simulating the long run took {sim:.0f} s; 'all' includes the front end, which both "
        "backends share in one pass; 'backend only' is the per-keyframe time of each backend)"
    )
    fig, ax = plt.subplots(figsize=(8, 5))
    for r in res:
        n = np.array(r.landmark_counts)
        lat = np.array(r.latencies) * 1000
        # median latency per bin of landmark count
        bins = np.linspace(0, n.max() + 1, 30)
        idx = np.digitize(n, bins)
        xs = [n[idx == i].mean() for i in np.unique(idx)]
        ys = [np.median(lat[idx == i]) for i in np.unique(idx)]
        ax.plot(n, lat, ".", ms=1.5, alpha=0.3)
        ax.plot(xs, ys, "-", lw=2, label=f"{r.backend} (median)")
    ax.set_xlabel("landmarks in the map")
    ax.set_ylabel("time per keyframe (ms)")
    ax.set_yscale("log")
    ax.set_title("cost per step against map size, 600 m corridor")
    ax.legend()
    fig.tight_layout()
    fig.savefig(HERE / "bench_backends.png", dpi=110)


if __name__ == "__main__":
    main()
