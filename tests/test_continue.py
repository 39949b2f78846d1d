"""Continuing a saved session with a new log (issue 35, item 3): the graph restored from the
session, the new log anchored on it, the two joined by loop closures and saved as one."""

from __future__ import annotations

import json
import math

import gtsam
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from factors.geometry import between_poses, compose_poses
from factors.odometry import relative_pose
from fgslam.config import load_config
from fgslam.evaluation.metrics import interpolate_poses
from fgslam.events import TruthPose
from fgslam.io.formats import open_log
from fgslam.session import Session, SessionError, load_session, save_session
from fgslam.session.join import Anchor, Continuation, find_anchor
from fgslam.sim import simulate_to_log
from fgslam.sim.world import load_world
from fgslam.slam.graph import GraphBackend
from fgslam.slam.graph_keys import X
from fgslam.slam.runner import run_backends

SPLIT = 100.0  # s: the log's first part is mapped, the rest continues it


@pytest.fixture(scope="module")
def halves(tmp_path_factory):
    """The corridor (seed 1, 200 s) cut at SPLIT: the first part mapped (laser iSAM2) and
    saved; the events of the second; the truth of the whole."""
    d = tmp_path_factory.mktemp("continue")
    cfg = load_config(None)
    simulate_to_log(load_world("corridor"), cfg, d / "whole.log.gz", seed=1, duration=200.0)
    events = list(open_log(d / "whole.log.gz"))
    first = run_backends([e for e in events if e.t < SPLIT], cfg, ["isam2"], "laser")[0]
    save_session(Session.from_result(first, cfg, {"log": "first"}), d / "map")
    truth = np.array([(e.t, e.x, e.y, e.theta) for e in events if isinstance(e, TruthPose)])
    second = [e for e in events if e.t >= SPLIT]
    return d, load_session(d / "map"), second, truth, cfg, first


def _errors(times, poses, truth) -> np.ndarray:
    at = interpolate_poses(truth[:, 0], truth[:, 1:], times)
    return np.hypot(poses[:, 0] - at[:, 0], poses[:, 1] - at[:, 1])


def test_a_continued_run_joins_the_saved_map(halves, tmp_path):
    """The second part, no initial pose: placed on the map by the global search, mapped on;
    loop closures between its keyframes and the saved ones; every keyframe of the joined
    graph, saved and new, within 3 cm of the truth (the whole log in one run: 1.4 cm max);
    saved as one session that says which keyframes came from which log."""
    _, session, second, truth, cfg, first = halves
    anchor = find_anchor(session, second, cfg)
    assert anchor.how == "global search" and anchor.t >= SPLIT
    at = interpolate_poses(truth[:, 0], truth[:, 1:], [anchor.t])[0]
    assert math.hypot(*(anchor.pose[:2] - at[:2])) < 0.05
    c = Continuation(session, anchor, "map")
    res = run_backends(second, cfg, ["isam2"], "laser", continuation=c)[0]
    n0 = session.keyframes
    assert len(res.times) > n0 + 50
    assert np.all(np.diff(res.times) > 0)  # the saved keyframes first, in time order
    assert res.continued["saved_keyframes"] == n0
    err = _errors(res.times, res.poses, truth)
    assert err[:n0].max() < 0.03 and err[n0:].max() < 0.03
    joined = [c for c in res.loop_closures if c["accepted"] and c["from"] < n0 <= c["to"]]
    assert len(joined) >= 5
    # every scan of both logs has a pose (the saved scans between keyframes placed again)
    n_scans = len(first.scan_times) + int(np.sum(res.scan_times >= anchor.t))
    assert len(res.scan_times) == n_scans
    assert _errors(res.scan_times, res.scan_poses, truth).max() < 0.05

    joined_session = Session.from_result(res, cfg, {"log": "second"}, c)
    save_session(joined_session, tmp_path / "joined")
    s = load_session(tmp_path / "joined")
    assert s.keyframes == len(res.times)
    segs = s.meta["segments"]
    assert [g["log"] for g in segs] == ["first", "second"]
    assert segs[0]["keyframes"] == [0, n0] and segs[1]["keyframes"] == [n0, s.keyframes]
    kinds = [k["kind"] for k in s.constraints]
    assert kinds.count("anchor") == 1
    a = next(k for k in s.constraints if k["kind"] == "anchor")
    assert a["from"] == anchor.keyframe and a["to"] == n0
    assert len(s.between) == len(res.scan_times) - s.keyframes


