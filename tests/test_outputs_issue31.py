"""Outputs never crash (issue 31, item 4): every output of a finished or partial run is
written whatever the trajectory's length or the reference's coverage; a metric that cannot be
computed is left out with its reason; an output that fails is warned about and listed, and
the others are still written.

Partial runs come from the real pipeline on a short simulated log with a backend failure
injected at a chosen keyframe (as an indeterminate system would fail it), so the result has
the shape a real one has: the odometry track covers every keyframe, the estimate stops at
the failure (the cause of the crash on acapulco-corrected, iSAM2 laser)."""

from __future__ import annotations

import dataclasses
import json
import math
from collections import Counter

import numpy as np
import pytest

from fgslam.cli import main
from fgslam.errors import UserError
from fgslam.evaluation import metrics as evaluation
from fgslam.events import TruthPose
from fgslam.sim.scenes import room_events
from fgslam.slam import outputs, runner
from fgslam.slam.compare import markdown_table, plot_comparison
from fgslam.slam.graph_solve import BackendError
from fgslam.slam.outputs import write_outputs
from fgslam.slam.runner import SlamResult, run_slam

FILES = ("trajectory.tum", "map.json", "report.json", "map.png")


def _partial_run(monkeypatch, fail_at: int | None, truth: bool = True) -> SlamResult:
    """EKF, laser, on 6 s of the simulated room (7 keyframes); the backend fails at keyframe
    ``fail_at`` (None: never)."""
    evs, cfg, _ = room_events(0, 6.0)
    if not truth:
        evs = tuple(e for e in evs if not isinstance(e, TruthPose))
    if fail_at is not None:
        keyframe = runner._Session.keyframe

        def failing(self, t, *args, **kwargs):
            if self.k + 1 >= fail_at:
                self.k += 1
                raise BackendError(f"injected failure at keyframe {self.k}")
            return keyframe(self, t, *args, **kwargs)

        with monkeypatch.context() as m:
            m.setattr(runner._Session, "keyframe", failing)
            return run_slam(evs, cfg, "ekf", "laser")
    return run_slam(evs, cfg, "ekf", "laser")


def _written(folder) -> None:
    for name in FILES:
        assert (folder / name).stat().st_size > 0 or name == "trajectory.tum", name


def _strict_json(path) -> dict:
    """report.json parsed as strict JSON (NaN or Infinity in it: an error)."""

    def refuse(c):
        raise AssertionError(f"{path.name} holds {c}")

    return json.loads(path.read_text(), parse_constant=refuse)


def _result(times, poses, truth_t, truth, odometry=None) -> SlamResult:
    poses = np.asarray(poses, dtype=float).reshape(-1, 3)
    times = np.asarray(times, dtype=float)
    return SlamResult(
        backend="isam2",
        sensors="laser",
        times=times,
        poses=poses,
        covs=[np.eye(3) * 0.01] * len(poses),
        filtered=poses,
        odometry=poses if odometry is None else np.asarray(odometry, dtype=float),
        landmarks={},
        means={},
        landmark_covs={},
        truth_t=np.asarray(truth_t, dtype=float),
        truth=np.asarray(truth, dtype=float).reshape(-1, 3),
        latencies=[0.01] * len(poses),
        wall_time=1.0,
        log_duration=10.0,
        stats=Counter(),
    )


def _evaluate(tmp_path, run_dir, res: SlamResult, capsys) -> tuple[int, dict]:
    """fgslam evaluate of a run's folder against its reference (as a TUM file)."""
    ref = tmp_path / "reference.tum"
    evaluation.write_tum(ref, res.truth_t, res.truth)
    out = tmp_path / "evaluation.json"
    rc = main(["evaluate", str(run_dir), "--reference", str(ref), "--out", str(out)])
    capsys.readouterr()
    return rc, (json.loads(out.read_text()) if out.exists() else {})


