"""A small simulator of MRCLAM-like logs (the UTIAS multi-robot dataset's format,
:mod:`fgslam.io.readers.mrclam`): robots driving in an arena of point landmarks with
barcodes, their velocity commands, camera range-bearing sightings and ground truth.

The arena is a rectangle centred on the origin (x along its long side; m, rad, the ground
truth's frame). Landmarks are placed at random, at least ``min_separation`` apart and 0.5 m
inside the walls. The driven robots (subjects 1..``robots``) wander on a smooth random path
(an Ornstein-Uhlenbeck turn rate, steered back toward the centre when 1.5 m ahead of them
leaves the arena less a 1 m margin, and away from a landmark or robot less than 0.8 m ahead;
collisions are not modelled otherwise); the others of the dataset's five are parked at
random, and are sighted like landmarks under their robots' barcodes. Every command period
(1/``odometry_rate``, on a millisecond clock) the robot moves by its command plus
:class:`~fgslam.io.readers.mrclam.MrclamNoise`'s white velocity noise (the reader's model:
with the same ``noise`` the reader's covariances are the simulator's). A camera frame every
1/``measurement_rate`` s (jittered) sights each landmark or robot within [``min_range``,
``max_range``] and ``fov`` ahead with probability ``p_detect``, with the noise's range and
bearing sigmas; a frame holds a misread (a barcode not in Barcodes.dat, anywhere in view)
with probability ``p_misread``. Ground truth at ``truth_rate``. Deterministic in ``seed``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from factors.geometry import compose_poses, wrap_angle, wrap_angles
from fgslam.io.readers.mrclam import (
    BARCODES,
    DEFAULT_NOISE,
    LANDMARKS,
    ROBOTS,
    MrclamNoise,
    robot_files,
)
from fgslam.io.readers.source import StrPath

# the barcodes of subjects 1-20 (two-digit, as the dataset's); more landmarks take others
CODES = (5, 14, 41, 32, 23, 72, 27, 54, 70, 36, 18, 25, 9, 81, 16, 90, 61, 45, 7, 63)
WANDER_RATE = 0.3  # rad/s: the random turn rate's standard deviation
WANDER_TIME = 4.0  # s: its correlation time
LOOKAHEAD, MARGIN, AVOID = 1.5, 1.0, 0.8  # m
STEER_TIME = 0.5  # s: the turn command follows its target with this time constant


@dataclass
class MrclamLike:
    """What was written: the directory, the landmarks (subject -> (x, y), m), the parked
    robots (subject -> (x, y, theta)) and each driven robot's number of sightings written
    (of landmarks, robots and misreads)."""

    directory: Path
    landmarks: dict[int, NDArray[np.float64]]
    parked: dict[int, NDArray[np.float64]]
    sightings: dict[int, int] = field(default_factory=dict)


def _exp(twist: NDArray[np.float64], dt: NDArray[np.float64]) -> NDArray[np.float64]:
    """(n, 3) motions in the start frame of moving at body velocities ``twist`` (n, 3: vx,
    vy m/s, w rad/s) for ``dt`` (n,) s (SE(2) exponential)."""
    th = twist[:, 2] * dt
    a = np.sinc(th / (2 * np.pi)) ** 2 * th / 2  # (1 - cos th) / th, safe at 0
    b = np.sinc(th / np.pi)  # sin th / th
    vx, vy = twist[:, 0] * dt, twist[:, 1] * dt
    return np.column_stack([b * vx - a * vy, a * vx + b * vy, th])


def _exp1(vx: float, vy: float, w: float, dt: float) -> tuple[float, float, float]:
    """:func:`_exp` of one twist."""
    th = w * dt
    if abs(th) < 1e-9:
        a, b = th / 2, 1.0
    else:
        a, b = (1 - math.cos(th)) / th, math.sin(th) / th
    return b * vx * dt - a * vy * dt, a * vx * dt + b * vy * dt, th


def _place(
    rng: np.random.Generator, n: int, half: NDArray[np.float64], others: list, sep: float
) -> NDArray[np.float64]:
    """``n`` random points within +-``half`` (m), ``sep`` from each other and ``others``."""
    pts = list(others)
    out = []
    for _ in range(20000):
        if len(out) == n:
            return np.array(out).reshape(-1, 2)
        p = rng.uniform(-half, half)
        if all(math.dist(p, q) >= sep for q in pts):
            pts.append(p)
            out.append(p)
    raise ValueError(f"cannot place {n} points {sep} m apart in a {2 * half} m arena")


@dataclass
class _Run:
    """One driven robot: command times (s from the start), commands (v, w), the true pose
    at each command time and the noisy body velocities held until the next."""

    t: NDArray[np.float64]
    cmd: NDArray[np.float64]
    start: NDArray[np.float64]
    twist: NDArray[np.float64]

    def pose_at(self, t: NDArray[np.float64]) -> NDArray[np.float64]:
        """True poses at times ``t`` (s, within the commands' span; heading unwrapped)."""
        k = np.clip(np.searchsorted(self.t, t, side="right") - 1, 0, len(self.t) - 1)
        return compose_poses(self.start[k], _exp(self.twist[k], t - self.t[k]))


def _drive(
    rng: np.random.Generator,
    t: NDArray[np.float64],
    pose: NDArray[np.float64],
    half: NDArray[np.float64],
    avoid: NDArray[np.float64],
    speed: float,
    max_turn: float,
    noise: MrclamNoise,
) -> _Run:
    """Wander from ``pose`` with commands at the times ``t``; ``avoid``: (k, 2) points to
    steer clear of."""
    n = len(t)
    dts = np.diff(t, append=t[-1])
    z = rng.standard_normal((n, 4))
    cmd, start, twist = np.zeros((n, 2)), np.zeros((n, 3)), np.zeros((n, 3))
    x, y, th = (float(v) for v in pose)
    wander = w = 0.0
    inner = half - MARGIN
    for k in range(n):
        dt = float(dts[k])
        start[k] = x, y, th
        if dt <= 0:  # the last command: its period is not driven
            cmd[k] = cmd[k - 1] if k else (0.0, 0.0)
            continue
        wander += (-wander * dt + WANDER_RATE * math.sqrt(2 * dt * WANDER_TIME) * z[k, 3]) / (
            WANDER_TIME
        )
        c, s = math.cos(th), math.sin(th)
        lx, ly = x + LOOKAHEAD * c, y + LOOKAHEAD * s
        if abs(lx) > inner[0] or abs(ly) > inner[1]:
            target = 2.0 * wrap_angle(math.atan2(-y, -x) - th)
        else:
            target = wander
            ahead = (avoid[:, 0] - x) * c + (avoid[:, 1] - y) * s
            side = -(avoid[:, 0] - x) * s + (avoid[:, 1] - y) * c
            near = (ahead > 0) & (np.hypot(ahead, side) < AVOID) & (np.abs(side) < ahead + 0.3)
            if near.any():
                target = -max_turn if side[near][np.argmin(ahead[near])] > 0 else max_turn
        w += (max(-max_turn, min(max_turn, target)) - w) * min(1.0, dt / STEER_TIME)
        w = round(w, 6)
        v = round(speed * (1.0 - 0.5 * abs(w) / max_turn), 6)
        cmd[k] = v, w
        qa, ql, qh = noise.intensities(v, w)
        # white noise held over the period: the integrated error's variance q dt
        ea, el, eh = (z[k, i] * math.sqrt(q / dt) for i, q in enumerate((qa, ql, qh)))
        twist[k] = v + ea, el, w + eh
        dx, dy, dth = _exp1(v + ea, el, w + eh, dt)
        x, y = x + c * dx - s * dy, y + s * dx + c * dy
        th += dth
    return _Run(t, cmd, start, twist)


def _sightings(
    rng: np.random.Generator,
    tf: NDArray[np.float64],
    pose: NDArray[np.float64],
    targets: list[tuple[int, NDArray[np.float64]]],
    misread_codes: NDArray[np.int64],
    noise: MrclamNoise,
    max_range: float,
    min_range: float,
    fov: float,
    p_detect: float,
    p_misread: float,
) -> NDArray[np.float64]:
    """(n, 4) rows (time, barcode, range, bearing) of frames at ``tf`` taken from the true
    ``pose`` (m, 3) of targets (barcode, (m, 2) positions at the frames), time order."""
    rows = []
    for code, xy in targets:
        dx, dy = xy[:, 0] - pose[:, 0], xy[:, 1] - pose[:, 1]
        r = np.hypot(dx, dy)
        b = wrap_angles(np.arctan2(dy, dx) - pose[:, 2])
        seen = (r >= min_range) & (r <= max_range) & (np.abs(b) <= fov / 2)
        seen &= rng.random(len(tf)) < p_detect
        zr = np.maximum(r + noise.range_sigma * rng.standard_normal(len(tf)), min_range / 2)
        zb = wrap_angles(b + noise.bearing_sigma * rng.standard_normal(len(tf)))
        rows.append(np.column_stack([tf, np.full(len(tf), code), zr, zb])[seen])
    bad = rng.random(len(tf)) < p_misread
    m = int(bad.sum())
    rows.append(
        np.column_stack(
            [
                tf[bad],
                rng.choice(misread_codes, m),
                rng.uniform(min_range, max_range, m),
                rng.uniform(-fov / 2, fov / 2, m),
            ]
        )
    )
    out = np.vstack(rows)
    return out[np.argsort(out[:, 0], kind="stable")]


def write_mrclam_like(
    directory: StrPath,
    seed: int,
    robots: int = 1,
    duration: float = 120.0,
    *,
    noise: MrclamNoise = DEFAULT_NOISE,
    arena: tuple[float, float] = (15.0, 8.0),
    n_landmarks: int = 15,
    min_separation: float = 1.0,
    speed: float = 0.15,
    max_turn: float = 0.5,
    odometry_rate: float = 67.0,
    truth_rate: float = 100.0,
    measurement_rate: float = 4.0,
    max_range: float = 5.0,
    min_range: float = 0.3,
    fov: float = math.radians(60.0),
    p_detect: float = 0.9,
    p_misread: float = 0.02,
    start_time: float = 1248272272.0,
) -> MrclamLike:
    """Write an MRCLAM-format directory (see the module's description): ``robots`` driven
    robots (1-5) for ``duration`` s in an ``arena`` (m) with ``n_landmarks`` landmarks
    (subjects 6...), commands at ``odometry_rate`` Hz at ``speed`` m/s (slower when
    turning, up to ``max_turn`` rad/s), camera frames at ``measurement_rate`` Hz, ground
    truth at ``truth_rate`` Hz, times from ``start_time`` (s, the files' clock). ``noise``:
    the motion and sighting noise (by default the reader's defaults: the reader's
    covariances are then the simulator's)."""
    if robots not in ROBOTS:
        raise ValueError(f"robots = {robots}: the dataset has 1-5")
    if not 0 < n_landmarks <= 99 - len(ROBOTS) - 10:
        raise ValueError(f"n_landmarks = {n_landmarks}: 1 to {99 - len(ROBOTS) - 10}")
    root = Path(directory)
    root.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng([seed, 20110])
    half = np.array(arena, dtype=float) / 2
    codes = list(CODES) + [c for c in range(1, 100) if c not in CODES]
    subjects = list(range(1, len(ROBOTS) + 1 + n_landmarks))
    code_of = dict(zip(subjects, codes, strict=False))
    misread = np.array([c for c in range(1, 100) if c not in code_of.values()])
    lm_xy = _place(rng, n_landmarks, half - 0.5, [], min_separation)
    landmarks = {len(ROBOTS) + 1 + i: lm_xy[i] for i in range(n_landmarks)}
    parked_xy = _place(rng, len(ROBOTS) - robots, half - 0.5, list(lm_xy), min_separation)
    parked = {
        robots + 1 + i: np.array([*parked_xy[i], rng.uniform(-math.pi, math.pi)])
        for i in range(len(parked_xy))
    }
    starts = _place(rng, robots, half - MARGIN - 0.5, list(lm_xy) + list(parked_xy), 0.5)
    t_cmd = np.round(np.arange(int(duration * odometry_rate) + 1) / odometry_rate, 3)
    t_cmd = np.unique(t_cmd)
    avoid_fixed = np.vstack([lm_xy, parked_xy]) if len(parked_xy) else lm_xy
    runs = {}
    for n in range(1, robots + 1):
        pose = np.array([*starts[n - 1], rng.uniform(-math.pi, math.pi)])
        runs[n] = _drive(
            np.random.default_rng([seed, n]), t_cmd, pose, half, avoid_fixed, speed, max_turn, noise
        )

    _write(
        root / BARCODES,
        "Subject #    Barcode #",
        np.array([[s, code_of[s]] for s in subjects]),
        "%d %d",
    )
    _write(
        root / LANDMARKS,
        "Subject #    x [m]    y [m]    x std-dev [m]    y std-dev [m]",
        np.array([[s, *xy, 1e-3, 1e-3] for s, xy in landmarks.items()]),
        "%d %.6f %.6f %.6f %.6f",
    )
    out = MrclamLike(root, landmarks, parked)
    end = t_cmd[-1]
    for n, run in runs.items():
        r = np.random.default_rng([seed, n, 1])
        tt = np.round(np.arange(0.0, end + 1e-9, 1.0 / truth_rate), 3)
        tt = tt[tt <= end]
        truth = run.pose_at(tt)
        period = 1.0 / measurement_rate
        tf = np.arange(period, end - period, period)
        tf = np.unique(np.round(tf + r.uniform(-0.1, 0.1, len(tf)) * period, 3))
        pose = run.pose_at(tf)
        targets = [(code_of[s], np.broadcast_to(xy, (len(tf), 2))) for s, xy in landmarks.items()]
        targets += [(code_of[s], np.broadcast_to(p[:2], (len(tf), 2))) for s, p in parked.items()]
        targets += [(code_of[m], o.pose_at(tf)[:, :2]) for m, o in runs.items() if m != n]
        meas = _sightings(
            r, tf, pose, targets, misread, noise, max_range, min_range, fov, p_detect, p_misread
        )
        out.sightings[n] = len(meas)
        gt_name, odo_name, meas_name = robot_files(n)
        truth[:, 2] = wrap_angles(truth[:, 2])
        _write(
            root / gt_name,
            "Time [s]    x [m]    y [m]    orientation [rad]",
            np.column_stack([start_time + tt, truth]),
            "%.3f %.6f %.6f %.6f",
        )
        _write(
            root / odo_name,
            "Time [s]    forward velocity [m/s]    angular velocity [rad/s]",
            np.column_stack([start_time + run.t, run.cmd]),
            "%.3f %.6f %.6f",
        )
        meas[:, 0] += start_time
        _write(
            root / meas_name,
            "Time [s]    Barcode #    range [m]    bearing [rad]",
            meas,
            "%.3f %d %.6f %.6f",
        )
    return out


def _write(path: Path, header: str, rows: NDArray[np.float64], fmt: str) -> None:
    np.savetxt(path, rows, fmt=fmt, delimiter=" ", header=header, comments="# ")
