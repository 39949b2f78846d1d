"""CARMEN records, one line at a time (the format: :mod:`fgslam.io.readers.carmen`):
:func:`parse_record` turns a line's tokens into a dict with ``tag``, ``t`` and its fields or
raises ``_Bad`` with a one-line reason; :func:`odometry_check` and :func:`flaser_scans` read
a log's records unchecked, for the tests and experiments behind the reader's rules. The log
as events is :class:`fgslam.io.readers.carmen.CarmenLog`.
"""

from __future__ import annotations

import math

import numpy as np

from fgslam.io.readers.common import open_lines
from fgslam.io.readers.odometry import relative
from fgslam.io.readers.sanity import MAX_STAMP
from fgslam.io.readers.source import StrPath

MAX_COORD = 1e7  # m (and rad): a pose field beyond is not a pose
LASER_TAGS = ("FLASER", "ROBOTLASER1")
USED_TAGS = ("FLASER", "ROBOTLASER1", "ODOM", "TRUEPOS", "PARAM")


class _Bad(Exception):
    pass


def _floats(tok: list[str], what: str) -> list[float]:
    try:
        out = [float(x) for x in tok]
    except ValueError:
        raise _Bad(f"{what}: expected numbers") from None
    # the sum is finite if every number is (a NaN or inf spreads); only then can it overflow
    if not math.isfinite(sum(out)) and not all(map(math.isfinite, out)):
        raise _Bad(f"{what}: expected finite numbers")
    return out


def _stamp(v: float, what: str) -> float:
    if not abs(v) < MAX_STAMP:
        raise _Bad(f"{what}: timestamp {v:.6g} out of range (seconds below {MAX_STAMP:g})")
    return v


def _pose(v: list[float], what: str) -> tuple[float, float, float]:
    if not (abs(v[0]) < MAX_COORD and abs(v[1]) < MAX_COORD and abs(v[2]) < MAX_COORD):
        raise _Bad(f"{what}: pose {v[0]:.6g} {v[1]:.6g} {v[2]:.6g} out of range")
    return (v[0], v[1], v[2])


def _logger(tok: str) -> float:
    """The logger_timestamp field, NaN when it is not a number in range."""
    try:
        v = float(tok)
    except ValueError:
        return math.nan
    return v if abs(v) < MAX_STAMP else math.nan


def _ranges(tok: list[str], what: str) -> np.ndarray:
    """Range fields (m); NaN and infinite ones are kept (no return), text is not a number."""
    try:
        return np.array([float(x) for x in tok], dtype=float)
    except ValueError:
        raise _Bad(f"{what}: expected numbers") from None


def _span(fov: float, resolution: float, n: int) -> float:
    """A ``ROBOTLASER1``'s angle from its first to its last beam (deg): ``fov`` where
    ``fov / (n - 1)`` is the resolution within 0.1 % (rounded fields), else ``(n - 1)
    resolution`` (CARMEN places beam k at ``start_angle + k resolution``)."""
    step = math.radians(fov) / (n - 1) if n > 1 else 0.0
    if n < 2 or not resolution > 0 or abs(step - resolution) <= 1e-3 * resolution:
        return fov
    return math.degrees((n - 1) * resolution)


def _int(tok: str, what: str) -> int:
    try:
        v = int(tok)
    except ValueError:
        raise _Bad(f"{what}: expected an integer, got {tok[:20]!r}") from None
    if v < 0 or v > 100000:
        raise _Bad(f"{what}: {v} out of range")
    return v


