"""Map reuse (issue 35): saved sessions, their occupancy grid, localization on them."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image

from fgslam.config import load_config
from fgslam.evaluation.metrics import interpolate_poses
from fgslam.events import TruthPose
from fgslam.io.formats import open_log
from fgslam.scanmatch import scan_points
from fgslam.session import Session, SessionError, load_session, save_session
from fgslam.session.grid import PIXEL_FREE, PIXEL_OCCUPIED, PIXEL_UNKNOWN
from fgslam.session.localize import Localizer
from fgslam.sim import simulate_to_log
from fgslam.sim.raycast import raycast
from fgslam.sim.scenes import BOX_ROOM
from fgslam.sim.world import load_world
from fgslam.slam.runner import run_backends

# -- a session of a box room: scans from known poses --------------------------------------


def _box_session(seed: int = 0, n: int = 6) -> Session:
    cfg = load_config(None)
    bearings = cfg.laser.bearings
    segs = np.asarray(BOX_ROOM, dtype=float)
    rng = np.random.default_rng(seed)
    poses = np.column_stack(
        [rng.uniform(1, 7, n), rng.uniform(1, 4, n), rng.uniform(-math.pi, math.pi, n)]
    )
    scans = []
    for p in poses:  # the laser at the robot's origin (laser_xy 0, 0 below)
        r = raycast(p[:2], p[2] + bearings, segs)
        scans.append(scan_points(r + rng.normal(0, 0.005, r.shape), bearings, max_range=20.0))
    covs = np.tile(np.diag([1e-4, 1e-4, 1e-5]), (n, 1, 1))
    covs[0] = np.nan  # a keyframe without a covariance
    scans[2] = None  # and one without a laser scan
    return Session(
        times=np.arange(n) * 1.5,
        poses=poses,
        covs=covs,
        scans=scans,
        laser_xy=(0.0, 0.0),
        config=cfg.to_dict(),
        landmarks=[{"id": 3, "kind": "line", "mean": [1.0, 0.5], "cov": [[1e-4, 0], [0, 1e-4]]}],
        constraints=[
            {"kind": "loop", "from": 0, "to": 4, "pose": [1.0, 2.0, 0.1], "cov": np.eye(3).tolist()}
        ],
        calibration=None,
        meta={"log": "box"},
    )


def _read_yaml(path) -> dict:
    """map_server's map.yaml as a small reader sees it (key: value per line)."""
    out = {}
    for line in path.read_text().splitlines():
        k, _, v = line.partition(":")
        v = v.strip()
        out[k.strip()] = json.loads(v) if v[:1] in "[0123456789-" else v
    return out


def test_a_session_reads_back_as_saved(tmp_path):
    s = _box_session()
    save_session(s, tmp_path / "map")
    r = load_session(tmp_path / "map")
    assert np.array_equal(r.times, s.times) and np.array_equal(r.poses, s.poses)
    assert np.array_equal(r.covs, s.covs, equal_nan=True)
    assert r.scans[2] is None
    for a, b in zip(r.scans, s.scans, strict=True):
        assert (a is None and b is None) or np.array_equal(a, b)
    assert r.landmarks == s.landmarks and r.constraints == s.constraints
    assert r.config == json.loads(json.dumps(s.config)) and r.meta == s.meta
    assert r.robot_config().laser.n_beams == load_config(None).laser.n_beams


