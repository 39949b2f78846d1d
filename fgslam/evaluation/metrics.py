"""Trajectory evaluation: SE(2) alignment, absolute trajectory error, NEES, TUM files.

Poses are (x, y, theta) in m and rad; times in s.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.stats import chi2

from factors.geometry import wrap_angles
from fgslam.errors import EvaluationError


def interpolate_poses(t_ref: ArrayLike, poses: ArrayLike, t: ArrayLike) -> NDArray[np.float64]:
    """Poses at times t, linearly interpolated (heading unwrapped), clamped at the ends."""
    t_ref = np.asarray(t_ref, dtype=float)
    poses = np.asarray(poses, dtype=float)
    t = np.asarray(t, dtype=float)
    th = np.unwrap(wrap_angles(poses[:, 2]))  # wrapped first: no overflow from any finite angle
    out = np.column_stack(
        [
            np.interp(t, t_ref, poses[:, 0]),
            np.interp(t, t_ref, poses[:, 1]),
            np.interp(t, t_ref, th),
        ]
    )
    out[:, 2] = wrap_angles(out[:, 2])
    return out


def _poses(a: ArrayLike, name: str, cols: int = 3) -> NDArray[np.float64]:
    """``a`` as an (n, ``cols``) float array (an empty input: (0, ``cols``)); EvaluationError
    naming ``name`` for any other shape or for non-finite values."""
    try:
        p = np.asarray(a, dtype=float)
    except (TypeError, ValueError) as exc:
        raise EvaluationError(f"{name}: not an array of poses ({exc})") from None
    if p.size == 0:
        return p.reshape(0, cols)
    if p.ndim != 2 or p.shape[1] != cols:
        raise EvaluationError(f"{name}: expected an (n, {cols}) array of poses, got {p.shape}")
    bad = int(np.count_nonzero(~np.isfinite(p).all(axis=1)))
    if bad:
        raise EvaluationError(f"{name}: {bad} of {len(p)} poses are not finite")
    return p


def _pair(est: ArrayLike, ref: ArrayLike, cols: int = 3) -> tuple[NDArray, NDArray]:
    """Estimate and reference, checked by :func:`_poses` and for matching pose by pose."""
    e, r = _poses(est, "estimate", cols), _poses(ref, "reference", cols)
    if len(e) != len(r):
        raise EvaluationError(
            f"estimate has {len(e)} poses, reference {len(r)}: they must be matched pose by "
            "pose (evaluation.match_times)"
        )
    return e, r


def align_se2(est: ArrayLike, ref: ArrayLike) -> tuple[float, NDArray[np.float64]]:
    """The rotation angle (rad) and translation (m) that best map estimated positions onto
    reference positions in the least-squares sense (Umeyama/Horn in 2-D, no scale).

    ``est``, ``ref``: (n, 3) poses (or (n, 2) positions), matched row by row, n >= 2.
    EvaluationError for other shapes, fewer than 2 poses (no alignment), non-finite values
    or positions so large that the sums overflow."""
    cols = 2 if np.ndim(est) == 2 and np.shape(est)[1] == 2 else 3
    P, Q = (p[:, :2] for p in _pair(est, ref, cols))
    if len(P) < 2:
        raise EvaluationError(f"{len(P)} pose(s): at least 2 are needed for an alignment")
    with np.errstate(over="ignore", invalid="ignore"):
        mp, mq = P.mean(axis=0), Q.mean(axis=0)
        A, B = P - mp, Q - mq
        angle = math.atan2(
            float(np.sum(A[:, 0] * B[:, 1] - A[:, 1] * B[:, 0])), float(np.sum(A * B))
        )
        c, s = math.cos(angle), math.sin(angle)
        t = mq - np.array([c * mp[0] - s * mp[1], s * mp[0] + c * mp[1]])
    if not (math.isfinite(angle) and np.isfinite(t).all()):
        big = float(np.max(np.abs(np.vstack([P, Q]))))
        raise EvaluationError(f"the alignment overflows (positions up to {big:.3g} m)")
    return angle, t


def apply_se2(angle: float, t: ArrayLike, poses: ArrayLike) -> NDArray[np.float64]:
    poses = np.asarray(poses, dtype=float)
    c, s = math.cos(angle), math.sin(angle)
    out = poses.copy()
    out[:, 0] = c * poses[:, 0] - s * poses[:, 1] + t[0]
    out[:, 1] = s * poses[:, 0] + c * poses[:, 1] + t[1]
    out[:, 2] = wrap_angles(poses[:, 2] + angle)
    return out


def ate(est: ArrayLike, ref: ArrayLike, align: bool = True) -> dict[str, float]:
    """Absolute trajectory error of positions (m: RMSE, mean, max) and heading RMSE (deg) of
    (n, 3) poses matched row by row, after SE(2) alignment by default (n >= 2; without
    alignment n >= 1). EvaluationError for shapes that differ, too few or non-finite poses
    and errors that overflow."""
    est, ref = _pair(est, ref)
    if not len(est):
        raise EvaluationError("no poses to compare")
    if align:
        est = apply_se2(*align_se2(est, ref), est)
    with np.errstate(over="ignore", invalid="ignore"):
        err = np.hypot(est[:, 0] - ref[:, 0], est[:, 1] - ref[:, 1])
        out = {
            "rmse": float(np.sqrt(np.mean(err**2))),
            "mean": float(err.mean()),
            "max": float(err.max()),
            "heading_rmse_deg": float(
                np.degrees(np.sqrt(np.mean(wrap_angles(est[:, 2] - ref[:, 2]) ** 2)))
            ),
        }
    if not all(math.isfinite(v) for v in out.values()):
        raise EvaluationError(f"the ATE overflows (errors up to {float(err.max()):.3g} m)")
    return out


def position_errors(est: ArrayLike, ref: ArrayLike, align: bool = True) -> NDArray[np.float64]:
    """Position error (m) of each of the (n, 3) poses matched row by row, after SE(2)
    alignment by default; EvaluationError as :func:`ate`."""
    est, ref = _pair(est, ref)
    if align:
        est = apply_se2(*align_se2(est, ref), est)
    with np.errstate(over="ignore", invalid="ignore"):
        return np.hypot(est[:, 0] - ref[:, 0], est[:, 1] - ref[:, 1])


def ate_at_times(
    t_est: ArrayLike,
    est: ArrayLike,
    t_ref: ArrayLike,
    ref: ArrayLike,
    max_gap: float | None = None,
) -> dict[str, float]:
    """:func:`ate` (SE(2)-aligned) of poses ``est`` at times ``t_est`` (s) against the
    reference (``t_ref``, ``ref``) interpolated at their times, over the poses within the
    reference's time span (:func:`match_times`); with ``poses_compared`` and
    ``poses_outside_reference``. EvaluationError when fewer than 2 poses lie within it (no
    alignment), or as :func:`ate`."""
    t_est = np.asarray(t_est, dtype=float).reshape(-1)
    est = _poses(est, "estimate")
    if len(t_est) != len(est):
        raise EvaluationError(f"{len(t_est)} times for {len(est)} estimated poses")
    mask, ref_m = match_times(t_est, t_ref, ref, max_gap)
    n = int(mask.sum())
    if n < 2:
        raise EvaluationError(
            f"{n} of {len(est)} poses within the reference's time span: no alignment"
        )
    return {
        **ate(est[mask], ref_m),
        "poses_compared": n,
        "poses_outside_reference": len(est) - n,
    }


def scale_about_start(est: ArrayLike, ref: ArrayLike) -> tuple[NDArray[np.float64], float]:
    """The estimate's positions scaled about its first one (anchored) by the least-squares
    factor k that best takes them onto the reference's (headings kept), and k. What remains
    once a map's absolute scale, which wheels and range sensors with unknown scale errors
    cannot tell, is taken out (m, rad). EvaluationError where it overflows or a pose is
    not finite."""
    est = np.array(est, dtype=float)
    ref = np.asarray(ref, dtype=float)
    with np.errstate(over="ignore", invalid="ignore"):
        p, q = est[:, :2] - est[0, :2], ref[:, :2] - ref[0, :2]
        pp = float(np.sum(p * p))
        k = float(np.sum(p * q) / pp) if pp > 0 else 1.0
        est[:, :2] = est[0, :2] + k * p
    if not (math.isfinite(k) and np.isfinite(est).all()):
        raise EvaluationError("the scale alignment overflows or meets non-finite poses")
    return est, k


def nees(est: ArrayLike, cov: ArrayLike, ref: ArrayLike) -> dict[str, float]:
    """Pose NEES e^T P^-1 e (e = estimate - reference, heading wrapped; 3 dof) of (n, 3) poses
    matched row by row with their (n, 3, 3) world-frame covariances: its mean and the fraction
    of poses inside the two-sided 95 % chi-square interval. EvaluationError for shapes that
    differ, no poses, non-finite values or a singular covariance."""
    est, ref = _pair(est, ref)
    cov = np.asarray(cov, dtype=float)
    if not len(est):
        raise EvaluationError("no poses to compare")
    if cov.shape != (len(est), 3, 3):
        raise EvaluationError(f"expected {len(est)} 3x3 covariances, got shape {cov.shape}")
    if not np.isfinite(cov).all():
        raise EvaluationError("a pose covariance is not finite")
    e = est - ref
    e[:, 2] = wrap_angles(e[:, 2])
    try:
        with np.errstate(over="ignore", invalid="ignore"):
            vals = np.einsum("ni,ni->n", e, np.linalg.solve(cov, e[..., None])[..., 0])
    except np.linalg.LinAlgError:
        raise EvaluationError("a pose covariance is singular") from None
    if not np.isfinite(vals).all():
        raise EvaluationError("the NEES overflows (covariances near singular)")
    lo, hi = chi2.ppf([0.025, 0.975], 3)
    return {
        "mean": float(vals.mean()),
        "median": float(np.median(vals)),
        "within_95": float(np.mean((vals >= lo) & (vals <= hi))),
        "dof": 3,
    }


def write_tum(path: str | Path, t: ArrayLike, poses: ArrayLike) -> None:
    """TUM trajectory: ``timestamp x y z qx qy qz qw`` with z = 0 and a yaw quaternion."""
    t = np.asarray(t, dtype=float)
    poses = np.asarray(poses, dtype=float)
    with open(path, "w", encoding="utf-8") as fh:
        for ti, (x, y, th) in zip(t, poses, strict=True):
            fh.write(
                f"{ti:.6f} {x:.6f} {y:.6f} 0.000000 0.000000 0.000000 "
                f"{math.sin(th / 2):.9f} {math.cos(th / 2):.9f}\n"
            )


def numeric_rows(
    path: str | Path, columns: int, what: str, inline_comments: bool = True
) -> Iterator[tuple[int, list[float]]]:
    """(line number, values) of each line of a text table of ``columns`` numbers, blank lines
    and comments skipped (``#`` anywhere on a line; with ``inline_comments`` False, only a
    line whose first field starts with ``#``). ValueError naming the line (``line N: ...``;
    the caller names the file) for another count of fields (``what`` names them, e.g.
    ``"columns (t x y)"``) or a non-number."""
    with open(path, encoding="utf-8", errors="replace") as fh:
        for lineno, line in enumerate(fh, 1):
            tok = (line.split("#", 1)[0] if inline_comments else line).split()
            if not tok or tok[0].startswith("#"):
                continue
            if len(tok) != columns:
                raise ValueError(f"line {lineno}: expected {columns} {what}, got {len(tok)}")
            try:
                row = [float(x) for x in tok]
            except ValueError:
                raise ValueError(f"line {lineno}: not a number in {line.strip()[:60]!r}") from None
            yield lineno, row


TUM_FIELDS = ("timestamp", "tx", "ty", "tz", "qx", "qy", "qz", "qw")
TUM_MAX_STAMP = 1e10  # s; beyond, not a time (the year 2286 as Unix time)
TUM_MAX_POSITION = 1e9  # m; beyond, not a position
TUM_QUATERNION_NORM = (1e-3, 1e3)  # a TUM quaternion is a unit one: outside, not a rotation


def read_tum(
    path: str | Path, ordered: bool = False
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Times and (x, y, yaw) of a TUM trajectory (yaw from the quaternion, normalised).

    ValueError naming the line and field for a wrong column count, a non-number, a
    non-finite or absurd value (stamp beyond 1e10 s, position beyond 1e9 m), a quaternion of
    zero norm or of a norm that no unit quaternion written out has (outside
    :data:`TUM_QUATERNION_NORM`), and with ``ordered`` a stamp before the one of the pose
    before it."""
    rows = []
    last = (-math.inf, 0)  # the previous pose's stamp and line
    what = "columns (timestamp x y z qx qy qz qw)"
    for lineno, row in numeric_rows(path, 8, what, inline_comments=False):
        for name, v in zip(TUM_FIELDS, row, strict=True):
            top = TUM_MAX_STAMP if name == "timestamp" else TUM_MAX_POSITION
            if not math.isfinite(v) or (name[0] != "q" and abs(v) > top):
                raise ValueError(f"line {lineno}: field {name}: {v!r} is not plausible")
        big = max(abs(v) for v in row[4:])
        norm = big * math.hypot(*(v / big for v in row[4:])) if big else 0.0
        if norm < 1e-9:
            raise ValueError(f"line {lineno}: quaternion (qx qy qz qw) has zero norm")
        lo, hi = TUM_QUATERNION_NORM
        if not lo <= norm <= hi:
            raise ValueError(
                f"line {lineno}: quaternion (qx qy qz qw) has norm {norm:.3g}: not a "
                f"rotation (a unit quaternion; {lo:g} to {hi:g} accepted)"
            )
        if ordered and row[0] < last[0]:
            raise ValueError(
                f"line {lineno}: field timestamp: {row[0]!r} is before {last[0]!r} "
                f"(line {last[1]}): the stamps go backwards"
            )
        last = (row[0], lineno)
        rows.append(row)
    data = np.array(rows, dtype=float).reshape(-1, 8)
    q = data[:, 4:] / np.linalg.norm(data[:, 4:], axis=1, keepdims=True)
    qx, qy, qz, qw = q.T
    yaw = np.arctan2(2 * (qw * qz + qx * qy), 1 - 2 * (qy**2 + qz**2))
    return data[:, 0], np.column_stack([data[:, 1], data[:, 2], yaw])


