"""The simulated run: a joystick-like drive along a world's route, and the sensor events.

:func:`plan_run` drives the route (turns on the spot, straight legs at 0.3-0.5 m/s with
acceleration limits and short pauses, a controller keeping to the leg line) and integrates the
true pose at the encoder rate. :func:`events` then yields odometry, truth, sonar and laser
events in time order, computing each sensor reading lazily. Deterministic for a given seed:
each part of the simulation draws from its own random stream.
"""

from __future__ import annotations

import heapq
import math
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from factors.geometry import wrap_angle_half_open
from fgslam.config import RobotConfig
from fgslam.events import Event, LaserScan, OdometryEvent, SonarReading, TruthPose
from fgslam.sim.sensors import SimParams, laser_scan, sonar_echoes
from fgslam.sim.world import World

LIN_ACCEL = 0.4  # m/s^2
ANG_ACCEL = 2.0  # rad/s^2


@dataclass
class Run:
    """A planned run: true poses (after each encoder sample) and measured ticks."""

    t: NDArray[np.float64]  # (N,) sample times, s
    poses: NDArray[np.float64]  # (N, 3) true world pose after each sample
    ticks: NDArray[np.int64]  # (N, 2) right, left encoder increments
    seed: int

    @property
    def duration(self) -> float:
        return float(self.t[-1]) if len(self.t) else 0.0

    @property
    def distance(self) -> float:
        return float(np.hypot(*np.diff(self.poses[:, :2], axis=0).T).sum())

    def pose_at(self, t: float) -> NDArray[np.float64]:
        """True pose at time t (s): between the two encoder samples around it, linearly (the
        heading along the shorter turn); the first or last pose outside them. (The nearest
        sample's pose would put a scan up to half a sample period off its time: 3 mrad at
        0.6 rad/s, beyond a corner's modelled bearing error.)"""
        n = len(self.t)
        if n == 1:
            return self.poses[0].copy()
        u = min(max(t / (self.t[1] - self.t[0]) - 1.0, 0.0), n - 1.0)
        k = min(int(u), n - 2)
        f = u - k
        a, b = self.poses[k], self.poses[k + 1]
        th = a[2] + f * wrap_angle_half_open(b[2] - a[2])
        return np.array(
            [a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1]), wrap_angle_half_open(th)]
        )


FIRST_SCAN = 0.05  # s: the first simulated laser scan's true time


def laser_scan_time(cfg: RobotConfig, k: int | NDArray[np.int64]) -> float | NDArray[np.float64]:
    """The true time (s) of the k-th simulated laser scan: one every scan period."""
    return FIRST_SCAN + k * cfg.laser.scan_period


def true_scan_time(cfg: RobotConfig, t: float) -> float:
    """The true time (s) of the simulated scan that the front end stamps ``t`` (its host
    stamp less the mean delay: within half the delay spread of it, less than half a scan
    period)."""
    k = max(0, round((t - FIRST_SCAN) / cfg.laser.scan_period))
    return float(laser_scan_time(cfg, k))


def _streams(seed: int) -> list[np.random.Generator]:
    return [np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(4)]


def _sound_bias(rng_sonar: np.random.Generator, params: SimParams) -> float:
    """The run's relative speed-of-sound error: the sonar stream's first draw."""
    return float(rng_sonar.normal(0.0, params.sound_speed_bias_sigma))


def sound_speed_bias(seed: int, params: SimParams | None = None) -> float:
    """The relative speed-of-sound error of the run of ``seed`` (every echo's range reads
    r (1 + bias) before its random error), as :func:`events` draws it."""
    return _sound_bias(_streams(seed)[3], params or SimParams())


def calibration_truth(seed: int, params: SimParams | None = None) -> dict[str, float]:
    """The run's true calibration errors by the names of
    :class:`fgslam.slam.calibration.Calibration` (relative; the laser offset in m)."""
    params = params or SimParams()
    return {
        "e_r": params.radius_error_right,
        "e_l": params.radius_error_left,
        "e_b": params.wheelbase_error,
        "laser_offset": params.laser_sys_offset,
        "laser_scale": params.laser_sys_per_metre,
        "sound": sound_speed_bias(seed, params),
    }


