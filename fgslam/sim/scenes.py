"""Small simulated scenes with known truth, shared by the tests and the experiments.

- :data:`ROOM` and :func:`room_events`: a room with a pillar, a table and a recessed door,
  driven around for ~40 s (all events in memory).
- :data:`PAPER`: the paper's scheme as a ``[scanmatch]`` section (wheel odometry, every scan a
  keyframe, no loop closures), for :func:`fgslam.config.with_scanmatch`.
- :func:`standing_scene`: a robot standing still in a small world for 13 s, its sonar sweeping
  around one laser scan; :data:`QUIET` the quiet sensors and :data:`EXACT_WHEELS`,
  :data:`NO_LASER_BIAS`, :data:`NO_CLUTTER` the simulator's true errors switched off by group.
- :func:`synthetic_park` and :func:`park_run`: point-landmark data in the Victoria Park format
  (two laps among 12 trees), exact or noisy, optionally with wrong associations.
"""

from __future__ import annotations

import functools
import math

import numpy as np

from factors.geometry import wrap_angle
from fgslam.config import RobotConfig, load_config
from fgslam.events import Event, LaserScan, OdometryEvent, SonarReading
from fgslam.io.readers.victoria import Sighting, Step, VictoriaPark
from fgslam.sim.sensors import SimParams, laser_scan, sonar_echoes
from fgslam.sim.simulate import events, plan_run
from fgslam.sim.world import parse_world

# the paper's scheme: wheel odometry, every scan a keyframe, no loop closures (the tests of
# map management and of the wheel-odometry models that count keyframes per scan)
PAPER = {"odometry": "wheels", "keyframes": "every-scan", "loop_closures": "off"}

# Groups of the simulator's true errors switched off (keywords of SimParams):
# the real wheel radii and wheelbase are the nominal ones
EXACT_WHEELS = {"radius_error_right": 0.0, "radius_error_left": 0.0, "wheelbase_error": 0.0}
# the laser's ranges carry their random error only (no offset, no error growing with range)
NO_LASER_BIAS = {"laser_sys_offset": 0.0, "laser_sys_per_metre": 0.0}
# no mixed pixels, no misclassified sonar echoes, no phantom echoes
NO_CLUTTER = {"mixed_pixel_prob": 0.0, "misclass_prob": 0.0, "phantom_prob": 0.0}
# quiet sensors: 5 mm laser noise, sonar 0.3 deg and 0.2 %, every echo detected, no bias, no
# clutter (the front end's scenes)
QUIET = SimParams(
    laser_sigma=0.005,
    sonar_bearing_sigma_deg=0.3,
    sonar_range_sigma_rel=0.002,
    detect_prob=1.0,
    **NO_LASER_BIAS,
    **NO_CLUTTER,
)


def standing_scene(
    world_dict: dict,
    pose: tuple[float, float, float] = (0.0, 0.0, 0.0),
    seed: int = 0,
    params: SimParams = QUIET,
    cfg: RobotConfig | None = None,
    t_scan: float = 6.5,
    sonar: bool = True,
    sound_bias: float = 0.0,
) -> tuple[list[Event], np.ndarray]:
    """Events of a robot standing at ``pose`` (world x, y m, heading rad) for 13 s in the world
    ``world_dict`` (the world file's keys): odometry without motion, both sonar arrays sweeping
    (ranges read r (1 + sound_bias)) and one laser scan at ``t_scan`` s. Returns (events in time
    order, the scan's ranges in m)."""
    cfg = cfg or load_config()
    world = parse_world({"name": "scene", **world_dict}, "<scene>")
    rng = np.random.default_rng(seed)
    evs: list[Event] = [OdometryEvent(round(0.01 * k, 2), 0, 0) for k in range(1, 1301)]
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
    """The room's run with the default robot: (events, configuration, world)."""
    cfg = load_config()
    w = parse_world(ROOM, "room")
    run = plan_run(w, cfg, seed, SimParams(), duration)
    return tuple(events(w, cfg, run)), cfg, w