# ---------------------------------------------------------------------------------------------
# Relative pose error, matching by time, reports (fgslam evaluate)


def _relative_poses(poses: NDArray[np.float64], i: NDArray, j: NDArray) -> NDArray[np.float64]:
    """inverse(poses[i]) * poses[j], row by row, heading wrapped."""
    a, b = poses[i], poses[j]
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    dx, dy = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
    return np.column_stack([c * dx + s * dy, -s * dx + c * dy, wrap_angles(b[:, 2] - a[:, 2])])


def rpe(est: ArrayLike, ref: ArrayLike, delta: float = 1.0) -> dict[str, float]:
    """Relative pose error over distance deltas: for every pose i, the first pose j at which
    the reference has travelled at least ``delta`` m along its path since i; the error of the
    estimated motion i -> j against the reference motion, inverse(ref_ij) * est_ij. Returns
    RMSE, mean and max of its translation (m) and of its rotation (deg), and the number of
    pairs (0 when the reference never travels ``delta``: the other values are then NaN).
    EvaluationError as :func:`ate`, for a ``delta`` that is not a positive number, and for
    errors that overflow."""
    est, ref = _pair(est, ref)
    if not 0 < delta < math.inf:
        raise EvaluationError(f"delta must be a positive number, got {delta}")
    if not len(ref):
        raise EvaluationError("no poses to compare")
    with np.errstate(over="ignore", invalid="ignore"):
        dist = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(ref[:, :2], axis=0).T))])
    if not np.isfinite(dist[-1]):
        big = float(np.max(np.abs(ref[:, :2])))
        raise EvaluationError(
            f"the reference's path length overflows (positions up to {big:.3g} m)"
        )
    i = np.arange(len(ref))
    j = np.searchsorted(dist, dist + delta - 1e-12)
    ok = j < len(ref)
    i, j = i[ok], j[ok]
    nan = float("nan")
    if not len(i):
        return {k: nan for k in _RPE_KEYS} | {"pairs": 0, "delta_m": delta}
    with np.errstate(over="ignore", invalid="ignore"):
        e = _relative_poses(
            np.vstack([_relative_poses(ref, i, j), _relative_poses(est, i, j)]),
            np.arange(len(i)),
            np.arange(len(i), 2 * len(i)),
        )
        tr = np.hypot(e[:, 0], e[:, 1])
        rot = np.degrees(np.abs(e[:, 2]))
        out = {
            "trans_rmse": float(np.sqrt(np.mean(tr**2))),
            "trans_mean": float(tr.mean()),
            "trans_max": float(tr.max()),
            "rot_rmse_deg": float(np.sqrt(np.mean(rot**2))),
            "rot_mean_deg": float(rot.mean()),
            "rot_max_deg": float(rot.max()),
        }
    if not all(math.isfinite(v) for v in out.values()):
        raise EvaluationError(f"the RPE overflows (errors up to {float(tr.max()):.3g} m)")
    return out | {"pairs": len(i), "delta_m": delta}


