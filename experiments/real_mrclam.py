"""Point SLAM on the UTIAS MRCLAM dataset's format (fgslam.io.readers.mrclam): EKF, iSAM2 and
batch with the landmarks' subjects as the given association and with the project's own,
against the ground truth.

Run: python experiments/real_mrclam.py [DIR] [--robot N] [--seeds K] [--duration S]
With DIR (an MRCLAM dataset directory: Barcodes.dat, Landmark_Groundtruth.dat,
Robot{n}_*.dat) robot N's run (the first S seconds with --duration); without, K simulated
MRCLAM-like logs (fgslam.sim.landmarks.write_mrclam_like, seeds 0..K-1, S seconds each, 300
by default) written to a temporary directory. The reader's noise model is its defaults
(fgslam.io.readers.mrclam.MrclamNoise; the simulator draws from the same model).

One markdown table per run: backend, association, ATE RMSE of the trajectory against the
ground truth interpolated at the pose times after SE(2) alignment (m), that of the
odometry alone, the own association's purity / split / unassigned share against the
landmarks' subjects, the landmark map error (the median distance of each estimated landmark,
moved by the trajectory's alignment, to the nearest true landmark of
Landmark_Groundtruth.dat; m), the "unreliable" marks of the map's lifecycle and the
run time (s); then the medians over the runs.

The map parameters are pointslam's POINT_MAP_PARAMS, set for Victoria Park (trees seen up
to 80 m): ``max_range`` 100 m makes every landmark of the arena "predicted in view" in the
half-plane ahead, so the lifecycle counts misses of landmarks the 5 m camera cannot see
and marks them unreliable (the "unreliable" column), which changes no association here.
``--map-range R`` runs with ``max_range`` R m and a 70 deg field of view instead (the camera's).
"""

from __future__ import annotations

import argparse
import math
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np

from fgslam.evaluation.metrics import align_se2, apply_se2, ate_at_times, match_times
from fgslam.io.readers.mrclam import Mrclam, read_mrclam
from fgslam.sim.landmarks import write_mrclam_like
from fgslam.slam.pointslam import (
    ASSOCIATIONS,
    BACKENDS,
    POINT_MAP_PARAMS,
    PointSlamResult,
    association_agreement,
    run_points,
)

COLUMNS = (
    "backend",
    "association",
    "ATE RMSE (m)",
    "odometry ATE (m)",
    "purity",
    "split",
    "unassigned",
    "map error (m)",
    "unreliable",
    "time (s)",
)


def map_error(m: Mrclam, r: PointSlamResult) -> float:
    """Median distance (m) of the estimated landmarks, moved by the SE(2) alignment of the
    trajectory onto the ground truth, to the nearest true landmark (the landmarks are 1 m
    apart or more, the errors cm: the nearest is the landmark's own; whether the own
    association put the right sightings together is the purity's to say)."""
    t = m.pose_times[r.index]
    mask, ref = match_times(t, m.truth_t, m.truth)
    angle, shift = align_se2(r.poses[mask], ref)
    if not r.landmarks or not m.landmarks_truth:
        return float("nan")
    est = np.array([[x, y, 0.0] for x, y in (v[:2] for v in r.landmarks.values())])
    est = apply_se2(angle, shift, est)[:, :2]
    true = np.array(list(m.landmarks_truth.values()))
    d = np.hypot(*(est[:, None, :] - true[None, :, :]).transpose(2, 0, 1)).min(axis=1)
    return float(np.median(d))


def row(m: Mrclam, r: PointSlamResult) -> dict[str, object]:
    t = m.pose_times[r.index]
    agree = association_agreement(r.assigned) if r.association == "own" else None
    return {
        "backend": r.backend,
        "association": r.association,
        "ATE RMSE (m)": ate_at_times(t, r.poses, m.truth_t, m.truth)["rmse"],
        "odometry ATE (m)": ate_at_times(t, r.odometry, m.truth_t, m.truth)["rmse"],
        "purity": agree["purity"] if agree else None,
        "split": agree["split"] if agree else None,
        "unassigned": agree["unassigned"] if agree else None,
        "map error (m)": map_error(m, r),
        "unreliable": r.stats.get("points_unreliable", 0),
        "time (s)": r.wall_time,
    }


