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
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from fgslam.config import RobotConfig
from fgslam.events import SONAR_KINDS, SonarReading

KIND_CODE = {k: i for i, k in enumerate(SONAR_KINDS)}  # plane 0, corner 1, edge 2


class PoseHistory:
    """Odometry poses (world_odo frame: x, y in m, theta in rad, unwrapped) by time (s),
    for moving sonar readings between times; kept for ``keep`` seconds."""

    def __init__(self, keep: float = 20.0) -> None:
        self.keep = keep
        self._t: list[float] = []
        self._p: list[tuple[float, float, float]] = []
        self._arr: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None

    def add(self, t: float, pose: NDArray[np.float64]) -> None:
        self._t.append(t)
        self._p.append((float(pose[0]), float(pose[1]), float(pose[2])))
        self._arr = None
        if len(self._t) > 4096 and self._t[-1] - self._t[0] > 2 * self.keep:
            cut = int(np.searchsorted(self._t, self._t[-1] - self.keep))
            del self._t[:cut], self._p[:cut]

    def at(self, t: NDArray[np.float64] | float) -> NDArray[np.float64]:
        """Poses at times t, linearly interpolated (clamped at the ends); shape (..., 3)."""
        if not self._t:
            return np.zeros((*np.shape(t), 3))
        if self._arr is None:
            self._arr = (np.array(self._t), np.array(self._p))
        ts, ps = self._arr
        t = np.asarray(t, dtype=float)
        out = np.empty((*t.shape, 3))
        for k in range(3):
            out[..., k] = np.interp(t, ts, ps[:, k])
        return out

    @property
    def last_time(self) -> float:
        return self._t[-1] if self._t else -math.inf


class SonarBuffer:
    """Sonar echoes as flat arrays (one row per echo) for fast windowing by time.

    Row fields: time (s), reading id, kind code, range (m), bearing (rad, transducer frame),
    and the transducer's pose on the robot (mount x, y in m; mount yaw + pan in rad).
    """

    def __init__(self, cfg: RobotConfig) -> None:
        self.arrays = [
            (a.mount.x, a.mount.y, math.radians(a.mount.yaw_deg)) for a in cfg.sonar.arrays
        ]
        self.readings: dict[int, SonarReading] = {}
        self._rows: list[tuple[float, int, int, float, float, float, float, float]] = []
        self._arr: NDArray[np.float64] | None = None
        self._next_id = 0

    def add(self, rd: SonarReading) -> None:
        rid = self._next_id
        self._next_id += 1
        self.readings[rid] = rd
        mx, my, myaw = self.arrays[rd.array]
        for e in rd.echoes:
            self._rows.append(
                (rd.t, rid, KIND_CODE[e.kind], e.range, e.bearing, mx, my, myaw + rd.pan)
            )
        self._arr = None

    def drop_before(self, t: float) -> None:
        """Forget echoes older than t."""
        if self._rows and self._rows[0][0] < t:
            k = 0
            while k < len(self._rows) and self._rows[k][0] < t:
                k += 1
            gone = {row[1] for row in self._rows[:k]}
            del self._rows[:k]
            for rid in gone:
                self.readings.pop(rid, None)
            self._arr = None

    def window(self, t0: float, t1: float) -> NDArray[np.float64]:
        """Rows with t0 <= t <= t1, shape (N, 8)."""
        if self._arr is None:
            self._arr = np.array(self._rows, dtype=float).reshape(-1, 8)
        a = self._arr
        lo = int(np.searchsorted(a[:, 0], t0, side="left"))
        hi = int(np.searchsorted(a[:, 0], t1, side="right"))
        return a[lo:hi]


@dataclass
class SonarPoints:
    """Echoes of a window, in the laser frame at the scan's time; one entry per echo.

    ``kind`` code (0 plane, 1 corner, 2 edge), position ``xy`` (for planes the normal foot
    point), ``line`` (alpha, d) for planes (NaN otherwise), measured range ``r`` and
    ``bearing`` (transducer frame), reading time ``t``, ``reading`` id (key of
    :attr:`SonarBuffer.readings`), and ``sensor`` the transducer pose in the laser frame.
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
    alpha = np.where(d < 0, a + math.pi, a)
    alpha = (alpha + math.pi) % (2 * math.pi) - math.pi
    kind = kind.astype(np.int64)
    line = np.where((kind == 0)[:, None], np.column_stack([alpha, np.abs(d)]), np.nan)
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

    @property
    def dominant(self) -> int:
        return int(np.argmax(self.counts))


def cluster(pts: SonarPoints, radius: float, kinds: tuple[int, ...] = (1, 2)) -> list[Cluster]:
    """Single-linkage clusters (link distance ``radius`` m) of the echoes of the given kinds."""
    idx = np.flatnonzero(np.isin(pts.kind, kinds))
    if idx.size == 0:
        return []
    xy = pts.xy[idx]
    pairs = cKDTree(xy).query_pairs(radius, output_type="ndarray")
    n = idx.size
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    ncomp, labels = connected_components(graph, directed=False)
    out = []
    for c in range(ncomp):
        m = idx[labels == c]
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
