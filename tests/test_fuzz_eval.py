"""Evaluation inputs are checked like logs (issue 39, item 4): a relations file, a TUM
trajectory, a covariance file, a map.json or a log's reference poses holding an impossible
value is a one-line error naming the file (and the line), never an inf or NaN in a report,
a numpy warning or a traceback.

Regression tests of the issue's cases, then hypothesis fuzz tests through ``fgslam evaluate``
(``fgslam.cli.main``) and the evaluation functions: a report of finite numbers, or a
UserError naming the file; anything else fails."""

from __future__ import annotations

import contextlib
import io
import json
import math
import tempfile
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fgslam.cli import main
from fgslam.errors import EvaluationError, UserError
from fgslam.evaluation import dense
from fgslam.evaluation import metrics as evaluation
from fgslam.evaluation.reference import load_reference

N = 20  # poses of the test trajectory, 0.5 s apart


def _truth(n: int = N) -> np.ndarray:
    k = np.arange(n)
    return np.column_stack([0.3 * k, 0.02 * k**2, 0.05 * k])


def _times(n: int = N) -> np.ndarray:
    return 0.5 * np.arange(n)


def _relation_lines(n: int = N) -> list[str]:
    p, t = _truth(n), _times(n).tolist()
    d = evaluation._relative_poses(p, np.arange(n - 2), np.arange(2, n)).tolist()
    return [
        f"{t[k]!r} {t[k + 2]!r} {d[k][0]!r} {d[k][1]!r} 0 0 0 {d[k][2]!r}" for k in range(n - 2)
    ]


def _tum_lines(n: int = N) -> list[str]:
    p, t = _truth(n).tolist(), _times(n).tolist()
    return [
        f"{t[k]!r} {p[k][0]!r} {p[k][1]!r} 0 0 0 {math.sin(p[k][2] / 2)!r} "
        f"{math.cos(p[k][2] / 2)!r}"
        for k in range(n)
    ]


def _evaluate(*args: str) -> tuple[int, str, str]:
    """``fgslam evaluate ARGS`` with numpy's warnings as errors: (status, stdout, stderr)."""
    out, err = io.StringIO(), io.StringIO()
    with (
        contextlib.redirect_stdout(out),
        contextlib.redirect_stderr(err),
        warnings.catch_warnings(),
        np.errstate(over="warn", invalid="warn", divide="warn", under="ignore"),
    ):
        warnings.simplefilter("error")
        rc = main(["evaluate", *args])
    return rc, out.getvalue(), err.getvalue()


def _one_line_error(err: str, *parts: str) -> None:
    assert err.startswith("fgslam evaluate: error: ") and err.count("\n") == 1, err
    for p in parts:
        assert p in err, (p, err)


def _all_finite(x) -> bool:
    if isinstance(x, dict):
        return all(_all_finite(v) for v in x.values())
    if isinstance(x, list):
        return all(_all_finite(v) for v in x)
    if isinstance(x, float):
        return math.isfinite(x)
    return True


@pytest.fixture
def traj(tmp_path: Path) -> Path:
    p = tmp_path / "est.tum"
    p.write_text("\n".join(_tum_lines()) + "\n")
    return p


def _with_line(lines: list[str], k: int, text: str) -> str:
    lines = list(lines)
    lines[k] = text
    return "\n".join(lines) + "\n"


# -- relations files -------------------------------------------------------------------------


