"""Scan odometry and keyframes (fgslam.slam.keyframes) and loop closures (fgslam.slam.loops)
on scans ray-cast in small synthetic worlds where the truth is known."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from factors.geometry import between_poses, compose_poses, wrap_angle
from factors.odometry import relative_pose
from fgslam.config import load_config
from fgslam.config.robot import KeyframeParams, LoopParams
from fgslam.scanmatch import MatchParams
from fgslam.sim.raycast import raycast
from fgslam.slam.graph import GraphBackend
from fgslam.slam.keyframes import ScanOdometry
from fgslam.slam.loops import AWAITING, LoopCloser
from fgslam.slam.step import SlamStep

BEARINGS = np.radians(np.linspace(-90.0, 90.0, 181))


def _box(x0, y0, x1, y1):
    return [(x0, y0, x1, y0), (x1, y0, x1, y1), (x1, y1, x0, y1), (x0, y1, x0, y0)]


def _room(ox: float = 0.0, pillar=(3.0, 2.0)) -> list:
    """A 10 x 6 m room at x offset ``ox`` with a pillar, an alcove and a cabinet."""
    px, py = pillar
    segs = _box(ox, 0.0, ox + 10.0, 6.0)
    segs += _box(ox + px, py, ox + px + 0.5, py + 0.5)
    segs += _box(ox + 7.0, 4.0, ox + 8.2, 4.6)
    segs += [(ox + 5.0, 6.0, ox + 5.0, 5.0), (ox + 5.0, 5.0, ox + 6.0, 5.0)]
    return segs


def _scan(segs, pose, rng, sigma=0.01) -> np.ndarray:
    """Robot-frame points of a 181-beam laser at ``pose`` (world), range noise ``sigma``."""
    x, y, th = pose
    r = raycast((x, y), th + BEARINGS, np.asarray(segs, dtype=float))
    ok = np.isfinite(r) & (r < 20.0)
    r = r[ok] + sigma * rng.standard_normal(ok.sum())
    b = BEARINGS[ok]
    return np.column_stack([r * np.cos(b), r * np.sin(b)])


def _mp():
    cfg = load_config()
    return MatchParams.from_config(cfg)


def test_keyframes_by_distance_and_scan_odometry_beats_drifting_wheels():
    """A straight drive at 5 cm per scan: a keyframe every 0.5 m; the scans between carry
    their pose from the keyframe by matching, far better than wheels that over-read 5 % and
    drift 1 deg per scan."""
    rng = np.random.default_rng(0)
    segs = _room()
    truth = [np.array([1.0 + 0.05 * i, 1.0 + 0.005 * i, 0.002 * i]) for i in range(60)]
    so = ScanOdometry(KeyframeParams(distance=0.5, angle=math.radians(20)), _mp())
    odom = np.zeros(3)
    kf_true = None
    kfs = []
    for i, p in enumerate(truth):
        if i:
            d = between_poses(truth[i - 1], p)
            odom = compose_poses(odom, d * np.array([1.05, 1.0, 1.0]) + [0, 0, math.radians(1.0)])
        st = so.add(_scan(segs, p, rng), odom)
        if st.keyframe:
            if kf_true is not None:
                assert st.scan is not None
                m = np.array([st.scan.delta.x(), st.scan.delta.y(), st.scan.delta.theta()])
                e = m - between_poses(kf_true, p)
                assert math.hypot(e[0], e[1]) < 0.03 and abs(e[2]) < math.radians(0.5)
            kf_true = p
            kfs.append(i)
        else:
            e = st.rel - between_poses(kf_true, p)
            assert math.hypot(e[0], e[1]) < 0.03 and abs(e[2]) < math.radians(0.5), (i, e)
    gaps = np.diff(kfs)
    assert 9 <= gaps.min() and gaps.max() <= 11  # 0.5 m at 5.1 cm per scan
    assert so.stats["keyframes_distance"] == len(kfs) - 1


def test_frozen_wheels_that_catch_up_are_bridged_by_the_steady_guess():
    """Wheel odometry that freezes for five scans and then catches up in one jump (as MIT
    CSAIL's does): the jump puts the wheels' guess 0.6 m off, outside the search window; the
    last scan's motion carried on is the guess that matches, and no scan is lost."""
    rng = np.random.default_rng(7)
    segs = _room()
    truth = [np.array([1.0 + 0.12 * i, 3.5, 0.0]) for i in range(30)]
    so = ScanOdometry(KeyframeParams(distance=1.5), _mp())
    kf = None
    for i, p in enumerate(truth):
        frozen = 10 <= i < 15
        odom = truth[9] if frozen else p  # the jump comes at scan 15
        st = so.add(_scan(segs, p, rng), odom - truth[0])
        if kf is not None:  # rel: in the frame of the keyframe before this scan
            e = st.rel - between_poses(kf, p)
            assert math.hypot(e[0], e[1]) < 0.03 and abs(e[2]) < math.radians(0.5), (i, e)
        if st.keyframe:
            kf = p
    assert so.stats["scan_matches_rejected"] == 0
    assert so.stats["scan_matches_recovered"] >= 1


def test_every_scan_policy_and_wheels_only_never_match():
    rng = np.random.default_rng(1)
    segs = _room()
    so = ScanOdometry(KeyframeParams(policy="every-scan", odometry="wheels"), _mp())
    for i in range(5):
        st = so.add(_scan(segs, (1.0 + 0.1 * i, 2.0, 0.0), rng), np.array([0.1 * i, 0, 0]))
        assert st.keyframe and st.scan is None and st.match is None
    assert so.stats["scan_matches"] == 0


def test_turn_on_the_spot_makes_keyframes_by_angle():
    rng = np.random.default_rng(2)
    segs = _room()
    so = ScanOdometry(KeyframeParams(distance=0.5, angle=math.radians(20)), _mp())
    n = 0
    for i in range(31):
        th = math.radians(3.0 * i)
        st = so.add(_scan(segs, (4.0, 3.0, th), rng), np.array([0.0, 0.0, th]))
        n += st.keyframe
    assert so.stats["keyframes_angle"] >= 3 and n <= 6  # 90 deg in steps of 21 deg


def _loop_run(loops: bool, segs, truth, rng, drift_deg=0.5):
    """Keyframes around a loop with heading-drifting odometry; returns final estimate and
    the loop closer."""
    be = GraphBackend()
    mp = _mp()
    closer = LoopCloser(LoopParams(enabled=loops, radius=3.0, min_travel=6.0), mp)
    step = SlamStep(be, loops=closer)
    C = np.diag([0.02, 0.02, math.radians(1.0)]) ** 2
    for k, p in enumerate(truth):
        pts = _scan(segs, p, rng)
        if k == 0:
            step.keyframe(0.0, [], None, p, points=pts)
            continue
        d = between_poses(truth[k - 1], p) + np.array([0.0, 0.0, math.radians(drift_deg)])
        step.keyframe(float(k), [], relative_pose(d, C), points=pts)
    traj = be.finish()
    return np.array([q for _, q, _ in traj]), closer


def _square(n_side=8):
    pts = []
    corners = [(1.5, 1.2), (8.5, 1.2), (8.5, 4.6), (1.5, 4.6), (1.5, 1.2), (4.0, 1.2)]
    for (x0, y0), (x1, y1) in itertools.pairwise(corners):
        th = math.atan2(y1 - y0, x1 - x0)
        for i in range(n_side):
            f = i / n_side
            pts.append(np.array([x0 + f * (x1 - x0), y0 + f * (y1 - y0), th]))
    return pts


def test_loop_closure_pulls_a_drifting_loop_back():
    """Odometry that drifts 0.5 deg per keyframe around the room: without loop closures the
    end is half a metre off; with them (verified matches against the start) within 0.15 m."""
    segs = _room()
    truth = _square()
    est0, _ = _loop_run(False, segs, truth, np.random.default_rng(3))
    est1, closer = _loop_run(True, segs, truth, np.random.default_rng(3))
    err0 = np.hypot(*(est0[:, :2] - np.array(truth)[:, :2]).T)
    err1 = np.hypot(*(est1[:, :2] - np.array(truth)[:, :2]).T)
    assert err0[-1] > 0.5
    assert closer.stats["loop_closures_accepted"] >= 1
    assert err1[-1] < 0.15 and err1.max() < 0.5, (err1[-1], err1.max())
    for c in closer.closures:  # every accepted closure is true to 5 cm / 1 deg
        if c.accepted:
            e = c.pose - between_poses(truth[c.j], truth[c.k])
            e[2] = wrap_angle(float(e[2]))
            assert math.hypot(e[0], e[1]) < 0.05 and abs(e[2]) < math.radians(1.0)


@pytest.mark.parametrize("place", ["same room", "similar room"])
def test_loop_closure_rejects_a_similar_looking_different_room(place):
    """Two rooms alike but for the pillar (moved 1.2 m). The estimate (drifted) believes the
    robot is back at an old keyframe in room A while it is in room B: the match there is not
    verified (weak or inconsistent with the estimate). A true revisit of room A is."""
    rng = np.random.default_rng(4)
    segs = _room(0.0) + _room(20.0, pillar=(4.2, 2.0))
    mp = _mp()
    closer = LoopCloser(LoopParams(), mp)
    old = np.array([2.0, 3.0, 0.0])
    poses = np.array([old])
    closer.add_keyframe(0, _scan(segs, old, rng), old)
    here = old + np.array([0.3, 0.1, 0.05])
    if place == "similar room":
        here = here + np.array([20.0, 0.0, 0.0])
    closer.add_keyframe(1, _scan(segs, here, rng), here)
    import gtsam

    believed = between_poses(old, old + np.array([0.3, 0.1, 0.05]))  # the aliased belief
    cov = np.diag([0.15, 0.15, math.radians(3.0)]) ** 2
    c = closer.verify(0, 1, poses, gtsam.Pose2(*believed), cov)
    if place == "same room":  # verified; over this much uncertainty it waits for a second
        assert c.reason == AWAITING and not c.accepted, c
        sure = closer.verify(0, 1, poses, gtsam.Pose2(*believed), cov / 16)
        assert sure.accepted, sure
    else:
        assert not c.accepted and c.reason not in ("", AWAITING), c


def test_a_closure_the_estimate_is_too_sure_against_waits_for_a_second():
    """An overconfident estimate (2 mm, 0.05 deg) believes the robot 0.25 m from where it
    is: the right match is not thrown away as inconsistent but waits for a second closure
    that agrees (a wrong estimate is what closures are there to mend)."""
    import gtsam

    rng = np.random.default_rng(5)
    segs = _room()
    closer = LoopCloser(LoopParams(), _mp())
    old = np.array([2.0, 3.0, 0.0])
    here = old + np.array([0.3, 0.1, 0.05])
    closer.add_keyframe(0, _scan(segs, old, rng), old)
    closer.add_keyframe(1, _scan(segs, here, rng), here)
    believed = between_poses(old, here) + np.array([0.25, 0.0, 0.0])
    cov = np.diag([0.002, 0.002, math.radians(0.05)]) ** 2
    c = closer.verify(0, 1, np.array([old]), gtsam.Pose2(*believed), cov)
    assert c.reason == AWAITING and not c.accepted, c
    assert c.mahalanobis2 > 30.0  # outside the 99.9 % gate (16.3)
    assert closer.stats["loop_doubt_inconsistent_with_the_estimate"] == 1
    e = c.pose - between_poses(old, here)
    assert math.hypot(e[0], e[1]) < 0.03
    strict = LoopCloser(LoopParams(doubt=False), _mp())  # the rule before: thrown away
    strict.add_keyframe(0, _scan(segs, old, rng), old)
    strict.add_keyframe(1, _scan(segs, here, rng), here)
    c = strict.verify(0, 1, np.array([old]), gtsam.Pose2(*believed), cov)
    assert c.reason == "inconsistent with the estimate" and not c.accepted


def _drifted_revisit(params: LoopParams, offset: float):
    """Keyframe 0 in the room, then keyframes without scans along 40 m of corridor, then a
    return to keyframe 0's place that the estimate believes ``offset`` m further in x (it
    drifted, and is sure of it: 2 mm, 0.05 deg, as after many scan matches). Returns the
    candidates of the return, its match against keyframe 0 and the true relative pose."""
    import gtsam

    rng = np.random.default_rng(6)
    segs = _room()
    closer = LoopCloser(params, _mp())
    old = np.array([2.0, 3.0, 0.0])
    closer.add_keyframe(0, _scan(segs, old, rng), old)
    for i in range(1, 5):  # out along y and back, 10 m steps, no scans
        closer.add_keyframe(i, None, np.array([2.0, 3.0 + 10.0 * min(i, 4 - i), 0.0]))
    here = old + np.array([0.3, 0.1, 0.05])
    believed = here + np.array([offset, 0.0, 0.0])
    closer.add_keyframe(5, _scan(segs, here, rng), believed)
    cands = closer.candidates(5, np.vstack([old] * 5), believed)
    cov = np.diag([0.002, 0.002, math.radians(0.05)]) ** 2
    c = closer.verify(0, 5, np.array([old]), gtsam.Pose2(*between_poses(old, believed)), cov)
    return cands, c, between_poses(old, here)


def test_a_revisit_the_estimate_misplaces_by_metres_is_still_found():
    """An estimate sure to 2 mm that is 2.5 m off at a revisit (the Intel bag's first loop
    came back 2-5 m off with 3 sigma under 2 m): the search window's floor (3 m) still holds
    the true pose, which the match finds; the closure then waits for a second, being
    inconsistent with the estimate. At 4.5 m off the old place is still a candidate (within
    6 m). With the floors before (window 1-2 m, candidates within 4 m) neither."""
    cands, c, true = _drifted_revisit(LoopParams(), 2.5)
    assert cands == [0] and c.reason == AWAITING and c.mahalanobis2 > 1e3, c
    e = c.pose - true
    assert math.hypot(e[0], e[1]) < 0.03 and abs(wrap_angle(float(e[2]))) < math.radians(0.5)
    assert _drifted_revisit(LoopParams(), 4.5)[0] == [0]
    before = LoopParams(radius=4.0, min_search_xy=1.0, max_search_xy=2.0)
    _, c, true = _drifted_revisit(before, 2.5)
    e = c.pose - true
    assert not (c.reason == AWAITING and math.hypot(e[0], e[1]) < 0.03), c
    assert _drifted_revisit(before, 4.5)[0] == []


def test_an_uncertain_closure_enters_only_with_a_second_that_agrees():
    """Two verified closures of consecutive keyframes to neighbouring old ones enter together
    when they agree through the estimate's geometry; one that disagrees waits, and expires."""
    from fgslam.slam.loops import Closure

    closer = LoopCloser(LoopParams(confirm_window=3), _mp())
    poses = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [5.0, 5.0, 1.0], [5.5, 5.0, 1.0]])
    here = np.array([5.5, 5.0, 1.0])

    def closure(j, k, pose):
        return Closure(j, k, np.array(pose, dtype=float), np.eye(3) * 1e-4, False, AWAITING)

    true = [between_poses(poses[0], poses[2]), between_poses(poses[1], here)]
    first = closure(0, 2, true[0])
    assert closer._confirm(first, poses, poses[2]) == []  # pending
    wrong = closure(1, 3, true[1] + np.array([0.5, 0.0, 0.0]))
    assert closer._confirm(wrong, poses, here) == []
    good = closure(1, 3, true[1] + np.array([0.03, -0.02, 0.005]))
    both = closer._confirm(good, poses, here)
    assert both == [first, good] and first.accepted and good.accepted
    closer._expire(3 + 4)  # the wrong one finds no partner in time
    assert wrong.reason == "unconfirmed" and not closer.pending


