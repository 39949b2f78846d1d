"""The simulator: worlds, the robot's run, and its sensors (odometry, SICK PLS, sonar)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from pathlib import Path

from fgslam.config import RobotConfig
from fgslam.io.logwriter import LogWriter
from fgslam.sim.sensors import SimParams
from fgslam.sim.simulate import Run, calibration_truth, events, plan_run, sound_speed_bias
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


def true_calibration(meta: dict) -> dict[str, float] | None:
    """The true calibration errors of a simulated log (by the names of
    :class:`fgslam.slam.calibration.Calibration`) from its header's ``meta``: the seed and the
    simulator's parameters; None for a log that is not simulated, or whose parameters this
    simulator does not know."""
    seed, params = meta.get("seed"), meta.get("sim_params")
    if not isinstance(seed, int) or isinstance(seed, bool) or not isinstance(params, dict):
        return None
    try:
        truth = calibration_truth(seed, SimParams(**params))
    except (TypeError, ValueError, ArithmeticError):  # another simulator's parameters
        return None
    ok = all(isinstance(v, float | int) and math.isfinite(v) for v in truth.values())
    return truth if ok else None