@pytest.mark.parametrize(
    "bad, field",
    [
        ("0.5 2.5 1e308 0 0 0 0 0", "field x: 1e+308"),  # was inf in the report
        ("0.5 2.5 0.6 -1e200 0 0 0 0", "field y"),  # was inf in the report
        ("0.5 2.5 0.6 0 0 0 0 1e300", "field yaw"),  # was a meaningless finite error
        ("0.5 2.5 nan 0 0 0 0 0", "field x: nan"),
        ("inf 2.5 0.6 0 0 0 0 0", "field t1: inf"),
        ("0.5 1e300 0.6 0 0 0 0 0", "field t2"),
        ("0.5 2.5 0.6 0 1e9 0 0 0", "field z"),
        ("0.5 2.5 0.6 0 0 -inf 0 0", "field roll"),
        ("0.5 2.5 0.6 0 0 0 0", "expected 8 fields"),
        ("0.5 2.5 0.6 0 0 0 0 0 0", "expected 8 fields"),
        ("0.5 2.5 0.6 0 zz 0 0 0", "not a number"),
    ],
)
def test_absurd_relation_is_a_line_error(tmp_path, traj, bad, field):
    rel = tmp_path / "r.relations"
    rel.write_text(_with_line(_relation_lines(), 1, bad))
    rc, out, err = _evaluate(str(traj), "--relations", str(rel))
    assert rc == 2 and "inf" not in out and "nan" not in out
    _one_line_error(err, "r.relations", "line 2", field)


def test_relations_file_without_relations_is_an_error(tmp_path, traj):
    """Was a numpy UserWarning ("input contained no data") on the console."""
    rel = tmp_path / "r.relations"
    rel.write_text("# t1 t2 x y z roll pitch yaw\n\n")
    rc, _, err = _evaluate(str(traj), "--relations", str(rel))
    assert rc == 2
    _one_line_error(err, "r.relations", "no relations")


def test_read_relations_keeps_comments_and_names_the_line(tmp_path):
    p = tmp_path / "r.relations"
    p.write_text("# header\n\n1 2 0.5 0 0 0 0 0.1  # a comment\n")
    assert dense.read_relations(p).tolist() == [[1, 2, 0.5, 0, 0.1]]
    p.write_text("# header\n1 2 0.5 0 0 0 0 0.1\n1 2 0.5 0 0 0 0 nan\n")
    with pytest.raises(ValueError, match=r"^line 3: field yaw"):
        dense.read_relations(p)