class _Backend:
    """The two things loop closure asks of a backend, from given poses (the last: the
    current keyframe's prediction) and a fixed relative covariance."""

    def __init__(self, poses, cov=None):
        self.poses = [np.asarray(p, dtype=float) for p in poses]
        self.cov = np.diag([0.05, 0.05, math.radians(1.0)]) ** 2 if cov is None else cov

    def keyframe_poses(self):
        return np.array(self.poses[:-1]).reshape(-1, 3)

    def relative(self, j):
        import gtsam

        return gtsam.Pose2(*between_poses(self.poses[j], self.poses[-1])), self.cov.copy()


def test_a_local_map_is_built_once_and_rebuilt_when_its_keyframes_move():
    """The local map of an old keyframe is prepared for matching once and reused while its
    keyframes keep their poses relative to it (the whole map may move); a keyframe that moves
    by more than ``cache_xy`` makes it rebuilt, and a reused map gives the same match."""
    import gtsam

    rng = np.random.default_rng(6)
    segs = _room()
    truth = [np.array([1.5 + 0.5 * i, 3.0, 0.02 * i]) for i in range(5)]
    closer = LoopCloser(LoopParams(), _mp())
    for i, p in enumerate(truth):
        closer.add_keyframe(i, _scan(segs, p, rng), p)
    poses = np.array(truth)
    ref, _ = closer.reference(2, poses)
    assert closer.reference(2, poses)[0] is ref
    moved = np.array([compose_poses((3.0, -1.0, 0.7), p) for p in truth])  # all together
    assert closer.reference(2, moved)[0] is ref
    assert (closer.stats["loop_maps_built"], closer.stats["loop_maps_reused"]) == (1, 2)
    bent = poses.copy()
    bent[3, 1] += 0.05  # one keyframe 5 cm off relative to the others
    assert closer.reference(2, bent)[0] is not ref
    assert closer.stats["loop_maps_built"] == 2
    here = truth[2] + np.array([0.2, 0.1, 0.03])
    closer.add_keyframe(5, _scan(segs, here, rng), here)
    rel = gtsam.Pose2(*between_poses(truth[2], here))
    cov = np.diag([0.05, 0.05, 0.01]) ** 2
    cached = closer.verify(2, 5, bent, rel, cov)
    assert closer.stats["loop_maps_reused"] == 3
    fresh = LoopCloser(LoopParams(cache_size=0), _mp())
    fresh.scans, fresh.speeds = closer.scans, closer.speeds
    again = fresh.verify(2, 5, bent, rel, cov)
    assert fresh.stats["loop_maps_built"] == 1
    assert np.allclose(cached.pose, again.pose) and cached.reason == again.reason == ""


