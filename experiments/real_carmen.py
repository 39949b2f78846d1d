"""Laser-only line and corner SLAM on the Intel Research Lab and Freiburg 079 CARMEN logs,
against their corrected (GMapping) poses, next to odometry alone.

Run: python experiments/real_carmen.py [--logs intel freiburg-079] [--backends ekf isam2 batch]
       [--max-scans N] [--association jcbb|nn]
Reads ``../shared/data/<log>-corrected.log.gz`` with fgslam.io.readers.carmen (odometry rebuilt
as inverse(P_{k-1}) * ODOM_before_k, the corrected poses as the reference trajectory, not
ground truth), runs the front end in "laser" mode and each backend (EKF alone, on the first
``--ekf-max-scans`` scans; iSAM2 and batch share one graph), and prints ATE after SE(2)
alignment and RPE over 1 m against the reference. A backend that fails is reported as
failed. Writes real_carmen.png next to this file (reference, odometry and the estimates,
aligned to the reference).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from fgslam.evaluation import metrics as evaluation
from fgslam.events import LaserScan
from fgslam.io.readers.carmen import CarmenLog
from fgslam.slam.graph_solve import BackendError
from fgslam.slam.runner import run_backends

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"


def limited(log: CarmenLog, max_scans: int | None):
    n = 0
    for ev in log:
        if isinstance(ev, LaserScan):
            n += 1
            if max_scans is not None and n > max_scans:
                return
        yield ev


def run(
    name: str,
    backends: list[str],
    max_scans: int | None,
    ekf_max_scans: int | None,
    association: str = "jcbb",
) -> list[dict]:
    path = DATA / f"{name}-corrected.log.gz"
    rows = []
    groups = [[b] for b in backends if b == "ekf"] + [[b for b in backends if b != "ekf"]]
    for group in [g for g in groups if g]:
        log = CarmenLog(path)
        n = max_scans
        if group == ["ekf"] and ekf_max_scans is not None:
            n = min(n or ekf_max_scans, ekf_max_scans)
        t0 = time.perf_counter()
        try:
            results = run_backends(
                limited(log, n), log.config, group, "laser", association=association
            )
        except BackendError as exc:
            for b in group:
                rows.append({"log": name, "backend": b, "error": str(exc)})
            continue
        wall = time.perf_counter() - t0
        for res in results:
            ref = evaluation.interpolate_poses(res.truth_t, res.truth, res.times)
            rows.append(
                {
                    "log": name,
                    "backend": res.backend,
                    "scans": len(res.times),
                    "distance": float(np.sum(np.hypot(*np.diff(ref[:, :2], axis=0).T))),
                    "landmarks": dict(
                        sorted(
                            (k, sum(lm.kind == k for lm in res.landmarks.values()))
                            for k in ("line", "corner")
                        )
                    ),
                    "never": sum(v for k, v in res.stats.items() if k.endswith("_never_confirmed")),
                    "unreliable": sum(lm.status == "unreliable" for lm in res.landmarks.values()),
                    "partial": res.stats.get("partial"),
                    "ate": evaluation.ate(res.poses, ref),
                    "ate_odo": evaluation.ate(res.odometry, ref),
                    "rpe": evaluation.rpe(res.poses, ref, 1.0),
                    "rpe_odo": evaluation.rpe(res.odometry, ref, 1.0),
                    "wall": res.wall_time if len(group) > 1 else wall,
                    "problems": log.problems.summary(),
                    "res": res,
                    "ref": ref,
                }
            )
    return rows


HEADER = (
    "| log | backend | scans | path (m) | landmarks | ATE RMSE (m) | ATE max (m) "
    "| odometry ATE RMSE (m) | RPE 1 m trans (m) | RPE 1 m rot (deg) | odometry RPE trans / "
    "rot | time (s) |\n|---|---|---|---|---|---|---|---|---|---|---|---|"
)


def print_row(r: dict) -> None:
    if "error" in r:
        print(f"| {r['log']} | {r['backend']} | failed: {r['error']} |", flush=True)
        return
    lm = ", ".join(f"{v} {k}s" for k, v in r["landmarks"].items())
    lm += f" ({r['unreliable']} unreliable; {r['never']} tentative never confirmed)"
    if r.get("partial"):
        lm += f" PARTIAL: {r['partial']}"
    print(
        f"| {r['log']} | {r['backend']} | {r['scans']} | {r['distance']:.0f} | {lm} "
        f"| {r['ate']['rmse']:.2f} | {r['ate']['max']:.2f} | {r['ate_odo']['rmse']:.2f} "
        f"| {r['rpe']['trans_rmse']:.3f} | {r['rpe']['rot_rmse_deg']:.2f} "
        f"| {r['rpe_odo']['trans_rmse']:.3f} / {r['rpe_odo']['rot_rmse_deg']:.2f} "
        f"| {r['wall']:.0f} |",
        flush=True,
    )


def plot(rows: list[dict], logs: list[str], png: Path) -> None:
    ok = [r for r in rows if "error" not in r]
    names = [n for n in logs if any(r["log"] == n for r in ok)]
    if not names:
        return
    fig, axes = plt.subplots(1, len(names), figsize=(8 * len(names), 7), squeeze=False)
    colors = {"ekf": "tab:red", "isam2": "tab:blue", "batch": "tab:green"}
    for ax, name in zip(axes[0], names, strict=True):
        mine = [r for r in ok if r["log"] == name]
        longest = max(mine, key=lambda r: len(r["ref"]))  # the EKF may have a prefix only
        ref = longest["ref"]
        odo = longest["res"].odometry
        ax.plot(ref[:, 0], ref[:, 1], "-", color="0.5", lw=1.2, label="reference (corrected)")
        o = evaluation.apply_se2(*evaluation.align_se2(odo, ref), odo)
        ax.plot(o[:, 0], o[:, 1], ":", color="tab:orange", lw=1.0, label="odometry")
        for r in mine:
            p = r["res"].poses
            p = evaluation.apply_se2(*evaluation.align_se2(p, r["ref"]), p)
            ax.plot(
                p[:, 0],
                p[:, 1],
                "-",
                color=colors[r["backend"]],
                lw=0.8,
                label=f"{r['backend']}, {r['scans']} scans (ATE {r['ate']['rmse']:.2f} m)",
            )
        ax.set(aspect="equal", title=f"{name}: laser-only lines and corners", xlabel="x (m)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(png, dpi=80)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--logs", nargs="+", default=["intel", "freiburg-079"])
    ap.add_argument("--backends", nargs="+", default=["ekf", "isam2", "batch"])
    ap.add_argument("--max-scans", type=int, help="only the first N scans of each log")
    ap.add_argument(
        "--ekf-max-scans",
        type=int,
        default=1200,
        help="the EKF on the first N scans only (default 1200: its cost per update grows with "
        "the square of the map; on the whole Freiburg 079 log it had not finished after 6 minutes)",
    )
    ap.add_argument(
        "--png", type=Path, default=Path(__file__).with_suffix(".png"), help="figure to write"
    )
    ap.add_argument("--association", choices=["jcbb", "nn"], default="jcbb")
    args = ap.parse_args()
    print(f"association: {args.association}")
    print(HEADER, flush=True)
    rows: list[dict] = []
    for name in args.logs:  # rows and the figure as each log finishes
        new = run(name, args.backends, args.max_scans, args.ekf_max_scans, args.association)
        for r in new:
            print_row(r)
        rows += new
        plot(rows, args.logs, args.png)
    for name in args.logs:
        ok = [r for r in rows if r["log"] == name and "error" not in r]
        if ok:  # the reader's counts over the longest read
            print(f"{name}: reader: {max(ok, key=lambda r: r['scans'])['problems']}")


if __name__ == "__main__":
    main()
