"""The UTIAS Multi-Robot Cooperative Localization and Mapping dataset (MRCLAM, Leung et al.
2011) as a point-landmark log: one robot's run as a :class:`~fgslam.io.readers.victoria.
VictoriaPark` record (odometry steps and sightings per pose), for
:mod:`fgslam.slam.pointslam`, with the ground truth beside it.

A dataset is a directory of whitespace-separated text files (``#`` starts a comment line)::

    Barcodes.dat               subject# barcode#          (subjects 1-5 robots, 6-20 landmarks)
    Landmark_Groundtruth.dat   subject# x y x_std y_std   (m)
    Robot{n}_Groundtruth.dat   time x y orientation       (s, m, rad)
    Robot{n}_Odometry.dat      time v w                   (s, commanded m/s and rad/s, ~67 Hz)
    Robot{n}_Measurement.dat   time barcode# range bearing (s, m, rad in the robot frame)

The files share one clock. What :func:`read_mrclam` makes of them:

- Poses: pose 0 at the first odometry command; then one pose per time stamp of the
  measurement file that holds a sighting of a landmark (the sightings of one time stamp are
  that pose's). Poses are numbered in time order; ``Mrclam.pose_times`` gives their times.
- Steps: the commands integrated between consecutive pose times as a unicycle, each command
  held until the next one (exact arcs, split at the pose times); the last command's end is
  unknown, so the log ends at the last command. ``delta`` is the end pose in the start
  pose's frame (m, rad). Its covariance, in the end pose's tangent (x, y, theta), is that of
  :class:`MrclamNoise`'s white velocity noise, carried to the step's end by the adjoints of
  the motion after each piece (first order).
- Sightings: only of landmarks (a barcode of Barcodes.dat whose subject is not a robot);
  ``landmark`` is the subject number (the dataset's truth, the "given" association), ``xy``
  = (r cos b, r sin b) in the robot frame (m), its covariance that of independent range and
  bearing errors (:class:`MrclamNoise`) through the polar Jacobian. Sightings of robots
  (counted in ``problems.ignored``), of barcodes not in Barcodes.dat (misreads) and outside
  the commands' time span are counted in ``problems`` and ``Mrclam.dropped`` and dropped
  (those after ``duration``: in ``Mrclam.dropped`` only).

Bad lines (wrong number of fields, a field that is not a number, not finite or beyond
:data:`MAX_VALUE`, a subject or barcode that is not a non-negative integer, a range not
positive, a negative standard deviation, a subject or barcode given twice, a time before the
line above's) raise a one-line :class:`~fgslam.errors.ReaderError` naming the file and line;
with ``tolerant`` they are skipped and counted in ``problems`` (a time going backwards also
in ``problems.backwards`` by file). A missing file is an error; with ``tolerant`` the ground
truth files may be missing (no truth then). Reading one robot's files of the real dataset
(~100 000 odometry lines) takes about a second: the parsing, the integration and the
covariances are vectorised.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TypeVar

import numpy as np
from numpy.typing import NDArray

from factors.geometry import wrap_angles
from fgslam.errors import ReaderError
from fgslam.io.readers.common import open_lines
from fgslam.io.readers.source import Problems, StrPath
from fgslam.io.readers.victoria import Sighting, Step, VictoriaPark

ROBOTS = (1, 2, 3, 4, 5)  # the subjects that are robots; the others of Barcodes.dat landmarks
MAX_VALUE = 1e12  # no time (s since 1970), position, speed or angle of the dataset is larger
MIN_RANGE = 1e-6  # m: a sighting at the camera has no bearing
Num = TypeVar("Num", float, NDArray[np.float64])

BARCODES = "Barcodes.dat"
LANDMARKS = "Landmark_Groundtruth.dat"


def robot_files(robot: int) -> tuple[str, str, str]:
    """The ground truth, odometry and measurement files' names of robot ``robot``."""
    return tuple(f"Robot{robot}_{k}.dat" for k in ("Groundtruth", "Odometry", "Measurement"))


