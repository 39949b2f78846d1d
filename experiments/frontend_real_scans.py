"""Lines and corners extracted by the front end from real SICK LMS scans (Freiburg building 079).

Run: python experiments/frontend_real_scans.py [--scans 300 1100 1900 2700 3500 4300]
       [--every 10]
Reads the given scans (0-based indices among the FLASER lines) of
``../shared/data/freiburg-079-corrected.log.gz`` (relative to the repository root) with the
CARMEN reader (fgslam.io.readers.carmen), and runs the front end's per-scan processing
(``FrontEnd.process_scan`` in "laser" mode: segmentation, polar line fits, right-angle corner
fits) on each with the reader's robot configuration for that laser: n beams over 180 deg (the
configuration's bearings: first beam at -90 deg), mounted at the robot origin, 1 cm range
resolution, sigma_range 1 cm, readings of 80 m or more (the LMS's "no return" codes, 81.91) as
no return. The robot's speed is
taken as zero (no time-registration inflation). Prints per scan the lines, corners and the
rejections counted in the scan's statistics, and draws the scans with their features in a
2 x 3 grid to frontend_real_scans.png next to this file (robot frame, x forward). The scans
drawn are evenly spread over the log, not chosen for their features; a summary over every
``--every``-th scan of the log follows.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from fgslam.events import LaserScan
from fgslam.frontend.pipeline import FrontEnd
from fgslam.io.readers.carmen import CarmenLog

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
LOG = DATA / "freiburg-079-corrected.log.gz"


def read_scans(path: Path):
    """The reader's configuration, and the timestamps (s) and ranges (m, NaN = no return) of
    every scan of a CARMEN log."""
    log = CarmenLog(path)
    scans = [e for e in log if isinstance(e, LaserScan)]
    return log.config, np.array([s.t for s in scans]), [s.ranges for s in scans]


def extract(fe: FrontEnd, t: float, r: np.ndarray):
    return r, fe.process_scan(LaserScan(t, r), 0.0, 0.0)


def rejections(stats, prefix: str) -> dict[str, int]:
    return {k[len(prefix) :]: v for k, v in stats.items() if k.startswith(prefix) and v}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scans", type=int, nargs="+", default=[300, 1100, 1900, 2700, 3500, 4300])
    ap.add_argument("--every", type=int, default=10, help="summary over every k-th scan")
    ap.add_argument("--log", type=Path, default=LOG)
    args = ap.parse_args()
    cfg, times, ranges = read_scans(args.log)
    n = cfg.laser.n_beams
    fe = FrontEnd(cfg, "laser")
    phi = cfg.laser.bearings
    print(f"{args.log.name}: {len(ranges)} scans of {n} beams over 180 deg")
    print(
        "| scan | time (s) | valid beams | lines | corners (tried) | segments too short "
        "| lines rejected | corners rejected |"
    )
    print(
        "|------|----------|-------------|-------|-----------------|--------------------"
        "|----------------|------------------|"
    )
    fmt = lambda d: ", ".join(f"{v} {k}" for k, v in sorted(d.items())) or "0"  # noqa: E731
    ncol = 3
    nrow = math.ceil(len(args.scans) / ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(5.4 * ncol, 4.6 * nrow), squeeze=False)
    for ax, k in zip(axes.flat, args.scans, strict=False):
        r, sf = extract(fe, times[k], ranges[k])
        st = sf.stats
        print(
            f"| {k:4d} | {times[k] - times[0]:8.1f} | {int(np.isfinite(r).sum()):11d} "
            f"| {st['lines']:5d} | {st['corners']:7d} ({st['corners_tried']:3d}) "
            f"| {st['segments_rejected_too_few_points']:18d} "
            f"| {fmt(rejections(st, 'lines_rejected_')):>14s} "
            f"| {fmt(rejections(st, 'corners_rejected_')):>16s} |"
        )
        x, y = r * np.cos(phi), r * np.sin(phi)
        ax.plot(x, y, ".", color="0.55", ms=2.5, label="scan points")
        first = {"line": True, "corner": True}
        for f in sf.features:
            if f.kind == "line":
                e = f.endpoints
                ax.plot(
                    e[:, 0],
                    e[:, 1],
                    "-",
                    color="tab:blue",
                    lw=2.2,
                    label="lines" if first["line"] else None,
                )
                first["line"] = False
            elif f.kind == "corner":
                phi_c, r_c = f.z[0], f.z[1]
                v = np.array([r_c * math.cos(phi_c), r_c * math.sin(phi_c)])
                arm = np.array([f.endpoints[0], v, f.endpoints[1]])
                ax.plot(arm[:, 0], arm[:, 1], "-", color="tab:red", lw=1.2, alpha=0.8)
                ax.plot(
                    *v,
                    "o",
                    color="tab:red",
                    ms=7,
                    mfc="none",
                    mew=2,
                    label="corners" if first["corner"] else None,
                )
                first["corner"] = False
        ax.plot(0, 0, "k^", ms=8)
        ok = np.isfinite(x)
        lo = np.percentile(np.column_stack([x[ok], y[ok]]), 1, axis=0)
        hi = np.percentile(np.column_stack([x[ok], y[ok]]), 99, axis=0)
        ax.set(
            aspect="equal",
            xlim=(min(lo[0], 0) - 0.5, hi[0] + 0.5),
            ylim=(min(lo[1], 0) - 0.5, max(hi[1], 0) + 0.5),
            title=f"scan {k} (t = {times[k] - times[0]:.0f} s): {st['lines']} lines, "
            f"{st['corners']} corners",
        )
        ax.grid(alpha=0.3)
        ax.tick_params(labelsize=8)
        ax.legend(fontsize=8, loc="best")
    for ax in axes.flat[len(args.scans) :]:
        ax.axis("off")
    fig.suptitle(
        "Freiburg 079 (SICK LMS): front-end lines and corners, robot frame (x forward, m); "
        "lines end at 8 m (the front end's maximum line range)",
        fontsize=11,
    )
    fig.tight_layout()
    fig.savefig(Path(__file__).with_suffix(".png"), dpi=70)

    # summary over the log
    total: dict[str, int] = {}
    picked = range(0, len(ranges), args.every)
    for k in picked:
        _, sf = extract(fe, times[k], ranges[k])
        for key, v in sf.stats.items():
            total[key] = total.get(key, 0) + v
    m = len(picked)
    print(
        f"\nevery {args.every}th scan ({m} scans): per scan {total.get('lines', 0) / m:.1f} lines, "
        f"{total.get('corners', 0) / m:.2f} corners ({total.get('corners_tried', 0) / m:.2f} "
        f"tried), {total.get('segments_rejected_too_few_points', 0) / m:.1f} segments too short"
    )
    print(
        f"  lines rejected: {fmt(rejections(total, 'lines_rejected_'))}; corners rejected: "
        f"{fmt(rejections(total, 'corners_rejected_'))}"
    )


if __name__ == "__main__":
    main()
