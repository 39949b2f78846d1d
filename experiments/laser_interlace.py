"""Does the laser interlace its scans? (issue 34, item 4: the heading error in turns)

Run: python experiments/laser_interlace.py [--logs mit-csail freiburg-079 intel] [--scans N]

A SICK LMS at 0.5 deg builds a scan from two 1 deg sweeps, one mirror turn (13.3 ms at 75 Hz)
apart: while the robot turns at w rad/s the odd beams are rotated by about w x 13 ms from the
even ones. For the N fastest-turning scans of each CARMEN log (turn rate from the log's own
odometry, scan to scan) and as many still ones, the odd beams' points are matched against the
even beams' (fgslam.scanmatch.match, from the identity); the rotation found is regressed on
the turn rate. A slope of about 13 ms with a correlation near 1 is interlacing; 0 is none.
Prints one markdown row per log.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from fgslam.events import LaserScan, scan_bearings
from fgslam.io.formats import open_log
from fgslam.io.readers.carmen import odometry_chain
from fgslam.scanmatch import Reference, match, scan_points

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
FILES = {
    "mit-csail": "mit-csail.clf",
    "freiburg-079": "freiburg-079-corrected.log.gz",
    "intel": "intel-corrected.log.gz",
}


def offsets(path: Path, n: int) -> tuple[int, np.ndarray]:
    """(beams, rows of (turn rate rad/s, odd-vs-even rotation rad)) of one log."""
    reader = open_log(path)
    cfg = reader.config
    scans = [e for e in reader if isinstance(e, LaserScan)]
    chain = odometry_chain(path)
    m = min(len(scans), len(chain.scan_poses))
    w = np.gradient(np.unwrap(np.asarray(chain.scan_poses)[:m, 2]), chain.scan_t[:m])
    order = np.argsort(-np.abs(w))
    still = np.flatnonzero(np.abs(w) < 0.02)[:n]
    rows = []
    for i in [*order[:n], *still]:
        r = np.asarray(scans[i].ranges, dtype=float)
        phi = scan_bearings(scans[i], cfg.laser)
        parity = np.arange(len(r)) % 2
        half = [scan_points(np.where(parity == k, r, np.nan), phi, max_range=20.0) for k in (0, 1)]
        if min(len(h) for h in half) < 50:
            continue
        ref = Reference.build(half[0], cfg.matcher, np.zeros(2))
        res = match(ref, half[1], np.zeros(3), cfg.matcher)
        if res.ok:
            rows.append((w[i], res.pose[2]))
    return cfg.laser.n_beams, np.array(rows)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--logs", nargs="+", default=list(FILES), choices=list(FILES))
    ap.add_argument("--scans", type=int, default=150, help="fastest-turning scans per log")
    args = ap.parse_args()
    print(
        "| log | beams | scans matched | slope (ms) | correlation | |rotation| at |w| > 0.5 "
        "(deg) | |rotation| standing (deg) |"
    )
    print("|---|---|---|---|---|---|---|")
    for name in args.logs:
        beams, rows = offsets(DATA / FILES[name], args.scans)
        w, yaw = rows[:, 0], rows[:, 1]
        slope = float(w @ yaw / (w @ w))  # through the origin
        fast, still = np.abs(w) > 0.5, np.abs(w) < 0.02
        print(
            f"| {name} | {beams} | {len(rows)} | {1e3 * slope:.1f} | "
            f"{np.corrcoef(w, yaw)[0, 1]:.2f} | {np.degrees(np.abs(yaw[fast])).mean():.2f} | "
            f"{np.degrees(np.abs(yaw[still])).mean():.3f} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
