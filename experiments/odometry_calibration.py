"""Odometry NEES of the shared logs before and after `fgslam calibrate` (issue 13, section 2).

Run: python experiments/odometry_calibration.py [--max-span 10]

For intel, freiburg-079 and mit-csail: the relative motions of the benchmark relations of
at most --max-span s; the odometry's error against them and its covariance under the log's
derived configuration (the virtual drive's eq 5 model: "before") and under the motion error
model fitted by maximum likelihood (fgslam.evaluation.calibrate). The model is fitted on the
motions of
the first half of the log (by time) and its NEES reported on both halves: on the fitted half
the mean NEES of a maximum-likelihood fit is 3 by construction, the held-out half is the
test. NEES: e^T P^-1 e, 3 dof (3 on average, 95 % within [0.22, 9.35] if consistent).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from scipy.stats import chi2

from factors.geometry import between_poses as _between
from factors.geometry import wrap_angles
from factors.odometry import COVARIANCE_FLOOR
from fgslam.evaluation.calibrate import (
    _nees,
    _samples_and_reference,
    fit_alphas,
    motion_covariances,
    relative_motions,
)
from fgslam.evaluation.dense import _at, odometry_path

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
LOGS = {
    "intel": ("intel-corrected.log.gz", "intel-corrected.relations"),
    "freiburg-079": ("freiburg-079-corrected.log.gz", "freiburg-079-corrected.relations"),
    "mit-csail": ("mit-csail.clf", "mit-csail.relations"),
}


def stats(n: np.ndarray) -> str:
    lo, hi = chi2.ppf([0.025, 0.975], 3)
    inside = np.mean((n >= lo) & (n <= hi))
    return f"{n.mean():9.3g} | {np.median(n):6.3g} | {100 * inside:4.0f} %"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--max-span", type=float, default=10.0)
    args = ap.parse_args()
    print(
        "| log | motions fit/test | model | NEES mean | median | in 95 % | alpha1..5 |\n"
        "|---|---|---|---|---|---|---|"
    )
    for name, (log, rel) in LOGS.items():
        cfg, samples = _samples_and_reference(str(DATA / log), str(DATA / rel), {})
        pairs = relative_motions(DATA / rel)
        span = pairs[:, 1] - pairs[:, 0]
        keep = (span > 0) & (span <= args.max_span)
        keep &= (pairs[:, 0] >= samples[0, 0]) & (pairs[:, 1] <= samples[-1, 0])
        pairs = pairs[keep]
        ok, P0, C = motion_covariances(samples, pairs, cfg.odometry.params())
        pairs, P0, C = pairs[ok], P0[ok], C[ok]
        ot, op = odometry_path(samples, cfg.odometry.wheelbase)
        e = pairs[:, 2:5] - _between(_at(ot, op, pairs[:, 0]), _at(ot, op, pairs[:, 1]))
        e[:, 2] = wrap_angles(e[:, 2])
        first = pairs[:, 0] < np.median(pairs[:, 0])
        a = fit_alphas(e[first], C[first])
        eye = np.eye(3) * COVARIANCE_FLOOR
        after = _nees(e, eye + np.einsum("i,kirc->krc", a, C))
        before = _nees(e, P0 + eye)
        n1, n2 = int(first.sum()), int((~first).sum())
        alphas = ", ".join(f"{v:.3g}" for v in a)
        print(f"| {name} | {n1}/{n2} | before (eq 5, virtual drive), all | {stats(before)} | |")
        print(f"| {name} | | fitted, fit half | {stats(after[first])} | {alphas} |")
        print(f"| {name} | | fitted, held-out half | {stats(after[~first])} | |")


if __name__ == "__main__":
    main()
