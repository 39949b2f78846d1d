"""Run every backend and sensor mode on one log and compare them: per-run outputs,
comparison.json, comparison.md and comparison.png (trajectories and errors over time)."""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from fgslam import evaluation
from fgslam.config import load_config
from fgslam.logfile import LogReader
from fgslam.slam.outputs import write_outputs
from fgslam.slam.runner import BACKENDS, SENSORS, SlamResult, run_backends


def _run_mode(
    log: str, config: str | None, sensors: str, backends: list[str], association: str = "jcbb"
) -> list[SlamResult]:
    reader = LogReader(log)
    cfg = load_config(config) if config else reader.config
    return run_backends(reader, cfg, backends, sensors, association=association)


def compare(
    log: str | Path,
    out: str | Path,
    config: str | None = None,
    backends: tuple[str, ...] = BACKENDS,
    sensors: tuple[str, ...] = SENSORS,
    workers: int | None = None,
    on_done: Callable[[SlamResult], None] | None = None,
    association: str = "jcbb",
) -> list[dict[str, Any]]:
    """Every backend in every sensor mode on ``log``; one process per sensor mode (the front
    end runs once per mode and feeds all backends); ``association`` "jcbb" or "nn" for every
    run. Returns the rows of the comparison."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    with LogReader(log) as r:
        true_map = r.meta.get("true_map")
    workers = workers or min(len(sensors), os.cpu_count() or 1)
    results: list[SlamResult] = []
    with ProcessPoolExecutor(max_workers=workers) as pool:
        futs = [
            pool.submit(_run_mode, str(log), config, s, list(backends), association)
            for s in sensors
        ]
        for fut in futs:
            for res in fut.result():
                results.append(res)
                if on_done:
                    on_done(res)
    rows = []
    for res in results:
        rep = write_outputs(res, out / f"{res.backend}-{res.sensors}", true_map)
        rows.append(rep)
    (out / "comparison.json").write_text(json.dumps(rows, indent=2))
    (out / "comparison.md").write_text(markdown_table(rows))
    plot_comparison(results, out / "comparison.png")
    return rows


def markdown_table(rows: list[dict[str, Any]]) -> str:
    head = (
        "| backend | sensors | ATE RMSE (m) | ATE max (m) | final error (m) | NEES mean (3) | "
        "lines | corners | points | real-time factor | latency p95 (ms) |\n"
        "|---|---|---|---|---|---|---|---|---|---|---|\n"
    )
    lines = []
    for r in rows:
        ate = r.get("ate", {})
        lm = r.get("landmarks", {})
        nees = r.get("nees", {}).get("mean")
        fin = r.get("final_pose_error", {}).get("position_m")

        def f(v, p=3):
            return "-" if v is None else f"{v:.{p}f}"

        lines.append(
            f"| {r['backend']} | {r['sensors']} | {f(ate.get('rmse'))} | {f(ate.get('max'))} | "
            f"{f(fin)} | {f(nees, 1)} | {lm.get('line', 0)} | {lm.get('corner', 0)} | "
            f"{lm.get('point', 0)} | {f(r.get('realtime_factor'), 1)} | "
            f"{f(r['keyframe_latency_ms']['p95'], 1)} |"
        )
    odo = next((r["ate_odometry"] for r in rows if "ate_odometry" in r), None)
    tail = (
        f"\nOdometry alone: ATE RMSE {odo['rmse']:.3f} m, max {odo['max']:.3f} m.\n" if odo else ""
    )
    return head + "\n".join(lines) + "\n" + tail


def plot_comparison(results: list[SlamResult], path: Path) -> None:
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(14, 9), gridspec_kw={"height_ratios": [3, 2]})
    truth_drawn = False
    for res in results:
        if res.has_truth and not truth_drawn:
            ax1.plot(res.truth[:, 0], res.truth[:, 1], "-", color="0.5", lw=2, label="truth")
            ref = evaluation.interpolate_poses(res.truth_t, res.truth, res.times)
            err = evaluation.position_errors(res.odometry, ref, align=False)
            ax2.plot(res.times, err, ":", color="0.3", label="odometry only")
            truth_drawn = True
        label = f"{res.backend} / {res.sensors}"
        ax1.plot(res.poses[:, 0], res.poses[:, 1], "-", lw=0.9, label=label)
        if res.has_truth:
            ref = evaluation.interpolate_poses(res.truth_t, res.truth, res.times)
            ax2.plot(
                res.times,
                evaluation.position_errors(res.poses, ref, align=False),
                "-",
                lw=0.9,
                label=label,
            )
    ax1.set_aspect("equal")
    ax1.set_xlabel("x (m)")
    ax1.set_ylabel("y (m)")
    ax1.legend(fontsize=7, ncol=3)
    ax1.set_title("trajectories")
    ax2.set_xlabel("time (s)")
    ax2.set_ylabel("position error (m)")
    ax2.set_yscale("log")
    ax2.legend(fontsize=7, ncol=4)
    ax2.set_title("position error against the truth (map anchored at the first true pose)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
