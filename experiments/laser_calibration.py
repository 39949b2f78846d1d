"""The laser's range offset and scale as estimated variables (issue 15, section 1): what the
simulator's runs say about them.

Run: python experiments/laser_calibration.py

Prints three tables:
1. Recovery: the room of the tests (exact wheels, taken as exact) with a known range bias,
   every backend, the paper's worst-case term ("off") against the estimated offset and scale
   ("range"): ATE and the estimates with their sigmas.
2. The front end's line features against the truth: with no range bias at all, lines of a
   robot driving through the room, and along a straight corridor, measured against the true
   walls from the true pose (the bias an estimated offset absorbs), with the line fits'
   end trimming ([frontend] line_end_trim) off and on.
3. Observability on the corridor (150 s, laser only, iSAM2): no simulated error of any kind,
   the calibration parts estimated alone and together (the scale is seen only against the
   wheels' scale: a map scaled whole looks the same).
"""

from __future__ import annotations

import dataclasses
import itertools
import math

import numpy as np

from factors.line import line_residual
from fgslam.config import load_config, with_scanmatch
from fgslam.evaluation import metrics as evaluation
from fgslam.events import TruthPose
from fgslam.frontend.pipeline import FrontEnd
from fgslam.sim.scenes import PAPER, ROOM
from fgslam.sim.sensors import SimParams
from fgslam.sim.simulate import events, plan_run
from fgslam.sim.world import load_world, parse_world
from fgslam.slam.runner import run_backends

EXACT = {"radius_error_right": 0.0, "radius_error_left": 0.0, "wheelbase_error": 0.0}
STRAIGHT = {
    "name": "straight",
    "walls": [
        {"id": "a", "points": [[-5, -1], [40, -1]]},
        {"id": "b", "points": [[-5, 1.2], [40, 1.2]]},
        {"id": "c", "points": [[40, -1], [40, 1.2]]},
    ],
    "route": [[0, 0], [30, 0.1]],
}


def _cfg(laser: str, wheels: str, prior=(0.01, 0.002), trim: float = 0.0):
    cfg = with_scanmatch(load_config(), PAPER)
    cfg = dataclasses.replace(cfg, frontend=dataclasses.replace(cfg.frontend, line_end_trim=trim))
    las = dataclasses.replace(
        cfg.laser, calibration=laser, systematic_offset=prior[0], systematic_per_metre=prior[1]
    )
    odo = dataclasses.replace(cfg.odometry, calibration=wheels)
    return dataclasses.replace(cfg, laser=las, odometry=odo)


def _runs(world, sim: SimParams, cfg, backends, sensors, duration=None):
    evs = list(events(world, cfg, plan_run(world, cfg, 2, sim, duration), sim))
    for res in run_backends(evs, cfg, backends, sensors):
        ref = evaluation.interpolate_poses(res.truth_t, res.truth, res.times)
        yield res, evaluation.ate(res.poses, ref, align=False)["rmse"]


def _cal(res) -> str:
    if res.calibration is None:
        return "-"
    return ", ".join(
        f"{n} {1e3 * e:.2f} +- {1e3 * s:.2f}"
        for n, e, s in zip(
            res.calibration["parameters"],
            res.calibration["estimate"],
            res.calibration["sigma"],
            strict=True,
        )
    )


def recovery() -> None:
    print("\n### 1. Recovery of a known range bias (room, fused, exact wheels taken as exact)\n")
    print("Calibration values in mm (offset) and 1e-3 (scale).\n")
    print(
        "| true offset, scale | prior sigmas | backend | ATE off (cm) | ATE range (cm) | estimate |"
    )
    print("|---|---|---|---|---|---|")
    room = parse_world(ROOM, "room")
    for truth, prior in (((0.008, 0.0015), (0.01, 0.002)), ((0.02, 0.005), (0.03, 0.01))):
        sim = SimParams(
            **EXACT,
            laser_sys_offset=truth[0],
            laser_sys_per_metre=truth[1],
            sound_speed_bias_sigma=0.0,
        )
        cells = {}
        for mode in ("off", "range"):
            for res, ate in _runs(room, sim, _cfg(mode, "off", prior), BACKENDS, "fused"):
                cells.setdefault(res.backend, []).append((res, ate))
        for b, ((_, a_off), (res, a_on)) in cells.items():
            print(
                f"| {1e3 * truth[0]:.0f} mm, {1e3 * truth[1]:.1f}e-3 | {1e3 * prior[0]:.0f} mm, "
                f"{1e3 * prior[1]:.0f}e-3 | {b} | {100 * a_off:.2f} | {100 * a_on:.2f} | "
                f"{_cal(res)} |",
                flush=True,
            )