@dataclass(frozen=True)
class MrclamNoise:
    """The noise model of the reader's covariances and of the simulator
    (:func:`fgslam.sim.landmarks.write_mrclam_like` draws its noise from the same model, so
    that its defaults and the reader's are one).

    Motion: the robot's velocities are the commanded ones plus white noise, along track,
    lateral and in heading, independent, each of intensity (variance per second of the
    integrated error) ``*_per_s**2 + *_per_m**2 * |v| (+ heading_per_rad**2 * |w|)``: the
    variance of the error grows with time at rest, with the distance driven and the angle
    turned. The values are typical of dead reckoning from the commands of a small
    differential drive (an iRobot Create at 0.1-0.2 m/s; the dataset's odometry is the
    commands, not its wheel encoders): 5 % of the distance along track, 1 % lateral, 1.7
    deg per metre driven and 10 % of the angle turned, as a random walk (sigma after 1 m,
    1 rad); a few mm (mrad) per root-second at rest. They are not fitted to any file.

    Sightings: range sigma ``range_sigma`` (m) and bearing sigma ``bearing_sigma`` (rad),
    independent: a few cm and 2 deg, the camera's barcode reading at a few metres."""

    along_per_m: float = 0.05  # m per root-metre driven
    lateral_per_m: float = 0.01  # m per root-metre driven
    heading_per_m: float = 0.03  # rad per root-metre driven
    heading_per_rad: float = 0.1  # rad per root-radian turned
    along_per_s: float = 0.003  # m per root-second
    lateral_per_s: float = 0.003  # m per root-second
    heading_per_s: float = 0.003  # rad per root-second
    range_sigma: float = 0.05  # m
    bearing_sigma: float = math.radians(2.0)  # rad

    def __post_init__(self) -> None:
        for name, value in vars(self).items():
            rest = name.endswith(("_per_s", "_sigma"))
            if not (math.isfinite(value) and (value > 0 if rest else value >= 0)):
                need = "> 0" if rest else ">= 0"
                raise ValueError(f"MrclamNoise.{name} = {value!r}: must be finite and {need}")

    def intensities(self, v: Num, w: Num) -> tuple[Num, Num, Num]:
        """Variances per second of the along-track, lateral and heading errors (m^2/s,
        m^2/s, rad^2/s) while driving at ``v`` (m/s) and turning at ``w`` (rad/s): numbers
        or arrays alike."""
        av, aw = abs(v), abs(w)
        return (
            self.along_per_s**2 + self.along_per_m**2 * av,
            self.lateral_per_s**2 + self.lateral_per_m**2 * av,
            self.heading_per_s**2 + self.heading_per_m**2 * av + self.heading_per_rad**2 * aw,
        )


DEFAULT_NOISE = MrclamNoise()


@dataclass
class Mrclam:
    """One robot's run: ``data`` (poses numbered in time order; sightings' ``landmark``: the
    subject number), ``pose_times`` (s, the files' clock) of each pose index, the robot's
    ground truth (``truth_t`` (M,) s, ``truth`` (M, 3) x, y (m), theta (rad) in the arena's
    frame; empty when missing and tolerated), the landmarks' (``landmarks_truth``: subject ->
    (x, y), m), and the sightings dropped (``dropped``: by reason)."""

    data: VictoriaPark
    pose_times: NDArray[np.float64]
    truth_t: NDArray[np.float64]
    truth: NDArray[np.float64]
    landmarks_truth: dict[int, NDArray[np.float64]]
    robot: int = 1
    dropped: dict[str, int] = field(default_factory=dict)


