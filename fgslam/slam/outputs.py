"""The files every SLAM run writes: trajectory.tum, map.json, report.json, map.png.

World frame, m, rad. The map frame is anchored at the first keyframe's true pose when the log
has ground truth, so errors against the truth need no alignment; the ATE is reported after an
SE(2) alignment all the same, as is customary.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.patches import Ellipse

from factors.geometry import wrap_angle
from fgslam import evaluation
from fgslam.slam.runner import SlamResult


def map_dict(res: SlamResult) -> dict[str, Any]:
    """Every landmark with kind, parameters, covariance, endpoints and sensor support."""
    out = []
    for lid, lm in sorted(res.landmarks.items()):
        if lid not in res.means:
            continue
        m = res.means[lid]
        d: dict[str, Any] = {"id": lid, "kind": lm.kind}
        if lm.kind == "line":
            d["alpha"], d["d"] = float(m[0]), float(m[1])
            if lm.ends is not None:  # world points: no (alpha, d) flip can mirror them
                d["endpoints"] = np.asarray(lm.ends).round(4).tolist()
        elif lm.kind == "corner":
            d["x"], d["y"], d["theta"] = (float(v) for v in m)
            d["convex"] = lm.convex
            if lm.arms is not None:
                d["endpoints"] = lm.arms.round(4).tolist()
        else:
            d["x"], d["y"] = float(m[0]), float(m[1])
        cov = res.landmark_covs.get(lid)
        d["covariance"] = None if cov is None else np.asarray(cov).tolist()
        d["observations"] = dict(lm.observations)
        d["sonar_readings"] = lm.sonar_readings
        d["status"] = lm.status  # "confirmed", or "unreliable": in view, not seen for long
        out.append(d)
    return {"frame": "world (m, rad)", "landmarks": out}


def map_error(res: SlamResult, true_map: dict[str, Any]) -> dict[str, Any]:
    """Errors of the estimated landmarks against the nearest true feature of their kind."""
    out: dict[str, Any] = {}
    lines = [ln for ln in true_map.get("lines", []) if ln.get("laser", True)]
    errs = {"line_d": [], "line_alpha_deg": [], "corner": [], "point": []}
    for lid, lm in res.landmarks.items():
        if lid not in res.means:
            continue
        m = res.means[lid]
        if lm.kind == "line" and lines:
            best = min(
                lines,
                key=lambda t: abs(wrap_angle(t["alpha"] - m[0])) * 3.0 + abs(t["d"] - m[1]),
            )
            errs["line_d"].append(abs(best["d"] - m[1]))
            errs["line_alpha_deg"].append(math.degrees(abs(wrap_angle(best["alpha"] - m[0]))))
        elif lm.kind in ("corner", "point"):
            pts = true_map.get("corners" if lm.kind == "corner" else "points", [])
            if lm.kind == "point":
                pts = pts + true_map.get("corners", [])
            if pts:
                errs[lm.kind].append(min(math.hypot(p["x"] - m[0], p["y"] - m[1]) for p in pts))
    for k, v in errs.items():
        if v:
            out[k] = {"median": float(np.median(v)), "mean": float(np.mean(v)), "n": len(v)}
    return out


def report_dict(res: SlamResult, true_map: dict[str, Any] | None = None) -> dict[str, Any]:
    lat = np.array(res.latencies) * 1000 if res.latencies else np.zeros(1)
    kinds: dict[str, int] = {}
    for lm in res.landmarks.values():
        kinds[lm.kind] = kinds.get(lm.kind, 0) + 1
    rep: dict[str, Any] = {
        "backend": res.backend,
        "sensors": res.sensors,
        "poses": len(res.times),
        "landmarks": kinds,
        "landmarks_total": sum(kinds.values()),
        "wall_time_s": round(res.wall_time, 3),
        "log_duration_s": round(res.log_duration, 3),
        "realtime_factor": round(res.log_duration / res.wall_time, 2) if res.wall_time else None,
        "batch_optimisation_s": round(res.batch_seconds, 3),
        "keyframe_latency_ms": {
            "p50": float(np.percentile(lat, 50)),
            "p95": float(np.percentile(lat, 95)),
            "max": float(lat.max()),
        },
        "statistics": dict(res.stats),
    }
    if res.has_truth and len(res.times):
        ref = evaluation.interpolate_poses(res.truth_t, res.truth, res.times)
        rep["ate"] = evaluation.ate(res.poses, ref)
        rep["ate_online"] = evaluation.ate(res.filtered, ref)
        rep["ate_odometry"] = evaluation.ate(res.odometry, ref)
        e = res.poses[-1] - ref[-1]
        rep["final_pose_error"] = {
            "position_m": float(math.hypot(e[0], e[1])),
            "heading_deg": float(math.degrees(abs(wrap_angle(e[2])))),
        }
        covs = [c for c in res.covs if c is not None]
        if len(covs) == len(res.times):
            rep["nees"] = evaluation.nees(res.poses, np.array(covs), ref)
        if true_map:
            rep["map_error"] = map_error(res, true_map)
    return rep


def plot_map(res: SlamResult, path: str | Path, title: str = "") -> None:
    fig, ax = plt.subplots(figsize=(14, 6))
    if res.has_truth:
        ax.plot(res.truth[:, 0], res.truth[:, 1], "-", color="0.6", lw=1.0, label="true path")
    if len(res.odometry):
        ax.plot(
            res.odometry[:, 0],
            res.odometry[:, 1],
            ":",
            color="tab:orange",
            lw=1.0,
            label="odometry only",
        )
    ax.plot(
        res.poses[:, 0],
        res.poses[:, 1],
        "-",
        color="tab:green",
        lw=1.2,
        label=f"{res.backend} estimate",
    )
    for lid, lm in res.landmarks.items():
        if lid not in res.means:
            continue
        m = res.means[lid]
        cov = res.landmark_covs.get(lid)
        if lm.kind == "line" and lm.ends is not None:
            e = np.asarray(lm.ends)
            ax.plot(e[:, 0], e[:, 1], "-", color="tab:blue", lw=1.5)
        elif lm.kind in ("corner", "point"):
            ax.plot(
                m[0],
                m[1],
                "^" if lm.kind == "corner" else "o",
                color="tab:red" if lm.kind == "corner" else "tab:purple",
                ms=4,
                mfc="none",
            )
            if cov is not None:
                _ellipse(ax, m[:2], np.asarray(cov)[:2, :2])
    ax.plot([], [], "-", color="tab:blue", label="map lines")
    ax.plot([], [], "^", color="tab:red", mfc="none", label="corners (3-sigma ellipses)")
    ax.plot([], [], "o", color="tab:purple", mfc="none", label="points")
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title or f"{res.backend}, {res.sensors}: {len(res.landmarks)} landmarks")
    ax.legend(loc="best", fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _ellipse(ax, mean, cov, nsig: float = 3.0) -> None:
    vals, vecs = np.linalg.eigh(cov)
    vals = np.maximum(vals, 0.0)
    ang = math.degrees(math.atan2(vecs[1, 1], vecs[0, 1]))
    ax.add_patch(
        Ellipse(
            mean,
            2 * nsig * math.sqrt(vals[1]),
            2 * nsig * math.sqrt(vals[0]),
            angle=ang,
            fill=False,
            color="tab:red",
            lw=0.6,
        )
    )


def write_outputs(
    res: SlamResult, out: str | Path, true_map: dict[str, Any] | None = None
) -> dict[str, Any]:
    """Write the four files into directory ``out``; returns the report."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    evaluation.write_tum(out / "trajectory.tum", res.times, res.poses)
    (out / "map.json").write_text(json.dumps(map_dict(res), indent=1))
    rep = report_dict(res, true_map)
    (out / "report.json").write_text(json.dumps(rep, indent=2))
    plot_map(res, out / "map.png")
    return rep
