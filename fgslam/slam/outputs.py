"""The files every SLAM run writes: trajectory.tum, map.json, report.json, map.png.

World frame, m, rad. The map frame is anchored at the first keyframe's true pose when the log
has ground truth, so errors against the truth need no alignment; the ATE is reported after an
SE(2) alignment all the same, as is customary. Every file is written atomically (a temporary
file in the same folder, renamed), so a folder never holds half a file. A result whose
backend failed mid-run (``stats["partial"]``) is written all the same, marked partial.

Outputs never stop a run's end: each is written on its own (:class:`OutputGuard`), and a
metric that cannot be computed is left out of report.json with its reason.
"""

from __future__ import annotations

import contextlib
import json
import math
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.patches import Ellipse

from factors.geometry import wrap_angle
from fgslam.config import RobotConfig
from fgslam.errors import EvaluationError, OutputWarning
from fgslam.evaluation import metrics as evaluation
from fgslam.events import Event, LaserScan
from fgslam.io import safeio
from fgslam.slam.runner import SlamResult

MAX_MAP_POINTS = 150_000  # laser points drawn in map.png at most
_T = TypeVar("_T")


class ScanSample:
    """A bounded, evenly thinned sample of a run's laser scans, for drawing the map: every
    ``every``-th scan is kept, and when more than ``max_scans`` are held every other one is
    dropped and ``every`` doubles, so memory stays bounded on logs of any length. A scan is
    kept as (time, ranges), or (time, ranges, bearings) when it has its own bearings
    (:class:`fgslam.events.LaserScan`)."""

    def __init__(self, max_scans: int = 800) -> None:
        self.max_scans = max_scans
        self.every = 1
        self.seen = 0
        self.scans: list[tuple] = []

    def add(self, ev: Event) -> None:
        if not isinstance(ev, LaserScan):
            return
        if self.seen % self.every == 0:
            r = np.asarray(ev.ranges, dtype=np.float32)
            self.scans.append((ev.t, r) if ev.bearings is None else (ev.t, r, ev.bearings))
            if len(self.scans) > self.max_scans:
                self.scans = self.scans[::2]
                self.every *= 2
        self.seen += 1


def laser_points(
    scans: list[tuple],
    times: np.ndarray,
    poses: np.ndarray,
    cfg: RobotConfig,
    max_points: int = MAX_MAP_POINTS,
) -> np.ndarray:
    """World (x, y) of the returns of ``scans`` (time, ranges in the laser frame, and the
    scan's own bearings in rad where it has them, as :class:`ScanSample` keeps them; else
    ``cfg.laser.bearings``), placed with the trajectory ``times``/``poses`` (interpolated
    between keyframes) and the laser mount; scans outside the trajectory's time span and
    no-return readings are left out, and the points thinned evenly to at most
    ``max_points``."""
    if not scans or len(times) < 1:
        return np.zeros((0, 2))
    t = np.array([s[0] for s in scans])
    keep = (t >= times[0] - 1e-9) & (t <= times[-1] + 1e-9)
    if not keep.any():
        return np.zeros((0, 2))
    t = t[keep]
    kept = [s for s, k in zip(scans, keep, strict=True) if k]
    if len(times) == 1:
        robot = np.repeat(poses[:1], len(t), axis=0)
    else:
        robot = evaluation.interpolate_poses(times, poses, t)
    m = cfg.laser.mount
    c, s = np.cos(robot[:, 2]), np.sin(robot[:, 2])
    lx = robot[:, 0] + c * m.x - s * m.y
    ly = robot[:, 1] + s * m.x + c * m.y
    if all(len(k) < 3 or k[2] is None for k in kept):  # the configured geometry: one array
        rng = np.array([k[1] for k in kept], dtype=float)
        ang = robot[:, 2:3] + math.radians(m.yaw_deg) + cfg.laser.bearings[None, :]
        ok = np.isfinite(rng) & (rng > 0) & (rng < 0.999 * cfg.laser.max_range)
        px = (lx[:, None] + rng * np.cos(ang))[ok]
        py = (ly[:, None] + rng * np.sin(ang))[ok]
    else:  # scans with their own bearings (beam counts may differ): scan by scan
        xs, ys = [], []
        for i, k in enumerate(kept):
            r = np.asarray(k[1], dtype=float)
            b = cfg.laser.bearings if len(k) < 3 or k[2] is None else np.asarray(k[2], float)
            if b.size != r.size:
                raise ValueError(f"a scan of {r.size} ranges with {b.size} bearings")
            ok = np.isfinite(r) & (r > 0) & (r < 0.999 * cfg.laser.max_range)
            a = robot[i, 2] + math.radians(m.yaw_deg) + b[ok]
            xs.append(lx[i] + r[ok] * np.cos(a))
            ys.append(ly[i] + r[ok] * np.sin(a))
        px, py = np.concatenate(xs), np.concatenate(ys)
    step = max(1, math.ceil(px.size / max_points))
    return np.column_stack([px[::step], py[::step]])


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


