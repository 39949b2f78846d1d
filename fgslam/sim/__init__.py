"""The simulator: worlds, the robot's run, and its sensors (odometry, SICK PLS, sonar)."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path

from fgslam.config import RobotConfig
from fgslam.io.logwriter import LogWriter
from fgslam.sim.sensors import SimParams
from fgslam.sim.simulate import Run, events, plan_run, sound_speed_bias
from fgslam.sim.world import World

SIMULATOR_VERSION = 1


def simulate_to_log(
    world: World,
    cfg: RobotConfig,
    out: str | Path,
    seed: int,
    duration: float | None = None,
    params: SimParams | None = None,
    progress: Callable[[float, float], None] | None = None,
) -> Run:
    """Simulate a run and write it as a native log (``.gz`` compressed); ``progress`` is
    called with (simulated time of each event, run duration). Returns the planned run."""
    params = params or SimParams()
    run = plan_run(world, cfg, seed, params, duration)
    meta = {
        "simulator": SIMULATOR_VERSION,
        "seed": seed,
        "duration": run.duration,
        "distance": round(run.distance, 3),
        "sim_params": dataclasses.asdict(params),
        "sound_speed_bias": sound_speed_bias(seed, params),
        "true_map": world.feature_map(),
    }
    with LogWriter(out, cfg, world.name, meta) as log:
        for ev in events(world, cfg, run, params):
            log.write(ev)
            if progress is not None:
                progress(ev.t, run.duration)
    return run