class _Table:
    """One file's rows as an (n, k) array with their line numbers; rows refused (an error
    naming the first) or, tolerant, skipped into ``problems``."""

    def __init__(
        self, path: Path, columns: tuple[str, ...], problems: Problems, tolerant: bool
    ) -> None:
        self.name, self.base = str(path), path.name
        self.problems, self.tolerant = problems, tolerant
        rows: list[list[str]] = []
        lines: list[int] = []
        for lineno, text in open_lines(path):
            f = text.split()
            if f and not f[0].startswith("#"):
                rows.append(f)
                lines.append(lineno)
        k = len(columns)
        self.lines = np.array(lines, dtype=np.int64)
        counts = np.fromiter(map(len, rows), dtype=np.int64, count=len(rows))
        ok = self.refuse(
            counts != k,
            "wrong number of fields",
            lambda i: f"expected {k} fields ({', '.join(columns)}), got {counts[i]}",
        )
        good = [r for r, o in zip(rows, ok, strict=True) if o]
        try:
            vals = np.array(good, dtype=float).reshape(-1, k)
        except ValueError:  # find the rows that are not numbers (a slow path: bad files only)
            bad = np.array([_not_numbers(r) is not None for r in good], dtype=bool)
            rows_left = [r for r, b in zip(good, bad, strict=True) if not b]
            self.refuse(bad, "not a number", lambda i: f"not a number: {_not_numbers(good[i])}")
            vals = np.array(rows_left, dtype=float).reshape(-1, k)
        self.vals = vals
        with np.errstate(invalid="ignore"):
            big = ~(np.abs(vals) <= MAX_VALUE).all(axis=1)  # NaN fails too
        self.check(
            big,
            "not finite",
            lambda i: (
                f"not a finite number up to {MAX_VALUE:g}: "
                + " ".join(repr(float(v)) for v in self.vals[i])
            ),
        )

    def refuse(
        self, bad: NDArray[np.bool_], reason: str, detail: Callable[[int], str]
    ) -> NDArray[np.bool_]:
        """The rows ``bad``: an error naming the first (``detail(row)``), or, tolerant, each
        skipped and counted under ``reason``; returns the mask of the rows kept, and keeps
        only those line numbers."""
        if bad.any():
            rows = np.flatnonzero(bad)
            if not self.tolerant:
                i = int(rows[0])
                raise ReaderError(f"{self.name}:{self.lines[i]}: {detail(i)}")
            for i in rows:
                self.problems.skip(
                    f"{self.base}: {reason}", f"{self.name}:{self.lines[i]}: {detail(int(i))}"
                )
        self.lines = self.lines[~bad]
        return ~bad

    def check(self, bad: NDArray[np.bool_], reason: str, detail: Callable[[int], str]) -> None:
        """:meth:`refuse` on the values' rows, which are then kept likewise."""
        keep = self.refuse(bad, reason, detail)
        self.vals = self.vals[keep]

    def integers(self, col: int, what: str) -> None:
        v = self.vals[:, col]
        self.check(
            (v != np.round(v)) | (v < 0),
            f"{what} not an integer",
            lambda i: f"{what} {self.vals[i, col]:g}: not a non-negative integer",
        )

    def unique(self, col: int, what: str) -> None:
        """A value of column ``col`` given again (the later rows) refused."""
        first = np.zeros(len(self.vals), dtype=bool)
        first[np.unique(self.vals[:, col], return_index=True)[1]] = True
        self.check(
            ~first, f"{what} given twice", lambda i: f"{what} {self.vals[i, col]:g} given twice"
        )

    def in_time_order(self) -> None:
        """Rows whose time (column 0) is before an earlier row's: refused, or (tolerant)
        skipped and counted in ``problems.backwards``."""
        t = self.vals[:, 0]
        before = np.concatenate([[-np.inf], np.maximum.accumulate(t)[:-1]]) if len(t) else t
        bad = t < before
        self.check(
            bad,
            "time going backwards",
            lambda i: f"time {self.vals[i, 0]:.6f} s before an earlier line's {before[i]:.6f} s",
        )
        if bad.any():
            self.problems.backwards[self.base] += int(bad.sum())


