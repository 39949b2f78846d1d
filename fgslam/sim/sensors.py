"""Sensor models of the simulator: SICK PLS laser and advanced sonar, from world geometry.

The error models here are the *true* errors of the simulated devices (``SimParams``), which
are deliberately different from, and mostly smaller than, the error models the estimator
assumes (the robot configuration), as with real sensors.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from factors.geometry import wrap_angle, wrap_angle_half_open, wrap_angles
from fgslam.config import LaserConfig, SonarConfig
from fgslam.events import SonarEcho
from fgslam.sim.raycast import blocked, raycast
from fgslam.sim.world import World


@dataclass(frozen=True)
class SimParams:
    """True error characteristics of the simulated robot and sensors."""

    # odometry: systematic relative errors of the real wheel radii and wheelbase (a scale
    # error of 0.55 % along the path, a 0.1 % left/right mismatch that curves it)
    radius_error_right: float = 0.006
    radius_error_left: float = 0.005
    wheelbase_error: float = 0.005
    # laser (true): random sigma (m), range-dependent systematic error, mixed pixels
    # 1.38 cm Gaussian + the 5 cm quantisation (1.44 cm) = the configured 2 cm random error
    laser_sigma: float = 0.0138
    laser_sys_offset: float = 0.008
    laser_sys_per_metre: float = 0.0015
    mixed_pixel_prob: float = 0.6
    mixed_pixel_jump: float = 0.15  # m of depth discontinuity within a beam's footprint
    beam_width_deg: float = 0.5  # laser footprint
    # sonar (true)
    sonar_bearing_sigma_deg: float = 0.5
    sonar_range_sigma_rel: float = 0.003
    sound_speed_bias_sigma: float = 0.005  # per-run relative bias (air temperature)
    misclass_prob: float = 0.02
    detect_prob: float = 0.95
    phantom_prob: float = 0.3
    max_echoes: int = 6


def _one_surface(hits: NDArray[np.float64], half: float, tol: NDArray[np.float64]) -> NDArray:
    """Per beam: whether its centre ray (hits[0], bearing 0) meets the chord between its edge
    rays' hits (hits[1] at -half, hits[2] at +half rad) within ``tol`` m, i.e. whether the
    footprint lies on one surface rather than across a depth discontinuity."""
    r0, r1, r2 = hits
    c, s = math.cos(half), math.sin(half)
    # edge hits in the beam's frame (centre ray along +x); the centre ray meets the chord at
    # x where the line through them crosses y = 0
    x1, y1, x2, y2 = r1 * c, -r1 * s, r2 * c, r2 * s
    with np.errstate(invalid="ignore", divide="ignore"):
        x = x1 - y1 * (x2 - x1) / (y2 - y1)
        return np.abs(r0 - x) <= tol


def laser_scan(
    world: World,
    laser: LaserConfig,
    params: SimParams,
    pose: tuple[float, float, float],
    t: float,
    rng: np.random.Generator,
) -> NDArray[np.float64]:
    """Ranges (m, NaN = no return) of one scan from the laser's world ``pose`` at time t.

    Each beam is cast three times across its footprint; where those disagree by more than a
    mixed-pixel jump and the footprint straddles a depth discontinuity (its centre's range is
    not the chord's between its edges': a wall seen at a grazing angle spans that depth too,
    but as one surface), the PLS may report a range in between. Glass is not seen. Ranges get
    true systematic and random errors, are quantised to the range resolution, and beyond the
    maximum range read as no return.
    """
    x, y, th = pose
    bearings = laser.bearings
    half = math.radians(params.beam_width_deg) / 2
    angles = th + np.concatenate([bearings, bearings - half, bearings + half])
    circles = world.circles(t)
    hits = raycast((x, y), angles, world.laser_segments, circles).reshape(3, -1)
    r = hits[0].copy()
    lo, hi = hits.min(axis=0), hits.max(axis=0)
    with np.errstate(invalid="ignore"):
        mixed = np.isfinite(hi) & (hi - lo > params.mixed_pixel_jump)
        mixed &= ~_one_surface(hits, half, (hi - lo) / 4)
    mixed &= rng.random(r.size) < params.mixed_pixel_prob
    r[mixed] = lo[mixed] + rng.random(int(mixed.sum())) * (hi[mixed] - lo[mixed])
    r = r * (1 + params.laser_sys_per_metre) + params.laser_sys_offset
    r = r + rng.normal(0.0, params.laser_sigma, r.size)
    q = laser.range_resolution
    r = np.round(np.round(r / q) * q, 6)  # whole quanta, written compactly in logs
    r[~np.isfinite(r) | (r > laser.max_range) | (r <= 0)] = np.nan
    return r


def sonar_echoes(
    world: World,
    sonar: SonarConfig,
    params: SimParams,
    pose: tuple[float, float, float],
    t: float,
    rng: np.random.Generator,
    sound_bias: float,
) -> tuple[SonarEcho, ...]:
    """Classified echoes of one measurement cycle from the transducer's world ``pose``.

    Visibility: a plane (wall or glass) only when the normal from the transducer to it lies
    within the plane-incidence angle of the beam axis and its foot is on the segment; a
    concave right-angle corner when its vertex is in the beam and the transducer inside the
    corner's quadrant; an edge (convex vertex, wall end, moulding, leg, pedestrian) when it
    is in the beam and faces the transducer. Nothing is heard through walls or glass. Phantoms:
    an edge or corner heard via one specular bounce on a wall appears mirrored behind it.
    """
    x, y, th = pose
    half = math.radians(sonar.beam_half_width_deg)
    segs = world.sonar_segments
    circles = world.circles(t)
    cands: list[tuple[str, float, float]] = []  # kind, range, world bearing

    # planes: foot of the perpendicular from the transducer
    ax, ay, bx, by = segs.T
    ex, ey = bx - ax, by - ay
    L2 = ex * ex + ey * ey
    s = ((x - ax) * ex + (y - ay) * ey) / L2
    fx, fy = ax + s * ex, ay + s * ey
    dist = np.hypot(fx - x, fy - y)
    ang = np.arctan2(fy - y, fx - x)
    inc = math.radians(sonar.plane_incidence_deg)
    ok = (s > 0.02) & (s < 0.98) & (dist > 0.05) & (dist < sonar.max_range_plane)
    ok &= np.abs(wrap_angles(ang - th)) < inc
    idx = np.flatnonzero(ok)
    if idx.size:
        vis = ~blocked((x, y), np.column_stack([fx[idx], fy[idx]]), segs, circles)
        for i in idx[vis]:
            cands.append(("plane", float(dist[i]), float(ang[i])))

    # concave corners
    reflectors: list[tuple[str, float, float, float, float]] = []  # kind, x, y, range, bearing
    if len(world.corners):
        cx, cy, cb = world.corners.T
        d = np.hypot(cx - x, cy - y)
        ang = np.arctan2(cy - y, cx - x)
        inside = np.abs(wrap_angles(np.arctan2(y - cy, x - cx) - cb)) < math.pi / 4
        ok = inside & (d < sonar.max_range_corner) & (d > 0.05)
        for i in np.flatnonzero(ok):
            reflectors.append(("corner", cx[i], cy[i], float(d[i]), float(ang[i])))

    # edges (point reflectors, possibly with radius) and pedestrians
    edges = world.edges
    if len(circles) > len(world.legs):
        peds = circles[len(world.legs) :]
        extra = np.column_stack([peds, np.zeros(len(peds)), np.full(len(peds), np.pi)])
        edges = np.vstack([edges, extra])
    if len(edges):
        px, py, pr, axis, hw = edges.T
        d = np.hypot(px - x, py - y) - pr
        ang = np.arctan2(py - y, px - x)
        facing = np.abs(wrap_angles(np.arctan2(y - py, x - px) - axis)) <= hw
        ok = facing & (d < sonar.max_range_edge) & (d > 0.05)
        for i in np.flatnonzero(ok):
            reflectors.append(("edge", px[i], py[i], float(d[i]), float(ang[i])))

    if reflectors:
        pts = np.array([(r[1], r[2]) for r in reflectors])
        # circles hide what is behind them but not themselves: test against walls and others
        vis = ~blocked((x, y), pts, segs, None)
        for (kind, _, _, rng_, brg), v in zip(reflectors, vis, strict=True):
            if v and abs(wrap_angle(brg - th)) < half:
                cands.append((kind, rng_, brg))
        cands.extend(_phantoms(world, reflectors, vis, (x, y, th), half, rng, params))

    echoes = []
    for kind, r, brg in sorted(cands, key=lambda c: c[1])[: params.max_echoes]:
        if rng.random() > params.detect_prob:
            continue
        if rng.random() < params.misclass_prob:
            kind = ("plane", "corner", "edge")[int(rng.integers(3))]
        r_meas = r * (1 + sound_bias) * (1 + rng.normal(0, params.sonar_range_sigma_rel))
        b_meas = wrap_angle_half_open(brg - th) + rng.normal(
            0, math.radians(params.sonar_bearing_sigma_deg)
        )
        echoes.append(SonarEcho(kind, float(r_meas), float(wrap_angle_half_open(b_meas))))
    return tuple(echoes)


def _phantoms(world, reflectors, visible, pose, half, rng, params):
    """Multiple reflections: a visible reflector heard via a specular bounce off a wall.
    The echo's apparent source is the reflector mirrored in the wall, i.e. behind the wall."""
    x, y, th = pose
    out = []
    segs = world.laser_segments
    for (kind, px, py, _, _), vis in zip(reflectors, visible, strict=True):
        if not vis or rng.random() > params.phantom_prob:
            continue
        # try one wall at random among those in front of the transducer
        k = int(rng.integers(len(segs)))
        ax, ay, bx, by = segs[k]
        ex, ey = bx - ax, by - ay
        L2 = ex * ex + ey * ey
        s = ((px - ax) * ex + (py - ay) * ey) / L2
        mx, my = 2 * (ax + s * ex) - px, 2 * (ay + s * ey) - py  # mirror image
        dist = math.hypot(mx - x, my - y)
        brg = math.atan2(my - y, mx - x)
        if dist > 2 * 6.0 or abs(wrap_angle(brg - th)) > half:
            continue
        # the bounce point is where the path to the image crosses the wall
        dx, dy = mx - x, my - y
        den = dx * ey - dy * ex
        if abs(den) < 1e-9:
            continue
        tt = ((ax - x) * ey - (ay - y) * ex) / den
        ss = ((ax - x) * dy - (ay - y) * dx) / den
        if not (0 < tt < 1 and 0.02 < ss < 0.98):
            continue
        bxp, byp = x + tt * dx, y + tt * dy
        others = np.delete(segs, k, axis=0)
        if blocked((x, y), np.array([[bxp, byp]]), others)[0]:
            continue
        if blocked((bxp, byp), np.array([[px, py]]), others)[0]:
            continue
        out.append((kind, dist, brg))
    return out
