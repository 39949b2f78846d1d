"""The relations benchmark (Kümmerle et al. 2009) on the shared laser logs (issue 13 section 5):
laser-only SLAM with each backend, next to odometry alone, the reference (GMapping) poses and
the published figures.

Run: python experiments/real_relations.py [--logs intel mit-csail freiburg-079 intel-bag]
       [--backends ekf isam2 batch] [--max-scans N] [--calibration off|wheels]
       [--laser-calibration off|offset|range] [--line-end-trim K]
       [--corners with-lines|replace-lines|off] [--landmarks on|off]
       [--time-registration per-feature|per-scan]
Reads ``../shared/data/<log>`` with fgslam.io.readers (corrected logs: odometry rebuilt, the
corrected poses as reference; mit-csail: a raw log), runs the front end in "laser" mode and
the backends (iSAM2 and batch share one graph; the EKF alone), and scores the keyframe poses
with the log's own odometry records filling relation ends between keyframes
(:func:`fgslam.evaluation.dense.relations_error_chain`, the benchmark's method); the ROS bag
(every scan, no reference poses) by its every-scan trajectory, interpolated. A backend that
fails is reported as failed, with what it did up to then. Prints one markdown row per run.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from real_carmen import limited  # the same scan limit as the ATE experiment

from fgslam.choices import (
    CALIBRATION_CHOICES,
    CORNER_CHOICES,
    LASER_CALIBRATION_CHOICES,
    TIME_REGISTRATION_CHOICES,
)
from fgslam.config import with_options
from fgslam.evaluation import dense
from fgslam.evaluation import metrics as evaluation
from fgslam.io.formats import open_log
from fgslam.io.readers.carmen import odometry_chain
from fgslam.sim.scenes import PAPER
from fgslam.slam.outputs import ScanSample, laser_points
from fgslam.slam.runner import run_backends

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
FILES = {
    "intel": ("intel-corrected.log.gz", "intel-corrected.relations"),
    "freiburg-079": ("freiburg-079-corrected.log.gz", "freiburg-079-corrected.relations"),
    "mit-csail": ("mit-csail.clf", "mit-csail.relations"),
    "intel-bag": ("intel.orig.bag", "intel.orig.relations"),
}
# published translational errors, m (Kümmerle et al. 2009; Cartographer: Hess et al. 2016)
PUBLISHED = {
    "intel": "graph 0.031, Cartographer 0.023, GMapping 0.070, scan matching 0.220",
    "freiburg-079": "graph 0.056, Cartographer 0.045, GMapping 0.061, scan matching 0.258",
    "mit-csail": "graph 0.004, Cartographer 0.032, GMapping 0.049, scan matching 0.106",
    "intel-bag": "the Intel anchors: graph 0.031, Cartographer 0.023, GMapping 0.070",
}


def score(chain, rel, t, poses) -> dict:
    """Relations error of the poses at times ``t``: along the log's odometry chain, or (no
    chain: an every-scan bag) interpolated."""
    if chain is None:
        return dense.relations_error(rel, t, poses)
    est, has = dense.estimate_at_scans(chain, t, poses)
    return dense.relations_error_chain(rel, chain, est, has)


def fmt(m: dict) -> str:
    return (
        f"{m['trans_mean']:.3f} ± {m['trans_std']:.3f} (max {m['trans_max']:.2f}) | "
        f"{m['rot_mean_deg']:.2f} ± {m['rot_std_deg']:.2f} | {m['relations_used']}"
    )


MODES = {  # the paper's pipeline (wheel odometry, every scan) and scan matching (issue 14)
    "wheels": PAPER,
    "scan": {"odometry": "both", "keyframes": "motion", "loop_closures": "on"},
    "scan-noloops": {"odometry": "both", "keyframes": "motion", "loop_closures": "off"},
}


def tap(events, sample: ScanSample):
    for ev in events:
        sample.add(ev)
        yield ev


def figure(folder: Path, name: str, mode: str, res, sample: ScanSample, cfg) -> None:
    """The map as laser points placed with the reference poses (left, where the log has them)
    and with the estimate (right): real_map_<log>_<mode>_<backend>.png."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = []
    if res.has_truth:
        panels.append(("reference (GMapping) poses", res.truth_t, res.truth))
    panels.append((f"{res.backend}, {mode}: estimate", *res.every_scan))
    fig, axs = plt.subplots(1, len(panels), figsize=(7 * len(panels), 7), squeeze=False)
    for ax, (title, t, poses) in zip(axs[0], panels, strict=True):
        pts = laser_points(sample.scans, t, poses, cfg)
        ax.plot(pts[:, 0], pts[:, 1], ".", ms=0.5, color="k", alpha=0.5)
        ax.plot(poses[:, 0], poses[:, 1], "-", lw=0.6, color="tab:green")
        ax.set_aspect("equal")
        ax.set_title(title)
    fig.suptitle(f"{name}: laser points placed with each trajectory")
    fig.tight_layout()
    folder.mkdir(parents=True, exist_ok=True)
    fig.savefig(folder / f"real_map_{name}_{mode}_{res.backend}.png", dpi=90)
    plt.close(fig)