def report_dict(
    res: SlamResult,
    true_map: dict[str, Any] | None = None,
    true_calibration: dict[str, float] | None = None,
) -> dict[str, Any]:
    """report.json: counts, timing, statistics, the calibration estimates (against
    ``true_calibration``, a simulated log's, when given: :func:`calibration_against_truth`)
    and, against the log's reference poses, the metrics of :func:`reference_metrics` (those
    that cannot be computed, and why, under ``not_evaluated``)."""
    lat = np.array(res.latencies) * 1000 if res.latencies else np.zeros(1)
    kinds: dict[str, int] = {}
    for lm in res.landmarks.values():
        kinds[lm.kind] = kinds.get(lm.kind, 0) + 1
    rep: dict[str, Any] = {
        "backend": res.backend,
        "sensors": res.sensors,
        "poses": len(res.times),
        "scans_placed": len(res.every_scan[0]),
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
    if res.continued is not None:
        rep["continued"] = res.continued
    if res.loop_closures:
        acc = [c for c in res.loop_closures if c["accepted"]]
        rep["loop_closures"] = {
            "accepted": len(acc),
            "rejected": len(res.loop_closures) - len(acc),
            "attempts": res.loop_closures,
        }
        if res.has_truth:  # how many of the accepted ones the reference confirms
            rep["loop_closures"]["against_reference"] = evaluation.loop_agreement(
                res.loop_closures, res.times, res.truth_t, res.truth
            )
    if res.calibration is not None:
        rep["calibration"] = calibration_against_truth(res.calibration, true_calibration)
    if res.stats.get("partial"):
        rep["partial"] = dict(res.stats["partial"])
    if res.has_truth:
        rep.update(reference_metrics(res, true_map))
    else:
        rep["not_evaluated"] = {
            "ate": f"the log has {len(res.truth)} reference poses (ground truth or a "
            "reference trajectory): at least 2 are needed"
        }
    return rep


def calibration_against_truth(
    cal: dict[str, Any], truth: dict[str, float] | None
) -> dict[str, Any]:
    """report.json's ``calibration``: the estimates (``parameters``, ``estimate``, ``sigma``:
    relative errors; the laser's range offset in m, its scale per m) and, with the true
    values by name (a simulated log's), ``truth`` and ``error_sigmas`` ((estimate - truth) /
    sigma per parameter; null where there is no truth or sigma)."""
    out = dict(cal)
    if not truth:
        return out
    names, est, sig = cal["parameters"], cal["estimate"], cal.get("sigma")
    out["truth"] = [truth.get(n) for n in names]
    z = []
    for i, (e, t) in enumerate(zip(est, out["truth"], strict=True)):
        s = sig[i] if sig else None
        ok = t is not None and s is not None and s > 0 and math.isfinite(e - t)
        z.append(float((e - t) / s) if ok else None)
    out["error_sigmas"] = z
    return out


def reference_metrics(res: SlamResult, true_map: dict[str, Any] | None = None) -> dict[str, Any]:
    """The run against its reference (ground truth or a log's reference poses): the ATE of
    the final estimate ("ate"), of the online one ("ate_online") and of odometry alone
    ("ate_odometry"), each over its own poses within the reference's time span (the
    reference interpolated at their times; SE(2)-aligned), the unaligned error of the last
    such pose ("final_pose_error"), the NEES of those poses, raw and with the map's absolute
    scale taken out ("nees_scale_aligned", with the scale error k - 1), and the map error. A
    metric that cannot be computed (fewer than 2 poses within the reference: no alignment;
    non-finite poses) is left out, its reason under ``not_evaluated``."""
    out: dict[str, Any] = {}
    tracks = res.tracks()
    for key, track in (("ate", "estimate"), ("ate_online", "online"), ("ate_odometry", "odometry")):
        t, poses = tracks[track]
        evaluation.add_metric(
            out, key, lambda t=t, p=poses: evaluation.ate_at_times(t, p, res.truth_t, res.truth)
        )
    mask, ref = evaluation.match_times(res.times, res.truth_t, res.truth)
    idx = np.flatnonzero(mask)
    if not len(idx):
        out.setdefault("not_evaluated", {})["final_pose_error"] = (
            f"none of the {len(res.times)} poses lies within the reference's time span"
        )
        return out

    def final() -> dict[str, float]:
        e = res.poses[idx[-1]] - ref[-1]
        if not np.isfinite(e).all():
            raise EvaluationError(f"the last pose compared is not finite: {res.poses[idx[-1]]}")
        return {
            "position_m": float(math.hypot(e[0], e[1])),
            "heading_deg": float(math.degrees(abs(wrap_angle(e[2])))),
            "t": float(res.times[idx[-1]]),
        }

    evaluation.add_metric(out, "final_pose_error", final)
    covs = [res.covs[i] for i in idx] if len(res.covs) == len(res.times) else []
    if covs and all(c is not None for c in covs):
        evaluation.add_metric(
            out, "nees", lambda: evaluation.nees(res.poses[idx], np.array(covs), ref)
        )

        def scale_aligned() -> dict[str, float]:
            # the map's absolute scale taken out (docs/design.md, 6: odometry and laser with
            # unknown scale errors cannot observe it); k - 1 is the scale error
            scaled, k = evaluation.scale_about_start(res.poses[idx], ref)
            return {**evaluation.nees(scaled, np.array(covs), ref), "scale_error": k - 1.0}

        evaluation.add_metric(out, "nees_scale_aligned", scale_aligned)
    if true_map:
        out["map_error"] = map_error(res, true_map)
    return out


def plot_map(
    res: SlamResult,
    path: str | Path,
    title: str = "",
    *,
    world: Any = None,
    points: np.ndarray | None = None,
    truth_label: str = "true path",
) -> None:
    """The map as a person recognises it: the laser points placed with the estimate (grey),
    the world outline of a simulated log (black), the true or reference path, odometry, the
    estimate, and the landmarks on top; the figure is sized to what is drawn."""
    fig, ax = plt.subplots(figsize=_figsize(res, points))
    if points is not None and len(points):
        ax.plot(points[:, 0], points[:, 1], ".", color="0.35", ms=0.6, mew=0, alpha=0.8)
        ax.plot([], [], ".", color="0.35", ms=3, label="laser points (placed with the estimate)")
    if world is not None:
        from fgslam.evaluation.plotting import draw_world

        draw_world(ax, world)
        ax.plot([], [], "k-", lw=1.0, label="world (simulator)")
    if res.has_truth:
        ax.plot(res.truth[:, 0], res.truth[:, 1], "-", color="tab:cyan", lw=1.0, label=truth_label)
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
    _draw_loops(ax, res)
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
    lim = _extent(res, points)
    if lim is not None:
        ax.set_xlim(lim[0], lim[1])
        ax.set_ylim(lim[2], lim[3])
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    partial = " (PARTIAL: backend failed)" if res.stats.get("partial") else ""
    ax.set_title(
        (title or f"{res.backend}, {res.sensors}: {len(res.landmarks)} landmarks") + partial
    )
    handles, labels = ax.get_legend_handles_labels()
    uniq = {
        lab: h for lab, h in zip(labels, handles, strict=True) if lab != "laser points (estimate)"
    }
    ax.legend(uniq.values(), uniq.keys(), loc="best", fontsize=7)
    fig.tight_layout()
    with safeio.atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120)
    plt.close(fig)