def _not_numbers(row: list[str]) -> str | None:
    """The first field of ``row`` that is not a number (repr, cut short), or None."""
    for tok in row:
        try:
            float(tok)
        except ValueError:
            return repr(tok[:20])
    return None


def _subjects(codes: NDArray[np.float64], barcodes: NDArray[np.float64]) -> NDArray[np.int64]:
    """The subject of each barcode by the (subject, barcode) rows ``codes``; -1 if none."""
    order = np.argsort(codes[:, 1])
    known, subj = codes[order, 1], codes[order, 0].astype(np.int64)
    at = np.minimum(np.searchsorted(known, barcodes), max(len(known) - 1, 0))
    if not len(known):
        return np.full(len(barcodes), -1, dtype=np.int64)
    return np.where(known[at] == barcodes, subj[at], -1)


def _table(
    path: Path, columns: tuple[str, ...], pr: Problems, tolerant: bool, times: bool = True
) -> _Table:
    t = _Table(path, columns, pr, tolerant)
    if times:
        t.in_time_order()
    return t


def unicycle_pieces(
    v: NDArray[np.float64], w: NDArray[np.float64], dt: NDArray[np.float64]
) -> NDArray[np.float64]:
    """The (n, 3) motions (dx, dy, dtheta) in the start frame of driving at ``v`` (m/s) and
    turning at ``w`` (rad/s) for ``dt`` (s): exact arcs (the chord of length v dt sinc(phi/2)
    at phi/2, phi = w dt)."""
    phi = w * dt
    chord = v * dt * np.sinc(phi / (2 * np.pi))
    return np.column_stack([chord * np.cos(phi / 2), chord * np.sin(phi / 2), phi])


def chain(pieces: NDArray[np.float64]) -> NDArray[np.float64]:
    """The (n + 1, 3) poses reached by composing ``pieces`` (n, 3) from the origin, heading
    not wrapped (vectorised: the headings are the cumulative turns)."""
    th = np.concatenate([[0.0], np.cumsum(pieces[:, 2])])
    c, s = np.cos(th[:-1]), np.sin(th[:-1])
    dxy = np.column_stack(
        [c * pieces[:, 0] - s * pieces[:, 1], s * pieces[:, 0] + c * pieces[:, 1]]
    )
    xy = np.vstack([np.zeros((1, 2)), np.cumsum(dxy, axis=0)])
    return np.column_stack([xy, th])