def synthetic_park(noise: float = 0.0, seed: int = 0) -> tuple[VictoriaPark, np.ndarray]:
    """A robot driving two laps of an 18 m circle among 12 trees, with exact (or noisy)
    odometry and sightings of the trees within 15 m. Returns the data and the true poses in
    the frame of the first pose (where point SLAM starts)."""
    rng = np.random.default_rng(seed)
    trees = np.array(
        [[22 * math.cos(a), 22 * math.sin(a)] for a in np.linspace(0, 2 * math.pi, 8, False)]
        + [[14 * math.cos(a), 14 * math.sin(a)] for a in np.linspace(0.3, 2 * math.pi, 4, False)]
    )
    n = 160
    poses = np.array(
        [
            [18 * math.cos(a), 18 * math.sin(a), a + math.pi / 2]
            for a in np.linspace(0, 4 * math.pi, n + 1)
        ]
    )
    data = VictoriaPark()
    cov_o = np.diag([0.01, 0.01, 0.001]) ** 2 + np.eye(3) * 1e-6
    idx = 0
    for k in range(n + 1):
        if k:
            a, b = poses[k - 1], poses[k]
            c, s = math.cos(a[2]), math.sin(a[2])
            d = np.array(
                [
                    c * (b[0] - a[0]) + s * (b[1] - a[1]),
                    -s * (b[0] - a[0]) + c * (b[1] - a[1]),
                    wrap_angle(b[2] - a[2]),
                ]
            )
            d = d + noise * rng.standard_normal(3) * [0.01, 0.01, 0.001]
            data.steps.append(Step(idx, idx + 1, d, cov_o))
            idx += 1
        p = poses[k]
        c, s = math.cos(p[2]), math.sin(p[2])
        for j, t in enumerate(trees):
            dx, dy = t - p[:2]
            xy = np.array([c * dx + s * dy, -s * dx + c * dy])
            if np.hypot(*xy) < 15 and xy[0] > 0:
                xy = xy + noise * rng.standard_normal(2) * 0.05
                data.sightings.setdefault(idx, []).append(
                    Sighting(idx, 1000 + j, xy, np.eye(2) * 0.05**2)
                )
    c, s = math.cos(poses[0, 2]), math.sin(poses[0, 2])
    d = poses[:, :2] - poses[0, :2]
    local = np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]])
    return data, np.column_stack([local, poses[:, 2] - poses[0, 2]])


def park_run(seed: int, wrong: float = 0.0) -> tuple[VictoriaPark, np.ndarray, int]:
    """The noisy :func:`synthetic_park` of ``seed`` with a share ``wrong`` of its sightings
    moved to another (random) tree. Returns the data, the true poses and how many sightings
    were moved."""
    data, truth = synthetic_park(noise=1.0, seed=seed)
    rng = np.random.default_rng(seed + 100)
    trees = sorted({s.landmark for v in data.sightings.values() for s in v})
    moved = 0
    for v in data.sightings.values():
        for i, s in enumerate(v):
            if rng.random() < wrong:
                other = int(rng.choice([t for t in trees if t != s.landmark]))
                v[i] = type(s)(s.pose, other, s.xy, s.cov)
                moved += 1
    return data, truth, moved


BOX_ROOM = ((0, 0, 8, 0), (8, 0, 8, 5), (8, 5, 0, 5), (0, 5, 0, 0), (3, 2.5, 3.5, 3.0))


def box_room_scans(seed: int = 0) -> tuple:
    """Two simulated laser scans (the shipped laser's bearings, 1 cm range noise; robot-frame
    points, m) of an 8 x 5 m box room with a pillar (:data:`BOX_ROOM`, segments x0 y0 x1
    y1): the reference's from a random pose, the query's from up to 0.3 m and 0.1 rad away.
    Returns (reference points, query points, the query's true pose in the reference's frame
    (x, y, theta), the random generator) for scan-matcher tests and benchmarks."""
    from fgslam.scanmatch import scan_points
    from fgslam.sim.raycast import raycast

    segs = np.asarray(BOX_ROOM, dtype=float)
    bearings = load_config().laser.bearings
    rng = np.random.default_rng(seed)

    def scan(pose):
        r = raycast(np.asarray(pose[:2]), pose[2] + bearings, segs)
        return scan_points(r + rng.normal(0, 0.01, r.shape), bearings, max_range=20.0)

    a = np.array([rng.uniform(1.5, 2.5), rng.uniform(1.5, 3.5), rng.uniform(-np.pi, np.pi)])
    b = a + np.array([*rng.uniform(-0.3, 0.3, 2), rng.uniform(-0.1, 0.1)])
    c, s = math.cos(a[2]), math.sin(a[2])
    d = b[:2] - a[:2]
    truth = np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1], b[2] - a[2]])
    return scan(a), scan(b), truth, rng