def plan_run(
    world: World,
    cfg: RobotConfig,
    seed: int,
    params: SimParams | None = None,
    duration: float | None = None,
) -> Run:
    """Drive the world's route; returns true poses and encoder ticks at the sample rate."""
    if world.route is None or len(world.route) < 2:
        raise ValueError(f"world '{world.name}' has no route to drive")
    params = params or SimParams()
    rng_drive, rng_odo, _, _ = _streams(seed)
    odo = cfg.odometry
    dt = odo.sample_period
    D_true = odo.wheelbase * (1 + params.wheelbase_error)
    route = world.route
    x, y = route[0]
    th = world.start_heading
    v = w = 0.0
    leg, phase, pause_left = 0, "turn", 0.0
    v_max, w_max = rng_drive.uniform(0.3, 0.5), rng_drive.uniform(0.5, 0.8)
    lr_list: list[float] = []
    ll_list: list[float] = []
    poses: list[tuple[float, float, float]] = []
    limit = math.inf if duration is None else duration
    kd = odo.k_d
    while len(poses) * dt < limit:
        a, b = route[leg], route[leg + 1]
        if phase == "pause":
            v_cmd = w_cmd = 0.0
            pause_left -= dt
            if pause_left <= 0 and abs(v) < 1e-6 and abs(w) < 1e-6:
                leg += 1
                if leg >= len(route) - 1:
                    break
                phase = "turn"
                v_max, w_max = rng_drive.uniform(0.3, 0.5), rng_drive.uniform(0.5, 0.8)
        elif phase == "turn":
            err = wrap_angle_half_open(math.atan2(b[1] - y, b[0] - x) - th)
            v_cmd, w_cmd = 0.0, max(-w_max, min(w_max, 2.5 * err))
            if abs(err) < 0.01 and abs(w) < 0.05:
                phase = "drive"
        else:
            ux, uy = (b - a) / np.hypot(*(b - a))
            rem = (b[0] - x) * ux + (b[1] - y) * uy
            lat = ux * (y - a[1]) - uy * (x - a[0])
            desired = math.atan2(uy, ux) - math.atan(lat / 0.6)
            v_cmd = min(v_max, math.sqrt(2 * LIN_ACCEL * max(rem, 0.0)))
            w_cmd = max(-0.6, min(0.6, 2.0 * wrap_angle_half_open(desired - th)))
            if rem < 0.02:
                phase, pause_left = "pause", rng_drive.uniform(0.0, 1.5)
        v += max(-LIN_ACCEL * dt, min(LIN_ACCEL * dt, v_cmd - v))
        w += max(-ANG_ACCEL * dt, min(ANG_ACCEL * dt, w_cmd - w))
        lr, ll = (v + w * D_true / 2) * dt, (v - w * D_true / 2) * dt
        # effective wheelbase noise (eq 5), drawn so that the turn rate stays unbiased
        dth = (lr - ll) / D_true * (1 + kd * rng_odo.standard_normal())
        ds = 0.5 * (lr + ll)
        x += ds * math.cos(th + dth / 2)
        y += ds * math.sin(th + dth / 2)
        th = wrap_angle_half_open(th + dth)
        lr_list.append(lr)
        ll_list.append(ll)
        poses.append((x, y, th))
    lr_t, ll_t = np.array(lr_list), np.array(ll_list)
    # encoders: each wheel's rotation is its ground distance with random slip (eq 5 model),
    # counted in ticks of the real (not nominal) wheel radius
    slip_r = 1 + odo.k_r * rng_odo.standard_normal(lr_t.size)
    slip_l = 1 + odo.k_l * rng_odo.standard_normal(ll_t.size)
    mpt_r = odo.metres_per_tick_right * (1 + params.radius_error_right)
    mpt_l = odo.metres_per_tick_left * (1 + params.radius_error_left)
    cum_r = np.floor(np.cumsum(lr_t * slip_r) / mpt_r).astype(np.int64)
    cum_l = np.floor(np.cumsum(ll_t * slip_l) / mpt_l).astype(np.int64)
    ticks = np.column_stack([np.diff(cum_r, prepend=0), np.diff(cum_l, prepend=0)])
    t = dt * np.arange(1, len(poses) + 1)
    return Run(t=t, poses=np.array(poses).reshape(-1, 3), ticks=ticks, seed=seed)


