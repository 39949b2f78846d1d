"""Map management: association (fresh estimates, JCBB vs nearest neighbour), the landmark
lifecycle (confirmation, unconstrained candidates, duplicates, unreliable marks), robust
factors under wrong associations, iSAM2 at the optimum, partial results on a backend failure."""

from __future__ import annotations

import json
import math

import gtsam
import numpy as np
import pytest

from factors.odometry import Preintegrated
from fgslam.config import with_scanmatch
from fgslam.config.robot import AssociationParams, MapParams
from fgslam.errors import RunWarning
from fgslam.evaluation import metrics as evaluation
from fgslam.frontend.features import Feature
from fgslam.sim.scenes import PAPER, park_run, room_events
from fgslam.slam import association, step
from fgslam.slam.association import Candidate
from fgslam.slam.ekf import EkfBackend
from fgslam.slam.graph import GraphBackend
from fgslam.slam.graph_solve import BackendError, BatchSmoother
from fgslam.slam.runner import SlamPipeline
from fgslam.slam.step import SlamStep


def _still():
    c = np.eye(3) * 1e-8
    return Preintegrated(gtsam.Pose2(), c, c, 1)


def _point(xy, cov=None):
    """A point feature (bearing, range) of a robot-frame position."""
    x, y = xy
    return Feature(
        "point",
        np.array([math.atan2(y, x), math.hypot(x, y)]),
        np.diag([1e-4, 0.05**2]) if cov is None else cov,
    )


# ------------------------------------------------------------------ association


def test_graph_association_decisions_equal_those_from_fresh_estimates(monkeypatch):
    """GraphBackend's cached means are stale by up to 10 keyframes; every association
    decision of an iSAM2 run equals the one computed with fresh means of every landmark
    (before the fix the gate used the stale residual with the fresh covariance)."""
    evs, cfg, _ = room_events(0)
    cfg = with_scanmatch(cfg, PAPER)  # one keyframe per scan
    calls = {"n": 0, "stale": 0}
    real = association.associate

    def checked(features, pose, cands, hint, estimate, params=None):
        be = estimate.__self__
        fresh = {lid: be._mean(lid, fresh=True) for lid in hint}
        if any(np.abs(fresh[i] - hint[i]).max() > 1e-6 for i in hint):
            calls["stale"] += 1
        a = real(features, pose, cands, hint, estimate, params)
        b = real(features, pose, cands, fresh, estimate, params)
        assert (a.pairs, a.ambiguous, a.merges) == (b.pairs, b.ambiguous, b.merges)
        calls["n"] += 1
        return a

    monkeypatch.setattr(step, "associate", checked)
    pipe = SlamPipeline(cfg, ["isam2"], "fused")
    for ev in [e for e in evs if e.t < 25.0]:
        pipe.add(ev)
    pipe.finish()
    assert calls["n"] > 50 and calls["stale"] > 10  # the cache was stale, decisions were not


def _static(means, P_pose, sigma_l=1e-3):
    def estimate(lids):
        n = 3 + 2 * len(lids)
        P = np.eye(n) * sigma_l**2
        P[:3, :3] = P_pose
        return {i: means[i] for i in lids}, P

    return estimate


def test_jcbb_rejects_a_jointly_incompatible_pairing_that_nearest_neighbour_accepts():
    """Two trees 3 m apart, the pose uncertain by 0.4 m sideways. Feature a is 0.8 m left of
    tree 0's prediction, feature b 0.8 m right of tree 1's: each is individually compatible
    with its nearest tree, but together they need the robot 0.8 m left AND 0.8 m right.
    Nearest neighbour takes both; JCBB keeps one pairing, jointly compatible."""
    means = {0: np.array([5.0, 0.0]), 1: np.array([5.0, 3.0])}
    P_pose = np.diag([0.01, 0.4**2, 1e-6])
    feats = [_point((5.0, 0.8)), _point((5.0, 2.2))]
    cands = [Candidate(0, "point"), Candidate(1, "point")]
    args = (feats, np.zeros(3), cands, means, _static(means, P_pose))
    nn = association.associate(*args, AssociationParams(method="nn"))
    jc = association.associate(*args, AssociationParams(method="jcbb"))
    assert nn.pairs == [0, 1]
    assert sum(p is not None for p in jc.pairs) == 1
    # NN's pairing fails the joint gate: stack both innovations with the shared pose error
    est = _static(means, P_pose)
    _, P = est([0, 1])
    e, A = [], []
    for i, (f, lid) in enumerate(zip(feats, [0, 1], strict=True)):
        r, Hx, Hl = association.models.residual("point", np.zeros(3), means[lid], f.z)
        row = np.zeros((2, 7))
        row[:, :3], row[:, 3 + 2 * i : 5 + 2 * i] = Hx, Hl
        e.append(r)
        A.append(row)
    e, A = np.concatenate(e), np.vstack(A)
    S = A @ P @ A.T + np.diag([1e-4, 0.0025, 1e-4, 0.0025])
    assert e @ np.linalg.solve(S, e) > association.chi2_gate(4)