def test_the_grid_is_a_map_server_map_of_the_room(tmp_path):
    """map.pgm (P5) and map.yaml read by standard readers (Pillow; key: value): the walls
    occupied, the room's inside free, outside the walls unknown."""
    save_session(_box_session(n=10), tmp_path / "map")
    img = np.array(Image.open(tmp_path / "map" / "map.pgm"))
    meta = _read_yaml(tmp_path / "map" / "map.yaml")
    assert meta["image"] == "map.pgm" and meta["mode"] == "trinary" and meta["negate"] == 0
    res, (ox, oy, _) = meta["resolution"], meta["origin"]
    rows = img.shape[0]

    def pixel(x, y):
        return img[rows - 1 - int((y - oy) // res), int((x - ox) // res)]

    # walls: along the room's four sides, most cells occupied
    wall = [pixel(x, 0.0 + 0.01) for x in np.arange(0.5, 7.5, 0.1)]
    wall += [pixel(8.0 - 0.01, y) for y in np.arange(0.5, 4.5, 0.1)]
    assert np.mean(np.array(wall) == PIXEL_OCCUPIED) > 0.8
    inside = [  # away from the pillar, whose shadow may be unseen
        pixel(x, y)
        for x in np.arange(1.0, 7.0, 0.25)
        for y in (1.0, 2.0, 4.0)
        if math.hypot(x - 3.25, y - 2.75) > 1.5
    ]
    assert np.mean(np.array(inside) == PIXEL_FREE) > 0.9
    assert set(np.unique(img)) <= {PIXEL_FREE, PIXEL_OCCUPIED, PIXEL_UNKNOWN}
    assert pixel(ox + 0.5 * res, oy + 0.5 * res) == PIXEL_UNKNOWN  # beyond the walls


def test_a_newer_or_corrupt_session_is_refused_by_name(tmp_path):
    save_session(_box_session(), tmp_path / "map")
    index = tmp_path / "map" / "session.json"
    data = json.loads(index.read_text())
    data["version"] = 99
    index.write_text(json.dumps(data))
    with pytest.raises(SessionError, match="newer fgslam"):
        load_session(tmp_path / "map")
    save_session(_box_session(), tmp_path / "b")
    npz = tmp_path / "b" / "scans.npz"
    raw = bytearray(npz.read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    npz.write_bytes(bytes(raw))
    with pytest.raises(SessionError, match="corrupt"):
        load_session(tmp_path / "b")
    (tmp_path / "c").mkdir()
    (tmp_path / "c" / "session.json").write_text("{not json")
    with pytest.raises(SessionError, match="corrupt"):
        load_session(tmp_path / "c")
    with pytest.raises(SessionError, match="no such session"):
        load_session(tmp_path / "nowhere")


def test_saving_never_overwrites_what_is_not_a_session(tmp_path):
    s = _box_session()
    other = tmp_path / "work"
    other.mkdir()
    (other / "notes.txt").write_text("mine")
    with pytest.raises(SessionError, match="not overwritten"):
        save_session(s, other)
    assert [p.name for p in other.iterdir()] == ["notes.txt"]
    newer = tmp_path / "newer"
    save_session(s, newer)
    data = json.loads((newer / "session.json").read_text())
    data["version"] = 99
    (newer / "session.json").write_text(json.dumps(data))
    before = {p.name: p.read_bytes() for p in newer.iterdir()}
    with pytest.raises(SessionError, match="not overwritten"):
        save_session(s, newer)
    assert {p.name: p.read_bytes() for p in newer.iterdir()} == before
    # a session of ours is replaced, and nothing of the writing is left beside it
    ok = tmp_path / "ok"
    save_session(_box_session(seed=1), ok)
    save_session(s, ok)
    assert np.array_equal(load_session(ok).poses, s.poses)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["newer", "ok", "work"]


# -- localization on the simulated corridor --------------------------------------------------


@pytest.fixture(scope="module")
def corridor(tmp_path_factory):
    """A map of the corridor world's first 150 s (seed 1, laser iSAM2, saved and read back)
    and another run of it (seed 2) as a log."""
    d = tmp_path_factory.mktemp("corridor")
    cfg = load_config(None)
    world = load_world("corridor")
    simulate_to_log(world, cfg, d / "map.log.gz", seed=1, duration=150.0)
    simulate_to_log(world, cfg, d / "run.log.gz", seed=2, duration=150.0)
    res = run_backends(open_log(d / "map.log.gz"), cfg, ["isam2"], "laser")[0]
    save_session(Session.from_result(res, cfg), d / "session")
    return load_session(d / "session"), list(open_log(d / "run.log.gz")), cfg


def _truth(events):
    tr = np.array([(e.t, e.x, e.y, e.theta) for e in events if isinstance(e, TruthPose)])
    return tr


def test_the_session_holds_the_run(corridor):
    s, _, _ = corridor
    assert s.keyframes > 20 and sum(p is not None for p in s.scans) == s.keyframes
    kinds = {c["kind"] for c in s.constraints}
    assert "scan" in kinds
    assert all(np.shape(c["cov"]) == (3, 3) for c in s.constraints)


@pytest.mark.parametrize("start", [20.0, 70.0, 100.0])
def test_global_localization_finds_the_robot_anywhere_on_the_path(corridor, start):
    """No initial pose, the log started part way: localized (the lab is symmetric under a
    half turn but for its door: it may take the robot a lap's part to see it), then every
    localized scan within 5 cm and 1 deg of the truth (target: 0.2 m, 3 deg); and every
    scan, those before the localization carried back to it by the wheels,
    within 0.2 m (seen: 0.13)."""
    s, events, cfg = corridor
    loc = Localizer(s, cfg)
    for e in events:
        if e.t >= start:
            loc.add(e)
    res = loc.finish()
    rep = res.report()
    assert rep["localized"]
    assert rep["first_localization"]["how"] == "global search"
    err = rep["error_vs_truth"]
    assert err["position_max_m"] < 0.05 and err["heading_max_deg"] < 1.0
    assert rep["scans_localized"] >= 20
    tr = _truth(events)
    all_poses = res.bridged()
    assert np.isfinite(all_poses).all() and rep["scans_bridged"] > 0
    x = np.interp(res.times, tr[:, 0], tr[:, 1])
    y = np.interp(res.times, tr[:, 0], tr[:, 2])
    assert np.hypot(all_poses[:, 0] - x, all_poses[:, 1] - y).max() < 0.2


def test_a_kidnapped_robot_is_found_again(corridor):
    """The log cut from 60 s to 100 s (the robot carried away: its odometry says it stood
    still): lost, searched for, localized again; the poses after within 5 cm."""
    s, events, cfg = corridor
    first = [e for e in events if e.t < 60.0]
    later = [e for e in events if e.t >= 100.0]
    from dataclasses import replace

    jumped = first + [replace(e, t=e.t - 40.0) for e in later]
    loc = Localizer(s, cfg)
    for e in jumped:
        loc.add(e)
    res = loc.finish()
    rep = res.report()
    assert rep["lost"] and rep["relocalizations"] >= 1
    back = [e for e in rep["events"] if e["event"] == "localized" and e["t"] > 60.0]
    assert back and back[0]["t"] < 60.0 + 30.0
    # after the relocalization every localized pose is right again
    ok = (res.times > back[0]["t"]) & np.isfinite(res.poses).all(axis=1)
    tr = _truth(jumped)
    x = np.interp(res.times[ok], tr[:, 0], tr[:, 1])
    y = np.interp(res.times[ok], tr[:, 0], tr[:, 2])
    assert np.hypot(res.poses[ok, 0] - x, res.poses[ok, 1] - y).max() < 0.05
    # and nothing wrong was reported while it was lost: no pose between lost and found
    lost_t = rep["lost"][0]["t"]
    gap = (res.times > lost_t + 1e-3) & (res.times < back[0]["t"] - 1e-3)  # (rounded times)
    assert not np.isfinite(res.poses[gap]).any()


def test_a_wrong_initial_pose_is_found_wrong(corridor):
    """An initial pose 1.5 m off: its matches fail, it is lost, and the global search finds
    the robot."""
    s, events, cfg = corridor
    tr = _truth(events)
    start = tr[np.searchsorted(tr[:, 0], 30.0)]
    loc = Localizer(s, cfg, (start[1] + 1.5, start[2], start[3]))
    for e in events:
        if e.t >= 30.0:
            loc.add(e)
    rep = loc.finish().report()
    assert rep["lost"]
    assert any(e["how"] == "global search" for e in rep["events"] if e["event"] == "localized")
    assert rep["error_vs_truth"]["position_max_m"] < 0.05 + 1.5  # the first guesses included


def test_cli_run_save_then_localize(tmp_path, corridor, capsys):
    from fgslam.cli import main

    log = tmp_path / "short.log.gz"
    simulate_to_log(load_world("corridor"), load_config(None), log, seed=3, duration=40.0)
    argv = ["run", str(log), "--sensors", "laser", "--out", str(tmp_path / "o")]
    assert main([*argv, "--save", str(tmp_path / "m")]) == 0
    assert {p.name for p in (tmp_path / "m").iterdir()} == {
        "session.json",
        "scans.npz",
        "map.pgm",
        "map.yaml",
    }
    assert (
        main(["localize", str(log), "--map", str(tmp_path / "m"), "--out", str(tmp_path / "l")])
        == 0
    )
    rep = json.loads((tmp_path / "l" / "report.json").read_text())
    assert rep["localized"] and rep["error_vs_truth"]["position_rmse_m"] < 0.03
    assert (tmp_path / "l" / "trajectory.tum").stat().st_size > 0
    assert (tmp_path / "l" / "map.png").stat().st_size > 0


def test_cli_refuses_bad_sessions_in_one_line(tmp_path, one_line_error):
    log = tmp_path / "s.log.gz"
    simulate_to_log(load_world("corridor"), load_config(None), log, seed=3, duration=5.0)
    one_line_error(
        ["localize", str(log), "--map", str(tmp_path / "none"), "--out", "o"], "no such session"
    )
    one_line_error(
        ["online", "--laser", "/dev/null", "--map", str(tmp_path / "none"), "--out", "o"],
        "no such session",
    )
    (tmp_path / "x").mkdir()
    (tmp_path / "x" / "keep.txt").write_text("mine")
    one_line_error(
        ["run", str(log), "--out", "o", "--save", str(tmp_path / "x")], "not overwritten"
    )
    assert (tmp_path / "x" / "keep.txt").read_text() == "mine"


def test_online_localization_on_emulated_devices(corridor, tmp_path):
    """``fgslam online --map``'s loop: the corridor's devices emulated on pseudo-terminals
    (seed 2, 40 s at 3x), localized on the saved map from no initial pose; the last pose
    within 0.15 m and 2 deg of the simulated run's last true pose (the last scan and the end
    of the run are up to a scan period apart, 0.1 m at its speed)."""
    from fgslam.online.device_process import DeviceProcess, EmulationSpec
    from fgslam.online.loop import run_online

    s, _, cfg = corridor
    spec = EmulationSpec("corridor", seed=2, duration=40.0)
    lines: list[str] = []
    dev = DeviceProcess(
        cfg, speed=3.0, record_dir=tmp_path / "raw", world="corridor", emulation=spec
    )
    with dev:
        run = run_online(dev, cfg, idle_timeout=1.5, on_status=lines.append, session=s)
    res = run.result
    rep = res.report()
    assert rep["localized"] and not rep["lost"], (rep["events"], rep["stats"], lines[-3:])
    assert any(line.startswith("localized |") for line in lines)
    log = tmp_path / "sim.log"
    simulate_to_log(load_world("corridor"), cfg, log, seed=2, duration=40.0)
    end = _truth(list(open_log(log)))[-1]
    last = res.poses[np.isfinite(res.poses).all(axis=1)][-1]
    assert math.hypot(last[0] - end[1], last[1] - end[2]) < 0.15, (last, end)
    assert abs(math.degrees(math.remainder(last[2] - end[3], 2 * math.pi))) < 2.0


# -- fuzz: a session folder is read or refused with one SessionError ------------------------

_INDEX_VALUES = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(2**63), 2**63),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=8),
    st.lists(st.integers(-3, 3), max_size=3),
    st.dictionaries(st.text(max_size=4), st.integers(), max_size=2),
)