def test_relations_error_that_overflows_is_an_evaluation_error():
    """An estimate far beyond any TUM file's (1e200 m) over a relation: an EvaluationError,
    never an inf in the report or an overflow warning."""
    rel = np.array([[0.0, 1.0, 1.0, 0.0, 0.0]])
    t, traj = np.array([0.0, 1.0]), np.array([[-1e200, 0, 0], [1e200, 0, 0]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(EvaluationError, match=r"overflows|not finite"):
            dense.relations_error(rel, t, traj)


# -- TUM files and references ----------------------------------------------------------------


@pytest.mark.parametrize(
    "bad, field",
    [
        ("2.5 inf 0 0 0 0 0 1", "line 6: field tx: inf"),
        ("2.5 1e308 0 0 0 0 0 1", "line 6: field tx"),
        ("2.5 0 0 0 0 0 1e300 1e300", "line 6: quaternion"),  # was an overflow warning
        ("2.5 0 0 0 0 0 0 1e-5", "line 6: quaternion"),
        ("2.5 0 0 0 0 0 0 0", "line 6: quaternion (qx qy qz qw) has zero norm"),
        ("1.0 0 0 0 0 0 0 1", "line 6: field timestamp: 1.0 is before 2.0 (line 5)"),
        ("2.5 0 0 0 0 0 1", "line 6: expected 8 columns"),
    ],
)
@pytest.mark.parametrize("role", ["estimate", "reference"])
def test_absurd_tum_line_is_a_line_error(tmp_path, traj, bad, field, role):
    tum = tmp_path / "bad.tum"
    tum.write_text(_with_line(_tum_lines(), 5, bad))
    args = [str(tum), "--reference", str(traj)]
    if role == "reference":
        args = [str(traj), "--reference", str(tum)]
    rc, _, err = _evaluate(*args)
    assert rc == 2
    _one_line_error(err, "bad.tum", field)


@pytest.mark.parametrize("value", ["1e300", "-1e300", "1e10"])
def test_absurd_truth_pose_in_a_log_is_not_compared(tmp_path, traj, value):
    """A log's truth record that no pose has (finite, 1e300 m): refused with an error naming
    the log and the record's time (fgslam.cli.evaluate), or left out by the reader; never aligned
    with the estimate (an ATE of 1e300 m or inf)."""
    from readers_helpers import write_native

    log = tmp_path / "run.log"
    write_native(log)
    lines = log.read_text().splitlines()
    k = [i for i, ln in enumerate(lines) if ln.startswith("T ")][2]  # t = 0.5 s
    f = lines[k].split()
    f[2] = value
    lines[k] = " ".join(f)
    log.write_text("\n".join(lines) + "\n")
    try:
        _, poses, _, _ = load_reference(log)
    except UserError as exc:
        assert f"run.log: truth or reference pose at t = {float(f[1])!r} s" in str(exc)
    else:
        assert (np.abs(poses[:, :2]) <= evaluation.TUM_MAX_POSITION).all()
    rep = tmp_path / "r.json"
    rc, _, err = _evaluate(str(traj), "--reference", str(log), "--out", str(rep))
    if rc == 2:
        _one_line_error(err, "run.log", f"t = {float(f[1])!r}", "not a pose")
    else:
        assert rc == 0
        got = json.loads(rep.read_text())
        assert _all_finite(got) and got["ate"]["max"] < 100


@pytest.mark.parametrize(
    "pose", [(1e300, 0.0, 0.0), (0.0, -2e9, 0.0), (0.0, 0.0, 1e300), (math.nan, 0.0, 0.0)]
)
def test_reference_poses_are_checked_as_a_tum_files(pose):
    """What a reader passes on from a log is held to a TUM file's bounds (the backstop of
    load_reference)."""
    from fgslam.evaluation.reference import _check_reference

    t, poses = _times(4), _truth(4)
    _check_reference("run.log", t, poses)
    poses[2] = pose
    with pytest.raises(UserError, match=r"^run\.log: truth or reference pose at t = 1\.0 s"):
        _check_reference("run.log", t, poses)


@pytest.mark.parametrize(
    "text, what",
    [
        ("0 1 0 0 0 1 0 0 0 nan\n", "line 1: a value is not finite"),
        ("0 1 0 0 0 1 0 0 0\n", "line 1: expected 10 columns"),
        ("# timestamp c_xx ...\n", "no covariances"),
    ],
)
def test_bad_covariance_file_is_a_line_error(tmp_path, traj, text, what):
    cov = tmp_path / "c.txt"
    cov.write_text(text)
    rc, _, err = _evaluate(str(traj), "--reference", str(traj), "--covariances", str(cov))
    assert rc == 2
    _one_line_error(err, "c.txt", what)


@pytest.mark.parametrize(
    "option", [["--rpe-delta", "nan"], ["--rpe-delta", "inf"], ["--max-gap", "nan"]]
)
def test_non_numbers_in_options_are_errors(traj, option):
    rc, out, err = _evaluate(str(traj), "--reference", str(traj), *option)
    assert rc == 2 and "nan" not in out
    _one_line_error(err, option[0])


@pytest.mark.parametrize(
    "landmark",
    [{"kind": "line", "alpha": "x", "d": 1.0}, {"kind": "corner", "x": 1.0}, "not a landmark"],
)
def test_bad_map_landmark_is_an_error(tmp_path, landmark):
    """Was a TypeError or KeyError traceback from evaluation.map_error."""
    from readers_helpers import write_native

    true_map = {"lines": [{"alpha": 0.0, "d": 1.0}], "points": [{"x": 1.0, "y": 0.0}]}
    log = tmp_path / "run.log"
    write_native(log)
    text = log.read_text().splitlines()
    k = next(i for i, ln in enumerate(text) if ln.startswith("WORLD"))
    text.insert(k + 1, "META " + json.dumps({"true_map": true_map}))
    log.write_text("\n".join(text) + "\n")
    t, poses, got, _ = load_reference(log)
    assert got == true_map
    evaluation.write_tum(tmp_path / "e.tum", t, poses)
    m = tmp_path / "map.json"
    good = {"kind": "point", "x": 0.0, "y": 0.0}
    m.write_text(json.dumps({"landmarks": [good]}))
    rc, out, _ = _evaluate(str(tmp_path / "e.tum"), "--reference", str(log), "--map", str(m))
    assert rc == 0 and "map error point" in out
    m.write_text(json.dumps({"landmarks": [good, landmark]}))
    rc, _, err = _evaluate(str(tmp_path / "e.tum"), "--reference", str(log), "--map", str(m))
    assert rc == 2
    _one_line_error(err, "map.json", "landmark 1")


# -- the evaluation functions on absurd poses ------------------------------------------------


@pytest.mark.parametrize("big", [1e155, 1e200, 1.7e308])
def test_rpe_of_absurd_positions_is_an_evaluation_error(big):
    """Was an "overflow encountered" warning and inf in the result."""
    ref = _truth()
    est = ref.copy()
    est[7, 0] = big
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(EvaluationError, match="overflows"):
            evaluation.rpe(est, ref)
        with pytest.raises(EvaluationError, match="overflows"):
            evaluation.rpe(ref, est)


def test_absurd_heading_is_interpolated_without_overflow():
    """np.unwrap of headings near the float limit overflowed ("overflow in accumulate")."""
    t = _times()
    ref = _truth()
    ref[:, 2] = np.where(np.arange(N) % 2, 1.7e308, -1.7e308)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = evaluation.interpolate_poses(t, ref, t + 0.25)
        rep = evaluation.evaluate_trajectory(t, _truth(), t, ref)
    assert np.isfinite(out).all()
    assert _all_finite({k: v for k, v in rep.items() if k != "not_evaluated"})


@pytest.mark.parametrize("big", [math.inf, math.nan, 1e200, 1.7e308])
def test_alignment_of_absurd_trajectories_is_an_evaluation_error(big):
    """The run's reference comparison (align_se2, ate, ate_at_times; e.g. a log with one
    odometry record of 1e25 ticks): an alignment of finite numbers or an EvaluationError,
    an ATE that overflows an EvaluationError, never a warning or a traceback."""
    ref = _truth()
    est = ref.copy()
    est[3:, 0] = big
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        try:
            angle, t = evaluation.align_se2(est, ref)
            assert math.isfinite(angle) and np.isfinite(t).all()
        except EvaluationError:
            pass
        for f in (
            lambda: evaluation.ate(est, ref),
            lambda: evaluation.ate_at_times(_times(), est, _times(), ref),
        ):
            with pytest.raises(EvaluationError):
                f()


# -- fuzz ------------------------------------------------------------------------------------

HOSTILE = (
    "nan",
    "inf",
    "-inf",
    "1e308",
    "-1e308",
    "1e300",
    "1e200",
    "1e155",
    "1e10",
    "1e7",
    "-0.0",
    "0",
    "1e-300",
    "x",
    "#",
    "",
    "1_0",
    "0x10",
    "\x00",
)
_token = st.one_of(
    st.sampled_from(HOSTILE),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.floats(-1e3, 1e3).map(repr),
)


@st.composite
def _mutated(draw, lines: list[str]) -> str:
    """A valid file's lines with a few mutations: a token replaced, tokens dropped or added,
    a line repeated, removed or swapped."""
    lines = [ln.split() for ln in lines]
    for _ in range(draw(st.integers(1, 4))):
        if not lines:
            break
        k = draw(st.integers(0, len(lines) - 1))
        op = draw(st.sampled_from(["token", "token", "token", "drop", "add", "dup", "del", "swap"]))
        if op == "token" and lines[k]:
            lines[k][draw(st.integers(0, len(lines[k]) - 1))] = draw(_token)
        elif op == "drop" and lines[k]:
            del lines[k][draw(st.integers(0, len(lines[k]) - 1))]
        elif op == "add":
            lines[k].append(draw(_token))
        elif op == "dup":
            lines.insert(k, list(lines[k]))
        elif op == "del":
            del lines[k]
        elif op == "swap":
            j = draw(st.integers(0, len(lines) - 1))
            lines[k], lines[j] = lines[j], lines[k]
    return "\n".join(" ".join(ln) for ln in lines) + "\n"


def _generated(fields: int) -> st.SearchStrategy[str]:
    row = st.lists(_token, min_size=fields - 1, max_size=fields + 1)
    return st.lists(row, max_size=6).map(lambda rows: "".join(" ".join(r) + "\n" for r in rows))


def _check_outcome(name: str, rc: int, out: str, err: str, report: Path) -> None:
    if rc == 0:
        assert not err, err
        assert _all_finite(json.loads(report.read_text())), out
    else:
        assert rc == 2, (rc, err)
        _one_line_error(err, name)


@given(st.one_of(_mutated(_relation_lines(12)), _generated(8)))
@settings(max_examples=350, deadline=None)
def test_fuzz_relations_through_evaluate(text):
    with tempfile.TemporaryDirectory() as d:
        traj, rel, rep = Path(d) / "est.tum", Path(d) / "fuzz.relations", Path(d) / "r.json"
        traj.write_text("\n".join(_tum_lines()) + "\n")
        rel.write_text(text, encoding="utf-8")
        rc, out, err = _evaluate(str(traj), "--relations", str(rel), "--out", str(rep))
        _check_outcome("fuzz.relations", rc, out, err, rep)


@given(st.one_of(_mutated(_tum_lines(12)), _generated(8)), st.booleans())
@settings(max_examples=350, deadline=None)
def test_fuzz_tum_through_evaluate(text, as_reference):
    with tempfile.TemporaryDirectory() as d:
        good, tum, rep = Path(d) / "good.tum", Path(d) / "fuzz.tum", Path(d) / "r.json"
        good.write_text("\n".join(_tum_lines()) + "\n")
        rel = Path(d) / "good.relations"
        rel.write_text("\n".join(_relation_lines()) + "\n")
        tum.write_text(text, encoding="utf-8")
        if as_reference:
            args = [str(good), "--reference", str(tum)]
        else:
            args = [str(tum), "--reference", str(good), "--relations", str(rel)]
        rc, out, err = _evaluate(*args, "--out", str(rep))
        _check_outcome("fuzz.tum", rc, out, err, rep)


_coord = st.one_of(
    st.floats(-1e3, 1e3),
    st.sampled_from([0.0, 1e9, -1e9, 1e155, 1e200, 1e308, -1e308, math.inf, math.nan]),
)


@given(
    st.lists(st.tuples(_coord, _coord, _coord), min_size=0, max_size=8),
    st.lists(st.tuples(_coord, _coord, _coord), min_size=0, max_size=8),
    st.floats(allow_nan=True, allow_infinity=True),
)
@settings(max_examples=500, deadline=None)
def test_fuzz_evaluation_functions(est, ref, delta):
    """evaluate_trajectory, rpe, align_se2 and the relations metric on any poses: finite
    numbers or an EvaluationError, no numpy warning."""
    n = min(len(est), len(ref))
    t = np.arange(n, dtype=float)
    e, r = np.array(est[:n]).reshape(-1, 3), np.array(ref[:n]).reshape(-1, 3)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for f in (
            lambda: evaluation.evaluate_trajectory(t, e, t, r),
            lambda: evaluation.rpe(e, r, delta),
            lambda: evaluation.align_se2(e, r)[1],
            lambda: evaluation.ate(e, r, align=False),
        ):
            try:
                got = f()
            except EvaluationError:
                continue
            if isinstance(got, dict):
                if "pairs" in got and got["pairs"] == 0:  # rpe: no pair, documented NaN
                    continue
                assert _all_finite({k: v for k, v in got.items() if k != "not_evaluated"})
            else:
                assert np.isfinite(got).all()
        if n >= 2 and np.isfinite(e).all() and (np.abs(e) <= evaluation.TUM_MAX_POSITION).all():
            rel = np.column_stack([t[:-1], t[1:], np.zeros((n - 1, 3))])
            try:
                got = dense.relations_error(rel, t, e)
            except EvaluationError:
                return
            except ValueError as exc:  # none within the span: a plain ValueError, by design
                assert "nothing to compare" in str(exc)
                return
            assert _all_finite(got)


def test_user_error_is_the_error():
    assert issubclass(EvaluationError, UserError)