def test_mutual_exclusion_and_ambiguity():
    """Two features near one tree: NN gives both to it, JCBB only one. A feature between two
    trees that both explain it equally well is rejected (neither associated nor new)."""
    means = {0: np.array([5.0, 0.0]), 1: np.array([5.0, 0.6])}
    P_pose = np.diag([0.01, 0.2**2, 1e-6])
    cands = [Candidate(0, "point")]
    feats = [_point((5.0, 0.1)), _point((5.0, -0.1))]
    one = {0: means[0]}
    nn = association.associate(
        feats, np.zeros(3), cands, one, _static(one, P_pose), AssociationParams(method="nn")
    )
    jc = association.associate(feats, np.zeros(3), cands, one, _static(one, P_pose))
    assert nn.pairs == [0, 0] and sorted(jc.pairs, key=str) == [0, None]
    cands = [Candidate(0, "point"), Candidate(1, "point")]
    mid = [_point((5.0, 0.3))]
    a = association.associate(mid, np.zeros(3), cands, means, _static(means, P_pose))
    assert a.pairs == [None] and a.ambiguous == [True]


# ------------------------------------------------------------------ lifecycle


def test_a_landmark_its_sightings_do_not_constrain_never_reaches_the_graph():
    """Issue 16's failing pattern: a point seen from one place with its range unknown
    (variance 1e8 m^2: a bearing-only sighting). Admitted at once, iSAM2 stopped with an
    indeterminate system near the landmark (until issue 31: now the landmark's weak prior
    keeps the system solvable and the run goes on); the lifecycle admits a landmark only
    once its sightings constrain it (every sigma of its fused world estimate below
    confirm_sigma)."""
    bad = _point((4.0, 1.0), np.diag([1e-4, 1e8]))
    old_rule = MapParams(confirm_sigma_m=math.inf, confirm_sigma_rad=math.inf)
    s = SlamStep(GraphBackend(), old_rule)
    s.keyframe(0.0, [bad], None, np.zeros(3))
    s.keyframe(1.0, [bad], _still())
    assert list(s.be.kinds.values()) == ["point"] and np.all(np.isfinite(s.be.pose()))
    s = SlamStep(GraphBackend())
    for k in range(6):
        s.keyframe(float(k), [bad], _still() if k else None, np.zeros(3) if k == 0 else None)
    assert s.be.kinds == {} and s.stats["points_unconstrained"] >= 4
    good = _point((4.0, 1.0))
    s.keyframe(6.0, [good], _still())
    s.keyframe(7.0, [good], _still())
    assert list(s.be.kinds.values()) == ["point"]


def test_seen_once_stays_tentative_confirmed_after_two_keyframes_duplicates_merged():
    """One sighting: tentative, not in the EKF; the second on another keyframe confirms it.
    Two confirmed points at the same place (made so by a wrong merge-less start) are
    detected as duplicates by their joint-covariance test and merged into the older."""
    s = SlamStep(EkfBackend())
    s.keyframe(0.0, [_point((4.0, 1.0))], None, np.zeros(3))
    assert s.be.index == {}
    s.keyframe(1.0, [_point((4.0, 1.0)), _point((4.0, 1.0))], _still())
    assert len(s.be.index) == 1  # the second feature of the scan: ambiguous/another tentative
    # force a duplicate: a second landmark 2 cm away enters the state directly
    s.map.new_id(1.5, _point((4.0, 1.02)), "confirmed")
    dup = max(s.landmarks)
    s.be.add_landmark(dup, _point((4.0, 1.02)))
    s.keyframe(2.0, [_point((4.0, 1.0)), _point((4.0, 1.02))], _still())
    s.keyframe(3.0, [], _still())  # duplicates found after keyframe 2 merge now
    assert s.stats["point_duplicates_merged"] == 1
    assert s.landmarks[dup].merged_into is not None and len(s.be.index) == 1