def fmt(key: str, v: object) -> str:
    if v is None:
        return "-"
    if key in ("purity", "unassigned"):
        return f"{100 * float(v):.1f} %"  # type: ignore[arg-type]
    if key == "split":
        return f"{float(v):.2f}"  # type: ignore[arg-type]
    if key == "unreliable":
        return f"{float(v):.0f}"  # type: ignore[arg-type]
    if key == "time (s)":
        return f"{float(v):.1f}"  # type: ignore[arg-type]
    if isinstance(v, float):
        return f"{v:.3f}"
    return str(v)


def table(rows: list[dict[str, object]]) -> str:
    lines = ["| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    lines += ["| " + " | ".join(fmt(k, r[k]) for k in COLUMNS) + " |" for r in rows]
    return "\n".join(lines)


def run(name: str, m: Mrclam, params, backends) -> list[dict[str, object]]:
    data = m.data
    lines_skipped = sum(n for k, n in data.problems.skipped_by_reason.items() if ".dat: " in k)
    print(
        f"\n### {name}: robot {m.robot}, {len(data.steps) + 1} poses over "
        f"{m.pose_times[-1] - m.pose_times[0]:.0f} s, {data.n_sightings} sightings of "
        f"{len(data.landmarks)} landmarks; dropped: "
        + ", ".join(f"{k} {v}" for k, v in m.dropped.items())
        + f"; bad lines skipped {lines_skipped}\n"
    )
    rows = [
        row(m, run_points(data, backend, assoc, map_params=params))
        for assoc in ASSOCIATIONS
        for backend in backends
    ]
    print(table(rows))
    return rows


def median_rows(runs: list[list[dict[str, object]]]) -> list[dict[str, object]]:
    out = []
    for k, first in enumerate(runs[0]):
        med: dict[str, object] = {"backend": first["backend"], "association": first["association"]}
        for key in COLUMNS[2:]:
            vals = [r[k][key] for r in runs]
            med[key] = None if vals[0] is None else float(np.median(np.array(vals, dtype=float)))
        out.append(med)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("directory", nargs="?", type=Path, help="an MRCLAM dataset directory")
    ap.add_argument("--robot", type=int, default=1, help="the robot's number (1-5)")
    ap.add_argument("--seeds", type=int, default=5, help="simulated logs (without DIR)")
    ap.add_argument("--duration", type=float, help="seconds (simulated: 300 by default)")
    ap.add_argument("--backends", nargs="+", choices=BACKENDS, default=list(BACKENDS))
    ap.add_argument("--map-range", type=float, help="the map's max_range (m), camera's fov")
    args = ap.parse_args()
    params = POINT_MAP_PARAMS
    if args.map_range is not None:
        params = replace(params, max_range=args.map_range, fov=math.radians(70.0))
    runs = []
    if args.directory is not None:
        m = read_mrclam(args.directory, args.robot, duration=args.duration)
        runs.append(run(str(args.directory), m, params, args.backends))
    else:
        duration = args.duration or 300.0
        with tempfile.TemporaryDirectory() as tmp:
            for seed in range(args.seeds):
                d = Path(tmp) / f"seed{seed}"
                write_mrclam_like(d, seed, robots=args.robot, duration=duration)
                m = read_mrclam(d, args.robot)
                runs.append(
                    run(f"simulated, seed {seed}, {duration:g} s", m, params, args.backends)
                )
    if len(runs) > 1:
        print(f"\n### median over the {len(runs)} runs\n")
        print(table(median_rows(runs)))


if __name__ == "__main__":
    main()
