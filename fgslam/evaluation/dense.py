"""The trajectory between keyframes, and the relations benchmark (Kuemmerle et al. 2009).

A SLAM run estimates poses at its keyframes only. Between them the best estimate is the
*nearest* keyframe's pose composed with the odometry from that keyframe's time to the time
asked for (what the benchmark's own evaluator does): ``X(t) = X_k * inverse(O(t_k)) * O(t)``,
``k`` the keyframe nearest in time to ``t``, ``O`` the odometry path (cumulative, from the
samples, linearly interpolated between them: samples are at most 5 cm / 2 deg apart in the
foreign-log readers). Linear interpolation between keyframes instead would inflate the
benchmark's error (intel 0.126 m instead of 0.054 m for the same poses).

World frame, poses (x, y, theta) in m and rad, times in s.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from factors.geometry import between_poses, compose_poses, wrap_angles
from factors.odometry import integrate_poses
from fgslam.evaluation.metrics import numeric_rows
from fgslam.io.readers.odometry import OdometryChain


def odometry_path(samples: ArrayLike, wheelbase: float) -> tuple[NDArray, NDArray]:
    """Times and cumulative odometry poses (heading unwrapped) of odometry samples given as
    rows ``(t, L_r, L_l)`` (wheel distances in m), starting at the origin at the first
    sample's time."""
    s = np.asarray(samples, dtype=float).reshape(-1, 3)
    if not len(s):
        return np.zeros(0), np.zeros((0, 3))
    poses = integrate_poses(s[:, 1], s[:, 2], wheelbase)
    t = np.concatenate([[s[0, 0]], s[:, 0]])
    return t, np.vstack([np.zeros(3), poses])


def _at(t_path: NDArray, path: NDArray, t: NDArray, how: str = "linear") -> NDArray:
    """The path (heading unwrapped) at times t: linearly interpolated (``linear``) or its
    sample nearest in time (``nearest``), clamped at the ends."""
    if how == "nearest" and len(t_path) > 1:
        j = np.clip(np.searchsorted(t_path, t), 1, len(t_path) - 1)
        return path[np.where(np.abs(t - t_path[j - 1]) <= np.abs(t_path[j] - t), j - 1, j)]
    return np.column_stack([np.interp(t, t_path, path[:, i]) for i in range(3)])


def dense_poses(
    kf_t: ArrayLike,
    kf_poses: ArrayLike,
    odo_t: ArrayLike,
    odo_path: ArrayLike,
    t: ArrayLike,
    odometry: str = "linear",
) -> NDArray[np.float64]:
    """Poses at times ``t``: the keyframe nearest in time composed with the odometry from its
    time to ``t`` (see the module documentation; ``odometry``: ``linear`` interpolation of
    the odometry path, or its ``nearest`` record, as the benchmark's evaluator takes the
    odometry record of the scan). Without odometry (empty ``odo_t``), the nearest keyframe's
    pose. ``odo_t`` must be sorted."""
    kt = np.asarray(kf_t, dtype=float)
    kp = np.asarray(kf_poses, dtype=float).reshape(-1, 3)
    t = np.asarray(t, dtype=float)
    if not len(kt):
        raise ValueError("no keyframes")
    order = np.argsort(kt, kind="stable")
    kt, kp = kt[order], kp[order]
    j = np.clip(np.searchsorted(kt, t), 1, max(len(kt) - 1, 1))
    i = np.where(np.abs(t - kt[j - 1]) <= np.abs(kt[np.minimum(j, len(kt) - 1)] - t), j - 1, j)
    i = np.minimum(i, len(kt) - 1)
    ot = np.asarray(odo_t, dtype=float)
    if len(ot) < 2:
        return kp[i].copy()
    op = np.asarray(odo_path, dtype=float)
    rel = between_poses(_at(ot, op, kt[i], odometry), _at(ot, op, t, odometry))
    return compose_poses(kp[i], rel)


RELATION_FIELDS = ("t1", "t2", "x", "y", "z", "roll", "pitch", "yaw")
RELATION_MAX_STAMP = 1e10  # s; beyond, not a time (as a TUM stamp or a log's)
RELATION_MAX_TRANSLATION = 1e6  # m; beyond, not a robot's motion (the benchmark's: < 100 m)
RELATION_MAX_ANGLE = 1e3  # rad (160 turns); beyond, not a rotation


