"""Evaluation metrics against hand-computed cases; fgslam evaluate on the command line."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from fgslam.cli import main
from fgslam.evaluation import metrics as ev


def straight(n: int, step: float = 1.0) -> np.ndarray:
    return np.column_stack([np.arange(n) * step, np.zeros(n), np.zeros(n)])


def test_ate_of_a_rigidly_moved_copy_is_zero_after_alignment():
    ref = np.array([[0, 0, 0], [1, 0, 0.1], [2, 1, 0.5], [2, 3, 1.5]], dtype=float)
    c, s = math.cos(0.7), math.sin(0.7)
    est = ref.copy()
    est[:, 0] = c * ref[:, 0] - s * ref[:, 1] + 5
    est[:, 1] = s * ref[:, 0] + c * ref[:, 1] - 2
    est[:, 2] = ref[:, 2] + 0.7
    a = ev.ate(est, ref)
    assert a["rmse"] == pytest.approx(0, abs=1e-12)
    assert a["heading_rmse_deg"] == pytest.approx(0, abs=1e-9)
    # without alignment: every point moved; the first one by |(5, -2)|
    assert ev.position_errors(est, ref, align=False)[0] == pytest.approx(math.hypot(5, 2))


def test_ate_hand_computed():
    """Errors 0, 0, 3 and 4 m against a reference whose alignment is the identity (the
    estimate is offset symmetrically): RMSE sqrt(25/4), mean 7/4, max 4."""
    ref = np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0], [10, 10, 0]], dtype=float)
    est = ref.copy()
    est[2, 1] += 3.0
    est[3, 1] += 4.0
    a = ev.ate(est, ref, align=False)
    assert (a["rmse"], a["mean"], a["max"]) == pytest.approx((2.5, 1.75, 4.0))


def test_rpe_constant_scale_error():
    """Estimate steps 1.1 m where the reference steps 1 m: over 1 m every pair is one step
    apart with a 0.1 m translation error and no rotation error; over 2 m, two steps: 0.2 m."""
    ref = straight(11)
    est = straight(11, 1.1)
    r = ev.rpe(est, ref, 1.0)
    assert r["pairs"] == 10
    assert (r["trans_rmse"], r["trans_mean"], r["trans_max"]) == pytest.approx((0.1, 0.1, 0.1))
    assert r["rot_rmse_deg"] == pytest.approx(0.0)
    assert ev.rpe(est, ref, 2.0)["trans_max"] == pytest.approx(0.2)
    assert ev.rpe(est, ref, 1.5)["pairs"] == 9  # pairs two steps apart
    assert ev.rpe(est, ref, 100.0)["pairs"] == 0


def test_rpe_rotation_error_is_seen_in_the_frame_of_the_first_pose():
    """The estimate turns 0.1 rad more than the reference at pose 1 and then drives 1 m
    straight: over 1 m the pair (1, 2) has a rotation error of 0 and a translation error of
    |R(0.1) (1, 0) - (1, 0)| in pose 1's frame, i.e. 2 sin(0.05); the pair (0, 1) has only
    the 0.1 rad rotation error."""
    ref = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0]], dtype=float)
    est = np.array([[0, 0, 0], [1, 0, 0.1], [1 + math.cos(0.1), math.sin(0.1), 0.1]])
    r = ev.rpe(est, ref, 1.0)
    assert r["pairs"] == 2
    assert r["rot_max_deg"] == pytest.approx(math.degrees(0.1))
    assert r["trans_max"] == pytest.approx(0.0, abs=1e-12)  # the motion is the same length
    # now the estimate drives the second metre straight on in the world frame
    est[2] = [2, 0, 0.1]
    r = ev.rpe(est, ref, 1.0)
    assert r["trans_max"] == pytest.approx(2 * math.sin(0.05))


def test_nees_hand_computed():
    """Errors (0.1, 0, 0) with variance 4 in x: 0.0025; (0, 2, 0.1) with variances 1 and
    0.01: 4 + 1 = 5. The chi-square(3) 95 % interval is [0.216, 9.35]: one of two inside."""
    est = np.array([[0.1, 0.0, 0.0], [0.0, 2.0, 0.1]])
    ref = np.zeros((2, 3))
    cov = np.array([np.diag([4.0, 1.0, 1.0]), np.diag([1.0, 1.0, 0.01])])
    n = ev.nees(est, cov, ref)
    assert n["mean"] == pytest.approx((0.0025 + 5.0) / 2)
    assert n["within_95"] == pytest.approx(0.5)


def test_scale_about_start_takes_out_a_map_scale():
    """A trajectory scaled by 1.004 about its first pose (headings unchanged) plus small
    noise: the factor found is 1 / 1.004 to the noise, the scaled copy is back on the
    reference, headings and the first pose untouched; a hand case: (0,0), (2,0), (0,2)
    against (0,0), (1,0), (0,1) gives k = 0.5."""
    rng = np.random.default_rng(2)
    ref = np.column_stack([rng.uniform(-20, 20, (50, 2)), rng.uniform(-3, 3, 50)])
    ref[0] = (1.0, -2.0, 0.3)
    est = ref.copy()
    est[:, :2] = ref[0, :2] + 1.004 * (ref[:, :2] - ref[0, :2]) + rng.normal(0, 1e-4, (50, 2))
    est[0] = ref[0]
    scaled, k = ev.scale_about_start(est, ref)
    assert k == pytest.approx(1 / 1.004, abs=2e-6)
    np.testing.assert_allclose(scaled[:, :2], ref[:, :2], atol=5e-4)
    np.testing.assert_array_equal(scaled[:, 2], est[:, 2])
    np.testing.assert_array_equal(scaled[0], est[0])
    hand = np.array([[0.0, 0, 0], [2, 0, 0], [0, 2, 0]])
    assert ev.scale_about_start(hand, hand / [2, 2, 1])[1] == pytest.approx(0.5)


def test_match_times_interpolates_and_drops_outside():
    t_ref = np.array([0.0, 1.0, 2.0])
    ref = np.array([[0, 0, 0], [1, 0, 0], [1, 1, math.pi / 2]], dtype=float)
    mask, r = ev.match_times([-1.0, 0.5, 1.5, 3.0], t_ref, ref)
    assert mask.tolist() == [False, True, True, False]
    assert r == pytest.approx(np.array([[0.5, 0, 0], [1, 0.5, math.pi / 4]]))
    with pytest.raises(ValueError, match="backwards"):
        ev.match_times([0.5], [1.0, 0.0], ref[:2])


def test_map_error_hand_computed():
    true_map = {
        "lines": [{"alpha": 0.0, "d": 2.0}, {"alpha": math.pi / 2, "d": 3.0}],
        "corners": [{"x": 1.0, "y": 1.0}],
        "points": [{"x": 5.0, "y": 5.0}],
    }
    lms = [
        {"kind": "line", "alpha": 0.01, "d": 2.1},
        {"kind": "corner", "x": 1.3, "y": 1.4},
        {"kind": "point", "x": 1.0, "y": 1.2},  # nearer to the corner than to the point
    ]
    m = ev.map_error(lms, true_map)
    assert m["line_d"]["median"] == pytest.approx(0.1)
    assert m["line_alpha_deg"]["median"] == pytest.approx(math.degrees(0.01))
    assert m["corner"]["median"] == pytest.approx(0.5)
    assert m["point"]["median"] == pytest.approx(0.2)


def test_tum_and_covariances_round_trip(tmp_path):
    t = np.array([0.5, 1.5, 2.5])
    p = np.array([[0, 0, 0], [1, 2, 3.0], [-1, 0, -3.0]])
    ev.write_tum(tmp_path / "a.tum", t, p)
    t2, p2 = ev.read_tum(tmp_path / "a.tum")
    assert t2 == pytest.approx(t) and p2 == pytest.approx(p, abs=1e-6)
    covs = np.array([np.eye(3) * k for k in (1.0, 2.0, 3.0)])
    ev.write_covariances(tmp_path / "a.cov", t, covs)
    t3, c3 = ev.read_covariances(tmp_path / "a.cov")
    assert t3 == pytest.approx(t) and c3 == pytest.approx(covs)


def test_evaluate_command(tmp_path, capsys):
    """fgslam evaluate: the estimate is the reference with every step 10 % long."""
    t = np.arange(11.0)
    ev.write_tum(tmp_path / "ref.tum", t, straight(11))
    ev.write_tum(tmp_path / "est.tum", t + 0.5, straight(11, 1.1))  # stamped half a step late
    covs = np.array([np.eye(3)] * 11)
    ev.write_covariances(tmp_path / "est.cov", t + 0.5, covs)
    out = tmp_path / "report.json"
    rc = main(
        [
            "evaluate",
            str(tmp_path / "est.tum"),
            "--reference",
            str(tmp_path / "ref.tum"),
            "--covariances",
            str(tmp_path / "est.cov"),
            "--out",
            str(out),
        ]
    )
    assert rc == 0
    rep = json.loads(out.read_text())
    assert rep["poses_compared"] == 10 and rep["poses_outside_reference"] == 1
    assert rep["rpe"]["pairs"] == 9 and rep["rpe"]["trans_max"] == pytest.approx(0.1, abs=1e-6)
    assert "nees" in rep
    assert "ATE (SE(2)-aligned)" in capsys.readouterr().out
    rc = main(["evaluate", str(tmp_path / "est.tum"), "--reference", str(tmp_path / "nope")])
    assert rc == 2
    assert "no such file" in capsys.readouterr().err


def test_evaluate_run_against_simulated_log(tmp_path, capsys):
    """A simulated log as the reference: ground truth poses and the true map; the ATE is the
    one the run reported, the map error is that of outputs.map_error."""
    log = tmp_path / "sim.log.gz"
    assert main(["simulate", "--seed", "4", "--duration", "15", "--out", str(log)]) == 0
    run = tmp_path / "run"
    assert main(["run", str(log), "--backend", "ekf", "--out", str(run)]) == 0
    out = tmp_path / "eval.json"
    assert main(["evaluate", str(run), "--reference", str(log), "--out", str(out)]) == 0
    rep = json.loads(out.read_text())
    run_rep = json.loads((run / "report.json").read_text())
    assert rep["reference_kind"] == "ground truth"
    assert rep["ate"]["rmse"] == pytest.approx(run_rep["ate"]["rmse"], abs=1e-4)
    assert rep["map_error"].keys() == run_rep["map_error"].keys()
    for k, v in rep["map_error"].items():
        assert v["n"] == run_rep["map_error"][k]["n"]
        assert v["median"] == pytest.approx(run_rep["map_error"][k]["median"], abs=1e-3)
    assert "map error" in capsys.readouterr().out