_RPE_KEYS = (
    "trans_rmse",
    "trans_mean",
    "trans_max",
    "rot_rmse_deg",
    "rot_mean_deg",
    "rot_max_deg",
)


def match_times(
    t_est: ArrayLike, t_ref: ArrayLike, ref: ArrayLike, max_gap: float | None = None
) -> tuple[NDArray[np.bool_], NDArray[np.float64]]:
    """The estimated poses whose time lies within the reference's time span (and, with
    ``max_gap``, within ``max_gap`` s of a reference pose), and the reference interpolated at
    their times: (mask over t_est, reference poses at t_est[mask])."""
    t_est = np.asarray(t_est, dtype=float).reshape(-1)
    t_ref = np.asarray(t_ref, dtype=float).reshape(-1)
    if len(t_ref) == 0:
        return np.zeros(len(t_est), dtype=bool), np.zeros((0, 3))
    ref = _poses(ref, "reference")
    if len(ref) != len(t_ref):
        raise EvaluationError(f"{len(t_ref)} reference times for {len(ref)} reference poses")
    if np.any(np.diff(t_ref) < 0):
        raise EvaluationError("reference times must not go backwards")
    mask = (t_est >= t_ref[0]) & (t_est <= t_ref[-1])
    if max_gap is not None and len(t_ref):
        k = np.clip(np.searchsorted(t_ref, t_est), 1, max(len(t_ref) - 1, 1))
        gap = np.minimum(
            np.abs(t_est - t_ref[k - 1]), np.abs(t_ref[np.minimum(k, len(t_ref) - 1)] - t_est)
        )
        mask &= gap <= max_gap
    return mask, interpolate_poses(t_ref, ref, t_est[mask])