def line_bias() -> None:
    print("\n### 2. The front end's lines against the true walls (no range bias simulated)\n")
    print(
        "Laser only, no mixed pixels, 5 mm range noise, 1 mm resolution; d error = predicted "
        "from the true pose - measured (negative: measured too far), weighted by the lines' "
        "inverse variance, and by the number of beams.\n"
    )
    print(
        "| world | line_end_trim | lines | weighted mean (mm) | median, 80+ beams (mm) "
        "| median, < 30 beams (mm) |"
    )
    print("|---|---|---|---|---|---|")
    for (name, world), trim in itertools.product(
        (
            ("room (corners, a pillar, a door recess)", parse_world(ROOM, "room")),
            ("straight corridor (two walls)", parse_world(STRAIGHT, "straight")),
        ),
        (0.0, 4.0),
    ):
        cfg = load_config()
        cfg = dataclasses.replace(
            cfg,
            laser=dataclasses.replace(cfg.laser, range_resolution=1e-3),
            frontend=dataclasses.replace(cfg.frontend, line_end_trim=trim),
        )
        sim = SimParams(
            **EXACT,
            laser_sys_offset=0.0,
            laser_sys_per_metre=0.0,
            mixed_pixel_prob=0.0,
            laser_sigma=0.005,
        )
        evs = list(events(world, cfg, plan_run(world, cfg, 0, sim, 150.0), sim))
        truth = [e for e in evs if isinstance(e, TruthPose)]
        tt = np.array([e.t for e in truth])
        tp = np.array([(e.x, e.y, e.theta) for e in truth])
        walls = []
        for x1, y1, x2, y2 in np.array(world.laser_segments).reshape(-1, 4):
            a = math.atan2(x2 - x1, -(y2 - y1))
            d = x1 * math.cos(a) + y1 * math.sin(a)
            walls.append((a + math.pi, -d) if d < 0 else (a, d))
        fe = FrontEnd(cfg, "laser")
        out = [sf for ev in evs for sf in fe.add(ev)] + fe.finish()
        rows = []
        for sf in out:
            pose = evaluation.interpolate_poses(tt, tp, np.array([sf.t]))[0]
            for f in sf.features:
                if f.kind != "line":
                    continue
                errs = [line_residual(pose, np.array(w), f.z)[0] for w in walls]
                e = min(errs, key=lambda v: abs(v[1]) + 3 * abs(v[0]))
                if abs(e[1]) < 0.1 and abs(e[0]) < 0.05:  # the wall it measures
                    rows.append((e[1], f.cov[1, 1], f.laser_support))
        r = np.array(rows)
        w = 1 / r[:, 1]
        long, short = r[r[:, 2] >= 80, 0], r[r[:, 2] < 30, 0]
        print(
            f"| {name} | {trim:g} | {len(r)} | {1e3 * np.sum(w * r[:, 0]) / np.sum(w):+.2f} | "
            f"{1e3 * np.median(long):+.2f} | "
            + (f"{1e3 * np.median(short):+.2f}" if short.size else "-")
            + " |",
            flush=True,
        )


def observability() -> None:
    print("\n### 3. Observability on the corridor (150 s, laser only, no simulated error)\n")
    print(
        "| wheels | laser | line_end_trim | ATE (cm) "
        "| estimate (e_*: 1e-3, offset: mm, scale: 1e-3) |"
    )
    print("|---|---|---|---|---|")
    sim = SimParams(**EXACT, laser_sys_offset=0.0, laser_sys_per_metre=0.0)
    corridor = load_world("corridor")
    for wheels, laser, trim in (
        ("wheels", "off", 0.0),
        ("off", "range", 0.0),
        ("wheels", "offset", 0.0),
        ("wheels", "range", 0.0),
        ("off", "range", 4.0),
        ("wheels", "offset", 4.0),
        ("wheels", "range", 4.0),
    ):
        cfg = _cfg(laser, wheels, trim=trim)
        for res, ate in _runs(corridor, sim, cfg, ["isam2"], "laser", 150.0):
            print(f"| {wheels} | {laser} | {trim:g} | {100 * ate:.2f} | {_cal(res)} |", flush=True)


BACKENDS = ["ekf", "isam2", "batch"]

if __name__ == "__main__":
    recovery()
    line_bias()
    observability()
