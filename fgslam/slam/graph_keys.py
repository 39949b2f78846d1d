"""The factor graph's variables (docs/design.md, 6): robot poses X(k) (``Pose2``; and S(k) at
the stamps with the per-scan time registration), landmarks
L(id) (lines ``Vector2`` (alpha, d), corners ``Pose2``, points ``Point2``) and the
calibration errors C (one ``Vector`` for the whole run), and the small helpers every graph
module shares."""

from __future__ import annotations

import dataclasses

import gtsam
import numpy as np
from numpy.typing import NDArray

from fgslam.slam import models


def X(k: int) -> int:
    return gtsam.symbol("x", k)


def S(k: int) -> int:
    """Keyframe k's pose at its scan's stamp (``[laser] time_registration = "per-scan"``):
    X(k) is the robot's pose at the scan's true time, which the scan's features see."""
    return gtsam.symbol("s", k)


def L(i: int) -> int:
    return gtsam.symbol("l", i)


# the calibration errors (fgslam.slam.calibration.Calibration), one Vector for the whole run
C = gtsam.symbol("c", 0)

# the robot's poses are Pose2 variables like a corner's; the calibration is a plain vector
POSE_VARIABLE = dataclasses.replace(models.KINDS["corner"], name="pose")


def key_name(key: int) -> str:
    sym = gtsam.Symbol(key)
    return f"{chr(sym.chr())}{sym.index()}"


def blockdiag(blocks: list[NDArray[np.float64]]) -> NDArray[np.float64]:
    n = sum(b.shape[0] for b in blocks)
    T = np.zeros((n, n))
    o = 0
    for b in blocks:
        k = b.shape[0]
        T[o : o + k, o : o + k] = b
        o += k
    return T