_TOUR = [(2.0, 3.0, 0.0), (12.0, 3.0, 0.0), (12.0, 13.0, 0.0), (2.0, 13.0, 0.0)]


def _back_at_the_start(params, backend, back, seed=8, closer_type=LoopCloser):
    """Keyframe 0 in the room, a tour of 40 m away and back (``_TOUR``), then the keyframes
    ``back`` next to it, each trying to close loops with ``backend`` (a :class:`_Backend`
    type). Returns the loop closer and the keyframes at which a match was tried."""
    rng = np.random.default_rng(seed)
    segs = _room()
    closer = closer_type(params, _mp())
    tried, poses = [], []
    for k, p in enumerate(_TOUR + back):
        poses.append(np.array(p, dtype=float))
        closer.add_keyframe(k, _scan(segs, p, rng), p)
        if k:
            n = len(closer.closures)
            closer.try_close(k, backend(poses), p)
            tried += [c.k for c in closer.closures[n:]]
    return closer, tried


def test_a_candidate_whose_local_map_did_not_look_where_the_scan_looks_is_not_matched():
    """Back at the start facing the other way (the old keyframe's scan saw the room ahead of
    it, the new one sees what was behind it): with ``min_view`` the candidate is skipped
    without a match; without, it is matched (and fails)."""
    back = [(2.3, 3.1, math.pi)]
    closer, tried = _back_at_the_start(LoopParams(min_view=0.0), _Backend, back)
    assert tried == [4] and not closer.closures[0].accepted
    closer, tried = _back_at_the_start(LoopParams(), _Backend, back)
    assert tried == [] and closer.stats["loop_skipped_little_view"] == 1
    # the same place facing the same way is matched and verified
    closer, tried = _back_at_the_start(LoopParams(), _Backend, [(2.3, 3.1, 0.05)])
    assert tried == [4] and closer.closures[0].reason in ("", AWAITING)


