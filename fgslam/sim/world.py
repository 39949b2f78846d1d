"""Simulated worlds: a JSON file of walls, doors, mouldings, legs, glass and pedestrians,
compiled into the geometry the sensor models cast against. Documented in docs/world-format.md.

All coordinates are world frame, m; angles rad unless a key says ``_deg``.
Compiled geometry (arrays, for vectorised ray casting):
- ``laser_segments`` (N, 4): x1 y1 x2 y2 of everything the laser sees (walls, door planes,
  jambs; not glass); ``sonar_segments``: the same plus glass (sound reflects off glass).
- ``corners``: right-angle vertices of wall polylines: vertex (x, y) and the direction of the
  bisector of the concave side (pointing from the vertex into the free space inside the angle).
- ``edges``: point reflectors for sonar: convex sides of polyline vertices, free wall ends,
  mouldings and legs (with radius), each with the direction range from which it is visible.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from factors.line import normalize_line
from fgslam.errors import UserError

BUILTIN_WORLDS = ("corridor", "corridor-oneway")


class WorldError(UserError, ValueError):
    """An invalid world file; the message names the file and the element."""


@dataclass
class Pedestrian:
    """A person walking once along ``path`` (m) at ``speed`` (m/s), from time ``start`` (s);
    a circle of ``radius`` (m) to both sensors while walking, absent before and after."""

    path: np.ndarray
    speed: float
    start: float
    radius: float

    def __post_init__(self) -> None:
        self._seg = np.diff(self.path, axis=0)
        lens = np.hypot(self._seg[:, 0], self._seg[:, 1])
        self._cum = np.concatenate([[0.0], np.cumsum(lens)])

    def position(self, t: float) -> np.ndarray | None:
        """Position at time t, or None when not walking."""
        s = (t - self.start) * self.speed
        if s < 0 or s > self._cum[-1]:
            return None
        k = int(min(np.searchsorted(self._cum, s, side="right") - 1, len(self._seg) - 1))
        f = (s - self._cum[k]) / (self._cum[k + 1] - self._cum[k])
        return self.path[k] + f * self._seg[k]


@dataclass
class World:
    """Compiled world geometry. Build with :func:`load_world`."""

    name: str
    polylines: list[np.ndarray]  # laser-opaque walls after doors are cut in
    glass: list[np.ndarray]
    legs: np.ndarray  # (K, 3): x, y, radius
    mouldings: np.ndarray  # (M, 2): edge reflectors 1 cm proud of a wall
    pedestrians: list[Pedestrian]
    route: np.ndarray | None  # default waypoints for the simulated run
    start_heading: float = 0.0
    laser_segments: np.ndarray = field(init=False)
    sonar_segments: np.ndarray = field(init=False)
    corners: np.ndarray = field(init=False)  # (C, 3): x, y, concave bisector angle
    edges: np.ndarray = field(init=False)  # (E, 5): x, y, radius, centre angle, half width

    def __post_init__(self) -> None:
        self.laser_segments = _segments(self.polylines)
        self.sonar_segments = np.vstack([self.laser_segments, _segments(self.glass)])
        corners, edges = [], []
        for pl in self.polylines:
            closed = len(pl) > 3 and np.allclose(pl[0], pl[-1])
            # a closed polyline bounds the free space: interior on the left if counter-clockwise
            area = 0.5 * float(np.sum(pl[:-1, 0] * pl[1:, 1] - pl[1:, 0] * pl[:-1, 1]))
            orient = (1.0 if area > 0 else -1.0) if closed else 0.0
            n = len(pl)
            idx = range(n - 1) if closed else range(1, n - 1)
            for i in idx:
                prev = pl[i - 1] if i > 0 else pl[-2]
                v, nxt = pl[i], pl[i + 1]
                u1, u2 = _unit(v - prev), _unit(nxt - v)
                turn = math.atan2(u1[0] * u2[1] - u1[1] * u2[0], u1 @ u2)
                if abs(turn) < math.radians(10):
                    continue
                concave = _unit(u2 - u1)  # bisector between the two walls' directions from v
                ang = math.atan2(concave[1], concave[0])
                inner = math.pi - abs(turn)  # the angle between the walls at v
                # in a closed room a vertex is concave (left turn of a counter-clockwise
                # boundary) or convex as seen from inside; a free-standing wall has both sides
                if orient * turn >= 0 and abs(abs(turn) - math.pi / 2) < math.radians(1):
                    corners.append((v[0], v[1], ang))
                if orient * turn <= 0:
                    # the reflex side echoes as an edge, visible within (2pi - inner)/2 of its axis
                    edges.append((v[0], v[1], 0.0, ang + math.pi, math.pi - inner / 2))
            if not closed:
                for end, nb in ((pl[0], pl[1]), (pl[-1], pl[-2])):
                    d = _unit(end - nb)
                    edges.append((end[0], end[1], 0.0, math.atan2(d[1], d[0]), math.pi))
        for x, y in self.mouldings:
            edges.append((x, y, 0.0, 0.0, math.pi))
        for x, y, r in self.legs:
            edges.append((x, y, r, 0.0, math.pi))
        self.corners = np.array(corners, dtype=float).reshape(-1, 3)
        self.edges = np.array(edges, dtype=float).reshape(-1, 5)

    def pedestrian_circles(self, t: float) -> np.ndarray:
        """(P, 3) x, y, radius of the pedestrians present at time t."""
        out = []
        for p in self.pedestrians:
            pos = p.position(t)
            if pos is not None:
                out.append((pos[0], pos[1], p.radius))
        return np.array(out, dtype=float).reshape(-1, 3)

    def circles(self, t: float) -> np.ndarray:
        """Legs and pedestrians at time t: (K, 3) x, y, radius."""
        return np.vstack([self.legs, self.pedestrian_circles(t)])

    def clearance(self, points: np.ndarray) -> np.ndarray:
        """Distance (m) from each point (N, 2) to the nearest wall, glass pane or leg."""
        pts = np.asarray(points, dtype=float).reshape(-1, 2)
        d = point_segment_distance(pts, self.sonar_segments).min(axis=1)
        if len(self.legs):
            dl = np.hypot(
                pts[:, None, 0] - self.legs[None, :, 0], pts[:, None, 1] - self.legs[None, :, 1]
            )
            d = np.minimum(d, (dl - self.legs[None, :, 2]).min(axis=1))
        return d

    def feature_map(self) -> dict[str, list]:
        """The true feature map for map-error evaluation (world frame, m, rad).

        ``lines``: every wall segment and glass pane as {alpha, d (d >= 0), endpoints,
        laser (seen by the laser)}; ``corners``: concave right-angle corners as {x, y, theta}
        with theta the bisector pointing from the vertex into free space; ``points``: sonar
        point reflectors (convex vertices, wall ends, mouldings, door frames, legs) as {x, y,
        radius}.
        """
        lines = []
        for segs, laser in ((self.laser_segments, True), (_segments(self.glass), False)):
            for x1, y1, x2, y2 in segs:
                nx, ny = y1 - y2, x2 - x1  # a normal of the segment
                n = math.hypot(nx, ny)
                alpha = math.atan2(ny, nx)
                d = (x1 * nx + y1 * ny) / n
                alpha, d = normalize_line(alpha, d)
                lines.append(
                    {"alpha": alpha, "d": d, "endpoints": [[x1, y1], [x2, y2]], "laser": laser}
                )
        corners = [{"x": x, "y": y, "theta": t} for x, y, t in self.corners.tolist()]
        points = [{"x": x, "y": y, "radius": r} for x, y, r in self.edges[:, :3].tolist()]
        return {"lines": lines, "corners": corners, "points": points}

    def bounds(self) -> tuple[float, float, float, float]:
        s = self.sonar_segments
        xs, ys = np.concatenate([s[:, 0], s[:, 2]]), np.concatenate([s[:, 1], s[:, 3]])
        return float(xs.min()), float(xs.max()), float(ys.min()), float(ys.max())


def _unit(v: np.ndarray) -> np.ndarray:
    n = float(np.hypot(v[0], v[1]))
    return v / n if n > 0 else v


def _segments(polylines: list[np.ndarray]) -> np.ndarray:
    segs = [np.hstack([pl[:-1], pl[1:]]) for pl in polylines if len(pl) >= 2]
    return np.vstack(segs) if segs else np.zeros((0, 4))


def point_segment_distance(points: np.ndarray, segs: np.ndarray) -> np.ndarray:
    """(N, M) distances from points (N, 2) to segments (M, 4)."""
    p = points[:, None, :]
    a, b = segs[None, :, :2], segs[None, :, 2:]
    ab = b - a
    denom = np.maximum((ab**2).sum(-1), 1e-18)
    t = np.clip(((p - a) * ab).sum(-1) / denom, 0.0, 1.0)
    closest = a + t[..., None] * ab
    return np.hypot(*(p - closest).transpose(2, 0, 1))


# ------------------------------------------------------------------ loading and validation


MAX_VALUE = 1e6  # no coordinate, size, time or angle of a world is larger


def _err(src: str, where: str, msg: str) -> WorldError:
    return WorldError(f"world {src}: {where}: {msg}")


def _number(v: Any, src: str, where: str, positive: bool = False, nonneg: bool = False) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        raise _err(src, where, f"expected a finite number, got {v!r}")
    if not abs(v) <= MAX_VALUE:
        raise _err(src, where, f"{v!r} is beyond {MAX_VALUE:g} (m, s or deg): not a building")
    if positive and v <= 0:
        raise _err(src, where, f"expected a positive number, got {v!r}")
    if nonneg and v < 0:
        raise _err(src, where, f"expected a non-negative number, got {v!r}")
    return float(v)


def _points(v: Any, src: str, where: str, min_n: int = 2) -> np.ndarray:
    if not isinstance(v, list) or len(v) < min_n:
        raise _err(src, where, f"expected a list of at least {min_n} [x, y] points")
    out = []
    for i, p in enumerate(v):
        if not isinstance(p, list) or len(p) != 2:
            raise _err(src, f"{where}[{i}]", f"expected [x, y], got {p!r}")
        out.append([_number(c, src, f"{where}[{i}]") for c in p])
    arr = np.array(out)
    if np.any(np.hypot(*np.diff(arr, axis=0).T) < 1e-6):
        raise _err(src, where, "two consecutive points coincide")
    return arr


def _check_keys(d: Any, allowed: set[str], required: set[str], src: str, where: str) -> None:
    if not isinstance(d, dict):
        raise _err(src, where, f"expected an object, got {type(d).__name__}")
    for k in d:
        if k not in allowed:
            raise _err(
                src, where, f"unknown key '{k}' (expected one of: {', '.join(sorted(allowed))})"
            )
    for k in required:
        if k not in d:
            raise _err(src, where, f"missing key '{k}'")


def _cut_doors(
    pts: np.ndarray, doors: list[tuple[int, float, float, float, int, bool, str]], src: str
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Insert doors into one wall polyline. Each door: (segment, at, width, recess, side,
    open, where). Returns the resulting polylines and the flush-door frame points."""
    by_seg: dict[int, list] = {}
    for d in doors:
        by_seg.setdefault(d[0], []).append(d)
    lines: list[list[np.ndarray]] = [[pts[0]]]
    frames: list[np.ndarray] = []
    for k in range(len(pts) - 1):
        a, b = pts[k], pts[k + 1]
        u = _unit(b - a)
        length = float(np.hypot(*(b - a)))
        last_end = 0.0
        for _seg, at, width, recess, side, is_open, where in sorted(
            by_seg.get(k, []), key=lambda d: d[1]
        ):
            if at < last_end + 0.05 or at + width > length - 0.05:
                raise _err(src, where, "door overlaps another door or the segment's ends")
            last_end = at + width
            p, q = a + at * u, a + (at + width) * u
            if is_open:
                lines[-1].append(p)
                lines.append([q])
                continue
            if recess > 0:
                n = side * np.array([-u[1], u[0]])
                lines[-1].extend([p, p + recess * n, q + recess * n, q])
            else:
                frames.extend([p, q])
        lines[-1].append(b)
    return [np.array(pl) for pl in lines if len(pl) >= 2], frames