def _outcome(folder) -> str:
    """'loaded' or 'refused' (one SessionError); any other exception or warning fails."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        try:
            load_session(folder)
        except SessionError as e:
            assert str(e) and "\n" not in str(e)
            return "refused"
    return "loaded"


@settings(max_examples=60, deadline=None)
@given(
    key=st.sampled_from(
        [
            "format",
            "version",
            "keyframes",
            "scans_sha256",
            "config",
            "landmarks",
            "constraints",
            "meta",
        ]
    ),
    value=_INDEX_VALUES,
)
def test_fuzz_session_index(key, value):
    """session.json with one entry replaced by a hostile value (or removed)."""
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        save_session(_box_session(n=3), f"{d}/s")
        index = json.loads(open(f"{d}/s/session.json").read())
        if value is None:
            index.pop(key)
        else:
            index[key] = value
        open(f"{d}/s/session.json", "w").write(json.dumps(index))
        _outcome(f"{d}/s")


@settings(max_examples=60, deadline=None)
@given(
    name=st.sampled_from(["times", "poses", "covs", "points", "offsets", "has_scan", "laser_xy"]),
    shape=st.lists(st.integers(0, 5), min_size=0, max_size=3),
    fill=st.sampled_from([0.0, -1.0, 1e300, float("nan"), float("inf"), 7.0]),
    dtype=st.sampled_from(["f8", "i8", "u1", "b1", "U3"]),
)
def test_fuzz_session_arrays(name, shape, fill, dtype):
    """scans.npz with one array replaced by one of another shape, type or value, its
    checksum updated (a corrupt file with a stale checksum is refused by it already)."""
    import hashlib
    import io
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        save_session(_box_session(n=3), f"{d}/s")
        with np.load(f"{d}/s/scans.npz") as z:
            arrays = {k: z[k] for k in z.files}
        with np.errstate(invalid="ignore"):  # (the hostile array itself: NaN to integers)
            bad = np.full(shape, fill).astype(dtype) if dtype != "U3" else np.full(shape, "x")
        arrays[name] = bad
        buf = io.BytesIO()
        np.savez(buf, **arrays)
        data = buf.getvalue()
        open(f"{d}/s/scans.npz", "wb").write(data)
        index = json.loads(open(f"{d}/s/session.json").read())
        index["scans_sha256"] = hashlib.sha256(data).hexdigest()
        open(f"{d}/s/session.json", "w").write(json.dumps(index))
        _outcome(f"{d}/s")


def _result(poses, odometry, times=None):
    from fgslam.session.localize import LocalizationResult

    n = len(poses)
    return LocalizationResult(
        times=np.arange(n, dtype=float) if times is None else times,
        poses=poses,
        matched=np.isfinite(poses).all(axis=1),
        odometry=odometry,
        events=[],
        stats={},
        truth_t=np.zeros(0),
        truth=np.zeros((0, 3)),
        wall_time=1.0,
        log_duration=1.0,
        places=1,
    )


def test_bridging_the_gaps_between_localized_scans():
    """Odometry that is the truth in another frame bridges every gap exactly (before the
    first localized scan, between two, after the last); odometry with a heading bias
    meets both ends of a gap, its error spread between them (smaller than carried from one
    side)."""
    from factors.geometry import between_poses, compose_poses

    rng = np.random.default_rng(3)
    truth = np.zeros((40, 3))
    for i in range(1, 40):
        truth[i] = compose_poses(truth[i - 1], [0.3, 0.0, rng.normal(0, 0.2)])
    other = compose_poses(np.tile([5.0, -2.0, 1.0], (40, 1)), truth)  # another frame
    poses = truth.copy()
    poses[:4] = poses[10:25] = poses[33:] = np.nan
    got = _result(poses, other).bridged()
    assert np.allclose(got, truth, atol=1e-9)
    # a heading bias of 0.02 rad per step: the gap's ends meet, its middle is off less than
    # the one-sided carry would be
    biased = truth.copy()
    for i in range(1, 40):
        d = between_poses(truth[i - 1], truth[i]) + np.array([0.0, 0.0, 0.02])
        biased[i] = compose_poses(biased[i - 1], d)
    got = _result(poses, biased).bridged()
    one_side = compose_poses(
        np.tile(truth[9], (15, 1)), between_poses(np.tile(biased[9], (15, 1)), biased[10:25])
    )
    mid_err = np.hypot(*(got[10:25, :2] - truth[10:25, :2]).T)
    one_err = np.hypot(*(one_side[:, :2] - truth[10:25, :2]).T)
    assert mid_err.max() < 0.6 * one_err.max()
    assert np.allclose(got[~np.isnan(poses[:, 0])], truth[~np.isnan(poses[:, 0])])
    # nothing localized: nothing to bridge from
    assert np.isnan(_result(np.full((3, 3), np.nan), other[:3]).bridged()).all()


def test_a_session_without_scans_is_refused_for_localization(tmp_path):
    s = _box_session(n=3)
    s.scans = [None, None, None]
    with pytest.raises(SessionError, match="no keyframe with a laser scan"):
        Localizer(s, load_config(None))


def test_fused_motion_is_as_good_as_its_better_source(corridor):
    """The localizer's scan-to-scan motion on the corridor run (60 s), each second's against
    the truth's: the wheels and the scan odometry fused by their covariances move no worse
    than the better of the two in position, and better than the wheels in heading (the scan
    odometry alone is better still in heading here, worse in position: along the bare
    corridor)."""
    from factors.geometry import between_poses, wrap_angles
    from fgslam.config.robot import KeyframeParams
    from fgslam.events import OdometryEvent
    from fgslam.frontend.pipeline import FrontEnd
    from fgslam.scanmatch import MatchParams
    from fgslam.slam.keyframes import FusedMotion, ScanOdometry

    _, events, cfg = corridor
    events = [e for e in events if e.t < 60.0]
    kp, mp = KeyframeParams.from_config(cfg), MatchParams.from_config(cfg)
    origin = (cfg.laser.mount.x, cfg.laser.mount.y)
    fm = {
        fuse: FusedMotion(ScanOdometry(kp, mp, origin), cfg.odometry.params(), 0.999, fuse)
        for fuse in (True, False)
    }
    rows = []

    def select(t, points, odom, v=0.0, w=0.0):
        rows.append((t, *odom, *(fm[f].add(t, points, odom, (v, w)) for f in (True, False))))
        return False

    fe = FrontEnd(cfg, "laser", select=select)
    for e in events:
        if isinstance(e, OdometryEvent):
            sample = (e.t, *cfg.odometry.wheel_travel(e.ticks_right, e.ticks_left))
            for f in fm.values():
                f.sample(*sample)
        fe.add(e)
    t = np.array([r[0] for r in rows])
    wheels = np.array([r[1:4] for r in rows])
    fused = np.array([r[4] for r in rows])
    scan = np.array([r[5] for r in rows])
    tr = _truth(events)
    truth = interpolate_poses(tr[:, 0], tr[:, 1:], t)
    i = np.arange(0, len(t) - 10, 10)  # one second apart

    def err(p):
        d = between_poses(p[i], p[i + 10])
        g = between_poses(truth[i], truth[i + 10])
        return np.sqrt(np.mean(np.degrees(wrap_angles(d[:, 2] - g[:, 2])) ** 2))

    def err_xy(p):
        d = between_poses(p[i], p[i + 10])
        g = between_poses(truth[i], truth[i + 10])
        return np.sqrt(np.mean(np.sum((d[:, :2] - g[:, :2]) ** 2, axis=1)))

    # (seen: position 5.7 / 6.4 / 8.4 mm, heading 0.41 / 0.62 / 0.20 deg per second)
    assert err_xy(fused) <= 1.05 * min(err_xy(wheels), err_xy(scan))
    assert err(fused) < err(wheels)