def read_relations(path: str | Path) -> NDArray[np.float64]:
    """Rows ``(t1, t2, x, y, yaw)`` of a relations file (``t1 t2 x y z roll pitch yaw`` per
    line, ``#`` comments): the true pose at t2 in the frame of the pose at t1.

    ValueError naming the line (``line N: ...``; the caller names the file) for a wrong
    field count, a non-number, a value that is not finite or not plausible (a time beyond
    :data:`RELATION_MAX_STAMP` s, a translation beyond :data:`RELATION_MAX_TRANSLATION` m,
    an angle beyond :data:`RELATION_MAX_ANGLE` rad), or a file without relations."""
    rows = []
    for lineno, row in numeric_rows(path, 8, "fields (t1 t2 x y z roll pitch yaw)"):
        for k, (name, v) in enumerate(zip(RELATION_FIELDS, row, strict=True)):
            top, unit = (
                (RELATION_MAX_STAMP, "s")
                if k < 2
                else (RELATION_MAX_TRANSLATION, "m")
                if k < 5
                else (RELATION_MAX_ANGLE, "rad")
            )
            if not abs(v) <= top:
                raise ValueError(
                    f"line {lineno}: field {name}: {v!r} is not plausible "
                    f"(finite, at most {top:g} {unit})"
                )
        rows.append(row)
    if not rows:
        raise ValueError("no relations (lines t1 t2 x y z roll pitch yaw)")
    return np.array(rows, dtype=float)[:, [0, 1, 2, 3, 7]]


def relation_scan_pairs(
    relations: ArrayLike, stamps: ArrayLike, max_distance: float = math.inf, tol: float = 1e-3
) -> list[tuple[int, int, NDArray[np.float64]]]:
    """The relations (rows ``t1 t2 x y yaw``) whose two ends are scans: ``(i, j, pose)`` with
    ``i``, ``j`` the indices of the scans stamped within ``tol`` s of t1 and t2 (``stamps``
    ascending) and ``pose`` (x, y, yaw) of j in i's frame (m, rad); relations longer than
    ``max_distance`` m are left out. File order kept."""
    r = np.asarray(relations, dtype=float).reshape(-1, 5)
    st = np.asarray(stamps, dtype=float)
    if not len(st):
        return []

    def nearest(t: NDArray) -> NDArray:
        k = np.clip(np.searchsorted(st, t), 1, max(len(st) - 1, 1))
        k = np.where(np.abs(st[k - 1] - t) <= np.abs(st[np.minimum(k, len(st) - 1)] - t), k - 1, k)
        return np.minimum(k, len(st) - 1)

    i, j = nearest(r[:, 0]), nearest(r[:, 1])
    keep = (np.abs(st[i] - r[:, 0]) <= tol) & (np.abs(st[j] - r[:, 1]) <= tol)
    keep &= np.hypot(r[:, 2], r[:, 3]) <= max_distance
    return [(int(i[n]), int(j[n]), r[n, 2:5].copy()) for n in np.nonzero(keep)[0]]


def relations_error(
    relations: ArrayLike,
    t_traj: ArrayLike,
    traj: ArrayLike,
    *,
    kf_t: ArrayLike | None = None,
    kf_poses: ArrayLike | None = None,
    odo_t: ArrayLike | None = None,
    odo_path: ArrayLike | None = None,
    odometry: str = "linear",
) -> dict:
    """The relations metric: for each relation (t1, t2, x, y, yaw), the estimate's relative
    pose d = X(t1)^-1 X(t2); translational error |trans(d) - (x, y)| (m), rotational error
    |wrap(yaw(d) - yaw)| (deg); mean, std, max and RMSE over the relations whose two ends
    lie within the estimate's time span. X(t) from keyframes and odometry
    (:func:`dense_poses`) when ``kf_t``/``kf_poses``/``odo_t``/``odo_path`` are given, else
    the trajectory ``(t_traj, traj)`` linearly interpolated (right for a dense trajectory,
    e.g. a run's ``trajectory_dense.tum``). Raises ``ValueError`` when no relation can be
    evaluated."""
    r = np.asarray(relations, dtype=float).reshape(-1, 5)
    if kf_t is not None:
        tt = np.asarray(kf_t, dtype=float)
    else:
        tt = np.asarray(t_traj, dtype=float)
    if len(tt) == 0:
        raise ValueError("empty trajectory: no relation can be evaluated")
    used = _within(r, float(tt.min()), float(tt.max()))
    if kf_t is not None:
        ot = np.zeros(0) if odo_t is None else odo_t
        op = np.zeros((0, 3)) if odo_path is None else odo_path
        x1 = dense_poses(kf_t, kf_poses, ot, op, used[:, 0], odometry)
        x2 = dense_poses(kf_t, kf_poses, ot, op, used[:, 1], odometry)
    else:
        p = np.asarray(traj, dtype=float).reshape(-1, 3).copy()
        p[:, 2] = np.unwrap(p[:, 2])
        x1, x2 = _at(tt, p, used[:, 0]), _at(tt, p, used[:, 1])
    return _metrics(between_poses(x1, x2), used, len(r))


