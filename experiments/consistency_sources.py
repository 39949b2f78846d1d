"""Which simulated error keeps the pose NEES above its 3 dof (issue 15, section 4).

The simulated corridor's first ``--duration`` s, fused, the paper's scheme (wheels, every scan
a keyframe), the default calibration (wheels and laser offset estimated), run with the
simulator's systematic errors removed one group at a time: the laser's range scale, its
offset, its mixed pixels, the wheels' errors. Prints per case and backend the trajectory
error, the mean pose NEES and its share of keyframes inside the 95 % band, the mean squared
normalised error per component (x, y, heading; 1 when consistent) and the share of runs with
every calibration estimate within 3 sigma of the truth.

Run: python experiments/consistency_sources.py [--seeds 3] [--duration 200] [--workers 1]
[--sensors fused|laser] [--backends ekf isam2] [--laser-calibration off|offset|range]
[--sonar-calibration off|sound] [--corners with-lines|replace-lines|off] [--cases NAME ...]
[--json consistency_sources.json]
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
from functools import partial
from pathlib import Path

import numpy as np

from factors.geometry import wrap_angles
from fgslam.choices import CORNER_CHOICES, LASER_CALIBRATION_CHOICES, SONAR_CALIBRATION_CHOICES
from fgslam.config import load_config, with_options, with_scanmatch
from fgslam.evaluation import metrics as evaluation
from fgslam.sim.scenes import PAPER
from fgslam.sim.sensors import SimParams
from fgslam.sim.simulate import calibration_truth, events, plan_run
from fgslam.sim.world import load_world
from fgslam.slam.runner import run_backends
from fgslam.sweep import sweep_function

HERE = Path(__file__).resolve().parent
NO_SCALE = {"laser_sys_per_metre": 0.0}
NO_LASER = {**NO_SCALE, "laser_sys_offset": 0.0, "mixed_pixel_prob": 0.0}
NO_WHEELS = {"radius_error_right": 0.0, "radius_error_left": 0.0, "wheelbase_error": 0.0}
# name: (what the simulator leaves out, its overrides)
CASES = {
    "all": ("as simulated", {}),
    "no-mixed": ("no mixed pixels", {"mixed_pixel_prob": 0.0}),
    "no-scale": ("no laser range scale", NO_SCALE),
    "no-laser": ("no laser systematic error (scale, offset, mixed pixels)", NO_LASER),
    "no-laser-wheels": ("no laser systematic error, exact wheels", {**NO_LASER, **NO_WHEELS}),
}


def one(
    case: str,
    seed: int,
    duration: float,
    sensors: str,
    backends: tuple[str, ...],
    options: dict | None = None,
) -> list:
    """One simulated run of ``case`` and every backend on it (the configuration with
    ``options``, by section): a row each."""
    sim = dataclasses.replace(SimParams(), **CASES[case][1])
    cfg = load_config()
    world = load_world("corridor")
    evs = list(events(world, cfg, plan_run(world, cfg, seed, sim, duration), sim))
    truth = calibration_truth(seed, sim)
    rows = []
    cfg = with_options(with_scanmatch(cfg, PAPER), options)
    for res in run_backends(evs, cfg, list(backends), sensors):
        ref = evaluation.interpolate_poses(res.truth_t, res.truth, res.times)
        covs = np.array(res.covs)
        e = res.poses - ref
        e[:, 2] = wrap_angles(e[:, 2])
        z2 = e**2 / np.einsum("nii->ni", covs)
        scaled, k = evaluation.scale_about_start(res.poses, ref)
        cal = res.calibration
        est, sig = np.array(cal["estimate"]), np.array(cal["sigma"])
        tru = np.array([truth[n] for n in cal["parameters"]])
        rows.append(
            {
                "case": case,
                "seed": seed,
                "backend": res.backend,
                "ate": evaluation.ate(res.poses, ref, align=False)["rmse"],
                "nees": evaluation.nees(res.poses, covs, ref),
                "nees_scaled": evaluation.nees(scaled, covs, ref),
                "scale": k - 1.0,
                "z2": z2.mean(axis=0).tolist(),
                "calibration": dict(zip(cal["parameters"], est.tolist(), strict=True)),
                "within_3_sigma": bool(np.all(np.abs(est - tru) < 3 * sig)),
            }
        )
    return rows


def summarise(rows: list[dict]) -> str:
    out = [
        "| simulated errors | backend | ATE (mm) | NEES (3 dof) | NEES in 95 % band | "
        "z^2 x, y, heading | calibration within 3 sigma | scale error (1e-3) | "
        "NEES, scale aligned | in band, scale aligned |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for case in CASES:
        for backend in dict.fromkeys(r["backend"] for r in rows):
            rs = [r for r in rows if r["case"] == case and r["backend"] == backend]
            if not rs:
                continue
            ate = 1e3 * np.mean([r["ate"] for r in rs])
            nees = np.median([r["nees"]["mean"] for r in rs])
            band = np.mean([r["nees"]["within_95"] for r in rs])
            z2 = np.mean([r["z2"] for r in rs], axis=0)
            inside = np.mean([r["within_3_sigma"] for r in rs])
            scale = 1e3 * np.mean([r["scale"] for r in rs])
            nees_s = np.median([r["nees_scaled"]["mean"] for r in rs])
            band_s = np.mean([r["nees_scaled"]["within_95"] for r in rs])
            out.append(
                f"| {CASES[case][0]} | {backend} | {ate:.1f} | {nees:.1f} | {band:.0%} | "
                f"{', '.join(f'{v:.1f}' for v in z2)} | {inside:.0%} | {scale:+.2f} | "
                f"{nees_s:.1f} | {band_s:.0%} |"
            )
    seeds = sorted({r["seed"] for r in rows})
    out.append(
        f"\nSeeds {seeds}; ATE without alignment, mean over seeds; NEES: median over seeds of "
        "the mean pose NEES; band, z^2 and calibration: means over seeds. Scale error: the "
        "least-squares factor k - 1 that takes the estimated positions (about the anchored "
        "first pose) onto the truth's, mean over seeds; the NEES is then of the trajectory "
        "scaled by k."
    )
    return "\n".join(out)


def _cell_rows(opts: dict, settings: dict) -> list[dict]:
    o = opts
    return one(
        settings["case"],
        settings["seed"],
        o["duration"],
        o["sensors"],
        o["backends"],
        o["options"],
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--duration", type=float, default=200.0, help="s of the corridor run")
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--sensors", default="fused", choices=["fused", "laser"])
    ap.add_argument("--backends", nargs="+", default=["ekf", "isam2"])
    ap.add_argument(
        "--laser-calibration",
        choices=LASER_CALIBRATION_CHOICES,
        help="the laser's range errors estimated (default: the configuration's, offset)",
    )
    ap.add_argument(
        "--sonar-calibration",
        choices=SONAR_CALIBRATION_CHOICES,
        help="the speed of sound estimated (default: the configuration's, off)",
    )
    ap.add_argument(
        "--corners",
        choices=CORNER_CHOICES,
        help="a corner's two lines kept too, dropped, or no corners (default: the "
        "configuration's, with-lines)",
    )
    ap.add_argument(
        "--cases", nargs="+", choices=list(CASES), default=list(CASES), help="(default: all)"
    )
    ap.add_argument("--json", default="consistency_sources.json", help="name in experiments/out")
    args = ap.parse_args()
    options = {
        "laser": {"calibration": args.laser_calibration},
        "sonar": {"calibration": args.sonar_calibration},
        "frontend": {"corners": args.corners},
    }
    opts = {
        "duration": args.duration,
        "sensors": args.sensors,
        "backends": tuple(args.backends),
        "options": options,
    }
    key = hashlib.sha1(json.dumps(opts, sort_keys=True).encode()).hexdigest()[:8]

    def progress(p: dict) -> None:
        if "dashboard" not in p:
            print(f"{p['done']}/{p['total']} runs done", flush=True)

    per_cell = sweep_function(
        partial(_cell_rows, opts),
        {"case": list(args.cases), "seed": list(range(args.seeds))},
        HERE / "out" / f"{Path(args.json).stem}-{key}",
        workers=args.workers,
        name=args.json,
        extra=("case",),
        progress=progress,
    )
    rows: list[dict] = [r for rs in per_cell for r in rs]
    (HERE / "out").mkdir(exist_ok=True)
    (HERE / "out" / args.json).write_text(json.dumps(rows))
    print(summarise(rows))


if __name__ == "__main__":
    main()
