"""The trajectory between keyframes (nearest keyframe composed with odometry) and the
relations benchmark (fgslam.evaluation.dense): hand-computed cases, a run's trajectory_dense.tum,
the
evaluate command, and the known figures of the shared logs."""

from __future__ import annotations

import math

import numpy as np
import pytest
from readers_helpers import DATA

from factors.odometry import integrate_poses
from fgslam.cli import main
from fgslam.evaluation.dense import (
    dense_poses,
    odometry_path,
    read_relations,
    relations_error,
    write_dense_trajectory,
)
from fgslam.evaluation.metrics import read_tum

INTEL = DATA / "intel-corrected"
FREIBURG = DATA / "freiburg-079-corrected"


def test_nearest_keyframe_composed_with_odometry():
    """Keyframes at t = 0 and 10 (the second one off the odometry by a 90 deg turn of the
    frame); odometry drives straight at 1 m/s. At t = 2 the nearest keyframe is the first:
    (2, 0, 0); at t = 8 it is the second one, (0, 5, pi/2), moved back 2 m along its own
    heading: (0, 3, pi/2). Interpolating between the keyframes would give neither."""
    kf_t = [0.0, 10.0]
    kf = [(0.0, 0.0, 0.0), (0.0, 5.0, math.pi / 2)]
    ot = np.arange(0.0, 10.01, 0.5)
    op = np.column_stack([ot, np.zeros_like(ot), np.zeros_like(ot)])
    got = dense_poses(kf_t, kf, ot, op, [2.0, 8.0, 0.0, 10.0])
    assert got == pytest.approx(
        np.array([[2, 0, 0], [0, 3, math.pi / 2], [0, 0, 0], [0, 5, math.pi / 2]]), abs=1e-12
    )


def test_odometry_path_from_samples():
    s = [(1.0, 0.1, 0.1), (2.0, 0.1, 0.1), (3.0, 0.2, 0.0)]
    t, p = odometry_path(s, 0.5)
    assert t.tolist() == [1.0, 1.0, 2.0, 3.0]
    assert p[0] == pytest.approx([0, 0, 0])
    assert p[1:] == pytest.approx(integrate_poses([0.1, 0.1, 0.2], [0.1, 0.1, 0.0], 0.5))


def test_relations_error_hand_computed():
    """A straight trajectory at 1 m/s: relation (1, 3) true motion (2, 0.1, 0.05): errors
    0.1 m and 0.05 rad; relation (0, 2) exact; relation (5, 20) outside the span: left out.
    Mean 0.05 m, std 0.05, max 0.1."""
    t = np.arange(0.0, 10.01, 1.0)
    traj = np.column_stack([t, np.zeros_like(t), np.zeros_like(t)])
    rel = np.array([[1, 3, 2.0, 0.1, 0.05], [0, 2, 2.0, 0.0, 0.0], [5, 20, 1.0, 0.0, 0.0]])
    r = relations_error(rel, t, traj)
    assert r["relations_used"] == 2 and r["relations_outside"] == 1
    assert r["trans_mean"] == pytest.approx(0.05) and r["trans_std"] == pytest.approx(0.05)
    assert r["trans_max"] == pytest.approx(0.1)
    assert r["rot_max_deg"] == pytest.approx(math.degrees(0.05))
    with pytest.raises(ValueError, match="nothing to compare"):
        relations_error(rel[2:], t, traj)


def test_dense_file_and_evaluate_relations(tmp_path, capsys):
    """trajectory_dense.tum holds every odometry and keyframe time; `fgslam evaluate DIR
    --relations` uses it and reports mean +- std; a relations file outside the run's time
    span is an error, not a number."""
    kf_t = [0.0, 4.0]
    kf = [(0.0, 0.0, 0.0), (2.0, 0.0, 0.0)]
    samples = [(0.5 * k, 0.25, 0.25) for k in range(1, 9)]  # 0.5 m/s straight
    run = tmp_path / "run"
    run.mkdir()
    (run / "trajectory.tum").write_text("0 0 0 0 0 0 0 1\n4 2 0 0 0 0 0 1\n", encoding="utf-8")
    n = write_dense_trajectory(run / "trajectory_dense.tum", kf_t, kf, samples, 0.5)
    t, p = read_tum(run / "trajectory_dense.tum")
    assert n == 9 and t.tolist() == [0.5 * k for k in range(9)]
    assert p[:, 0] == pytest.approx(0.25 * np.arange(9))
    rel = tmp_path / "r.relations"
    rel.write_text("# t1 t2 x y z r p yaw\n1 3 1.1 0 0 0 0 0\n", encoding="utf-8")
    assert main(["evaluate", str(run), "--relations", str(rel)]) == 0
    out = capsys.readouterr().out
    assert "translation 0.100 +- 0.000 m" in out and "trajectory_dense.tum" in out
    rel.write_text("100 103 1 0 0 0 0 0\n", encoding="utf-8")
    assert main(["evaluate", str(run), "--relations", str(rel)]) == 2
    assert "nothing to compare" in capsys.readouterr().err