def integrate_odometry(
    t_cmd: NDArray[np.float64],
    v: NDArray[np.float64],
    w: NDArray[np.float64],
    t_pose: NDArray[np.float64],
    noise: MrclamNoise = DEFAULT_NOISE,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The steps between consecutive pose times ``t_pose`` (s, increasing, within
    [t_cmd[0], t_cmd[-1]]) of the commands (``t_cmd`` non-decreasing, s; ``v`` m/s; ``w``
    rad/s; each held until the next, the later of equal times winning): (n - 1, 3) deltas
    (dx, dy, dtheta wrapped; m, rad; the end pose in the start pose's frame) and (n - 1, 3,
    3) covariances in the end pose's tangent, from ``noise``'s white velocity noise on
    each piece (its intensity by the piece's command, in the piece's end frame) carried to
    the step's end by the adjoint of the motion after it."""
    t0 = t_cmd[0]
    tc, tp = t_cmd - t0, t_pose - t0
    bp = np.union1d(tc[tc < tp[-1]], tp)  # breakpoints: commands and poses
    dt = np.diff(bp)
    cmd = np.searchsorted(tc, bp[:-1], side="right") - 1
    pieces = unicycle_pieces(v[cmd], w[cmd], dt)
    P = chain(pieces)  # pose at every breakpoint
    kp = np.searchsorted(bp, tp)  # the poses' breakpoints
    a, b = P[kp[:-1]], P[kp[1:]]
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    d = b[:, :2] - a[:, :2]
    th = b[:, 2] - a[:, 2]
    deltas = np.column_stack(
        [c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], wrap_angles(th)]
    )
    # each piece's noise, moved to its step's end pose: Ad(rest^-1) Q Ad(rest^-1)^T, rest the
    # motion from the piece's end to the step's end
    step = np.searchsorted(kp, np.arange(len(dt)), side="right") - 1
    end = P[kp[step + 1]]
    at = P[1:]
    alpha = -(end[:, 2] - at[:, 2])  # rest^-1 = (R(alpha), u), u = -R(alpha) t_rest
    ca, sa = np.cos(at[:, 2]), np.sin(at[:, 2])
    e = end[:, :2] - at[:, :2]
    tr = np.column_stack([ca * e[:, 0] + sa * e[:, 1], -sa * e[:, 0] + ca * e[:, 1]])
    cb, sb = np.cos(alpha), np.sin(alpha)
    u = -np.column_stack([cb * tr[:, 0] - sb * tr[:, 1], sb * tr[:, 0] + cb * tr[:, 1]])
    Ad = np.zeros((len(dt), 3, 3))
    Ad[:, 0, 0], Ad[:, 0, 1], Ad[:, 0, 2] = cb, -sb, u[:, 1]
    Ad[:, 1, 0], Ad[:, 1, 1], Ad[:, 1, 2] = sb, cb, -u[:, 0]
    Ad[:, 2, 2] = 1.0
    q = np.column_stack(noise.intensities(v[cmd], w[cmd])) * dt[:, None]
    per_piece = np.einsum("nij,nj,nkj->nik", Ad, q, Ad)
    covs = np.add.reduceat(per_piece, kp[:-1], axis=0)
    return deltas, 0.5 * (covs + np.transpose(covs, (0, 2, 1)))