def test_partial_run_evaluates_each_track_at_its_own_times(tmp_path, monkeypatch):
    """The acapulco crash: the backend failed mid-run, so the estimate has fewer poses than
    the odometry track; each is evaluated at its own times (odometry: the same ATE as in a
    run that did not fail), and every output is written."""
    full = _partial_run(monkeypatch, None)
    res = _partial_run(monkeypatch, 4)
    assert len(res.times) == 4 and len(res.odometry) == len(full.odometry) > 4
    rep = write_outputs(res, tmp_path / "run")
    _written(tmp_path / "run")
    full_rep = write_outputs(full, tmp_path / "full")
    assert rep["partial"]["keyframe"] == 4
    assert rep["ate"]["poses_compared"] == 4
    assert rep["ate_odometry"]["poses_compared"] == len(full.odometry)
    assert rep["ate_odometry"]["rmse"] == pytest.approx(full_rep["ate_odometry"]["rmse"])
    assert "output_errors" not in rep
    plot_comparison([res, full], tmp_path / "comparison.png")
    assert "(PARTIAL)" in markdown_table([rep, full_rep])


def test_reference_covering_part_of_the_run(tmp_path):
    """A reference that ends halfway: only the poses within its time span are compared (not
    the rest against its last pose), and the report says how many."""
    t = np.arange(10.0)
    poses = np.column_stack([t, np.zeros(10), np.zeros(10)])
    poses[5:, 1] = 1.0  # off the reference's line, but after the reference ends
    truth = np.column_stack([t[:5], np.zeros(5), np.zeros(5)])
    rep = write_outputs(_result(t, poses, t[:5], truth), tmp_path)
    _written(tmp_path)
    assert rep["ate"]["poses_compared"] == 5 and rep["ate"]["poses_outside_reference"] == 5
    assert rep["ate"]["rmse"] == pytest.approx(0.0, abs=1e-12)
    assert rep["final_pose_error"]["t"] == 4.0
    assert rep["final_pose_error"]["position_m"] == pytest.approx(0.0, abs=1e-12)


def test_no_reference(tmp_path, monkeypatch, capsys):
    """A reference that covers none of the run, and no reference at all (a partial run of a
    log without truth): outputs written, no ATE and the report says why; `fgslam evaluate`
    writes its evaluation with 0 poses compared."""
    t = np.arange(10.0)
    poses = np.column_stack([t, np.zeros(10), np.zeros(10)])
    later = _result(t, poses, t + 100.0, poses)  # the reference starts after the run
    rep = write_outputs(later, tmp_path / "later")
    _written(tmp_path / "later")
    assert "ate" not in rep and "final_pose_error" not in rep
    assert rep["not_evaluated"]["ate"].startswith("0 of 10 poses")
    rc, ev = _evaluate(tmp_path, tmp_path / "later", later, capsys)
    assert rc == 0 and ev["poses_compared"] == 0 and "ate" in ev["not_evaluated"]

    res = _partial_run(monkeypatch, 3, truth=False)
    rep = write_outputs(res, tmp_path / "none")
    _written(tmp_path / "none")
    plot_comparison([res], tmp_path / "none.png")
    assert "ate" not in rep and "reference" in rep["not_evaluated"]["ate"]


def test_run_of_one_pose(tmp_path, monkeypatch, capsys):
    """One keyframe before the failure: no alignment (the report says so), the unaligned
    final error is given, odometry is evaluated over its own keyframes; `fgslam evaluate`
    writes the unaligned ATE."""
    res = _partial_run(monkeypatch, 1)
    assert len(res.times) == 1 and len(res.odometry) > 1
    rep = write_outputs(res, tmp_path / "run")
    _written(tmp_path / "run")
    assert "ate" not in rep and "no alignment" in rep["not_evaluated"]["ate"]
    assert rep["final_pose_error"]["position_m"] < 0.05
    assert rep["ate_odometry"]["poses_compared"] == len(res.odometry)
    plot_comparison([res], tmp_path / "comparison.png")
    rc, ev = _evaluate(tmp_path, tmp_path / "run", res, capsys)
    assert rc == 0 and ev["poses_compared"] == 1 and "ate_unaligned" in ev
    assert "no alignment" in ev["not_evaluated"]["ate"]


