"""Simulator geometry: ray casting against analytic intersections, laser and sonar rules."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from fgslam.config import load_config
from fgslam.sim.raycast import blocked, raycast
from fgslam.sim.scenes import NO_CLUTTER, NO_LASER_BIAS
from fgslam.sim.sensors import SimParams, laser_scan, sonar_echoes
from fgslam.sim.world import WorldError, load_world, parse_world

EXACT = SimParams(
    laser_sigma=0.0,
    sonar_bearing_sigma_deg=0.0,
    sonar_range_sigma_rel=0.0,
    detect_prob=1.0,
    **NO_LASER_BIAS,
    **NO_CLUTTER,
)
CFG = load_config()


def world(**kw):
    data = {"name": "test", "walls": kw.pop("walls", [{"id": "w", "points": [[50, 50], [51, 50]]}])}
    data.update(kw)
    return parse_world(data, "<test>")


def echoes(w, pose, t=0.0, params=EXACT):
    return sonar_echoes(w, CFG.sonar, params, pose, t, np.random.default_rng(0), 0.0)


def test_raycast_segments_against_analytic(rng):
    for _ in range(300):
        o = rng.uniform(-5, 5, 2)
        seg = rng.uniform(-5, 5, 4)
        ang = rng.uniform(-math.pi, math.pi)
        d = np.array([math.cos(ang), math.sin(ang)])
        # solve o + t d = a + s (b - a) directly
        A = np.column_stack([d, -(seg[2:] - seg[:2])])
        if abs(np.linalg.det(A)) < 1e-9:
            continue
        t, s = np.linalg.solve(A, seg[:2] - o)
        expect = t if (t > 0 and 0 <= s <= 1) else np.inf
        got = raycast(tuple(o), np.array([ang]), seg[None, :])[0]
        assert got == pytest.approx(expect, rel=1e-9, abs=1e-9)


def test_raycast_circles_and_nearest_hit():
    circles = np.array([[3.0, 0.0, 0.5], [6.0, 0.0, 0.5]])
    segs = np.array([[5.0, -1, 5.0, 1]])
    r = raycast((0.0, 0.0), np.array([0.0, math.pi, 0.1, 0.19]), segs, circles)
    assert r[0] == pytest.approx(2.5)
    assert r[1] == math.inf
    b = 3 * math.cos(0.1)  # analytic: t = b - sqrt(b^2 - (|c|^2 - r^2))
    assert r[2] == pytest.approx(b - math.sqrt(b * b - (9 - 0.25)), rel=1e-12)
    assert r[3] == pytest.approx(5.0 / math.cos(0.19))  # misses the circle, hits the wall
    # origin inside a circle does not see it
    assert raycast((3.0, 0.0), np.array([0.0]), segs, circles)[0] == pytest.approx(2.0)
    assert blocked((0, 0), np.array([[6.0, 0.0], [4.0, 0.0], [2.0, 3.0]]), segs).tolist() == [
        True,
        False,
        False,
    ]


def test_laser_sees_wall_quantised_and_not_glass():
    w = world(
        walls=[{"id": "w", "points": [[3, -10], [3, 10]]}],
        glass=[{"points": [[1.5, -10], [1.5, 10]]}],
    )
    r = laser_scan(w, CFG.laser, EXACT, (0.0, 0.0, 0.0), 0.0, np.random.default_rng(0))
    b = CFG.laser.bearings
    front = np.abs(b) < math.atan2(10, 3) - 0.01
    expect = np.round(3 / np.cos(b[front]) / 0.05) * 0.05
    expect[expect > CFG.laser.max_range] = np.nan
    np.testing.assert_allclose(r[front], expect, atol=1e-9)
    assert np.all(np.isnan(r[np.abs(b) > math.atan2(10, 3) + 0.01]))  # beyond the wall's end
    assert np.allclose(r / 0.05, np.round(r / 0.05), equal_nan=True)


def test_laser_mixed_pixels_at_discontinuity():
    w = world(
        walls=[{"id": "w", "points": [[4, -10], [4, 10]]}], legs=[{"x": 2, "y": 0, "radius": 0.1}]
    )
    p = dataclasses.replace(EXACT, mixed_pixel_prob=1.0)
    r = laser_scan(w, CFG.laser, p, (0.0, 0.0, 0.0), 0.0, np.random.default_rng(1))
    between = (r > 2.0) & (r < 3.9)
    assert 1 <= between.sum() <= 4  # the footprints straddling the leg's silhouette
    r0 = laser_scan(w, CFG.laser, EXACT, (0.0, 0.0, 0.0), 0.0, np.random.default_rng(1))
    assert not np.any((r0 > 2.0) & (r0 < 3.9))


def test_laser_grazing_wall_is_one_surface_not_mixed_pixels():
    # a wall seen at grazing angles spans more depth than the mixed-pixel jump across a
    # footprint, but is one surface: the PLS reads it, not a range in between
    w = world(walls=[{"id": "w", "points": [[-20, 1], [20, 1]]}])
    p = dataclasses.replace(EXACT, mixed_pixel_prob=1.0)
    lc = dataclasses.replace(CFG.laser, range_resolution=1e-6, max_range=80.0)
    r = laser_scan(w, lc, p, (0.0, 0.0, 0.0), 0.0, np.random.default_rng(3))
    b = lc.bearings
    seen = (b > 0.06) & (b < math.pi / 2 - 0.06)
    depth = 1 / np.sin(b - math.radians(0.25)) - 1 / np.sin(b + math.radians(0.25))
    assert np.sum(seen & (depth > p.mixed_pixel_jump)) > 5  # the case is exercised
    np.testing.assert_allclose(r[seen], 1 / np.sin(b[seen]), atol=2e-6)


def test_sonar_plane_only_near_normal_incidence():
    w = world(walls=[{"id": "w", "points": [[-5, 2], [5, 2]]}])
    e = echoes(w, (0.0, 0.0, math.pi / 2))
    planes = [x for x in e if x.kind == "plane"]
    assert len(planes) == 1
    assert planes[0].range == pytest.approx(2.0) and planes[0].bearing == pytest.approx(0.0)
    inc = math.radians(CFG.sonar.plane_incidence_deg)
    e = echoes(w, (0.0, 0.0, math.pi / 2 + inc - 0.01))
    assert [x.bearing for x in e if x.kind == "plane"] == [pytest.approx(-(inc - 0.01))]
    assert not [x for x in echoes(w, (0.0, 0.0, math.pi / 2 + inc + 0.01)) if x.kind == "plane"]


def test_sonar_nothing_through_walls_and_glass_heard():
    w = world(
        walls=[{"id": "far", "points": [[-5, 3], [5, 3]]}],
        glass=[{"points": [[-5, 2], [5, 2]]}],
        legs=[{"x": 0.0, "y": 2.5, "radius": 0.02}],
    )
    e = echoes(w, (0.0, 0.0, math.pi / 2))
    assert [(x.kind, round(x.range, 6)) for x in e] == [("plane", 2.0)]
    # and the laser sees the leg and the wall behind the glass
    r = laser_scan(w, CFG.laser, EXACT, (0.0, 0.0, math.pi / 2), 0.0, np.random.default_rng(0))
    assert np.nanmin(r) == pytest.approx(2.5, abs=0.05)


def test_sonar_concave_corner_inside_quadrant_and_convex_edge_outside():
    w = world(walls=[{"id": "L", "points": [[2, -3], [2, 2], [-3, 2]]}])
    assert len(w.corners) == 1
    e = echoes(w, (0.0, 0.0, math.pi / 4))
    corners = [x for x in e if x.kind == "corner"]
    assert len(corners) == 1 and corners[0].range == pytest.approx(2 * math.sqrt(2))
    assert corners[0].bearing == pytest.approx(0.0, abs=1e-9)
    # from outside the walls the vertex is a convex corner: an edge
    e = echoes(w, (4.0, 4.0, -3 * math.pi / 4))
    assert [x.kind for x in e] == ["edge"]
    assert e[0].range == pytest.approx(2 * math.sqrt(2))


def test_sonar_edges_only_inside_beam_and_range():
    w = world(legs=[{"x": 2.0, "y": 0.0, "radius": 0.02}])
    half = math.radians(CFG.sonar.beam_half_width_deg)
    assert [x.kind for x in echoes(w, (0.0, 0.0, half - 0.01))] == ["edge"]
    assert echoes(w, (0.0, 0.0, half + 0.01)) == ()
    e = echoes(w, (0.0, 0.0, 0.0))[0]
    assert e.range == pytest.approx(1.98) and e.bearing == pytest.approx(0.0)
    far = world(legs=[{"x": CFG.sonar.max_range_edge + 0.5, "y": 0.0}])
    assert echoes(far, (0.0, 0.0, 0.0)) == ()


def test_sonar_phantom_appears_behind_wall():
    # an edge at (1, 1) near a wall y = 2: its mirror image (1, 3) lies behind the wall
    w = world(walls=[{"id": "w", "points": [[-5, 2], [5, 2]]}], legs=[{"x": 1.0, "y": 1.0}])
    p = dataclasses.replace(EXACT, phantom_prob=1.0)
    found = set()
    for seed in range(20):  # the bounce wall is drawn at random among the walls
        e = sonar_echoes(
            w, CFG.sonar, p, (0.0, 0.0, math.atan2(3, 1)), 0.0, np.random.default_rng(seed), 0.0
        )
        found |= {round(x.range, 6) for x in e}
    assert round(math.hypot(1, 3), 6) in found  # the phantom: farther than the wall (2 m)


def test_corridor_world_contents():
    w = load_world("corridor")
    xmin, xmax, ymin, ymax = w.bounds()
    assert xmax - xmin >= 60 - 1e-9 and 6.9 < (ymax - ymin)
    assert len(w.corners) > 20  # recessed doors, doorway, alcoves
    assert len(w.legs) >= 8 and len(w.glass) >= 1 and len(w.pedestrians) >= 3
    assert len(w.mouldings) >= 10


def test_corridor_oneway_steps_seen_by_the_laser_one_way_and_by_sonar_both_ways():
    """The second world (issue 15, section 5): each step's face is seen by the forward laser
    only when driving toward -x; the step's convex edge is heard by the sonar from both
    directions; no 20 cm door recess or alcove is left."""
    w = load_world("corridor-oneway")
    ref = load_world("corridor")
    assert len(w.corners) < len(ref.corners)
    rng = np.random.default_rng(0)
    m = CFG.laser.mount
    for x_step, y0, y1 in ((-15.0, 9.2, 9.4), (5.0, 9.4, 9.6), (22.0, 7.0, 7.2)):
        for heading, ahead in ((math.pi, -1), (0.0, 1)):  # toward -x: face seen
            x = x_step - ahead * 3.0  # 3 m before the step, driving toward it
            pose = (x + math.cos(heading) * m.x, 8.2, heading)
            r = laser_scan(w, CFG.laser, EXACT, pose, 0.0, rng)
            a = heading + CFG.laser.bearings
            px, py = pose[0] + r * np.cos(a), pose[1] + r * np.sin(a)
            on_face = np.abs(px - x_step) < 0.03
            on_face &= (py > min(y0, y1) + 0.02) & (py < max(y0, y1) - 0.02)
            assert (np.sum(on_face) > 0) == (heading == math.pi), (x_step, heading)
            edge_y = 9.2 if x_step == -15.0 else (9.4 if x_step == 5.0 else 7.2)
            dy = edge_y - 8.2
            sp = (x, 8.2, math.atan2(dy, x_step - x))  # a transducer pointed at the edge
            heard = [e for e in echoes(w, sp) if e.kind == "edge"]
            assert any(abs(e.range - math.hypot(x_step - x, dy)) < 0.02 for e in heard)


@pytest.mark.parametrize(
    "data, msg",
    [
        ({"walls": []}, "missing key 'name'"),
        ({"name": "x", "walls": [{"id": "a", "points": [[0, 0]]}]}, "walls[0] ('a').points"),
        (
            {"name": "x", "walls": [{"id": "a", "points": [[0, 0], [1, "y"]]}]},
            "walls[0] ('a').points[1]",
        ),
        (
            {
                "name": "x",
                "walls": [{"id": "a", "points": [[0, 0], [1, 0]]}],
                "doors": [{"wall": "b", "at": 0, "width": 1}],
            },
            "doors[0]: unknown wall 'b'",
        ),
        (
            {"name": "x", "walls": [{"id": "a", "points": [[0, 0], [1, 0]]}], "legs": [{"x": 1}]},
            "legs[0]: missing key 'y'",
        ),
        (
            {"name": "x", "walls": [{"id": "a", "points": [[0, 0], [1, 0]]}], "sofas": []},
            "unknown key 'sofas'",
        ),
        (
            {
                "name": "x",
                "walls": [{"id": "a", "points": [[0, 0], [5, 0]]}],
                "doors": [{"wall": "a", "at": 4.5, "width": 1}],
            },
            "doors[0]: door overlaps",
        ),
        (
            {
                "name": "x",
                "walls": [{"id": "a", "points": [[0, 0], [1, 0]]}],
                "pedestrians": [{"path": [[0, 0], [1, 1]], "speed": -1}],
            },
            "pedestrians[0].speed",
        ),
    ],
)
def test_invalid_world_names_element(data, msg):
    with pytest.raises(WorldError) as exc:
        parse_world(data, "w.json")
    assert msg in str(exc.value) and "w.json" in str(exc.value)


def test_world_file_errors(tmp_path):
    p = tmp_path / "w.json"
    p.write_text("{not json")
    with pytest.raises(WorldError, match="not valid JSON"):
        load_world(p)
    with pytest.raises(WorldError, match="cannot read"):
        load_world(tmp_path / "missing.json")


def test_recessed_door_makes_corners_and_flush_door_frames():
    base = {"name": "x", "walls": [{"id": "a", "points": [[0, 0], [10, 0]]}]}
    door = {"wall": "a", "at": 4, "width": 1, "recess": 0.2, "side": "right"}
    w = parse_world({**base, "doors": [door]}, "t")
    assert len(w.corners) == 4  # a free-standing wall: every right angle has a concave side
    # in a closed room (counter-clockwise, door recessed outward) only the back of the
    # recess is concave; its front vertices are convex edges
    room = {
        "name": "x",
        "walls": [{"id": "a", "points": [[0, 0], [10, 0], [10, 5], [0, 5]], "closed": True}],
    }
    w = parse_world({**room, "doors": [door]}, "t")
    back = w.corners[w.corners[:, 1] < -0.1]
    np.testing.assert_allclose(sorted(back[:, 0]), [4.0, 5.0])
    assert len(w.corners) == 6  # 4 room corners + 2 at the back of the recess
    front = w.edges[(np.abs(w.edges[:, 1]) < 1e-9) & (w.edges[:, 2] == 0)]
    np.testing.assert_allclose(sorted(front[:, 0]), [4.0, 5.0])
    # the concave bisectors point into the room/recess
    for x, y, a in w.corners:
        assert 0 < x + 0.1 * math.cos(a) < 10 and -0.2 < y + 0.1 * math.sin(a) < 5
    w2 = parse_world({**base, "doors": [{"wall": "a", "at": 4, "width": 1}]}, "t")
    assert len(w2.corners) == 0 and len(w2.mouldings) == 2
    w3 = parse_world({**base, "doors": [{"wall": "a", "at": 4, "width": 1, "open": True}]}, "t")
    assert len(w3.polylines) == 2


def test_true_feature_map():
    room = {
        "name": "x",
        "walls": [{"id": "a", "points": [[0, 0], [10, 0], [10, 5], [0, 5]], "closed": True}],
    }
    door = {"wall": "a", "at": 4, "width": 1, "recess": 0.2, "side": "right"}
    fm = parse_world({**room, "doors": [door], "legs": [{"x": 3, "y": 3}]}, "t").feature_map()
    assert len(fm["lines"]) == 4 + 4  # the room's walls, the door's jambs and plane
    for line in fm["lines"]:
        (x1, y1), (x2, y2) = line["endpoints"]
        assert line["d"] >= 0
        for x, y in ((x1, y1), (x2, y2)):  # endpoints lie on the line
            assert x * math.cos(line["alpha"]) + y * math.sin(line["alpha"]) == pytest.approx(
                line["d"]
            )
    assert len(fm["corners"]) == 6
    assert {(p["x"], p["y"]) for p in fm["points"]} >= {(3.0, 3.0), (4.0, 0.0), (5.0, 0.0)}
