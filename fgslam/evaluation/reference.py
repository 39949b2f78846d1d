"""Reference trajectories for evaluation: a TUM file or any log with truth or reference poses
(times s, poses x, y m and heading rad in the log's world frame)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from fgslam.errors import UserError
from fgslam.evaluation import metrics as evaluation
from fgslam.events import TruthPose


def _looks_like_tum(path: Path) -> bool:
    try:
        with open(path, "rb") as f:
            head = f.read(4096)
    except OSError as exc:
        raise UserError(f"{path}: cannot open: {exc.strerror or exc}") from None
    if head[:2] == b"\x1f\x8b":
        return False
    for line in head.decode("utf-8", errors="replace").splitlines():
        tok = line.split()
        if not tok or tok[0].startswith("#"):
            continue
        try:
            [float(x) for x in tok]
        except ValueError:
            return False
        return len(tok) == 8
    return False


MAX_HEADING = 1e7  # rad: a log's heading beyond is not one (as the CARMEN reader's poses)


def read_tum_file(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """A TUM trajectory (:func:`evaluation.read_tum`, stamps in order); UserError naming the
    file, and the line, for anything it cannot hold."""
    try:
        return evaluation.read_tum(path, ordered=True)
    except (ValueError, OSError) as exc:
        raise UserError(f"{path}: not a TUM trajectory ({exc})") from None


def _check_reference(path: str | Path, t: np.ndarray, poses: np.ndarray) -> None:
    """A log's truth or reference poses hold what a TUM file may (:func:`evaluation.read_tum`):
    UserError naming the file and the pose's time for a value that is not finite or not
    plausible (a position beyond ``evaluation.TUM_MAX_POSITION`` m, a heading beyond
    :data:`MAX_HEADING` rad)."""
    top = evaluation.TUM_MAX_POSITION
    with np.errstate(invalid="ignore"):
        ok = (np.abs(poses[:, :2]) <= top).all(axis=1) & (np.abs(poses[:, 2]) <= MAX_HEADING)
    bad = ~(ok & np.isfinite(t))
    if bad.any():
        k = int(np.argmax(bad))
        raise UserError(
            f"{path}: truth or reference pose at t = {float(t[k])!r} s: "
            f"({', '.join(repr(float(v)) for v in poses[k])}) is not a pose (finite, "
            f"positions at most {top:g} m, heading at most {MAX_HEADING:g} rad)"
        )


def load_reference(path: str | Path, **options: Any) -> tuple[np.ndarray, np.ndarray, dict, str]:
    """Times, poses, true map (or {}) and what the poses are, from a TUM file or a log."""
    p = Path(path)
    if p.is_file() and _looks_like_tum(p):
        t, poses = read_tum_file(p)
        return t, poses, {}, "reference trajectory (TUM)"
    from fgslam.io.formats import open_log

    reader = open_log(p, **options)
    t, poses = [], []
    last = -np.inf
    for ev in reader:
        if isinstance(ev, TruthPose) and ev.t >= last:
            t.append(ev.t)
            poses.append((ev.x, ev.y, ev.theta))
            last = ev.t
    if len(t) < 2:
        raise UserError(f"{path}: the log has no truth or reference poses")
    t_a, poses_a = np.array(t, dtype=float), np.array(poses, dtype=float)
    _check_reference(path, t_a, poses_a)
    kind = reader.reference_kind or "ground truth"
    return t_a, poses_a, reader.meta.get("true_map") or {}, kind
