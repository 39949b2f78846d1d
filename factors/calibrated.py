"""Measurements that move with calibration errors (docs/design.md, 6): z = h(x) + J c + noise,
with c a calibration ``Vector`` variable and J the measurement's fixed Jacobian w.r.t. it (e.g.
a laser line's w.r.t. the range offset and scale, :attr:`fgslam.frontend.features.Feature.Jc`).
"""

from __future__ import annotations

from collections.abc import Callable

import gtsam
import numpy as np
from numpy.typing import ArrayLike


def calibrated(
    noise: gtsam.noiseModel.Base,
    keys: list[int],
    cal_key: int,
    cal_jacobian: ArrayLike,
    error: Callable,
) -> gtsam.CustomFactor:
    """The factor of ``error`` (a ``CustomFactor`` callback over ``keys`` returning
    prediction - measurement) with the measurement corrected by the calibration: its error
    plus ``cal_jacobian`` c, Jacobian ``cal_jacobian`` w.r.t. the variable ``cal_key``."""
    J = np.array(cal_jacobian, dtype=float)
    n = len(keys)

    def with_cal(this: gtsam.CustomFactor, values: gtsam.Values, H: list | None) -> np.ndarray:
        e = error(this, values, H)
        if H is not None:
            H[n] = J
        return e + J @ values.atVector(cal_key)

    return gtsam.CustomFactor(noise, [*keys, cal_key], with_cal)