def test_landmark_in_view_and_never_seen_again_is_marked_unreliable(tmp_path):
    p = MapParams(unseen_limit=5)
    s = SlamStep(EkfBackend(), p)
    f = _point((4.0, 1.0))
    s.keyframe(0.0, [f], None, np.zeros(3))
    s.keyframe(1.0, [f], _still())
    (lid,) = s.be.index
    for k in range(2, 7):
        s.keyframe(float(k), [], _still())
    assert s.landmarks[lid].status == "unreliable" and s.landmarks[lid].active
    s.keyframe(7.0, [f], _still())
    assert s.landmarks[lid].status == "confirmed"


# ------------------------------------------------------------------ robust back end


def test_robust_graph_survives_ten_percent_wrong_associations():
    """10 % of the sightings moved to another tree: the robust (Cauchy, the default) batch
    and iSAM2 solutions stay within 2x of the clean run's ATE, the Gaussian one does not
    (measured: experiments/robust_kernels.py)."""
    from fgslam.slam import pointslam

    def ate(data, truth, robust, backend="batch"):
        r = pointslam.run_points(data, backend, "given", robust=robust)
        return evaluation.ate(r.poses, truth)["rmse"]

    clean, truth, _ = park_run(3)
    bad, _, moved = park_run(3, 0.1)
    assert moved > 20
    a_clean = ate(clean, truth, "cauchy")
    a_plain = ate(bad, truth, "none")
    for backend in ("batch", "isam2"):
        a_robust = ate(bad, truth, "cauchy", backend)
        assert a_robust < 2 * a_clean < a_plain, (backend, a_clean, a_robust, a_plain)


def test_isam2_final_estimate_is_at_the_batch_optimum():
    """After the last keyframe iSAM2 updates until converged: its cost on the whole graph is
    within 1 % of batch LM's on the same graph (a real Victoria-Park-like noisy run)."""
    from fgslam.slam import pointslam

    data, _, _ = park_run(5, 0.0)
    be = {}
    orig = GraphBackend.__init__

    def init(self, *a, **kw):
        orig(self, *a, **kw)
        be["b"] = self

    GraphBackend.__init__ = init
    try:
        pointslam.run_points(data, "isam2", "given")
    finally:
        GraphBackend.__init__ = orig
    g = be["b"]
    isam_cost = g.chi2_per_dof()
    batch = BatchSmoother(g)
    assert g.final_updates >= 1
    assert isam_cost <= 1.01 * batch.chi2_per_dof() + 1e-9, (isam_cost, batch.chi2_per_dof())


# ------------------------------------------------------------------ partial results


def _unconstrained_at_30(monkeypatch):
    """GraphBackend.commit with an unconstrained variable (a point only a bearing measures)
    slipped into keyframe 30's update."""
    real = GraphBackend.commit

    def commit(self):
        if self.k == 30:
            self.kinds[999] = "point"
            self.new_values.insert(gtsam.symbol("l", 999), np.array([2.0, 0.0]))
            noise = gtsam.noiseModel.Isotropic.Sigma(1, 0.01)
            self.new_graph.add(
                gtsam.BearingFactor2D(
                    gtsam.symbol("x", self.k), gtsam.symbol("l", 999), gtsam.Rot2(0.0), noise
                )
            )
        return real(self)

    monkeypatch.setattr(GraphBackend, "commit", commit)


def _room_pass(backends):
    evs, cfg, _ = room_events(0)
    cfg = with_scanmatch(cfg, PAPER)  # one keyframe per scan
    pipe = SlamPipeline(cfg, backends, "fused")
    for ev in [e for e in evs if e.t < 20.0]:
        pipe.add(ev)
    return pipe.finish()