def _compose(pose: NDArray[np.float64], mount: tuple[float, float, float]) -> tuple[float, ...]:
    x, y, th = pose
    mx, my, mth = mount
    c, s = math.cos(th), math.sin(th)
    return (x + c * mx - s * my, y + s * mx + c * my, th + mth)


def events(
    world: World, cfg: RobotConfig, run: Run, params: SimParams | None = None
) -> Iterator[Event]:
    """All sensor events of a planned run in time order (ties: odometry, truth, sonar, laser)."""
    params = params or SimParams()
    _, _, rng_laser, rng_sonar = _streams(run.seed)
    sound_bias = _sound_bias(rng_sonar, params)
    end = run.duration

    def odometry() -> Iterator[tuple[float, int, int, Event]]:
        for k in range(len(run.t)):
            t = float(run.t[k])
            yield t, 0, k, OdometryEvent(t, int(run.ticks[k, 0]), int(run.ticks[k, 1]))
            x, y, th = run.poses[k]
            yield t, 1, k, TruthPose(t, float(x), float(y), float(th))

    def sonar(i: int) -> Iterator[tuple[float, int, int, Event]]:
        arr = cfg.sonar.arrays[i]
        mount = arr.mount.pose
        base = (mount.x(), mount.y(), mount.theta())
        lo, hi = math.radians(arr.pan_min_deg), math.radians(arr.pan_max_deg)
        period = 1.0 / cfg.sonar.cycle_rate
        t = 0.013 * (i + 1)
        k = 0
        while t <= end:
            phase = (t / arr.sweep_period + 0.5 * i) % 1.0
            pan = lo + (hi - lo) * (2 * phase if phase < 0.5 else 2 - 2 * phase)
            pose = _compose(run.pose_at(t), (base[0], base[1], base[2] + pan))
            echoes = sonar_echoes(world, cfg.sonar, params, pose, t, rng_sonar, sound_bias)
            yield t, 2, k, SonarReading(t, i, pan, echoes)
            k += 1
            t = 0.013 * (i + 1) + k * period

    def laser() -> Iterator[tuple[float, int, int, Event]]:
        m = cfg.laser.mount
        mount = (m.x, m.y, math.radians(m.yaw_deg))
        k = 0
        t_scan = laser_scan_time(cfg, k)
        pending: list[tuple[float, int, Event]] = []
        while True:
            if t_scan <= end:
                delay = rng_laser.uniform(cfg.laser.delay_min, cfg.laser.delay_max)
                pose = _compose(run.pose_at(t_scan), mount)
                ranges = laser_scan(world, cfg.laser, params, pose, t_scan, rng_laser)
                t_host = t_scan + delay
                if t_host <= end:
                    pending.append((t_host, k, LaserScan(t_host, ranges)))
                k += 1
                t_scan = laser_scan_time(cfg, k)
            if not pending:
                return
            pending.sort(key=lambda p: p[0])
            # a delayed scan can only be overtaken by one started within the delay spread
            if t_scan <= end and pending[0][0] > t_scan + cfg.laser.delay_min:
                continue
            t_host, kk, ev = pending.pop(0)
            yield t_host, 3, kk, ev

    sources = [odometry(), laser()] + [sonar(i) for i in range(len(cfg.sonar.arrays))]
    for _, _, _, ev in heapq.merge(*sources, key=lambda e: (e[0], e[1], e[2])):
        yield ev
