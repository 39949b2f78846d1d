"""The Victoria Park text format (as distributed with GTSAM's examples).

::

    ODOMETRY i j dx dy dtheta c_xx c_xy c_xt c_yy c_yt c_tt
    LANDMARK i l dx dy c_xx c_xy c_yy

``ODOMETRY``: pose j relative to pose i (m, rad) with the upper triangle of its 3x3
covariance. ``LANDMARK``: landmark l seen from pose i at (dx, dy) in the robot frame, with
the upper triangle of its 2x2 covariance; the landmark index is the given data association.
Poses and landmarks share one index space (a landmark takes an index the pose chain skips).

This is not a sensor log (no times, no scans): :func:`read_victoria` returns the steps and
observations, and :mod:`fgslam.slam.pointslam` drives the backends with them. A
``(bearing, range)`` measurement and its covariance (through the Jacobian of the polar
conversion) come from :func:`to_bearing_range`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from fgslam.errors import ReaderError
from fgslam.io.readers.common import open_lines
from fgslam.io.readers.source import Problems, StrPath


@dataclass(frozen=True)
class Step:
    """One odometry step: pose ``j`` relative to pose ``i`` with its covariance."""

    i: int
    j: int
    delta: NDArray[np.float64]
    cov: NDArray[np.float64]


@dataclass(frozen=True)
class Sighting:
    """Landmark ``landmark`` seen from pose ``pose`` at ``xy`` (robot frame) with ``cov``."""

    pose: int
    landmark: int
    xy: NDArray[np.float64]
    cov: NDArray[np.float64]


@dataclass
class VictoriaPark:
    """A parsed file: the odometry chain in file order and the sightings per pose."""

    steps: list[Step] = field(default_factory=list)
    sightings: dict[int, list[Sighting]] = field(default_factory=dict)
    problems: Problems = field(default_factory=Problems)

    @property
    def n_sightings(self) -> int:
        return sum(len(v) for v in self.sightings.values())

    @property
    def landmarks(self) -> set[int]:
        return {s.landmark for v in self.sightings.values() for s in v}


MAX_VALUE = 1e12  # no position, angle or variance of a park is larger


class _Bad(Exception):
    pass


def _nums(tok: list[str], n_int: int, n: int, what: str) -> tuple[list[int], list[float]]:
    if len(tok) != n:
        raise _Bad(f"{what}: expected {n} fields, got {len(tok)}")
    try:
        ints = [int(x) for x in tok[:n_int]]
        vals = [float(x) for x in tok[n_int:]]
    except ValueError:
        raise _Bad(f"{what}: expected {n_int} integers and {n - n_int} numbers") from None
    if any(i < 0 for i in ints):
        raise _Bad(f"{what}: negative index")
    if not all(math.isfinite(v) for v in vals):
        raise _Bad(f"{what}: expected finite numbers")
    if not all(abs(v) <= MAX_VALUE for v in vals):
        raise _Bad(f"{what}: a number beyond {MAX_VALUE:g} (m, rad or their squares)")
    return ints, vals


def _posdef(c: NDArray[np.float64], what: str) -> NDArray[np.float64]:
    try:
        np.linalg.cholesky(c)
    except np.linalg.LinAlgError:
        raise _Bad(f"{what}: covariance not positive definite") from None
    return c


def read_victoria(path: StrPath, tolerant: bool = False) -> VictoriaPark:
    """Parse a Victoria Park file. Malformed records raise :class:`ReaderError` (with
    ``tolerant``: skipped and counted); unknown tags are skipped and counted; a step that does
    not continue the chain (``i`` not the previous ``j``) or goes back in pose index, and a
    sighting from a pose the chain has not reached, are counted in ``problems.backwards``."""
    out = VictoriaPark()
    pr = out.problems
    name = str(path)
    last_j: int | None = None
    seen = False
    for lineno, text in open_lines(path):
        f = text.split()
        if not f or f[0].startswith("#"):
            continue
        seen = True
        try:
            if f[0] == "ODOMETRY":
                (i, j), v = _nums(f[1:], 2, 11, "ODOMETRY")
                c = v[3:]
                cov = np.array([[c[0], c[1], c[2]], [c[1], c[3], c[4]], [c[2], c[4], c[5]]])
                step = Step(i, j, np.array(v[:3]), _posdef(cov, "ODOMETRY"))
                if j <= i:
                    pr.backwards["ODOMETRY pose index"] += 1
                    pr.skip("odometry going back in pose index")
                    continue
                if last_j is not None and i != last_j:
                    pr.backwards["ODOMETRY chain broken"] += 1
                    pr.skip(
                        "odometry not continuing the chain",
                        f"{name}:{lineno}: ODOMETRY {i} {j} does not continue from pose {last_j}",
                    )
                    continue
                out.steps.append(step)
                last_j = j
            elif f[0] == "LANDMARK":
                (i, lm), v = _nums(f[1:], 2, 7, "LANDMARK")
                c = v[2:]
                cov = np.array([[c[0], c[1]], [c[1], c[2]]])
                s = Sighting(i, lm, np.array(v[:2]), _posdef(cov, "LANDMARK"))
                if math.hypot(*s.xy) < 1e-9:
                    raise _Bad("LANDMARK: at the robot's position (no bearing)")
                if (last_j is None and i != 0) or (last_j is not None and i > last_j):
                    pr.backwards["LANDMARK before its pose"] += 1
                    pr.skip("sighting before its pose")
                    continue
                out.sightings.setdefault(i, []).append(s)
            else:
                pr.ignore(f"unknown record {f[0][:20]}")
        except _Bad as exc:
            msg = f"{name}:{lineno}: {exc}"
            if not tolerant:
                raise ReaderError(msg) from None
            pr.skip(f"bad {f[0][:20]} record", msg)
    if not seen or not out.steps:
        raise ReaderError(f"{name}: no ODOMETRY records: not a Victoria Park file")
    return out


def to_bearing_range(
    xy: NDArray[np.float64], cov: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(bearing, range) of a robot-frame point and its covariance, J C J^T with J the
    Jacobian of the polar conversion at the point."""
    x, y = float(xy[0]), float(xy[1])
    r2 = x * x + y * y
    r = math.sqrt(r2)
    J = np.array([[-y / r2, x / r2], [x / r, y / r]])
    C = J @ cov @ J.T
    return np.array([math.atan2(y, x), r]), 0.5 * (C + C.T)