def evaluate_trajectory(
    t_est: ArrayLike,
    est: ArrayLike,
    t_ref: ArrayLike,
    ref: ArrayLike,
    rpe_delta: float = 1.0,
    covs: ArrayLike | None = None,
    max_gap: float | None = None,
) -> dict:
    """ATE (after SE(2) alignment, and without), RPE over ``rpe_delta`` m, and with ``covs``
    (world-frame 3x3 per estimated pose) the NEES, of an estimate (poses in m, rad at times in
    s) against a reference matched by time. Any number of poses: a metric that cannot be
    computed (fewer than 2 poses within the reference's time span: no alignment; a reference
    that never travels ``rpe_delta``; non-finite poses) is left out, its reason under
    ``not_evaluated``."""
    t_est = np.asarray(t_est, dtype=float).reshape(-1)
    est = np.asarray(est, dtype=float).reshape(-1, 3)
    if len(t_est) != len(est):
        raise EvaluationError(f"{len(t_est)} times for {len(est)} estimated poses")
    mask, ref_m = match_times(t_est, t_ref, ref, max_gap)
    n = int(mask.sum())
    e = est[mask]
    out: dict = {"poses_compared": n, "poses_outside_reference": int(len(est) - n)}
    few = f"{n} of {len(est)} poses within the reference's time span"

    def aligned() -> dict:
        if n < 2:
            raise EvaluationError(f"{few}: no alignment")
        return ate(e, ref_m)

    def relative() -> dict:
        if n < 2:
            raise EvaluationError(f"{few}: no pair of poses")
        r = rpe(e, ref_m, rpe_delta)
        if r["pairs"] == 0:
            raise EvaluationError(
                f"the reference never travels {rpe_delta:g} m: no pair (a smaller delta may)"
            )
        return r

    add_metric(out, "ate", aligned)
    add_metric(out, "ate_unaligned", lambda: ate(e, ref_m, align=False))
    add_metric(out, "rpe", relative)
    if covs is not None:
        c = np.asarray(covs, dtype=float).reshape(-1, 3, 3)
        if len(c) != len(est):
            raise EvaluationError(f"{len(c)} covariances for {len(est)} estimated poses")
        add_metric(out, "nees", lambda: nees(e, c[mask], ref_m))
    return out