def test_run_of_zero_poses(tmp_path, monkeypatch, capsys):
    """The backend failed at its first keyframe: every output written (an empty
    trajectory), the comparison figure drawn, `fgslam evaluate` writes 0 poses compared."""
    res = _partial_run(monkeypatch, 0)
    assert len(res.times) == 0 and len(res.odometry) > 1
    plot_comparison([res], tmp_path / "comparison.png")
    assert (tmp_path / "comparison.png").stat().st_size > 0
    rep = write_outputs(res, tmp_path / "run")
    _written(tmp_path / "run")
    assert rep["poses"] == 0 and "ate" not in rep and "ate" in rep["not_evaluated"]
    assert rep["ate_odometry"]["poses_compared"] == len(res.odometry)
    rc, ev = _evaluate(tmp_path, tmp_path / "run", res, capsys)
    assert rc == 0 and ev["poses_compared"] == 0


@pytest.mark.filterwarnings("error")  # no numpy overflow/invalid warnings either
def test_huge_and_non_finite_poses(tmp_path):
    """A diverged estimate (a NaN pose, a pose at 1e300 m) and odometry gone to infinity:
    every output written, report.json strict JSON with the reasons, trajectory.tum readable
    (the bad poses left out and counted), the comparison drawn."""
    t = np.arange(8.0)
    truth = np.column_stack([t, np.zeros(8), np.zeros(8)])
    poses = truth.copy()
    poses[3] = (np.nan, np.nan, np.nan)
    poses[5] = (1e300, -1e300, 0.0)
    odo = truth.copy()
    odo[6] = (np.inf, 0.0, 0.0)
    res = _result(t, poses, t, truth, odometry=odo)
    rep = write_outputs(res, tmp_path)
    _written(tmp_path)
    stored = _strict_json(tmp_path / "report.json")
    assert stored["not_evaluated"]["ate"] == "estimate: 1 of 8 poses are not finite"
    assert "not finite" in stored["not_evaluated"]["ate_odometry"]
    assert rep["trajectory_poses_left_out"] == 2
    t_back, _ = evaluation.read_tum(tmp_path / "trajectory.tum")
    assert len(t_back) == 6
    big = _result(t, np.where(np.isfinite(poses), poses, 0.0), t, truth)
    assert "overflows" in write_outputs(big, tmp_path / "big")["not_evaluated"]["ate"]
    plot_comparison([res], tmp_path / "comparison.png")


def test_evaluation_refuses_mismatched_shapes_with_a_clear_error():
    """ate, align_se2 and nees name the mismatch (a project error), not numpy broadcasting."""
    a, b = np.zeros((858, 3)), np.zeros((449, 3))
    for call in (
        lambda: evaluation.ate(a, b),
        lambda: evaluation.align_se2(a, b),
        lambda: evaluation.nees(a, np.tile(np.eye(3), (858, 1, 1)), b),
    ):
        with pytest.raises(UserError, match="858 poses, reference 449"):
            call()
    with pytest.raises(UserError, match="at least 2"):
        evaluation.align_se2(a[:1], b[:1])
    with pytest.raises(UserError, match="expected 2 3x3 covariances"):
        evaluation.nees(a[:2], np.eye(3), b[:2])


