"""Helpers for front-end tests: a robot standing still in a small world, with simulated laser
and sonar readings around one scan (sensor errors chosen by the caller)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from sim_helpers import NO_CLUTTER, NO_LASER_BIAS

from fgslam.config import load_config
from fgslam.events import LaserScan, OdometryEvent, SonarReading
from fgslam.sim.sensors import SimParams, laser_scan, sonar_echoes
from fgslam.sim.world import parse_world

CFG = load_config()
QUIET = SimParams(
    laser_sigma=0.005,
    sonar_bearing_sigma_deg=0.3,
    sonar_range_sigma_rel=0.002,
    detect_prob=1.0,
    **NO_LASER_BIAS,
    **NO_CLUTTER,
)


def scene_events(
    world_dict,
    pose=(0.0, 0.0, 0.0),
    seed=0,
    params=QUIET,
    cfg=CFG,
    t_scan=6.5,
    sonar=True,
    sound_bias=0.0,
):
    """Events of a robot standing at ``pose`` for 13 s: odometry (no motion), sonar sweeping
    (its ranges read r (1 + sound_bias)), and one laser scan at t_scan. Returns (events in
    time order, the scan's ranges)."""
    world = parse_world({"name": "scene", **world_dict}, "<scene>")
    rng = np.random.default_rng(seed)
    evs = [OdometryEvent(round(0.01 * k, 2), 0, 0) for k in range(1, 1301)]
    m = cfg.laser.mount
    x, y, th = pose
    c, s = math.cos(th), math.sin(th)
    lp = (x + c * m.x - s * m.y, y + s * m.x + c * m.y, th + math.radians(m.yaw_deg))
    ranges = laser_scan(world, cfg.laser, params, lp, t_scan, rng)
    evs.append(LaserScan(t_scan, ranges))
    if sonar:
        for i, arr in enumerate(cfg.sonar.arrays):
            lo, hi = math.radians(arr.pan_min_deg), math.radians(arr.pan_max_deg)
            for k in range(int(13 * cfg.sonar.cycle_rate)):
                t = 0.005 + 0.013 * i + k / cfg.sonar.cycle_rate
                ph = (t / arr.sweep_period + 0.5 * i) % 1.0
                pan = lo + (hi - lo) * (2 * ph if ph < 0.5 else 2 - 2 * ph)
                a = th + math.radians(arr.mount.yaw_deg) + pan
                sp = (
                    x + c * arr.mount.x - s * arr.mount.y,
                    y + s * arr.mount.x + c * arr.mount.y,
                    a,
                )
                e = sonar_echoes(world, cfg.sonar, params, sp, t, rng, sound_bias)
                evs.append(SonarReading(t, i, pan, e))
    evs.sort(key=lambda e: e.t)
    return evs, ranges


def run_frontend(evs, mode="fused", cfg=CFG, params=None):
    from fgslam.frontend.pipeline import FrontEnd

    fe = FrontEnd(cfg, mode, params)
    out = []
    for ev in evs:
        out.extend(fe.add(ev))
    out.extend(fe.finish())
    return out


def replace(p, **kw):
    return dataclasses.replace(p, **kw)
