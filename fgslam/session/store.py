"""A saved session (``fgslam run --save DIR``; docs/sessions.md): what localization and a
continued run need of a finished run.

The folder holds:

- ``session.json``: the format name and version, the fgslam version that wrote it, what was
  run (log, backend, sensors), the robot configuration (its keys), the calibration
  estimate, the landmarks (kind, mean, covariance; world frame), the constraints between
  keyframes (``scan``: consecutive scan matches, ``odometry``: consecutive wheel odometry
  where no scan matched, ``loop``: accepted loop closures, ``anchor``: a continued log's
  first keyframe placed on the saved ones; each the relative pose of the second keyframe in
  the first's frame and its covariance, GTSAM's between convention) and
  the SHA-256 of ``scans.npz``;
- ``scans.npz``: the keyframes' times (s), poses ((N, 3) world, m, rad), pose covariances
  ((N, 3, 3), NaN where none), their laser points concatenated ((M, 2) robot frame, m) with
  each keyframe's offset ((N + 1,)), the laser's position on the robot (m), and the scans
  between keyframes (``between``, (M, 5): time s, the keyframe k before it, its pose in k's
  frame; a continued run places them again on the re-estimated keyframes);
- ``map.pgm`` and ``map.yaml``: the occupancy grid (:mod:`fgslam.session.grid`).

Saving never leaves a half-written session: the files are written into a new folder that
then takes the place of ``DIR``; a ``DIR`` that holds anything but a session this version can
read (other files, a corrupt session, a newer format) is refused and left as it was."""

from __future__ import annotations

import hashlib
import io
import json
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from factors.geometry import between_poses
from fgslam import __version__
from fgslam.config import ConfigError, from_dict
from fgslam.errors import UserError
from fgslam.session.grid import OccupancyGrid, occupancy_grid, write_map

FORMAT_NAME = "fgslam-session"
FORMAT_VERSION = 1
INDEX, SCANS = "session.json", "scans.npz"


class SessionError(UserError, ValueError):
    """A session folder that cannot be read or written; the message names it and says why."""