def dense_times(kf_t: ArrayLike, odo_t: ArrayLike) -> NDArray[np.float64]:
    """Every odometry sample time and keyframe time within the keyframes' span, sorted,
    without repeats."""
    kt = np.asarray(kf_t, dtype=float)
    ot = np.asarray(odo_t, dtype=float)
    if not len(kt):
        return kt
    ot = ot[(ot >= kt.min()) & (ot <= kt.max())]
    return np.unique(np.concatenate([kt, ot]))


def write_dense_trajectory(
    path: str | Path,
    kf_t: ArrayLike,
    kf_poses: ArrayLike,
    samples: ArrayLike,
    wheelbase: float,
) -> int:
    """Write the trajectory at every odometry sample and keyframe time (TUM, see
    :func:`fgslam.evaluation.metrics.write_tum`) from keyframe poses and odometry samples ``(t, L_r,
    L_l)``; returns the number of poses written."""
    from fgslam.evaluation.metrics import write_tum
    from fgslam.io.safeio import atomic_path

    ot, op = odometry_path(samples, wheelbase)
    t = dense_times(kf_t, ot)
    with atomic_path(path) as tmp:  # complete or not there at all
        if not len(t):
            write_tum(tmp, np.zeros(0), np.zeros((0, 3)))
            return 0
        write_tum(tmp, t, dense_poses(kf_t, kf_poses, ot, op, t))
    return len(t)


def _within(r: NDArray, lo: float, hi: float) -> NDArray:
    """The relations (rows t1 t2 ...) whose both ends lie in [lo, hi] s; ValueError if none."""
    inside = (np.minimum(r[:, 0], r[:, 1]) >= lo - 1e-9) & (
        np.maximum(r[:, 0], r[:, 1]) <= hi + 1e-9
    )
    if not inside.any():
        raise ValueError(
            f"none of the {len(r)} relations lies within the estimate's time span "
            f"[{lo:.6f}, {hi:.6f}] s: nothing to compare"
        )
    return r[inside]


def _metrics(d: NDArray, used: NDArray, n: int) -> dict:
    """The relations metric's figures; EvaluationError (a ValueError) when an estimated
    relative pose is not finite or the errors overflow (no inf or NaN in a report)."""
    from fgslam.errors import EvaluationError

    with np.errstate(over="ignore", invalid="ignore"):
        tr = np.hypot(d[:, 0] - used[:, 2], d[:, 1] - used[:, 3])
        rot = np.degrees(np.abs(wrap_angles(d[:, 2] - used[:, 4])))
        sums = np.array([np.sum(tr**2), tr.std(), np.sum(rot**2), rot.std()])
    bad = ~(np.isfinite(tr) & np.isfinite(rot))
    if bad.any():
        k = int(np.argmax(bad))
        raise EvaluationError(
            f"the estimate's relative pose over relation t1 = {used[k, 0]:.6f}, "
            f"t2 = {used[k, 1]:.6f} s is not finite ({int(bad.sum())} of {len(used)} relations)"
        )
    if not np.isfinite(sums).all():
        raise EvaluationError(
            f"the relations error overflows (errors up to {float(tr.max()):.3g} m)"
        )
    return {
        "relations": n,
        "relations_used": len(used),
        "relations_outside": n - len(used),
        "trans_mean": float(tr.mean()),
        "trans_std": float(tr.std()),
        "trans_max": float(tr.max()),
        "trans_rmse": float(math.sqrt(np.mean(tr**2))),
        "rot_mean_deg": float(rot.mean()),
        "rot_std_deg": float(rot.std()),
        "rot_max_deg": float(rot.max()),
        "rot_rmse_deg": float(math.sqrt(np.mean(rot**2))),
    }