def test_a_failing_output_leaves_the_others_written(tmp_path, monkeypatch):
    """map.png fails: a one-line warning naming it and the cause, listed in report.json,
    the stale map.png of an earlier run removed, the other outputs written."""
    res = _result(np.arange(5.0), np.zeros((5, 3)), np.arange(5.0), np.zeros((5, 3)))
    (tmp_path / "map.png").write_bytes(b"an earlier run's")

    def broken(*args, **kwargs):
        raise RuntimeError("no space left on device\nsecond line")

    monkeypatch.setattr(outputs, "plot_map", broken)
    with pytest.warns(
        UserWarning, match=r"^map.png not written: RuntimeError: no space left on device$"
    ):
        rep = write_outputs(res, tmp_path)
    errors = [{"output": "map.png", "error": "RuntimeError: no space left on device"}]
    assert rep["output_errors"] == errors
    assert _strict_json(tmp_path / "report.json")["output_errors"] == errors
    assert not (tmp_path / "map.png").exists()
    for name in ("trajectory.tum", "map.json"):
        assert (tmp_path / name).stat().st_size > 0


def test_a_failing_output_is_an_error_in_the_tests(tmp_path, monkeypatch):
    """The test suite turns the warning into an error (pyproject's filterwarnings), so an
    output that fails in any test is not lost in a warning summary."""
    res = _result(np.arange(5.0), np.zeros((5, 3)), np.arange(5.0), np.zeros((5, 3)))
    monkeypatch.setattr(outputs, "map_dict", lambda res: 1 / 0)
    with pytest.raises(UserWarning, match=r"map\.json not written: ZeroDivisionError"):
        write_outputs(res, tmp_path)


def test_cli_run_reports_a_failing_output_in_one_line(tmp_path, monkeypatch, capsys):
    """`fgslam run` with map.png failing: the other files (the dense trajectory too) are
    written, one warning line names map.png and the cause, the exit status is 1."""
    log = tmp_path / "sim.log.gz"
    assert main(["simulate", "--seed", "2", "--duration", "5", "--out", str(log)]) == 0
    monkeypatch.setattr(outputs, "plot_map", lambda *a, **k: math.sqrt(-1))
    out = tmp_path / "run"
    rc = main(["run", str(log), "--backend", "ekf", "--sensors", "laser", "--out", str(out)])
    err = capsys.readouterr().err
    assert rc == 1
    assert "fgslam run: warning: map.png not written: ValueError: math domain error\n" in err
    assert "Traceback" not in err
    rep = json.loads((out / "report.json").read_text())
    assert [e["output"] for e in rep["output_errors"]] == ["map.png"]
    for name in ("trajectory.tum", "trajectory_dense.tum", "map.json"):
        assert (out / name).stat().st_size > 0


def test_compare_writes_the_other_outputs_when_one_fails(tmp_path, monkeypatch):
    """compare: comparison.png fails; comparison.json and comparison.md are written, the
    table names what was not written."""
    from fgslam.slam import compare as cmp

    log = tmp_path / "sim.log.gz"
    assert main(["simulate", "--seed", "2", "--duration", "5", "--out", str(log)]) == 0

    def broken(*args, **kwargs):
        raise MemoryError("figure too large")

    monkeypatch.setattr(cmp, "plot_comparison", broken)
    out = tmp_path / "cmp"
    with pytest.warns(UserWarning, match=r"comparison\.png not written: MemoryError"):
        rows = cmp.compare(log, out, backends=("ekf",), sensors=("laser",), workers=1)
    assert len(rows) == 1 and "output_errors" not in rows[0]
    assert json.loads((out / "comparison.json").read_text())[0]["backend"] == "ekf"
    assert (
        "Not written: comparison.png (MemoryError: figure too large)"
        in (out / "comparison.md").read_text()
    )
    assert not (out / "comparison.png").exists()


def test_tracks_carry_their_own_times():
    """SlamResult.tracks: each track with its own times (the estimate's by default)."""
    res = _result(np.arange(3.0), np.zeros((3, 3)), [], [])
    assert [len(t) for t, _ in res.tracks().values()] == [3, 3, 3]
    longer = dataclasses.replace(res, odometry=np.zeros((5, 3)), odometry_times=np.arange(5.0))
    assert len(longer.tracks()["odometry"][0]) == 5