def _draw_loops(ax, res: SlamResult) -> None:
    """Loop closures between the keyframes' estimated poses: accepted solid, rejected dotted."""
    n = len(res.poses)
    for accepted, style, label in ((False, ":", "rejected"), (True, "-", "accepted")):
        segs = [
            (res.poses[c["from"], :2], res.poses[c["to"], :2])
            for c in res.loop_closures
            if c["accepted"] == accepted and c["from"] < n and c["to"] < n
        ]
        for a, b in segs:
            ax.plot([a[0], b[0]], [a[1], b[1]], style, color="tab:pink", lw=0.8, alpha=0.8)
        if segs:
            ax.plot([], [], style, color="tab:pink", label=f"loop closures {label} ({len(segs)})")


def _extent(res: SlamResult, points: np.ndarray | None) -> tuple[float, ...] | None:
    """x0, x1, y0, y1 of the trajectories, the landmarks and (all but the farthest 0.2 % of)
    the laser points, with a margin."""
    parts = [res.poses[:, :2]]
    marks = []
    for lid, lm in res.landmarks.items():
        m = res.means.get(lid)
        if m is None:
            continue
        if lm.kind == "line" and lm.ends is not None:  # world points
            marks.append(np.asarray(lm.ends, dtype=float).reshape(-1, 2))
        elif lm.kind in ("corner", "point"):
            marks.append(np.asarray(m[:2], dtype=float).reshape(1, 2))
    if marks:
        lm_xy = np.concatenate(marks)
        if len(lm_xy) > 100:  # a few wild landmarks must not shrink the map to a corner
            lm_xy = np.percentile(lm_xy, [1.0, 99.0], axis=0)
        parts.append(lm_xy)
    if res.has_truth:
        parts.append(res.truth[:, :2])
    if points is not None and len(points) > 10:
        lo = np.percentile(points, 0.1, axis=0)
        hi = np.percentile(points, 99.9, axis=0)
        parts.append(np.array([lo, hi]))
    xy = np.concatenate([p for p in parts if len(p)]) if any(len(p) for p in parts) else None
    if xy is not None:  # a diverged (non-finite) pose is not drawn; it must not set the axes
        xy = xy[np.isfinite(xy).all(axis=1)]
    if xy is None or not len(xy):
        return None
    x0, y0 = xy.min(axis=0)
    x1, y1 = xy.max(axis=0)
    pad = 0.04 * max(x1 - x0, y1 - y0, 1.0)
    return x0 - pad, x1 + pad, y0 - pad, y1 + pad