def test_an_unconstrained_variable_is_repaired_and_the_run_goes_on(monkeypatch):
    """Until issue 31 the run of iSAM2 ended at keyframe 30; now the keyframe is repaired
    (the new landmark removed, a warning naming it, report.json's statistics list it) and
    the run goes on to the end, as accurate as before."""
    _unconstrained_at_30(monkeypatch)
    with pytest.warns(RunWarning, match="keyframe 30 .*l999"):
        (isam,) = _room_pass(["isam2"])
    assert "partial" not in isam.stats and isam.stats["graph_repairs"] == 1
    assert "l999" in isam.stats["graph_repair_log"][0]
    assert len(isam.times) > 30 and np.all(np.isfinite(isam.poses))
    truth = evaluation.interpolate_poses(isam.truth_t, isam.truth, isam.times)
    assert evaluation.ate(isam.poses, truth)["rmse"] < 0.1


def test_backend_failure_mid_run_returns_the_result_up_to_the_last_good_keyframe(monkeypatch):
    """A keyframe no repair can save (every repair fails): the pipeline stops feeding iSAM2
    and its result holds keyframes 0-29 with stats["partial"] naming keyframe, time and
    variable; the EKF in the same pass runs on."""
    _unconstrained_at_30(monkeypatch)

    def no_repair(self, reason, keys, bad=None):
        self.failed = f"iSAM2 could not solve keyframe {self.k}: {reason}"
        raise BackendError(self.failed)

    monkeypatch.setattr(GraphBackend, "_repair", no_repair)
    ekf, isam = _room_pass(["ekf", "isam2"])
    part = isam.stats["partial"]
    assert part["keyframe"] == 30 and "l999" in part["error"] and part["t"] > 0
    json.dumps(part)
    assert len(isam.times) == 30 and np.all(np.isfinite(isam.poses))
    assert "partial" not in ekf.stats and len(ekf.times) > 30
    truth = evaluation.interpolate_poses(isam.truth_t, isam.truth, isam.times)
    assert evaluation.ate(isam.poses, truth)["rmse"] < 0.1


def test_cli_run_takes_the_association_option(tmp_path):
    """``fgslam run --association nn|jcbb``: both run; only JCBB searches hypotheses; map.json
    says each landmark's status."""
    from fgslam.cli import main

    log = tmp_path / "s.log.gz"
    assert main(["simulate", "--seed", "1", "--duration", "12", "--out", str(log)]) == 0
    stats = {}
    for method in ("nn", "jcbb"):
        out = tmp_path / method
        args = ["run", str(log), "--backend", "ekf", "--association", method, "--out", str(out)]
        assert main(args) == 0
        stats[method] = json.loads((out / "report.json").read_text())["statistics"]
        lms = json.loads((out / "map.json").read_text())["landmarks"]
        assert lms and all(lm["status"] in ("confirmed", "unreliable") for lm in lms)
    jc = stats["jcbb"]
    assert jc.get("jcbb_nodes", 0) + jc.get("jcbb_nearest_compatible", 0) > 0
    assert "jcbb_nodes" not in stats["nn"] and "jcbb_nearest_compatible" not in stats["nn"]
    with pytest.raises(SystemExit):
        main(["run", str(log), "--association", "greedy", "--out", str(tmp_path / "x")])


def test_two_disjoint_segments_of_one_wall_may_share_a_line():
    """The documented exception to mutual exclusion: one wall seen as two segments (an
    occluder in front of its middle) gives two line features that both observe the wall;
    two overlapping segments may not."""
    from fgslam.frontend.features import End

    def line(y0, y1):
        return Feature(
            "line",
            np.array([0.0, 2.0]),
            np.diag([1e-4, 1e-4]),
            "laser",
            np.array([(2.0, y0), (2.0, y1)]),
            End.OUTLIERS,
            End.OUTLIERS,
        )

    means = {0: np.array([0.0, 2.0])}
    ends = np.array([(2.0, -3.0), (2.0, 3.0)])
    cands = [Candidate(0, "line", ends)]

    def estimate(lids):
        P = np.eye(3 + 2 * len(lids)) * 1e-6
        return {i: means[i] for i in lids}, P

    a = association.associate(
        [line(-2.5, -0.5), line(0.5, 2.5)], np.zeros(3), cands, means, estimate
    )
    assert a.pairs == [0, 0]
    a = association.associate(
        [line(-2.5, 0.5), line(-0.5, 2.5)], np.zeros(3), cands, means, estimate
    )
    assert sorted(a.pairs, key=str) == [0, None]