@dataclass
class Session:
    """A saved run; frames and units as in the module doc."""

    times: NDArray[np.float64]
    poses: NDArray[np.float64]
    covs: NDArray[np.float64]
    scans: list[NDArray[np.float64] | None]
    laser_xy: tuple[float, float]
    config: dict[str, Any]
    landmarks: list[dict[str, Any]] = field(default_factory=list)
    constraints: list[dict[str, Any]] = field(default_factory=list)
    calibration: dict[str, Any] | None = None
    meta: dict[str, Any] = field(default_factory=dict)
    between: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 5)))

    def __post_init__(self) -> None:
        self.times = np.asarray(self.times, dtype=float).reshape(-1)
        n = len(self.times)
        self.poses = np.asarray(self.poses, dtype=float).reshape(n, 3)
        self.covs = np.asarray(self.covs, dtype=float).reshape(n, 3, 3)
        if len(self.scans) != n:
            raise ValueError(f"{len(self.scans)} scans for {n} keyframes")
        self.between = np.asarray(self.between, dtype=float).reshape(-1, 5)

    @property
    def keyframes(self) -> int:
        return len(self.times)

    def robot_config(self):
        """The configuration the session was run with (:class:`~fgslam.config.RobotConfig`)."""
        return from_dict(self.config, "<saved session>")

    @classmethod
    def from_result(
        cls, res, cfg, meta: dict[str, Any] | None = None, continuation=None
    ) -> Session:
        """A finished run's :class:`~fgslam.slam.runner.SlamResult` with its configuration;
        a continued run's (``continuation``, :class:`~fgslam.session.join.Continuation`) is
        the joined session: the saved keyframes and this log's, the saved landmarks and
        this run's (ids after the saved ones), ``meta["segments"]`` saying which is which."""
        n = len(res.times)
        covs = np.full((n, 3, 3), np.nan)
        for i, c in enumerate(res.covs[:n]):
            if c is not None and np.shape(c) == (3, 3):
                covs[i] = c
        scans = list(res.keyframe_scans[:n]) + [None] * max(0, n - len(res.keyframe_scans))
        saved = [] if continuation is None else continuation.session.landmarks
        landmarks = [dict(m) for m in saved]
        first_id = 1 + max((int(m["id"]) for m in landmarks), default=-1)
        for lid, mean in sorted(res.means.items()):
            lm = res.landmarks.get(lid)
            cov = res.landmark_covs.get(lid)
            landmarks.append(
                {
                    "id": first_id + int(lid),
                    "kind": lm.kind if lm is not None else "unknown",
                    "mean": [float(v) for v in np.ravel(mean)],
                    "cov": None if cov is None else np.asarray(cov, float).tolist(),
                }
            )
        constraints = []
        for i, link in enumerate(getattr(res, "keyframe_links", [])[: max(n - 1, 0)]):
            if link is not None:
                rel, cov, kind = link
                constraints.append(_constraint(kind, i, i + 1, rel, cov))
        for c in res.loop_closures:
            if c.get("accepted") and c.get("pose") is not None and c.get("cov") is not None:
                if c["from"] < n and c["to"] < n:
                    constraints.append(_constraint("loop", c["from"], c["to"], c["pose"], c["cov"]))
        m = {"backend": res.backend, "sensors": res.sensors}
        m.update(meta or {})
        # the scans between keyframes, each in the frame of the keyframe before it
        kf_t = np.asarray(res.times, dtype=float)
        is_kf = np.isin(res.scan_times, kf_t)
        st, sp = res.scan_times[~is_kf], res.scan_poses[~is_kf]
        k = np.searchsorted(kf_t, st, side="right") - 1
        keep = k >= 0
        st, sp, k = st[keep], sp[keep], k[keep]
        rel = between_poses(np.asarray(res.poses)[k], sp) if len(k) else np.zeros((0, 3))
        between = np.column_stack([st, k, rel]) if len(k) else np.zeros((0, 5))
        if continuation is not None:
            n0 = continuation.keyframes
            constraints += continuation.constraints(n0)
            m["segments"] = continuation.segments(str(m.get("log", "")), n - n0)
        return cls(
            times=res.times,
            poses=res.poses,
            covs=covs,
            scans=scans,
            laser_xy=(cfg.laser.mount.x, cfg.laser.mount.y),
            config=cfg.to_dict(),
            landmarks=landmarks,
            constraints=constraints,
            calibration=res.calibration,
            meta=m,
            between=between,
        )

    def grid(self, resolution: float = 0.05) -> OccupancyGrid:
        """The occupancy grid of the keyframes' scans at their poses."""
        return occupancy_grid(self.poses, self.scans, self.laser_xy, resolution)


def _constraint(kind: str, i: int, j: int, rel, cov) -> dict[str, Any]:
    return {
        "kind": kind,
        "from": int(i),
        "to": int(j),
        "pose": [float(v) for v in np.ravel(rel)],
        "cov": np.asarray(cov, dtype=float).reshape(3, 3).tolist(),
    }


def _scans_bytes(s: Session) -> bytes:
    counts = [0 if p is None else len(p) for p in s.scans]
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    parts = [np.asarray(p, dtype=float).reshape(-1, 2) for p in s.scans if p is not None]
    points = np.vstack(parts) if parts else np.zeros((0, 2))
    has = np.array([p is not None for p in s.scans], dtype=bool)
    buf = io.BytesIO()
    np.savez_compressed(
        buf,
        times=s.times,
        poses=s.poses,
        covs=s.covs,
        points=points,
        offsets=offsets,
        has_scan=has,
        laser_xy=np.asarray(s.laser_xy, dtype=float),
        between=s.between,
    )
    return buf.getvalue()