def parse_record(f: list[str]) -> dict:
    """One CARMEN record (tokens) as a dict with ``tag``, ``t`` and its fields; raises
    ``_Bad`` for a malformed record of a known type."""
    tag = f[0]
    if tag == "FLASER":
        if len(f) < 2:
            raise _Bad("FLASER: no beam count")
        n = _int(f[1], "FLASER n")
        if len(f) != n + 11:
            raise _Bad(f"FLASER: expected {n + 11} fields for n={n}, got {len(f)}")
        ranges = _ranges(f[2 : n + 2], "FLASER ranges")
        v = _floats(f[n + 2 : n + 9], "FLASER")
        return {
            "tag": tag,
            "ranges": ranges,
            "pose": _pose(v[0:3], "FLASER"),
            "odom": _pose(v[3:6], "FLASER odometry"),
            "t": _stamp(v[6], "FLASER"),
            "t_logger": _logger(f[-1]),
            "fov": 180.0,  # deg from the first beam to the last
            "start": -math.pi / 2,  # rad, the first beam
            "max_range": math.inf,
            "laser_pose": None,
        }
    if tag == "ROBOTLASER1":
        if len(f) < 9:
            raise _Bad("ROBOTLASER1: too few fields")
        n = _int(f[8], "ROBOTLASER1 n")
        if len(f) < 10 + n:
            raise _Bad("ROBOTLASER1: too few fields for its ranges")
        m = _int(f[9 + n], "ROBOTLASER1 remission count")
        if len(f) != 10 + n + m + 14:
            raise _Bad(f"ROBOTLASER1: expected {24 + n + m} fields, got {len(f)}")
        head = _floats(f[2:7], "ROBOTLASER1")
        ranges = _ranges(f[9 : 9 + n], "ROBOTLASER1 ranges")
        # laser pose, robot pose, tv, rv, forward/side safety, turn axis, timestamp
        tail = _floats(f[10 + n + m : 10 + n + m + 12], "ROBOTLASER1")
        fov = math.degrees(head[1])
        if not 0 < fov <= 360:
            raise _Bad(f"ROBOTLASER1: field of view {fov} deg")
        if not abs(head[0]) <= 2 * math.pi:
            raise _Bad(f"ROBOTLASER1: start angle {head[0]:.6g} rad (beyond one turn)")
        span = _span(fov, head[2], n)
        if not 0 < span <= 360 or (n > 1 and math.radians(span) / (n - 1) < 1e-6):
            raise _Bad(f"ROBOTLASER1: {n} beams over {span:.6g} deg")
        return {
            "tag": tag,
            "ranges": ranges,
            "pose": _pose(tail[3:6], "ROBOTLASER1"),
            "odom": _pose(tail[3:6], "ROBOTLASER1"),
            "laser_pose": _pose(tail[0:3], "ROBOTLASER1 laser"),
            "t": _stamp(tail[11], "ROBOTLASER1"),
            "t_logger": _logger(f[-1]),
            "fov": span,
            "start": head[0],
            "max_range": head[3] if head[3] > 0 else math.inf,
        }
    if tag == "ODOM":
        if len(f) != 10:
            raise _Bad(f"ODOM: expected 10 fields, got {len(f)}")
        v = _floats(f[1:8], "ODOM")
        return {
            "tag": tag,
            "pose": _pose(v[0:3], "ODOM"),
            "t": _stamp(v[6], "ODOM"),
            "t_logger": _logger(f[-1]),
        }
    if tag == "TRUEPOS":
        if len(f) != 10:
            raise _Bad(f"TRUEPOS: expected 10 fields, got {len(f)}")
        v = _floats(f[1:8], "TRUEPOS")
        return {
            "tag": tag,
            "pose": _pose(v[0:3], "TRUEPOS"),
            "odom": _pose(v[3:6], "TRUEPOS odometry"),
            "t": _stamp(v[6], "TRUEPOS"),
            "t_logger": _logger(f[-1]),
        }
    if tag == "PARAM":
        if len(f) < 3:
            raise _Bad("PARAM: expected 'PARAM name value ...'")
        return {"tag": tag, "name": f[1], "value": f[2], "t": None}
    return {"tag": tag, "t": None}


def odometry_check(path: StrPath) -> dict[str, np.ndarray]:
    """The data behind the corrected-log odometry rule, per scan k >= 1 of a corrected log:
    ``increment`` = inverse(P_{k-1}) * ODOM_before_k (the rule), ``corrected`` = inverse(P_{k-1})
    * P_k, ``first_step`` = the first ODOM line after scan k-1 relative to P_{k-1} (small if the
    ODOM lines restart from the corrected pose), ``jump`` = the same line relative to
    ODOM_before_{k-1} (small if they held cumulative raw odometry instead), and ``global`` =
    inverse(ODOM_before_{k-1}) * ODOM_before_k (the increment under that other reading)."""
    prev_pose = prev_before = None
    before = first = None
    out: dict[str, list] = {
        k: [] for k in ("increment", "corrected", "first_step", "jump", "global")
    }
    for _, text in open_lines(path):
        f = text.split()
        if not f or f[0] not in ("ODOM", "FLASER"):
            continue
        rec = parse_record(f)
        if rec["tag"] == "ODOM":
            if rec["t"] == 0.0:
                continue
            before = rec["pose"]
            if first is None:
                first = rec["pose"]
            continue
        if prev_pose is not None and before is not None and first is not None:
            out["increment"].append(relative(prev_pose, before))
            out["corrected"].append(relative(prev_pose, rec["pose"]))
            out["first_step"].append(relative(prev_pose, first))
            ref = prev_before if prev_before is not None else prev_pose
            out["global"].append(relative(ref, before))
            out["jump"].append(relative(ref, first))
        prev_pose, prev_before, first = rec["pose"], before, None
    return {k: np.array(v) for k, v in out.items()}


def flaser_scans(path: StrPath, limit: int | None = None) -> dict[str, np.ndarray]:
    """The ``FLASER`` records of a CARMEN log in file order, unchecked (for experiments and
    tests on the raw scans): ``ranges`` (N, n) in m with NaN for no return (80 m and beyond),
    ``t`` (N,) their stamps, ``pose`` and ``odom`` (N, 3) the two pose fields."""
    ranges, t, pose, odom = [], [], [], []
    for _, text in open_lines(path):
        f = text.split()
        if not f or f[0] != "FLASER":
            continue
        rec = parse_record(f)
        r = np.asarray(rec["ranges"], dtype=float)
        ranges.append(np.where(r >= 80.0, np.nan, r))
        t.append(rec["t"])
        pose.append(rec["pose"])
        odom.append(rec["odom"])
        if limit is not None and len(t) >= limit:
            break
    return {
        "ranges": np.array(ranges),
        "t": np.array(t),
        "pose": np.array(pose).reshape(-1, 3),
        "odom": np.array(odom).reshape(-1, 3),
    }