def chain_poses(
    chain: OdometryChain,
    estimate: NDArray[np.float64],
    has: NDArray[np.bool_],
    t: ArrayLike,
) -> NDArray[np.float64]:
    """Poses at times ``t`` from estimated poses at the log's scans (``estimate`` (S, 3),
    ``has``: which scans have one) and the odometry records: the record nearest in time to
    t (the benchmark's relation ends are the original scans, each an odometry record), then,
    of the two scans around that record in file order, the one nearer in time that has an
    estimate (else the estimated scan nearest in time), composed with the odometry along the
    file-order chain from that scan to the record."""
    t = np.asarray(t, dtype=float)
    order = np.argsort(chain.t, kind="stable")
    ts = chain.t[order]
    j = np.clip(np.searchsorted(ts, t), 1, len(ts) - 1)
    j = order[np.where(np.abs(t - ts[j - 1]) <= np.abs(ts[j] - t), j - 1, j)]
    rec_of_scan = chain.scan_records()
    n = len(chain.scan_t)
    est_idx = np.flatnonzero(has)
    if not len(est_idx):
        raise ValueError("no scan has an estimated pose")
    kb = np.clip(chain.scan[j], 0, n - 1)
    ka = np.where(chain.is_scan[j], kb, np.minimum(kb + 1, n - 1))
    pick = np.where(np.abs(chain.scan_t[kb] - t) <= np.abs(chain.scan_t[ka] - t), kb, ka)
    other = np.where(pick == kb, ka, kb)
    pick = np.where(has[pick], pick, np.where(has[other], other, -1))
    missing = pick < 0
    if missing.any():
        st = chain.scan_t[est_idx]
        o = np.argsort(st)
        q = np.clip(np.searchsorted(st[o], t[missing]), 1, max(len(o) - 1, 1))
        lo, hi = o[q - 1], o[np.minimum(q, len(o) - 1)]
        near = np.where(np.abs(st[lo] - t[missing]) <= np.abs(st[hi] - t[missing]), lo, hi)
        pick[missing] = est_idx[near]
    rel = between_poses(chain.poses[rec_of_scan[pick]], chain.poses[j])
    return compose_poses(estimate[pick], rel)


def estimate_at_scans(
    chain: OdometryChain, kf_t: ArrayLike, kf_poses: ArrayLike, tol: float = 1e-3
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """A run's keyframe poses placed at the log's scans (matched by time within ``tol`` s):
    (S, 3) poses and which scans have one."""
    kt = np.asarray(kf_t, dtype=float)
    kp = np.asarray(kf_poses, dtype=float).reshape(-1, 3)
    est = np.zeros((len(chain.scan_t), 3))
    has = np.zeros(len(chain.scan_t), dtype=bool)
    if not len(kt):
        return est, has
    o = np.argsort(kt)
    q = np.clip(np.searchsorted(kt[o], chain.scan_t), 1, max(len(o) - 1, 1))
    lo, hi = o[q - 1], o[np.minimum(q, len(o) - 1)]
    near = np.where(np.abs(kt[lo] - chain.scan_t) <= np.abs(kt[hi] - chain.scan_t), lo, hi)
    has = np.abs(kt[near] - chain.scan_t) <= tol
    est[has] = kp[near[has]]
    return est, has


def relations_error_chain(
    relations: ArrayLike, chain: OdometryChain, estimate: ArrayLike, has: ArrayLike
) -> dict:
    """The relations metric (as :func:`relations_error`) with X(t) from estimated poses at
    the log's scans and the log's odometry records (:func:`chain_poses`); relations whose
    ends lie outside the estimated scans' time span are left out."""
    r = np.asarray(relations, dtype=float).reshape(-1, 5)
    has = np.asarray(has, dtype=bool)
    if not has.any():
        raise ValueError("no scan has an estimated pose: nothing to compare")
    st = chain.scan_t[has]
    used = _within(r, float(st.min()), float(st.max()))
    est = np.asarray(estimate, dtype=float)
    x1 = chain_poses(chain, est, has, used[:, 0])
    x2 = chain_poses(chain, est, has, used[:, 1])
    return _metrics(between_poses(x1, x2), used, len(r))