def parse_world(data: Any, src: str) -> World:
    """Validate and compile a world given as the parsed JSON object."""
    top = {"name", "description", "walls", "doors", "mouldings", "legs", "tables", "glass"}
    top |= {"pedestrians", "route", "start_heading_deg"}
    _check_keys(data, top, {"name", "walls"}, src, "top level")
    if not isinstance(data["name"], str) or not data["name"]:
        raise _err(src, "name", "expected a non-empty string")
    walls: dict[str, np.ndarray] = {}
    order: list[str] = []
    if not isinstance(data["walls"], list) or not data["walls"]:
        raise _err(src, "walls", "expected a non-empty list")
    for i, w in enumerate(data["walls"]):
        where = f"walls[{i}]"
        _check_keys(w, {"id", "points", "closed"}, {"id", "points"}, src, where)
        wid = w["id"]
        where = f"walls[{i}] ('{wid}')"
        if not isinstance(wid, str) or wid in walls:
            raise _err(src, where, "id must be a unique string")
        pts = _points(w["points"], src, f"{where}.points")
        if w.get("closed", False):
            pts = np.vstack([pts, pts[:1]])
        walls[wid] = pts
        order.append(wid)
    doors: dict[str, list] = {wid: [] for wid in walls}
    for i, d in enumerate(data.get("doors", [])):
        where = f"doors[{i}]"
        _check_keys(
            d,
            {"wall", "segment", "at", "width", "recess", "side", "open"},
            {"wall", "at", "width"},
            src,
            where,
        )
        if d["wall"] not in walls:
            raise _err(src, where, f"unknown wall '{d['wall']}'")
        seg = d.get("segment", 0)
        if (
            isinstance(seg, bool)
            or not isinstance(seg, int)
            or not 0 <= seg < len(walls[d["wall"]]) - 1
        ):
            raise _err(src, f"{where}.segment", f"no segment {seg!r} in wall '{d['wall']}'")
        side = d.get("side", "left")
        if side not in ("left", "right"):
            raise _err(src, f"{where}.side", f"expected 'left' or 'right', got {side!r}")
        doors[d["wall"]].append(
            (
                seg,
                _number(d["at"], src, f"{where}.at", nonneg=True),
                _number(d["width"], src, f"{where}.width", positive=True),
                _number(d.get("recess", 0.0), src, f"{where}.recess", nonneg=True),
                1 if side == "left" else -1,
                bool(d.get("open", False)),
                where,
            )
        )
    polylines: list[np.ndarray] = []
    frame_points: list[np.ndarray] = []
    for wid in order:
        pls, frames = _cut_doors(walls[wid], doors[wid], src)
        polylines.extend(pls)
        frame_points.extend(frames)
    mould = []
    for i, m in enumerate(data.get("mouldings", [])):
        where = f"mouldings[{i}]"
        _check_keys(m, {"wall", "segment", "at", "side"}, {"wall", "at"}, src, where)
        if m["wall"] not in walls:
            raise _err(src, where, f"unknown wall '{m['wall']}'")
        pts = walls[m["wall"]]
        seg = m.get("segment", 0)
        if not isinstance(seg, int) or not 0 <= seg < len(pts) - 1:
            raise _err(src, f"{where}.segment", f"no segment {seg!r} in wall '{m['wall']}'")
        a, b = pts[seg], pts[seg + 1]
        at = _number(m["at"], src, f"{where}.at", nonneg=True)
        if at > np.hypot(*(b - a)):
            raise _err(src, f"{where}.at", "beyond the end of the segment")
        u = _unit(b - a)
        side = 1 if m.get("side", "left") == "left" else -1
        mould.append(a + at * u + 0.01 * side * np.array([-u[1], u[0]]))
    # flush doors: their frames stand proud of the wall like mouldings
    mould.extend(frame_points)
    legs = []
    for i, leg in enumerate(data.get("legs", [])):
        where = f"legs[{i}]"
        _check_keys(leg, {"x", "y", "radius"}, {"x", "y"}, src, where)
        legs.append(
            (
                _number(leg["x"], src, f"{where}.x"),
                _number(leg["y"], src, f"{where}.y"),
                _number(leg.get("radius", 0.02), src, f"{where}.radius", positive=True),
            )
        )
    for i, t in enumerate(data.get("tables", [])):
        where = f"tables[{i}]"
        _check_keys(
            t,
            {"x", "y", "width", "depth", "yaw_deg", "leg_radius"},
            {"x", "y", "width", "depth"},
            src,
            where,
        )
        cx, cy = _number(t["x"], src, f"{where}.x"), _number(t["y"], src, f"{where}.y")
        w = _number(t["width"], src, f"{where}.width", positive=True)
        dp = _number(t["depth"], src, f"{where}.depth", positive=True)
        yaw = math.radians(_number(t.get("yaw_deg", 0.0), src, f"{where}.yaw_deg"))
        r = _number(t.get("leg_radius", 0.02), src, f"{where}.leg_radius", positive=True)
        c, s = math.cos(yaw), math.sin(yaw)
        for sx, sy in ((1, 1), (-1, 1), (-1, -1), (1, -1)):
            lx, ly = sx * (w / 2 - 0.05), sy * (dp / 2 - 0.05)
            legs.append((cx + c * lx - s * ly, cy + s * lx + c * ly, r))
    glass = []
    for i, g in enumerate(data.get("glass", [])):
        where = f"glass[{i}]"
        _check_keys(g, {"id", "points"}, {"points"}, src, where)
        glass.append(_points(g["points"], src, f"{where}.points"))
    peds = []
    for i, p in enumerate(data.get("pedestrians", [])):
        where = f"pedestrians[{i}]"
        _check_keys(p, {"path", "speed", "start", "radius"}, {"path"}, src, where)
        peds.append(
            Pedestrian(
                _points(p["path"], src, f"{where}.path"),
                _number(p.get("speed", 1.2), src, f"{where}.speed", positive=True),
                _number(p.get("start", 0.0), src, f"{where}.start", nonneg=True),
                _number(p.get("radius", 0.2), src, f"{where}.radius", positive=True),
            )
        )
    route = _points(data["route"], src, "route") if "route" in data else None
    heading = math.radians(_number(data.get("start_heading_deg", 0.0), src, "start_heading_deg"))
    return World(
        name=data["name"],
        polylines=polylines,
        glass=glass,
        legs=np.array(legs, dtype=float).reshape(-1, 3),
        mouldings=np.array(mould, dtype=float).reshape(-1, 2),
        pedestrians=peds,
        route=route,
        start_heading=heading,
    )


def load_world(name_or_path: str | Path) -> World:
    """A built-in world by name (``corridor``) or a world JSON file."""
    if str(name_or_path) in BUILTIN_WORLDS:
        text = resources.files("fgslam.data").joinpath(f"world_{name_or_path}.json").read_text()
        src = f"<built-in {name_or_path}>"
    else:
        path = Path(name_or_path)
        src = str(path)
        try:
            text = path.read_text("utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            raise WorldError(
                f"world {src}: cannot read ({getattr(exc, 'strerror', None) or exc}); "
                f"built-in worlds: {', '.join(BUILTIN_WORLDS)}"
            ) from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise WorldError(f"world {src}: not valid JSON: {exc}") from None
    return parse_world(data, src)