def add_metric(out: dict, key: str, compute: Callable[[], object]) -> None:
    """``out[key] = compute()``; if it raises EvaluationError (the metric cannot be computed
    from these poses), its message goes under ``out["not_evaluated"][key]`` instead."""
    try:
        out[key] = compute()
    except EvaluationError as exc:
        out.setdefault("not_evaluated", {})[key] = str(exc)


def map_error(landmarks: list[dict], true_map: dict) -> dict:
    """Map error of estimated landmarks (``map.json``'s ``landmarks``) against the true
    features of a simulator world (a log's ``true_map`` metadata): per kind, the median and
    mean distance to the nearest true feature of that kind (lines: |d| and angle; corners and
    points: position; points may also match corners)."""
    lines = [ln for ln in true_map.get("lines", []) if ln.get("laser", True)]
    errs: dict[str, list[float]] = {"line_d": [], "line_alpha_deg": [], "corner": [], "point": []}
    for lm in landmarks:
        kind = lm.get("kind")
        if kind == "line" and lines:
            a, d = lm["alpha"], lm["d"]
            best = min(
                lines,
                key=lambda t: (
                    abs(wrap_angles(np.array([t["alpha"] - a]))[0]) * 3.0 + abs(t["d"] - d)
                ),
            )
            errs["line_d"].append(abs(best["d"] - d))
            errs["line_alpha_deg"].append(
                math.degrees(abs(wrap_angles(np.array([best["alpha"] - a]))[0]))
            )
        elif kind in ("corner", "point"):
            pts = list(true_map.get("corners" if kind == "corner" else "points", []))
            if kind == "point":
                pts += true_map.get("corners", [])
            if pts:
                errs[kind].append(min(math.hypot(p["x"] - lm["x"], p["y"] - lm["y"]) for p in pts))
    return {
        k: {"median": float(np.median(v)), "mean": float(np.mean(v)), "n": len(v)}
        for k, v in errs.items()
        if v
    }