def save_session(s: Session, folder: str | Path, resolution: float = 0.05) -> Path:
    """Write ``s`` (and its occupancy grid at ``resolution`` m) as the session folder
    ``folder``; an existing session there is replaced, anything else is refused
    (:class:`SessionError`) and left untouched."""
    folder = Path(folder)
    check_replaceable(folder)
    tmp = folder.parent / f".{folder.name}.saving-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        tmp.mkdir(parents=True)
        data = _scans_bytes(s)
        (tmp / SCANS).write_bytes(data)
        index = {
            "format": FORMAT_NAME,
            "version": FORMAT_VERSION,
            "fgslam": __version__,
            "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "keyframes": s.keyframes,
            "scans_sha256": hashlib.sha256(data).hexdigest(),
            "meta": s.meta,
            "config": s.config,
            "calibration": s.calibration,
            "landmarks": s.landmarks,
            "constraints": s.constraints,
        }
        (tmp / INDEX).write_text(json.dumps(index, indent=1, allow_nan=False))
        write_map(s.grid(resolution), tmp)
    except (OSError, ValueError) as e:
        shutil.rmtree(tmp, ignore_errors=True)
        raise SessionError(f"{folder}: cannot write the session ({e})") from e
    old = folder.parent / f".{folder.name}.old-{os.getpid()}"
    if folder.exists():
        os.replace(folder, old)
    os.replace(tmp, folder)
    shutil.rmtree(old, ignore_errors=True)
    return folder


def check_replaceable(folder: str | Path) -> None:
    """Raise :class:`SessionError` unless ``folder`` is absent, empty or a readable session
    (what :func:`save_session` may replace)."""
    folder = Path(folder)
    if not folder.exists():
        return
    if not folder.is_dir():
        raise SessionError(f"{folder} is a file, not a session folder: not overwritten")
    if not any(folder.iterdir()):
        return
    if not (folder / INDEX).exists():
        raise SessionError(
            f"{folder} holds files but no {INDEX}: not a session, not overwritten "
            "(choose another folder)"
        )
    try:
        load_session(folder)
    except SessionError as e:
        raise SessionError(f"{e}; not overwritten (choose another folder)") from None


def load_session(folder: str | Path) -> Session:
    """Read a session folder; :class:`SessionError` naming what is wrong (missing, corrupt,
    written by a newer format)."""
    folder = Path(folder)
    index_path = folder / INDEX
    if not folder.is_dir():
        raise SessionError(f"{folder}: no such session folder")
    try:
        index = json.loads(index_path.read_text())
    except FileNotFoundError:
        raise SessionError(f"{folder}: not a session (no {INDEX})") from None
    except (OSError, UnicodeDecodeError, ValueError) as e:
        raise SessionError(f"{index_path}: corrupt ({e})") from None
    if not isinstance(index, dict) or index.get("format") != FORMAT_NAME:
        raise SessionError(f"{index_path}: not an fgslam session index")
    version = index.get("version")
    if not isinstance(version, int) or isinstance(version, bool):
        raise SessionError(f"{index_path}: corrupt (format version {version!r})")
    if version > FORMAT_VERSION:
        raise SessionError(
            f"{folder}: written by a newer fgslam ({index.get('fgslam', '?')}, session format "
            f"{version}); this fgslam ({__version__}) reads format {FORMAT_VERSION}: upgrade it"
        )
    try:
        data = (folder / SCANS).read_bytes()
    except OSError as e:
        raise SessionError(f"{folder}: cannot read {SCANS} ({e.strerror or e})") from None
    if hashlib.sha256(data).hexdigest() != index.get("scans_sha256"):
        raise SessionError(f"{folder / SCANS}: corrupt (its checksum does not match {INDEX})")
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        return _session(index, arrays)
    except SessionError:
        raise
    except (ValueError, KeyError, TypeError, OSError, EOFError, OverflowError) as e:
        raise SessionError(f"{folder}: corrupt session ({type(e).__name__}: {e})") from None


CONSTRAINT_KINDS = ("scan", "odometry", "loop", "anchor")