class _Off(_Backend):
    """An estimate that believes the robot 0.6 m to the left of where it is, and is sure."""

    def relative(self, j):
        import gtsam

        d = between_poses(self.poses[j], self.poses[-1]) + np.array([0.0, 0.6, 0.0])
        return gtsam.Pose2(*d), np.diag([0.01, 0.01, 0.002]) ** 2


def test_a_place_whose_match_was_rejected_waits_before_it_is_tried_again():
    """Back at the start with an estimate 0.6 m off and sure of itself, the window too small
    to reach the truth (nothing there fits the scan: low score): with ``retry_after`` 3 the
    place is tried at every fourth keyframe, without at each."""
    back = [(2.3 + 0.05 * i, 3.1, 0.05) for i in range(10)]
    small = {"min_search_xy": 0.3, "max_search_xy": 0.3}
    for retry, expect in ((0, list(range(4, 14))), (3, [4, 8, 12])):
        closer, tried = _back_at_the_start(LoopParams(retry_after=retry, **small), _Off, back)
        assert tried == expect, (retry, tried)
        assert all(c.reason.startswith("low score") for c in closer.closures)


def test_a_place_that_fitted_but_was_doubted_is_tried_again_at_once():
    """A match rejected as ambiguous or seeing through the old place found the place (the
    next keyframe often passes): no waiting. One that found nothing there waits."""
    from fgslam.slam.loops import Closure

    back = [(2.3 + 0.05 * i, 3.1, 0.05) for i in range(5)]
    for reason, expect in (
        ("ambiguous (0.60 > 0.5)", [4, 5, 6, 7, 8]),
        ("sees through the old place", [4, 5, 6, 7, 8]),
        ("low score (0.30 < 0.5)", [4, 8]),
        ("diverged (ICP left the search result)", [4, 8]),
    ):

        class Rejecting(LoopCloser):
            def verify(self, j, k, poses, rel, rel_cov):
                return Closure(j, k, np.zeros(3), np.eye(3), False, reason)

        _, tried = _back_at_the_start(LoopParams(), _Backend, back, closer_type=Rejecting)
        assert tried == expect, (reason, tried)
