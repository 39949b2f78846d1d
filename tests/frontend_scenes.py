"""Helpers for front-end tests: a robot standing still in a small world, with simulated laser
and sonar readings around one scan (sensor errors chosen by the caller)."""

from __future__ import annotations

import dataclasses

from fgslam.config import load_config
from fgslam.sim.scenes import QUIET, standing_scene

CFG = load_config()


def scene_events(world_dict, pose=(0.0, 0.0, 0.0), seed=0, params=QUIET, cfg=CFG, **kw):
    """:func:`fgslam.sim.scenes.standing_scene` with the shipped configuration."""
    return standing_scene(world_dict, pose, seed, params, cfg, **kw)


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