def run(
    name: str,
    backends: list[str],
    max_scans: int | None,
    mode: str = "scan",
    header: bool = True,
    figures: Path | None = None,
    calibration: str | None = None,
    corners: str | None = None,
    laser_calibration: str | None = None,
    line_end_trim: float | None = None,
    landmarks: bool | None = None,
    time_registration: str | None = None,
) -> None:
    log_file, rel_file = FILES[name]
    path, rel = DATA / log_file, dense.read_relations(DATA / rel_file)
    chain = None if path.suffix == ".bag" else odometry_chain(path)
    reference = None if chain is None else chain.scan_poses
    groups = [[b] for b in backends if b == "ekf"] + [[b for b in backends if b != "ekf"]]
    first = header
    for group in [g for g in groups if g]:
        reader = open_log(path)
        cfg = with_options(
            reader.config,
            {
                "scanmatch": MODES[mode],
                "odometry": {"calibration": calibration},
                "laser": {"calibration": laser_calibration, "time_registration": time_registration},
                "frontend": {"corners": corners, "line_end_trim": line_end_trim},
                "map": {"landmarks": landmarks},
            },
        )
        sample = ScanSample(max_scans=1500)
        t0 = time.perf_counter()
        results = run_backends(tap(limited(reader, max_scans), sample), cfg, group, "laser")
        wall = time.perf_counter() - t0
        for res in results:
            if first:  # odometry alone and the reference, on the same keyframes
                first = False
                odo = score(chain, rel, res.times, res.odometry)
                print(f"| {name} | odometry alone | {fmt(odo)} | | | | | |")
                if chain is not None and np.isfinite(reference).all() and name != "mit-csail":
                    ref = dense.relations_error_chain(
                        rel, chain, reference, np.ones(len(reference), dtype=bool)
                    )
                    print(f"| {name} | reference (GMapping) poses | {fmt(ref)} | | | | | |")
            m = score(chain, rel, *res.every_scan)
            ate = ""
            if res.has_truth:
                truth = evaluation.interpolate_poses(res.truth_t, res.truth, res.times)
                ate = f"{evaluation.ate(res.poses, truth)['rmse']:.2f}"
            note = ""
            if "partial" in res.stats:
                note = " (partial: " + str(res.stats["partial"]["error"])[:60] + ")"
            if figures is not None and res.backend == "isam2":
                figure(figures, name, mode, res, sample, cfg)
            loops = sum(c["accepted"] for c in res.loop_closures)
            if res.calibration is not None:
                est = ", ".join(f"{1e3 * v:.1f}" for v in res.calibration["estimate"])
                note += f" (calibration 1e-3: {est})"
            print(
                f"| {name} | {res.backend} ({mode}){note} | {fmt(m)} | {ate} | "
                f"{len(res.landmarks)} | {len(res.times)} | {loops} | {wall:.0f} |",
                flush=True,
            )
    if header:
        print(f"| {name} | published | {PUBLISHED[name]} | | | | | | | |", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--logs", nargs="+", default=list(FILES), choices=list(FILES))
    ap.add_argument("--backends", nargs="+", default=["ekf", "isam2", "batch"])
    ap.add_argument("--max-scans", type=int, default=None)
    ap.add_argument(
        "--modes",
        nargs="+",
        choices=list(MODES),
        default=["wheels", "scan"],
        help="wheels: the paper's pipeline (wheel odometry, every scan a keyframe, no loops); "
        "scan: scan matching, keyframes by motion, loop closures",
    )
    ap.add_argument(
        "--figures", type=Path, default=None, help="write real_map_*.png into this folder"
    )
    ap.add_argument(
        "--calibration",
        choices=CALIBRATION_CHOICES,
        help="estimate the wheel calibration (default: the log's configuration, off)",
    )
    ap.add_argument(
        "--laser-calibration",
        choices=LASER_CALIBRATION_CHOICES,
        help="estimate the laser's range offset (and scale) (default: the log's "
        "configuration, off)",
    )
    ap.add_argument(
        "--line-end-trim",
        type=float,
        help="line fits leave out end beams beyond this many robust range sigmas (default: the "
        "configuration's, 0: off)",
    )
    ap.add_argument(
        "--corners",
        choices=CORNER_CHOICES,
        help="corners with their lines (the paper), instead of them, or none (default: the "
        "configuration's)",
    )
    ap.add_argument(
        "--landmarks",
        choices=["on", "off"],
        help="line and corner landmarks in the graph, or scan matching and loop closures "
        "alone (default: the configuration's, on)",
    )
    ap.add_argument(
        "--time-registration",
        choices=TIME_REGISTRATION_CHOICES,
        help="a scan's time error on each laser feature, or once per scan on the pose "
        "(default: the configuration's)",
    )
    args = ap.parse_args()
    print(
        "| log | estimate | relations trans (m): mean ± std (max) | rot (deg) | relations used "
        "| ATE vs reference (m) | landmarks | keyframes | loops | wall (s) |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for name in args.logs:
        for i, mode in enumerate(args.modes):
            run(
                name,
                args.backends,
                args.max_scans,
                mode,
                header=i == 0,
                figures=args.figures,
                calibration=args.calibration,
                corners=args.corners,
                laser_calibration=args.laser_calibration,
                line_end_trim=args.line_end_trim,
                landmarks=None if args.landmarks is None else args.landmarks == "on",
                time_registration=args.time_registration,
            )


if __name__ == "__main__":
    main()