def polar_sightings(
    r: NDArray[np.float64], b: NDArray[np.float64], noise: MrclamNoise = DEFAULT_NOISE
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(n, 2) robot-frame points (m) of ranges ``r`` (m) and bearings ``b`` (rad) and their
    (n, 2, 2) covariances J diag(range_sigma^2, bearing_sigma^2) J^T, J = d(x, y)/d(r, b)."""
    c, s = np.cos(b), np.sin(b)
    J = np.stack([np.column_stack([c, -r * s]), np.column_stack([s, r * c])], axis=1)
    var = np.array([noise.range_sigma**2, noise.bearing_sigma**2])
    cov = np.einsum("nij,j,nkj->nik", J, var, J)
    return np.column_stack([r * c, r * s]), cov


def read_mrclam(
    directory: StrPath,
    robot: int = 1,
    tolerant: bool = False,
    *,
    noise: MrclamNoise = DEFAULT_NOISE,
    duration: float | None = None,
) -> Mrclam:
    """Robot ``robot``'s run of the MRCLAM dataset directory ``directory`` (see the module's
    description; ``noise``: the model of the steps' and sightings' covariances, defaults in
    :class:`MrclamNoise`; ``duration``: only the first ``duration`` seconds after the first
    command). ReaderError for a missing or bad file (one line naming it and the line), a
    robot that is not 1-5, no commands, or no sighting of a landmark within them."""
    root = Path(directory)
    if robot not in ROBOTS:
        raise ReaderError(f"{root}: robot {robot}: the dataset's robots are 1-5")
    if duration is not None and not duration > 0:
        raise ValueError(f"duration {duration!r}: must be a positive number of seconds")
    if not root.is_dir():
        raise ReaderError(f"{root}: not a directory (an MRCLAM dataset is one)")
    out = VictoriaPark()
    pr = out.problems
    truth_name, odo_name, meas_name = robot_files(robot)

    codes = _table(root / BARCODES, ("subject", "barcode"), pr, tolerant, times=False)
    codes.integers(0, "subject")
    codes.integers(1, "barcode")
    codes.unique(0, "subject")
    codes.unique(1, "barcode")

    def optional(name: str, columns: tuple[str, ...], times: bool) -> NDArray[np.float64]:
        try:
            t = _table(root / name, columns, pr, tolerant, times)
        except ReaderError as exc:
            if not tolerant or (root / name).exists():
                raise
            pr.skip(f"{name}: missing", str(exc))
            return np.zeros((0, len(columns)))
        if not times:
            t.integers(0, "subject")
            t.check(
                (t.vals[:, 3:] < 0).any(axis=1),
                "negative standard deviation",
                lambda i: "negative standard deviation",
            )
            t.unique(0, "subject")
        return t.vals

    lms = optional(LANDMARKS, ("subject", "x", "y", "x_std_dev", "y_std_dev"), False)
    truth = optional(truth_name, ("time", "x", "y", "orientation"), True)
    odo = _table(root / odo_name, ("time", "forward_velocity", "angular_velocity"), pr, tolerant)
    meas = _table(root / meas_name, ("time", "barcode", "range", "bearing"), pr, tolerant)
    meas.integers(1, "barcode")
    meas.check(
        meas.vals[:, 2] < MIN_RANGE,
        "range not positive",
        lambda i: f"range {meas.vals[i, 2]:g} m: not positive",
    )
    if not len(odo.vals):
        raise ReaderError(f"{odo.name}: no odometry commands")
    t_odo = odo.vals[:, 0]
    t_end = t_odo[-1] if duration is None else min(t_odo[-1], t_odo[0] + duration)

    # the sightings: landmarks kept, robots and misreads counted and dropped
    subject = _subjects(codes.vals, meas.vals[:, 1])
    is_robot = np.isin(subject, ROBOTS)
    unknown = subject < 0
    t_meas = meas.vals[:, 0]
    outside = (t_meas < t_odo[0]) | (t_meas > t_odo[-1])
    late = ~outside & (t_meas > t_end)  # beyond ``duration``: not read, not a problem
    keep = ~is_robot & ~unknown & ~outside & ~late
    inside = ~outside & ~late
    dropped = {
        "sighting of a robot": int((is_robot & inside).sum()),
        "unknown barcode": int((unknown & inside).sum()),
        "outside the commands' time span": int(outside.sum()),
    }
    for reason, n in dropped.items():
        if n:
            pr.skipped_by_reason[reason] += n
    dropped["after duration"] = int(late.sum())
    if dropped["sighting of a robot"]:
        pr.ignored["sighting of a robot"] += dropped["sighting of a robot"]
    if not keep.any():
        raise ReaderError(f"{meas.name}: no sighting of a landmark within the commands' span")

    t_seen = t_meas[keep]
    pose_times = np.unique(np.concatenate([[t_odo[0]], t_seen]))
    if len(pose_times) < 2:
        raise ReaderError(f"{meas.name}: no sighting of a landmark after the first command")
    deltas, covs = integrate_odometry(t_odo, odo.vals[:, 1], odo.vals[:, 2], pose_times, noise)
    out.steps = [Step(k, k + 1, deltas[k], covs[k]) for k in range(len(deltas))]
    xy, cov = polar_sightings(meas.vals[keep, 2], meas.vals[keep, 3], noise)
    pose = np.searchsorted(pose_times, t_seen)
    for k, (p, lm) in enumerate(zip(pose.tolist(), subject[keep].tolist(), strict=True)):
        out.sightings.setdefault(p, []).append(Sighting(p, lm, xy[k], cov[k]))
    return Mrclam(
        data=out,
        pose_times=pose_times,
        truth_t=truth[:, 0].copy(),
        truth=truth[:, 1:4].copy(),
        landmarks_truth={int(r[0]): r[1:3].copy() for r in lms},
        robot=robot,
        dropped=dropped,
    )