def _is_int(v: object) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _check_constraint(c: object, n: int) -> None:
    """A constraint as :class:`Session` holds it, between keyframes of ``n``; else ValueError."""
    what = f"{INDEX}: constraint {str(c)[:80]}"
    if not isinstance(c, dict) or c.get("kind") not in CONSTRAINT_KINDS:
        raise ValueError(f"{what}: not one of the kinds {CONSTRAINT_KINDS}")
    i, j = c.get("from"), c.get("to")
    if not (_is_int(i) and _is_int(j) and 0 <= i < n and 0 <= j < n and i != j):
        raise ValueError(f"{what}: not between two keyframes")
    try:
        pose = np.asarray(c.get("pose"), dtype=float)
        cov = np.asarray(c.get("cov"), dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{what}: pose or covariance not numbers") from None
    if pose.shape != (3,) or cov.shape != (3, 3):
        raise ValueError(f"{what}: pose or covariance of the wrong shape")
    if not (np.isfinite(pose).all() and np.isfinite(cov).all()):
        raise ValueError(f"{what}: pose or covariance not finite")
    if np.linalg.eigvalsh(0.5 * (cov + cov.T)).min() <= 0:
        raise ValueError(f"{what}: covariance not positive definite")


def _session(index: dict[str, Any], z: dict[str, NDArray]) -> Session:
    n = index["keyframes"]
    if not isinstance(n, int) or isinstance(n, bool) or n < 0:
        raise ValueError(f"{INDEX}: keyframes = {n!r}")
    kinds = {"offsets": "iu", "has_scan": "b"}
    for name in ("times", "poses", "covs", "points", "offsets", "has_scan", "laser_xy"):
        if z[name].dtype.kind not in kinds.get(name, "fiu"):
            raise ValueError(f"{SCANS}: {name} holds {z[name].dtype} values")
    offsets = z["offsets"].astype(np.int64)
    points = z["points"].astype(float).reshape(-1, 2)
    has = z["has_scan"].astype(bool)
    if len(offsets) != n + 1 or len(has) != n or offsets[-1] != len(points):
        raise ValueError("the scans' offsets do not match the keyframes")
    if np.any(np.diff(offsets) < 0) or offsets[0] != 0:
        raise ValueError("the scans' offsets are not increasing")
    scans = [points[offsets[i] : offsets[i + 1]] if has[i] else None for i in range(n)]
    lx, ly = (float(v) for v in z["laser_xy"].reshape(2))
    for key in ("config", "landmarks", "constraints", "meta"):
        if not isinstance(index.get(key), dict if key in ("config", "meta") else list):
            raise ValueError(f"{INDEX}: {key} missing or of the wrong type")
    try:
        from_dict(index["config"], "<saved session>")
    except ConfigError as e:
        raise ValueError(f"its configuration: {e}") from None
    if not (np.isfinite(z["times"]).all() and np.isfinite(z["poses"]).all()):
        raise ValueError(f"{SCANS}: keyframe times or poses not finite")
    between = z.get("between", np.zeros((0, 5)))  # (sessions saved before it: none)
    if between.dtype.kind not in "fiu" or between.ndim != 2 or between.shape[1] != 5:
        raise ValueError(f"{SCANS}: between holds {between.dtype} values of shape {between.shape}")
    between = between.astype(float)
    k = between[:, 1]
    if not np.isfinite(between).all() or np.any((k < 0) | (k >= n) | (k != np.round(k))):
        raise ValueError(f"{SCANS}: between holds scans of no keyframe or not finite")
    for c in index["constraints"]:
        _check_constraint(c, n)
    for lm in index["landmarks"]:
        if not isinstance(lm, dict) or not _is_int(lm.get("id")):
            raise ValueError(f"{INDEX}: a landmark without an integer id: {str(lm)[:80]}")
    return Session(
        times=z["times"],
        poses=z["poses"],
        covs=z["covs"],
        scans=scans,
        laser_xy=(lx, ly),
        config=index["config"],
        landmarks=index["landmarks"],
        constraints=index["constraints"],
        calibration=index.get("calibration"),
        meta=index["meta"],
        between=between,
    )
