"""Victoria Park (ACFR): EKF, iSAM2 and batch with the given and with the project's own data
association (fgslam.slam.pointslam), on ``../shared/data/victoria_park.txt``.

Run: python experiments/real_victoria_park.py [--limit N] [--association jcbb|nn]
Every odometry step is a keyframe; sightings are point features (bearing, range) with the
file's x-y covariance carried through the polar Jacobian. The file has no ground truth: the
table gives each run's RMS position difference from the batch solution with the given
association (the best estimate available), the final pose, run time and the association's
agreement with the given one. Own association is run with the file's odometry covariances,
with them multiplied by 100 (sigma x 10; the old hand factor), with that association smoothed
again under the file's covariances (two passes: ``run_points(..., odometry_scale=100,
resolve_scale=1)``) and with the variances scaled by the self-calibration
(fgslam.slam.point_calibration, fitted on the own association, nothing of the given one; an
option, not the default). The file's covariances are not the model
the self-calibration finds, and the reference depends on them: the given association with the
self-calibrated covariances is in the table too, and each own row gives its RMS to the given
association's batch under the same odometry model (the association's own share of the
difference). The agreement is also given with the file's landmark indices merged where two
were never sighted from one pose and lie within ``SAME_TREE`` m of each other in the
reference: the file gives one tree two indices there, so the own association, which gives
it one, is scored with the pair merged (the measure of the own association's agreement;
``SAME_TREE`` is set by the sightings' sigma, not by the result). Writes
real_victoria_park.png next to this file.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import replace
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from fgslam.io.readers.victoria import read_victoria
from fgslam.slam.pointslam import (
    POINT_MAP_PARAMS,
    association_agreement,
    run_points,
    self_calibrate,
)

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "victoria_park.txt"
SAME_TREE = 1.0  # m: sightings' sigma 0.63 m; two indices never seen together this close
TWO_PASS = "x100 -> x1"


def rms_diff(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((a[:, :2] - b[:, :2]) ** 2, axis=1))))


def near_twins(data, ref) -> dict[int, int]:
    """Pairs of the file's landmark indices never sighted from one pose whose sightings,
    placed with the reference poses ``ref`` (a run's result), average within ``SAME_TREE``
    m of each other: the later index -> the earlier."""
    row = {int(i): k for k, i in enumerate(ref.index)}
    pts: dict[int, list] = {}
    together: set[tuple[int, int]] = set()
    for pose, ss in data.sightings.items():
        if pose not in row:
            continue
        x, y, th = ref.poses[row[pose]]
        c, s = math.cos(th), math.sin(th)
        for sg in ss:
            pts.setdefault(sg.landmark, []).append(
                (x + c * sg.xy[0] - s * sg.xy[1], y + s * sg.xy[0] + c * sg.xy[1])
            )
        ids = sorted({sg.landmark for sg in ss})
        together.update((a, b) for i, a in enumerate(ids) for b in ids[i + 1 :])
    ids = sorted(pts)
    mean = np.array([np.mean(pts[i], axis=0) for i in ids])
    twins: dict[int, int] = {}
    for a in range(len(ids)):
        for b in range(a + 1, len(ids)):
            pair = (ids[a], ids[b])
            if pair not in together and np.hypot(*(mean[a] - mean[b])) < SAME_TREE:
                twins.setdefault(ids[b], twins.get(ids[a], ids[a]))
    return twins


def pct(agree: dict | None, key: str) -> str:
    return "-" if agree is None else f"{100 * agree[key]:.1f} %"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--limit", type=int, help="only the first N odometry steps")
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument(
        "--association", choices=["jcbb", "nn"], default="jcbb", help="own association method"
    )
    args = ap.parse_args()
    data = read_victoria(args.data)
    print(
        f"{args.data.name}: {len(data.steps)} odometry steps, {data.n_sightings} sightings of "
        f"{len(data.landmarks)} landmarks; problems: {data.problems.summary()['skipped']}"
    )
    params = replace(POINT_MAP_PARAMS, association=args.association)
    cal = self_calibrate(data, limit=args.limit, map_params=params)
    print("\nself-calibration of the odometry noise (variance scales x, y, theta; EKF, own):")
    for h in cal.history:
        used = ", ".join(f"{v:.3g}" for v in h["scale_used"])
        fit = ", ".join(f"{v:.3g}" for v in h["scale_fitted"])
        print(f"  with ({used}): {h['landmarks']} landmarks, fitted ({fit})")
    self_label = "self (" + ", ".join(f"{v:.3g}" for v in cal.scale) + ")"
    models = {"x1": 1.0, "x100": 100.0, TWO_PASS: 100.0, self_label: cal.scale}
    runs = []
    for assoc, label in (
        ("given", "x1"),
        ("given", self_label),
        ("own", "x1"),
        ("own", "x100"),
        ("own", TWO_PASS),
        ("own", self_label),
    ):
        for backend in ("ekf", "isam2", "batch"):
            r = run_points(
                data,
                backend,
                assoc,
                params,
                limit=args.limit,
                odometry_scale=models[label],
                resolve_scale=1.0 if label == TWO_PASS else None,
            )
            runs.append((assoc, label, r))
    given_batch = {lab: r for a, lab, r in runs if a == "given" and r.backend == "batch"}
    ref = given_batch["x1"]
    odo = ref.odometry
    print(
        "\n| association | odometry cov | backend | time (s) | p95 step (ms) | landmarks "
        "| RMS diff to batch/given (m) | RMS diff to batch/given, same odometry (m) "
        "| final pose (x, y, deg) | agreement | agreement, file's near twins merged "
        "| unassigned |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    twins = near_twins(data, ref)
    for assoc, label, r in runs:
        agree = association_agreement(r.assigned) if assoc == "own" else None
        merged = (
            association_agreement([(twins.get(g, g), o) for g, o in r.assigned])
            if assoc == "own"
            else None
        )
        same = given_batch.get("x1" if label == TWO_PASS else label)
        x, y, th = r.poses[-1]
        print(
            f"| {assoc} | {label} | {r.backend} | {r.wall_time:.1f} "
            f"| {1000 * np.percentile(r.latencies, 95):.1f} | {len(r.landmarks)} "
            f"| {rms_diff(r.poses, ref.poses):.2f} "
            f"| {'-' if same is None else f'{rms_diff(r.poses, same.poses):.2f}'} "
            f"| ({x:.1f}, {y:.1f}, {math.degrees(th):.0f}) "
            f"| {pct(agree, 'purity')} | {pct(merged, 'purity')} | {pct(agree, 'unassigned')} |"
        )
    print(f"| odometry alone | | | | | | {rms_diff(odo, ref.poses):.2f} | | | | | |")
    print(
        f"\nThe file's near twins (indices never sighted from one pose, within {SAME_TREE} m "
        "in the reference): " + ", ".join(f"{a}~{b}" for a, b in sorted(twins.items()))
    )
    # agreement between backends with the given association
    given = {r.backend: r for a, lab, r in runs if a == "given" and lab == "x1"}
    print("\nRMS position difference between backends (given association, m):")
    for a, b in (("ekf", "isam2"), ("ekf", "batch"), ("isam2", "batch")):
        print(f"  {a} vs {b}: {rms_diff(given[a].poses, given[b].poses):.3f}")
    fig, axes = plt.subplots(1, 4, figsize=(24, 6.5))
    titles = (
        "given association",
        "own association, x100",
        "own association, x100, smoothed again with x1",
        "own association, self-calibrated",
    )
    shown = (("given", "x1"), ("own", "x100"), ("own", TWO_PASS), ("own", self_label))
    for ax, (assoc, scale), title in zip(axes, shown, titles, strict=True):
        ax.plot(odo[:, 0], odo[:, 1], ":", color="tab:orange", lw=0.8, label="odometry")
        for (_, _, r), color in zip(
            [x for x in runs if x[0] == assoc and x[1] == scale],
            ("tab:red", "tab:blue", "tab:green"),
            strict=True,
        ):
            ax.plot(r.poses[:, 0], r.poses[:, 1], "-", color=color, lw=0.8, label=r.backend)
            if r.backend == "batch":
                lm = np.array(list(r.landmarks.values()))
                if len(lm):
                    ax.plot(lm[:, 0], lm[:, 1], "k+", ms=4, label="landmarks (batch)")
        ax.set(aspect="equal", title=title, xlabel="x (m)", ylabel="y (m)")
        ax.set_xlim(-150, 250)
        ax.set_ylim(-100, 300)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="upper left")
    fig.suptitle("Victoria Park: EKF, iSAM2 and batch (fgslam backends), point landmarks")
    fig.tight_layout()
    fig.savefig(Path(__file__).with_suffix(".png"), dpi=80)


if __name__ == "__main__":
    main()