def test_a_session_continued_twice_keeps_its_parts(halves, tmp_path):
    """The joined session continued again by the log's last 50 s (placed by an initial pose:
    50 s of the symmetric lab may not tell its ends apart): three segments, the first two
    anchors kept, every keyframe within 5 cm (each anchor is one match, 1-2 cm
    off: the whole log in one run stays within 1.4 cm)."""
    _, session, second, truth, cfg, _ = halves
    part2 = [e for e in second if e.t < 150.0]
    part3 = [e for e in second if e.t >= 150.0]
    c2 = Continuation(session, find_anchor(session, part2, cfg), "map")
    r2 = run_backends(part2, cfg, ["isam2"], "laser", continuation=c2)[0]
    save_session(Session.from_result(r2, cfg, {"log": "2"}, c2), tmp_path / "j2")
    s2 = load_session(tmp_path / "j2")
    start = interpolate_poses(truth[:, 0], truth[:, 1:], [part3[0].t])[0]
    c3 = Continuation(s2, find_anchor(s2, part3, cfg, tuple(start)), "j2")
    assert c3.anchor.how == "initial pose"
    r3 = run_backends(part3, cfg, ["isam2"], "laser", continuation=c3)[0]
    s3 = Session.from_result(r3, cfg, {"log": "3"}, c3)
    assert [g["log"] for g in s3.meta["segments"]] == ["first", "2", "3"]
    assert sum(k["kind"] == "anchor" for k in s3.constraints) == 2
    assert _errors(r3.times, r3.poses, truth).max() < 0.05


def test_a_log_that_never_finds_the_map_cannot_continue_it(halves):
    """A log whose scans never match the map (its laser saw nothing) is refused with the
    reason."""
    from dataclasses import replace

    from fgslam.errors import UserError
    from fgslam.events import LaserScan

    _, session, second, _, cfg, _ = halves
    blind = [
        replace(e, ranges=np.full_like(e.ranges, cfg.laser.max_range + 1.0))
        if isinstance(e, LaserScan)
        else e
        for e in second
        if e.t < SPLIT + 20.0
    ]
    with pytest.raises(UserError, match="never localized"):
        find_anchor(session, blind, cfg)


# -- the graph: restored keyframes and a keyframe placed on an earlier one ----------------


def _chain(n: int = 6, seed: int = 0):
    rng = np.random.default_rng(seed)
    poses = np.zeros((n, 3))
    for i in range(1, n):
        poses[i] = compose_poses(poses[i - 1], [1.0, rng.normal(0, 0.2), rng.normal(0, 0.3)])
    cov = np.diag([1e-3, 2e-3, 1e-4])
    links = [relative_pose(between_poses(poses[i], poses[i + 1]), cov) for i in range(n - 1)]
    return poses, links, cov


def test_restored_keyframes_keep_their_poses_and_a_new_one_hangs_on_its_origin():
    """Consistent links: the restored estimate is the saved poses; a keyframe predicted from
    keyframe 1 (not the last) sits at pose 1 composed with the link, and its covariance is
    pose 1's marginal carried through the link: the same as GTSAM's batch Marginals of the
    graph with that factor (computed another way: full elimination)."""
    poses, links, _ = _chain()
    be = GraphBackend()
    start = np.diag([1e-6, 1e-6, 1e-8])
    be.restore(np.arange(6.0), poses, links, [], start)
    assert np.allclose(be.keyframe_poses()[:6], poses, atol=1e-9)
    rel = np.array([0.5, 2.0, 1.0])
    m_cov = np.diag([4e-4, 9e-4, 1e-4])
    be.predict(6.0, None, relative_pose(rel, m_cov), origin=1)
    assert np.allclose(be.pose(), compose_poses(poses[1], rel), atol=1e-9)
    _, P = be.estimate([])
    g = gtsam.NonlinearFactorGraph(be.graph)
    g.push_back(be.new_graph)
    v = gtsam.Values(be.isam.calculateEstimate())
    v.insert(X(6), gtsam.Pose2(*be.pose()))
    marg = gtsam.Marginals(g, v).marginalCovariance(X(6))
    th = be.pose()[2]
    R = np.array([[math.cos(th), -math.sin(th), 0], [math.sin(th), math.cos(th), 0], [0, 0, 1]])
    assert np.allclose(P, R @ marg @ R.T, rtol=1e-6, atol=1e-12)
    # and the new keyframe is tied to keyframe 1 only: its covariance is smaller than one
    # hung on the last keyframe (further from the prior) would be
    be.commit()
    rel_c = be.joint_covariance([X(1), X(6)])
    assert np.trace(rel_c[3:, 3:]) < np.trace(be.joint_covariance([X(5)])) + np.trace(m_cov)