def _figsize(res: SlamResult, points: np.ndarray | None) -> tuple[float, float]:
    """A figure of the map's aspect ratio, 12 in on its long side (legend room added)."""
    lim = _extent(res, points)
    if lim is None:
        return (8.0, 6.0)
    w, h = lim[1] - lim[0], lim[3] - lim[2]
    if w >= h:
        return (12.0, float(np.clip(12.0 * h / w, 3.0, 12.0)) + 0.8)
    return (float(np.clip(10.0 * w / h, 3.0, 10.0)) + 0.8, 10.0)


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


class OutputGuard:
    """Writes a run's outputs one at a time into ``folder``, so that one failing leaves the
    others written: :meth:`write` catches an output's failure (any exception), warns
    (:class:`~fgslam.errors.OutputWarning`, one line naming the output and the cause),
    removes the file an earlier run left under that name (it is not this run's) and lists the
    failure in :attr:`errors` (``{"output": name, "error": cause}``, for report.json)."""

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)
        self.errors: list[dict[str, str]] = []

    def run(self, name: str, make: Callable[[], _T]) -> _T | None:
        """``make()``, or None when it raised (reported as a failure of output ``name``)."""
        try:
            return make()
        except Exception as exc:  # one output's failure: reported, the others go on
            cause = f"{type(exc).__name__}: {exc}".strip().splitlines()[0]
            self.errors.append({"output": name, "error": cause})
            warnings.warn(f"{name} not written: {cause}", OutputWarning, stacklevel=2)
            return None

    def write(self, name: str, write: Callable[[Path], _T]) -> _T | None:
        """``write(folder / name)``, as :meth:`run`; on failure a file of that name is removed."""
        path = self.folder / name
        n = len(self.errors)
        got = self.run(name, lambda: write(path))
        if len(self.errors) > n:
            with contextlib.suppress(OSError):
                path.unlink(missing_ok=True)
        return got


