"""Sonar processing around a laser scan (paper III-A): readings from 6 s before to 6 s after
the scan are moved into the laser frame with odometry, phantoms far behind laser surfaces are
removed, the rest clustered, and clusters far from every laser point marked invisible.

All positions are in the laser frame at the scan's time (m); bearings in rad.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from factors.line import normalize_lines
from fgslam.config import RobotConfig
from fgslam.events import SONAR_KINDS, SonarReading

KIND_CODE = {k: i for i, k in enumerate(SONAR_KINDS)}  # plane 0, corner 1, edge 2


class PoseHistory:
    """Odometry poses (world_odo frame: x, y in m, theta in rad, unwrapped) by time (s),
    for moving sonar readings between times; kept for ``keep`` seconds.

    Stored in growing arrays (amortised doubling) so that :meth:`at` needs no conversion."""

    def __init__(self, keep: float = 20.0) -> None:
        self.keep = keep
        self._t = np.empty(1024)
        self._p = np.empty((1024, 3))
        self._lo = self._hi = 0  # the poses kept are rows lo..hi-1

    def add(self, t: float, pose: NDArray[np.float64]) -> None:
        if self._hi == len(self._t):
            n = self._hi - self._lo
            cap = max(1024, 2 * n)
            t_new, p_new = np.empty(cap), np.empty((cap, 3))
            t_new[:n], p_new[:n] = self._t[self._lo : self._hi], self._p[self._lo : self._hi]
            self._t, self._p, self._lo, self._hi = t_new, p_new, 0, n
        self._t[self._hi] = t
        self._p[self._hi] = (float(pose[0]), float(pose[1]), float(pose[2]))
        self._hi += 1
        ts = self._t
        if self._hi - self._lo > 4096 and ts[self._hi - 1] - ts[self._lo] > 2 * self.keep:
            cut = int(np.searchsorted(ts[self._lo : self._hi], ts[self._hi - 1] - self.keep))
            self._lo += cut

    def at(self, t: NDArray[np.float64] | float) -> NDArray[np.float64]:
        """Poses at times t, linearly interpolated (clamped at the ends); shape (..., 3)."""
        if self._hi == self._lo:
            return np.zeros((*np.shape(t), 3))
        ts, ps = self._t[self._lo : self._hi], self._p[self._lo : self._hi]
        t = np.asarray(t, dtype=float)
        out = np.empty((*t.shape, 3))
        for k in range(3):
            out[..., k] = np.interp(t, ts, ps[:, k])
        return out

    def velocity(self, t: float, window: float = 0.25) -> tuple[float, float]:
        """The robot's speed (m/s, negative backwards) and turn rate (rad/s,
        counter-clockwise positive) at ``t``: the odometry's motion over the ``window`` s
        before it (one sample's rate is noise on logs whose samples come at irregular or
        repeated stamps)."""
        if self._hi - self._lo < 2:
            return 0.0, 0.0
        a, b = self.at(np.array([t - window, t]))
        span = min(window, t - float(self._t[self._lo]))
        if span <= 0:
            return 0.0, 0.0
        d, turn = b[:2] - a[:2], float(b[2] - a[2])
        mid = float(a[2]) + 0.5 * turn
        forward = float(d[0]) * math.cos(mid) + float(d[1]) * math.sin(mid)
        return math.copysign(float(np.hypot(*d)), forward) / span, turn / span

    @property
    def last_time(self) -> float:
        return float(self._t[self._hi - 1]) if self._hi > self._lo else -math.inf


class SonarBuffer:
    """Sonar echoes as flat arrays (one row per echo) for fast windowing by time.

    Row fields: time (s), reading id, kind code, range (m), bearing (rad, transducer frame),
    and the transducer's pose on the robot (mount x, y in m; mount yaw + pan in rad).
    New rows are collected in a list and appended to the array when a window is asked for.
    """

    def __init__(self, cfg: RobotConfig) -> None:
        self.arrays = [
            (a.mount.x, a.mount.y, math.radians(a.mount.yaw_deg)) for a in cfg.sonar.arrays
        ]
        self.readings: dict[int, SonarReading] = {}  # readings with echoes, by id
        self._new: list[tuple[float, int, int, float, float, float, float, float]] = []
        self._arr: NDArray[np.float64] = np.empty((0, 8))
        self._next_id = 0

    def add(self, rd: SonarReading) -> None:
        rid = self._next_id
        self._next_id += 1
        if not rd.echoes:
            return
        self.readings[rid] = rd
        mx, my, myaw = self.arrays[rd.array]
        for e in rd.echoes:
            self._new.append(
                (rd.t, rid, KIND_CODE[e.kind], e.range, e.bearing, mx, my, myaw + rd.pan)
            )

    def _rows(self) -> NDArray[np.float64]:
        if self._new:
            self._arr = np.concatenate([self._arr, np.array(self._new, dtype=float)])
            self._new = []
        return self._arr

    def drop_before(self, t: float) -> None:
        """Forget the echoes (in arrival order) before the first one at or after time t."""
        a = self._rows()
        if len(a) and a[0, 0] < t:
            later = a[:, 0] >= t
            k = int(np.argmax(later)) if later.any() else len(a)
            for rid in np.unique(a[:k, 1]).astype(int).tolist():
                self.readings.pop(rid, None)
            self._arr = a[k:]

    def window(self, t0: float, t1: float) -> NDArray[np.float64]:
        """Rows with t0 <= t <= t1, shape (N, 8)."""
        a = self._rows()
        lo = int(np.searchsorted(a[:, 0], t0, side="left"))
        hi = int(np.searchsorted(a[:, 0], t1, side="right"))
        return a[lo:hi]


@dataclass
class SonarPoints:
    """Echoes of a window, in the laser frame at the scan's time; one entry per echo.

    ``kind`` code (0 plane, 1 corner, 2 edge), position ``xy`` (for planes the normal foot
    point), ``line`` (alpha, d) for planes (NaN otherwise), measured range ``r`` and
    ``bearing`` (transducer frame), reading time ``t``, ``reading`` id (key of
    :attr:`SonarBuffer.readings`), ``sensor`` the transducer pose in the laser frame and
    ``mount`` its pose on the robot (x, y, yaw + pan; robot frame at the reading's time).
    """

    readings: dict[int, SonarReading]
    kind: NDArray[np.int64]
    xy: NDArray[np.float64]
    line: NDArray[np.float64]
    r: NDArray[np.float64]
    t: NDArray[np.float64]
    reading: NDArray[np.int64]
    sensor: NDArray[np.float64]
    bearing: NDArray[np.float64]
    mount: NDArray[np.float64]

    def __len__(self) -> int:
        return len(self.kind)

    def subset(self, mask: NDArray[np.bool_]) -> SonarPoints:
        return SonarPoints(
            self.readings,
            self.kind[mask],
            self.xy[mask],
            self.line[mask],
            self.r[mask],
            self.t[mask],
            self.reading[mask],
            self.sensor[mask],
            self.bearing[mask],
            self.mount[mask],
        )


def to_laser_frame(
    buf: SonarBuffer, cfg: RobotConfig, poses: PoseHistory, t_scan: float, window: float
) -> SonarPoints:
    """Move the echoes within ``window`` s of ``t_scan`` into the laser frame at ``t_scan``
    with odometry."""
    rows = buf.window(t_scan - window, t_scan + window)
    t, rid, kind, rng, brg, mx, my, mth = rows.T
    lm = cfg.laser.mount
    p_scan = poses.at(t_scan)
    c, s = math.cos(p_scan[2]), math.sin(p_scan[2])
    lx = p_scan[0] + c * lm.x - s * lm.y
    ly = p_scan[1] + s * lm.x + c * lm.y
    lth = p_scan[2] + math.radians(lm.yaw_deg)
    P = poses.at(t)
    cr, sr = np.cos(P[:, 2]), np.sin(P[:, 2])
    sx = P[:, 0] + cr * mx - sr * my  # transducer in the odometry world frame
    sy = P[:, 1] + sr * mx + cr * my
    sth = P[:, 2] + mth
    cl, sl = math.cos(lth), math.sin(lth)
    dx, dy = sx - lx, sy - ly
    tx, ty = cl * dx + sl * dy, -sl * dx + cl * dy  # transducer in the laser frame
    tth = sth - lth
    a = tth + brg
    xy = np.column_stack([tx + rng * np.cos(a), ty + rng * np.sin(a)])
    # planes: (alpha = bearing, d = range) in the transducer frame -> laser frame
    d = rng + tx * np.cos(a) + ty * np.sin(a)
    alpha, d = normalize_lines(a, d)
    kind = kind.astype(np.int64)
    line = np.where((kind == 0)[:, None], np.column_stack([alpha, d]), np.nan)
    return SonarPoints(
        buf.readings,
        kind,
        xy,
        line,
        rng,
        t,
        rid.astype(np.int64),
        np.column_stack([tx, ty, tth]),
        brg,
        np.column_stack([mx, my, mth]),
    )


def remove_phantoms(
    pts: SonarPoints, scan_phi: NDArray[np.float64], scan_r: NDArray[np.float64], margin: float
) -> tuple[SonarPoints, int]:
    """Drop echoes more than ``margin`` m behind the laser surface in their direction (seen
    from the laser); returns the kept echoes and how many were dropped."""
    if len(pts) == 0:
        return pts, 0
    ang = np.arctan2(pts.xy[:, 1], pts.xy[:, 0])
    dist = np.hypot(pts.xy[:, 0], pts.xy[:, 1])
    step = scan_phi[1] - scan_phi[0]
    k = np.clip(np.round((ang - scan_phi[0]) / step).astype(int), 0, len(scan_phi) - 1)
    in_fov = (ang >= scan_phi[0] - step) & (ang <= scan_phi[-1] + step)
    surface = scan_r[k]
    phantom = in_fov & np.isfinite(surface) & (dist > surface + margin)
    return pts.subset(~phantom), int(phantom.sum())


@dataclass
class Cluster:
    """A cluster of sonar echoes (indices into a :class:`SonarPoints`)."""

    members: NDArray[np.int64]
    centre: NDArray[np.float64]
    counts: NDArray[np.int64]  # echoes per kind: plane, corner, edge
    visible: bool = True

    @property
    def has_corner_or_edge(self) -> bool:
        return bool(self.counts[1] + self.counts[2] > 0)


def _components(n: int, pairs: NDArray[np.intp]) -> NDArray[np.intp]:
    """Connected components of n nodes linked by ``pairs`` (K, 2): each node's label is the
    smallest node index of its component (min-label propagation with pointer jumping)."""
    lab = np.arange(n)
    if len(pairs) == 0:
        return lab
    a, b = pairs[:, 0], pairs[:, 1]
    while True:
        m = np.minimum(lab[a], lab[b])
        new = lab.copy()
        np.minimum.at(new, a, m)
        np.minimum.at(new, b, m)
        new = new[new]  # a label is a node of the same component with a smaller index
        if np.array_equal(new, lab):
            return lab
        lab = new


def cluster(pts: SonarPoints, radius: float, kinds: tuple[int, ...] = (1, 2)) -> list[Cluster]:
    """Single-linkage clusters (link distance ``radius`` m) of the echoes of the given kinds,
    ordered by their first echo."""
    idx = np.flatnonzero(np.isin(pts.kind, kinds))
    if idx.size == 0:
        return []
    xy = pts.xy[idx]
    pairs = cKDTree(xy).query_pairs(radius, output_type="ndarray")
    labels = _components(idx.size, pairs)
    order = np.argsort(labels, kind="stable")
    starts = np.flatnonzero(np.diff(labels[order], prepend=-1))
    out = []
    for m in np.split(idx[order], starts[1:]):
        counts = np.bincount(pts.kind[m], minlength=3)
        out.append(Cluster(m, pts.xy[m].mean(axis=0), counts))
    return out


def mark_invisible(clusters: list[Cluster], scan_xy: NDArray[np.float64], max_dist: float) -> None:
    """A cluster farther than ``max_dist`` m from every laser point is invisible this scan."""
    if not clusters:
        return
    if len(scan_xy) == 0:
        for c in clusters:
            c.visible = False
        return
    d, _ = cKDTree(scan_xy).query(np.array([c.centre for c in clusters]))
    for c, di in zip(clusters, d, strict=True):
        c.visible = bool(di <= max_dist)