def write_covariances(path: str | Path, t: ArrayLike, covs: ArrayLike) -> None:
    """Pose covariances next to a TUM file: ``timestamp`` and the 9 entries of the world-frame
    3x3 (x, y, theta) covariance, row by row, one pose a line."""
    t = np.asarray(t, dtype=float)
    covs = np.asarray(covs, dtype=float).reshape(-1, 9)
    np.savetxt(path, np.column_stack([t, covs]), fmt="%.9g", header="timestamp c_xx c_xy ... c_tt")


def read_covariances(path: str | Path) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Times and (n, 3, 3) covariances of a file of :func:`write_covariances`. ValueError
    naming the line (``line N: ...``; the caller names the file) for a wrong column count, a
    non-number or a value that is not finite, and for a file without covariances."""
    rows = []
    for lineno, row in numeric_rows(path, 10, "columns (timestamp and a 3x3 covariance)"):
        if not all(math.isfinite(v) for v in row):
            raise ValueError(f"line {lineno}: a value is not finite")
        rows.append(row)
    if not rows:
        raise ValueError("no covariances (timestamp and a 3x3 covariance per line)")
    data = np.array(rows, dtype=float)
    return data[:, 0], data[:, 1:].reshape(-1, 3, 3)


def loop_agreement(
    closures: list[dict],
    kf_times: ArrayLike,
    ref_t: ArrayLike,
    ref_poses: ArrayLike,
    xy_tol: float = 0.2,
    theta_tol_deg: float = 2.0,
) -> dict[str, float | int]:
    """How many accepted loop closures (report.json's attempts: "from"/"to" keyframe indices,
    "pose" the matched x, y, theta of "to" in the frame of "from"; m, rad) agree with the
    reference: the reference poses (``ref_t`` s, (n, 3) world) interpolated at the two
    keyframes' times ``kf_times`` give the true relative pose; a closure agrees when it is
    within ``xy_tol`` m and ``theta_tol_deg`` deg of it. Closures whose keyframes lie outside
    the reference's time span are not checked."""
    t = np.asarray(kf_times, dtype=float)
    rt = np.asarray(ref_t, dtype=float)
    acc = [c for c in closures if c.get("accepted") and c.get("pose") is not None]
    pairs = [
        (int(c["from"]), int(c["to"]), c["pose"])
        for c in acc
        if 0 <= int(c["from"]) < len(t) and 0 <= int(c["to"]) < len(t)
    ]
    inside = [
        p
        for p in pairs
        if len(rt) >= 2 and rt[0] <= min(t[p[0]], t[p[1]]) <= max(t[p[0]], t[p[1]]) <= rt[-1]
    ]
    out: dict[str, float | int] = {
        "accepted": len(acc),
        "checked": len(inside),
        "agree": 0,
        "xy_tol_m": xy_tol,
        "theta_tol_deg": theta_tol_deg,
    }
    if not inside:
        return out
    j = np.array([p[0] for p in inside])
    k = np.array([p[1] for p in inside])
    ref = interpolate_poses(rt, ref_poses, t)
    true = _relative_poses(ref, j, k)
    got = np.array([p[2] for p in inside], dtype=float).reshape(-1, 3)
    dxy = np.hypot(got[:, 0] - true[:, 0], got[:, 1] - true[:, 1])
    dth = np.degrees(np.abs(wrap_angles(got[:, 2] - true[:, 2])))
    out["agree"] = int(np.sum((dxy <= xy_tol) & (dth <= theta_tol_deg)))
    out["median_error_m"] = round(float(np.median(dxy)), 4)
    out["median_error_deg"] = round(float(np.median(dth)), 3)
    return out