def test_a_restored_loop_pulls_the_chain():
    """A saved loop closure is a factor of the restored graph: the chain's end moves toward
    what it says."""
    poses, links, _ = _chain()
    be = GraphBackend()
    target = compose_poses(poses[0], between_poses(poses[0], poses[5]) + np.array([0.3, 0, 0]))
    loop = relative_pose(between_poses(poses[0], target), np.diag([1e-4, 1e-4, 1e-5]))
    be.restore(np.arange(6.0), poses, links, [(0, 5, loop)], np.diag([1e-6, 1e-6, 1e-8]))
    be.finish()
    end = be.final_estimate().atPose2(X(5))
    assert math.hypot(end.x() - poses[5, 0], end.y() - poses[5, 1]) > 0.1


# -- sessions that cannot be continued ---------------------------------------------------


def _box(n: int = 5) -> Session:
    """A session of a chain of keyframes (no scans) with one loop closure."""
    poses, links, cov = _chain(n)
    cons = [
        {
            "kind": "scan",
            "from": i,
            "to": i + 1,
            "pose": [m.delta.x(), m.delta.y(), m.delta.theta()],
            "cov": cov.tolist(),
        }
        for i, m in enumerate(links)
    ]
    cons.insert(
        0, {"kind": "loop", "from": 0, "to": 3, "pose": [1.0, 2.0, 0.1], "cov": cov.tolist()}
    )
    return Session(
        times=np.arange(n) * 1.5,
        poses=poses,
        covs=np.tile(cov, (n, 1, 1)),
        scans=[None] * n,
        laser_xy=(0.0, 0.0),
        config=load_config(None).to_dict(),
        constraints=cons,
    )


@settings(max_examples=80, deadline=None)
@given(
    field=st.sampled_from(["kind", "from", "to", "pose", "cov"]),
    value=st.one_of(
        st.none(),
        st.booleans(),
        st.integers(-5, 8),
        st.floats(allow_nan=True, allow_infinity=True),
        st.text(max_size=6),
        st.lists(st.floats(allow_nan=True, allow_infinity=True), max_size=4),
        st.lists(st.lists(st.floats(-2, 2), min_size=3, max_size=3), min_size=3, max_size=3),
    ),
)
def test_fuzz_a_saved_constraint(field, value):
    """One field of a saved constraint replaced by a hostile value: refused by name
    (SessionError, one line), or loaded and then restored into a graph without error."""
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        save_session(_box(), f"{d}/s")
        index = json.loads(open(f"{d}/s/session.json").read())
        index["constraints"][0][field] = value
        open(f"{d}/s/session.json", "w").write(json.dumps(index))
        try:
            s = load_session(f"{d}/s")
        except SessionError as e:
            assert "\n" not in str(e)
            return
        anchor = Anchor(100.0, s.poses[1], np.eye(3) * 1e-3, 1, "initial pose", 99.0)
        c = Continuation(s, anchor)
        links, loops, _ = c.replay()
        be = GraphBackend()
        be.restore(c.times(), s.poses, links, loops, np.eye(3) * 1e-6)
        assert np.isfinite(be.pose()).all()


def test_continue_cli(halves, tmp_path, capsys, one_line_error):
    """`fgslam run LOG --continue DIR` replaces DIR by the joined session (report.json
    says what was continued); with --save the saved session is left as it was; the EKF
    and --initial-pose without --continue are refused in one line."""
    import shutil

    from fgslam.cli import main
    from fgslam.io.logwriter import LogWriter

    d, session, second, _, cfg, _ = halves
    log = tmp_path / "second.log.gz"
    with LogWriter(log, cfg, "corridor") as w:
        for e in second:
            w.write(e)
    shutil.copytree(d / "map", tmp_path / "map")
    before = (tmp_path / "map" / "session.json").read_text()
    argv = ["run", str(log), "--sensors", "laser", "--continue", str(tmp_path / "map")]
    assert main([*argv, "--out", str(tmp_path / "o1"), "--save", str(tmp_path / "other")]) == 0
    assert (tmp_path / "map" / "session.json").read_text() == before
    assert load_session(tmp_path / "other").keyframes > session.keyframes
    assert main([*argv, "--out", str(tmp_path / "o2")]) == 0
    joined = load_session(tmp_path / "map")
    assert len(joined.meta["segments"]) == 2
    rep = json.loads((tmp_path / "o2" / "report.json").read_text())
    assert rep["continued"]["saved_keyframes"] == session.keyframes
    assert "placed on" in capsys.readouterr().out
    one_line_error([*argv, "--backend", "ekf", "--out", str(tmp_path / "o3")], "isam2")
    one_line_error(
        ["run", str(log), "--initial-pose", "0,0,0", "--out", str(tmp_path / "o4")],
        "--continue",
    )