def write_trajectory(path: str | Path, res: SlamResult) -> int:
    """trajectory.tum: the final estimate's poses that are finite and within
    ``evaluation.TUM_MAX_POSITION`` (what :func:`~fgslam.evaluation.metrics.read_tum` reads back);
    returns how many poses were left out."""
    t = np.asarray(res.times, dtype=float).reshape(-1)
    p = np.asarray(res.poses, dtype=float).reshape(-1, 3)
    ok = np.isfinite(p).all(axis=1) & np.isfinite(t)
    ok &= (np.abs(np.nan_to_num(p[:, :2])) <= evaluation.TUM_MAX_POSITION).all(axis=1)
    with safeio.atomic_path(path) as tmp:
        evaluation.write_tum(tmp, t[ok], p[ok])
    return int(len(p) - ok.sum())


def write_outputs(
    res: SlamResult,
    out: str | Path,
    true_map: dict[str, Any] | None = None,
    *,
    true_calibration: dict[str, float] | None = None,
    extra: dict[str, Any] | None = None,
    world: Any = None,
    scans: list[tuple[float, np.ndarray]] | None = None,
    cfg: RobotConfig | None = None,
    figure: bool = True,
    more: dict[str, Callable[[Path], object]] | None = None,
) -> dict[str, Any]:
    """Write trajectory.tum, map.json, map.png and report.json into directory ``out`` (each
    atomically, each on its own: one that fails is warned about and listed in report.json's
    ``output_errors``, and the others are still written; see :class:`OutputGuard`); returns
    the report.

    ``true_map``, ``true_calibration``: a simulated log's truth (:func:`report_dict`);
    ``extra``: more keys for report.json (what the reader found, ...); ``world``: the
    simulator's world, drawn as an outline; ``scans`` (time, ranges) with ``cfg``: laser scans
    drawn in map.png placed with the estimated trajectory (see :class:`ScanSample`);
    ``figure`` False leaves map.png out (a checkpoint of an online run); ``more``: further
    outputs by file name, each written by its function given its path (trajectory_dense.tum,
    ...). report.json is written last, so that it lists the failures of the others."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    guard = OutputGuard(out)
    rep = guard.run("report.json (metrics)", lambda: report_dict(res, true_map, true_calibration))
    if rep is None:  # report.json is written all the same, with what needs no computing
        rep = {"backend": res.backend, "sensors": res.sensors, "poses": len(res.times)}
        if res.stats.get("partial"):
            rep["partial"] = dict(res.stats["partial"])
    if extra:
        rep.update(extra)
    left_out = guard.write("trajectory.tum", lambda p: write_trajectory(p, res))
    if left_out:
        rep["trajectory_poses_left_out"] = left_out  # not finite, or beyond 1e9 m
    guard.write("map.json", lambda p: safeio.write_text(p, json.dumps(map_dict(res), indent=1)))
    for name, write in (more or {}).items():
        guard.write(name, write)
    if figure:
        label = "reference path" if rep.get("truth_source") == "reference" else "true path"

        def draw(path: Path) -> None:
            opened = set(plt.get_fignums())
            try:
                points = None
                if scans and cfg is not None and len(res.times):
                    points = laser_points(scans, *res.every_scan, cfg)
                plot_map(res, path, world=world, points=points, truth_label=label)
            finally:  # a figure left open by a failure
                for num in set(plt.get_fignums()) - opened:
                    plt.close(num)

        guard.write("map.png", draw)
    if guard.errors:
        rep["output_errors"] = guard.errors
    guard.write("report.json", lambda p: safeio.write_json(p, rep))
    if guard.errors:
        rep["output_errors"] = guard.errors
    return rep
