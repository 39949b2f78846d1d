"""The paper's experiment over many seeds: the simulated corridor run with every backend (EKF,
iSAM2, batch) and sensor mode (fused, laser only, sonar only).

Run: python experiments/paper_corridor.py [--seeds 10] [--workers 2] [--sensors fused ...]
[--association jcbb|nn] [--mode paper|scan] [--calibration off|wheels]
[--laser-calibration off|offset|range]
[--corners with-lines|replace-lines|off] [--points-from any-echo|unfused-echoes]
[--sonar-timing scan-frame|own-time] [--sonar-calibration off|sound]
[--time-registration per-feature|per-scan] [--line-end-trim K] [--json NAME]
``--mode paper`` (default) is the paper's scheme: wheel odometry, every scan a keyframe, no
loop closures; ``scan`` the configuration's defaults (scan matching, keyframes by motion,
loop closures; issue 14). ``--calibration wheels`` estimates the wheel calibration errors,
``--laser-calibration`` the laser's range offset (and scale) (issue 15; default: the
configuration's); a second table then compares the estimates with the simulator's true
errors. ``--corners`` chooses whether a corner's points also count
as its two lines' measurements, ``--points-from`` whether an echo fused into a line or corner
may also give a point feature (issue 15, section 3), ``--sonar-timing`` whether iSAM2 and batch
attach sonar points and planes at their readings' own time (issue 15, section 2),
``--sonar-calibration sound`` estimates the speed of sound's relative error (issue 15,
section 1; its truth is the simulator's per-run draw), ``--time-registration`` whether a
scan's time error is on each laser feature or once per scan on the pose, ``--line-end-trim``
whether line fits leave out end beams beyond K robust range sigmas (issue 37).
Prints a table of means over seeds (ATE RMSE, maximum error, final error, NEES, landmarks,
time) and the share of seeds in which the run "kept track" (maximum position error below
0.5 m); writes experiments/paper_corridor.png and the per-seed reports to
experiments/out/paper_corridor.json. The seeds run as a sweep on a local Dask cluster of
``--workers`` (fgslam.sweep; each seed's rows kept under experiments/out/, so that a run
stopped and started again with the same options runs only the seeds still missing).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import tempfile
from functools import partial
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from fgslam.choices import (
    CALIBRATION_CHOICES,
    CORNER_CHOICES,
    LASER_CALIBRATION_CHOICES,
    POINTS_FROM_CHOICES,
    SONAR_CALIBRATION_CHOICES,
    SONAR_TIMING_CHOICES,
    TIME_REGISTRATION_CHOICES,
)
from fgslam.config import load_config, with_options
from fgslam.evaluation import metrics as evaluation
from fgslam.io.logfile import LogReader
from fgslam.sim import simulate_to_log, true_calibration
from fgslam.sim.scenes import PAPER
from fgslam.sim.sensors import SimParams
from fgslam.sim.world import load_world
from fgslam.slam.outputs import report_dict
from fgslam.slam.runner import BACKENDS, SENSORS, run_backends
from fgslam.sweep import sweep_function

HERE = Path(__file__).resolve().parent
KEPT_TRACK = 0.5  # m of maximum position error
MODES = {
    "paper": PAPER,
    "scan": {},  # the configuration's [scanmatch] defaults
}


def one_seed(
    seed: int,
    sensors_list=SENSORS,
    association: str = "jcbb",
    mode: str = "paper",
    calibration: str | None = None,
    laser_calibration: str | None = None,
    corners: str | None = None,
    points_from: str | None = None,
    sonar_timing: str | None = None,
    sonar_calibration: str | None = None,
    time_registration: str | None = None,
    line_end_trim: float | None = None,
    world: str = "corridor",
    sim_params: SimParams | None = None,
) -> list[dict]:
    """Simulate ``world`` (with the simulator's true errors ``sim_params``, default its
    defaults) for ``seed`` and run every backend in each of ``sensors_list``: one report
    row each (report.json's, plus the seed, the options and the error curve)."""
    with tempfile.TemporaryDirectory() as d:
        log = Path(d) / "run.log.gz"
        simulate_to_log(load_world(world), load_config(), log, seed, params=sim_params)
        reader = LogReader(log)
        true_map = reader.meta["true_map"]
        rows = []
        cfg = with_options(
            reader.config,
            {
                "scanmatch": MODES[mode],
                "odometry": {"calibration": calibration},
                "laser": {"calibration": laser_calibration, "time_registration": time_registration},
                "frontend": {
                    "corners": corners,
                    "points_from": points_from,
                    "line_end_trim": line_end_trim,
                },
                "sonar": {"timing": sonar_timing, "calibration": sonar_calibration},
            },
        )
        truth = true_calibration(reader.meta)
        for sensors in sensors_list:
            for res in run_backends(
                LogReader(log), cfg, list(BACKENDS), sensors, association=association
            ):
                rep = report_dict(res, true_map, truth)
                rep["seed"] = seed
                rep["association"] = association
                rep["mode"] = mode
                ref = evaluation.interpolate_poses(res.truth_t, res.truth, res.times)
                err = evaluation.position_errors(res.poses, ref, align=False)
                rep["error_curve"] = [res.times.tolist()[::10], err.tolist()[::10]]
                rows.append(rep)
        return rows


def _seed_rows(opts: dict, settings: dict) -> list[dict]:
    return one_seed(settings["seed"], **opts)


def sweep_seeds(opts: dict, seeds: int, workers: int, name: str) -> list[dict]:
    """Seeds 0 .. seeds - 1 with the options ``opts`` of :func:`one_seed`, as a sweep on a
    local Dask cluster (fgslam.sweep): one cell per seed under experiments/out/<name>-<hash
    of the options>/, so that a run stopped and started again only runs the seeds missing."""
    key = hashlib.sha1(json.dumps(opts, sort_keys=True).encode()).hexdigest()[:8]
    out = HERE / "out" / f"{Path(name).stem}-{key}"

    def progress(p: dict) -> None:
        if "dashboard" not in p:
            print(f"{p['done']} of {p['total']} seeds done, {p['failed']} failed", flush=True)

    fn = partial(_seed_rows, opts)
    per_seed = sweep_function(
        fn, {"seed": list(range(seeds))}, out, workers=workers, name=name, progress=progress
    )
    return [row for rows in per_seed for row in rows]


def _groups(rows: list[dict]):
    """(sensors, backend, their rows) in table order, for the groups that have rows."""
    for sensors in SENSORS:
        for backend in BACKENDS:
            rs = [r for r in rows if r["backend"] == backend and r["sensors"] == sensors]
            if rs:
                yield sensors, backend, rs


def summarise(rows: list[dict]) -> str:
    out = [
        "| backend | sensors | kept track | ATE RMSE (m) | max error (m) | final error (m) | "
        "NEES (3 dof) | NEES in 95 % band | landmarks | line / corner / point | "
        "real-time factor |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for sensors, backend, rs in _groups(rows):
        ate = np.array([r["ate"]["rmse"] for r in rs])
        mx = np.array([r["ate"]["max"] for r in rs])
        fin = np.array([r["final_pose_error"]["position_m"] for r in rs])
        nees = np.array([r.get("nees", {}).get("mean", np.nan) for r in rs])
        band = np.array([r.get("nees", {}).get("within_95", np.nan) for r in rs])
        lm = np.array([r["landmarks_total"] for r in rs])
        kinds = [
            np.mean([r["landmarks"].get(k, 0) for r in rs]) for k in ("line", "corner", "point")
        ]
        rt = np.array([r["realtime_factor"] for r in rs])
        kept = np.mean(mx < KEPT_TRACK)
        out.append(
            f"| {backend} | {sensors} | {kept:.0%} | {ate.mean():.3f} +- {ate.std():.3f} | "
            f"{mx.mean():.3f} (worst {mx.max():.2f}) | {fin.mean():.3f} | "
            f"{np.nanmedian(nees):.1f} | {np.nanmean(band):.0%} | {lm.mean():.0f} | "
            f"{kinds[0]:.0f} / {kinds[1]:.0f} / {kinds[2]:.0f} | {rt.mean():.1f} |"
        )
    cal = [r for r in rows if r.get("calibration")]
    if cal:
        names = cal[0]["calibration"].get("parameters", ["e_r", "e_l", "e_b"])
        out += [
            f"\nCalibration errors ({', '.join(names)}; 1e-3, laser_offset in mm), mean +- std "
            "over seeds of the estimate, its mean sigma, the truth, and the share of seeds with "
            "all of them (and of each) within 3 sigma of the truth (the truth's mean over seeds; "
            "the speed of sound's is drawn per seed):\n",
            f"| backend | sensors | {' | '.join(names)} | sigma | truth | within 3 sigma | each |",
            "|---|---|" + "---|" * len(names) + "---|---|---|---|",
        ]
        for sensors, backend, rs in _groups(cal):
            est = 1e3 * np.array([r["calibration"]["estimate"] for r in rs])
            sig = 1e3 * np.array([r["calibration"]["sigma"] or [np.nan] * len(names) for r in rs])
            tru = 1e3 * np.array([r["calibration"]["truth"] for r in rs])
            each = np.abs(est - tru) < 3 * sig
            inside = np.mean(np.all(each, axis=1))
            cells = [f"{m:.2f} +- {d:.2f}" for m, d in zip(est.mean(0), est.std(0), strict=True)]
            out.append(
                f"| {backend} | {sensors} | {' | '.join(cells)} | "
                f"{', '.join(f'{v:.2f}' for v in np.nanmean(sig, 0))} | "
                f"{', '.join(f'{v:.1f}' for v in tru.mean(0))} | {inside:.0%} | "
                f"{', '.join(f'{v:.0%}' for v in each.mean(0))} |"
            )
    aligned = [r for r in rows if "nees_scale_aligned" in r]
    if aligned:
        out += [
            "\nThe NEES with the map's absolute scale taken out (positions scaled about the "
            "anchored first pose by the least-squares factor k onto the truth's; scale error "
            "k - 1, mean +- std over seeds; NEES and band as above):\n",
            "| backend | sensors | scale error (1e-3) | NEES (3 dof) | NEES in 95 % band |",
            "|---|---|---|---|---|",
        ]
        for sensors, backend, rs in _groups(aligned):
            sc = 1e3 * np.array([r["nees_scale_aligned"]["scale_error"] for r in rs])
            ne = [r["nees_scale_aligned"]["mean"] for r in rs]
            band = [r["nees_scale_aligned"]["within_95"] for r in rs]
            out.append(
                f"| {backend} | {sensors} | {sc.mean():+.2f} +- {sc.std():.2f} | "
                f"{np.median(ne):.1f} | {np.mean(band):.0%} |"
            )
    out += [
        "\nMap error against the true map (cm; mean over seeds of each run's median error of its "
        "landmarks against the nearest true feature of their kind):\n",
        "| backend | sensors | line d | corner | point |",
        "|---|---|---|---|---|",
    ]
    for sensors, backend, rs in _groups(rows):
        cells = []
        for k in ("line_d", "corner", "point"):
            v = [r["map_error"][k]["median"] for r in rs if k in r.get("map_error", {})]
            cells.append(f"{100 * np.mean(v):.1f}" if v else "-")
        out.append(f"| {backend} | {sensors} | {' | '.join(cells)} |")
    per_seed = {r["seed"]: r["ate_odometry"]["rmse"] for r in rows}  # the same in every row
    odo = np.array(list(per_seed.values()))
    out.append(
        f"\nOdometry alone: ATE RMSE {odo.mean():.2f} +- {odo.std():.2f} m over {odo.size} "
        "seeds. NEES: median over seeds of the mean pose NEES; band: mean over seeds of the "
        "share of keyframes inside the two-sided 95 % chi-square interval."
    )
    return "\n".join(out)


def plot(rows: list[dict], path: Path) -> None:
    present = [s for s in SENSORS if any(r["sensors"] == s for r in rows)]  # a panel each
    fig, axs = plt.subplots(1, len(present), figsize=(5 * len(present), 4.5), sharey=True)
    axs = np.atleast_1d(axs)
    colors = {"ekf": "tab:red", "isam2": "tab:blue", "batch": "tab:green"}
    for ax, sensors in zip(axs, present, strict=True):
        for r in rows:
            if r["sensors"] != sensors:
                continue
            t, e = r["error_curve"]
            ax.plot(t, e, "-", lw=0.6, alpha=0.7, color=colors[r["backend"]])
        for b, c in colors.items():
            ax.plot([], [], color=c, label=b)
        ax.set_yscale("log")
        ax.set_ylim(1e-3, 3.0)  # the first pose is anchored at the truth: error 0 at t = 0
        ax.set_title(f"{sensors}: position error over the run, every seed")
        ax.set_xlabel("time (s)")
        ax.axhline(KEPT_TRACK, color="k", lw=0.5, ls="--")
    axs[0].set_ylabel("position error (m)")
    axs[0].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--sensors", nargs="+", default=list(SENSORS), choices=SENSORS)
    ap.add_argument("--association", default="jcbb", choices=["jcbb", "nn"])
    ap.add_argument("--mode", default="paper", choices=list(MODES))
    ap.add_argument(
        "--calibration",
        choices=CALIBRATION_CHOICES,
        help="estimate the wheel calibration (default: the configuration's)",
    )
    ap.add_argument(
        "--laser-calibration",
        choices=LASER_CALIBRATION_CHOICES,
        help="estimate the laser's range offset, or offset and scale (default: the "
        "configuration's)",
    )
    ap.add_argument(
        "--corners",
        choices=CORNER_CHOICES,
        help="a corner and its two lines: both measured (the paper), the corner alone, or the "
        "lines alone (default: the configuration's)",
    )
    ap.add_argument(
        "--points-from",
        choices=POINTS_FROM_CHOICES,
        help="sonar point features also from echoes fused into a line or corner, or not "
        "(default: the configuration's)",
    )
    ap.add_argument(
        "--sonar-timing",
        choices=SONAR_TIMING_CHOICES,
        help="iSAM2 and batch: sonar points and planes at their readings' own time, or moved "
        "into the scan's frame (default: the configuration's)",
    )
    ap.add_argument(
        "--sonar-calibration",
        choices=SONAR_CALIBRATION_CHOICES,
        help="estimate the speed of sound's relative error (default: the configuration's)",
    )
    ap.add_argument(
        "--time-registration",
        choices=TIME_REGISTRATION_CHOICES,
        help="a scan's time error on each laser feature, or once per scan on the pose "
        "(default: the configuration's)",
    )
    ap.add_argument(
        "--line-end-trim",
        type=float,
        help="line fits leave out end beams beyond this many robust range sigmas "
        "(default: the configuration's, 0: off)",
    )
    ap.add_argument("--json", default="paper_corridor.json", help="name in experiments/out")
    ap.add_argument(
        "--replot", action="store_true", help="table and figure from experiments/out only"
    )
    args = ap.parse_args()
    if args.replot:
        rows = json.loads((HERE / "out" / args.json).read_text())
        print(summarise(rows))
        plot(rows, HERE / args.json.replace(".json", ".png"))
        return
    opts = {
        "sensors_list": tuple(args.sensors),
        "association": args.association,
        "mode": args.mode,
        "calibration": args.calibration,
        "laser_calibration": args.laser_calibration,
        "corners": args.corners,
        "points_from": args.points_from,
        "sonar_timing": args.sonar_timing,
        "sonar_calibration": args.sonar_calibration,
        "time_registration": args.time_registration,
        "line_end_trim": args.line_end_trim,
    }
    rows = sweep_seeds(opts, args.seeds, args.workers, args.json)
    (HERE / "out").mkdir(exist_ok=True)
    (HERE / "out" / args.json).write_text(json.dumps(rows))
    print(summarise(rows))
    plot(rows, HERE / args.json.replace(".json", ".png"))


if __name__ == "__main__":
    main()
