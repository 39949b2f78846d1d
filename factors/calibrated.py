"""Measurements that move with calibration errors (docs/design.md, 6): z = h(x) + J c + noise,
with c a calibration ``Vector`` variable and J the measurement's fixed Jacobian w.r.t. it (e.g.
a laser line's w.r.t. the range offset and scale, :attr:`fgslam.frontend.features.Feature.Jc`).
"""

from __future__ import annotations

from collections.abc import Callable

import gtsam
import numpy as np
from numpy.typing import ArrayLike, NDArray


def calibrated(
    noise: gtsam.noiseModel.Base,
    keys: list[int],
    cal_key: int,
    cal_jacobian: ArrayLike,
    error: Callable,
    gain: ArrayLike | None = None,
) -> gtsam.CustomFactor:
    """The factor of ``error`` (a ``CustomFactor`` callback over ``keys`` returning
    prediction - measurement) with the measurement corrected by the calibration: its error
    plus ``cal_jacobian`` c, Jacobian ``cal_jacobian`` w.r.t. the variable ``cal_key``.

    ``gain`` (as ``cal_jacobian``; :func:`scale_gain`): the scale errors' columns of the
    Jacobian taken at the prediction, not at the measurement: the error is e (1 + gain c) +
    ``cal_jacobian`` c, row by row. A scale's Jacobian is the measured length itself, so taken
    at the measurement it carries the measurement's noise, and a fit gains by shrinking the
    world with the scale (docs/design.md, 6: errors in variables)."""
    J = np.array(cal_jacobian, dtype=float)
    G = None if gain is None else np.array(gain, dtype=float)
    n = len(keys)

    def with_cal(this: gtsam.CustomFactor, values: gtsam.Values, H: list | None) -> np.ndarray:
        e = error(this, values, H)
        c = values.atVector(cal_key)
        if G is None:
            if H is not None:
                H[n] = J
            return e + J @ c
        k = 1.0 + G @ c
        if H is not None:
            for i in range(n):
                H[i] = k[:, None] * H[i]
            H[n] = J + e[:, None] * G
        return k * e + J @ c

    return gtsam.CustomFactor(noise, [*keys, cal_key], with_cal)


def scale_gain(
    cal_jacobian: ArrayLike, z: ArrayLike, scale_columns: ArrayLike
) -> NDArray[np.float64] | None:
    """For :func:`calibrated`: a measurement's length (its second component: a line's d, a
    corner's or point's range) over the measured length, in the columns of c that are scale
    errors (relative: the laser's range scale, the speed of sound's error); None when there
    are none or the length is not positive."""
    J = np.asarray(cal_jacobian, dtype=float)
    cols = np.asarray(scale_columns, dtype=np.intp)
    length = float(np.asarray(z, dtype=float)[1])
    if not cols.size or not length > 0:
        return None
    G = np.zeros_like(J)
    G[1, cols] = J[1, cols] / length
    return G if G.any() else None
