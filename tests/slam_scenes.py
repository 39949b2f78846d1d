"""A small simulated world and run for SLAM tests: a room with pillars, chairs, a recessed door,
driven around for ~40 s (all events in memory)."""

from __future__ import annotations

import functools

from fgslam.config import load_config
from fgslam.sim.sensors import SimParams
from fgslam.sim.simulate import events, plan_run
from fgslam.sim.world import parse_world

# the paper's scheme: wheel odometry, every scan a keyframe, no loop closures (the tests of
# map management and of the wheel-odometry models that count keyframes per scan)
PAPER = {"odometry": "wheels", "keyframes": "every-scan", "loop_closures": "off"}

ROOM = {
    "name": "room",
    "walls": [
        {"id": "r", "points": [[0, 0], [9, 0], [9, 6], [0, 6]], "closed": True},
        {"id": "p1", "points": [[4, 2.6], [4.6, 2.6], [4.6, 3.4], [4, 3.4]], "closed": True},
    ],
    "doors": [
        {"wall": "r", "segment": 2, "at": 3.0, "width": 0.9, "recess": 0.15, "side": "right"}
    ],
    "tables": [{"x": 7.2, "y": 4.6, "width": 0.45, "depth": 0.45}],
    "route": [[1.5, 1.2], [7.5, 1.2], [7.5, 4.9 - 0.8], [1.5, 4.6], [1.5, 1.2], [6.0, 1.2]],
}


@functools.cache
def room_events(seed: int = 0, duration: float | None = None) -> tuple:
    cfg = load_config()
    w = parse_world(ROOM, "room")
    run = plan_run(w, cfg, seed, SimParams(), duration)
    return tuple(events(w, cfg, run)), cfg, w