@pytest.mark.skipif(not (FREIBURG.with_suffix(".log.gz")).exists(), reason="no shared data")
def test_known_figures_of_the_corrected_poses():
    """The corrected (GMapping) poses with the logs' odometry records score the check
    figures that come with the benchmark data: intel 0.054 m and freiburg-079 0.058 m (+-0.005);
    the odometry alone 7.4 and 6.5 m."""
    from fgslam.evaluation.dense import relations_error_chain
    from fgslam.io.readers.carmen import odometry_chain

    expect = {INTEL: (0.054, 2983, 7.4), FREIBURG: (0.058, 1685, 6.5)}
    for name, (trans, n, odo) in expect.items():
        chain = odometry_chain(name.with_suffix(".log.gz"))
        rel = read_relations(name.with_suffix(".relations"))
        has = np.ones(len(chain.scan_t), dtype=bool)
        r = relations_error_chain(rel, chain, chain.scan_poses, has)
        assert r["relations_used"] == n
        assert r["trans_mean"] == pytest.approx(trans, abs=0.005), name.name
        o = relations_error_chain(rel, chain, chain.poses[chain.scan_records()], has)
        assert o["trans_mean"] == pytest.approx(odo, abs=0.05), name.name
    assert r["rot_mean_deg"] == pytest.approx(0.72, abs=0.05)  # freiburg-079


def test_chain_poses_hand_computed():
    """Scans at t = 0 (estimate (0, 0, 0)) and t = 2 (estimate (0, 5, pi/2)); odometry records
    in file order: the scan, r1 at 0.5 (1 m ahead), r2 stamped 0.2 (junk: backwards, but
    2 m ahead in the file), the scan at 2 (3 m ahead), r3 at 2.6 (4 m ahead). End at 0.2 ->
    record r2, scans around it in the file: 0 and 2, nearer 0: (2, 0, 0). End at 2.5 ->
    r3, scan 2: (0, 5) moved 1 m along pi/2: (0, 6, pi/2). A scan without an estimate is
    replaced by its neighbour in the file."""
    from fgslam.evaluation.dense import OdometryChain, chain_poses

    ch = OdometryChain(
        t=np.array([0.0, 0.5, 0.2, 2.0, 2.6]),
        scan=np.array([0, 0, 0, 1, 1]),
        is_scan=np.array([True, False, False, True, False]),
        poses=np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0], [4, 0, 0]], float),
        scan_t=np.array([0.0, 2.0]),
        scan_poses=np.zeros((2, 3)),
    )
    est = np.array([[0, 0, 0], [0, 5, math.pi / 2]])
    got = chain_poses(ch, est, np.array([True, True]), [0.2, 2.5])
    assert got == pytest.approx(np.array([[2, 0, 0], [0, 6, math.pi / 2]]), abs=1e-12)
    got = chain_poses(ch, est, np.array([False, True]), [0.2])
    assert got == pytest.approx(np.array([[0, 4, math.pi / 2]]), abs=1e-12)  # from scan 2


def test_evaluate_with_the_logs_odometry_records(tmp_path, capsys):
    """`fgslam evaluate TRAJ --relations R --odometry-log LOG` on a synthetic corrected log:
    the reference poses as the estimate score 0 on relations between its scans; a file that
    is no log is a one-line error."""
    from readers_helpers import carmen_text, path, rel

    from fgslam.evaluation.metrics import write_tum

    log = tmp_path / "room.log"
    text = carmen_text(corrected=True)
    log.write_text(text)
    truth = path(30)
    write_tum(tmp_path / "est.tum", 1.0 + np.arange(30), np.array(truth))
    r = tmp_path / "r.relations"
    rows = [
        f"{1 + k} {3 + k} {' '.join(str(v) for v in rel(truth[k], truth[k + 2])[:2])} 0 0 0 "
        f"{rel(truth[k], truth[k + 2])[2]}"
        for k in range(20)
    ]
    r.write_text("\n".join(rows) + "\n")
    args = ["evaluate", str(tmp_path / "est.tum"), "--relations", str(r)]
    assert main([*args, "--odometry-log", str(log)]) == 0
    out = capsys.readouterr().out
    assert "translation 0.000 +- 0.000 m" in out
    assert main([*args, "--odometry-log", str(tmp_path / "est.tum")]) == 2
    assert "unknown log format" in capsys.readouterr().err


def test_relation_scan_pairs_match_stamps_and_distance():
    from fgslam.evaluation.dense import relation_scan_pairs

    stamps = np.array([0.0, 0.5, 1.0, 1.5, 2.0])
    rel = np.array(
        [
            [0.0, 1.0, 0.3, 0.0, 0.1],  # both ends scans
            [0.5004, 2.0, 0.2, 0.1, 0.0],  # within 1 ms
            [0.7, 1.0, 0.1, 0.0, 0.0],  # t1 between scans
            [1.0, 2.0, 3.0, 0.0, 0.0],  # too long
            [1.5, 9.0, 0.1, 0.0, 0.0],  # beyond the last scan
        ]
    )
    got = relation_scan_pairs(rel, stamps, max_distance=1.0)
    assert [(i, j) for i, j, _ in got] == [(0, 2), (1, 4)]
    np.testing.assert_allclose(got[0][2], [0.3, 0.0, 0.1])
    assert len(relation_scan_pairs(rel, stamps)) == 3
    assert relation_scan_pairs(rel, []) == []
